"""Any frame rate the library's divides (issue 35, item 4): the recogniser computes the features of
the index frames' poses alone (:func:`daemon.features.sampled_features`), so a recording resampled
from 120 Hz to 60 or 30 Hz gives the shipped library's detections at 120 Hz, class and time, on
CMU and HDM05 recordings; through ``mocapd detect`` of the resampled recording written as BVH too."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from daemon.features import features, sampled_features
from daemon.library import default_library_path, load_library
from daemon.recognizer import Detection, detect_positions
from daemon.recordings import read_recording
from replay import JOINT_NAMES
from replay.bvh import write_bvh
from replay.convert import motion_to_bvh
from replay.kinematics import joint_positions
from tests.helpers import assert_ok, assert_one_error_line, hdm05_clip, mocapd, pair_id, recording_pairs

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


def test_a_take_at_a_rate_the_librarys_does_not_divide_is_one_line_naming_it(tmp_path: Path) -> None:
    """100 Hz (Xsens, Rokoko) is not yet read (issue 35): one line naming the file and both rates."""
    (asf, amc) = next(p for p in recording_pairs() if pair_id(p) == "02_01")
    take = tmp_path / "at100.bvh"
    take.write_bytes(write_bvh(motion_to_bvh(read_recording(asf, amc), 100.0)))
    line = assert_one_error_line(mocapd("detect", "--bvh", take))
    assert line.startswith(f"mocapd: {take}: ") and "100 Hz" in line and "30 Hz" in line
