"""``mocapd search`` run for real in a subprocess on an index of real HDM05 clips: keyframe queries
equal the library's Ω^Z components in AMC frame numbers; a query by example finds its own clip first
at cost 0; bad options exit 2 with one line."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from daemon.keyframes import parse_keyframe_queries
from daemon.recordings import read_features, read_manifest
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
    KEYFRAMES,
    assert_ok,
    assert_one_error_line,
    hdm05_clip,
    hits_json,
    mocapd,
    write_manifest,
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
