"""The published manual keyframes on every HDM05 clip in ../shared/data/mocap indexed as one database
(thesis Table 5.2's setting): each class keeps at least 90 % of its clips with few hits in other
classes' clips, and the hits are well-formed Ω^Z components."""

from __future__ import annotations

import json

import pytest

from bench.eval_keyframes import ClassResult, evaluate, hdm05_rows
from daemon.keyframes import parse_keyframe_queries
from daemon.search.keyframes import keyframe_search
from daemon.search.store import MotionIndex, build_index
from tests.helpers import DATA, SHARED


@pytest.fixture(scope="module")
def database() -> tuple[MotionIndex, list[str]]:
    rows = hdm05_rows(DATA)
    return build_index(rows), [r.amc.parent.name for r in rows]


@pytest.fixture(scope="module")
def results(database: tuple[MotionIndex, list[str]]) -> list[ClassResult]:
    return evaluate(*database)


@pytest.mark.slow
def test_every_class_present_is_evaluated(
    results: list[ClassResult], database: tuple[MotionIndex, list[str]]
) -> None:
    assert {r.name for r in results} == set(database[1])
    assert len(results) == 11


FALSE_POSITIVES = {"depositFloorR": 9}
"""The most hits in clips of other classes a class may have; every other class: 1. Measured with
``python -m bench.eval_keyframes`` (188 clips, 11 classes): depositFloorR 7 (24 hits, 17 in its 18
clips), every other class 0; 7 in all."""
ALL_FALSE_POSITIVES = 10


def test_keyframes_keep_the_relevant_clips_and_few_others(results: list[ClassResult]) -> None:
    for r in results:
        assert r.false_negatives <= 0.1 * r.relevant, r
        assert r.false_positives <= FALSE_POSITIVES.get(r.name, 1), r
        assert 0 < r.kept < 0.25, r
    assert sum(r.false_positives for r in results) <= ALL_FALSE_POSITIVES, results


def test_hits_are_disjoint_components_inside_documents(database: tuple[MotionIndex, list[str]]) -> None:
    index, _ = database
    path = SHARED / "reference" / "manual-keyframes.json"
    queries = parse_keyframe_queries(json.loads(path.read_text()), str(path))
    frames = [d.frames for d in index.documents]
    for name, query in queries.items():
        hits = keyframe_search(index.sets, frames, query, index.rate)
        for d, s, e in zip(hits.doc.tolist(), hits.start.tolist(), hits.end.tolist(), strict=True):
            assert 0 <= s <= e < frames[d], name
        same = hits.doc[1:] == hits.doc[:-1]
        assert (hits.start[1:][same] > hits.end[:-1][same]).all(), name
