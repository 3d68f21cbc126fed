"""Ranked retrieval with motion templates (thesis §3.4 and §5, the two-step retrieval).

The database is the index itself: its segments give every frame's 39 features (the lower, upper and
mix codes side by side in one 64-bit code, bit i = feature i), so no second copy of the features is
stored. A class's quantised soft MT, expanded by its weights (toolbox ``expandV = 1``), is matched by
subsequence DTW (:mod:`daemon.dtw`, retrieval cost of reference facts section d) over every
document, or only over the ranges a keyframe search kept; two blocked columns separate the pieces
so that no path crosses from one into the next (also with the (1,2)/(2,1) steps). Hits are the local
minima of Δ at or below τ after the toolbox's non-maximum suppression, applied within each piece (a hit
never suppresses one in another document), ranked by cost.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from daemon.dtw import Match, Steps, local_minima, retrieval_tables, subsequence_codes, suppress, to_cost
from daemon.features import SET_SLICES
from daemon.keyframes import KeyframeQuery
from daemon.search.index import concatenated_ranges
from daemon.search.keyframes import KeyframeHits, keyframe_search
from daemon.search.store import MotionIndex
from daemon.templates import MotionTemplate, expand
from daemon.types import FEATURE_SETS, CodeArray, FloatArray, IntArray

SEPARATOR = 2
PIECES_PER_PASS = 1 << 14  # keeps the fixed-point row sums far from int64 overflow (dtw.INF)
EXTENSION = 1.5


@dataclass(frozen=True)
class TemplateHits:
    """Hits ranked by cost: ``doc``, ``start``, ``end`` (inclusive index-rate frames) and ``cost``,
    each ``(H,)``. ``searched``: database frames the DTW ran over; ``keyframes``: the pre-selection,
    if one ran."""

    doc: IntArray
    start: IntArray
    end: IntArray
    cost: FloatArray
    searched: int
    keyframes: KeyframeHits | None

    def __len__(self) -> int:
        return int(self.doc.shape[0])


def frame_codes(index: MotionIndex) -> CodeArray:
    """Every index-rate frame's 39 features as a code, documents one after another: ``(n_frames,)``."""
    out = np.zeros(index.n_frames, dtype=np.uint64)
    for s in FEATURE_SETS:
        si = index.sets[s]
        order = np.lexsort((si.start, si.doc))
        codes = np.repeat(si.code[order].astype(np.uint64), si.length[order])
        out |= codes << np.uint64(SET_SLICES[s].start)
    return out


def keyframe_extension(query: KeyframeQuery, template_length: int, rate: float) -> tuple[int, int]:
    """How far a keyframe range is widened before ranking, in frames at ``rate``: the template's
    columns before the first keyframe and after the last, times 1.5 for slower performances, so the
    whole motion and not just its keyframe span can be matched."""
    first = query.keyframes[0].position
    last = query.keyframes[-1].position
    scale = rate / query.rate * EXTENSION
    return math.ceil(max(0, first) * scale), math.ceil(max(0, template_length - 1 - last) * scale)


def template_search(
    index: MotionIndex,
    template: MotionTemplate,
    *,
    tau: float,
    steps: Steps = "thesis",
    keyframes: KeyframeQuery | None = None,
    extend: tuple[int, int] | None = None,
    limit: int | None = None,
    codes: CodeArray | None = None,
) -> TemplateHits:
    """Subsequence DTW of the quantised ``template`` (at the index rate) over ``index``: over every
    document, or with ``keyframes`` only over the ranges the keyframe search keeps, widened by
    ``extend`` = (left, right) frames (default :func:`keyframe_extension`). At most ``limit`` hits.
    ``codes``: :func:`frame_codes` of the index, if already at hand."""
    frames = np.asarray([d.frames for d in index.documents], dtype=np.int64)
    found = None
    if keyframes is None:
        doc = np.arange(len(frames), dtype=np.int64)
        start, end = np.zeros(len(frames), dtype=np.int64), frames - 1
    else:
        if extend is None:
            extend = keyframe_extension(keyframes, template.length, index.rate)
        found = keyframe_search(index.sets, frames, keyframes, index.rate, extend=extend)
        doc, start, end = found.doc, found.start, found.end
    all_codes = frame_codes(index) if codes is None else codes
    base = np.concatenate([[0], np.cumsum(frames)[:-1]]).astype(np.int64)
    t = expand(template)
    tables = retrieval_tables(t.values, t.weights)
    found_hits: list[tuple[float, int, int, int]] = []  # cost, doc, start, end
    for p in range(0, len(doc), PIECES_PER_PASS):
        piece = slice(p, p + PIECES_PER_PASS)
        sizes = end[piece] - start[piece] + 1
        # each piece followed by SEPARATOR blocked columns
        offsets = np.concatenate([[0], np.cumsum(sizes + SEPARATOR)]).astype(np.int64)
        columns = concatenated_ranges(offsets[:-1], sizes)
        db = np.zeros(int(offsets[-1]), dtype=np.uint64)
        db[columns] = all_codes[concatenated_ranges(base[doc[piece]] + start[piece], sizes)]
        blocked = np.ones(len(db), dtype=bool)
        blocked[columns] = False
        delta, first = subsequence_codes(tables, db, blocked, steps)
        by_piece: dict[int, list[Match]] = {}
        for m in local_minima(to_cost(delta), first, tau):
            by_piece.setdefault(int(np.searchsorted(offsets, m.end, "right")) - 1, []).append(m)
        # hits in different pieces never suppress each other
        for r, candidates in by_piece.items():
            shift = int(start[p + r] - offsets[r])
            for m in suppress(candidates, limit):
                found_hits.append((m.cost, int(doc[p + r]), m.start + shift, m.end + shift))
    found_hits.sort()
    found_hits = found_hits[:limit]
    table = np.asarray(found_hits, dtype=np.float64).reshape(-1, 4)
    return TemplateHits(
        table[:, 1].astype(np.int64),
        table[:, 2].astype(np.int64),
        table[:, 3].astype(np.int64),
        table[:, 0],
        int((end - start + 1).sum()),
        found,
    )
