"""The stream table's frame intake (:meth:`daemon.service.streams.StreamTable.frame`) against its
definition: each subject taken or refused exactly as its own pose message would be by
:meth:`~daemon.service.streams.StreamTable.pose`, after the same subjects before it; on random
frames of known and unknown streams, good and bad subjects, repeated and out-of-order sequence
numbers, and with a worker's share of the streams."""

from __future__ import annotations

from functools import cache

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from daemon.library import Library, default_library_path, load_library
from daemon.service.streams import Refused, StreamTable
from protocols.messages import FrameMessage, PoseMessage, SkeletonMessage, WireError, frame_of
from protocols.routing import mine
from replay import JOINT_NAMES

KNOWN = ("a", "b", "c")


@cache
def library() -> Library:
    return load_library(default_library_path())


def table() -> StreamTable:
    t = StreamTable(library(), session="t")
    for name in KNOWN:
        t.skeleton(SkeletonMessage(name, 120.0, JOINT_NAMES), 0.0)
    return t


@st.composite
def frames(draw: st.DrawFn) -> list[FrameMessage]:
    out = []
    for _ in range(draw(st.integers(1, 4))):
        poses = []
        for _ in range(draw(st.integers(1, 6))):
            joints = draw(st.sampled_from([len(JOINT_NAMES), len(JOINT_NAMES), 3]))
            values = np.full((joints, 3), draw(st.sampled_from([1.0, 2.0, np.nan])), np.float32)
            poses.append(
                PoseMessage(
                    draw(st.sampled_from([*KNOWN, "unknown", "a.b"])),
                    draw(st.integers(0, 6)),
                    draw(st.sampled_from([1.0, float("inf")])),
                    positions=values,
                )
            )
        out.append(frame_of(poses, "rig", draw(st.sampled_from([None, "e1"]))))
    return out


def outcome(e: Exception | None) -> str:
    return "taken" if e is None else str(getattr(e, "reason", type(e).__name__))


@settings(max_examples=150, deadline=None)
@given(frames(), st.sampled_from([None, (0, 2), (1, 2)]))
def test_a_frame_is_taken_as_its_poses_one_by_one(
    sent: list[FrameMessage], share: tuple[int, int] | None
) -> None:
    owned = None if share is None else mine(*share, cached=3)
    batch, single = table(), table()
    for frame in sent:
        taken, refused = batch.frame(frame, 1.0, owned)
        want: list[tuple[str, str]] = []
        for stream, pose in zip(frame.streams, frame.poses(), strict=True):
            if owned is not None and not owned(stream):
                continue
            error: Exception | None = pose if isinstance(pose, WireError) else None
            if isinstance(pose, PoseMessage):
                try:
                    single.pose(pose, 1.0)
                except Refused as e:
                    error = e
            want.append((stream, outcome(error)))
        seen = [(frame.streams[i], "taken") for i in taken] + [(s, outcome(e)) for s, e in refused]
        assert sorted(seen) == sorted(want)
    for name in KNOWN:
        assert [p.seq for p in batch.streams[name].queue] == [p.seq for p in single.streams[name].queue]
        assert batch.streams[name].last_received == single.streams[name].last_received
