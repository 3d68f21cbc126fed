"""The ``mocapd`` command, run for real in a subprocess (``python -m daemon`` and the console script)."""

from __future__ import annotations

import csv
import gzip
import json
import os
import re
import subprocess
import sys
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import numpy.typing as npt
import pytest

from daemon import cli
from replay import JOINT_NAMES, KinematicModel, MocapFormatError, Motion, read_amc, read_asf
from tests.helpers import (
    CMU_AMC,
    CMU_ASF,
    CONTROL,
    DG_CLIPS,
    HDM_AMC,
    HDM_ASF,
    MOCAPD_SCRIPT,
    REPO,
    TRAINING,
    assert_ok,
    assert_one_error_line,
    csv_written,
    hdm05_clip,
    mocapd,
    training_rows,
    write_manifest,
    write_training,
)

CM_PER_ASF_UNIT = 2.54 / 0.45
SIX_DECIMALS = re.compile(r"-?\d+\.\d{6}")


def info_fields(stdout: str) -> dict[str, str]:
    """``key: value`` lines of ``mocapd info``'s text output."""
    fields = {}
    for line in stdout.splitlines():
        key, value = line.split(":", 1)
        fields[key] = value.strip()
    return fields


# --------------------------------------------------------------------------------------------------
# info


@pytest.mark.slow
@pytest.mark.parametrize("script", [False, True], ids=["python-m-daemon", "mocapd-script"])
def test_info_text(script: bool) -> None:
    assert MOCAPD_SCRIPT.is_file()
    result = mocapd("info", "--asf", CMU_ASF, "--amc", CMU_AMC, script=script)
    assert_ok(result)
    fields = info_fields(result.stdout)
    skeleton = read_asf(CMU_ASF)
    assert fields["frames"] == "343 (AMC frames 1-343)"
    assert fields["duration"] == "2.858 s at 120 Hz (assumed)"
    assert fields["bones"] == "30: " + " ".join(b.name for b in skeleton.bones)
    assert fields["channels"] == "62"
    assert fields["joints"] == "26: " + " ".join(JOINT_NAMES)
    assert fields["asf"].startswith(f"{CMU_ASF} (VICON;")
    assert fields["amc"] == f"{CMU_AMC} (angles in deg)"


def info_json(*extra: str) -> dict[str, object]:
    result = mocapd("info", "--asf", CMU_ASF, "--amc", CMU_AMC, "--json", *extra)
    assert_ok(result)
    assert result.stdout.count("\n") == 1
    summary = json.loads(result.stdout)
    assert isinstance(summary, dict)
    return summary


def test_info_json() -> None:
    summary = info_json()
    skeleton = read_asf(CMU_ASF)
    assert summary["frames"] == 343
    assert (summary["first_frame"], summary["last_frame"]) == (1, 343)
    assert summary["frame_rate_hz"] == 120.0
    assert summary["frame_rate_source"] == "assumed"
    assert summary["duration_s"] == pytest.approx(343 / 120)
    assert round(float(summary["duration_s"]), 3) == 2.858  # type: ignore[arg-type]
    assert summary["bones"] == [b.name for b in skeleton.bones]
    assert len(skeleton.bones) == 30
    assert summary["joints"] == list(JOINT_NAMES)
    assert len(JOINT_NAMES) == 26
    assert summary["missing_joint_bones"] == []
    assert summary["channels"] == 62
    assert (summary["asf"], summary["amc"]) == (str(CMU_ASF), str(CMU_AMC))
    assert (summary["angle_unit"], summary["length_unit"], summary["skeleton"]) == ("deg", 0.45, "VICON")


@pytest.mark.slow
def test_info_fps_60_doubles_the_duration() -> None:
    at_120, at_60 = info_json(), info_json("--native-fps", "60")
    assert at_60["frame_rate_hz"] == 60.0
    assert at_60["frame_rate_source"] == "given"
    assert at_60["frames"] == at_120["frames"] == 343
    assert at_60["duration_s"] == pytest.approx(2 * float(at_120["duration_s"]))  # type: ignore[arg-type]

    result = mocapd("info", "--asf", CMU_ASF, "--amc", CMU_AMC, "--native-fps", "60")
    assert_ok(result)
    assert info_fields(result.stdout)["duration"] == "5.717 s at 60 Hz (given)"


def test_info_hdm05() -> None:
    result = mocapd("info", "--asf", HDM_ASF, "--amc", HDM_AMC, "--json")
    assert_ok(result)
    summary = json.loads(result.stdout)
    assert summary["frames"] == len(read_amc(HDM_AMC, read_asf(HDM_ASF))) == 140
    assert summary["duration_s"] == pytest.approx(140 / 120)
    assert summary["joints"] == list(JOINT_NAMES)


# --------------------------------------------------------------------------------------------------
# positions


@dataclass(frozen=True)
class Csv:
    header: list[str]
    frames: npt.NDArray[np.int64]
    joints: list[str]
    xyz: npt.NDArray[np.float64]
    text: str


def read_positions_csv(text: str) -> Csv:
    rows = list(csv.reader(text.splitlines()))
    body = rows[1:]
    assert all(len(r) == 5 for r in body)
    assert all(SIX_DECIMALS.fullmatch(v) for r in body for v in r[2:])
    return Csv(
        header=rows[0],
        frames=np.array([int(r[0]) for r in body], dtype=np.int64),
        joints=[r[1] for r in body],
        xyz=np.array([[float(v) for v in r[2:]] for r in body], dtype=np.float64),
        text=text,
    )


def expected_joints(motion: Motion, unit: str) -> npt.NDArray[np.float64]:
    """Joint positions from the library: shape (frames x joints, 3), rows in CSV order."""
    model = KinematicModel(motion.skeleton)
    joints = model.joints(model.positions(motion.channels, "cm" if unit == "cm" else "asf"))
    return joints.reshape(-1, 3)


def run_positions(tmp: Path, asf: Path, amc: Path, *extra: str) -> Csv:
    return read_positions_csv(csv_written("positions", tmp / "positions.csv", asf, amc, *extra))


@pytest.fixture(scope="module")
def cmu_motion() -> Motion:
    return read_amc(CMU_AMC, read_asf(CMU_ASF))


@pytest.fixture(scope="module")
def cmu_csv(tmp_path_factory: pytest.TempPathFactory) -> Csv:
    return run_positions(tmp_path_factory.mktemp("asf"), CMU_ASF, CMU_AMC)


@pytest.fixture(scope="module")
def cmu_csv_cm(tmp_path_factory: pytest.TempPathFactory) -> Csv:
    return run_positions(tmp_path_factory.mktemp("cm"), CMU_ASF, CMU_AMC, "--cm")


def check_positions(table: Csv, motion: Motion, unit: str) -> None:
    n = len(motion)
    assert table.header == ["frame", "joint", "x", "y", "z"]
    assert len(table.joints) == n * 26
    np.testing.assert_array_equal(table.frames, np.repeat(motion.frames, 26))
    assert table.joints == list(JOINT_NAMES) * n
    assert np.max(np.abs(table.xyz - expected_joints(motion, unit))) <= 1e-6


def test_positions_csv(cmu_csv: Csv, cmu_motion: Motion) -> None:
    assert len(cmu_motion) == 343
    check_positions(cmu_csv, cmu_motion, "asf")


def test_positions_csv_hdm05(tmp_path: Path) -> None:
    motion = read_amc(HDM_AMC, read_asf(HDM_ASF))
    check_positions(run_positions(tmp_path, HDM_ASF, HDM_AMC), motion, "asf")


def test_positions_cm(cmu_csv: Csv, cmu_csv_cm: Csv, cmu_motion: Motion) -> None:
    check_positions(cmu_csv_cm, cmu_motion, "cm")
    np.testing.assert_array_equal(cmu_csv_cm.frames, cmu_csv.frames)
    # both CSVs are rounded to 6 decimals: 0.5e-6 each, the ASF one scaled by 2.54 / 0.45
    assert (
        np.max(np.abs(cmu_csv_cm.xyz - cmu_csv.xyz * CM_PER_ASF_UNIT))
        <= 0.5e-6 * (1 + CM_PER_ASF_UNIT) + 1e-9
    )
    assert np.max(np.abs(cmu_csv.xyz)) > 1.0  # not a degenerate comparison


def test_positions_to_stdout(cmu_csv: Csv) -> None:
    """``--csv -`` writes the same text to stdout (run through the console script)."""
    result = mocapd("positions", "--asf", CMU_ASF, "--amc", CMU_AMC, "--csv", "-", script=True)
    assert_ok(result)
    assert result.stdout == cmu_csv.text


def test_positions_stdout_closed_early() -> None:
    """``mocapd positions --csv - | head``: the reader goes away after one line. Whatever mocapd does
    then, it must not print a traceback or an error that names no file ("None: Broken pipe")."""
    command = [sys.executable, "-m", "daemon", "positions", "--asf", str(CMU_ASF), "--amc", str(CMU_AMC)]
    with subprocess.Popen(
        [*command, "--csv", "-"], cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True
    ) as proc:
        assert proc.stdout is not None and proc.stderr is not None
        assert proc.stdout.readline() == "frame,joint,x,y,z\n"
        proc.stdout.close()  # far more than a pipe buffer of CSV is still to come
        stderr = proc.stderr.read()
        proc.wait(timeout=60)
    assert "Traceback" not in stderr, stderr
    assert "None" not in stderr, stderr


# --------------------------------------------------------------------------------------------------
# bad input: exit status 2, one line on stderr naming the file (and the line)


@pytest.mark.slow
@pytest.mark.parametrize("command", ["info", "positions"])
@pytest.mark.parametrize("missing", ["asf", "amc"])
def test_missing_file(tmp_path: Path, command: str, missing: str) -> None:
    gone = tmp_path / f"nope.{missing}"
    asf, amc = (gone, CMU_AMC) if missing == "asf" else (CMU_ASF, gone)
    extra = ["--csv", str(tmp_path / "out.csv")] if command == "positions" else []
    line = assert_one_error_line(mocapd(command, "--asf", asf, "--amc", amc, *extra))
    assert line == f"mocapd: {gone}: No such file or directory"
    assert not (tmp_path / "out.csv").exists()


def malformed_amc(tmp_path: Path) -> tuple[Path, int]:
    """02_01 with a non-numeric value in frame 5's lowerback line; returns the file and that line."""
    lines = gzip.decompress(CMU_AMC.read_bytes()).decode("latin-1").split("\n")
    (at,) = [n for n, line in enumerate(lines, 1) if line.startswith("lowerback ")][4:5]
    words = lines[at - 1].split()
    lines[at - 1] = " ".join([words[0], words[1], "abc", words[3]]) + "\r"
    path = tmp_path / "bad.amc"
    path.write_bytes("\n".join(lines).encode("latin-1"))
    return path, at


@pytest.mark.slow
@pytest.mark.parametrize("command", ["info", "positions"])
def test_malformed_amc(tmp_path: Path, command: str) -> None:
    path, at = malformed_amc(tmp_path)
    with pytest.raises(
        MocapFormatError,
        match=rf"^{re.escape(str(path))}:{at}: value 'abc' for bone 'lowerback' is not a finite number$",
    ) as caught:
        read_amc(path, read_asf(CMU_ASF))
    assert caught.value.line == at
    extra = ["--csv", str(tmp_path / "out.csv")] if command == "positions" else []
    line = assert_one_error_line(mocapd(command, "--asf", CMU_ASF, "--amc", path, *extra))
    assert line == f"mocapd: {path}:{at}: {caught.value.reason}"
    assert "'abc'" in line and "lowerback" in line


def test_malformed_gzip_amc(tmp_path: Path) -> None:
    data = CMU_AMC.read_bytes()
    path = tmp_path / "cut.amc.gz"
    path.write_bytes(data[: len(data) // 2])
    line = assert_one_error_line(mocapd("info", "--asf", CMU_ASF, "--amc", path))
    assert re.fullmatch(rf"mocapd: {re.escape(str(path))}:\d+: damaged or truncated gzip data .*", line), line


def test_malformed_asf(tmp_path: Path) -> None:
    lines = CMU_ASF.read_text(encoding="latin-1").split("\n")
    (at,) = [n for n, line in enumerate(lines, 1) if line.split() == ["dof", "rx", "ry", "rz"]][:1]
    lines[at - 1] = "    dof rx ry rq"
    path = tmp_path / "bad.asf"
    path.write_text("\n".join(lines), encoding="latin-1")
    line = assert_one_error_line(mocapd("info", "--asf", path, "--amc", CMU_AMC))
    assert line == f"mocapd: {path}:{at}: unknown dof 'rq'"


@pytest.mark.slow
@pytest.mark.parametrize("fps", ["0", "-60", "nan"])
def test_info_bad_fps(fps: str) -> None:
    """A frame rate that is not a positive number is a bad option: exit 2, no traceback, no nonsense
    duration (``--fps 0`` divides by zero; ``-60`` and ``nan`` give a negative / nan duration)."""
    result = mocapd("info", "--asf", CMU_ASF, "--amc", CMU_AMC, "--native-fps", fps)
    assert "Traceback" not in result.stderr, result.stderr
    assert result.returncode == 2, (result.returncode, result.stdout, result.stderr)
    assert "fps" in result.stderr


def skeleton_without_lthumb(tmp_path: Path) -> tuple[Path, Path]:
    """02.asf without its lthumb bone, and 02_01 without the lthumb lines: a valid pair whose skeleton
    lacks a bone of the standard joint set."""
    asf = CMU_ASF.read_text(encoding="latin-1").split("\n")
    name = asf.index(next(line for line in asf if line.split() == ["name", "lthumb"]))
    begin = max(i for i in range(name) if asf[i].split() == ["begin"])
    end = min(i for i in range(name, len(asf)) if asf[i].split() == ["end"])
    del asf[begin : end + 1]
    asf = [line.replace("lwrist lhand lthumb", "lwrist lhand") for line in asf]
    asf_path = tmp_path / "nothumb.asf"
    asf_path.write_text("\n".join(asf), encoding="latin-1")
    amc = gzip.decompress(CMU_AMC.read_bytes()).decode("latin-1").split("\n")
    amc_path = tmp_path / "nothumb.amc"
    amc_path.write_text("\n".join(line for line in amc if not line.startswith("lthumb ")), encoding="latin-1")
    skeleton = read_asf(asf_path)
    assert "lthumb" not in skeleton.node_names and len(skeleton.bones) == 29
    assert len(read_amc(amc_path, skeleton)) == 343
    return asf_path, amc_path


def test_info_on_a_skeleton_without_a_joint_bone(tmp_path: Path) -> None:
    asf, amc = skeleton_without_lthumb(tmp_path)
    result = mocapd("info", "--asf", asf, "--amc", amc)
    assert_ok(result)
    assert info_fields(result.stdout)["joints"] == "none (skeleton lacks lthumb)"


def test_positions_on_a_skeleton_without_a_joint_bone(tmp_path: Path) -> None:
    """``positions`` needs the standard joint set; a skeleton that lacks one of its bones is bad input
    for it: exit 2 and one line naming the ASF and the missing bone, not a traceback."""
    asf, amc = skeleton_without_lthumb(tmp_path)
    result = mocapd("positions", "--asf", asf, "--amc", amc, "--csv", tmp_path / "out.csv")
    line = assert_one_error_line(result)
    assert str(asf) in line and "lthumb" in line


# ------------------------------------------------------------ found trying the commands as a new user would


def test_binary_amc_bytes_are_escaped(tmp_path: Path) -> None:
    """Bytes of a damaged AMC quoted in the message are escaped, not echoed to the terminal."""
    lines = gzip.decompress(HDM_AMC.read_bytes()).split(b"\n")
    at = next(i for i, line in enumerate(lines) if line.startswith(b"lowerback "))
    lines[at] = b"lowerback \x1b[2J\x00\xff\x07 1 2"
    amc = tmp_path / "binary.amc"
    amc.write_bytes(b"\n".join(lines))
    line = assert_one_error_line(mocapd("info", "--asf", HDM_ASF, "--amc", amc))
    assert line.startswith(f"mocapd: {amc}:{at + 1}: ")
    assert not CONTROL.search(line) and line.isascii()
    assert "\\x1b[2J\\x00\\xff\\x07" in line


def without_matplotlib(tmp_path: Path) -> dict[str, str]:
    """An environment in which ``import matplotlib`` fails, as on a machine without the plot extra:
    a package of that name that raises ImportError comes first on the path."""
    fake = tmp_path / "no-matplotlib" / "matplotlib"
    fake.mkdir(parents=True)
    (fake / "__init__.py").write_text("raise ImportError(\"No module named 'matplotlib'\")\n")
    return {**os.environ, "PYTHONPATH": str(fake.parent)}


@pytest.mark.slow
def test_png_extension_checked_before_the_csv_is_written(tmp_path: Path) -> None:
    csv = tmp_path / "out.csv"
    csv.write_text("previous\n")
    for png in ("out.pdf", "out", "out.png.txt"):
        line = assert_one_error_line(
            mocapd("features", "--asf", CMU_ASF, "--amc", CMU_AMC, "--csv", csv, "--png", tmp_path / png)
        )
        assert line == f"mocapd: --png: '{tmp_path / png}' does not end in .png (only PNG is written)"
    assert csv.read_text() == "previous\n"
    assert sorted(os.listdir(tmp_path)) == ["out.csv"]


def test_png_that_is_a_directory(tmp_path: Path) -> None:
    (tmp_path / "pictures").mkdir()
    csv = tmp_path / "out.csv"
    result = mocapd(
        "features", "--asf", CMU_ASF, "--amc", CMU_AMC, "--csv", csv, "--png", tmp_path / "pictures"
    )
    line = assert_one_error_line(result)
    assert line == f"mocapd: {tmp_path / 'pictures'}: is a directory; --png names the PNG file to write"
    assert sorted(os.listdir(tmp_path)) == ["pictures"]  # no pictures.png, no CSV


@pytest.mark.parametrize("command", ["features", "learn"])
def test_png_without_matplotlib_is_refused_before_the_work(tmp_path: Path, command: str) -> None:
    env = without_matplotlib(tmp_path)
    if command == "features":
        args = [
            "features",
            "--asf",
            CMU_ASF,
            "--amc",
            CMU_AMC,
            "--csv",
            tmp_path / "o.csv",
            "--png",
            tmp_path / "o.png",
        ]
    else:
        manifest = write_training(tmp_path / "clips.csv", training_rows(TRAINING[:2]))
        args = ["learn", "--manifest", manifest, "--out", tmp_path / "lib", "--png", tmp_path / "png"]
    result = subprocess.run(
        [sys.executable, "-m", "daemon", *map(str, args)],
        cwd=REPO,
        env=env,
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )
    line = assert_one_error_line(result)
    assert line == "mocapd: writing PNG needs matplotlib: pip install 'mocapd[plot]'"
    assert not (tmp_path / "o.csv").exists() and not (tmp_path / "lib").exists()


def test_device_output_errors_name_the_device() -> None:
    line = assert_one_error_line(
        mocapd("positions", "--asf", HDM_ASF, "--amc", HDM_AMC, "--csv", "/dev/full")
    )
    assert line == "mocapd: /dev/full: No space left on device"


@pytest.mark.slow
@pytest.mark.parametrize("command", ["positions", "index", "learn"])
def test_unwritable_output_found_before_the_work(tmp_path: Path, command: str) -> None:
    """/sys cannot be written even by root: the target is refused at once, named as given (no
    progress lines, no temporary name)."""
    target = Path("/sys/mocapd-output")
    if command == "positions":
        result = mocapd("positions", "--asf", HDM_ASF, "--amc", HDM_AMC, "--csv", target)
    elif command == "index":
        manifest = write_manifest(tmp_path / "m.csv", [hdm05_clip(*c) for c in DG_CLIPS], extra=False)
        result = mocapd("index", "build", "--manifest", manifest, "--out", target)
    else:
        manifest = write_training(tmp_path / "clips.csv", training_rows(TRAINING))
        result = mocapd("learn", "--manifest", manifest, "--out", target)
    line = assert_one_error_line(result)
    assert re.fullmatch(
        rf"mocapd: {target}: (Operation not permitted|Permission denied|Read-only file system)", line
    )


def test_version() -> None:
    from importlib.metadata import version

    for script in (False, True):
        result = mocapd("--version", script=script)
        assert_ok(result)
        assert result.stdout == f"mocapd {version('mocapd')}\n"


@pytest.mark.slow
@pytest.mark.parametrize(
    ("args", "message"),
    [
        ([], "the following arguments are required: COMMAND (see mocapd --help)"),
        (["index"], "the following arguments are required: {build,info} (see mocapd index --help)"),
        (
            ["info", "--asf", "a", "--amc", "b", "--fps", "3"],
            "unrecognized arguments: --fps 3 (see mocapd --help)",
        ),
        (
            ["features", "--asf", "a", "--amc", "b", "--csv", "c", "--fps", "x"],
            "argument --fps: must be a positive",
        ),
    ],
)
def test_usage_errors_are_one_line(args: list[str], message: str) -> None:
    assert message in assert_one_error_line(mocapd(*args))


def test_info_rate_option_says_what_it_is() -> None:
    info = " ".join(mocapd("info", "--help").stdout.split())
    features = " ".join(mocapd("features", "--help").stdout.split())
    assert "--native-fps HZ the rate recordings were captured at when their AMC file states none" in info
    assert "--fps" not in info.split("--native-fps")[0].split("options:")[-1]
    assert "--fps HZ output rate" in features


@pytest.fixture
def broken_info(monkeypatch: pytest.MonkeyPatch) -> Iterator[None]:
    """``mocapd info`` with a bug planted in its handler (the handler is looked up when the command
    line is built, so the planted one runs)."""
    import daemon.cli.recordings

    def crash(*_: object) -> int:
        return 1 // 0

    monkeypatch.setattr(daemon.cli.recordings, "_info", crash)
    yield


def test_internal_error_is_one_line_saying_it_is_a_bug(
    broken_info: None, capsys: pytest.CaptureFixture[str]
) -> None:
    status = cli.main(["info", "--asf", str(CMU_ASF), "--amc", str(CMU_AMC)])
    out, err = capsys.readouterr()
    assert status == cli.EXIT_BUG and out == ""
    assert err.count("\n") == 1 and "Traceback" not in err
    assert err.startswith(
        "mocapd: internal error: ZeroDivisionError: integer division or modulo by zero (this is a bug"
    )
    assert "--debug" in err
    status = cli.main(["--debug", "info", "--asf", str(CMU_ASF), "--amc", str(CMU_AMC)])
    _, err = capsys.readouterr()
    assert status == cli.EXIT_BUG
    assert err.startswith("Traceback (most recent call last):") and "1 // 0" in err
    assert err.splitlines()[-1].startswith("mocapd: internal error: ZeroDivisionError")
