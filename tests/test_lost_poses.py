"""Issue 32: a lost pose must not shift what is detected. The live path kept every k-th pose for the
index rate by counting poses, so a bridged gap of 1, 2, 3 or 29 frames moved every later index frame
and changed the detections. Now a gap of at most ``service.bridge_s`` is filled with interpolated
frames (:func:`daemon.frames.bridge`) and the index frames are sampled by frame number: a stream with
lost poses gives the detections of ``mocapd detect`` on the same frames (an AMC file that skips
their numbers), and every detection starts on an index frame of the motion.

Checked against slow, obviously correct references (hypothesis), the stream table against its batch
twin on real recordings with random lost runs of 1-30 frames, and end to end: ``mocapd detect`` and a
real daemon fed by ``mocapd replay`` of the same file."""

from __future__ import annotations

import gzip
import math
import random
from functools import cache
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from daemon.frames import FrameClock, bridge, bridged_runs, motion_runs
from daemon.library import Library, default_library_path, load_library
from daemon.recognizer import detect
from daemon.recordings import RecordingError, continuous, motion_features, read_recording
from daemon.service.streams import StreamTable
from daemon.types import DEFAULT_BRIDGE_S
from protocols.messages import DetectionMessage, PoseMessage, SkeletonMessage
from replay import Motion, iter_amc
from tests.helpers import (
    DATA,
    Daemon,
    assert_one_error_line,
    detection_keys,
    finished,
    hits_json,
    mocapd,
    replay,
    wait_for,
)

TRIAL = (DATA / "cmu" / "13" / "13.asf", DATA / "cmu" / "13" / "13_30.amc.gz")
BRIDGED = round(DEFAULT_BRIDGE_S * 120)  # 30 frames at 120 Hz


@cache
def library() -> Library:
    return load_library(default_library_path())


@cache
def trial() -> Motion:
    return read_recording(*TRIAL)


def without(motion: Motion, lost: set[int]) -> Motion:
    """``motion`` less the frames at indexes ``lost``."""
    keep = np.array([k for k in range(len(motion)) if k not in lost])
    return Motion(motion.source, motion.skeleton, motion.header, motion.frames[keep], motion.channels[keep])


def lost_runs(rng: random.Random, n: int, runs: int, longest: int = BRIDGED) -> set[int]:
    """Indexes of ``runs`` runs of 1..``longest`` lost frames, none at either end."""
    lost: set[int] = set()
    for _ in range(runs):
        at = rng.randrange(1, n - longest - 1)
        lost.update(range(at, at + rng.randint(1, longest)))
    return lost


# ----------------------------------------------------------------------- the pure functions


def slow_bridge(before: list[float], after: list[float], missing: int, angles: set[int]) -> list[list[float]]:
    """Each missing frame, each value on its own: a straight line, an angle the short way round."""
    out = []
    for k in range(1, missing + 1):
        row = []
        for c, (a, b) in enumerate(zip(before, after, strict=True)):
            delta = b - a
            if c in angles:
                while delta > math.pi:
                    delta -= 2 * math.pi
                while delta < -math.pi:
                    delta += 2 * math.pi
            row.append(a + k / (missing + 1) * delta)
        out.append(row)
    return out


angle_values = st.floats(-4 * math.pi, 4 * math.pi)


@settings(max_examples=300, deadline=None)
@given(
    st.integers(1, 12).flatmap(
        lambda c: st.tuples(
            st.lists(angle_values, min_size=c, max_size=c),
            st.lists(angle_values, min_size=c, max_size=c),
            st.sets(st.integers(0, c - 1)),
        )
    ),
    st.integers(1, 40),
)
def test_bridge_is_a_straight_line_the_short_way_round(
    frames: tuple[list[float], list[float], set[int]], missing: int
) -> None:
    before, after, angles = frames
    got = bridge(np.array(before), np.array(after), missing, np.array(sorted(angles), dtype=np.intp))
    want = np.array(slow_bridge(before, after, missing, angles))
    assert got.shape == (missing, len(before))
    assert np.allclose(got, want, rtol=0, atol=1e-9)
    steps = np.diff(np.vstack([before, got, after]), axis=0)
    turn = sorted(angles)
    steps[-1, turn] = steps[0, turn] + np.remainder(steps[-1, turn] - steps[0, turn] + 1, 2 * math.pi) - 1
    assert np.allclose(steps, steps[0], rtol=0, atol=1e-9)  # evenly spaced, to ``after`` (an angle: mod 2π)
    assert np.all(np.abs(steps[:, turn]) <= math.pi / (missing + 1) + 1e-9)  # the short way round


def test_bridge_keeps_the_shape_of_positions() -> None:
    before, after = np.zeros((26, 3)), np.ones((26, 3))
    got = bridge(before, after, 3)
    assert got.shape == (3, 26, 3) and np.allclose(got[:, 0, 0], [0.25, 0.5, 0.75])


@settings(max_examples=300, deadline=None)
@given(
    st.lists(st.integers(1, 12), min_size=1, max_size=40),
    st.integers(0, 10),
    st.integers(-1000, 1000),
)
def test_bridged_runs_equal_a_frame_by_frame_reading(steps: list[int], max_missing: int, start: int) -> None:
    """Frame numbers ``start`` then each step on; values a frame's own number, twice (so an
    interpolated value must equal its frame number). Each run is consecutive, keeps every frame it
    had, and a run ends exactly where a gap is longer than ``max_missing``."""
    numbers = np.cumsum([start, *steps[1:]]).astype(np.int64)
    values = np.repeat(numbers.astype(np.float64)[:, None], 2, axis=1)
    runs = bridged_runs(numbers, values, max_missing)
    expected: list[list[int]] = [[int(numbers[0])]]
    for a, b in zip(numbers[:-1].tolist(), numbers[1:].tolist(), strict=True):
        if b - a - 1 > max_missing:
            expected.append([b])
        else:
            expected[-1] += list(range(a + 1, b + 1))
    assert [r.tolist() for r, _ in runs] == expected
    for run_numbers, run_values in runs:
        assert np.allclose(run_values, run_numbers[:, None], rtol=0, atol=1e-9)
        present = np.isin(run_numbers, numbers)
        assert np.array_equal(run_values[present], values[np.isin(numbers, run_numbers)])


@given(hnp.arrays(np.int64, st.integers(2, 10), elements=st.integers(0, 50)))
def test_bridged_runs_refuse_numbers_that_do_not_increase(numbers: np.ndarray) -> None:
    if np.all(np.diff(numbers) >= 1):
        return
    with pytest.raises(ValueError, match="increase"):
        bridged_runs(numbers, np.zeros((len(numbers), 1)), 5)


# ----------------------------------------------------------------- the live path and its twin


def live(motion: Motion, *, jitter: bool = False) -> list[tuple[str, int, int, float, float, int]]:
    """The stream table's detections of ``motion``'s frames as poses numbered by their frame
    numbers (lost frames are missing sequence numbers), one tick per pose (``jitter``: after
    bursts of 1-5 poses, so that a gap's filling and the queue interleave)."""
    t = StreamTable(library(), session="t")
    t.skeleton(SkeletonMessage("s", 120.0, asf=TRIAL[0].read_text(), angle_unit="rad"), 0.0)
    out = []
    rng = random.Random(len(motion))
    pending = 0
    for seq, row in zip(motion.frames.tolist(), motion.channels, strict=True):
        t.pose(PoseMessage("s", seq, seq / 120, channels=row), seq / 120)
        pending += 1
        if not jitter or pending >= rng.randint(1, 5):
            while t.queued:
                out += t.tick()[0]
                assert t.queued == sum(len(x.queue) + len(x.filling) for x in t.streams.values())
            pending = 0
    out += t.flush_all()
    return [
        (m.class_name, m.start_frame, m.end_frame, m.cost, m.tau, m.emitted_at_frame)
        for e in out
        if isinstance(m := e.message, DetectionMessage)
    ]


def batch(motion: Motion) -> list[tuple[str, int, int, float, float, int]]:
    return [
        (d.class_name, d.start_frame, d.end_frame, d.cost, d.tau, d.emitted_at_frame)
        for d in detect(motion, library(), 120.0)
    ]


@pytest.mark.slow
@settings(max_examples=12, deadline=None)
@given(st.integers(0, 2**32), st.integers(1, 6), st.booleans())
def test_a_stream_with_lost_poses_gives_detect_on_the_same_frames(seed: int, runs: int, jitter: bool) -> None:
    """Random runs of 1-30 lost frames (bridged; one in three examples also one of 31-90, which
    ends the motion): the stream table gives exactly what its batch twin gives on the recording
    without those frames, and every detection starts on an index frame of its motion."""
    motion = trial()
    rng = random.Random(seed)
    lost = lost_runs(rng, len(motion), runs)
    if seed % 3 == 0:
        lost |= lost_runs(rng, len(motion), 1, longest=90)
    gappy = without(motion, lost)
    got = live(gappy, jitter=jitter)
    assert got == batch(gappy)
    assert got, "no detection: a vacuous comparison"
    step = FrameClock.of(120.0, library().rate).step
    firsts = [int(run.frames[0]) for run in motion_runs(gappy, 120.0)]
    assert all((d[1] - max(f for f in firsts if f <= d[1])) % step == 0 for d in got)


def test_one_lost_pose_leaves_every_index_frame_where_it_was() -> None:
    """One pose lost early in the trial: every detection still starts on an index frame of the
    motion (frame 1 + 4j), as without the loss (before: every later one moved by a frame)."""
    motion = trial()
    got = live(without(motion, {101}))
    assert got and all((start - int(motion.frames[0])) % 4 == 0 for _, start, *_ in got)


def test_a_lost_pose_changes_little() -> None:
    """With a few single poses lost, the detections are those of the whole recording: one
    interpolated frame at 120 Hz is close to the real one."""
    motion = trial()
    whole = batch(motion)
    for lost in ({101}, {500, 1402}, {77, 1937}):
        assert [d[:3] for d in batch(without(motion, lost))] == [d[:3] for d in whole], lost


# ------------------------------------------------------------------- recordings with gaps


def write_without(amc: Path, out: Path, lost_numbers: set[int]) -> Path:
    """A copy of AMC file ``amc`` less the frames numbered ``lost_numbers``."""
    with gzip.open(amc, "rt") if amc.suffix == ".gz" else amc.open() as f:
        lines = f.read().splitlines()
    kept, skipping = [], False
    for line in lines:
        word = line.split()[0] if line.split() else ""
        if word.isdigit():
            skipping = int(word) in lost_numbers
        if not skipping:
            kept.append(line)
    out.write_text("\n".join(kept) + "\n")
    return out


def test_an_amc_file_that_lost_frames_reads_with_their_numbers_missing(tmp_path: Path) -> None:
    motion = trial()
    lost = {int(motion.frames[k]) for k in (10, 11, 12, 700)}
    path = write_without(TRIAL[1], tmp_path / "gappy.amc", lost)
    read = read_recording(TRIAL[0], path)
    keep = ~np.isin(motion.frames, list(lost))
    assert np.array_equal(read.frames, motion.frames[keep])
    assert np.array_equal(read.channels, motion.channels[keep])
    streamed = list(iter_amc(path, motion.skeleton))  # the frame-by-frame reader agrees
    assert [f.frame for f in streamed] == read.frames.tolist()
    assert np.array_equal(np.array([f.channels for f in streamed]), read.channels)
    filled = continuous(read)
    assert np.array_equal(filled.frames, motion.frames)
    assert np.array_equal(filled.channels[keep], motion.channels[keep])
    features = motion_features(read, 30.0)
    assert np.array_equal(features.frames, motion.frames[::4])  # sampled by frame number


def test_features_of_a_recording_with_a_gap_too_long_are_refused(tmp_path: Path) -> None:
    motion = trial()
    lost = set(motion.frames[200:260].tolist())  # 60 frames: 0.5 s
    path = write_without(TRIAL[1], tmp_path / "gappy.amc", lost)
    with pytest.raises(RecordingError, match=r"gappy.amc.*frames 201-260 are missing"):
        continuous(read_recording(TRIAL[0], path))
    line = assert_one_error_line(
        mocapd("features", "--asf", TRIAL[0], "--amc", path, "--csv", tmp_path / "f.csv")
    )
    assert "gappy.amc" in line and "frames 201-260 are missing" in line


@pytest.mark.slow
def test_a_daemon_fed_a_recording_that_lost_frames_publishes_what_detect_finds(tmp_path: Path) -> None:
    """End to end, as a user runs it: CMU 13_30 with random runs of 1-30 frames lost (and one of
    45, which ends the motion), written as an AMC file; ``mocapd replay`` of it into a real daemon
    publishes exactly the detections ``mocapd detect`` prints for the same file."""
    motion = trial()
    rng = random.Random(32)
    lost = lost_runs(rng, len(motion), 12) | set(range(1500, 1545))
    path = write_without(TRIAL[1], tmp_path / "13_30.amc", {int(motion.frames[k]) for k in lost})
    want = hits_json(mocapd("detect", "--asf", TRIAL[0], "--amc", path, "--json").stdout)
    assert len(want) >= 8
    daemon = Daemon(tmp_path, config={"service": {"queue_frames": 100_000}}).start()
    try:
        finished(replay(TRIAL[0], path, "zmq+" + daemon.poses, speed="max"))
        frames = len(motion) - len(lost)
        wait_for(lambda: daemon.metrics().get("mocapd_frames_in_total") == frames, 60, "every pose received")
        assert daemon.stop() == 0
        assert detection_keys(daemon.detections_printed()) == detection_keys(want)
    finally:
        daemon.stop()
