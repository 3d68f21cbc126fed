"""Dynamic time warping over feature sequences (thesis §3.2, Alg. 3.1/3.2; reference facts section d).

Rows are the template (length ``M``), columns the sequence or database (length ``N``); a cost matrix
has shape ``(M, N)``. Steps are the thesis' (1,0), (0,1), (1,1) (``"thesis"``) or the toolbox's
retrieval steps (1,1), (1,2), (2,1) with weights 1, 1, 2 (``"toolbox"``; the weight multiplies the
cell's cost after the smallest predecessor is chosen, reference facts section d). Ties go to the
diagonal, then the database step, then the template step, as in the toolbox.

Cell costs are rounded to multiples of 2^-24 and accumulated in int64 (:func:`fixed`). Sums are then
exact, so the row-by-row batch pass, the column-by-column stream and a cell-by-cell reference give
bit-identical accumulated costs and the same tie decisions, whatever order they add in. Costs must
lie in [0, 64]; ``inf`` or NaN marks a cell no path may use (e.g. between two documents). An
accumulated cost of 2^22 or more counts as unreachable.

Subsequence DTW (free start and end in the database) carries each cell's start column along with its
cost instead of storing the matrix for backtracking, so it needs O(N) memory in the batch pass and
O(M) in the stream.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from typing import Literal

import numpy as np
import numpy.typing as npt

from daemon import _dtw
from daemon.types import FloatArray, IntArray

Steps = Literal["thesis", "toolbox"]
STEPS: tuple[Steps, ...] = ("thesis", "toolbox")

SCALE = 1 << 24
MAX_COST = 64.0
INF = 1 << 46
_NO_START = -1


def fixed(cost: npt.ArrayLike) -> IntArray:
    """Costs (any shape) in fixed point: ``round(c * 2^24)``; ``inf``/NaN become :data:`INF`."""
    c = np.asarray(cost, dtype=np.float64)
    finite = np.isfinite(c)
    if np.any(c[~np.isnan(c)] < 0) or np.any(c[finite] > MAX_COST):
        raise ValueError(f"DTW cell costs must lie in [0, {MAX_COST:g}] (or be inf to block a cell)")
    return np.where(finite, np.rint(np.where(finite, c, 0.0) * SCALE), INF).astype(np.int64)


def threshold(tau: float) -> int:
    """A cost threshold (any τ >= 0, inf included) in fixed point; never admits an unreachable cell."""
    if not tau >= 0:
        raise ValueError(f"a cost threshold must be >= 0, got {tau!r}")
    return INF - 1 if tau * SCALE >= INF else round(tau * SCALE)


def _scan(f: IntArray, step: IntArray) -> IntArray:
    """``D(j) = min(f(j), D(j-1) + step(j))`` (clamped at :data:`INF`) as a min-plus prefix scan,
    ``D(j) = cum(j) + min_{k<=j} (f(k) - cum(k))``: exact in integers. A run holding too many
    blocked steps for int64 is split at a blocked step, where every chain breaks anyway."""
    blocked = np.flatnonzero(step >= INF)
    if len(blocked) < 1 << 15:
        cum = np.cumsum(step)
        return np.minimum(cum + np.minimum.accumulate(f - cum), INF)
    cut = int(blocked[len(blocked) // 2])
    head = _scan(f[:cut], step[:cut])
    tail_f = f[cut:].copy()
    tail_f[0] = min(int(tail_f[0]), INF)  # the chain from the head ends at the blocked step
    return np.concatenate([head, _scan(tail_f, np.concatenate([[0], step[cut + 1 :]]))])


def to_cost(d: IntArray | int) -> FloatArray:
    """Fixed-point accumulated costs back to floats, ``inf`` where unreachable."""
    a = np.asarray(d, dtype=np.int64)
    return np.where(a >= INF, np.inf, a / SCALE)


def check_steps(steps: str) -> Steps:
    if steps not in STEPS:
        raise ValueError(f"steps must be one of {', '.join(STEPS)}, got {steps!r}")
    return steps


# ------------------------------------------------------------------------------------ cost matrices


def and_cost(template: FloatArray, sequence: FloatArray) -> FloatArray:
    """c& of thesis eq. (3.2)/(3.3) between every template column and sequence column: the number of
    features on which both are 0/1 and differ (½ costs nothing). ``template`` is ``(f, M)``,
    ``sequence`` ``(f, N)``, both over {0, ½, 1}; result ``(M, N)``."""
    t = np.asarray(template, dtype=np.float64)
    s = np.asarray(sequence, dtype=np.float64)
    return np.asarray((t == 1).T.astype(np.float64) @ (s == 0) + (t == 0).T.astype(np.float64) @ (s == 1))


def l1_cost(template: FloatArray, sequence: FloatArray) -> FloatArray:
    """Mean absolute difference over the ``f`` features (the ℓ1 cost of soft-MT learning, thesis §3.3.3):
    ``(f, M)`` and ``(f, N)`` to ``(M, N)``."""
    t = np.asarray(template, dtype=np.float64).T
    s = np.asarray(sequence, dtype=np.float64).T
    return np.asarray(np.abs(t[:, None, :] - s[None, :, :]).mean(axis=2))


def weighted(cost: FloatArray, template_weights: FloatArray, sequence_weights: FloatArray) -> FloatArray:
    """``cost`` times ``(w_a + w_b) / 2`` (reference facts section d)."""
    wa = np.asarray(template_weights, dtype=np.float64)
    wb = np.asarray(sequence_weights, dtype=np.float64)
    return np.asarray(cost * ((wa[:, None] + wb[None, :]) / 2))


def retrieval_factors(template: FloatArray, weights: FloatArray) -> FloatArray:
    """Per template column ``a`` of an ``(f, M)`` {0, ½, 1} template: ``(w_a + 1) / (2 M max(1, n_a))``
    with ``n_a`` its non-½ entries, the factor of the toolbox's retrieval cost (reference facts
    section d; database weights 1)."""
    t = np.asarray(template, dtype=np.float64)
    fixed_entries = np.count_nonzero(t != 0.5, axis=0)
    return np.asarray(
        (np.asarray(weights, dtype=np.float64) + 1) / (2 * t.shape[1] * np.maximum(1, fixed_entries))
    )


def retrieval_cost(template: FloatArray, weights: FloatArray, frames: FloatArray) -> FloatArray:
    """The retrieval cost ``(M, N)`` of an ``(f, M)`` quantised template with weights ``(M,)`` against
    ``(f, N)`` frames: c& (eq. 3.2) divided by M and by the column's number of 0/1 entries, times the
    mean of the two weights: each column costs at most about 1/M, so a path's cost is a mean."""
    return np.asarray(and_cost(template, frames) * retrieval_factors(template, weights)[:, None])


def pack(frames: npt.NDArray[np.bool_]) -> npt.NDArray[np.uint64]:
    """``(N, f)`` boolean frames (f <= 64) as ``(N,)`` codes, bit i = feature i."""
    f = np.asarray(frames, dtype=bool)
    if f.ndim != 2 or f.shape[1] > 64:
        raise ValueError(f"expected (N, f <= 64) boolean frames, got shape {f.shape}")
    return np.asarray(
        (f.astype(np.uint64) << np.arange(f.shape[1], dtype=np.uint64)).sum(axis=1, dtype=np.uint64)
    )


@dataclass(frozen=True)
class RetrievalTables:
    """:func:`retrieval_cost` of a template against packed frames, prepared: per template column its
    fixed bits (``masks``, ``(M,)``), their values (``values``, ``(M,)``) and the fixed-point cost of
    0..f differing bits (``tables``, ``(M, f + 1)``)."""

    masks: npt.NDArray[np.uint64]
    values: npt.NDArray[np.uint64]
    tables: IntArray


def retrieval_tables(template: FloatArray, weights: FloatArray) -> RetrievalTables:
    """The :class:`RetrievalTables` of an ``(f, M)`` quantised template (f <= 64) with weights ``(M,)``."""
    t = np.asarray(template, dtype=np.float64)
    f = t.shape[0]
    bit = np.uint64(1) << np.arange(f, dtype=np.uint64)
    masks = ((t != 0.5).T.astype(np.uint64) * bit).sum(axis=1, dtype=np.uint64)
    values = ((t == 1).T.astype(np.uint64) * bit).sum(axis=1, dtype=np.uint64)
    counts = np.arange(f + 1, dtype=np.float64)
    tables = np.stack([fixed(counts * factor) for factor in retrieval_factors(t, weights)])
    return RetrievalTables(masks, values, tables)


def retrieval_rows(
    template: FloatArray,
    weights: FloatArray,
    codes: npt.NDArray[np.uint64],
    blocked: npt.NDArray[np.bool_] | None = None,
) -> Iterator[IntArray]:
    """The fixed-point rows of :func:`retrieval_cost` against packed frames (:func:`pack`), one
    template column at a time (popcount of the differing fixed bits, then a table of the f + 1
    possible costs); ``blocked`` columns (e.g. between documents) get :data:`INF`. Equal to
    ``fixed(retrieval_cost(...))`` row by row."""
    t = retrieval_tables(template, weights)
    for mask, value, table in zip(t.masks, t.values, t.tables, strict=True):
        row = table[np.bitwise_count((codes ^ value) & mask)]
        if blocked is not None:
            row[blocked] = INF
        yield row


def retrieval_matrix(t: RetrievalTables, codes: npt.NDArray[np.uint64]) -> IntArray:
    """All rows of :func:`retrieval_rows` at once, shape ``(M, N)``, from prepared tables (for many
    short stretches of frames, where a Python loop per row would cost more than the rows)."""
    differing = np.bitwise_count((codes[None, :] ^ t.values[:, None]) & t.masks[:, None]).astype(np.intp)
    out: IntArray = np.take_along_axis(t.tables, differing, axis=1)
    return out


# -------------------------------------------------------------------------------------- full DTW


@dataclass(frozen=True)
class Alignment:
    """A full DTW: cost ``D(M-1, N-1)`` and the optimal warping path, ``(L, 2)`` pairs (template row,
    sequence column), 0-based, from (0, 0) to (M-1, N-1) (Def. 3.1)."""

    cost: float
    path: IntArray


def accumulated(cost: IntArray) -> IntArray:
    """Alg. 3.1: the accumulated cost matrix ``(M, N)`` of a fixed-point cost matrix, steps (1,0),
    (0,1), (1,1), D(0,0) = C(0,0), first row and column accumulated (compiled,
    :func:`daemon._dtw.accumulated`; :func:`accumulated_rows` is the same row by row in numpy)."""
    return _dtw.accumulated(np.ascontiguousarray(cost, dtype=np.int64))


def accumulated_rows(cost: IntArray) -> IntArray:
    """:func:`accumulated` one row at a time: the diagonal and template steps from the row before,
    the database step a min-plus prefix scan along the row."""
    m, n = cost.shape
    out = np.empty((m, n), dtype=np.int64)
    first = np.full(n, INF, dtype=np.int64)
    first[0] = cost[0, 0]
    out[0] = _scan(first, np.concatenate([[0], cost[0, 1:]]))
    for i in range(1, m):
        out[i] = _thesis_row(out[i - 1], np.zeros(n, dtype=np.int64), cost[i], seeds=0)[0]
    return out


def warping_path(d: IntArray) -> IntArray:
    """Alg. 3.2: backtrack from (M-1, N-1), preferring the diagonal, then (i, j-1), then (i-1, j)."""
    i, j = d.shape[0] - 1, d.shape[1] - 1
    path = [(i, j)]
    while i > 0 or j > 0:
        if i == 0:
            j -= 1
        elif j == 0:
            i -= 1
        else:
            diag, left, down = d[i - 1, j - 1], d[i, j - 1], d[i - 1, j]
            if diag <= left and diag <= down:
                i, j = i - 1, j - 1
            elif left <= down:
                j -= 1
            else:
                i -= 1
        path.append((i, j))
    return np.asarray(path[::-1], dtype=np.int64).reshape(-1, 2)


def full_dtw(cost: FloatArray) -> Alignment:
    """DTW distance (Def. 3.3) and optimal warping path for an ``(M, N)`` cost matrix."""
    c = fixed(cost)
    if c.ndim != 2 or 0 in c.shape:
        raise ValueError(f"a DTW cost matrix must be 2-D and non-empty, got shape {c.shape}")
    d = accumulated(c)
    return Alignment(float(to_cost(d[-1, -1])), warping_path(d))


# ----------------------------------------------------------------- one row / column of the recursion


def _thesis_row(
    prev: IntArray, prev_start: IntArray, c: IntArray, seeds: int
) -> tuple[IntArray, IntArray, npt.NDArray[np.bool_]]:
    """Row ``i`` of the thesis recursion from row ``i-1`` (``prev``), vectorised along the row: the
    diagonal and template steps come from ``prev``; the database step inside the row is a min-plus
    prefix scan, ``D(j) = cum(j) + min_{k<=j} (F(k) - cum(k))``, exact in integers. The first
    ``seeds`` entries of the row are given (``c`` holds their values, not costs). Returns the row,
    the start each cell inherits from row ``i-1`` and where it does (elsewhere it continues the row)."""
    n = len(c)
    diag = np.full(n, INF, dtype=np.int64)
    diag[1:] = prev[:-1]
    e_diag = np.minimum(diag + c, INF)
    e_down = np.minimum(prev + c, INF)
    f = np.minimum(e_diag, e_down)
    step = c.copy()
    if seeds:
        f[:seeds] = c[:seeds]
        step[:seeds] = 0
    row = _scan(f, step)
    left = np.full(n, INF, dtype=np.int64)
    left[1:] = np.minimum(row[:-1] + c[1:], INF)
    from_diag = e_diag == row
    from_down = ~from_diag & (left != row)
    src = np.where(from_diag, np.concatenate([[_NO_START], prev_start[:-1]]), prev_start)
    return row, src, from_diag | from_down


def _forward_fill(values: IntArray, is_set: npt.NDArray[np.bool_]) -> IntArray:
    idx = np.maximum.accumulate(np.where(is_set, np.arange(len(values)), 0))
    return values[idx]


def _thesis_row_starts(
    prev: IntArray, prev_start: IntArray, c: IntArray, seeds: int, seed_start: IntArray | None
) -> tuple[IntArray, IntArray]:
    row, src, is_set = _thesis_row(prev, prev_start, c, seeds)
    if seeds:
        assert seed_start is not None
        src[:seeds] = seed_start
        is_set[:seeds] = True
    start = _forward_fill(src, is_set)
    return row, np.where(row >= INF, _NO_START, start)


def _toolbox_cell(
    p1: IntArray, s1: IntArray, p2: IntArray, s2: IntArray, p3: IntArray, s3: IntArray, c: IntArray
) -> tuple[IntArray, IntArray]:
    """D = min(p1, p2, p3) + w·c with the predecessors of steps (1,1), (1,2), (2,1) (weights 1, 1, 2);
    ties in that order; unreachable stays unreachable."""
    one = (p1 <= p2) & (p1 <= p3)
    two = ~one & (p2 <= p3)
    best = np.where(one, p1, np.where(two, p2, p3))
    weight = np.where(one | two, 1, 2)
    d = np.where(best >= INF, INF, np.minimum(best + weight * c, INF))
    s = np.where(d >= INF, _NO_START, np.where(one, s1, np.where(two, s2, s3)))
    return d, s


def _shift(a: IntArray, k: int, fill: int) -> IntArray:
    out = np.full(len(a), fill, dtype=np.int64)
    if k < len(a):
        out[k:] = a[: len(a) - k]
    return out


# ---------------------------------------------------------------------------- subsequence DTW (batch)


@dataclass(frozen=True)
class Subsequence:
    """Subsequence DTW: Δ(b) = D(M-1, b), the cost of the best path ending at database column ``b``
    (``inf`` if none), and the column where that path starts; both ``(N,)``."""

    delta: FloatArray
    start: IntArray


def _subsequence_rows(
    rows: Iterable[IntArray], steps: Steps, seed: tuple[IntArray, IntArray] | None = None, first: int = 0
) -> Iterator[tuple[IntArray, IntArray]]:
    """Every row (D, start) of the subsequence recursion, row by row; the cost rows start at database
    column ``first``. ``seed`` = (D, start) ``(M, k)`` of the ``k`` columns before it, whose values
    are given (the stream's state after a reset)."""
    k = 0 if seed is None else seed[0].shape[1]
    prev: list[tuple[IntArray, IntArray]] = []
    for i, c_row in enumerate(rows):
        c = np.asarray(c_row, dtype=np.int64)
        n = len(c) + k
        cols = np.arange(first - k, first + n - k, dtype=np.int64)
        if k:
            assert seed is not None
            full_c = np.concatenate([seed[0][i], c])
        else:
            full_c = c
        if i == 0:
            d = full_c.copy()
            s = cols.copy()
            if k:
                assert seed is not None
                s[:k] = seed[1][0]
            s = np.where(d >= INF, _NO_START, s)
        elif steps == "thesis":
            d, s = _thesis_row_starts(
                prev[-1][0], prev[-1][1], full_c, k, None if seed is None else seed[1][i]
            )
        else:
            cc = np.concatenate([np.zeros(k, dtype=np.int64), c])
            p1, s1 = _shift(prev[-1][0], 1, INF), _shift(prev[-1][1], 1, _NO_START)
            p2, s2 = _shift(prev[-1][0], 2, INF), _shift(prev[-1][1], 2, _NO_START)
            if i >= 2:
                p3, s3 = _shift(prev[-2][0], 1, INF), _shift(prev[-2][1], 1, _NO_START)
            else:
                p3, s3 = np.full(n, INF, dtype=np.int64), np.full(n, _NO_START, dtype=np.int64)
            d, s = _toolbox_cell(p1, s1, p2, s2, p3, s3, cc)
            if k:
                assert seed is not None
                d[:k], s[:k] = seed[0][i], seed[1][i]
        prev = [*prev[-1:], (d, s)]
        yield d, s


def subsequence_fixed(rows: Iterable[IntArray], steps: Steps = "thesis") -> tuple[IntArray, IntArray]:
    """Δ and starts in fixed point from the template's cost rows (fixed point, each ``(N,)``), one row
    at a time, so the rows may be computed lazily: memory O(N)."""
    last = deque(_subsequence_rows(rows, check_steps(steps)), maxlen=1)  # earlier rows are dropped
    if not last:
        raise ValueError("a template needs at least one column")
    return last[0]


def subsequence_codes(
    t: RetrievalTables,
    codes: npt.NDArray[np.uint64],
    blocked: npt.NDArray[np.bool_] | None = None,
    steps: Steps = "thesis",
) -> tuple[IntArray, IntArray]:
    """:func:`subsequence_fixed` of :func:`retrieval_rows` (Δ and starts ``(N,)`` in fixed point) of a
    template's prepared tables against packed frames ``codes`` ``(N,)``, ``blocked`` columns
    unreachable, computed cell by cell in compiled code (:mod:`daemon._dtw`): the same integers, at
    C speed and in O(M) memory."""
    c = np.ascontiguousarray(codes, dtype=np.uint64)
    b = np.zeros(len(c), dtype=np.uint8) if blocked is None else np.ascontiguousarray(blocked, dtype=np.uint8)
    return _dtw.subsequence_codes(t.masks, t.values, t.tables, c, b, check_steps(steps) == "toolbox")


def subsequence_minima(
    t: RetrievalTables, codes: npt.NDArray[np.uint64], tau: float, steps: Steps = "thesis"
) -> list[Match]:
    """:func:`local_minima` at or below ``tau`` of :func:`subsequence_codes` over ``codes``, found in
    the compiled pass (the comparisons in fixed point, which order as the costs do)."""
    c = np.ascontiguousarray(codes, dtype=np.uint64)
    found = _dtw.minima_codes(
        t.masks,
        t.values,
        t.tables,
        c,
        np.zeros(len(c), dtype=np.uint8),
        check_steps(steps) == "toolbox",
        threshold(tau),
    )
    return [Match(s, e, d / SCALE) for s, e, d in found]


def subsequence_dtw(cost: FloatArray, steps: Steps = "thesis") -> Subsequence:
    """Subsequence DTW of an ``(M, N)`` cost matrix: D(0, b) = C(0, b) (free start), free end."""
    delta, start = subsequence_fixed(iter(fixed(cost)), steps)
    return Subsequence(to_cost(delta), start)


@dataclass(frozen=True)
class Match:
    """A subsequence ``start..end`` (database columns, inclusive) and its DTW cost."""

    start: int
    end: int
    cost: float


def local_minima(delta: FloatArray, start: IntArray, tau: float) -> list[Match]:
    """Every local minimum of Δ at or below ``tau`` (Δ(b) < Δ(b-1) and Δ(b) <= Δ(b+1): the first
    column of a plateau), with its start."""
    d = np.asarray(delta, dtype=np.float64)
    if d.size == 0:
        return []
    left = np.concatenate([[np.inf], d[:-1]])
    right = np.concatenate([d[1:], [np.inf]])
    at = np.flatnonzero((d <= tau) & (d < left) & (d <= right))
    return [Match(int(start[b]), int(b), float(d[b])) for b in at]


def suppress(candidates: Iterable[Match], limit: int | None = None) -> list[Match]:
    """Non-maximum suppression as the toolbox's retrieval does it (reference facts section d): take
    candidates by increasing cost (then end); one whose end lies in an end-exclusion zone is dropped;
    one whose start lies in a start-exclusion zone of a kept hit is dropped and masks ends with that
    hit's length; a kept hit of length L masks starts in [s - ⌈0.1L⌉, s + ⌈0.5L⌉]; both mask ends in
    [e - ⌈0.5L⌉, e + ⌈0.1L⌉]. Returns kept hits by increasing cost, at most ``limit``."""
    kept: list[Match] = []
    start_zones: list[tuple[int, int, int]] = []
    end_zones: list[tuple[int, int]] = []
    for m in sorted(candidates, key=lambda m: (m.cost, m.end)):
        if limit is not None and len(kept) >= limit:
            break
        if any(lo <= m.end <= hi for lo, hi in end_zones):
            continue
        zone = next((length for lo, hi, length in start_zones if lo <= m.start <= hi), None)
        if zone is None:
            length = m.end - m.start + 1
            kept.append(m)
            start_zones.append((m.start - math.ceil(0.1 * length), m.start + math.ceil(0.5 * length), length))
        else:
            length = zone
        end_zones.append((m.end - math.ceil(0.5 * length), m.end + math.ceil(0.1 * length)))
    return kept


def subsequence_matches(
    cost: FloatArray, tau: float, steps: Steps = "thesis", limit: int | None = None
) -> list[Match]:
    """Hits of a subsequence DTW: local minima of Δ at or below ``tau``, non-maximum suppressed."""
    sub = subsequence_dtw(cost, steps)
    return suppress(local_minima(sub.delta, sub.start, tau), limit)


# ------------------------------------------------------------------------ disjoint matches (SPRING)


def _kill(d: IntArray, s: IntArray, end: int) -> tuple[IntArray, IntArray]:
    """Drop the paths that start at or before ``end`` (they overlap a reported match)."""
    gone = s <= end
    return np.where(gone, INF, d), np.where(gone, _NO_START, s)


class SubsequenceStream:
    """Streaming subsequence DTW with SPRING's disjoint-match rule (Sakurai et al., ICDE 2007).

    ``push(column)`` takes the template's ``(M,)`` costs against the next database frame, updates one
    column of D and of the start columns in O(M) time and memory (two columns for the toolbox steps)
    and returns the matches it reports (a list of at most one). The best path ending at or below
    ``tau`` is held as a candidate; it is reported once every path still alive either costs at least
    as much or starts after the candidate ends, so no later frame can improve on it or overlap it;
    then paths overlapping it are dropped. :meth:`flush` reports a pending candidate at the end of the
    stream (in a list) and starts over. :func:`disjoint_matches` is the batch twin."""

    def __init__(self, m: int, tau: float, steps: Steps = "thesis") -> None:
        if m < 1:
            raise ValueError("a template needs at least one column")
        self.m = m
        self.steps = check_steps(steps)
        self.tau = threshold(tau)
        self._t = 0
        self._cols: list[tuple[IntArray, IntArray]] = []
        self._cand: tuple[int, int, int] | None = None

    def push(self, column: FloatArray) -> list[Match]:
        c = fixed(column)
        if c.shape != (self.m,):
            raise ValueError(f"expected {self.m} template costs, got shape {c.shape}")
        d, s = self._column(c)
        # the live columns: paths continue from the last one (thesis) or the last two (toolbox)
        self._cols = [*(self._cols[-1:] if self.steps == "toolbox" else []), (d, s)]
        out = []
        if self._cand is not None:
            dmin, ts, te = self._cand
            if all(bool(np.all((dd >= dmin) | (ss > te))) for dd, ss in self._cols):
                out.append(Match(ts, te, float(to_cost(dmin))))
                self._cand = None
                self._cols = [
                    (np.where(ss <= te, INF, dd), np.where(ss <= te, _NO_START, ss)) for dd, ss in self._cols
                ]
        last = int(self._cols[-1][0][-1])
        if last <= self.tau and (self._cand is None or last < self._cand[0]):
            self._cand = (last, int(self._cols[-1][1][-1]), self._t)
        self._t += 1
        return out

    def flush(self) -> list[Match]:
        out = (
            [] if self._cand is None else [Match(self._cand[1], self._cand[2], float(to_cost(self._cand[0])))]
        )
        self._t, self._cols, self._cand = 0, [], None
        return out

    def _column(self, c: IntArray) -> tuple[IntArray, IntArray]:
        m, t = self.m, self._t
        none_d = np.full(m, INF, dtype=np.int64)
        none_s = np.full(m, _NO_START, dtype=np.int64)
        p1d, p1s = self._cols[-1] if self._cols else (none_d, none_s)
        if self.steps == "thesis":
            # the column is the recursion with the roles of the axes swapped: the template step is
            # the scan, the database step comes from the previous column
            e_diag = np.minimum(np.concatenate([[INF], p1d[:-1]]) + c, INF)
            e_left = np.minimum(p1d + c, INF)
            f = np.minimum(e_diag, e_left)
            f[0] = c[0]
            step = c.copy()
            step[0] = 0
            d = _scan(f, step)
            from_diag = e_diag == d
            from_left = ~from_diag & (e_left == d)
            src = np.where(from_diag, np.concatenate([[_NO_START], p1s[:-1]]), p1s)
            is_set = from_diag | from_left
            src[0], is_set[0] = t, True
            s = _forward_fill(src, is_set)
            return d, np.where(d >= INF, _NO_START, s)
        p2d, p2s = self._cols[-2] if len(self._cols) > 1 else (none_d, none_s)
        d, s = _toolbox_cell(
            _shift(p1d, 1, INF),
            _shift(p1s, 1, _NO_START),
            _shift(p2d, 1, INF),
            _shift(p2s, 1, _NO_START),
            _shift(p1d, 2, INF),
            _shift(p1s, 2, _NO_START),
            c,
        )
        d[0], s[0] = c[0], (t if c[0] < INF else _NO_START)
        return d, s


def disjoint_matches(cost: FloatArray, tau: float, steps: Steps = "thesis") -> list[Match]:
    """The batch twin of :class:`SubsequenceStream`: the same matches from the ``(M, N)`` cost matrix,
    with D and the starts computed row by row over all remaining columns, and the report rule checked
    for every column at once; after a report the recursion restarts from the reset columns. Memory
    O(M·N)."""
    c = fixed(cost)
    steps = check_steps(steps)
    width = 1 if steps == "thesis" else 2
    tau_f = threshold(tau)
    n = c.shape[1]

    def matrices(first: int, seed: tuple[IntArray, IntArray] | None) -> tuple[IntArray, IntArray]:
        rows = list(_subsequence_rows(iter(c[:, first:]), steps, seed, first))
        return np.stack([d for d, _ in rows]), np.stack([s for _, s in rows])

    out: list[Match] = []
    d, s = matrices(0, None)
    offset = 0  # database column of d[:, 0]
    cand: tuple[int, int, int] | None = None
    t = 0
    while t < n:
        j = t - offset
        if cand is None:
            hit = np.flatnonzero(d[-1, j:] <= tau_f)
            if not hit.size:
                break
            t += int(hit[0])
            cand = (int(d[-1, t - offset]), int(s[-1, t - offset]), t)
            t += 1
            continue
        dmin, ts, te = cand
        column_ok = np.all((d[:, j - width + 1 :] >= dmin) | (s[:, j - width + 1 :] > te), axis=0)
        ok = column_ok[width - 1 :]
        if width == 2:
            ok = ok & column_ok[:-1]
        event = np.flatnonzero(ok | (d[-1, j:] < dmin))
        if not event.size:
            break
        t += int(event[0])
        j = t - offset
        if ok[event[0]]:
            out.append(Match(ts, te, float(to_cost(dmin))))
            cand = None
            live = slice(j - width + 1, j + 1)
            seed = _kill(d[:, live], s[:, live], te)
            if t + 1 < n:
                d, s = matrices(t + 1, seed)
            else:
                d, s = seed
            offset = t - width + 1
            j = t - offset
            if d[-1, j] <= tau_f:
                cand = (int(d[-1, j]), int(s[-1, j]), t)
        else:
            cand = (int(d[-1, j]), int(s[-1, j]), t)
        t += 1
    if cand is not None:
        out.append(Match(cand[1], cand[2], float(to_cost(cand[0]))))
    return out
