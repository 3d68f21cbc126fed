"""Any frame rate (issue 35, item 4): the recogniser computes the features of the poses at the index
frames' instants alone (:func:`daemon.features.sampled_features`), so a recording resampled from
120 Hz to 60 or 30 Hz gives the shipped library's detections at 120 Hz, class and time, on CMU and
HDM05 recordings; through ``mocapd detect`` of the resampled recording written as BVH too. At a
rate the library's does not divide (100 Hz, 50 Hz) the pose at each index frame's instant is
blended from the two frames around it, in the live path as in the batch, and the detections are
those at 120 Hz within a frame."""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path

import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from daemon.features import features, sample_poses, sampled_features
from daemon.library import default_library_path, load_library
from daemon.recognizer import Detection, Recognizer, detect, detect_positions
from daemon.recordings import read_recording
from daemon.types import FloatArray
from replay import JOINT_NAMES
from replay.bvh import write_bvh
from replay.convert import motion_to_bvh
from replay.kinematics import joint_positions
from tests.helpers import assert_ok, hdm05_clip, mocapd, pair_id, recording_pairs, resampled_motion
from tests.naive import slow_sample_poses

TRIALS = ("13_29", "86_01", "02_05")
CLIPS = (("bd", "squat1Reps", 1), ("dg", "hopBothLegs1hops", 22), ("bd", "kickLFront1Reps", 1))


def recordings() -> list[tuple[str, Path, Path]]:
    pairs = {pair_id(p): p for p in recording_pairs()}
    out = [(t, *pairs[t]) for t in TRIALS]
    for actor, cls, take in CLIPS:
        asf, amc = hdm05_clip(actor, cls, take)
        out.append((amc.name, asf, amc))
    return out


def in_seconds(found: list[Detection], rate: float) -> list[tuple[str, float, float]]:
    """Each detection's class, start and end (the end of its last frame) in seconds from frame 0."""
    return [(d.class_name, d.start_frame / rate, (d.end_frame + 1) / rate) for d in found]


@pytest.mark.parametrize(("name", "asf", "amc"), recordings(), ids=[r[0] for r in recordings()])
def test_a_recording_resampled_to_60_and_30_hz_gives_its_detections_at_120_hz(
    name: str, asf: Path, amc: Path
) -> None:
    library = load_library(default_library_path())
    positions = joint_positions(read_recording(asf, amc))
    base = in_seconds(detect_positions(positions, np.arange(len(positions)), library, 120.0), 120.0)
    assert base or name.startswith("HDM")  # the CMU trials hold motions of the library's classes
    for k in (2, 4):
        rate = 120.0 / k
        lower = positions[::k]
        got = in_seconds(detect_positions(lower, np.arange(len(lower)), library, rate), rate)
        assert [c for c, _, _ in got] == [c for c, _, _ in base]
        for (_, s, e), (_, s0, e0) in zip(got, base, strict=True):
            assert s == s0  # the same index frame
            assert abs(e - e0) <= 1 / 30  # the last index frame's end: within one index frame


@settings(max_examples=30, deadline=None)
@given(st.integers(1, 6), st.integers(0, 5), st.integers(40, 160))
def test_the_features_of_every_kth_pose_are_those_of_the_recording_at_the_lower_rate(
    step: int, offset: int, n: int
) -> None:
    """On real poses: the sampled features at ``30·k`` Hz equal the features of the poses resampled
    to 30 Hz, and they are not the rows of the native matrix (whose windows span native frames)."""
    (asf, amc) = next(p for p in recording_pairs() if pair_id(p) == "13_29")
    poses = joint_positions(read_recording(asf, amc))[300 + offset : 300 + offset + n * step]
    got = sampled_features(poses, JOINT_NAMES, 30.0 * step, step)
    assert np.array_equal(got, features(poses[::step], JOINT_NAMES, 30.0))
    assert got.shape == (len(poses[::step]), 39)


def test_mocapd_detect_of_a_take_written_at_30_hz_gives_the_detections_at_120_hz(tmp_path: Path) -> None:
    """A user's path: CMU 13_29 resampled to 30 Hz and written as BVH (``replay.convert``), then
    ``mocapd detect --bvh``: the AMC's detections at 120 Hz, in seconds from the first frame."""
    (asf, amc) = next(p for p in recording_pairs() if pair_id(p) == "13_29")
    motion = read_recording(asf, amc)
    lower = dataclasses.replace(motion, frames=motion.frames[::4], channels=motion.channels[::4])
    take = tmp_path / "13_29_30hz.bvh"
    take.write_bytes(write_bvh(motion_to_bvh(lower, 30.0)))
    at_30 = mocapd("detect", "--bvh", take, "--json")
    at_120 = mocapd("detect", "--asf", asf, "--amc", amc, "--json")
    assert_ok(at_30)
    first = int(motion.frames[0])

    def found(output: str, rate: float, first: int) -> list[tuple[str, float, float]]:
        rows = [json.loads(line) for line in output.splitlines()]
        return [
            (r["class"], (r["start_frame"] - first) / rate, (r["end_frame"] + 1 - first) / rate) for r in rows
        ]

    got, want = found(at_30.stdout, 30.0, 1), found(at_120.stdout, 120.0, first)
    assert want and [c for c, _, _ in got] == [c for c, _, _ in want]
    for (_, s, e), (_, s0, e0) in zip(got, want, strict=True):
        assert abs(s - s0) < 1e-9 and abs(e - e0) <= 1 / 30


def resampled(positions: FloatArray, native: float, rate: float) -> FloatArray:
    """``positions`` (N, J, 3) at ``native`` Hz resampled to ``rate`` Hz (linear interpolation)."""
    n = int((len(positions) - 1) * rate / native) + 1
    t = np.arange(n) * native / rate
    i = np.minimum(t.astype(int), len(positions) - 2)
    w = (t - i)[:, None, None]
    out: FloatArray = (1 - w) * positions[i] + w * positions[i + 1]
    return out


@pytest.mark.parametrize(("name", "asf", "amc"), recordings(), ids=[r[0] for r in recordings()])
def test_a_recording_resampled_to_100_and_50_hz_gives_its_detections_at_120_hz(
    name: str, asf: Path, amc: Path
) -> None:
    """Rates the library's 30 Hz does not divide (Rokoko's and Xsens' 100 Hz): every detection's
    class, its start and its end within an index frame (the poses at the index instants are
    blends, not the recording's own) and a native frame (an index frame is the first frame at or
    after its instant)."""
    library = load_library(default_library_path())
    positions = joint_positions(read_recording(asf, amc))
    base = in_seconds(detect_positions(positions, np.arange(len(positions)), library, 120.0), 120.0)
    for rate in (100.0, 50.0):
        lower = resampled(positions, 120.0, rate)
        got = in_seconds(detect_positions(lower, np.arange(len(lower)), library, rate), rate)
        assert [c for c, _, _ in got] == [c for c, _, _ in base], rate
        for (_, s, e), (_, s0, e0) in zip(got, base, strict=True):
            assert abs(s - s0) <= 1 / 30 + 1 / rate + 1e-9
            assert abs(e - e0) <= 1 / 30 + 1 / rate + 1e-9


@settings(max_examples=100, deadline=None)
@given(st.integers(1, 12), st.integers(1, 5), st.integers(0, 60), st.integers(0, 2**32 - 1))
def test_the_poses_at_the_index_instants_equal_a_slow_enumeration(
    step: int, per: int, n: int, seed: int
) -> None:
    assume(step >= per and math.gcd(step, per) == 1)
    positions = np.random.default_rng(seed).normal(size=(n, 4, 3))
    got = sample_poses(positions, step, per)
    want = slow_sample_poses(positions, step, per)
    assert got.shape == want.shape and np.array_equal(got, want)


@pytest.mark.parametrize("kind", ["channels", "positions"])
def test_the_live_path_at_100_hz_equals_its_batch_twin(kind: str) -> None:
    """A stream at 100 Hz pushed frame by frame (forward kinematics of the frames around each index
    instant, the blend in compiled code) gives the batch twin's detections, bit for bit."""
    library = load_library(default_library_path())
    (asf, amc) = next(p for p in recording_pairs() if pair_id(p) == "13_29")
    motion = read_recording(asf, amc)
    frames = motion.frames[:3000]
    motion = dataclasses.replace(motion, frames=frames, channels=motion.channels[:3000])
    want = detect(motion, library, 100.0, stream="s", session="t")
    assert want
    if kind == "channels":
        recognizer = Recognizer.for_skeleton(library, motion.skeleton, 100.0, stream="s", session="t")
        values = list(motion.channels)
    else:
        recognizer = Recognizer.for_positions(library, JOINT_NAMES, 100.0, stream="s", session="t")
        values = list(joint_positions(motion))
    got = [d for number, v in zip(frames.tolist(), values, strict=True) for d in recognizer.push(number, v)]
    assert got + recognizer.flush() == want


def test_mocapd_detect_of_a_take_at_100_hz_gives_the_detections_at_120_hz(tmp_path: Path) -> None:
    """A user's path: CMU 13_29 resampled to 100 Hz (its channels blended, angles the short way
    round) and written as BVH, then ``mocapd detect --bvh``: the AMC's detections at 120 Hz, each
    start within an index frame."""
    (asf, amc) = next(p for p in recording_pairs() if pair_id(p) == "13_29")
    motion = read_recording(asf, amc)
    take = tmp_path / "13_29_100hz.bvh"
    take.write_bytes(write_bvh(motion_to_bvh(resampled_motion(motion, 120.0, 100.0), 100.0)))
    at_100 = mocapd("detect", "--bvh", take, "--json")
    at_120 = mocapd("detect", "--asf", asf, "--amc", amc, "--json")
    assert_ok(at_100)
    first = int(motion.frames[0])
    got = [json.loads(line) for line in at_100.stdout.splitlines()]
    want = [json.loads(line) for line in at_120.stdout.splitlines()]
    assert want and [r["class"] for r in got] == [r["class"] for r in want]
    for r, r0 in zip(got, want, strict=True):
        assert abs((r["start_frame"] - 1) / 100 - (r0["start_frame"] - first) / 120) <= 1 / 30 + 1e-9
