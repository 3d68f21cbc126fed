"""``mocapd detect`` in a real process: the detections of the library's recogniser, as JSON lines or
readable lines, paced or not, drawn with the labels; bad options exit 2 with one line."""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np
import pytest

from daemon.learn.library import save_library
from daemon.library import Library, default_library_path, load_library
from daemon.recognizer import detect, detect_positions
from daemon.recordings import native_rate, read_recording
from replay.bvh import read_bvh
from replay.rigs import bvh_standard_joints
from tests.helpers import (
    CMU_AMC,
    CMU_ASF,
    assert_one_error_line,
    hdm05_clip,
    mocapd,
    small_library,
    takes,
)

FIELDS = ["id", "stream", "class", "start_frame", "end_frame", "cost", "tau", "emitted_at_frame"]


@pytest.fixture(scope="module")
def library(tmp_path_factory: pytest.TempPathFactory) -> tuple[Library, Path]:
    where = tmp_path_factory.mktemp("lib")
    library = small_library(where)
    save_library(library, where / "library")
    return library, where / "library"


def squat() -> tuple[Path, Path]:
    return hdm05_clip("dg", "squat1Reps", takes("squat1Reps", "dg")[0])


def test_json_lines_are_the_recognizers(library: tuple[Library, Path]) -> None:
    lib, path = library
    asf, amc = squat()
    result = mocapd("detect", "--asf", asf, "--amc", amc, "--library", path, "--json")
    assert (result.returncode, result.stderr) == (0, "")
    got = [json.loads(line) for line in result.stdout.splitlines()]
    assert got and all(list(d) == FIELDS for d in got)
    motion = read_recording(asf, amc)
    stream = amc.name.removesuffix(".amc.gz")
    expected = [d.as_json() for d in detect(motion, lib, native_rate(motion), stream=stream)]
    assert [{**d, "id": ""} for d in got] == [{**d, "id": ""} for d in expected]
    assert len({d["id"] for d in got}) == len(got)


def test_readable_lines_and_classes(library: tuple[Library, Path]) -> None:
    _, path = library
    asf, amc = squat()
    result = mocapd("detect", "--asf", asf, "--amc", amc, "--library", path, "--classes", "squat1Reps")
    assert (result.returncode, result.stderr) == (0, "")
    *lines, summary = result.stdout.splitlines()
    assert len(lines) == 1
    assert lines[0].split()[0] == "squat1Reps"
    assert " s  cost " in lines[0] and "latency" in lines[0]
    assert summary.startswith("1 detections in 179 frames (1.5 s at 120 Hz), 1 classes")


@pytest.mark.slow
def test_paced_by_the_clock(library: tuple[Library, Path]) -> None:
    """At twice real time, 179 frames at 120 Hz take at least 0.74 s; as fast as possible, the
    same detections."""
    _, path = library
    asf, amc = squat()
    began = time.perf_counter()
    paced = mocapd("detect", "--asf", asf, "--amc", amc, "--library", path, "--json", "--speed", "2")
    assert time.perf_counter() - began >= 178 / 240
    fast = mocapd("detect", "--asf", asf, "--amc", amc, "--library", path, "--json", "--speed", "max")
    assert paced.returncode == fast.returncode == 0
    strip = [{**json.loads(line), "id": ""} for line in paced.stdout.splitlines()]
    assert strip == [{**json.loads(line), "id": ""} for line in fast.stdout.splitlines()]


@pytest.mark.slow
def test_png_with_truth(library: tuple[Library, Path], tmp_path: Path) -> None:
    _, path = library
    truth = tmp_path / "truth.csv"
    truth.write_text(
        "trial,label_name,start_frame,end_frame\n13_29,Squat,1,400\nother,Squat,1,9\n", encoding="utf-8"
    )
    out = tmp_path / "t.png"
    result = mocapd(
        "detect",
        "--asf",
        CMU_ASF,
        "--amc",
        CMU_AMC,
        "--library",
        path,
        "--png",
        out,
        "--truth",
        truth,
        "--json",
    )
    assert (result.returncode, result.stderr) == (0, "")
    assert out.read_bytes().startswith(b"\x89PNG")


@pytest.mark.slow
@pytest.mark.parametrize(
    ("extra", "message"),
    [
        (("--speed", "0"), "--speed: must be 'max' or a positive factor"),
        (("--speed", "fast"), "--speed: must be 'max' or a positive factor"),
        (("--classes", "squat1Reps,nope"), "no class 'nope' in the library"),
        (("--classes", "squat1Reps,"), "--classes: an empty class name"),
        (("--classes", "squat1Reps,squat1Reps"), "--classes: a class is named twice"),
        (("--truth", "x.csv"), "--truth: --truth is drawn in --png"),
        (("--png", "x.txt"), "does not end in .png"),
    ],
)
def test_bad_options(library: tuple[Library, Path], extra: tuple[str, ...], message: str) -> None:
    _, path = library
    asf, amc = squat()
    line = assert_one_error_line(mocapd("detect", "--asf", asf, "--amc", amc, "--library", path, *extra))
    assert message in line


def test_bad_truth_names_file_and_line(library: tuple[Library, Path], tmp_path: Path) -> None:
    _, path = library
    asf, amc = squat()
    truth = tmp_path / "truth.csv"
    truth.write_text("class,start_frame,end_frame\nsquat1Reps,10,x\n", encoding="utf-8")
    line = assert_one_error_line(
        mocapd(
            "detect",
            "--asf",
            asf,
            "--amc",
            amc,
            "--library",
            path,
            "--png",
            tmp_path / "a.png",
            "--truth",
            truth,
        )
    )
    assert line == f"mocapd: {truth}:2: start_frame and end_frame must be integers"


def test_missing_library(tmp_path: Path) -> None:
    asf, amc = squat()
    line = assert_one_error_line(mocapd("detect", "--asf", asf, "--amc", amc, "--library", tmp_path / "none"))
    assert str(tmp_path / "none") in line


BANDAI = Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "mocap" / "bandai2"


def test_a_bvh_recording_is_recognised_as_its_standard_joints_are() -> None:
    """``--bvh``: a bandai2 take (CC BY-NC-ND 4.0, read unmodified) through its rig map, live, gives
    the batch twin's detections of its standard joints (frames numbered from 1), at its 30 Hz."""
    take = BANDAI / "dataset-2_walk_normal_001.bvh.gz"
    result = mocapd("detect", "--bvh", take, "--json")
    assert (result.returncode, result.stderr) == (0, "")
    got = [json.loads(line) for line in result.stdout.splitlines()]
    motion = read_bvh(take)
    joints, _ = bvh_standard_joints(motion)
    stream = "dataset-2_walk_normal_001"
    expected = detect_positions(
        joints, np.arange(1, len(joints) + 1), load_library(default_library_path()), 30.0, stream=stream
    )
    assert got and [{**d, "id": ""} for d in got] == [{**d.as_json(), "id": ""} for d in expected]


@pytest.mark.parametrize(
    ("extra", "message"),
    [
        (("--bvh", "x.bvh", "--asf", "a.asf"), "--bvh: give --bvh, or --asf and --amc, not both"),
        ((), "--asf: give --asf and --amc (or --bvh)"),
        (
            ("--bvh", str(BANDAI / "content_label.txt")),
            "content_label.txt:1: a BVH file begins with HIERARCHY",
        ),
    ],
)
def test_bad_bvh_options_and_files(extra: tuple[str, ...], message: str) -> None:
    line = assert_one_error_line(mocapd("detect", *extra))
    assert message in line, line
