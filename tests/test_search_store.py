"""The on-disk motion index (daemon/search/store.py) on a handful of real HDM05 clips: manifests, the
index against an independent segmentation of each clip, the directory format and its validation."""

from __future__ import annotations

import hashlib
import json
import os
import re
import shutil
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import numpy.typing as npt
import pytest

from daemon.errors import FileAccessError
from daemon.recordings import ManifestError, ManifestRow, RateError, read_manifest
from daemon.search.segments import segment
from daemon.search.store import (
    ARRAYS,
    Document,
    IndexFormatError,
    MotionIndex,
    build_index,
    index_files,
    index_from_matrices,
    load_index,
    save_index,
)
from daemon.types import FEATURE_SETS, FeatureSet
from replay import MocapFormatError, read_amc, read_asf
from tests.helpers import INDEX_CLIPS, INDEX_PATHS, write_manifest
from tests.naive import naive_features

CLIPS, PATHS = INDEX_CLIPS, INDEX_PATHS


@dataclass(frozen=True)
class Built:
    manifest: Path
    rows: list[ManifestRow]
    index: MotionIndex
    progress: list[tuple[int, int, str]]
    matrices: list[npt.NDArray[np.bool_]]  # independently computed, 30 Hz, (N_d, 39)


@pytest.fixture(scope="module")
def built(tmp_path_factory: pytest.TempPathFactory) -> Built:
    manifest = write_manifest(tmp_path_factory.mktemp("manifest") / "m.csv", PATHS)
    rows = read_manifest(manifest)
    calls: list[tuple[int, int, str]] = []
    index = build_index(rows, progress=lambda i, n, doc: calls.append((i, n, doc.amc)), base=manifest.parent)
    matrices = [naive_features(asf, amc, 4) for asf, amc in PATHS]
    return Built(manifest, rows, index, calls, matrices)


@pytest.fixture(scope="module")
def saved(built: Built, tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("saved") / "idx"
    save_index(built.index, path)
    return path


def copy_index(saved: Path, tmp_path: Path) -> Path:
    out = tmp_path / "idx"
    shutil.copytree(saved, out)
    return out


# ------------------------------------------------------------------------------------- building


def test_documents(built: Built) -> None:
    index = built.index
    assert index.rate == 30.0
    assert len(index.documents) == len(CLIPS)
    for doc, (asf, amc), (_, _, _, n) in zip(index.documents, PATHS, CLIPS, strict=True):
        assert doc == Document(str(amc), str(asf), 1, n, 4, -(-n // 4), 120.0)
    assert index.n_frames == sum(-(-n // 4) for *_, n in CLIPS) == 35 + 14 + 22 + 41
    assert built.progress == [(i + 1, 4, str(amc)) for i, (_, amc) in enumerate(PATHS)]
    assert set(index.sets) == {"lower", "upper", "mix"}
    assert {s: index.sets[s].bits for s in FEATURE_SETS} == {"lower": 12, "upper": 14, "mix": 13}


@pytest.mark.parametrize("feature_set", FEATURE_SETS)
def test_segments_are_each_clips_own_segmentation(built: Built, feature_set: FeatureSet) -> None:
    """Per document, the index's segments equal ``segment(features(joints[::4], 30 Hz), set)`` of the
    clip computed here, and their AMC frames are the clip's 30 Hz samples."""
    index = built.index
    s = index.sets[feature_set]
    assert np.all(np.diff(s.doc) >= 0)  # documents in manifest order, numbered globally
    assert s.n_segments > 2 * len(CLIPS)  # not a degenerate comparison: features change in these clips
    for d, (matrix, (asf, amc)) in enumerate(zip(built.matrices, PATHS, strict=True)):
        mine = s.doc == d
        own = segment(matrix, feature_set)
        np.testing.assert_array_equal(s.start[mine], own.start)
        np.testing.assert_array_equal(s.length[mine], own.end - own.start + 1)
        np.testing.assert_array_equal(s.code[mine], own.code)
        samples = read_amc(amc, read_asf(asf)).frames[::4]
        for start, end in zip(own.start.tolist(), own.end.tolist(), strict=True):
            first, last = index.amc_frames(d, start, end)
            assert first == samples[start]
            assert last == min(int(samples[end]) + 3, index.documents[d].last_amc_frame)
    # the inverted lists: list v holds exactly the segments with code v, ascending
    for v in np.unique(s.code).tolist():
        np.testing.assert_array_equal(s.inverted_list(v), np.flatnonzero(s.code == v))
    assert int(s.offsets[-1]) == s.n_segments == len(s.postings)


def test_index_from_matrices_equals_build_index(built: Built) -> None:
    again = index_from_matrices(built.matrices, built.index.documents, 30.0)
    assert again.documents == built.index.documents and again.rate == built.index.rate
    for s in FEATURE_SETS:
        for a in ARRAYS:
            np.testing.assert_array_equal(getattr(again.sets[s], a), getattr(built.index.sets[s], a))


def test_index_from_matrices_checks_its_input(built: Built) -> None:
    docs, mats = built.index.documents, built.matrices
    with pytest.raises(ValueError, match="4 feature matrices for 3 documents"):
        index_from_matrices(mats, docs[:3], 30.0)
    with pytest.raises(ValueError, match=r"document 1 .*expected \(14, 39\)"):
        index_from_matrices([mats[0], mats[1][:-1], *mats[2:]], docs, 30.0)
    with pytest.raises(ValueError, match="120 Hz every 4 frames is not 60 Hz"):
        index_from_matrices(mats, docs, 60.0)


def test_other_rate() -> None:
    """``rate`` 60: every other frame."""
    asf, amc = PATHS[1]
    index = build_index([ManifestRow(2, "a", "m", asf, amc)], rate=60.0)
    (doc,) = index.documents
    assert (doc.step, doc.frames, doc.amc, doc.asf) == (2, 28, "m", "a")
    assert index.amc_frames(0, 27, 27) == (55, 56)


def test_rate_that_does_not_divide_the_native_rate(tmp_path: Path) -> None:
    """25 Hz of 120 Hz: 5 index frames in 24 AMC frames, each the first frame at or after its
    instant, the features of the poses blended at the instants (the recogniser's); saved with its
    ``per`` and read back. A rate above the native one is refused naming the file."""
    asf, amc = PATHS[0]
    index = build_index([ManifestRow(2, str(asf), str(amc), asf, amc)], rate=25.0)
    (doc,) = index.documents
    n = doc.last_amc_frame - doc.first_amc_frame + 1
    assert (doc.step, doc.per, doc.frames) == (24, 5, (n - 1) * 5 // 24 + 1)
    starts = [index.amc_frames(0, j, j)[0] - doc.first_amc_frame for j in range(doc.frames)]
    assert starts == [-(-j * 24 // 5) for j in range(doc.frames)]
    assert index.amc_frames(0, 0, doc.frames - 1) == (doc.first_amc_frame, doc.last_amc_frame)
    again = index_from_matrices([naive_features(asf, amc, 24, per=5)], index.documents, 25.0)
    for feature_set in FEATURE_SETS:
        for a in ARRAYS:
            np.testing.assert_array_equal(
                getattr(again.sets[feature_set], a), getattr(index.sets[feature_set], a)
            )
    save_index(index, tmp_path / "idx")
    assert load_index(tmp_path / "idx").documents == index.documents
    assert '"per": 5' in (tmp_path / "idx" / "index.json").read_text(encoding="utf-8")
    with pytest.raises(RateError, match="240 Hz is above the native 120 Hz") as caught:
        build_index([ManifestRow(2, str(asf), str(amc), asf, amc)], rate=240.0)
    assert str(caught.value).startswith(f"{amc}: ")


def test_unreadable_recording_raises_the_readers_error(tmp_path: Path) -> None:
    asf = PATHS[0][0]
    amc = tmp_path / "bad.amc"
    amc.write_text(":FULLY-SPECIFIED\n:DEGREES\n1\nroot 1 2\n", encoding="utf-8")
    with pytest.raises(MocapFormatError, match=f"^{re.escape(str(amc))}:4: ") as caught:
        build_index([ManifestRow(2, str(asf), str(amc), asf, amc)])
    assert caught.value.path == str(amc)


# ------------------------------------------------------------------------------------ amc_frames


def test_amc_frames_mapping() -> None:
    """Index frame j is AMC frame first + 4j; a range ends where the next sample begins, clipped at the
    last AMC frame: AMC frames 11..20 give samples 11, 15, 19."""
    doc = Document("m.amc", "a.asf", 11, 20, 4, 3, 120.0)
    index = index_from_matrices([np.zeros((3, 39), dtype=bool)], [doc], 30.0)
    assert index.amc_frames(0, 0, 0) == (11, 14)  # the first sample
    assert index.amc_frames(0, 1, 1) == (15, 18)
    assert index.amc_frames(0, 2, 2) == (19, 20)  # the last sample, clipped
    assert index.amc_frames(0, 0, 2) == (11, 20)
    for start, end in [(-1, 0), (1, 0), (0, 3)]:
        with pytest.raises(ValueError, match=r"outside 0\.\.2"):
            index.amc_frames(0, start, end)


def test_amc_frames_of_real_clips(built: Built) -> None:
    index = built.index
    assert index.amc_frames(0, 0, 0) == (1, 4)
    assert index.amc_frames(0, 34, 34) == (137, 140)  # 140 frames: the last sample is whole
    assert index.amc_frames(2, 21, 21) == (85, 86)  # 86 frames: samples 1, 5, ..., 85
    assert index.amc_frames(3, 40, 40) == (161, 161)  # 161 frames: the last sample is the last frame
    assert index.amc_frames(3, 0, 40) == (1, 161)


# ------------------------------------------------------------------------------------- save / load


def test_save_and_load_round_trip(built: Built, saved: Path) -> None:
    assert sorted(os.listdir(saved)) == sorted(index_files())
    meta = json.loads((saved / "index.json").read_text(encoding="utf-8"))
    assert (meta["format"], meta["version"], meta["rate"]) == ("mocapd-index", 2, 30.0)
    assert meta["base"] == str(built.manifest.parent.resolve())
    assert meta["documents"][0] == {
        "amc": str(PATHS[0][1]),
        "asf": str(PATHS[0][0]),
        "first_amc_frame": 1,
        "last_amc_frame": 140,
        "step": 4,
        "frames": 35,
        "native_rate": 120.0,
    }
    loaded = load_index(saved)
    assert loaded.rate == built.index.rate
    assert loaded.documents == built.index.documents
    assert loaded.n_frames == built.index.n_frames
    for s in FEATURE_SETS:
        mine, theirs = loaded.sets[s], built.index.sets[s]
        assert (mine.feature_set, mine.bits) == (theirs.feature_set, theirs.bits)
        sums = {
            a: hashlib.sha256(np.ascontiguousarray(getattr(theirs, a)).tobytes()).hexdigest() for a in ARRAYS
        }
        assert meta["sets"][s] == {"bits": theirs.bits, "segments": theirs.n_segments, "sha256": sums}
        for a in ARRAYS:
            array = getattr(mine, a)
            assert isinstance(array, np.memmap), a
            assert array.dtype == np.int64 and not array.flags.writeable
            np.testing.assert_array_equal(array, getattr(theirs, a))
        np.testing.assert_array_equal(mine.union([1, 2, 3]), theirs.union([1, 2, 3]))


def test_save_replaces_an_index_and_leaves_nothing_else(built: Built, tmp_path: Path) -> None:
    path = tmp_path / "idx"
    save_index(built.index, path)
    smaller = index_from_matrices(built.matrices[:1], built.index.documents[:1], 30.0)
    save_index(smaller, path)
    assert load_index(path).documents == built.index.documents[:1]
    assert os.listdir(tmp_path) == ["idx"]  # no temporary sibling left
    (tmp_path / "empty").mkdir()
    save_index(smaller, tmp_path / "empty")  # an empty directory may be written over
    assert load_index(tmp_path / "empty").documents == smaller.documents


def test_save_refuses_to_replace_something_else(built: Built, tmp_path: Path) -> None:
    (tmp_path / "file").write_text("keep me", encoding="utf-8")
    (tmp_path / "dir").mkdir()
    (tmp_path / "dir" / "notes.txt").write_text("keep me", encoding="utf-8")
    for target in ("file", "dir"):
        with pytest.raises(FileAccessError, match=r"is not a mocapd index, not replaced$") as caught:
            save_index(built.index, tmp_path / target)
        assert caught.value.path == str(tmp_path / target)
    assert (tmp_path / "file").read_text(encoding="utf-8") == "keep me"
    assert os.listdir(tmp_path / "dir") == ["notes.txt"]
    with pytest.raises(FileAccessError, match=r"/no/idx: No such file or directory$"):
        save_index(built.index, tmp_path / "no" / "idx")
    assert sorted(os.listdir(tmp_path)) == ["dir", "file"]


def edit_json(path: Path, change: dict[str, object]) -> None:
    meta = json.loads((path / "index.json").read_text(encoding="utf-8"))
    for dotted, value in change.items():
        *parents, key = dotted.split(".")
        node = meta
        for p in parents:
            node = node[int(p)] if p.isdigit() else node[p]
        node[key] = value
    (path / "index.json").write_text(json.dumps(meta), encoding="utf-8")


def test_load_missing_npy(saved: Path, tmp_path: Path) -> None:
    path = copy_index(saved, tmp_path)
    (path / "upper.postings.npy").unlink()
    with pytest.raises(IndexFormatError, match="missing") as caught:
        load_index(path)
    assert str(caught.value).startswith(f"{path / 'upper.postings.npy'}: ")


def _truncate(file: Path) -> None:
    file.write_bytes(file.read_bytes()[:-8])


def _shorten(file: Path) -> None:
    np.save(file, np.load(file)[:-1])


def _narrow(file: Path) -> None:
    np.save(file, np.load(file).astype(np.int32))


@pytest.mark.parametrize(
    ("name", "damage", "message"),
    [
        ("mix.postings.npy", _truncate, r"not a readable \.npy array: "),
        ("lower.postings.npy", _shorten, r"\d+ entries, index\.json implies \d+"),
        ("lower.code.npy", _narrow, r".*int64"),
    ],
)
def test_load_damaged_array(
    saved: Path, tmp_path: Path, name: str, damage: Callable[[Path], None], message: str
) -> None:
    path = copy_index(saved, tmp_path)
    file = path / name
    damage(file)
    with pytest.raises(IndexFormatError, match=f"^{re.escape(str(file))}: {message}"):
        load_index(path)


def test_load_offsets_that_do_not_end_at_the_segment_count(saved: Path, tmp_path: Path) -> None:
    path = copy_index(saved, tmp_path)
    file = path / "upper.offsets.npy"
    offsets = np.load(file)
    offsets[-1] += 1
    np.save(file, offsets)
    sha = re.escape("SHA-256 differs from index.json's sets.upper.sha256.offsets")
    with pytest.raises(IndexFormatError, match=f"^{re.escape(str(file))}: {sha}$"):
        load_index(path)
    # with a matching checksum the structure check itself finds it
    edit_json(path, {"sets.upper.sha256.offsets": hashlib.sha256(offsets.tobytes()).hexdigest()})
    segments = len(np.load(path / "upper.code.npy"))
    with pytest.raises(
        IndexFormatError, match=f"^{re.escape(str(file))}: must rise from 0 to the {segments} segments$"
    ) as caught:
        load_index(path)
    assert str(caught.value).startswith(f"{file}: ")


def test_load_bad_json(saved: Path, tmp_path: Path) -> None:
    path = copy_index(saved, tmp_path)
    (path / "index.json").write_text('{"format": "mocapd-index",', encoding="utf-8")
    with pytest.raises(IndexFormatError, match="not valid JSON") as caught:
        load_index(path)
    assert str(caught.value).startswith(f"{path / 'index.json'}:1: ")


@pytest.mark.parametrize(
    ("change", "field"),
    [
        ({"version": 1}, "version"),
        ({"version": 3}, "version"),
        ({"version": True}, "version"),
        ({"format": "something"}, "format"),
        ({"rate": 0}, "rate"),
        ({"documents": []}, "documents"),
        ({"documents.0.frames": "35"}, "documents[0].frames"),
        ({"documents.1.frames": 15}, "documents[1].frames"),
        ({"documents.0.step": 0}, "documents[0].step"),
        ({"documents.0.per": 5}, "documents[0].per"),  # more index frames than frames
        ({"documents.0.per": 2}, "documents[0].per"),  # 2 in 4: not in lowest terms
        ({"documents.0.per": 0}, "documents[0].per"),
        ({"documents.0.native_rate": "120"}, "documents[0].native_rate"),
        ({"rate": 1}, "documents[0].step"),  # the documents' steps no longer give the rate
        ({"documents.1.native_rate": 60.0}, "documents[1].step"),
        ({"documents.2.amc": 7}, "documents[2].amc"),
        ({"documents.0.last_amc_frame": 0}, "documents[0].last_amc_frame"),
        ({"sets.mix.bits": 12}, "sets.mix.bits"),
        ({"sets.lower.segments": 3}, None),  # found at the first array of that length
        ({"sets.upper": None}, "sets.upper"),
    ],
)
def test_load_bad_fields(saved: Path, tmp_path: Path, change: dict[str, object], field: str | None) -> None:
    path = copy_index(saved, tmp_path)
    edit_json(path, change)
    where = f"{path / 'lower.doc.npy'}: " if field is None else f"{path / 'index.json'}: {field}: "
    with pytest.raises(IndexFormatError, match=f"^{re.escape(where)}") as caught:
        load_index(path)
    message = str(caught.value)
    if field is None:
        assert message.startswith(f"{path / 'lower.doc.npy'}: "), message
    else:
        assert message.startswith(f"{path / 'index.json'}: {field}: "), message


def test_load_missing_and_unknown_keys(saved: Path, tmp_path: Path) -> None:
    path = copy_index(saved, tmp_path)
    meta = json.loads((path / "index.json").read_text(encoding="utf-8"))
    del meta["documents"][0]["step"]
    meta["documents"][0]["colour"] = "red"
    (path / "index.json").write_text(json.dumps(meta), encoding="utf-8")
    with pytest.raises(IndexFormatError, match=r"index.json: documents\[0\]: missing step"):
        load_index(path)


def test_load_something_that_is_not_an_index(tmp_path: Path) -> None:
    with pytest.raises(IndexFormatError, match=r"no index\.json") as caught:
        load_index(tmp_path)
    assert str(caught.value).startswith(f"{tmp_path}: ")
    with pytest.raises(IndexFormatError, match="not a directory"):
        load_index(tmp_path / "nothing")


# ----------------------------------------------------------------------------------------- manifest


def test_manifest_columns_in_any_order_among_others(built: Built) -> None:
    rows = built.rows
    assert [(r.asf, r.amc) for r in rows] == PATHS
    assert [(r.asf_text, r.amc_text) for r in rows] == [(str(a), str(m)) for a, m in PATHS]
    assert [r.line for r in rows] == [2, 3, 4, 5]


def test_manifest_relative_paths_resolve_against_its_directory(tmp_path: Path) -> None:
    where = tmp_path / "lists" / "deep"
    where.mkdir(parents=True)
    relative = [(os.path.relpath(asf, where), os.path.relpath(amc, where)) for asf, amc in PATHS[:2]]
    manifest = write_manifest(where / "m.csv", [(Path(a), Path(m)) for a, m in relative], extra=False)
    rows = read_manifest(manifest)
    assert [(r.asf_text, r.amc_text) for r in rows] == relative
    assert all(r.asf.samefile(a) and r.amc.samefile(m) for r, (a, m) in zip(rows, PATHS[:2], strict=True))
    index = build_index(rows)
    assert [d.amc for d in index.documents] == [m for _, m in relative]  # as written


def test_manifest_skips_blank_lines_and_spaces(tmp_path: Path) -> None:
    (asf, amc), (asf2, amc2) = PATHS[:2]
    manifest = tmp_path / "m.csv"
    manifest.write_text(f"\ufeff AMC , asf\n\n{amc} , {asf}\r\n\n{amc2},{asf2}\n\n", encoding="utf-8")
    rows = read_manifest(manifest)
    assert [(r.line, r.amc, r.asf) for r in rows] == [(3, amc, asf), (5, amc2, asf2)]


def bad_manifests(tmp_path: Path) -> dict[str, tuple[str, int, str]]:
    """name -> (manifest text, line of the error, words of the reason)."""
    asf, amc = PATHS[0]
    ok = f"{asf},{amc}"
    return {
        "no amc column": (f"asf,class\n{asf},x\n", 1, "lacks the column 'amc'"),
        "no asf column": (f"file,amc\n{asf},{amc}\n", 1, "lacks the column 'asf'"),
        "repeated column": (f"asf,amc,amc\n{ok},{amc}\n", 1, "repeats the column 'amc'"),
        "blank field": (f"asf,amc\n{ok}\n{asf},\n", 3, "'amc' field is blank"),
        "blank asf": (f"asf,amc\n{ok}\n  ,{amc}\n", 3, "'asf' field is blank"),
        "too few fields": (f"asf,amc,class\n{ok},x\n\n{ok}\n", 4, "2 fields, the header has 3"),
        "missing amc": (f"asf,amc\n{ok}\n{asf},{tmp_path / 'gone.amc'}\n", 3, "amc file not found"),
        "missing asf": (f"asf,amc\n{tmp_path / 'gone.asf'},{amc}\n", 2, "asf file not found"),
        "listed file is a directory": (f"asf,amc\n{asf},{tmp_path}\n", 2, "amc file not found"),
        "empty": ("", 1, "empty manifest: no header"),
        "blank lines only": ("\n\n", 1, "empty manifest: no header"),
        "header only": ("asf,amc\n", 1, "no recordings"),
        "not utf-8": (f"asf,amc\n{ok}\n\xfc,{amc}\n", 3, "not UTF-8"),
    }


@pytest.mark.parametrize("case", sorted(bad_manifests(Path("/x"))))
def test_manifest_errors_name_file_and_line(tmp_path: Path, case: str) -> None:
    text, line, reason = bad_manifests(tmp_path)[case]
    manifest = tmp_path / "m.csv"
    manifest.write_bytes(text.encode("latin-1" if case == "not utf-8" else "utf-8"))
    with pytest.raises(
        ManifestError, match=f"^{re.escape(str(manifest))}:{line}: .*{re.escape(reason)}"
    ) as caught:
        read_manifest(manifest)
    error = caught.value
    assert (error.path, error.line) == (str(manifest), line), str(error)
    assert str(error).startswith(f"{manifest}:{line}: "), str(error)
    assert reason in error.reason, str(error)
