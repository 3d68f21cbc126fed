"""Adaptive segmentation (MRC05 section 3.2): for a feature set F, an F-segment is a maximal run of
frames with the same F-vector. Lower, upper and mix are segmented separately.

A set's vector is written as an integer code, bit ``i`` = feature ``i`` of the set (the toolbox's
index code ``1 + sum f_i 2^(i-1)`` minus one; reference facts, section f). Batch twin:
:func:`segment`; streaming stage: :class:`Segmenter`.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np

from daemon.features import SET_SLICES
from daemon.types import N_FEATURES, BoolArray, FeatureSet, IntArray


def set_codes(matrix: BoolArray, feature_set: FeatureSet) -> IntArray:
    """Codes of the ``feature_set`` part of ``matrix`` shape ``(N, 39)``: shape ``(N,)``."""
    m = np.asarray(matrix, dtype=bool)
    if m.ndim != 2 or m.shape[1] != N_FEATURES:
        raise ValueError(f"feature matrix must have shape (N, {N_FEATURES}), got {m.shape}")
    part = m[:, SET_SLICES[feature_set]]
    weights = np.left_shift(1, np.arange(part.shape[1], dtype=np.int64))
    out: IntArray = part.astype(np.int64) @ weights
    return out


def vector_code(vector: BoolArray, feature_set: FeatureSet) -> int:
    """Code of the ``feature_set`` part of one vector shape ``(39,)``."""
    v = np.asarray(vector, dtype=bool)
    if v.shape != (N_FEATURES,):
        raise ValueError(f"feature vector must have shape ({N_FEATURES},), got {v.shape}")
    code = 0
    for i, bit in enumerate(v[SET_SLICES[feature_set]].tolist()):
        code |= bit << i
    return code


@dataclass(frozen=True)
class Segment:
    """Frames ``start`` to ``end`` (inclusive, indices of the sequence segmented) share ``code``."""

    start: int
    end: int
    code: int


@dataclass(frozen=True)
class Segments:
    """The F-segments of a sequence: ``start``, ``end`` (inclusive) and ``code``, each shape ``(S,)``,
    in order; consecutive segments have different codes and tile the sequence."""

    start: IntArray
    end: IntArray
    code: IntArray

    def __len__(self) -> int:
        return int(self.start.shape[0])

    def __iter__(self) -> Iterator[Segment]:
        for s, e, c in zip(self.start.tolist(), self.end.tolist(), self.code.tolist(), strict=True):
            yield Segment(s, e, c)


def segment_codes(codes: IntArray) -> Segments:
    """The maximal runs of equal values in ``codes`` shape ``(N,)``."""
    c = np.asarray(codes, dtype=np.int64)
    if c.ndim != 1:
        raise ValueError(f"codes must have shape (N,), got {c.shape}")
    if c.size == 0:
        empty = np.zeros(0, dtype=np.int64)
        return Segments(empty, empty.copy(), empty.copy())
    starts = np.flatnonzero(np.concatenate([[True], c[1:] != c[:-1]])).astype(np.int64)
    ends = np.concatenate([starts[1:] - 1, [c.size - 1]]).astype(np.int64)
    return Segments(starts, ends, c[starts])


def segment(matrix: BoolArray, feature_set: FeatureSet) -> Segments:
    """The ``feature_set``-segments of a feature matrix shape ``(N, 39)`` (batch twin of
    :class:`Segmenter`)."""
    return segment_codes(set_codes(matrix, feature_set))


class Segmenter:
    """F-segments of a stream of feature vectors: ``push(vector)`` returns the segment that the
    vector closed (its code differs from the running one) in a list, else an empty list;
    :meth:`flush` closes the last segment and starts over. State: the running segment only."""

    def __init__(self, feature_set: FeatureSet) -> None:
        self.feature_set = feature_set
        self._n = 0
        self._start = 0
        self._code = -1

    def push(self, vector: BoolArray) -> list[Segment]:
        code = vector_code(vector, self.feature_set)
        closed = []
        if self._n and code != self._code:
            closed.append(Segment(self._start, self._n - 1, self._code))
            self._start = self._n
        self._code = code
        self._n += 1
        return closed

    def flush(self) -> list[Segment]:
        closed = [Segment(self._start, self._n - 1, self._code)] if self._n else []
        self._n, self._start, self._code = 0, 0, -1
        return closed
