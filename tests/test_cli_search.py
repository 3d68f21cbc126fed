"""``mocapd search`` run for real in a subprocess on an index of real HDM05 clips: keyframe queries
equal the library's Ω^Z components in AMC frame numbers; a query by example finds its own clip first
at cost 0; bad options exit 2 with one line."""

from __future__ import annotations

import hashlib
import json
import os
import re
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest

from daemon.keyframes import parse_keyframe_queries
from daemon.learn.library import learn_class, save_library
from daemon.library import Library
from daemon.recordings import read_examples, read_features, read_manifest
from daemon.search.index import (
    adaptive_fuzzy_query,
    example_query,
    feature_selection,
    fuzzy_query,
    mismatch_query,
    ranked,
)
from daemon.search.keyframes import keyframe_search
from daemon.search.store import MotionIndex, build_index, load_index, save_index
from tests.helpers import (
    CMU_AMC,
    CMU_ASF,
    CONTROL,
    DATA,
    DG_CLIPS,
    HDM_AMC,
    HDM_ASF,
    KEYFRAMES,
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

CLIPS = [
    ("bd", "squat1Reps", 1),
    ("bk", "squat1Reps", 24),
    ("dg", "squat1Reps", 36),
    ("bd", "kickLFront1Reps", 1),
    ("bk", "kickLFront1Reps", 7),
    ("bd", "hopBothLegs1hops", 1),
    ("dg", "depositFloorR", 13),
]


@pytest.fixture(scope="module")
def index_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    where = tmp_path_factory.mktemp("search")
    manifest = write_manifest(where / "m.csv", [hdm05_clip(*c) for c in CLIPS], extra=False)
    out = where / "idx"
    save_index(build_index(read_manifest(manifest)), out)
    return out


def expected_keyframe_rows(index: MotionIndex, name: str, extend: tuple[int, int]) -> list[dict[str, object]]:
    query = parse_keyframe_queries(json.loads(KEYFRAMES.read_text()), "k")[name]
    hits = keyframe_search(index.sets, [d.frames for d in index.documents], query, index.rate, extend)
    rows = []
    for d, s, e in zip(hits.doc.tolist(), hits.start.tolist(), hits.end.tolist(), strict=True):
        first, last = index.amc_frames(d, s, e)
        rows.append({"document": index.documents[d].amc, "start_frame": first, "end_frame": last})
    return rows


@pytest.mark.slow
@pytest.mark.parametrize("name", ["squat1Reps", "kickLFront1Reps", "hopBothLegs1hops"])
def test_keyframe_search_json(index_dir: Path, name: str) -> None:
    result = mocapd("search", "--index", index_dir, "--keyframes", KEYFRAMES, "--class", name, "--json")
    assert_ok(result)
    rows = hits_json(result.stdout)
    index = load_index(index_dir)
    assert rows == expected_keyframe_rows(index, name, (0, 0))
    relevant = {str(hdm05_clip(*c)[1]) for c in CLIPS if c[1] == name}
    assert {str(r["document"]) for r in rows} >= relevant  # every clip of the class is found
    for r in rows:
        doc = next(d for d in index.documents if d.amc == r["document"])
        assert isinstance(r["start_frame"], int) and isinstance(r["end_frame"], int)
        assert doc.first_amc_frame <= r["start_frame"] <= r["end_frame"] <= doc.last_amc_frame


@pytest.mark.slow
def test_keyframe_search_extend_and_text(index_dir: Path) -> None:
    args: list[str | Path] = [
        "search",
        "--index",
        index_dir,
        "--keyframes",
        KEYFRAMES,
        "--class",
        "squat1Reps",
    ]
    wide = mocapd(*args, "--extend", "10,5", "--json")
    assert_ok(wide)
    index = load_index(index_dir)
    assert hits_json(wide.stdout) == expected_keyframe_rows(index, "squat1Reps", (10, 5))
    text = mocapd(*args, "--limit", "2")
    assert_ok(text)
    lines = text.stdout.splitlines()
    assert lines[0].startswith("keyframes of squat1Reps (4 keyframes") and "hits in" in lines[0]
    assert len(lines) == 3 and lines[1].startswith("    1. ") and " frames " in lines[1]


def test_query_by_example_finds_itself_first(index_dir: Path) -> None:
    asf, amc = hdm05_clip("bd", "squat1Reps", 1)
    features = "kneeRightBent,kneeLeftBent,feetApartRelHips"
    result = mocapd(
        "search", "--index", index_dir, "--example", asf, amc, "1", "140", "--features", features, "--json"
    )
    assert_ok(result)
    rows = hits_json(result.stdout)
    assert rows[0] == {"document": str(amc), "start_frame": 1, "end_frame": 140, "cost": 0}
    costs = [int(str(r["cost"])) for r in rows]
    assert costs == sorted(costs)
    assert sum("squat1Reps" in str(r["document"]) for r in rows) >= 2  # another actor's squat too


SQUAT_EXAMPLE = (
    ("bd", "squat1Reps", 1),
    1,
    140,
    "footLeftRaisedRelYBodyMin,feetApartRelHips,kneeLeftBent,footRightHighVel",
)
KICK_EXAMPLE = (("bd", "kickLFront1Reps", 1), 20, 120, "footLeftRaisedRelYBodyMin,kneeLeftBent")
Example = tuple[tuple[str, str, int], int, int, str]


def library_example_rows(
    index: MotionIndex, example: Example, fuzzy: int, plain: bool, mismatch: int | None
) -> list[dict[str, object]]:
    """The rows ``search --example ... --json`` should print, computed through the library."""
    clip, first, last, names = example
    asf, amc = hdm05_clip(*clip)
    got = read_features(asf, amc, index.rate)
    inside = (got.frames >= first) & (got.frames <= last)
    feature_set, mask = feature_selection(names.split(","))
    query = example_query(got.matrix[inside], feature_set, mask)
    sets = query.fuzzy_sets(fuzzy)
    set_index = index.sets[feature_set]
    if mismatch is not None:
        hits = mismatch_query(set_index, sets, mismatch)
    elif plain:
        hits = fuzzy_query(set_index, sets)
    else:
        hits = adaptive_fuzzy_query(set_index, sets)
    order, cost = ranked(hits, query.lengths)
    rows: list[dict[str, object]] = []
    for i, c in zip(order.tolist(), cost.tolist(), strict=True):
        d = int(hits.doc[i])
        start, end = index.amc_frames(d, int(hits.start[i]), int(hits.end[i]))
        rows.append({"document": index.document_path(d), "start_frame": start, "end_frame": end, "cost": c})
    return rows


@pytest.mark.slow
@pytest.mark.parametrize(
    ("example", "fuzzy", "plain", "mismatch"),
    [
        # the squat's query has 3 segments: knee straight, bent, straight (with 3 more features)
        (SQUAT_EXAMPLE, 0, False, None),  # 4 hits: the 3 squats and the hop
        (SQUAT_EXAMPLE, 1, False, None),  # 2 hits: the hop and the deposit (larger sets merge more)
        (SQUAT_EXAMPLE, 2, False, None),  # 2 hits: the two kicks
        (SQUAT_EXAMPLE, 1, True, None),  # 25 hits in all 7 documents
        (SQUAT_EXAMPLE, 0, False, 1),  # 13 hits in all 7 documents
        (KICK_EXAMPLE, 1, True, None),  # 6 hits in both kicks
        (KICK_EXAMPLE, 1, False, 1),  # 23 hits in the kicks, the hop and the deposit
    ],
    ids=[
        "squat-fuzzy0",
        "squat-fuzzy1",
        "squat-fuzzy2",
        "squat-plain1",
        "squat-mismatch1",
        "kick-plain1",
        "kick-mismatch1",
    ],
)
def test_query_by_example_rows_equal_the_library(
    index_dir: Path, example: Example, fuzzy: int, plain: bool, mismatch: int | None
) -> None:
    clip, first, last, names = example
    asf, amc = hdm05_clip(*clip)
    args: list[str | Path] = ["search", "--index", index_dir, "--example", asf, amc, str(first), str(last)]
    args += ["--features", names, "--fuzzy", str(fuzzy), "--json"]
    if plain:
        args.append("--plain")
    if mismatch is not None:
        args += ["--mismatch", str(mismatch)]
    result = mocapd(*args)
    assert_ok(result)
    rows = hits_json(result.stdout)
    expected = library_example_rows(load_index(index_dir), example, fuzzy, plain, mismatch)
    assert rows == expected
    assert len(rows) >= 2, rows  # the example has hits, and not only in its own document
    assert any(r["document"] != str(amc) for r in rows), rows
    costs = [int(str(r["cost"])) for r in rows]
    assert costs == sorted(costs)


@pytest.mark.slow
@pytest.mark.parametrize(
    ("extra", "message"),
    [
        (["--keyframes", KEYFRAMES, "--class", "noSuchClass"], "no class 'noSuchClass'"),
        (["--keyframes", KEYFRAMES], "--keyframes needs --class"),
        (["--keyframes", KEYFRAMES, "--class", "squat1Reps", "--fuzzy", "1"], "--fuzzy cannot be used"),
        (["--keyframes", KEYFRAMES, "--class", "squat1Reps", "--extend", "3"], "--extend must be LEFT,RIGHT"),
        (
            [
                "--example",
                *map(str, hdm05_clip("bd", "squat1Reps", 1)),
                "1",
                "140",
                "--features",
                "kneeRightBent,elbowRightBent",
            ],
            "several sets",
        ),
        (
            ["--example", *map(str, hdm05_clip("bd", "squat1Reps", 1)), "1", "140"],
            "--example needs --features",
        ),
        (
            [
                "--example",
                *map(str, hdm05_clip("bd", "squat1Reps", 1)),
                "500",
                "600",
                "--features",
                "kneeRightBent",
            ],
            "--example frames 500..600 are outside the recording's AMC frames 1..140",
        ),
        (
            [
                "--example",
                *map(str, hdm05_clip("bd", "squat1Reps", 1)),
                "2",
                "4",
                "--features",
                "kneeRightBent",
            ],
            "frames 2..4 hold no frame at 30 Hz",
        ),
        (
            [
                "--example",
                *map(str, hdm05_clip("bd", "squat1Reps", 1)),
                "-5",
                "40",
                "--features",
                "kneeRightBent",
            ],
            "--example frames -5..40 are outside the recording's AMC frames 1..140",
        ),
        (
            [
                "--example",
                *map(str, hdm05_clip("bd", "squat1Reps", 1)),
                "1",
                "140",
                "--features",
                "kneeRightBent",
                "--mismatch",
                "9",
            ],
            "--mismatch",
        ),
        (
            ["--example", *map(str, hdm05_clip("bd", "squat1Reps", 1)), "1", "140", "--features", "kneeBent"],
            "unknown feature",
        ),
    ],
)
def test_bad_search_options(index_dir: Path, extra: list[str | Path], message: str) -> None:
    line = assert_one_error_line(mocapd("search", "--index", index_dir, *extra))
    assert message in line


def test_bad_keyframe_file_names_the_file(index_dir: Path, tmp_path: Path) -> None:
    bad = tmp_path / "q.json"
    bad.write_text(
        '{"classes": {"a": [\n  {"set": "lower", "values": [0, 1], "position": 0}\n]}}\n', encoding="utf-8"
    )
    line = assert_one_error_line(mocapd("search", "--index", index_dir, "--keyframes", bad, "--class", "a"))
    assert f"{bad}: classes.a[0].values" in line
    bad.write_text("{\n  oops\n}\n", encoding="utf-8")
    line = assert_one_error_line(mocapd("search", "--index", index_dir, "--keyframes", bad, "--class", "a"))
    assert f"{bad}:2: not valid JSON" in line


# ------------------------------------------------------------ found trying the commands as a new user would


@pytest.fixture(scope="module")
def built(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A directory holding ``idx`` (an index of three dg clips, from a manifest of relative paths)
    and ``lib`` (hopBothLegs1hops and squat1Reps learned from bd clips)."""
    where = tmp_path_factory.mktemp("built")
    rows = [
        (Path(os.path.relpath(asf, where)), Path(os.path.relpath(amc, where)))
        for asf, amc in (hdm05_clip(*c) for c in DG_CLIPS)
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
