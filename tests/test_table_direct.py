"""The stream table's direct intake (:meth:`daemon.service.streams.StreamTable._direct`: the next
frame of a plain stream's run fed by the next tick without a queue) against its definition, the
same table with every pose queued: on random interleavings of frame messages, single poses, ticks,
ends, new runs, re-announcements and idle evictions over streams of a real recording, with
duplicated, repeated, missing and jumping sequence numbers, everything the two tables say and
count is the same, detections included."""

from __future__ import annotations

from dataclasses import replace
from functools import cache
from typing import Any

import numpy as np
from hypothesis import example, given, settings
from hypothesis import strategies as st

from daemon.config import RecognizerConfig, SegmentationConfig
from daemon.library import Library, default_library_path, load_library
from daemon.recordings import read_recording
from daemon.service.streams import Emitted, Refused, StreamTable
from protocols.messages import DetectionMessage, EndMessage, PoseMessage, SkeletonMessage, WireError, frame_of
from tests.helpers import DATA

ASF, AMC = DATA / "cmu" / "13" / "13.asf", DATA / "cmu" / "13" / "13_29.amc.gz"
NAMES = ("a", "b", "c")


@cache
def library() -> Library:
    return load_library(default_library_path())


@cache
def channels() -> np.ndarray:
    """The recording's channels in radians, ``(N, C)``."""
    return read_recording(ASF, AMC).channels


class Queueing(StreamTable):
    """The definition: every pose through the queue."""

    def _direct(self, name: str, s: object, epoch: str | None) -> bool:
        return False


def tables(segmenting: bool) -> list[StreamTable]:
    out = []
    for kind in (StreamTable, Queueing):
        t = kind(
            library(),
            session="d",
            recognizer=RecognizerConfig(hold_s=1.0),
            segmentation=SegmentationConfig(method="pca") if segmenting else SegmentationConfig(),
        )
        out.append(t)
    return out


def said(got: object) -> object:
    """What a table call returned, comparable between the two tables: emitted messages without
    their emit time, refusals by reason."""
    if isinstance(got, Emitted):
        m = got.message
        return replace(m, emit_time=0.0), got.arrived
    if isinstance(got, Refused | WireError):
        return ("refused", got.reason)
    if isinstance(got, list | tuple):
        return [said(x) for x in got]
    return got


def both(tables: tuple[StreamTable, StreamTable], method: str, *args: object) -> None:
    """``method`` of each table called with ``args``: the same said (or the same refusal)."""
    got = []
    for t in tables:
        try:
            got.append(said(getattr(t, method)(*args)))
        except Refused as e:
            got.append(said(e))
    assert got[0] == got[1]


names = st.lists(st.sampled_from(NAMES), min_size=1, max_size=3, unique=True)
advances = st.sampled_from([1, 1, 1, 1, 0, -1, 2, 5, 400])
actions = st.one_of(
    st.tuples(
        st.just("frame"),
        names,
        advances,
        st.sampled_from([None, None, "e1", "e2"]),
        st.sampled_from([1, 1, 2, 30]),
    ),
    st.tuples(st.just("pose"), st.sampled_from(NAMES), advances, st.sampled_from([None, "e1"]), st.just(1)),
    st.tuples(st.just("tick"), st.integers(0, 3)),
    st.tuples(st.just("end"), st.sampled_from(NAMES), st.sampled_from([None, "e1"])),
    st.tuples(
        st.just("announce"),
        st.sampled_from(NAMES),
        st.sampled_from([None, "e1", "e2"]),
        st.sampled_from([120.0, 60.0]),
    ),
    st.tuples(
        st.just("evict"),
    ),
)
START = ("frame", list(NAMES), 1, None, 2)
"""Every stream's run begun, its next frame ready: where the direct intake starts."""


@settings(max_examples=150, deadline=None)
@given(st.lists(actions, min_size=1, max_size=25), st.booleans())
# each stream's next pose ready (:data:`START`), then what must treat it as waiting
@example([("tick", 0), ("evict",)], False)
@example([("end", "a", None), ("tick", 1)], False)
@example([("announce", "b", None, 60.0), ("tick", 1)], False)
def test_direct_intake_says_what_the_queue_says(steps: list[tuple[Any, ...]], segmenting: bool) -> None:
    rows = channels()
    asf = ASF.read_text()
    direct, queueing = tables(segmenting)
    seq = dict.fromkeys(NAMES, 0)
    now = 0.0
    pair = (direct, queueing)
    for name in NAMES:
        both(pair, "skeleton", SkeletonMessage(name, 120.0, asf=asf, angle_unit="rad"), now)
    for step in [START, *steps]:
        kind = step[0]
        now += 1 / 120
        if kind in ("frame", "pose"):
            _, names, advance, epoch, repeat = step
            names = [names] if isinstance(names, str) else names
            for r in range(repeat):  # a run of frames, a tick after each but the last
                poses = []
                for n in names:
                    seq[n] = max(0, seq[n] + advance)
                    poses.append(
                        PoseMessage(n, seq[n], now, channels=rows[seq[n] % len(rows)].copy(), epoch=epoch)
                    )
                if kind == "frame":
                    both(pair, "frame", frame_of(poses, "rig", epoch), now)
                else:
                    both(pair, "pose", poses[0], now)
                if r < repeat - 1:
                    both(pair, "tick")
                    now += 1 / 120
        elif kind == "tick":
            for _ in range(step[1]):
                both(pair, "tick")
        elif kind == "end":
            both(pair, "end", EndMessage(step[1], seq[step[1]], epoch=step[2]))
        elif kind == "announce":
            again = SkeletonMessage(step[1], step[3], asf=asf, angle_unit="rad", epoch=step[2])
            both(pair, "skeleton", again, now)
        else:
            both(pair, "evict_idle", now, 0.005)
        assert direct.queued == queueing.queued
        assert direct.counts == queueing.counts
        assert direct.streams.keys() == queueing.streams.keys()
        for name in direct.streams:
            assert direct.waiting(name) == queueing.waiting(name)
            a, b = direct.streams[name], queueing.streams[name]
            assert (a.last_received, a.received, a.epoch) == (b.last_received, b.received, b.epoch)
    both(pair, "flush_all")
    assert direct.counts == queueing.counts


def test_direct_intake_detects_what_the_queue_detects() -> None:
    """A whole recording in frames of three streams, a tick after each frame: the same detections
    (there are some), every pose but each stream's first taken without a queue."""
    rows = channels()
    asf = ASF.read_text()
    direct, queueing = tables(False)
    out: list[list[Any]] = [[], []]
    for t, got in zip((direct, queueing), out, strict=True):
        for name in NAMES:
            t.skeleton(SkeletonMessage(name, 120.0, asf=asf, angle_unit="rad"), 0.0)
        for k in range(len(rows)):
            poses = [
                PoseMessage(n, k, k / 120, channels=rows[(k + 97 * j) % len(rows)])
                for j, n in enumerate(NAMES)
            ]
            t.frame(frame_of(poses, "rig"), k / 120)
            if k > 0:
                assert (len(t._ready) == 3) == (t is direct)
            got += t.tick()[0]
        got += t.flush_all()
    assert said(out[0]) == said(out[1])
    assert sum(isinstance(e.message, DetectionMessage) for e in out[0]) > 3
