"""The robustness defects found trying the commands as a new user would, each run for real: the
``mocapd`` command in a subprocess on real files (damaged copies of real indexes, libraries and
recordings), checked for one line on stderr naming the input, exit status 2, no traceback and no
output file changed or left half written."""

from __future__ import annotations

import gzip
import hashlib
import json
import os
import re
import shutil
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from daemon import cli
from daemon.learn.library import learn_class, save_library
from daemon.library import Library
from daemon.recordings import read_examples, read_manifest
from daemon.search.store import build_index, save_index
from tests.helpers import (
    CMU_AMC,
    CMU_ASF,
    DATA,
    HDM_AMC,
    HDM_ASF,
    REPO,
    SHARED,
    TRAINING,
    assert_ok,
    assert_one_error_line,
    hdm05_clip,
    hits_json,
    mocapd,
    training_rows,
    write_manifest,
    write_training,
)

DATABASE = [("dg", "squat1Reps", 25), ("dg", "squat1Reps", 26), ("dg", "hopBothLegs1hops", 22)]
CONTROL = re.compile(r"[\x00-\x1f\x7f-\x9f]")


@pytest.fixture(scope="module")
def built(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A directory holding ``idx`` (an index of three dg clips, from a manifest of relative paths)
    and ``lib`` (hopBothLegs1hops and squat1Reps learned from bd clips)."""
    where = tmp_path_factory.mktemp("built")
    rows = [
        (Path(os.path.relpath(asf, where)), Path(os.path.relpath(amc, where)))
        for asf, amc in (hdm05_clip(*c) for c in DATABASE)
    ]
    manifest = write_manifest(where / "db.csv", rows, extra=False)
    save_index(build_index(read_manifest(manifest), base=where), where / "idx")
    examples = read_examples(write_training(where / "clips.csv", training_rows(TRAINING)))
    save_library(Library(30.0, {n: learn_class(n, e) for n, e in examples.items()}), where / "lib")
    return where


@pytest.fixture
def copy(built: Path, tmp_path: Path) -> Path:
    """A fresh copy of the built index and library to damage."""
    for name in ("idx", "lib"):
        shutil.copytree(built / name, tmp_path / name)
    return tmp_path


def search_library(
    where: Path, name: str, *extra: str | Path, cwd: Path = REPO
) -> subprocess.CompletedProcess[str]:
    return mocapd(
        "search", "--index", where / "idx", "--library", where / "lib", "--class", name, *extra, cwd=cwd
    )


def reseal(index: Path, feature_set: str, array: str) -> None:
    """Write the SHA-256 of ``<set>.<array>.npy`` into index.json, as a crafted index would."""
    meta = json.loads((index / "index.json").read_text())
    data = np.load(index / f"{feature_set}.{array}.npy")
    meta["sets"][feature_set]["sha256"][array] = hashlib.sha256(data.tobytes()).hexdigest()
    (index / "index.json").write_text(json.dumps(meta))


def without_matplotlib(tmp_path: Path) -> dict[str, str]:
    """An environment in which ``import matplotlib`` fails, as on a machine without the plot extra:
    a package of that name that raises ImportError comes first on the path."""
    fake = tmp_path / "no-matplotlib" / "matplotlib"
    fake.mkdir(parents=True)
    (fake / "__init__.py").write_text("raise ImportError(\"No module named 'matplotlib'\")\n")
    return {**os.environ, "PYTHONPATH": str(fake.parent)}


# --------------------------------------------------------------------------- tracebacks -> one line


@pytest.mark.slow
@pytest.mark.parametrize("damage", ["truncated", "bit-flipped"])
def test_damaged_npz_names_it_and_spares_the_other_classes(copy: Path, damage: str) -> None:
    npz = copy / "lib" / "squat1Reps.npz"
    data = bytearray(npz.read_bytes())
    if damage == "truncated":
        data = data[: len(data) // 2]
    else:
        for at in range(len(data) // 3, len(data) // 3 + 64, 8):
            data[at] ^= 0xA5
    npz.write_bytes(bytes(data))
    line = assert_one_error_line(search_library(copy, "squat1Reps"))
    assert line.startswith(f"mocapd: {npz}: "), line
    assert not CONTROL.search(line)
    hop = search_library(copy, "hopBothLegs1hops", "--json")
    assert_ok(hop)
    assert hits_json(hop.stdout), "the undamaged class is still searched"


def test_library_arrays_swapped_for_others_of_the_same_shape(copy: Path) -> None:
    npz = copy / "lib" / "squat1Reps.npz"
    with np.load(npz) as arrays:
        swapped = {**arrays, "soft": arrays["quantised"], "quantised": arrays["soft"]}
    np.savez(npz, **swapped)
    line = assert_one_error_line(search_library(copy, "squat1Reps"))
    assert line == f"mocapd: {npz}: soft: SHA-256 differs from library.json's"


def test_index_arrays_swapped_for_others_of_the_same_shape(copy: Path) -> None:
    index = copy / "idx"
    start, length = index / "upper.start.npy", index / "upper.length.npy"
    a, b = start.read_bytes(), length.read_bytes()
    start.write_bytes(b)
    length.write_bytes(a)
    line = assert_one_error_line(mocapd("index", "info", index))
    assert line == f"mocapd: {start}: SHA-256 differs from index.json's sets.upper.sha256.start"


def test_index_naming_a_document_out_of_range(copy: Path) -> None:
    """A crafted index (checksums made to match) whose segments name a document the table lacks."""
    index = copy / "idx"
    doc = np.load(index / "mix.doc.npy")
    doc[-1] = 3  # three documents: 0..2
    np.save(index / "mix.doc.npy", doc)
    reseal(index, "mix", "doc")
    commands: list[list[str | Path]] = [
        ["index", "info", index],
        ["search", "--index", index, "--library", copy / "lib", "--class", "squat1Reps"],
    ]
    for command in commands:
        line = assert_one_error_line(mocapd(*command))
        reason = "documents must rise from 0 to 2, the documents of index.json"
        assert line == f"mocapd: {index / 'mix.doc.npy'}: {reason}"


@pytest.mark.slow
def test_wrong_dtype_and_garbage_npy_are_one_plain_line(copy: Path) -> None:
    index = copy / "idx"
    code = index / "lower.code.npy"
    values = np.load(code)
    np.save(code, values.astype(np.int32))
    line = assert_one_error_line(mocapd("index", "info", index))
    assert line == (
        f"mocapd: {code}: expected a one-dimensional int64 array, got int32 of shape ({len(values)},)"
    )
    code.write_bytes(b"\x00garbage, not an array\n" * 10)
    assert assert_one_error_line(mocapd("index", "info", index)) == f"mocapd: {code}: not a .npy array file"
    np.save(code, np.array([{"a": 1}] * len(values), dtype=object), allow_pickle=True)
    line = assert_one_error_line(mocapd("index", "info", index))
    assert (
        line
        == f"mocapd: {code}: expected a one-dimensional int64 array, got object of shape ({len(values)},)"
    )


@pytest.mark.parametrize("kind", ["keyframes", "config"])
def test_binary_keyframes_or_config_file(copy: Path, kind: str) -> None:
    binary = copy / f"binary.{'json' if kind == 'keyframes' else 'yaml'}"
    binary.write_bytes(b"{\n \x00\x01\xff\xfe\x1b[31m" + bytes(range(256)))
    if kind == "keyframes":
        result = mocapd("search", "--index", copy / "idx", "--keyframes", binary, "--class", "squat1Reps")
    else:
        result = mocapd("--config", binary, "info", "--asf", CMU_ASF, "--amc", CMU_AMC)
    line = assert_one_error_line(result)
    assert line == f"mocapd: {binary}:2: not UTF-8 text (byte 5)"


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


# --------------------------------------------------------------------------- outputs: checked first


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
        manifest = write_manifest(tmp_path / "m.csv", [hdm05_clip(*c) for c in DATABASE], extra=False)
        result = mocapd("index", "build", "--manifest", manifest, "--out", target)
    else:
        manifest = write_training(tmp_path / "clips.csv", training_rows(TRAINING))
        result = mocapd("learn", "--manifest", manifest, "--out", target)
    line = assert_one_error_line(result)
    assert re.fullmatch(
        rf"mocapd: {target}: (Operation not permitted|Permission denied|Read-only file system)", line
    )


# --------------------------------------------------------------------------- silent wrong answers


@pytest.mark.slow
def test_example_outside_the_recording_is_refused(built: Path) -> None:
    for start, end in (("-20", "40"), ("0", "40"), ("100", "141"), ("40", "20")):
        result = mocapd(
            "search",
            "--index",
            built / "idx",
            "--example",
            HDM_ASF,
            HDM_AMC,
            start,
            end,
            "--features",
            "kneeRightBent",
        )
        line = assert_one_error_line(result)
        reason = f"--example frames {start}..{end} are outside the recording's AMC frames 1..140"
        assert line == f"mocapd: {HDM_AMC}: {reason}"


# --------------------------------------------------------------------------------- confusing output


@pytest.mark.slow
def test_library_search_reports_the_total_not_the_limit(built: Path) -> None:
    every = search_library(built, "squat1Reps", "--tau", "0.3", "--json")
    assert_ok(every)
    total = len(hits_json(every.stdout))
    assert total >= 3
    shown = search_library(built, "squat1Reps", "--tau", "0.3", "--limit", "1")
    assert_ok(shown)
    first, *rows = shown.stdout.splitlines()
    assert re.search(rf": {total} hits in [\d.]+ ms$", first), first
    assert len(rows) == 1


def test_search_help_explains_adaptive_fuzzy_and_offers_plain() -> None:
    result = mocapd("search", "--help")
    assert_ok(result)
    text = " ".join(result.stdout.split())
    assert "adaptive fuzzy query" in text and "can find fewer hits" in text
    assert "--plain" in text and "a plain fuzzy query instead of an adaptive one" in text


@pytest.mark.slow
def test_document_paths_are_for_the_working_directory(built: Path) -> None:
    """The index's manifest lists relative paths: hits name each recording so that it opens from where
    the command runs (relative below the working directory, else absolute)."""
    for cwd in (REPO, SHARED, DATA / "hdm05"):
        result = search_library(built, "squat1Reps", "--json", cwd=cwd)
        assert_ok(result)
        documents = {str(row["document"]) for row in hits_json(result.stdout)}
        assert documents
        for document in documents:
            assert (cwd / document).is_file(), (cwd, document)
            if cwd == REPO:
                assert Path(document).is_absolute()
            else:
                assert document.startswith(("data/mocap/hdm05/cut/", "cut/"))


def test_index_progress_states_the_rate(tmp_path: Path) -> None:
    manifest = write_manifest(tmp_path / "m.csv", [hdm05_clip(*c) for c in DATABASE], extra=False)
    result = mocapd("index", "build", "--manifest", manifest, "--out", tmp_path / "idx", "--fps", "60")
    assert result.returncode == 0, result.stderr
    assert all(
        re.fullmatch(r"\[\d/3\] .+ \(\d+ frames at 60 Hz\)", line) for line in result.stderr.splitlines()
    )


def test_learn_on_an_empty_manifest_names_learns_columns(tmp_path: Path) -> None:
    empty = tmp_path / "clips.csv"
    empty.write_text("\n")
    line = assert_one_error_line(mocapd("learn", "--manifest", empty, "--out", tmp_path / "lib"))
    assert line == (
        f"mocapd: {empty}:1: empty manifest: no header line (it needs the columns asf, amc, class, "
        "[start_frame], [end_frame], [actor])"
    )


# ------------------------------------------------------------------------------ the command itself


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


@pytest.mark.slow
def test_learn_png_directory_is_checked_first_and_made_only_for_pictures(tmp_path: Path) -> None:
    bad = write_training(tmp_path / "clips.csv", ["squat1Reps,missing.asf,missing.amc,,"])
    line = assert_one_error_line(
        mocapd("learn", "--manifest", bad, "--out", tmp_path / "lib", "--png", tmp_path / "png" / "deep")
    )
    assert line.startswith(f"mocapd: {bad}:2: asf file not found")
    assert sorted(os.listdir(tmp_path)) == ["clips.csv"]  # no picture directory made for nothing
    (tmp_path / "file").write_text("keep")
    line = assert_one_error_line(
        mocapd("learn", "--manifest", bad, "--out", tmp_path / "lib", "--png", tmp_path / "file" / "png")
    )
    assert line == f"mocapd: {tmp_path / 'file'}: not a directory"
