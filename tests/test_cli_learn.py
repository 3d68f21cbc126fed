"""``mocapd learn`` and ``mocapd search --library`` run for real in subprocesses on real HDM05 clips: the
library they write is the library the code learns, the search prints the ranking the code computes
(also with keyframe pre-selection), progress goes to stderr, PNGs are drawn, and bad input exits 2
with one line naming the file and line or the option."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from daemon.calibration import MOST_GENERAL
from daemon.index_store import build_index, load_index, save_index
from daemon.keyframes import parse_keyframe_queries
from daemon.library import Library, learn_class, load_library, save_library
from daemon.recordings import read_examples, read_manifest
from daemon.retrieval import template_search
from tests.helpers import (
    HDM_AMC,
    HDM_ASF,
    KEYFRAMES,
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

DATABASE = [
    ("dg", "squat1Reps", 25),
    ("dg", "squat1Reps", 26),
    ("dg", "hopBothLegs1hops", 22),
    ("dg", "depositFloorR", 13),
]


SQUAT = ["--library", "{lib}", "--class", "squat1Reps"]
Learned = tuple[Path, Path, str, str]  # training manifest, directory, learn's stdout and stderr


@pytest.fixture(scope="module")
def learned(tmp_path_factory: pytest.TempPathFactory) -> Learned:
    where = tmp_path_factory.mktemp("learn")
    manifest = write_training(where / "clips.csv", training_rows(TRAINING))
    result = mocapd("learn", "--manifest", manifest, "--out", where / "lib", "--png", where / "png")
    assert result.returncode == 0, result.stderr
    index_manifest = write_manifest(where / "db.csv", [hdm05_clip(*c) for c in DATABASE], extra=False)
    save_index(build_index(read_manifest(index_manifest)), where / "idx")
    return manifest, where, result.stdout, result.stderr


def test_learn_writes_the_library_the_code_learns(learned: Learned) -> None:
    manifest, where, stdout, stderr = learned
    library = load_library(where / "lib")
    examples = read_examples(manifest)
    assert list(library.classes) == list(examples) == ["hopBothLegs1hops", "squat1Reps"]
    for name, items in examples.items():
        # one actor (bd): τ given, keyframes as general as calibration would make them
        expected = learn_class(name, items, generalisation=MOST_GENERAL)
        got = library.classes[name]
        np.testing.assert_array_equal(got.quantised.values, expected.quantised.values)
        np.testing.assert_array_equal(got.hard.values, expected.hard.values)
        assert got.keyframes == expected.keyframes and got.training == expected.training
    assert sorted(p.name for p in (where / "png").iterdir()) == ["hopBothLegs1hops.png", "squat1Reps.png"]
    assert all((where / "png" / p).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" for p in ("squat1Reps.png",))
    lines = stderr.splitlines()
    assert lines[0].startswith("[1/5] ") and lines[4].startswith("[5/5] ")
    assert lines[5].startswith("[class 1/2] hopBothLegs1hops: 3 examples, soft MT ")
    assert "classes:    2 (hopBothLegs1hops, squat1Reps)" in stdout


@pytest.mark.parametrize("keyframes", [None, KEYFRAMES])
def test_search_library_prints_the_ranking(learned: Learned, keyframes: Path | None) -> None:
    _, where, _, _ = learned
    extra: list[str | Path] = [] if keyframes is None else ["--keyframes", keyframes]
    lib: list[str | Path] = ["--library", where / "lib", "--class", "squat1Reps", "--tau", "0.2"]
    result = mocapd("search", "--index", where / "idx", *lib, "--json", *extra)
    assert_ok(result)
    index = load_index(where / "idx")
    cls = load_library(where / "lib").classes["squat1Reps"]
    query = None
    if keyframes is not None:
        query = parse_keyframe_queries(json.loads(keyframes.read_text()), "k")["squat1Reps"]
    hits = template_search(index, cls.quantised, tau=0.2, steps=cls.steps, keyframes=query)
    expected = []
    for d, s, e, c in zip(*(a.tolist() for a in (hits.doc, hits.start, hits.end, hits.cost)), strict=True):
        first, last = index.amc_frames(d, s, e)
        row = {"document": index.documents[d].amc, "start_frame": first, "end_frame": last}
        expected.append({**row, "cost": round(c, 6)})
    assert hits_json(result.stdout) == expected
    assert {h["document"] for h in expected[:2]} == {str(hdm05_clip(*c)[1]) for c in DATABASE[:2]}


def test_search_library_text_and_own_keyframes(learned: Learned) -> None:
    _, where, _, _ = learned
    lib: list[str | Path] = ["--library", where / "lib", "--class", "squat1Reps", "--keyframes"]
    result = mocapd("search", "--index", where / "idx", *lib, "--steps", "thesis", "--limit", "1")
    assert_ok(result)
    first = result.stdout.splitlines()[0]
    assert first.startswith("motion template of squat1Reps (") and "thesis steps; keyframes kept" in first
    assert len(result.stdout.splitlines()) <= 2


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--library", "{lib}"], "--library needs --class NAME"),
        (["--library", "{lib}", "--class", "walk"], "no class 'walk' in the library"),
        (
            ["--library", "{lib}", "--class", "squat1Reps", "--fuzzy", "2"],
            "--fuzzy cannot be used with --library",
        ),
        (["--library", "{lib}", "--class", "squat1Reps", "--extend", "2,2"], "--extend needs --keyframes"),
        (
            ["--keyframes", "--class", "squat1Reps"],
            "--keyframes needs a keyframe file unless --library is given",
        ),
        (
            ["--keyframes", str(KEYFRAMES), "--class", "squat1Reps", "--tau", "0.1"],
            "--tau cannot be used with",
        ),
        (["--library", "{where}", "--class", "squat1Reps"], "not a mocapd template library"),
    ],
)
def test_search_library_errors(learned: Learned, args: list[str], message: str) -> None:
    _, where, _, _ = learned
    filled = [a.format(lib=where / "lib", where=where) for a in args]
    line = assert_one_error_line(mocapd("search", "--index", where / "idx", *filled))
    assert message in line, line


def test_search_library_rate_mismatch(learned: Learned, tmp_path: Path) -> None:
    _, where, _, _ = learned
    library = load_library(where / "lib")
    save_library(Library(60.0, library.classes), tmp_path / "lib60")
    line = assert_one_error_line(
        mocapd("search", "--index", where / "idx", "--library", tmp_path / "lib60", "--class", "squat1Reps")
    )
    assert "index.json: rate: 30 Hz" in line and "was learned at 60 Hz" in line


@pytest.mark.parametrize(
    ("rows", "options", "message"),
    [
        (["squat1Reps,{asf},{amc},x,"], [], "clips.csv:2: start_frame 'x' is not an integer"),
        (["squat1Reps,{asf},missing.amc.gz,,"], [], "clips.csv:2: amc file not found"),
        (["squat1Reps,{asf},{amc},,"], ["--delta", "0.5"], "--delta must lie in [0, 0.5), got 0.5"),
        (["squat1Reps,{asf},{amc},,"], ["--keyframes", "-1"], "--keyframes must not be negative"),
    ],
)
def test_learn_errors(tmp_path: Path, rows: list[str], options: list[str], message: str) -> None:
    filled = [r.format(asf=HDM_ASF, amc=HDM_AMC) for r in rows]
    manifest = write_training(tmp_path / "clips.csv", filled)
    line = assert_one_error_line(mocapd("learn", "--manifest", manifest, "--out", tmp_path / "lib", *options))
    assert message in line, line
    assert not (tmp_path / "lib").exists()


def test_learn_refuses_to_overwrite_other_files(tmp_path: Path) -> None:
    (tmp_path / "lib").mkdir()
    (tmp_path / "lib" / "notes.txt").write_text("mine")
    manifest = write_training(tmp_path / "clips.csv", [f"squat1Reps,{HDM_ASF},{HDM_AMC},,"])
    line = assert_one_error_line(mocapd("learn", "--manifest", manifest, "--out", tmp_path / "lib"))
    assert "exists and is not a mocapd template library" in line
