"""``mocapd index build --manifest M --out IDX [--fps F]`` and ``mocapd index info IDX [--json]``, run
for real in a subprocess on a handful of real HDM05 clips."""

from __future__ import annotations

import json
import os
import re
from pathlib import Path

import numpy as np
import pytest

from daemon.search.store import ARRAYS, index_files, load_index
from daemon.types import FEATURE_SETS
from tests.helpers import (
    DG_CLIPS,
    REPO,
    assert_ok,
    assert_one_error_line,
    hdm05_clip,
    mocapd,
    write_manifest,
)
from tests.helpers import INDEX_PATHS as PATHS

PROGRESS = re.compile(r"\[(\d+)/(\d+)\] (.+) \((\d+) frames at 30 Hz\)")


@pytest.fixture(scope="module")
def manifest(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Relative paths (resolved against the manifest's directory), columns among others."""
    where = tmp_path_factory.mktemp("lists")
    rows = [(Path(os.path.relpath(a, where)), Path(os.path.relpath(m, where))) for a, m in PATHS]
    return write_manifest(where / "clips.csv", rows)


@pytest.fixture(scope="module")
def built(manifest: Path, tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, str, str]:
    """(index directory, stdout, stderr) of a successful build."""
    out = tmp_path_factory.mktemp("index") / "idx"
    result = mocapd("index", "build", "--manifest", manifest, "--out", out)
    assert result.returncode == 0, result.stderr
    return out, result.stdout, result.stderr


def test_build(built: tuple[Path, str, str], manifest: Path) -> None:
    out, stdout, stderr = built
    index = load_index(out)
    texts = [line.split(",")[1] for line in manifest.read_text(encoding="utf-8").splitlines()[1:]]
    assert [d.amc for d in index.documents] == texts  # as the manifest writes them
    lines = stderr.splitlines()
    assert len(lines) == len(PATHS)
    for i, (line, doc) in enumerate(zip(lines, index.documents, strict=True), start=1):
        match = PROGRESS.fullmatch(line)
        assert match, line
        # the recording as the reader in the working directory (the repository) finds it: outside it,
        # so an absolute path, not the manifest's relative one
        shown = os.path.normpath(manifest.parent / doc.amc)
        assert not shown.startswith(str(REPO)) and not doc.amc.startswith("/")
        assert match.groups() == (str(i), str(len(PATHS)), shown, str(doc.frames))
    assert index.rate == 30.0 and all(d.step == 4 for d in index.documents)
    assert f"documents:  {len(PATHS)}\n" in stdout
    assert f"frames:     {index.n_frames} at 30 Hz\n" in stdout
    for s in FEATURE_SETS:
        assert f"{s + ':':<11} {index.sets[s].n_segments} segments\n" in stdout
    size = sum((out / name).stat().st_size for name in index_files())
    assert f"size:       {size} bytes\n" in stdout
    assert re.search(r"^build time: \d+\.\d\d s$", stdout, re.MULTILINE)
    assert sorted(os.listdir(out.parent)) == ["idx"]


@pytest.mark.slow
def test_build_at_60_hz_replaces_the_index(manifest: Path, tmp_path: Path) -> None:
    out = tmp_path / "idx"
    assert mocapd("index", "build", "--manifest", manifest, "--out", out).returncode == 0
    result = mocapd("index", "build", "--manifest", manifest, "--out", out, "--fps", "60")
    assert result.returncode == 0, result.stderr
    index = load_index(out)
    assert index.rate == 60.0 and all(d.step == 2 for d in index.documents)


def test_info_json(built: tuple[Path, str, str]) -> None:
    out, _, _ = built
    result = mocapd("index", "info", out, "--json")
    assert_ok(result)
    info = json.loads(result.stdout)
    index = load_index(out)
    assert info["index"] == str(out)
    assert info["rate_hz"] == index.rate == 30.0
    assert info["documents"] == len(index.documents) == len(PATHS)
    assert info["frames"] == index.n_frames
    assert info["duration_s"] == pytest.approx(
        sum((d.last_amc_frame - d.first_amc_frame + 1) / 120.0 for d in index.documents)
    )
    assert info["bytes"] == sum((out / name).stat().st_size for name in index_files())
    for s in FEATURE_SETS:
        entry, expected = info["sets"][s], index.sets[s]
        size = sum((out / f"{s}.{a}.npy").stat().st_size for a in ARRAYS)
        assert entry == {
            "bits": expected.bits,
            "segments": expected.n_segments,
            "nonempty_lists": len(np.unique(np.asarray(expected.code))),
            "bytes": size,
            "bytes_per_segment": pytest.approx(size / expected.n_segments),
        }


def test_info_text(built: tuple[Path, str, str]) -> None:
    out, _, _ = built
    result = mocapd("index", "info", out)
    assert_ok(result)
    info = json.loads(mocapd("index", "info", out, "--json").stdout)
    fields = dict(line.split(":", 1) for line in result.stdout.splitlines())
    assert fields["rate"].strip() == "30 Hz"
    assert fields["documents"].strip() == str(len(PATHS))
    assert fields["frames"].strip() == str(info["frames"])
    assert fields["duration"].strip() == f"{info['duration_s']:.3f} s"
    for s in FEATURE_SETS:
        e = info["sets"][s]
        counts = f"{e['bits']} bits, {e['segments']} segments, {e['nonempty_lists']} non-empty lists"
        assert fields[s].strip().startswith(f"{counts}, {e['bytes']} bytes ("), fields[s]


# -------------------------------------------------------------------------------------- bad input


def test_bad_manifest(tmp_path: Path) -> None:
    asf, amc = PATHS[0]
    manifest = tmp_path / "m.csv"
    manifest.write_text(f"asf,amc\n{asf},{amc}\n{asf},{tmp_path / 'gone.amc.gz'}\n", encoding="utf-8")
    out = tmp_path / "idx"
    line = assert_one_error_line(mocapd("index", "build", "--manifest", manifest, "--out", out))
    assert line == f"mocapd: {manifest}:3: amc file not found: {tmp_path / 'gone.amc.gz'}"
    assert not out.exists()


def test_manifest_without_amc_column(tmp_path: Path) -> None:
    manifest = tmp_path / "m.csv"
    manifest.write_text("asf,motion\na,b\n", encoding="utf-8")
    line = assert_one_error_line(mocapd("index", "build", "--manifest", manifest, "--out", tmp_path / "i"))
    assert line.startswith(f"mocapd: {manifest}:1: header lacks the column 'amc'"), line


def test_missing_manifest(tmp_path: Path) -> None:
    gone = tmp_path / "gone.csv"
    line = assert_one_error_line(mocapd("index", "build", "--manifest", gone, "--out", tmp_path / "i"))
    assert line == f"mocapd: {gone}: No such file or directory"


def test_fps_above_the_native_rate(manifest: Path, tmp_path: Path) -> None:
    out = tmp_path / "idx"
    result = mocapd("index", "build", "--manifest", manifest, "--out", out, "--fps", "240")
    first = manifest.parent / os.path.relpath(PATHS[0][1], manifest.parent)  # as resolved, unnormalised
    line = assert_one_error_line(result)
    assert line == f"mocapd: {first}: 240 Hz is above the native 120 Hz"
    assert not out.exists()


def test_out_is_not_an_index(manifest: Path, tmp_path: Path) -> None:
    """Refused before the recordings are read: no progress lines."""
    line = assert_one_error_line(mocapd("index", "build", "--manifest", manifest, "--out", manifest))
    assert line == f"mocapd: {manifest}: exists and is not a mocapd index, not replaced"


def test_info_on_a_directory_that_is_not_an_index(tmp_path: Path) -> None:
    line = assert_one_error_line(mocapd("index", "info", tmp_path))
    assert line == f"mocapd: {tmp_path}: not a mocapd index (no index.json)"
    line = assert_one_error_line(mocapd("index", "info", tmp_path / "nothing", "--json"))
    assert line == f"mocapd: {tmp_path / 'nothing'}: not a mocapd index (not a directory)"


def test_info_on_a_damaged_index(built: tuple[Path, str, str], tmp_path: Path) -> None:
    out, _, _ = built
    damaged = tmp_path / "idx"
    damaged.mkdir()
    for name in index_files():
        if name != "upper.offsets.npy":
            (damaged / name).write_bytes((out / name).read_bytes())
    line = assert_one_error_line(mocapd("index", "info", damaged))
    assert line == f"mocapd: {damaged / 'upper.offsets.npy'}: missing"


def test_index_needs_a_subcommand() -> None:
    result = mocapd("index")
    assert result.returncode == 2 and "build" in result.stderr and result.stdout == ""


# ------------------------------------------------------------ found trying the commands as a new user would


def test_index_progress_states_the_rate(tmp_path: Path) -> None:
    manifest = write_manifest(tmp_path / "m.csv", [hdm05_clip(*c) for c in DG_CLIPS], extra=False)
    result = mocapd("index", "build", "--manifest", manifest, "--out", tmp_path / "idx", "--fps", "60")
    assert result.returncode == 0, result.stderr
    assert all(
        re.fullmatch(r"\[\d/3\] .+ \(\d+ frames at 60 Hz\)", line) for line in result.stderr.splitlines()
    )
