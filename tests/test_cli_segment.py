"""``mocapd segment`` in a real process: the cuts of :mod:`daemon.behaviours` in AMC frame numbers, as
JSON lines or readable lines, scored against a truth file and drawn; bad options and files exit 2
with one line. The truth readers."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from daemon import behaviours as bh
from daemon.behaviours import match_boundaries
from daemon.recordings import LabelError, native_rate, read_boundaries, read_recording
from daemon.types import Band
from tests.helpers import DATA, assert_one_error_line, mocapd

ASF = DATA / "cmu" / "86" / "86.asf"
AMC = DATA / "cmu" / "86" / "86_01.amc.gz"
CMU86 = DATA / "annotations" / "cmu86_aca_haca" / "cmu86_segments.csv"
MOCAP6 = DATA / "annotations" / "mocap6" / "per_frame_120hz" / "segments_120hz.csv"


def expected_cuts(method: bh.Method) -> list[int]:
    motion = read_recording(ASF, AMC)
    x = bh.JointRotations(motion.skeleton)(motion.channels)
    return [int(motion.frames[b.frame]) for b in bh.segment(x, native_rate(motion), method)]


@pytest.mark.slow
@pytest.mark.parametrize("method", ["pca", "ppca", "gmm"])
def test_json_lines_are_the_methods_cuts(method: bh.Method) -> None:
    result = mocapd("segment", "--asf", ASF, "--amc", AMC, "--method", method, "--json")
    assert (result.returncode, result.stderr) == (0, "")
    got = [json.loads(line) for line in result.stdout.splitlines()]
    assert all(list(c) == ["frame", "method", "score"] and c["method"] == method for c in got)
    assert [c["frame"] for c in got] == expected_cuts(method) != []


@pytest.mark.slow
def test_readable_lines_scored_against_the_truth_and_drawn(tmp_path: Path) -> None:
    png = tmp_path / "s.png"
    result = mocapd("segment", "--asf", ASF, "--amc", AMC, "--method", "pca", "--truth", CMU86, "--png", png)
    assert (result.returncode, result.stderr) == (0, "")
    *lines, summary, scored = result.stdout.splitlines()
    cuts = expected_cuts("pca")
    assert [int(line.split()[3]) for line in lines] == cuts
    assert summary.startswith(f"{len(cuts)} cuts by pca in 4579 frames (38.2 s at 120 Hz), 14 joints")
    bands = read_boundaries(CMU86, "86_01")
    hits = match_boundaries(cuts, bands)
    assert scored == (
        f"truth: {hits} of 6 boundaries, precision {hits / len(cuts):.2f}, recall {hits / 6:.2f}"
    )
    assert png.read_bytes().startswith(b"\x89PNG")


@pytest.mark.slow
@pytest.mark.parametrize(
    ("extra", "message"),
    [
        (("--method", "svd"), "--method: invalid choice: 'svd'"),
        (("--window", "0"), "--method ppca: window = 0 s is 0 frames at 120 Hz"),
        (("--method", "pca", "--ell", "nan"), "--method pca: ell must be a finite number of seconds"),
        (("--shortest", "-1"), "--method ppca: shortest = -1 s is -120 frames at 120 Hz; it must be >= 0"),
        (("--method", "gmm", "--variance", "2"), "--method gmm: variance must lie in (0, 1]"),
        (("--png", "x.txt"), "does not end in .png"),
    ],
)
def test_bad_options(extra: tuple[str, ...], message: str) -> None:
    line = assert_one_error_line(mocapd("segment", "--asf", ASF, "--amc", AMC, *extra))
    assert message in line


def test_bad_truth_names_file_and_line(tmp_path: Path) -> None:
    truth = tmp_path / "truth.csv"
    truth.write_text("trial,segment,start_frame,end_frame,end_lo,end_hi\n86_01,1,1,x,5,9\n", encoding="utf-8")
    line = assert_one_error_line(mocapd("segment", "--asf", ASF, "--amc", AMC, "--truth", truth))
    assert line == f"mocapd: {truth}:2: end_frame, end_lo, end_hi and segment must be integers"


# ------------------------------------------------------------------------------------ the truth


def test_boundaries_of_the_two_label_layouts(tmp_path: Path) -> None:
    # cmu86: after every segment but the last, with its band, in segment order
    bands = read_boundaries(CMU86, "86_01")
    assert bands[:2] == [Band(551, 501, 601), Band(1151, 1101, 1201)] and len(bands) == 6
    # mocap6: at the first frame of every run but the first, ± 0.5 s
    assert read_boundaries(MOCAP6, "13_30") == [
        Band(217, 157, 277),
        Band(805, 745, 865),
        Band(1417, 1357, 1477),
        Band(1933, 1873, 1993),
    ]
    assert read_boundaries(MOCAP6, "13_30", rate=60.0, tolerance_s=1.0)[0] == Band(217, 157, 277)
    shuffled = tmp_path / "t.csv"
    shuffled.write_text("class,start_frame,end_frame\nb,50,99\na,1,49\n", encoding="utf-8")
    assert read_boundaries(shuffled) == [Band(50, -10, 110)]  # segments in frame order
    shuffled.write_text("class,start_frame,end_frame\nb,50,9\n", encoding="utf-8")
    with pytest.raises(LabelError, match=r"t\.csv:2: start_frame 50 is after end_frame 9"):
        read_boundaries(shuffled)
