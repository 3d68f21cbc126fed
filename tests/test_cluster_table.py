"""The stream table's cluster rules (``docs/cluster.md``, "Takeover"), on a real recording: a worker
that takes a stream over mid-run, from a buffer that lost the run's start, publishes exactly the
detections a worker that saw the whole run publishes from its warm-up on, with the same ids, and
nothing else; motions begin at a multiple of the decimation step; ids depend on the source's run,
not on the process."""

from __future__ import annotations

import uuid
from functools import cache
from typing import Literal

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from daemon.config import RecognizerConfig, SegmentationConfig, ServiceConfig
from daemon.library import Library, default_library_path, load_library
from daemon.recordings import read_recording
from daemon.service.streams import Refused, StreamTable
from protocols.messages import BoundaryMessage, DetectionMessage, PoseMessage, SkeletonMessage
from tests.helpers import DATA

ASF, AMC = DATA / "cmu" / "13" / "13.asf", DATA / "cmu" / "13" / "13_30.amc.gz"
PASSES = 2
HOLD_S = 1.0
"""A shorter hold than the default's 5 s: a shorter reach, so the warm-up leaves more to compare."""


@cache
def library() -> Library:
    return load_library(default_library_path())


@cache
def channels() -> np.ndarray:
    """The recording looped ``PASSES`` times, shape ``(N, channels)``."""
    return np.concatenate([read_recording(ASF, AMC).channels] * PASSES)


def table() -> StreamTable:
    return StreamTable(
        library(),
        session="cluster",
        service=ServiceConfig(queue_frames=100_000),
        recognizer=RecognizerConfig(hold_s=HOLD_S),
        cluster=True,
    )


def run(first: int, *, warm: bool) -> tuple[list[DetectionMessage], StreamTable, int | None]:
    """A cluster table's detections of the stream from sequence number ``first`` on (``warm``: as a
    worker that took it over from a partial buffer), the stream's end flushed; the table, and the
    sequence number before which its detections were suppressed."""
    t = table()
    t.skeleton(SkeletonMessage("s", 120.0, asf=ASF.read_text(), angle_unit="rad", epoch="run1"), 0.0)
    if warm:
        t.warm_up("s")
    out = []
    frames = channels()
    for seq in range(first, len(frames)):
        t.pose(PoseMessage("s", seq, seq / 120, channels=frames[seq], epoch="run1"), seq / 120)
        out += t.tick()[0]
    limit = t.streams["s"].suppress_before
    out += t.flush_all()
    return [e.message for e in out if isinstance(e.message, DetectionMessage)], t, limit


@cache
def whole() -> list[DetectionMessage]:
    return run(0, warm=False)[0]


def key(d: DetectionMessage) -> tuple[object, ...]:
    return (d.id, d.class_name, d.start_frame, d.end_frame, d.cost, d.tau, d.emitted_at_frame)


def test_ids_are_the_runs_not_the_processes() -> None:
    found = whole()
    assert len(found) > 10
    for d in found:
        name = f"cluster/run1/s/{d.class_name}/{d.start_frame}/{d.end_frame}"
        assert d.id == str(uuid.uuid5(uuid.NAMESPACE_URL, name))


@settings(max_examples=8, deadline=None)
@given(st.integers(1, 2400))
def test_a_takeover_mid_run_gives_the_whole_runs_detections_after_its_warm_up(first: int) -> None:
    mine, t, limit = run(first, warm=True)
    begun = first + (-first % 4)  # the first multiple of the decimation step
    assert t.counts["aligning"] == begun - first
    assert limit is not None and limit > begun
    reference = whole()
    after = [key(d) for d in reference if d.start_frame >= limit]
    assert after, "nothing left after the warm-up to compare"
    # from its warm-up on it publishes what the whole run's worker publishes, ids and all, and
    # nothing else (what it suppressed, the old owner had published: docs/cluster.md)
    assert [key(d) for d in mine] == after
    assert t.counts["warmup_suppressed"] > 0


def test_the_buffer_a_takeover_needs() -> None:
    """docs/cluster.md: lease + 1 s + twice the reach + 1 s; 37.9 s with the shipped library."""
    from daemon.config import ClusterConfig, Config
    from daemon.service.cluster import buffer_seconds, needed_seconds, reach_seconds

    config = Config()
    assert round(reach_seconds(library(), config), 1) == 16.9
    assert needed_seconds(ClusterConfig(), library(), config) == 37.9
    shorter = Config(recognizer=RecognizerConfig(hold_s=HOLD_S))
    assert needed_seconds(ClusterConfig(lease_s=3.0), library(), shorter) == round(
        3.0 + 1 + 2 * reach_seconds(library(), shorter) + 1, 1
    )
    assert buffer_seconds(ClusterConfig(buffer_s=5.0), library(), config) == 5.0


@settings(max_examples=10, deadline=None)
@given(st.integers(0, 2 * 2465), st.integers(0, 12), st.integers(0, 3), st.booleans())
def test_a_stream_resumed_from_its_state_goes_on_as_the_table_it_left(
    cut: int, gap: int, where: int, degrees: bool
) -> None:
    """A stream's state (:meth:`StreamTable.state`) taken at any pose and resumed by another table
    (a worker that takes the partition over from a checkpoint): the detections of both tables
    together are those of one table fed every pose, ids, costs and frames alike, also with a gap
    bridged across the cut (``gap`` poses missing, ``where`` of them before it) and angles in
    degrees. Nothing is suppressed: the state leaves nothing to warm up."""
    frames = channels().copy()
    asf = ASF.read_text()
    unit: Literal["deg", "rad"] = "rad"
    if degrees:
        frames[:, read_recording(ASF, AMC).skeleton.angle_channels] /= np.pi / 180
        unit = "deg"
    missing = set(range(max(0, cut - min(where, gap)), max(0, cut - min(where, gap)) + gap))
    seqs = [q for q in range(len(frames)) if q not in missing]

    def feed(t: StreamTable, part: list[int]) -> list[DetectionMessage]:
        out = []
        for q in part:
            t.pose(PoseMessage("s", q, q / 120, channels=frames[q], epoch="run1"), q / 120)
            out += t.tick()[0]
        return [e.message for e in out if isinstance(e.message, DetectionMessage)]

    def started() -> StreamTable:
        t = table()
        t.skeleton(SkeletonMessage("s", 120.0, asf=asf, angle_unit=unit, epoch="run1"), 0.0)
        return t

    def flushed(t: StreamTable) -> list[DetectionMessage]:
        return [e.message for e in t.flush_all() if isinstance(e.message, DetectionMessage)]

    one = started()
    want = feed(one, seqs) + flushed(one)
    assert len(want) > 10
    first = started()
    before = [q for q in seqs if q < cut]
    got = feed(first, before)
    second = table()
    silent = first.streams["s"].seen
    assert second.resume(first.state("s", silent + 1.5), 100.0) == "s"
    assert second.streams["s"].seen == pytest.approx(100.0 - 1.5)  # as long silent as it was
    got += feed(second, [q for q in seqs if q >= cut]) + flushed(second)
    assert [key(d) for d in got] == [key(d) for d in want]
    assert second.counts["warmup_suppressed"] == 0


def test_a_damaged_or_foreign_stream_state_is_refused_and_takes_nothing() -> None:
    t = table()
    t.skeleton(SkeletonMessage("s", 120.0, asf=ASF.read_text(), angle_unit="rad", epoch="run1"), 0.0)
    for q in range(300):
        t.pose(PoseMessage("s", q, q / 120, channels=channels()[q], epoch="run1"), q / 120)
        t.tick()
    state = t.state("s", 3.0)
    other = StreamTable(library(), session="cluster", recognizer=RecognizerConfig(hold_s=2.0), cluster=True)
    for what, table_, data in (
        ("damaged", table(), state[:-40]),
        ("foreign", other, state),
        ("held already", t, state),
    ):
        before = set(table_.streams)
        with pytest.raises(Refused) as e:
            table_.resume(data, 0.0)
        assert e.value.reason == "state", what
        assert set(table_.streams) == before, what
    t.pose(PoseMessage("s", 300, 300 / 120, channels=channels()[300], epoch="run1"), 2.5)
    with pytest.raises(ValueError, match="poses waiting"):
        t.state("s", 3.0)


def test_boundary_ids_are_the_runs_not_the_tables() -> None:
    """In cluster mode a behaviour boundary's id, like a detection's, depends on the source's run
    (its epoch), not on how many streams the worker's table made before: two workers cutting the
    same run give the same ids (the store then keeps one), another run other ids."""

    def boundaries(before: int, epoch: str) -> list[tuple[str, int]]:
        t = StreamTable(
            library(),
            session="cluster",
            service=ServiceConfig(queue_frames=100_000),
            segmentation=SegmentationConfig("pca"),
            cluster=True,
        )
        asf = ASF.read_text()
        for k in range(before):  # streams made before: another generation for "s"
            t.skeleton(SkeletonMessage(f"other{k}", 120.0, asf=asf, angle_unit="rad", epoch="x"), 0.0)
        t.skeleton(SkeletonMessage("s", 120.0, asf=asf, angle_unit="rad", epoch=epoch), 0.0)
        frames = read_recording(ASF, AMC).channels
        out = []
        for seq, c in enumerate(frames):
            t.pose(PoseMessage("s", seq, seq / 120, channels=c, epoch=epoch), seq / 120)
            out += t.tick()[0]
        out += t.flush_all()
        return [(e.message.id, e.message.frame) for e in out if isinstance(e.message, BoundaryMessage)]

    first = boundaries(0, "run1")
    assert first and boundaries(3, "run1") == first
    assert {i for i, _ in boundaries(0, "run2")}.isdisjoint(i for i, _ in first)
