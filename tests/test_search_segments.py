"""F-segmentation (daemon/search/segments.py) against a plain loop building runs: :func:`segment_codes` and
:class:`Segmenter` equal it, segments tile the sequence, :func:`set_codes` bit ``i`` is feature
``i`` of the set.
"""

from __future__ import annotations

import itertools
from collections.abc import Sequence

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from daemon.features import SET_SLICES
from daemon.search.segments import Segment, Segmenter, segment, segment_codes, set_codes, vector_code
from daemon.types import BoolArray, FeatureSet
from tests.helpers import run_segmenter
from tests.naive import slow_runs

SETS: tuple[FeatureSet, ...] = ("lower", "upper", "mix")

codes_lists = st.one_of(
    st.lists(st.integers(0, 3), max_size=60),
    st.lists(st.integers(0, 2**14 - 1), max_size=20),
    st.lists(st.integers(-(2**63), 2**63 - 1), max_size=10),
)


def assert_tiles(segments: Sequence[Segment], codes: Sequence[int]) -> None:
    """Segments cover ``0..N-1`` in order without gaps or overlap, each one constant, consecutive
    codes different."""
    assert [s.start for s in segments[:1]] == ([0] if codes else [])
    assert [s.end for s in segments[-1:]] == ([len(codes) - 1] if codes else [])
    for s in segments:
        assert s.start <= s.end
        assert all(codes[i] == s.code for i in range(s.start, s.end + 1))
    for a, b in itertools.pairwise(segments):
        assert b.start == a.end + 1
        assert a.code != b.code


@settings(max_examples=300, deadline=None)
@given(codes_lists)
def test_segment_codes_equal_slow_runs(codes: list[int]) -> None:
    got = segment_codes(np.array(codes, dtype=np.int64))
    assert got.start.dtype == got.end.dtype == got.code.dtype == np.int64
    assert len(got) == len(slow_runs(codes))
    assert list(got) == slow_runs(codes)
    assert_tiles(list(got), codes)


@st.composite
def vector_sequences(draw: st.DrawFn) -> BoolArray:
    """Feature vectors ``(N, 39)`` picked from a small palette, so that runs occur and different
    vectors often share one set's code."""
    palette = draw(hnp.arrays(np.bool_, (draw(st.integers(1, 4)), 39)))
    picks = draw(st.lists(st.integers(0, len(palette) - 1), max_size=60))
    out: BoolArray = palette[picks].reshape(len(picks), 39)
    return out


@settings(max_examples=200, deadline=None)
@given(vector_sequences(), vector_sequences(), st.sampled_from(SETS))
def test_segmenter_equals_slow_runs(first: BoolArray, second: BoolArray, feature_set: FeatureSet) -> None:
    segmenter = Segmenter(feature_set)
    for matrix in (first, second):  # the second after the flush: a fresh stream, frames from 0
        codes = [vector_code(v, feature_set) for v in matrix]
        got = run_segmenter(segmenter, matrix)
        assert got == slow_runs(codes)
        assert got == list(segment(matrix, feature_set))
        assert_tiles(got, codes)
    assert segmenter.flush() == []


@settings(max_examples=200, deadline=None)
@given(hnp.arrays(np.bool_, st.tuples(st.integers(0, 30), st.just(39))))
def test_set_codes_bits_are_the_set_features(matrix: BoolArray) -> None:
    for feature_set in SETS:
        part = SET_SLICES[feature_set]
        width = part.stop - part.start
        codes = set_codes(matrix, feature_set)
        assert codes.shape == (len(matrix),)
        assert codes.dtype == np.int64
        assert ((codes >= 0) & (codes < 2**width)).all()
        for i in range(width):
            assert np.array_equal((codes >> i) & 1 == 1, matrix[:, part.start + i])
        assert [vector_code(v, feature_set) for v in matrix] == codes.tolist()


def test_set_codes_lsb_is_the_first_feature_of_the_set() -> None:
    for feature_set in SETS:
        vector = np.zeros(39, dtype=bool)
        vector[SET_SLICES[feature_set].start] = True
        assert vector_code(vector, feature_set) == 1
        assert set_codes(vector[None], feature_set).tolist() == [1]
        others = [s for s in SETS if s != feature_set]
        assert [vector_code(vector, s) for s in others] == [0, 0]
