"""``mocapd learn`` and ``mocapd search --library`` run for real in subprocesses on real HDM05 clips: the
library they write is the library the code learns (also with keyframes given in a file, or none),
the search prints the ranking the code computes (also with keyframe pre-selection), progress goes to
stderr, PNGs are drawn, and bad input exits 2 with one line naming the file and line or the option."""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import pytest

from daemon.keyframes import parse_keyframe_queries
from daemon.learn.library import learn_library, save_library
from daemon.library import DTW, GATED, LEARNED, PUBLISHED, Library, load_library
from daemon.recordings import read_examples, read_manifest
from daemon.search.retrieval import template_search
from daemon.search.store import build_index, load_index, save_index
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


def assert_same_library(got: Library, expected: Library) -> None:
    """Every class's templates, keyframes, τ and its provenance, mode and training clips equal."""
    assert list(got.classes) == list(expected.classes) and got.rate == expected.rate
    for name, cls in expected.classes.items():
        mine = got.classes[name]
        for field in ("soft", "quantised", "hard"):
            np.testing.assert_array_equal(getattr(mine, field).values, getattr(cls, field).values)
            np.testing.assert_array_equal(getattr(mine, field).weights, getattr(cls, field).weights)
        if cls.keyframes is None:
            assert mine.keyframes is None
        else:
            assert mine.keyframes is not None and mine.keyframes.keyframes == cls.keyframes.keyframes
        assert (mine.tau, mine.provenance, mine.training) == (cls.tau, cls.provenance, cls.training)
        assert (mine.mode, mine.mode_reason, mine.keyframe_source) == (
            cls.mode,
            cls.mode_reason,
            cls.keyframe_source,
        )
        assert len(mine.variants) == len(cls.variants)


@pytest.mark.slow
def test_learn_writes_the_library_the_code_learns(learned: Learned) -> None:
    manifest, where, stdout, stderr = learned
    library = load_library(where / "lib")
    examples = read_examples(manifest)
    assert list(library.classes) == list(examples) == ["hopBothLegs1hops", "squat1Reps"]
    # one actor (bd): calibrated on groups of its takes, as the code does it
    code = learn_library(examples)
    assert code.calibrated is not None and [f.group for f in code.calibrated.folds] == [
        "take 1",
        "take 2",
        "take 3",
    ]
    assert_same_library(library, code.library)
    for cls in library.classes.values():
        c = cls.provenance
        assert c.calibrated and c.method.startswith(
            f"left-out streams of {c.folds} folds (groups of one person"
        )
        assert cls.mode in (DTW, GATED) and cls.mode_reason
    assert library.classes["hopBothLegs1hops"].provenance.folds == 3  # 3 takes, one per group
    assert library.classes["squat1Reps"].provenance.folds == 2  # 2 takes: the third group has none
    assert sorted(p.name for p in (where / "png").iterdir()) == ["hopBothLegs1hops.png", "squat1Reps.png"]
    assert all((where / "png" / p).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" for p in ("squat1Reps.png",))
    lines = stderr.splitlines()
    assert lines[0].startswith("[1/5] ") and lines[4].startswith("[5/5] ")
    assert [line.split(" left out")[0] for line in lines[5:8]] == [
        "[fold 1/3] take 1",
        "[fold 2/3] take 2",
        "[fold 3/3] take 3",
    ]
    hop = library.classes["hopBothLegs1hops"]
    columns = hop.quantised.length
    assert (
        lines[8]
        == f"[class 1/2] hopBothLegs1hops: 3 examples, 1 template of {columns} columns, {hop.mode} mode"
    )
    assert lines[9].startswith("[class 2/2] squat1Reps: 2 examples, ") and len(lines) == 10
    assert "classes:    2 (hopBothLegs1hops, squat1Reps)" in stdout
    assert "actors:     1" in stdout
    assert "folds:      3 (groups of one person's examples (one actor: at most 3) left out)" in stdout
    for name, cls in library.classes.items():
        c = cls.provenance
        assert c.recall is not None and c.precision is not None
        if cls.mode == DTW:
            how = f"stream-wide DTW ({cls.mode_reason})"
        else:
            assert cls.keyframes is not None and cls.mode_reason.startswith("keyframes first: ")
            how = cls.mode_reason
        line = (
            f"{name}: {how}; tau {c.tau:.4g} calibrated: recall {c.recall:.2f}, precision {c.precision:.2f} "
            f"on {c.positives} left-out motions and {c.negatives} wrong candidates ({c.folds} folds)"
        )
        assert line in stdout


def keyframe_file(path: Path, classes: list[str]) -> Path:
    """The published keyframes of ``classes`` alone, in the schema of manual-keyframes.json."""
    published = json.loads(KEYFRAMES.read_text(encoding="utf-8"))
    published["classes"] = {name: published["classes"][name] for name in classes}
    path.write_text(json.dumps(published), encoding="utf-8")
    return path


Published = tuple[Path, Path, str]  # keyframe file, library directory, learn's stdout


@pytest.fixture(scope="module")
def published(learned: Learned, tmp_path_factory: pytest.TempPathFactory) -> Published:
    """The training clips learned with the published keyframes of squat1Reps given in a file."""
    manifest = learned[0]
    where = tmp_path_factory.mktemp("published")
    file = keyframe_file(where / "squat.json", ["squat1Reps"])
    result = mocapd("learn", "--manifest", manifest, "--out", where / "lib", "--keyframes", file)
    assert result.returncode == 0, result.stderr
    return file, where / "lib", result.stdout


@pytest.mark.slow
def test_learn_with_keyframes_given_in_a_file(learned: Learned, published: Published) -> None:
    """The classes the file names are gated by its keyframes; the others are learned as without it."""
    file, lib, stdout = published
    library, plain = load_library(lib), load_library(learned[1] / "lib")
    squat = library.classes["squat1Reps"]
    given = parse_keyframe_queries(json.loads(file.read_text()), file)["squat1Reps"]
    assert squat.keyframes is not None and squat.keyframes.keyframes == given.keyframes
    assert (squat.keyframe_source, squat.mode, squat.mode_reason) == (
        PUBLISHED,
        GATED,
        "keyframes given to mocapd learn",
    )
    np.testing.assert_array_equal(squat.quantised.values, plain.classes["squat1Reps"].quantised.values)
    assert squat.provenance == plain.classes["squat1Reps"].provenance
    hop = "hopBothLegs1hops"
    assert_same_library(Library(30.0, {hop: library.classes[hop]}), Library(30.0, {hop: plain.classes[hop]}))
    assert library.classes[hop].keyframe_source == LEARNED
    meta = json.loads((lib / "library.json").read_text())["classes"]
    assert (meta["squat1Reps"]["keyframe_source"], meta["squat1Reps"]["mode"]) == ("published", "keyframes")
    assert len(meta["squat1Reps"]["keyframes"]) == len(given.keyframes) and "keyframe_source" not in meta[hop]
    line = f"squat1Reps: keyframes first, {len(given.keyframes)} (keyframes given to mocapd learn); tau "
    assert line in stdout


def test_learn_keyframes_for_a_class_the_manifest_lacks(learned: Learned, tmp_path: Path) -> None:
    manifest, _, _, _ = learned
    file = keyframe_file(tmp_path / "k.json", ["squat1Reps", "jumpDown", "clap1Reps"])
    result = mocapd("learn", "--manifest", manifest, "--out", tmp_path / "lib", "--keyframes", file)
    assert result.returncode == 2 and "Traceback" not in result.stderr and result.stdout == ""
    last = result.stderr.splitlines()[-1]
    assert last == f"mocapd: {file}: keyframes for classes the manifest lacks: clap1Reps, jumpDown"
    assert not (tmp_path / "lib").exists()


def test_learn_without_keyframes(learned: Learned, tmp_path: Path) -> None:
    """``--keyframes 0``: every class found by the stream-wide DTW, no keyframes learned."""
    manifest, where, _, _ = learned
    result = mocapd("learn", "--manifest", manifest, "--out", tmp_path / "lib", "--keyframes", "0")
    assert result.returncode == 0, result.stderr
    library = load_library(tmp_path / "lib")
    plain = load_library(where / "lib")
    for name, cls in library.classes.items():
        assert (cls.mode, cls.keyframes, cls.mode_reason) == (
            DTW,
            None,
            "no keyframes asked for: stream-wide DTW",
        )
        np.testing.assert_array_equal(cls.quantised.values, plain.classes[name].quantised.values)
        assert f"{name}: stream-wide DTW (no keyframes asked for: stream-wide DTW); tau " in result.stdout
    meta = json.loads((tmp_path / "lib" / "library.json").read_text())["classes"]
    assert all((m["mode"], m["keyframes"]) == ("dtw", []) for m in meta.values())


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


@pytest.mark.slow
def test_search_library_text_and_own_keyframes(learned: Learned, published: Published) -> None:
    """``--keyframes`` without a file: the class's own keyframes (here the published ones it was
    learned with), as if their file were given; a class found by the stream-wide DTW has none."""
    file, lib, _ = published
    where = learned[1]
    own: list[str | Path] = ["--library", lib, "--class", "squat1Reps", "--keyframes"]
    result = mocapd("search", "--index", where / "idx", *own, "--steps", "thesis", "--limit", "1")
    assert_ok(result)
    first = result.stdout.splitlines()[0]
    assert first.startswith("motion template of squat1Reps (") and "thesis steps; keyframes kept" in first
    assert len(result.stdout.splitlines()) <= 2
    mine = hits_json(mocapd("search", "--index", where / "idx", *own, "--json").stdout)
    theirs = hits_json(mocapd("search", "--index", where / "idx", *own, file, "--json").stdout)
    assert mine == theirs and mine
    plain: list[str | Path] = ["--library", where / "lib", "--class", "squat1Reps", "--keyframes"]
    if load_library(where / "lib").classes["squat1Reps"].keyframes is None:
        line = assert_one_error_line(mocapd("search", "--index", where / "idx", *plain))
        assert line == f"mocapd: {where / 'lib'}: class squat1Reps has no keyframes"


@pytest.mark.slow
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


@pytest.mark.slow
@pytest.mark.parametrize(
    ("rows", "options", "message"),
    [
        (["squat1Reps,{asf},{amc},x,"], [], "clips.csv:2: start_frame 'x' is not an integer"),
        (["squat1Reps,{asf},missing.amc.gz,,"], [], "clips.csv:2: amc file not found"),
        (["squat1Reps,{asf},{amc},,"], ["--delta", "0.5"], "--delta must lie in [0, 0.5), got 0.5"),
        (
            ["squat1Reps,{asf},{amc},,"],
            ["--keyframes", "-1"],
            "argument --keyframes: must not be negative, got -1",
        ),
        (["squat1Reps,{asf},{amc},,"], ["--keyframes", " "], "a count of keyframes or a keyframe file"),
        (["squat1Reps,{asf},{amc},,"], ["--keyframes", "missing.json"], "missing.json"),
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


# ------------------------------------------------------------ found trying the commands as a new user would


def test_learn_on_an_empty_manifest_names_learns_columns(tmp_path: Path) -> None:
    empty = tmp_path / "clips.csv"
    empty.write_text("\n")
    line = assert_one_error_line(mocapd("learn", "--manifest", empty, "--out", tmp_path / "lib"))
    assert line == (
        f"mocapd: {empty}:1: empty manifest: no header line (it needs the columns asf, amc, class, "
        "[start_frame], [end_frame], [actor])"
    )


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
