"""Inverted-list index over F-segments and the queries of MRC05 section 5: exact, fuzzy, adaptive fuzzy
and m-mismatch, answered by shifted intersections and unions of sorted lists.

One index per feature set (lower, upper, mix; reference facts, section f). Segments of all documents
are numbered globally, document after document, so that "segment k followed by segment k+1" is an
integer shift; a hit must not cross a document boundary. The inverted list of a code is the sorted
array of the global numbers of the segments with that code (a CSR layout: ``offsets`` into one array),
so the index is linear in the number of segments.

Pure: numpy in, frozen dataclasses out; storing an index is :mod:`daemon.search.store`.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from functools import cached_property

import numpy as np
import numpy.typing as npt

from daemon.errors import MocapdError
from daemon.features import FEATURE_NAMES, SET_SLICES
from daemon.search.segments import segment_codes, set_codes
from daemon.types import BoolArray, FeatureSet, IntArray

CodeSet = Sequence[int] | IntArray  # the codes of a fuzzy set V


class QueryError(MocapdError, ValueError):
    """A query that cannot be run: no feature or an unknown one, features from several sets, more
    mismatches than the query has positions."""


@dataclass(frozen=True)
class SetIndex:
    """The segments of every document for one feature set, and their inverted lists.

    ``doc``, ``start``, ``length``, ``code``: shape ``(S,)``, segment ``s`` covers index-rate frames
    ``start[s] .. start[s] + length[s] - 1`` of document ``doc[s]``; ``offsets`` shape ``(2^f + 1,)``:
    the list of code ``v`` is ``postings[offsets[v]:offsets[v+1]]`` (ascending segment numbers)."""

    feature_set: FeatureSet
    bits: int
    doc: IntArray
    start: IntArray
    length: IntArray
    code: IntArray
    offsets: IntArray
    postings: IntArray

    @cached_property
    def ends(self) -> IntArray:
        """Frames before the end of each segment, counted over all documents: shape ``(S + 1,)``, a
        run of segments ``a .. b - 1`` covers ``ends[b] - ends[a]`` frames."""
        out: IntArray = np.concatenate([[0], np.cumsum(self.length)]).astype(np.int64)
        return out

    @property
    def nonempty_lists(self) -> int:
        """Codes that occur."""
        return int(np.count_nonzero(np.diff(self.offsets)))

    @property
    def n_segments(self) -> int:
        return int(self.code.shape[0])

    def inverted_list(self, code: int) -> IntArray:
        """L(v): the segments with code ``v``, ascending."""
        if not 0 <= code < 1 << self.bits:
            raise ValueError(f"code {code} is outside the {self.bits}-bit {self.feature_set} set")
        out: IntArray = self.postings[self.offsets[code] : self.offsets[code + 1]]
        return out

    def codes(self, codes: CodeSet) -> IntArray:
        """``codes`` as a sorted array without repeats, checked to be codes of this set."""
        c = np.unique(np.asarray(codes, dtype=np.int64))
        if len(c) and (c[0] < 0 or c[-1] >= 1 << self.bits):
            raise ValueError(f"codes must be in 0..{(1 << self.bits) - 1} for the {self.feature_set} set")
        out: IntArray = c
        return out

    def union(self, codes: CodeSet) -> IntArray:
        """L(V): the union of the lists of ``codes``, ascending (one gather and one sort, no loop over
        the codes)."""
        c = self.codes(codes)
        first, sizes = self.offsets[c], self.offsets[c + 1] - self.offsets[c]
        out: IntArray = np.sort(self.postings[concatenated_ranges(first, sizes)])
        return out

    def union_fixed(self, mask: int, value: int) -> IntArray:
        """L(V) for the fuzzy set of every code equal to ``value`` on the bits of ``mask``."""
        return self.union(matching_codes(self.bits, value, mask))

    def union_tolerant(self, mask: int, value: int, mismatches: int) -> IntArray:
        """L(V) for the fuzzy set of every code that differs from ``value`` in at most ``mismatches``
        bits of ``mask`` (a Hamming ball on the fixed bits; 0: :meth:`union_fixed`). The codes that
        occur are tested, not all 2^f."""
        if mismatches < 0:
            raise ValueError(f"mismatches must not be negative, got {mismatches}")
        present = np.flatnonzero(np.diff(self.offsets))
        near = np.bitwise_count((present ^ value) & mask) <= mismatches
        return self.union(present[near])


def concatenated_ranges(first: IntArray, sizes: IntArray) -> IntArray:
    """``first[j] .. first[j] + sizes[j] - 1`` for every j, concatenated: shape ``(sizes.sum(),)``."""
    before = np.concatenate([[0], np.cumsum(sizes)[:-1]]).astype(np.int64)
    out: IntArray = np.repeat(first - before, sizes) + np.arange(int(np.sum(sizes)), dtype=np.int64)
    return out


def build_set_index(matrices: Sequence[BoolArray], feature_set: FeatureSet) -> SetIndex:
    """The ``feature_set`` index of documents given as feature matrices, each shape ``(N_d, 39)`` at the
    index rate."""
    bits = SET_SLICES[feature_set].stop - SET_SLICES[feature_set].start
    return index_from_codes([set_codes(m, feature_set) for m in matrices], bits, feature_set)


def index_from_codes(documents: Sequence[IntArray], bits: int, feature_set: FeatureSet) -> SetIndex:
    """The index of documents given as per-frame codes, each shape ``(N_d,)`` with values below
    ``2^bits``."""
    segs = [segment_codes(np.asarray(c, dtype=np.int64)) for c in documents]
    for d, s in enumerate(segs):
        if len(s) and (s.code.min() < 0 or s.code.max() >= 1 << bits):
            raise ValueError(f"document {d} has codes outside 0..{(1 << bits) - 1}")

    def cat(parts: list[IntArray]) -> IntArray:
        return np.concatenate(parts).astype(np.int64) if parts else np.zeros(0, dtype=np.int64)

    doc = cat([np.full(len(s), d, dtype=np.int64) for d, s in enumerate(segs)])
    code = cat([s.code for s in segs])
    postings = np.argsort(code, kind="stable").astype(np.int64)
    offsets = np.zeros((1 << bits) + 1, dtype=np.int64)
    np.cumsum(np.bincount(code, minlength=1 << bits), out=offsets[1:])
    start = cat([s.start for s in segs])
    length = cat([s.end - s.start + 1 for s in segs])
    return SetIndex(feature_set, bits, doc, start, length, code, offsets, postings)


# ------------------------------------------------------------------------------------------ hits


@dataclass(frozen=True)
class Hits:
    """Query hits: ``doc``, ``first`` and ``last`` segment (global numbers), ``start`` and ``end``
    (inclusive) index-rate frames within the document, each shape ``(H,)``; ``lengths`` shape
    ``(H, K)``: the frames of the database stretch matched to each query position (for the temporal
    ranking of MRC05 section 6.2). Ordered by segment."""

    doc: IntArray
    first: IntArray
    last: IntArray
    start: IntArray
    end: IntArray
    lengths: IntArray

    def __len__(self) -> int:
        return int(self.doc.shape[0])


def _hits(index: SetIndex, bounds: IntArray) -> Hits:
    """Hits from ``bounds`` shape ``(H, K + 1)``: query position i matched segments
    ``bounds[:, i] .. bounds[:, i + 1] - 1``."""
    lengths: IntArray = np.diff(index.ends[bounds], axis=1)
    first = bounds[:, 0]
    start = index.start[first] if len(first) else np.zeros(0, dtype=np.int64)
    end = start + lengths.sum(axis=1) - 1
    return Hits(index.doc[first], first, bounds[:, -1] - 1, start, end, lengths)


def _same_document(index: SetIndex, first: IntArray, last: IntArray) -> npt.NDArray[np.bool_]:
    ok = last < index.n_segments
    out = np.zeros(first.shape, dtype=bool)
    out[ok] = index.doc[first[ok]] == index.doc[last[ok]]
    return out


def fuzzy_query(index: SetIndex, query: Sequence[CodeSet]) -> Hits:
    """Fuzzy hits (MRC05 eq. 4 with sets): segments ``k`` with ``code[k + i] in V_i`` for every query
    position ``i`` (0-based), inside one document. ``query``: the sets ``V_i`` as codes.

    The shifted intersection of the lists L(V_i) - i starts from the shortest one (list sizes are
    known from the offsets); membership of a candidate ``k`` in each other shifted list is
    ``code[k + i] in V_i``, one table lookup. Time: linear in the shortest list plus 2^f per
    position."""
    if not query:
        raise ValueError("a query needs at least one position")
    k = len(query)
    sets = [index.codes(v) for v in query]
    sizes = [int((index.offsets[v + 1] - index.offsets[v]).sum()) if len(v) else 0 for v in sets]
    seed = int(np.argmin(sizes))
    candidates = index.union(sets[seed]) - seed
    candidates = candidates[(candidates >= 0) & (candidates + k - 1 < index.n_segments)]
    for i, codes in enumerate(sets):
        if i != seed and len(candidates):
            member = np.zeros(1 << index.bits, dtype=bool)
            member[codes] = True
            candidates = candidates[member[index.code[candidates + i]]]
    candidates = candidates[_same_document(index, candidates, candidates + k - 1)]
    bounds = candidates[:, None] + np.arange(k + 1)[None, :]
    return _hits(index, bounds)


def exact_query(index: SetIndex, codes: Sequence[int]) -> Hits:
    """Exact hits: the query's F-feature sequence ``codes`` occurs at segment ``k`` (MRC05 eq. 4)."""
    return fuzzy_query(index, [[c] for c in codes])


def mismatch_query(index: SetIndex, query: Sequence[CodeSet], mismatches: int) -> Hits:
    """m-mismatch hits (MRC05 section 5.3): segments ``k`` where at most ``mismatches`` query
    positions ``i`` have ``code[k + i]`` outside ``V_i``, the ``K`` segments inside one document
    (``mismatches < K``, else :class:`QueryError`)."""
    k = len(query)
    if not 0 <= mismatches < k:
        raise QueryError(f"mismatches must be in 0..{k - 1} for a {k}-position query, got {mismatches}")
    shifted = np.concatenate([index.union(codes) - i for i, codes in enumerate(query)])
    shifted = shifted[shifted >= 0]
    starts, agree = np.unique(shifted, return_counts=True)
    candidates = starts[agree >= k - mismatches]
    candidates = candidates[_same_document(index, candidates, candidates + k - 1)]
    return _hits(index, candidates[:, None] + np.arange(k + 1)[None, :])


def adaptive_fuzzy_query(index: SetIndex, query: Sequence[CodeSet]) -> Hits:
    """Adaptive fuzzy hits (MRC05 section 5.2): the database segmentation coarsened to the query's
    sets. A hit starts at a segment ``k1`` in ``V_1`` whose predecessor (in the same document) is not
    in ``V_1``; position ``i`` takes the maximal run of following segments in ``V_i``, the segment
    after that run must be in ``V_{i+1}``; the last position also takes a maximal run.

    Candidates come from the list L(V_1); each later step follows only the surviving candidates,
    testing segment membership in ``V_i`` by the segments' codes (a table of 2^f entries)."""
    if not query:
        raise ValueError("a query needs at least one position")
    sets = [index.codes(v) for v in query]
    code, doc, n = index.code, index.doc, index.n_segments
    member = np.zeros((len(sets), 1 << index.bits), dtype=bool)
    for i, v in enumerate(sets):
        member[i, v] = True

    def inside(segments: IntArray, first: IntArray, i: int) -> npt.NDArray[np.bool_]:
        """``segments`` exist, lie in the document of ``first`` and are in V_i."""
        ok = segments < n
        ok[ok] = (doc[segments[ok]] == doc[first[ok]]) & member[i, code[segments[ok]]]
        return ok

    first = index.union(sets[0])
    before = first - 1
    first = first[~inside(np.where(before >= 0, before, n), first, 0)]
    bounds = [first]
    current = first
    for i in range(len(sets)):
        if i:
            ok = inside(current, first, i)
            first, current, bounds = first[ok], current[ok], [b[ok] for b in bounds]
        end = current.copy()
        active = np.arange(len(end))
        while len(active):  # extend each run while the next segment is still in V_i
            active = active[inside(end[active] + 1, first[active], i)]
            end[active] += 1
        current = end + 1
        bounds.append(current)
    return _hits(index, np.stack(bounds, axis=1).astype(np.int64))


def matching_codes(bits: int, code: int, mask: int) -> IntArray:
    """Every ``bits``-bit code that equals ``code`` on the bits of ``mask`` (feature selection as a
    fuzzy set), ascending."""
    codes = np.arange(1 << bits, dtype=np.int64)
    out: IntArray = codes[(codes & mask) == (code & mask)]
    return out


# ------------------------------------------------------------------------------ queries by example


def feature_selection(names: Sequence[str]) -> tuple[FeatureSet, int]:
    """The feature set and bit mask of the features ``names`` (all from one set: each set has its own
    index); :class:`QueryError` for none, an unknown name or names from several sets."""
    if not names:
        raise QueryError("select at least one feature")
    chosen: dict[FeatureSet, int] = {}
    for name in names:
        if name not in FEATURE_NAMES:
            raise QueryError(f"unknown feature '{name}' (known: {', '.join(FEATURE_NAMES)})")
        i = FEATURE_NAMES.index(name)
        fs = next(s for s, sl in SET_SLICES.items() if sl.start <= i < sl.stop)
        chosen[fs] = chosen.get(fs, 0) | 1 << (i - SET_SLICES[fs].start)
    if len(chosen) > 1:
        sets = ", ".join(f"{m.bit_count()} from {fs}" for fs, m in chosen.items())
        raise QueryError(f"the features come from several sets ({sets}); a query uses one set's index")
    ((fs, mask),) = chosen.items()
    return fs, mask


@dataclass(frozen=True)
class ExampleQuery:
    """A query induced by an example: the example's frames segmented by the selected features only
    (bits ``mask`` of ``feature_set``): ``codes`` shape ``(K,)`` (unselected bits 0) and ``lengths``
    shape ``(K,)`` in frames."""

    feature_set: FeatureSet
    mask: int
    codes: IntArray
    lengths: IntArray

    def fuzzy_sets(self, radius: int = 0) -> list[IntArray]:
        """V_i: every code that differs from position i's in at most ``radius`` selected features
        (unselected features free)."""
        bits = SET_SLICES[self.feature_set].stop - SET_SLICES[self.feature_set].start
        every = np.arange(1 << bits, dtype=np.int64)
        masked = every & self.mask
        distance = np.zeros((len(self.codes), len(every)), dtype=np.int64)
        for b in range(bits):
            if self.mask >> b & 1:
                distance += ((masked[None, :] ^ self.codes[:, None]) >> b) & 1
        return [every[row <= radius] for row in distance]


def example_query(matrix: BoolArray, feature_set: FeatureSet, mask: int) -> ExampleQuery:
    """The query of an example ``matrix`` shape ``(N, 39)`` at the index rate (MRC05 section 6.2:
    the selected features induce the example's segmentation)."""
    segs = segment_codes(set_codes(matrix, feature_set) & mask)
    return ExampleQuery(feature_set, mask, segs.code, segs.end - segs.start + 1)


def temporal_cost(hits: Hits, query_lengths: IntArray) -> IntArray:
    """MRC05 section 6.2's ranking heuristic: the sum over query positions of the difference between
    the frames of the query segment and of the database stretch matched to it, shape ``(H,)``."""
    out: IntArray = np.abs(hits.lengths - np.asarray(query_lengths)[None, :]).sum(axis=1)
    return out


def ranked(hits: Hits, query_lengths: IntArray) -> tuple[IntArray, IntArray]:
    """The hits' order by :func:`temporal_cost` (ties: database order) and the costs in that order."""
    cost = temporal_cost(hits, query_lengths)
    order: IntArray = np.argsort(cost, kind="stable")
    return order, cost[order]
