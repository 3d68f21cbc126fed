"""``mocapd features --asf A --amc M --csv OUT [--fps F] [--png P]``, run for real in a subprocess on
real files (see tests/test_cli.py for the other commands)."""

from __future__ import annotations

import csv
import gzip
import math
import re
from dataclasses import dataclass
from fractions import Fraction
from pathlib import Path

import numpy as np
import numpy.typing as npt
import pytest

from daemon.features import FEATURE_NAMES
from daemon.recordings import read_recording
from replay import MocapFormatError, Motion, read_amc, read_asf
from tests.helpers import (
    DATA,
    ORACLE,
    ORACLE_CLIPS,
    REPO,
    SOURCES,
    assert_ok,
    assert_one_error_line,
    csv_written,
    mocapd,
)
from tests.naive import naive_features

CMU_ASF, CMU_AMC = SOURCES["cmu"]
HEADER = ["frame", *FEATURE_NAMES]
PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


@dataclass(frozen=True)
class FeatureCsv:
    header: list[str]
    frames: npt.NDArray[np.int64]
    matrix: npt.NDArray[np.bool_]  # (rows, 39)
    text: str


def parse_features_csv(text: str) -> FeatureCsv:
    """Parse ``frame,<39 names>`` CSV text; every value must be exactly ``0`` or ``1``."""
    assert text.endswith("\n")
    rows = list(csv.reader(text.splitlines()))
    body = rows[1:]
    assert all(len(r) == 1 + len(FEATURE_NAMES) for r in body)
    assert all(v in ("0", "1") for r in body for v in r[1:])
    return FeatureCsv(
        header=rows[0],
        frames=np.array([int(r[0]) for r in body], dtype=np.int64),
        matrix=np.array([[v == "1" for v in r[1:]] for r in body], dtype=bool).reshape(
            -1, len(FEATURE_NAMES)
        ),
        text=text,
    )


def run_features(out: Path, asf: Path, amc: Path, *extra: str | Path) -> FeatureCsv:
    return parse_features_csv(csv_written("features", out, asf, amc, *extra))


@pytest.fixture(scope="module")
def cmu_motion() -> Motion:
    return read_recording(CMU_ASF, CMU_AMC)


@pytest.fixture(scope="module")
def cmu_batch() -> npt.NDArray[np.bool_]:
    return naive_features(CMU_ASF, CMU_AMC)


@pytest.fixture(scope="module")
def cmu_csv(tmp_path_factory: pytest.TempPathFactory) -> FeatureCsv:
    return run_features(tmp_path_factory.mktemp("features") / "02_01.csv", CMU_ASF, CMU_AMC)


# --------------------------------------------------------------------------------------------------
# the CSV at the native rate


def test_header(cmu_csv: FeatureCsv) -> None:
    assert cmu_csv.header == HEADER
    assert len(cmu_csv.header) == 40
    assert cmu_csv.text.split("\n", 1)[0] == "frame," + ",".join(FEATURE_NAMES)


@pytest.mark.parametrize("source", sorted(SOURCES))
def test_one_row_per_amc_frame_equal_to_the_library(
    source: str, tmp_path: Path, cmu_csv: FeatureCsv, cmu_motion: Motion, cmu_batch: npt.NDArray[np.bool_]
) -> None:
    if source == "cmu":
        table, motion, batch = cmu_csv, cmu_motion, cmu_batch
    else:
        asf, amc = SOURCES[source]
        table = run_features(tmp_path / "out.csv", asf, amc)
        motion = read_recording(asf, amc)
        batch = naive_features(asf, amc)
    assert table.header == HEADER
    assert len(table.frames) == len(motion) == len(batch)
    np.testing.assert_array_equal(table.frames, motion.frames)
    np.testing.assert_array_equal(table.frames, np.arange(1, len(motion) + 1))  # AMC frames are 1-based
    np.testing.assert_array_equal(table.matrix, batch)
    # not a degenerate comparison: features switch on and off in a walk
    assert 0 < table.matrix.sum() < table.matrix.size
    assert table.matrix.any(axis=0).sum() >= 10


@pytest.mark.slow
@pytest.mark.parametrize("clip", sorted(ORACLE_CLIPS))
def test_matches_the_toolbox_oracle(clip: str, tmp_path: Path) -> None:
    """Same header, frame numbers and 0/1 values as the original toolbox (120 Hz) on its 4 clips."""
    asf, amc = ORACLE_CLIPS[clip]
    ours = run_features(tmp_path / "out.csv", DATA / asf, DATA / amc)
    oracle = parse_features_csv((ORACLE / f"{clip}.features.csv").read_text(encoding="utf-8"))
    assert ours.header == oracle.header == HEADER
    np.testing.assert_array_equal(ours.frames, oracle.frames)
    assert ours.matrix.shape == oracle.matrix.shape
    mismatch = ours.matrix != oracle.matrix
    assert not mismatch.any(), {
        FEATURE_NAMES[k]: ours.frames[mismatch[:, k]].tolist()[:10]
        for k in np.flatnonzero(mismatch.any(axis=0))
    }


def test_csv_to_stdout(cmu_csv: FeatureCsv) -> None:
    """``--csv -`` writes the same text to stdout (through the console script) and no file."""
    result = mocapd("features", "--asf", CMU_ASF, "--amc", CMU_AMC, "--csv", "-", script=True)
    assert_ok(result)
    assert result.stdout == cmu_csv.text
    assert not (REPO / "-").exists()


# --------------------------------------------------------------------------------------------------
# --fps: decimation


@pytest.mark.slow
@pytest.mark.parametrize(("fps", "step"), [("120", 1), ("60", 2), ("30", 4), ("40", 3)])
def test_fps_keeps_every_kth_frame_from_the_first(
    fps: str, step: int, tmp_path: Path, cmu_motion: Motion, cmu_batch: npt.NDArray[np.bool_]
) -> None:
    """``--fps F`` gives the features of every (120 / F)-th pose, starting with the first, at F Hz:
    at 30 Hz those of AMC frames 1, 5, 9, ... (the toolbox's ``1:4:end`` of the poses, the
    velocity windows and hysteresis over those poses alone)."""
    table = run_features(tmp_path / "out.csv", CMU_ASF, CMU_AMC, "--fps", fps)
    n = len(cmu_motion)
    assert table.header == HEADER
    assert len(table.frames) == -(-n // step)  # ceil(343 / step)
    np.testing.assert_array_equal(table.frames, np.arange(1, n + 1, step))
    np.testing.assert_array_equal(table.frames, cmu_motion.frames[::step])
    np.testing.assert_array_equal(table.matrix, naive_features(CMU_ASF, CMU_AMC, step))
    if step > 1:  # not the native matrix's rows: windows over other instants
        assert not np.array_equal(table.matrix, cmu_batch[::step])
    if fps == "30":
        assert table.frames[:4].tolist() == [1, 5, 9, 13]
        assert len(table.frames) == 86


# --------------------------------------------------------------------------------------------------
# --png


@pytest.mark.slow
def test_png(tmp_path: Path, cmu_csv: FeatureCsv) -> None:
    """``--png`` writes a real PNG picture of the matrix, besides the unchanged CSV."""
    import matplotlib.image

    png = tmp_path / "features.png"
    table = run_features(tmp_path / "out.csv", CMU_ASF, CMU_AMC, "--png", png)
    assert table.text == cmu_csv.text
    data = png.read_bytes()
    assert data.startswith(PNG_SIGNATURE)
    assert data[12:16] == b"IHDR"
    assert len(data) > 10_000  # three panels with labels and 343 columns of features
    image = np.asarray(matplotlib.image.imread(png))
    assert image.ndim == 3 and image.shape[2] in (3, 4)
    height, width = image.shape[:2]
    assert height >= 300 and width >= 300
    luminance = image[..., :3].mean(axis=2)
    # white background and black feature cells (and grey text)
    assert (luminance > 0.95).mean() > 0.2
    assert (luminance < 0.05).mean() > 0.01


# --------------------------------------------------------------------------------------------------
# bad input: exit status 2, one line on stderr naming the option or the file (and the line), no output


@pytest.mark.slow
@pytest.mark.parametrize(("fps", "step", "per"), [("50", 12, 5), ("7", 120, 7)])
def test_fps_that_does_not_divide_the_native_rate_blends_the_poses(
    fps: str, step: int, per: int, tmp_path: Path, cmu_motion: Motion
) -> None:
    """``--fps F`` where F does not divide 120 Hz: the features of the poses at the instants of F
    Hz, each blended from the two frames around it, numbered by the first frame at or after it."""
    table = run_features(tmp_path / "out.csv", CMU_ASF, CMU_AMC, "--fps", fps)
    n = len(cmu_motion)
    instants = [Fraction(j * step, per) for j in range(n) if Fraction(j * step, per) <= n - 1]
    assert table.frames.tolist() == [int(cmu_motion.frames[0]) + math.ceil(t) for t in instants]
    np.testing.assert_array_equal(table.matrix, naive_features(CMU_ASF, CMU_AMC, step, per=per))


@pytest.mark.slow
@pytest.mark.parametrize("fps", ["240", "1000"])
def test_fps_above_the_native_rate(tmp_path: Path, fps: str) -> None:
    out = tmp_path / "out.csv"
    line = assert_one_error_line(
        mocapd("features", "--asf", CMU_ASF, "--amc", CMU_AMC, "--csv", out, "--fps", fps)
    )
    assert line.startswith("mocapd: --fps: "), line
    assert fps in line and "120" in line
    assert not out.exists()


@pytest.mark.slow
@pytest.mark.parametrize("fps", ["0", "-30", "nan", "abc"])
def test_fps_that_is_not_a_positive_number(tmp_path: Path, fps: str) -> None:
    out = tmp_path / "out.csv"
    result = mocapd("features", "--asf", CMU_ASF, "--amc", CMU_AMC, "--csv", out, "--fps", fps)
    assert result.returncode == 2, (result.returncode, result.stderr)
    assert "Traceback" not in result.stderr, result.stderr
    assert "--fps" in result.stderr and result.stdout == ""
    assert not out.exists()


@pytest.mark.parametrize("missing", ["asf", "amc"])
def test_missing_file(tmp_path: Path, missing: str) -> None:
    gone = tmp_path / f"nope.{missing}"
    asf, amc = (gone, CMU_AMC) if missing == "asf" else (CMU_ASF, gone)
    out = tmp_path / "out.csv"
    line = assert_one_error_line(mocapd("features", "--asf", asf, "--amc", amc, "--csv", out))
    assert line == f"mocapd: {gone}: No such file or directory"
    assert not out.exists()


def test_unwritable_csv(tmp_path: Path) -> None:
    out = tmp_path / "no-such-dir" / "out.csv"
    line = assert_one_error_line(mocapd("features", "--asf", CMU_ASF, "--amc", CMU_AMC, "--csv", out))
    assert line == f"mocapd: {out}: No such file or directory"


def amc_lines() -> list[str]:
    """02_01 decompressed, split on LF (every line keeps its CR)."""
    return gzip.decompress(CMU_AMC.read_bytes()).decode("latin-1").split("\n")


def check_format_error(tmp_path: Path, amc: Path, reason: str) -> tuple[int, str]:
    """Run ``features`` on a broken AMC: the library raises ``<file>:<line>: <reason>`` (``reason``
    matches the regular expression ``reason`` from its start), and the command exits 2 with
    ``mocapd: `` and that message, with no CSV written (to a file or to stdout). Returns (line,
    reason)."""
    with pytest.raises(MocapFormatError, match=rf"^{re.escape(str(amc))}:\d+: {reason}") as caught:
        read_amc(amc, read_asf(CMU_ASF))
    out = tmp_path / "out.csv"
    line = assert_one_error_line(mocapd("features", "--asf", CMU_ASF, "--amc", amc, "--csv", out))
    match = re.fullmatch(rf"mocapd: {re.escape(str(amc))}:(\d+): (.+)", line)
    assert match, line
    assert (int(match.group(1)), match.group(2)) == (caught.value.line, caught.value.reason)
    assert not out.exists()
    to_stdout = mocapd("features", "--asf", CMU_ASF, "--amc", amc, "--csv", "-")
    assert assert_one_error_line(to_stdout) == line  # also checks that nothing reached stdout
    return int(match.group(1)), match.group(2)


def test_amc_truncated_in_the_middle_of_a_frame(tmp_path: Path) -> None:
    """The file ends after frame 17's ``lradius`` line: the error names the file, the line where
    the missing bones should have been (just past the end) and the frame."""
    lines = amc_lines()
    (at,) = [n for n, line in enumerate(lines, 1) if line.startswith("lradius ")][16:17]
    assert lines.index("17\r") < at - 1 < lines.index("18\r")  # in frame 17's block
    path = tmp_path / "truncated.amc"
    path.write_text("\n".join(lines[:at]) + "\n", encoding="latin-1")
    line, reason = check_format_error(
        tmp_path, path, r"frame 17 \(line \d+\) is incomplete when the file ends: no line for lfemur, "
    )
    assert line in (at, at + 1), (line, at)
    assert "frame 17" in reason and "incomplete" in reason and "lfemur" in reason


@pytest.mark.slow
def test_amc_with_a_short_bone_line(tmp_path: Path) -> None:
    """Frame 100's ``rfemur`` line lost one of its 3 values: the error names that exact line."""
    lines = amc_lines()
    (at,) = [n for n, line in enumerate(lines, 1) if line.startswith("rfemur ")][99:100]
    words = lines[at - 1].split()
    assert len(words) == 4
    lines[at - 1] = " ".join(words[:3]) + "\r"
    path = tmp_path / "short.amc"
    path.write_bytes("\n".join(lines).encode("latin-1"))
    line, reason = check_format_error(
        tmp_path, path, r"bone 'rfemur' needs 3 values, got 2 \(3 dofs in .*\.asf\)$"
    )
    assert line == at
    assert "rfemur" in reason


def test_amc_gzip_cut_short(tmp_path: Path) -> None:
    data = CMU_AMC.read_bytes()
    path = tmp_path / "cut.amc.gz"
    path.write_bytes(data[: len(data) // 2])
    _, reason = check_format_error(tmp_path, path, r"damaged or truncated gzip data")
    assert reason.startswith("damaged or truncated gzip data")
