# cython: language_level=3, boundscheck=False, wraparound=False, initializedcheck=False, cdivision=True
"""Compiled subsequence DTW of a quantised template against packed frame codes (see daemon/dtw.py).

The recursion of :func:`daemon.dtw.subsequence_fixed` cell by cell, column by column, on the same
int64 fixed-point costs with the same tie order, so the results are the same integers; the cell
costs come from the template's retrieval tables (popcount of the differing fixed bits)."""

from cpython.mem cimport PyMem_Free, PyMem_Malloc
from libc.stdint cimport int64_t, uint64_t

import numpy as np

cdef extern from *:
    int popcount "__builtin_popcountll"(unsigned long long) nogil

cdef int64_t INF = (<int64_t>1) << 46
cdef int64_t NO_START = -1


cdef inline int64_t clamp(int64_t x) noexcept nogil:
    return INF if x > INF else x


cdef inline int64_t _toolbox_cell(
    int64_t c,
    Py_ssize_t i,
    const int64_t *p1_d,
    const int64_t *p1_s,
    const int64_t *p2_d,
    const int64_t *p2_s,
    int64_t *start,
) noexcept nogil:
    """Cell ``i`` (>= 1) of a column with the toolbox's steps (1,1), (1,2), (2,1), weights 1, 1, 2,
    from the two columns before, its cell cost ``c``: D, and its start column in ``start``."""
    cdef int64_t a1 = p1_d[i - 1]  # (i-1, j-1)
    cdef int64_t a2 = p2_d[i - 1]  # (i-1, j-2)
    cdef int64_t a3 = p1_d[i - 2] if i >= 2 else INF  # (i-2, j-1)
    if a1 <= a2 and a1 <= a3:
        start[0] = p1_s[i - 1]
        return clamp(a1 + c)
    if a2 <= a3:
        start[0] = p2_s[i - 1]
        return clamp(a2 + c)
    start[0] = p1_s[i - 2]
    return clamp(a3 + 2 * c)


cdef inline void _column(
    const uint64_t *masks,
    const uint64_t *values,
    const int64_t *tab,
    Py_ssize_t width,
    Py_ssize_t m,
    uint64_t code,
    bint blk,
    bint toolbox,
    Py_ssize_t j,
    int64_t *cur_c,
    int64_t *cur_d,
    int64_t *cur_s,
    const int64_t *p1_d,
    const int64_t *p1_s,
    const int64_t *p2_d,
    const int64_t *p2_s,
) noexcept nogil:
    """Column ``j`` of D and its cells' start columns (``cur_d``, ``cur_s``) from the two before."""
    cdef Py_ssize_t i
    cdef int64_t c, d, s, e_diag, e_left, e_down
    for i in range(m):
        cur_c[i] = INF if blk else tab[i * width + popcount((code ^ values[i]) & masks[i])]
    d = cur_c[0]
    cur_d[0] = d
    cur_s[0] = j if d < INF else NO_START
    if toolbox:
        for i in range(1, m):
            d = _toolbox_cell(cur_c[i], i, p1_d, p1_s, p2_d, p2_s, &s)
            if d >= INF:
                d = INF
                s = NO_START
            cur_d[i] = d
            cur_s[i] = s
    else:
        for i in range(1, m):
            c = cur_c[i]
            e_diag = clamp(p1_d[i - 1] + c)  # (i-1, j-1)
            e_left = clamp(p1_d[i] + c)  # (i, j-1): the database step
            e_down = clamp(cur_d[i - 1] + c)  # (i-1, j): the template step
            d = e_diag
            if e_left < d:
                d = e_left
            if e_down < d:
                d = e_down
            if d >= INF:
                s = NO_START
            elif e_diag == d:
                s = p1_s[i - 1]
            elif e_left == d:
                s = p1_s[i]
            else:
                s = cur_s[i - 1]
            cur_d[i] = d
            cur_s[i] = s


cdef inline Py_ssize_t _pruned_column(
    const uint64_t *masks,
    const uint64_t *values,
    const int64_t *tab,
    Py_ssize_t width,
    Py_ssize_t m,
    uint64_t code,
    Py_ssize_t j,
    int64_t limit,
    Py_ssize_t hi1,
    Py_ssize_t hi2,
    int64_t *cur_d,
    int64_t *cur_s,
    const int64_t *p1_d,
    const int64_t *p1_s,
    const int64_t *p2_d,
    const int64_t *p2_s,
) noexcept nogil:
    """:func:`_column` with the toolbox's steps for a caller that needs only the cells at most
    ``limit``: a cell above it is :data:`INF` (costs are never negative, so no path through it ends
    at or below ``limit``; every cell at or below it, and its start, is exactly :func:`_column`'s).
    Only rows a finite cell can reach are computed: up to ``hi1 + 2`` and ``hi2 + 1``, the highest
    finite rows of the two columns before; the three rows above those computed are written
    :data:`INF` (what the next two columns may read). Returns this column's highest finite row (-1:
    none)."""
    cdef Py_ssize_t i, hi = -1, top = hi1 + 2 if hi1 + 2 > hi2 + 1 else hi2 + 1
    cdef int64_t c, d, s
    if top > m - 1:
        top = m - 1
    d = tab[popcount((code ^ values[0]) & masks[0])]
    if d > limit:
        cur_d[0] = INF
        cur_s[0] = NO_START
    else:
        cur_d[0] = d
        cur_s[0] = j
        hi = 0
    for i in range(1, top + 1):
        c = tab[i * width + popcount((code ^ values[i]) & masks[i])]
        d = _toolbox_cell(c, i, p1_d, p1_s, p2_d, p2_s, &s)
        if d > limit:
            d = INF
            s = NO_START
        else:
            hi = i
        cur_d[i] = d
        cur_s[i] = s
    for i in range(top + 1, min(m, top + 4)):
        cur_d[i] = INF
        cur_s[i] = NO_START
    return hi


cdef void _subsequence(
    const uint64_t[::1] masks,
    const uint64_t[::1] values,
    const int64_t[:, ::1] tables,
    const uint64_t[::1] codes,
    const unsigned char[::1] blocked,
    bint toolbox,
    int64_t[::1] delta,
    int64_t[::1] start,
    int64_t[:, ::1] b,
) noexcept nogil:
    cdef Py_ssize_t m = masks.shape[0], n = codes.shape[0], i, j
    cdef int64_t *cur_d = &b[0, 0]
    cdef int64_t *cur_s = &b[1, 0]
    cdef int64_t *p1_d = &b[2, 0]
    cdef int64_t *p1_s = &b[3, 0]
    cdef int64_t *p2_d = &b[4, 0]
    cdef int64_t *p2_s = &b[5, 0]
    cdef int64_t *cur_c = &b[6, 0]
    cdef int64_t *tmp
    for i in range(m):
        p1_d[i] = INF
        p1_s[i] = NO_START
        p2_d[i] = INF
        p2_s[i] = NO_START
    for j in range(n):
        _column(&masks[0], &values[0], &tables[0, 0], tables.shape[1], m, codes[j], blocked[j] != 0,
                toolbox, j, cur_c, cur_d, cur_s, p1_d, p1_s, p2_d, p2_s)
        delta[j] = cur_d[m - 1]
        start[j] = cur_s[m - 1]
        # rotate: p2 <- p1 <- cur, cur <- old p2 (overwritten next column)
        tmp = p2_d
        p2_d = p1_d
        p1_d = cur_d
        cur_d = tmp
        tmp = p2_s
        p2_s = p1_s
        p1_s = cur_s
        cur_s = tmp


cdef check(const uint64_t[::1] masks, const uint64_t[::1] values, const int64_t[:, ::1] tables,
           const uint64_t[::1] codes, const unsigned char[::1] blocked):
    cdef Py_ssize_t m = masks.shape[0]
    if m == 0:
        raise ValueError("a template needs at least one column")
    if values.shape[0] != m or tables.shape[0] != m or blocked.shape[0] != codes.shape[0]:
        raise ValueError("masks, values and tables need one row per template column, blocked one per code")


def minima_codes(
    const uint64_t[::1] masks,
    const uint64_t[::1] values,
    const int64_t[:, ::1] tables,
    const uint64_t[::1] codes,
    const unsigned char[::1] blocked,
    bint toolbox,
    int64_t threshold,
):
    """The local minima of Δ (:func:`subsequence_codes`) at or below ``threshold`` (fixed point):
    Δ(b) < Δ(b-1) and Δ(b) <= Δ(b+1), outside the columns counting as unreachable; a list of
    (start, end, Δ) in column order. With the toolbox's steps and no blocked column only the cells
    at or below ``threshold`` are kept (:func:`_pruned_column`): the minima are the same, since a
    neighbour above the threshold is above any Δ that counts either way."""
    check(masks, values, tables, codes, blocked)
    cdef Py_ssize_t n = codes.shape[0], m = masks.shape[0], j, hi1 = -1, hi2 = -1, hi
    cdef int64_t[::1] delta
    cdef int64_t[::1] start
    cdef int64_t[:, ::1] b
    if toolbox and not any(blocked):
        delta = np.empty(n, dtype=np.int64)
        start = np.empty(n, dtype=np.int64)
        b = np.empty((6, m), dtype=np.int64)
        b[:, :] = INF
        with nogil:
            for j in range(n):
                hi = _pruned_column(&masks[0], &values[0], &tables[0, 0], tables.shape[1], m, codes[j], j,
                                    threshold, hi1, hi2, &b[2 * (j % 3), 0], &b[2 * (j % 3) + 1, 0],
                                    &b[2 * ((j + 2) % 3), 0], &b[2 * ((j + 2) % 3) + 1, 0],
                                    &b[2 * ((j + 1) % 3), 0], &b[2 * ((j + 1) % 3) + 1, 0])
                # the last row may not have been written this column: it is finite only if highest
                delta[j] = b[2 * (j % 3), m - 1] if hi == m - 1 else INF
                start[j] = b[2 * (j % 3) + 1, m - 1] if hi == m - 1 else NO_START
                hi2 = hi1
                hi1 = hi
    else:
        delta, start = subsequence_codes(masks, values, tables, codes, blocked, toolbox)
    out = []
    cdef int64_t d, before, after
    for j in range(n):
        d = delta[j]
        if d > threshold or d >= INF:
            continue
        before = delta[j - 1] if j > 0 else INF
        after = delta[j + 1] if j + 1 < n else INF
        if d < before and d <= after:
            out.append((start[j], j, d))
    return out


def subsequence_codes(
    const uint64_t[::1] masks,
    const uint64_t[::1] values,
    const int64_t[:, ::1] tables,
    const uint64_t[::1] codes,
    const unsigned char[::1] blocked,
    bint toolbox,
):
    """Δ (the last template row of D) and each cell's start column, both int64 ``(N,)``, of the
    template whose retrieval tables are ``masks``, ``values`` ``(M,)`` and ``tables`` ``(M, f + 1)``
    against ``codes`` ``(N,)``; columns where ``blocked`` is nonzero cost :data:`INF`. Steps: the
    toolbox's (1,1), (1,2), (2,1) with weights 1, 1, 2, else the thesis' (1,0), (0,1), (1,1)."""
    check(masks, values, tables, codes, blocked)
    cdef Py_ssize_t n = codes.shape[0]
    delta_out = np.empty(n, dtype=np.int64)
    start_out = np.empty(n, dtype=np.int64)
    cdef int64_t[::1] delta = delta_out, start = start_out
    cdef int64_t[:, ::1] b = np.empty((7, masks.shape[0]), dtype=np.int64)
    with nogil:
        _subsequence(masks, values, tables, codes, blocked, toolbox, delta, start, b)
    return delta_out, start_out


cdef class StreamDTW:
    """Subsequence DTW (:func:`subsequence_codes`) of several templates over one stream of codes, one
    column per frame: each :meth:`push` computes every template's column of the new frame and
    returns the local minima of Δ that it completes. Frames are numbered from 0 since the last
    :meth:`reset`. A template with the toolbox's steps keeps only the cells at or below its
    threshold (:func:`_pruned_column`; above it a cell reads :data:`INF`): a stream that looks
    nothing like a template costs a few rows per frame, not all. State: three columns per template
    (D and start column of each cell), whatever the stream's length; the templates' tables are the
    caller's arrays, not copied."""

    cdef list _arrays  # the templates' tables, kept alive for the pointers below
    cdef const uint64_t **_masks
    cdef const uint64_t **_values
    cdef const int64_t **_tables
    cdef Py_ssize_t k, total, most
    cdef readonly int64_t n
    cdef unsigned char[::1] toolbox
    cdef int64_t[::1] lengths, offsets, widths, thresholds
    cdef int64_t[:, ::1] cols  # rows: three (D, start) slots, frame f in slot f % 3; templates side by side
    cdef int64_t[::1] costs  # one template column's cell costs
    cdef int64_t[:, ::1] highest  # (templates, 3): each slot's highest finite row (pruned templates)

    def __cinit__(self):
        self._masks = NULL
        self._values = NULL
        self._tables = NULL

    def __dealloc__(self):
        PyMem_Free(self._masks)
        PyMem_Free(self._values)
        PyMem_Free(self._tables)

    def __init__(self, list templates):
        """``templates``: per template (masks, values, tables, threshold, toolbox): its retrieval
        tables (uint64 ``(M,)``, uint64 ``(M,)``, int64 ``(M, f + 1)``, contiguous), its τ in fixed
        point and whether it takes the toolbox's steps (else the thesis')."""
        if not templates:
            raise ValueError("a StreamDTW needs templates")
        self.k = len(templates)
        self._arrays = []
        self._masks = <const uint64_t **> PyMem_Malloc(self.k * sizeof(uint64_t *))
        self._values = <const uint64_t **> PyMem_Malloc(self.k * sizeof(uint64_t *))
        self._tables = <const int64_t **> PyMem_Malloc(self.k * sizeof(int64_t *))
        if self._masks == NULL or self._values == NULL or self._tables == NULL:
            raise MemoryError()
        cdef const uint64_t[::1] m_view
        cdef const uint64_t[::1] v_view
        cdef const int64_t[:, ::1] t_view
        lengths, widths = [], []
        for i, (masks, values, tables, _, _) in enumerate(templates):
            m_view = masks
            v_view = values
            t_view = tables
            if m_view.shape[0] == 0:
                raise ValueError("a template needs at least one column")
            if v_view.shape[0] != m_view.shape[0] or t_view.shape[0] != m_view.shape[0]:
                raise ValueError("masks, values and tables need one row per template column")
            self._arrays.append((masks, values, tables))
            self._masks[i] = &m_view[0]
            self._values[i] = &v_view[0]
            self._tables[i] = &t_view[0, 0]
            lengths.append(m_view.shape[0])
            widths.append(t_view.shape[1])
        self.toolbox = np.array([bool(t[4]) for t in templates], dtype=np.uint8)
        self.lengths = np.array(lengths, dtype=np.int64)
        self.offsets = np.concatenate([[0], np.cumsum(lengths)]).astype(np.int64)
        self.widths = np.array(widths, dtype=np.int64)
        self.thresholds = np.array([t[3] for t in templates], dtype=np.int64)
        self.total = self.offsets[self.k]
        self.most = max(lengths)
        self.cols = np.empty((6, self.total), dtype=np.int64)
        self.costs = np.empty(self.most, dtype=np.int64)
        self.highest = np.empty((self.k, 3), dtype=np.int64)
        self.reset()

    def reset(self):
        """A new stream: no frame seen."""
        cdef Py_ssize_t r, i
        for r in range(6):
            for i in range(self.total):
                self.cols[r, i] = INF if r % 2 == 0 else NO_START
        for i in range(self.k):
            for r in range(3):
                self.highest[i, r] = -1
        self.n = 0

    cdef inline int64_t _last(self, Py_ssize_t t, int64_t f) noexcept nogil:
        """Δ of template ``t`` at frame ``f`` (one of the last three; :data:`INF` before frame 0)."""
        if f < 0:
            return INF
        cdef Py_ssize_t slot = f % 3
        if self.toolbox[t] != 0 and self.highest[t, slot] != self.lengths[t] - 1:
            return INF  # the last row was not written this column
        return self.cols[2 * slot, self.offsets[t] + self.lengths[t] - 1]

    cdef inline int64_t _start(self, Py_ssize_t t, int64_t f) noexcept nogil:
        return self.cols[2 * (f % 3) + 1, self.offsets[t] + self.lengths[t] - 1]

    def push(self, uint64_t code):
        """The next frame's code; the local minima it completes: every template's Δ at the frame
        before (e), at or below its threshold, below Δ(e - 1) and not above Δ at this frame, as a
        list of (template, start column, e, Δ) in template order (None if there is none)."""
        cdef Py_ssize_t t, o, m, cur, p1, p2
        cdef int64_t f = self.n, d
        with nogil:
            cur = 2 * (f % 3)
            p1 = 2 * ((f + 2) % 3)
            p2 = 2 * ((f + 1) % 3)
            for t in range(self.k):
                o = self.offsets[t]
                m = self.lengths[t]
                if self.toolbox[t] != 0:
                    self.highest[t, f % 3] = _pruned_column(
                        self._masks[t], self._values[t], self._tables[t], self.widths[t], m, code, f,
                        self.thresholds[t], self.highest[t, (f + 2) % 3], self.highest[t, (f + 1) % 3],
                        &self.cols[cur, o], &self.cols[cur + 1, o], &self.cols[p1, o],
                        &self.cols[p1 + 1, o], &self.cols[p2, o], &self.cols[p2 + 1, o])
                else:
                    _column(self._masks[t], self._values[t], self._tables[t], self.widths[t], m, code,
                            False, False, f, &self.costs[0], &self.cols[cur, o], &self.cols[cur + 1, o],
                            &self.cols[p1, o], &self.cols[p1 + 1, o], &self.cols[p2, o],
                            &self.cols[p2 + 1, o])
                    self.highest[t, f % 3] = m - 1
        self.n = f + 1
        if f == 0:
            return None
        out = None
        for t in range(self.k):
            d = self._last(t, f - 1)
            if d <= self.thresholds[t] and d < INF and d < self._last(t, f - 2) and d <= self._last(t, f):
                if out is None:
                    out = []
                out.append((t, self._start(t, f - 1), f - 1, d))
        return out

    def finish(self):
        """The local minima at the last frame pushed, as if the stream ended there (no frame after
        it to compare with), as :meth:`push` lists them (None if there is none)."""
        cdef int64_t f = self.n - 1, d
        if f < 0:
            return None
        out = None
        for t in range(self.k):
            d = self._last(t, f)
            if d <= self.thresholds[t] and d < INF and d < self._last(t, f - 1):
                if out is None:
                    out = []
                out.append((t, self._start(t, f), f, d))
        return out

    def delta(self, Py_ssize_t template, int64_t frame):
        """(Δ, start) of ``template`` at ``frame``, one of the last three pushed; a template with
        the toolbox's steps gives (:data:`INF`, -1) where Δ is above its threshold."""
        if not (0 <= template < self.k and self.n - 3 <= frame < self.n and frame >= 0):
            raise IndexError(f"frame {frame} is not among the last 3 of {self.n}")
        d = self._last(template, frame)
        return (d, self._start(template, frame)) if d < INF else (INF, NO_START)

    def blocks(self, int64_t cost, int64_t start, int64_t end, Py_ssize_t lo, Py_ssize_t hi):
        """Whether a template ``lo`` .. ``hi - 1`` may still end a match below ``cost`` (fixed
        point) that shares more than half of the shorter range's frames with ``start .. end``
        (``end`` before the last frame pushed, j). Every path that ends at j or later and starts
        by ``end`` passes a cell of column j or j - 1, and costs only grow along a path; so it is a
        cell of those columns below ``cost`` and at most its template's threshold, in row i of M,
        whose start s allows 2 (end - max(start, s) + 1) > min(end - start, e - s) + 1 at the
        earliest end e a path through it can reach (the shorter range is shortest there): the
        column plus ⌈(M - 1 - i) / 2⌉ with the toolbox's steps (two rows per column at most), the
        column itself with the thesis' (rows may climb within a column), and not before j."""
        cdef int64_t j = self.n - 1, s, e, shared, shorter, d
        cdef Py_ssize_t t, i, o, slot, top, r, m
        cdef bint found = False
        if j <= end:
            raise ValueError(f"the range must end before the last frame pushed ({j}), got {end}")
        if not 0 <= lo <= hi <= self.k:
            raise IndexError(f"templates {lo}..{hi - 1} of {self.k}")
        with nogil:
            for t in range(lo, hi):
                o = self.offsets[t]
                m = self.lengths[t]
                for r in range(2):
                    if j - r < 0:
                        continue
                    slot = (j - r) % 3
                    top = self.highest[t, slot]
                    for i in range(top + 1):
                        d = self.cols[2 * slot, o + i]
                        if d >= cost or d > self.thresholds[t]:
                            continue
                        s = self.cols[2 * slot + 1, o + i]
                        if s < 0 or s > end:
                            continue
                        e = j - r + (m - i) // 2 if self.toolbox[t] != 0 else j - r
                        if e < j:
                            e = j
                        shared = end - (start if start > s else s) + 1
                        shorter = (end - start if end - start < e - s else e - s) + 1
                        if 2 * shared > shorter:
                            found = True
                            break
                    if found:
                        break
                if found:
                    break
        return found


def accumulated(const int64_t[:, ::1] cost):
    """Alg. 3.1 on a fixed-point cost matrix ``(M, N)``: D(i, j) = C(i, j) + min(D(i-1, j-1),
    D(i, j-1), D(i-1, j)), D(0, 0) = C(0, 0), the first row and column accumulated, clamped at
    :data:`INF`; int64 ``(M, N)``, the integers of :func:`daemon.dtw.accumulated`'s row scans."""
    cdef Py_ssize_t m = cost.shape[0], n = cost.shape[1], i, j
    if m == 0 or n == 0:
        raise ValueError("a DTW cost matrix must be non-empty")
    out = np.empty((m, n), dtype=np.int64)
    cdef int64_t[:, ::1] d = out
    cdef int64_t best
    with nogil:
        d[0, 0] = clamp(cost[0, 0])
        for j in range(1, n):
            d[0, j] = clamp(d[0, j - 1] + cost[0, j])
        for i in range(1, m):
            d[i, 0] = clamp(d[i - 1, 0] + cost[i, 0])
            for j in range(1, n):
                best = d[i - 1, j - 1]
                if d[i, j - 1] < best:
                    best = d[i, j - 1]
                if d[i - 1, j] < best:
                    best = d[i - 1, j]
                d[i, j] = clamp(best + cost[i, j])
    return out
