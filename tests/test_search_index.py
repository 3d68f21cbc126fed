"""The inverted-list index and the MRC05 queries against brute-force readings of their definitions."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from daemon.features import FEATURE_NAMES
from daemon.search.index import (
    ExampleQuery,
    Hits,
    SetIndex,
    adaptive_fuzzy_query,
    build_set_index,
    exact_query,
    example_query,
    feature_selection,
    fuzzy_query,
    index_from_codes,
    matching_codes,
    mismatch_query,
    ranked,
    temporal_cost,
)
from daemon.search.segments import segment_codes, set_codes
from tests.naive import brute_adaptive, brute_fuzzy

BITS = 3

# ---------------------------------------------------------------------------------- brute force


def check_hits(index: SetIndex, hits: Hits, expected: list[list[int]]) -> None:
    """``hits`` are exactly the hits whose per-position segment bounds are ``expected``."""
    assert len(hits) == len(expected)
    lengths = index.length.tolist()
    for h, bounds in enumerate(expected):
        assert hits.first[h] == bounds[0] and hits.last[h] == bounds[-1] - 1
        assert hits.doc[h] == index.doc[bounds[0]]
        per_position = [sum(lengths[bounds[i] : bounds[i + 1]]) for i in range(len(bounds) - 1)]
        assert hits.lengths[h].tolist() == per_position
        assert hits.start[h] == index.start[bounds[0]]
        assert hits.end[h] == index.start[bounds[-1] - 1] + index.length[bounds[-1] - 1] - 1


# ---------------------------------------------------------------------------------- strategies

documents = st.lists(
    st.lists(st.integers(0, (1 << BITS) - 1), min_size=0, max_size=40).map(
        lambda codes: np.repeat(np.array(codes, dtype=np.int64), 2)  # frames: runs of two at least
    ),
    min_size=1,
    max_size=5,
)
code_sets = st.sets(st.integers(0, (1 << BITS) - 1), min_size=1, max_size=4)


@pytest.mark.slow
@settings(max_examples=300, deadline=None)
@given(documents, st.lists(code_sets, min_size=1, max_size=5))
def test_fuzzy_query_equals_brute_force(docs: list[np.ndarray], query: list[set[int]]) -> None:
    index = index_from_codes(docs, BITS, "lower")
    check_hits(index, fuzzy_query(index, [sorted(v) for v in query]), brute_fuzzy(index, query))


@settings(max_examples=300, deadline=None)
@given(documents, st.lists(st.integers(0, (1 << BITS) - 1), min_size=1, max_size=5))
def test_exact_query_equals_brute_force(docs: list[np.ndarray], query: list[int]) -> None:
    index = index_from_codes(docs, BITS, "lower")
    check_hits(index, exact_query(index, query), brute_fuzzy(index, [{c} for c in query]))


@pytest.mark.slow
@settings(max_examples=300, deadline=None)
@given(documents, st.lists(code_sets, min_size=1, max_size=5), st.data())
def test_mismatch_query_equals_brute_force(
    docs: list[np.ndarray], query: list[set[int]], data: st.DataObject
) -> None:
    m = data.draw(st.integers(0, len(query) - 1))
    index = index_from_codes(docs, BITS, "lower")
    check_hits(index, mismatch_query(index, [sorted(v) for v in query], m), brute_fuzzy(index, query, m))


@settings(max_examples=300, deadline=None)
@given(documents, st.lists(code_sets, min_size=1, max_size=5))
def test_adaptive_fuzzy_query_equals_brute_force(docs: list[np.ndarray], query: list[set[int]]) -> None:
    index = index_from_codes(docs, BITS, "lower")
    check_hits(index, adaptive_fuzzy_query(index, [sorted(v) for v in query]), brute_adaptive(index, query))


@settings(max_examples=100, deadline=None)
@given(documents)
def test_index_lists_and_segments(docs: list[np.ndarray]) -> None:
    index = index_from_codes(docs, BITS, "lower")
    assert index.n_segments == sum(len(segment_codes(d)) for d in docs)
    for v in range(1 << BITS):
        listed = index.inverted_list(v)
        assert listed.tolist() == np.flatnonzero(index.code == v).tolist()
    # Segments tile each document.
    for d, codes in enumerate(docs):
        mine = index.doc == d
        assert index.length[mine].sum() == len(codes)
        assert (np.repeat(index.code[mine], index.length[mine]) == codes).all()


# ---------------------------------------------------------------------------------- MRC05


def walk_index() -> SetIndex:
    """F^2[D_walk] of MRC05 eq. (3), bit 0 = F^r, bit 1 = F^l: (1,1), (0,1), (1,1), (1,0), ... as
    implied by eq. (8): L((1,0)) = {4, 8}, L((1,1)) = {1, 3, 5, 7, 9}, L((0,1)) = {2, 6, 10} (1-based)."""
    both, left, right = 0b11, 0b10, 0b01
    walk = [both, left, both, right, both, left, both, right, both, left]
    return index_from_codes([np.repeat(np.array(walk, dtype=np.int64), 3)], 2, "lower")


def test_mrc05_equation_8() -> None:
    index = walk_index()
    hits = exact_query(index, [0b01, 0b11, 0b10])
    assert (hits.first + 1).tolist() == [4, 8]  # MRC05 counts segments from 1


def test_mrc05_adaptive_fuzzy_example() -> None:
    index = walk_index()
    v1 = v3 = [0b00, 0b10]  # (F^r, F^l) in {(0,0), (0,1)}
    v2 = [0b01, 0b11]  # {(1,0), (1,1)}
    assert len(fuzzy_query(index, [v1, v2, v3])) == 0
    hits = adaptive_fuzzy_query(index, [v1, v2, v3])
    assert (hits.first + 1).tolist() == [2, 6]
    # First hit: V1 <-> segment 2, V2 <-> segments 3-5, V3 <-> segment 6 (3 frames per segment).
    assert hits.lengths.tolist() == [[3, 9, 3], [3, 9, 3]]


def test_feature_selection_codes() -> None:
    codes = matching_codes(4, 0b1010, 0b0011)
    assert sorted(codes) == sorted(c for c in range(16) if c & 0b0011 == 0b10)


def test_build_from_feature_matrices() -> None:
    rng = np.random.default_rng(1)
    matrices = [rng.random((n, 39)) < 0.1 for n in (5, 17, 1)]
    for name in ("lower", "upper", "mix"):
        index = build_set_index(matrices, name)
        expected = index_from_codes([set_codes(m, name) for m in matrices], index.bits, name)
        assert np.array_equal(index.code, expected.code) and np.array_equal(index.postings, expected.postings)


def test_bad_queries() -> None:
    index = walk_index()
    with pytest.raises(ValueError, match="at least one"):
        fuzzy_query(index, [])
    with pytest.raises(ValueError, match="mismatches"):
        mismatch_query(index, [[1], [2]], 2)
    with pytest.raises(ValueError, match="outside"):
        index.inverted_list(4)


@settings(max_examples=200, deadline=None)
@given(documents, st.data())
def test_union_equals_concatenated_lists(docs: list[np.ndarray], data: st.DataObject) -> None:
    """L(V) of a set of codes, of the codes fixed by a mask, and of those within some mismatches of
    it on the mask."""
    index = index_from_codes(docs, BITS, "lower")
    codes = data.draw(st.lists(st.integers(0, (1 << BITS) - 1), max_size=6))
    expected = sorted(s for c in set(codes) for s in index.inverted_list(c).tolist())
    assert index.union(codes).tolist() == expected
    mask, value = data.draw(st.integers(0, (1 << BITS) - 1)), data.draw(st.integers(0, (1 << BITS) - 1))
    fixed = [s for s, c in enumerate(index.code.tolist()) if c & mask == value & mask]
    assert index.union_fixed(mask, value).tolist() == fixed
    assert index.union_tolerant(mask, value, 0).tolist() == fixed
    mismatches = data.draw(st.integers(0, BITS))
    near = [s for s, c in enumerate(index.code.tolist()) if ((c ^ value) & mask).bit_count() <= mismatches]
    assert index.union_tolerant(mask, value, mismatches).tolist() == near


@settings(max_examples=200, deadline=None)
@given(
    st.lists(st.integers(0, (1 << 5) - 1), min_size=1, max_size=4),
    st.integers(1, (1 << 5) - 1),
    st.integers(0, 5),
)
def test_fuzzy_sets_are_hamming_balls_on_the_selected_features(
    codes: list[int], mask: int, radius: int
) -> None:
    query = ExampleQuery(
        "lower", mask, np.array([c & mask for c in codes]), np.ones(len(codes), dtype=np.int64)
    )
    for c, members in zip(codes, query.fuzzy_sets(radius), strict=True):
        expected = [v for v in range(1 << 12) if ((v ^ c) & mask).bit_count() <= radius]
        assert members.tolist() == expected


def test_feature_selection_names_one_set() -> None:
    assert feature_selection(["kneeRightBent", "kneeLeftBent"]) == ("lower", 0b1100000)
    assert feature_selection(["rootHighVel"]) == ("mix", 1 << 12)
    assert feature_selection(["handRightToFrontRelTorso"]) == ("upper", 1)
    with pytest.raises(ValueError, match="several sets"):
        feature_selection(["kneeRightBent", "elbowRightBent"])
    with pytest.raises(ValueError, match="unknown feature 'kneeBent'"):
        feature_selection(["kneeBent"])
    with pytest.raises(ValueError, match="at least one"):
        feature_selection([])
    assert len(FEATURE_NAMES) == 39


def test_example_query_segments_by_the_selected_features() -> None:
    matrix = np.zeros((9, 39), dtype=bool)
    matrix[2:6, 5] = True  # kneeRightBent: selected
    matrix[4:9, 0] = True  # footRightBackRelLegLeft: not selected, so no new segment
    query = example_query(matrix, "lower", 1 << 5)
    assert query.codes.tolist() == [0, 1 << 5, 0]
    assert query.lengths.tolist() == [2, 4, 3]


def test_temporal_ranking_orders_by_length_differences() -> None:
    hits = Hits(
        doc=np.array([0, 0, 1]),
        first=np.array([0, 5, 9]),
        last=np.array([2, 7, 11]),
        start=np.array([0, 30, 2]),
        end=np.array([9, 40, 20]),
        lengths=np.array([[3, 4, 3], [2, 6, 3], [3, 5, 3]]),
    )
    query_lengths = np.array([3, 5, 3])
    assert temporal_cost(hits, query_lengths).tolist() == [1, 2, 0]
    order, cost = ranked(hits, query_lengths)
    assert order.tolist() == [2, 0, 1] and cost.tolist() == [0, 1, 2]
