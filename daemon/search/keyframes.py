"""Keyframe search with stiffness (thesis ch. 4): Algorithms 4.1/4.2 over the inverted lists of the
keyframes of a :class:`~daemon.keyframes.KeyframeQuery`, the hit-relevant range of a match
(Def. 4.6) and the Ω^Z components (Def. 4.7/4.8).

A keyframe's list Λ(V) is the union of the inverted lists of V (for a tolerant keyframe, of every
code within its ``mismatches`` of it), post-segmented (section 4.2.4: adjacent segments merged), so
Λ(V) is the maximal runs of frames whose vector lies in V. Frames are index-rate frames (0-based) of
one document; hits never cross documents. Pure: numpy and Python in, frozen dataclasses out.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from daemon.keyframes import KeyframeQuery, omega_z, query_bounds
from daemon.search.index import SetIndex, concatenated_ranges
from daemon.types import FeatureSet, IntArray

# ------------------------------------------------------------------------------- the algorithm


@dataclass(frozen=True)
class Search:
    """Alg. 4.1 on the lists of one document: ``matches`` (pointer tuples, 0-based, in the order
    found) and ``calls`` (calls of sucheRekursiv, Alg. 4.2)."""

    matches: list[tuple[int, ...]]
    calls: int


Intervals = tuple[Sequence[int], Sequence[int]]  # starts, ends (inclusive), sorted and disjoint


def search_document(
    lists: Sequence[Intervals], bounds: Sequence[tuple[int, int | None]], last: int
) -> Search:
    """Algorithms 4.1 and 4.2 on the lists ``lists[k]`` = Λ_k of one document whose last frame is
    ``last``; ``bounds[k]`` = (⌈σδ⌉, ⌊δ/σ⌋ or None) of gap k."""
    return search(lists, bounds, [[last] * len(s) for s, _ in lists])


def search(
    lists: Sequence[Intervals], bounds: Sequence[tuple[int, int | None]], lasts: Sequence[Sequence[int]]
) -> Search:
    """Algorithms 4.1 and 4.2 as published: pointers into the keyframe lists that move forward and
    step back once after a scan (lines 4, 13, 15 of Alg. 4.2). ``lasts[k][i]``: the last frame of the
    document of entry i of Λ_k; an allowed range ends there, so the lists of several documents laid
    out one after another (with a gap) can be searched in one pass: a range never reaches into the
    next document, and a range left empty by that cut moves no pointer."""
    k_all = len(lists)
    if len(bounds) != k_all - 1:
        raise ValueError(f"{k_all} keyframes need {k_all - 1} gaps, got {len(bounds)}")
    starts = [list(s) for s, _ in lists]
    ends = [list(e) for _, e in lists]
    size = [len(s) for s in starts]
    p = [0] * k_all
    matches: list[tuple[int, ...]] = []
    calls = 0
    if k_all == 1:
        return Search([(i,) for i in range(size[0])], 0)

    def recurse(k: int, lo: int, hi: int) -> None:  # sucheRekursiv(k, allowedRange = (lo, hi))
        nonlocal calls
        calls += 1
        if lo > hi:
            return
        s, e = starts[k], ends[k]
        while p[k] < size[k] and e[p[k]] < lo:
            p[k] += 1
        moved = False
        while p[k] < size[k]:
            a, b = max(s[p[k]], lo), min(e[p[k]], hi)
            if a > b:
                break
            if k == k_all - 1:
                matches.append(tuple(p))
            else:
                dmin, dmax = bounds[k]
                end = lasts[k][p[k]]
                recurse(k + 1, a + dmin, end if dmax is None else min(b + dmax, end))
            p[k] += 1
            moved = True
        if moved:
            p[k] -= 1

    dmin0, dmax0 = bounds[0]
    for i in range(size[0]):
        p[0] = i
        end = lasts[0][i]
        recurse(1, starts[0][i] + dmin0, end if dmax0 is None else min(ends[0][i] + dmax0, end))
    return Search(matches, calls)


def match_range(
    segments: Sequence[tuple[int, int]], bounds: Sequence[tuple[int, int | None]]
) -> tuple[int, int] | None:
    """The hit-relevant range R(M) of Def. 4.6: (smallest i_1, largest i_K) over the hits whose
    frames lie in ``segments`` (one (start, end) per keyframe), or None if there is no hit."""
    starts = [np.array([s], dtype=np.int64) for s, _ in segments]
    ends = [np.array([e], dtype=np.int64) for _, e in segments]
    first, last, ok = match_ranges(starts, ends, np.zeros((1, len(segments)), dtype=np.int64), bounds)
    return (int(first[0]), int(last[0])) if ok[0] else None


def match_ranges(
    starts: Sequence[IntArray],
    ends: Sequence[IntArray],
    matches: IntArray,
    bounds: Sequence[tuple[int, int | None]],
) -> tuple[IntArray, IntArray, npt.NDArray[np.bool_]]:
    """R(M) (Def. 4.6) of many matches at once: ``matches`` shape ``(M, K)`` picks entry
    ``matches[:, k]`` of list k (``starts[k]``, ``ends[k]``). Returns (first, last, has_hit), each
    shape ``(M,)``. The frames of a match's segment k that can be the k-th frame of a hit prefix form
    an interval: forward from k = 1, then back from k = K, where only the smallest frame with a
    successor needs tracking (every reachable frame has a reachable predecessor)."""
    lo, hi = starts[0][matches[:, 0]], ends[0][matches[:, 0]]
    ok = np.ones(lo.shape, dtype=bool)
    reach = [lo]
    for k, (dmin, dmax) in enumerate(bounds, start=1):
        s, e = starts[k][matches[:, k]], ends[k][matches[:, k]]
        lo, hi = np.maximum(s, lo + dmin), e if dmax is None else np.minimum(e, hi + dmax)
        ok &= lo <= hi
        reach.append(lo)
    first = reach[-1]
    for k in range(len(bounds) - 1, -1, -1):
        dmax = bounds[k][1]
        first = reach[k] if dmax is None else np.maximum(reach[k], first - dmax)
    return first, hi, ok


def post_segment(starts: IntArray, ends: IntArray, docs: IntArray) -> tuple[IntArray, IntArray, IntArray]:
    """Section 4.2.4: merge segments of a list that touch (next start = previous end + 1, same
    document). Arrays shape ``(L,)`` sorted by (doc, start); returns the merged (starts, ends, docs)."""
    if not len(starts):
        return starts, ends, docs
    new = np.ones(starts.shape, dtype=bool)
    new[1:] = (starts[1:] != ends[:-1] + 1) | (docs[1:] != docs[:-1])
    first = np.flatnonzero(new)
    last = np.concatenate([first[1:] - 1, [len(starts) - 1]])
    return starts[first], ends[last], docs[first]


# ------------------------------------------------------------------------------- over an index


@dataclass(frozen=True)
class KeyframeHits:
    """The Ω^Z components of a keyframe search: ``doc``, ``start``, ``end`` (inclusive index-rate
    frames), each shape ``(H,)``, ordered by document and frame. ``list_lengths``: the post-segmented
    list length per keyframe (Σℓ of thesis Table 5.3); ``matches``, ``calls``: Alg. 4.1 counts."""

    doc: IntArray
    start: IntArray
    end: IntArray
    list_lengths: tuple[int, ...]
    matches: int
    calls: int

    def __len__(self) -> int:
        return int(self.doc.shape[0])

    @property
    def frames(self) -> int:
        """Frames covered (the size of the reduced database)."""
        return int((self.end - self.start + 1).sum())


def keyframe_lists(
    sets: Mapping[FeatureSet, SetIndex], query: KeyframeQuery
) -> list[tuple[IntArray, IntArray, IntArray]]:
    """Λ_k for every keyframe (Alg. 4.1 line 2, then post-segmentation): (starts, ends, docs). A
    tolerant keyframe's V_k holds every code within its ``mismatches`` of it on the fixed bits."""
    out = []
    for kf in query.keyframes:
        index = sets[kf.feature_set]
        segs = index.union_tolerant(kf.mask, kf.value, kf.mismatches)
        start = index.start[segs]
        out.append(post_segment(start, start + index.length[segs] - 1, index.doc[segs]))
    return out


def _intersect(
    a_start: IntArray, a_end: IntArray, b_start: IntArray, b_end: IntArray
) -> tuple[IntArray, IntArray, IntArray]:
    """Pieces of two unions of sorted disjoint intervals that overlap: (starts, ends, index into b),
    sorted."""
    lo = np.searchsorted(a_end, b_start, "left")  # first a ending at or after b's start
    hi = np.searchsorted(a_start, b_end, "right")  # a starting at or before b's end
    n = np.maximum(hi - lo, 0)
    jb = np.repeat(np.arange(len(b_start), dtype=np.int64), n)
    ia = concatenated_ranges(lo, n)
    return np.maximum(a_start[ia], b_start[jb]), np.minimum(a_end[ia], b_end[jb]), jb


def _union(start: IntArray, end: IntArray) -> tuple[IntArray, IntArray]:
    """Sorted disjoint intervals covering the same frames as intervals with ascending ``start``."""
    keep = start <= end
    start, end = start[keep], end[keep]
    if not len(start):
        return start, end
    reach = np.maximum.accumulate(end)
    new = np.ones(start.shape, dtype=bool)
    new[1:] = start[1:] > reach[:-1] + 1
    first = np.flatnonzero(new)
    last = np.concatenate([first[1:] - 1, [len(start) - 1]])
    return start[first], reach[last]


GlobalList = tuple[IntArray, IntArray, IntArray, IntArray]  # starts, ends, first and last of document


def _prune(lists: Sequence[GlobalList], bounds: Sequence[tuple[int, int | None]]) -> list[IntArray]:
    """For each list, the entries that contain the k-th frame of some hit (Def. 4.4). The frames that
    can be the k-th of a hit are computed for all documents at once: forward, the frames reachable
    from keyframe 1 (F_k = Λ_k ∩ (F_{k-1} + [dmin, dmax])), then backward, those of F_k from which
    the last keyframe is reachable. Every match consists of such entries only, so dropping the others
    leaves the set of matches unchanged."""
    start, end, first, last = lists[0]
    owner = [np.arange(len(start), dtype=np.int64)]  # list entry of each reachable piece
    reach = [(start, end, first, last)]
    for (dmin, dmax), (s, e, f, t) in zip(bounds, lists[1:], strict=True):
        ps, pe, _, pt = reach[-1]
        us, ue = _union(ps + dmin, pt if dmax is None else np.minimum(pe + dmax, pt))
        rs, re_, j = _intersect(us, ue, s, e)
        owner.append(j)
        reach.append((rs, re_, f[j], t[j]))
    keep = [np.unique(owner[-1])]
    back_s, back_e, back_f, _ = reach[-1]
    for k in range(len(lists) - 2, -1, -1):
        dmin, dmax = bounds[k]
        rs, re_, rf, _ = reach[k]
        us, ue = _union(back_f if dmax is None else np.maximum(back_s - dmax, back_f), back_e - dmin)
        back_s, back_e, j = _intersect(us, ue, rs, re_)
        back_f = rf[j]
        keep.append(np.unique(owner[k][j]))
    return keep[::-1]


def keyframe_search(
    sets: Mapping[FeatureSet, SetIndex],
    doc_frames: Sequence[int] | IntArray,
    query: KeyframeQuery,
    rate: float,
    extend: tuple[int, int] = (0, 0),
    prune: bool = True,
    max_gap: int | None = None,
) -> KeyframeHits:
    """Run ``query`` on a database indexed at ``rate`` Hz whose document d has ``doc_frames[d]``
    frames: the Ω^Z components in every document, each optionally extended by ``extend`` = (left,
    right) frames and merged again where the extensions overlap.

    The documents are laid out one after another with a one-frame gap, so that Alg. 4.1 runs once
    over all of them; its lists are first pruned to the entries that take part in some hit (``prune``;
    off, the algorithm runs on the whole lists as published: same result, slower). ``max_gap``: see
    :func:`query_bounds` (None: unbounded gaps stay unbounded, as published)."""
    bounds = query_bounds(query, rate, max_gap)
    lists = keyframe_lists(sets, query)
    frames = np.asarray(doc_frames, dtype=np.int64)
    base = np.concatenate([[0], np.cumsum(frames + 1)[:-1]]).astype(np.int64)
    global_lists = [(base[d] + s, base[d] + e, base[d], base[d] + frames[d] - 1) for s, e, d in lists]
    if prune and len(lists) > 1:
        keep = _prune(global_lists, bounds)
    else:
        keep = [np.arange(len(s)) for s, _, _ in lists]
    pruned = [tuple(a[k] for a in g) for g, k in zip(global_lists, keep, strict=True)]
    found = search(
        [(s.tolist(), e.tolist()) for s, e, _, _ in pruned], bounds, [t.tolist() for *_, t in pruned]
    )
    matches = np.asarray(found.matches, dtype=np.int64).reshape(-1, len(lists))
    first, last, ok = match_ranges([p[0] for p in pruned], [p[1] for p in pruned], matches, bounds)
    ranges = list(zip(first[ok].tolist(), last[ok].tolist(), strict=True))
    components = omega_z(ranges)
    # an extension past the whole layout reaches every document's first or last frame, as the layout's
    # length does: so cut, it cannot overflow int64
    layout = int(base[-1] + frames[-1]) if len(frames) else 0
    left, right = min(extend[0], layout), min(extend[1], layout)
    if left or right:
        # extended within the document (its first frame is base[d], its last base[d] + frames[d] - 1)
        d = np.searchsorted(base, [s for s, _ in components], "right") - 1
        s_ext = np.maximum(np.asarray([s for s, _ in components], dtype=np.int64) - left, base[d])
        e_ext = np.minimum(
            np.asarray([t for _, t in components], dtype=np.int64) + right, base[d] + frames[d] - 1
        )
        components = omega_z(list(zip(s_ext.tolist(), e_ext.tolist(), strict=True)))
    spans = np.asarray(components, dtype=np.int64).reshape(-1, 2)
    doc = np.searchsorted(base, spans[:, 0], "right") - 1
    start, end = spans[:, 0] - base[doc], spans[:, 1] - base[doc]
    return KeyframeHits(doc, start, end, tuple(len(s) for s, _, _ in lists), len(found.matches), found.calls)
