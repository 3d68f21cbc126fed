"""Keyframe search (thesis ch. 4): the worked examples, and Ω^Z of Alg. 4.1 against a brute-force
reading of Def. 4.4-4.8 over frames on random databases and queries."""

from __future__ import annotations

import json
import re
from itertools import product

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from daemon.features import SET_SLICES
from daemon.keyframes import (
    Keyframe,
    KeyframeError,
    KeyframeQuery,
    gap_bounds,
    omega_z,
    parse_keyframe_queries,
)
from daemon.search.index import SetIndex, index_from_codes
from daemon.search.keyframes import keyframe_lists, keyframe_search, match_range, search_document
from daemon.types import FeatureSet
from tests.helpers import SHARED
from tests.naive import Lists, hits_of_match, keyframe_brute_force
from tests.synth import LOW_BITS, queries


def one_based(matches: list[tuple[int, ...]]) -> list[tuple[int, ...]]:
    return [tuple(i + 1 for i in m) for m in matches]


# ------------------------------------------------------------------------------- worked examples

EXAMPLE_421: Lists = [
    ([2, 7], [5, 7]),
    ([7, 11], [7, 15]),
    ([7, 9, 11, 24, 26, 32], [7, 10, 15, 25, 29, 34]),
]


def test_thesis_example_4_2_1_matches_hits_and_omega() -> None:
    bounds = [gap_bounds(6, 0.8), gap_bounds(10, 0.8)]
    assert bounds == [(5, 7), (8, 12)]  # μ_{0.8,6} and μ_{0.8,10} of Auflistung 4.3
    found = search_document(EXAMPLE_421, bounds, 100)
    assert one_based(found.matches) == [(1, 1, 3), (1, 2, 4), (2, 2, 4), (2, 2, 5)]
    assert found.calls == 5  # the five arrows of Auflistung 4.3
    table_4_1: dict[tuple[int, ...], set[tuple[int, ...]]] = {
        (1, 1, 3): {(2, 7, 15)},
        (1, 2, 4): {(5, 12, 24)},
        (2, 2, 4): {(7, 14, 24), (7, 13, 24), (7, 12, 24), (7, 14, 25), (7, 13, 25)},
        (2, 2, 5): {(7, 14, 26)},
    }
    ranges = []
    for m in found.matches:
        hits = set(hits_of_match(EXAMPLE_421, m, [6, 10], 0.8))
        assert hits == table_4_1[tuple(i + 1 for i in m)]
        r = match_range([(EXAMPLE_421[k][0][i], EXAMPLE_421[k][1][i]) for k, i in enumerate(m)], bounds)
        assert r == (min(h[0] for h in hits), max(h[-1] for h in hits))
        ranges.append(r)
    assert omega_z(ranges) == [(2, 26)]  # "überspannt die Frames 2 bis 26"


def test_thesis_example_4_2_1_needs_the_pointer_step_back() -> None:
    """Without lines 4, 13 and 15 of Alg. 4.2 the matches (2,2,4), (2,2,5) are lost and Ω^Z shrinks to
    frames 2-24; the published algorithm keeps them (checked above). Here: every match with a hit,
    found by enumerating all pointer tuples, and its Ω^Z equal the algorithm's."""
    complete = [
        m
        for m in product(*(range(len(s)) for s, _ in EXAMPLE_421))
        if hits_of_match(EXAMPLE_421, m, [6, 10], 0.8)
    ]
    assert one_based(complete) == [(1, 1, 3), (1, 2, 4), (2, 2, 4), (2, 2, 5)]


def test_thesis_worst_case_beispiel_4_5() -> None:
    """Figure 4.11 / Auflistung 4.5: K = 3, σ = 0.5, δ = (2, 2); 4 calls and 2 matches = Γ = 6, the
    bound (4.16) 3ℓ1 + 2ℓ2 + ℓ3 - 3 with ℓ = (2, 1, 1)."""
    lists: Lists = [([1, 3], [2, 4]), ([4], [7]), ([8], [12])]
    bounds = [gap_bounds(2, 0.5)] * 2
    assert bounds == [(1, 4), (1, 4)]
    found = search_document(lists, bounds, 100)
    assert one_based(found.matches) == [(1, 1, 1), (2, 1, 1)]
    assert found.calls + len(found.matches) == 6 == 3 * 2 + 2 * 1 + 1 - 3


def test_thesis_rounding_example() -> None:
    """Figure 4.6: with the rounding of μ there is no match (without it (1,1,1) would be reported)."""
    lists: Lists = [([1], [1]), ([2], [4]), ([9], [9])]
    found = search_document(lists, [gap_bounds(2, 0.7), gap_bounds(4, 0.7)], 100)
    assert found.matches == []
    assert hits_of_match(lists, (0, 0, 0), [2, 4], 0.7) == []


def test_gap_bounds_are_exact_for_decimal_stiffness() -> None:
    assert gap_bounds(30, 0.1) == (3, 300)  # 0.1 * 30 is 3.0000000000000004 in floating point
    assert gap_bounds(10, 0.7) == (7, 14)
    assert gap_bounds(0, 0.5) == (0, 0)
    assert gap_bounds(7, 0) == (0, None)
    assert gap_bounds(0, 0) == (0, None)
    assert gap_bounds(9, 1.0) == (9, 9)
    with pytest.raises(ValueError, match="stiffness"):
        gap_bounds(3, 1.5)
    with pytest.raises(ValueError, match="negative"):
        gap_bounds(-1, 0.5)


# ------------------------------------------------------------------------------- brute force

SET_CHOICES: tuple[FeatureSet, ...] = ("lower", "upper")


@st.composite
def databases(draw: st.DrawFn) -> dict[FeatureSet, list[list[int]]]:
    n_docs = draw(st.integers(1, 3))
    lengths = [draw(st.integers(1, 24)) for _ in range(n_docs)]
    out: dict[FeatureSet, list[list[int]]] = {}
    for fs in SET_CHOICES:
        docs = []
        for n in lengths:
            codes: list[int] = []
            while len(codes) < n:  # runs, so that segments are longer than one frame
                codes += [draw(st.integers(0, (1 << LOW_BITS) - 1))] * draw(st.integers(1, 5))
            docs.append(codes[:n])
        out[fs] = docs
    return out


def keyframe_queries(tolerant: bool = False) -> st.SearchStrategy[KeyframeQuery]:
    return queries(sets=SET_CHOICES, stiffnesses=(0.0, 0.2, 0.5, 0.7, 0.8, 0.9, 1.0), tolerant=tolerant)


def set_indexes(docs: dict[FeatureSet, list[list[int]]]) -> dict[FeatureSet, SetIndex]:
    return {
        fs: index_from_codes(
            [np.asarray(c, dtype=np.int64) for c in docs[fs]], SET_SLICES[fs].stop - SET_SLICES[fs].start, fs
        )
        for fs in SET_CHOICES
    }


@pytest.mark.parametrize("tolerant", [False, True], ids=["exact", "tolerant"])
@settings(max_examples=400, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(databases(), st.data(), st.sampled_from([(0, 0), (0, 0), (2, 0), (1, 3)]))
def test_keyframe_search_equals_brute_force(
    tolerant: bool, docs: dict[FeatureSet, list[list[int]]], data: st.DataObject, extend: tuple[int, int]
) -> None:
    """Also with keyframes that may miss some of their fixed entries (``tolerant``)."""
    query = data.draw(keyframe_queries(tolerant), label="query")
    expected = keyframe_brute_force(docs, query, extend)
    for prune in (True, False):
        found = keyframe_search(
            set_indexes(docs), [len(c) for c in docs["lower"]], query, 30.0, extend, prune
        )
        got = list(zip(found.doc.tolist(), found.start.tolist(), found.end.tolist(), strict=True))
        assert got == expected


@pytest.mark.slow
@settings(max_examples=200, deadline=None)
@given(databases(), keyframe_queries(tolerant=True))
def test_unpruned_search_per_document(docs: dict[FeatureSet, list[list[int]]], query: KeyframeQuery) -> None:
    """Alg. 4.1 as published, one document at a time on the whole post-segmented lists (no pruning):
    every pointer tuple it reports is a match (Behauptung 4.1) and Ω^Z of its matches equals Ω^Z of
    all matches (Behauptung 4.2), here the brute force; keyframes exact or tolerant."""
    lists = keyframe_lists(set_indexes(docs), query)
    bounds = [gap_bounds(d, s) for d, s in query.gaps(30.0)]
    got = []
    for d, codes in enumerate(docs["lower"]):
        per_doc: Lists = [(s[docs_ == d].tolist(), e[docs_ == d].tolist()) for s, e, docs_ in lists]
        if any(not s for s, _ in per_doc):
            continue
        ranges = []
        for m in search_document(per_doc, bounds, len(codes) - 1).matches:
            r = match_range([(per_doc[k][0][i], per_doc[k][1][i]) for k, i in enumerate(m)], bounds)
            assert r is not None
            ranges.append(r)
        got += [(d, s, t) for s, t in omega_z(ranges)]
    assert got == keyframe_brute_force(docs, query, (0, 0))


def test_equal_positions_and_full_stiffness() -> None:
    """δ = 0 with σ = 1: the keyframes must hold on the same frame; ranges touching but not sharing a
    frame stay separate components."""
    lower = [[1, 1, 0, 1, 1, 1, 0, 0]]
    upper = [[2, 2, 2, 2, 0, 2, 2, 0]]
    docs: dict[FeatureSet, list[list[int]]] = {"lower": lower, "upper": upper}
    values_l = (1.0, 0.5, 0.5) + (0.0,) * 9
    values_u = (0.5, 1.0, 0.5) + (0.0,) * 11
    query = KeyframeQuery(
        "same", (Keyframe("lower", values_l, 4, 1.0), Keyframe("upper", values_u, 4, None)), 30.0
    )
    found = keyframe_search(set_indexes(docs), [8], query, 30.0)
    assert list(zip(found.start.tolist(), found.end.tolist(), strict=True)) == [(0, 1), (3, 3), (5, 5)]
    assert [
        (0, s, t) for s, t in zip(found.start.tolist(), found.end.tolist(), strict=True)
    ] == keyframe_brute_force(docs, query, (0, 0))


# ------------------------------------------------------------------------------- the JSON schema


def test_published_keyframes_parse() -> None:
    path = SHARED / "reference" / "manual-keyframes.json"
    queries_ = parse_keyframe_queries(json.loads(path.read_text()), str(path))
    assert len(queries_) == 75
    squat = queries_["squat1Reps"]
    assert [k.feature_set for k in squat.keyframes] == ["mix", "mix", "mix", "upper"]
    assert [k.position for k in squat.keyframes] == [15, 25, 30, 32]
    assert squat.gaps(30.0) == [(10, 0.7), (5, 0.7), (2, 0.5)]
    assert squat.gaps(120.0) == [(40, 0.7), (20, 0.7), (8, 0.5)]
    assert squat.template_length == 47
    first = squat.keyframes[0]  # mix values 1,1,1,1,½,0,0,0,0,0,0,½,1
    assert first.mask == (1 << 13) - 1 - (1 << 4) - (1 << 11)
    assert first.value == 0b1000000001111


@pytest.mark.parametrize(
    ("mutate", "field"),
    [
        (lambda d: d["classes"]["a"][0].update(set="legs"), "classes.a[0].set"),
        (lambda d: d["classes"]["a"][0].update(values=[0] * 3), "classes.a[0].values"),
        (lambda d: d["classes"]["a"][1]["values"].__setitem__(2, 0.3), "classes.a[1].values[2]"),
        (lambda d: d["classes"]["a"][0].update(position="7"), "classes.a[0].position"),
        (lambda d: d["classes"]["a"][1].update(position=1), "classes.a[1].position"),
        (lambda d: d["classes"]["a"][0].update(stiffness_to_next=1.2), "classes.a[0].stiffness_to_next"),
        (lambda d: d["classes"]["a"][0].update(stiffness_to_next=None), "classes.a[0].stiffness_to_next"),
        (lambda d: d["classes"]["a"][0].update(mismatches=-1), "classes.a[0].mismatches"),
        (lambda d: d["classes"]["a"][0].update(mismatches=12), "classes.a[0].mismatches"),
        (lambda d: d["classes"]["a"][1].update(mismatches=1.0), "classes.a[1].mismatches"),
        (lambda d: d["classes"]["a"][1].update(mismatches=True), "classes.a[1].mismatches"),
        (lambda d: d["classes"]["a"][1].update(mismatches="2"), "classes.a[1].mismatches"),
        (lambda d: d["classes"]["a"][1].update(values=[0.5] * 14, mismatches=1), "classes.a[1].mismatches"),
        (lambda d: d.update(classes={}), "classes"),
        (lambda d: d.update(frame_rate_hz=0), "frame_rate_hz"),
    ],
)
def test_bad_keyframe_files_name_the_field(mutate: object, field: str) -> None:
    doc = {
        "frame_rate_hz": 30,
        "classes": {
            "a": [
                {"set": "lower", "values": [0] * 12, "position": 3, "stiffness_to_next": 0.5},
                {"set": "upper", "values": [1] * 14, "position": 5, "stiffness_to_next": None},
            ]
        },
    }
    parse_keyframe_queries(doc, "q.json")
    assert callable(mutate)
    mutate(doc)
    with pytest.raises(KeyframeError, match=re.escape(f"q.json: {field}")):
        parse_keyframe_queries(doc, "q.json")


def test_mismatches_are_optional_and_fewer_than_the_fixed_entries() -> None:
    """``mismatches`` defaults to 0 (the thesis' keyframe); at most the fixed entries - 1, and 0 for
    a keyframe that fixes none; the error says the range and why."""
    doc = {
        "classes": {
            "squat": [
                {
                    "set": "lower",
                    "values": [0] * 12,
                    "position": 3,
                    "stiffness_to_next": 0.5,
                    "mismatches": 11,
                },
                {
                    "set": "upper",
                    "values": [1, 0] + [0.5] * 12,
                    "position": 5,
                    "stiffness_to_next": 1,
                    "mismatches": 1,
                },
                {"set": "mix", "values": [0.5] * 13, "position": 6, "mismatches": 0},
            ]
        },
    }
    got = parse_keyframe_queries(doc, "q.json")["squat"].keyframes
    assert [k.mismatches for k in got] == [11, 1, 0]
    del doc["classes"]["squat"][0]["mismatches"]
    assert parse_keyframe_queries(doc, "q.json")["squat"].keyframes[0].mismatches == 0
    doc["classes"]["squat"][1]["mismatches"] = 2
    with pytest.raises(KeyframeError) as caught:
        parse_keyframe_queries(doc, "q.json")
    assert str(caught.value) == (
        "q.json: classes.squat[1].mismatches: must be an integer in [0, 1] (fewer than the keyframe's 2 "
        "fixed entries), got 2"
    )
    values = (1.0, 0.0) + (0.5,) * 12
    assert Keyframe("upper", values, 0, None, 1).max_mismatches == 1
    for bad in (2, -1, True):
        with pytest.raises(ValueError, match=r"mismatches must be an integer in \[0, 1\]"):
            Keyframe("upper", values, 0, None, bad)
    with pytest.raises(ValueError, match=r"in \[0, 0\] for a keyframe with 0 fixed entries"):
        Keyframe("upper", (0.5,) * 14, 0, None, 1)


def test_a_tolerant_keyframe_matches_within_its_mismatches() -> None:
    """``Keyframe.matches``: at most ``mismatches`` of the fixed bits differ; free bits never count."""
    kf = Keyframe("lower", (1.0, 1.0, 1.0, 0.0) + (0.5,) * 8, 0, None, 1)
    assert (kf.mask, kf.value) == (0b1111, 0b0111)
    codes = [0b0111, 0b0011, 0b1111, 0b1011, 0b0000, 0b0110, 0b11110111]
    assert [kf.matches(c) for c in codes] == [True, True, True, False, False, True, True]
    exact = Keyframe("lower", kf.values, 0, None)
    assert [exact.matches(c) for c in codes] == [(c & exact.mask) == exact.value for c in codes]
