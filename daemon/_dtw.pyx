# cython: language_level=3, boundscheck=False, wraparound=False, initializedcheck=False, cdivision=True
"""Compiled subsequence DTW of a quantised template against packed frame codes (see daemon/dtw.py).

The recursion of :func:`daemon.dtw.subsequence_fixed` cell by cell, column by column, on the same
int64 fixed-point costs with the same tie order, so the results are the same integers; the cell
costs come from the template's retrieval tables (popcount of the differing fixed bits)."""

from cpython.mem cimport PyMem_Free, PyMem_Malloc, PyMem_Realloc
from libc.string cimport memcpy, memmove
from libc.stdint cimport int64_t, uint64_t

import numpy as np

cdef extern from *:
    int popcount "__builtin_popcountll"(unsigned long long) nogil

cdef int64_t INF = (<int64_t>1) << 46
cdef int64_t NO_START = -1
cdef Py_ssize_t MAX_COLUMNS = 1 << 16

cdef enum:
    # the fields of a gated class's last whole keyframe hit (Competition.hits)
    HIT_LIVE, HIT_T, HIT_FIRST, HIT_LO, HIT_END, HIT_RELEASE, HIT_FIELDS


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
            if m_view.shape[0] > MAX_COLUMNS:  # D * M and τ * (i + 1) must stay in int64 (progress)
                raise ValueError(f"a template has at most {MAX_COLUMNS} columns")
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
        self.active = np.ones(self.k, dtype=np.uint8)
        self.reset()

    def reset(self):
        """A new stream: no frame seen."""
        self._reset()

    def state(self):
        """What :meth:`restore` needs to go on as this DTW would: (frames, the columns, each slot's
        highest row, the templates computing columns), arrays as bytes."""
        return (
            self.n, np.asarray(self.cols).tobytes(), np.asarray(self.highest).tobytes(),
            np.asarray(self.active).tobytes(),
        )

    def restore(self, state):
        """Take over a :meth:`state` of a DTW of the same templates; ValueError if it does not fit."""
        n, cols, highest, active = state
        c = np.frombuffer(cols, dtype=np.int64)
        h = np.frombuffer(highest, dtype=np.int64)
        a = np.frombuffer(active, dtype=np.uint8)
        if c.shape[0] != 6 * self.total or h.shape[0] != 3 * self.k or a.shape[0] != self.k or n < 0:
            raise ValueError(f"DTW: the state of {self.k} templates of {self.total} rows in all expected")
        np.asarray(self.cols)[...] = c.reshape(6, self.total)
        np.asarray(self.highest)[...] = h.reshape(self.k, 3)
        np.asarray(self.active)[...] = a
        self.n = n

    cdef void _reset(self) noexcept nogil:
        cdef Py_ssize_t r, i
        for r in range(6):
            for i in range(self.total):
                self.cols[r, i] = INF if r % 2 == 0 else NO_START
        for i in range(self.k):
            for r in range(3):
                self.highest[i, r] = -1
        self.n = 0

    cdef int64_t _last(self, Py_ssize_t t, int64_t f) noexcept nogil:
        """Δ of template ``t`` at frame ``f`` (one of the last three; :data:`INF` before frame 0)."""
        if f < 0:
            return INF
        cdef Py_ssize_t slot = f % 3
        if self.highest[t, slot] != self.lengths[t] - 1:
            return INF  # the last row was not written this column (or the template was inactive)
        return self.cols[2 * slot, self.offsets[t] + self.lengths[t] - 1]

    cdef int64_t _start(self, Py_ssize_t t, int64_t f) noexcept nogil:
        return self.cols[2 * (f % 3) + 1, self.offsets[t] + self.lengths[t] - 1]

    def push(self, uint64_t code):
        """The next frame's code; the local minima it completes: every template's Δ at the frame
        before (e), at or below its threshold, below Δ(e - 1) and not above Δ at this frame, as a
        list of (template, start column, e, Δ) in template order (None if there is none)."""
        cdef Candidate *found = <Candidate *> PyMem_Malloc(self.k * sizeof(Candidate))
        if found == NULL:
            raise MemoryError()
        cdef Py_ssize_t n = self.push_into(code, found), i
        out = [(found[i].member, found[i].start, found[i].end, found[i].cost) for i in range(n)] if n else None
        PyMem_Free(found)
        return out

    cdef void _compute(self, Py_ssize_t t, uint64_t code, int64_t f) noexcept nogil:
        """Template ``t``'s column of frame ``f`` (the two before it in their slots)."""
        cdef Py_ssize_t o = self.offsets[t], m = self.lengths[t]
        cdef Py_ssize_t cur = 2 * (f % 3), p1 = 2 * ((f + 2) % 3), p2 = 2 * ((f + 1) % 3)
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

    cdef void _clear(self, Py_ssize_t t) noexcept nogil:
        """Template ``t`` with no column: its three slots empty."""
        cdef Py_ssize_t r, i, o = self.offsets[t]
        for r in range(6):
            for i in range(o, o + self.lengths[t]):
                self.cols[r, i] = INF if r % 2 == 0 else NO_START
        for r in range(3):
            self.highest[t, r] = -1

    cdef bint _minimum(self, Py_ssize_t t, int64_t e, Candidate *out) noexcept nogil:
        """Whether template ``t``'s Δ at frame ``e`` is a local minimum within its threshold (the
        frames around it among the last three pushed or replayed); if so it is written to ``out``."""
        cdef int64_t d = self._last(t, e)
        if d <= self.thresholds[t] and d < INF and d < self._last(t, e - 1) and d <= self._last(t, e + 1):
            out.cost = d
            out.end = e
            out.member = t
            out.start = self._start(t, e)
            return True
        return False

    cdef Py_ssize_t push_into(self, uint64_t code, Candidate *out) noexcept nogil:
        """:meth:`push` into ``out`` (room for one per template): how many minima. A template that
        is not :attr:`active` gets an empty column (every Δ :data:`INF`)."""
        cdef Py_ssize_t t, found = 0
        cdef int64_t f = self.n
        for t in range(self.k):
            if self.active[t] != 0:
                self._compute(t, code, f)
            else:
                self.highest[t, f % 3] = -1
        self.n = f + 1
        if f == 0:
            return 0
        for t in range(self.k):
            if self._minimum(t, f - 1, &out[found]):
                found += 1
        return found

    cdef Py_ssize_t replay_into(self, Py_ssize_t t, int64_t a, int64_t lowest, const uint64_t *ring,
                                Py_ssize_t cap, Candidate *out) noexcept nogil:
        """Template ``t``'s columns computed anew from frame ``a`` (its Δ :data:`INF` before it) to
        the last frame pushed, whose codes are ``ring[f % cap]``: the local minima ending at
        ``lowest`` (at least ``a``) .. the frame before the last into ``out`` (room for one per
        frame), how many."""
        cdef int64_t f
        cdef Py_ssize_t found = 0
        self._clear(t)
        for f in range(a, self.n):
            self._compute(t, ring[f % cap], f)
            if f > a and f > lowest and self._minimum(t, f - 1, &out[found]):
                found += 1
        return found

    def finish(self):
        """The local minima at the last frame pushed, as if the stream ended there (no frame after
        it to compare with), as :meth:`push` lists them (None if there is none)."""
        cdef Candidate *found = <Candidate *> PyMem_Malloc(self.k * sizeof(Candidate))
        if found == NULL:
            raise MemoryError()
        cdef Py_ssize_t n = self.finish_into(found), i
        out = [(found[i].member, found[i].start, found[i].end, found[i].cost) for i in range(n)] if n else None
        PyMem_Free(found)
        return out

    cdef Py_ssize_t finish_into(self, Candidate *out) noexcept nogil:
        cdef int64_t f = self.n - 1, d
        cdef Py_ssize_t t, found = 0
        if f < 0:
            return 0
        for t in range(self.k):
            d = self._last(t, f)
            if d <= self.thresholds[t] and d < INF and d < self._last(t, f - 1):
                out[found].cost = d
                out[found].end = f
                out[found].member = t
                out[found].start = self._start(t, f)
                found += 1
        return found

    def delta(self, Py_ssize_t template, int64_t frame):
        """(Δ, start) of ``template`` at ``frame``, one of the last three pushed; a template with
        the toolbox's steps gives (:data:`INF`, -1) where Δ is above its threshold."""
        if not (0 <= template < self.k and self.n - 3 <= frame < self.n and frame >= 0):
            raise IndexError(f"frame {frame} is not among the last 3 of {self.n}")
        d = self._last(template, frame)
        return (d, self._start(template, frame)) if d < INF else (INF, NO_START)

    def progress(self, Py_ssize_t template, int64_t since=-1):
        """How far along ``template`` (M columns) the stream has got at the last frame pushed: the
        furthest row i of its column whose D(i) is within τ as a mean per template column,
        D(i)·M <= τ·(i + 1) in fixed point (cell costs carry the factor 1/M: D(M - 1) is a
        detection's cost), and whose path starts after frame ``since``, as (i, D(i)); (-1,
        :data:`INF`) if no row is, or no frame was pushed. With the toolbox's steps only cells
        within τ are kept, and those are exact: every row that qualifies (D(i) <= τ·(i + 1)/M <= τ)
        is one of them."""
        if not 0 <= template < self.k:
            raise IndexError(f"template {template} of {self.k}")
        cdef int64_t d = INF
        cdef Py_ssize_t i = self.progress_c(template, since, &d)
        if i < 0:
            return (-1, INF)
        return (i, d)

    cdef Py_ssize_t progress_c(self, Py_ssize_t t, int64_t since, int64_t *d) noexcept nogil:
        """:meth:`progress` of template ``t`` without its checks: the row (-1: none), D in ``d``."""
        if self.n == 0:
            return -1
        cdef Py_ssize_t slot = (self.n - 1) % 3, o = self.offsets[t], i
        cdef int64_t m = self.lengths[t], thr = self.thresholds[t], x
        for i in range(self.highest[t, slot], -1, -1):
            x = self.cols[2 * slot, o + i]
            if x < INF and x * m <= thr * (i + 1) and self.cols[2 * slot + 1, o + i] > since:
                d[0] = x
                return i
        return -1

    cdef bint reaches_c(self, Py_ssize_t lo, Py_ssize_t hi, int64_t end) noexcept nogil:
        """Whether a template ``lo`` .. ``hi - 1`` has a cell within its threshold in one of the last
        two columns whose path starts by column ``end``: every match that ends at the last frame
        pushed or later and starts by ``end`` passes such a cell (costs only grow along a path,
        and the toolbox's steps skip at most one column)."""
        cdef int64_t j = self.n - 1, s
        cdef Py_ssize_t t, i, o, slot, r
        for t in range(lo, hi):
            o = self.offsets[t]
            for r in range(2):
                if j - r < 0:
                    continue
                slot = (j - r) % 3
                for i in range(self.highest[t, slot] + 1):
                    if self.cols[2 * slot, o + i] <= self.thresholds[t]:
                        s = self.cols[2 * slot + 1, o + i]
                        if 0 <= s <= end:
                            return True
        return False

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
        if self.n - 1 <= end:
            raise ValueError(f"the range must end before the last frame pushed ({self.n - 1}), got {end}")
        if not 0 <= lo <= hi <= self.k:
            raise IndexError(f"templates {lo}..{hi - 1} of {self.k}")
        return self.blocks_c(cost, start, end, lo, hi)

    cdef bint blocks_c(self, int64_t cost, int64_t start, int64_t end, Py_ssize_t lo,
                       Py_ssize_t hi) noexcept nogil:
        """:meth:`blocks` without its checks."""
        cdef int64_t j = self.n - 1, s, e, shared, shorter, d
        cdef Py_ssize_t t, i, o, slot, top, r, m
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
                        return True
        return False


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


# ----------------------------------------------------------------------------------- competition


cdef int buf_init(Buf *b, Py_ssize_t stride) except -1:
    b.stride = stride
    b.head = 0
    b.n = 0
    b.cap = 8
    b.data = <int64_t *> PyMem_Malloc(b.cap * stride * sizeof(int64_t))
    if b.data == NULL:
        raise MemoryError()
    return 0


cdef inline Py_ssize_t buf_len(const Buf *b) noexcept nogil:
    return b.n - b.head


cdef inline int64_t *buf_row(Buf *b, Py_ssize_t i) noexcept nogil:
    """Row ``i`` of those held (0: the oldest; -1: the newest)."""
    return &b.data[(b.head + i if i >= 0 else b.n + i) * b.stride]


cdef int64_t *buf_append(Buf *b) except NULL:
    """A new row at the end (its values for the caller to write)."""
    cdef int64_t *grown
    if b.n == b.cap:
        if 2 * b.head >= b.n:  # half of it dropped at the front: slide back instead of growing
            memmove(b.data, &b.data[b.head * b.stride], (b.n - b.head) * b.stride * sizeof(int64_t))
            b.n -= b.head
            b.head = 0
        else:
            grown = <int64_t *> PyMem_Realloc(b.data, 2 * b.cap * b.stride * sizeof(int64_t))
            if grown == NULL:
                raise MemoryError()
            b.data = grown
            b.cap *= 2
    b.n += 1
    return &b.data[(b.n - 1) * b.stride]


cdef inline void buf_clear(Buf *b) noexcept nogil:
    b.head = 0
    b.n = 0


cdef bytes buf_bytes(Buf *b):
    """The rows held, oldest first, as int64 bytes."""
    return (<char *> &b.data[b.head * b.stride])[:buf_len(b) * b.stride * sizeof(int64_t)]


cdef int buf_load(Buf *b, bytes rows) except -1:
    """Hold exactly ``rows`` (:func:`buf_bytes` of a buffer of the same stride)."""
    cdef Py_ssize_t size = b.stride * sizeof(int64_t), i, n = len(rows) // size
    cdef const char *src = rows
    if len(rows) % size:
        raise ValueError(f"competition: candidates of {b.stride} values expected")
    buf_clear(b)
    for i in range(n):
        memcpy(buf_append(b), &src[i * size], size)
    return 0


cdef Candidate *reserve(Candidate *buf, Py_ssize_t *cap, Py_ssize_t need) except NULL:
    """``buf`` (room for ``cap[0]`` candidates) with room for ``need``: itself, or grown to twice
    ``need`` (``cap`` updated)."""
    cdef Candidate *grown
    if need <= cap[0]:
        return buf
    grown = <Candidate *> PyMem_Realloc(buf, 2 * need * sizeof(Candidate))
    if grown == NULL:
        raise MemoryError()
    cap[0] = 2 * need
    return grown


cdef inline bint before(const Candidate *x, const Candidate *y) noexcept nogil:
    """``x`` comes before ``y`` in the order (cost, end, member, start)."""
    if x.cost != y.cost:
        return x.cost < y.cost
    if x.end != y.end:
        return x.end < y.end
    if x.member != y.member:
        return x.member < y.member
    return x.start < y.start


cdef inline bint same_motion(int64_t a0, int64_t a1, int64_t b0, int64_t b1) noexcept nogil:
    """:func:`daemon.recognizer.same_motion` of the inclusive ranges a0..a1 and b0..b1."""
    cdef int64_t shared = (a1 if a1 < b1 else b1) - (a0 if a0 > b0 else b0) + 1
    cdef int64_t la = a1 - a0, lb = b1 - b0
    return 2 * shared > (la if la < lb else lb) + 1


cdef inline void get(const int64_t *row, Candidate *c) noexcept nogil:
    c.cost = row[0]
    c.end = row[1]
    c.member = row[2]
    c.start = row[3]


cdef inline void put(int64_t *row, const Candidate *c) noexcept nogil:
    row[0] = c.cost
    row[1] = c.end
    row[2] = c.member
    row[3] = c.start


cdef class Competition:
    """The confirmations of one stream of index-rate codes (the algorithm
    :class:`daemon.recognizer.CodeRecognizer`'s docstring states, the same operations in the same
    order) on C arrays: the DTW of every template (``dtw``), the keyframe-first classes' automata
    (``automata``: an :class:`~daemon._automaton.AutomatonSet` or None) and their windows, the
    candidates' competition and hold. ``owner`` ``(T,)``: each template's class; ``lo``, ``hi``
    ``(T,)``: the templates whose matches may beat its candidates; ``gated`` ``(G,)``: the class of
    each automaton, ``before``, ``after`` ``(G,)``: the frames its windows open before a match's
    range and stay open after the frame that completes it; ``back``: how far back a window may
    open; ``memory``: the frames candidates are remembered (:func:`daemon.recognizer.reach`). A
    confirmation is (class, start, end, fixed-point cost, template). State: the DTW's columns, the
    automata's partial matches, the codes of the last ``back`` + 1 frames, and the candidates of
    the last ``memory`` frames."""

    def __cinit__(self):
        self.found = NULL
        self.scratch = NULL
        self.held.data = NULL
        self.recent.data = NULL
        self.published.data = NULL

    def __dealloc__(self):
        PyMem_Free(self.found)
        PyMem_Free(self.scratch)
        PyMem_Free(self.held.data)
        PyMem_Free(self.recent.data)
        PyMem_Free(self.published.data)

    def __init__(self, StreamDTW dtw, owner, lo, hi, bint compete, int64_t hold, int64_t memory,
                 automata, gated, before=(), after=(), int64_t back=0):
        cdef Py_ssize_t g, k = dtw.k
        self.dtw = dtw
        self.owner = np.ascontiguousarray(owner, dtype=np.int64)
        self.lo = np.ascontiguousarray(lo, dtype=np.int64)
        self.hi = np.ascontiguousarray(hi, dtype=np.int64)
        if self.owner.shape[0] != k or self.lo.shape[0] != k or self.hi.shape[0] != k:
            raise ValueError("owner, lo and hi need one entry per template")
        classes = 1 + max(owner)
        slot = np.full(classes, -1, dtype=np.int64)
        for g, c in enumerate(gated):
            slot[c] = g
        self.slot = slot
        self.gated_of = np.array(list(gated) or [0], dtype=np.int64)
        self.n_gated = len(gated)
        if (self.n_gated > 0) != (automata is not None):
            raise ValueError("automata for the gated classes, and only for them")
        if len(before) != self.n_gated or len(after) != self.n_gated:
            raise ValueError("before and after need one entry per gated class")
        if back < 0 or min(before, default=0) < 0 or min(after, default=0) < 0:
            raise ValueError("a window's frames before and after, and how far back it opens, are >= 0")
        self.automata = automata
        self.compete = compete
        self.hold = hold
        self.memory = memory
        self.back = back
        self.ring = np.zeros(back + 1, dtype=np.uint64)
        self.before = np.ascontiguousarray(before, dtype=np.int64)
        self.after = np.ascontiguousarray(after, dtype=np.int64)
        self.seg_s = np.full(max(1, self.n_gated), -1, dtype=np.int64)
        self.seg_e = np.full(max(1, self.n_gated), -2, dtype=np.int64)
        self.found_cap = k + back + 1
        self.found = <Candidate *> PyMem_Malloc(self.found_cap * sizeof(Candidate))
        self.scratch_cap = 8
        self.scratch = <Candidate *> PyMem_Malloc(self.scratch_cap * sizeof(Candidate))
        if self.found == NULL or self.scratch == NULL:
            raise MemoryError()
        cls_lo = np.full(classes, k, dtype=np.int64)
        cls_hi = np.zeros(classes, dtype=np.int64)
        for g in range(k):
            cls_lo[owner[g]] = min(cls_lo[owner[g]], g)
            cls_hi[owner[g]] = max(cls_hi[owner[g]], g + 1)
        self.cls_lo = cls_lo
        self.cls_hi = cls_hi
        self.n_classes = classes
        initial = np.ones(k, dtype=np.uint8)
        for c in gated:
            initial[cls_lo[c]:cls_hi[c]] = 0
        self.initial = initial
        dtw.active[:] = self.initial
        self.hits = np.full((max(1, self.n_gated), HIT_FIELDS), -1, dtype=np.int64)
        self.hit_frames = [()] * self.n_gated
        self.last_pub = np.full((max(1, self.n_gated), 3), -1, dtype=np.int64)
        self.spent = np.full(classes, -1, dtype=np.int64)
        buf_init(&self.held, 4)
        buf_init(&self.recent, 4)
        buf_init(&self.published, 3)
        self.n = 0

    @property
    def state_size(self):
        """Candidates and detections remembered."""
        return buf_len(&self.held) + buf_len(&self.recent) + buf_len(&self.published)

    def push(self, uint64_t code):
        """The next code: the confirmations it made, in the order (end, start, class), or None."""
        return self.push_c(code)

    cdef list push_c(self, uint64_t code):
        cdef int64_t j = self.n, first, a, b
        cdef Py_ssize_t found = 0, g, t
        cdef StreamDTW dtw = self.dtw
        self.ring[j % (self.back + 1)] = code
        if self.automata is not None:
            for g, reached in self.automata.push(code):
                a = j
                for first, _ in reached:
                    a = min(a, max(first - self.before[g], j - self.back, 0))
                found = self._open(g, a, j + self.after[g], j, found)
            for g in range(self.n_gated):
                if self.seg_e[g] == j - 1:  # its window closes: its templates' columns are empty from here
                    for t in range(self.cls_lo[self.gated_class(g)], self.cls_hi[self.gated_class(g)]):
                        dtw.active[t] = 0
        found += dtw.push_into(code, &self.found[found])
        self.n += 1
        if found:
            self._sort_found(found)
            for t in range(found):
                self._arrive(&self.found[t])
        out = self._decide(j, False) if buf_len(&self.held) else None
        self._forget(j)
        return out

    cdef Py_ssize_t _open(self, Py_ssize_t g, int64_t a, int64_t b, int64_t j, Py_ssize_t found) except -1:
        """A window ``a`` .. ``b`` of gated class ``g`` reported at frame ``j`` (before its column):
        the class's open window extended to ``b``, or a new one from ``a`` whose templates' columns
        are computed from there to frame ``j - 1`` from the ring; the minima that finds (those
        ending after the last window) go to :attr:`found` after the ``found`` there, and their new
        count."""
        cdef Py_ssize_t t, k = self.gated_class(g), need
        cdef int64_t lowest = self.seg_e[g] + 1
        if self.seg_e[g] >= j - 1:
            if b > self.seg_e[g]:
                self.seg_e[g] = b
            return found
        self.seg_s[g] = a
        self.seg_e[g] = b
        need = found + (self.cls_hi[k] - self.cls_lo[k]) * (j - a + 1) + self.dtw.k
        self.found = reserve(self.found, &self.found_cap, need)
        for t in range(self.cls_lo[k], self.cls_hi[k]):
            self.dtw.active[t] = 1
            found += self.dtw.replay_into(t, a, lowest, &self.ring[0], self.back + 1, &self.found[found])
        return found

    cdef Py_ssize_t gated_class(self, Py_ssize_t g) noexcept nogil:
        return self.gated_of[g]

    cdef void _sort_found(self, Py_ssize_t found) noexcept nogil:
        """:attr:`found`'s first ``found`` in the order (cost, end, member, start) (insertion sort:
        a handful)."""
        cdef Py_ssize_t a, b
        cdef Candidate y
        for a in range(1, found):
            y = self.found[a]
            b = a - 1
            while b >= 0 and before(&y, &self.found[b]):
                self.found[b + 1] = self.found[b]
                b -= 1
            self.found[b + 1] = y

    def state(self):
        """What :meth:`restore` needs to go on as this competition would: (frames, the ring of
        codes, each gated class's window, hit and last detection, each class's last spent start,
        the hit's keyframe frames, the held, recent and published candidates as int64 bytes, the
        DTW's :meth:`StreamDTW.state`, the automata's :meth:`~daemon._automaton.AutomatonSet.state`
        or None)."""
        return (
            self.n,
            np.asarray(self.ring).tobytes(),
            np.asarray(self.seg_s).tobytes(),
            np.asarray(self.seg_e).tobytes(),
            np.asarray(self.hits).tobytes(),
            np.asarray(self.last_pub).tobytes(),
            np.asarray(self.spent).tobytes(),
            [list(f) for f in self.hit_frames],
            buf_bytes(&self.held),
            buf_bytes(&self.recent),
            buf_bytes(&self.published),
            self.dtw.state(),
            None if self.automata is None else self.automata.state(),
        )

    def restore(self, state):
        """Take over a :meth:`state` of a competition of the same templates, classes and settings;
        ValueError naming the part that does not fit."""
        n, ring, seg_s, seg_e, hits, last_pub, spent, hit_frames, held, recent, published, dtw, automata = state
        for name, view, data, dtype in (
            ("codes", self.ring, ring, np.uint64),
            ("windows", self.seg_s, seg_s, np.int64),
            ("windows", self.seg_e, seg_e, np.int64),
            ("hits", self.hits, hits, np.int64),
            ("detections", self.last_pub, last_pub, np.int64),
            ("spent", self.spent, spent, np.int64),
        ):
            if len(data) != np.asarray(view).nbytes:
                raise ValueError(f"competition: {name} of another shape ({len(data)} bytes)")
        if len(hit_frames) != self.n_gated or (automata is None) != (self.automata is None) or n < 0:
            raise ValueError(f"competition: {self.n_gated} classes gated by keyframes expected")
        self.dtw.restore(dtw)
        if self.automata is not None:
            self.automata.restore(automata)
        np.asarray(self.ring)[...] = np.frombuffer(ring, dtype=np.uint64)
        np.asarray(self.seg_s)[...] = np.frombuffer(seg_s, dtype=np.int64)
        np.asarray(self.seg_e)[...] = np.frombuffer(seg_e, dtype=np.int64)
        np.asarray(self.hits)[...] = np.frombuffer(hits, dtype=np.int64).reshape(np.asarray(self.hits).shape)
        np.asarray(self.last_pub)[...] = np.frombuffer(last_pub, dtype=np.int64).reshape(
            np.asarray(self.last_pub).shape)
        np.asarray(self.spent)[...] = np.frombuffer(spent, dtype=np.int64)
        self.hit_frames = [tuple(f) for f in hit_frames]
        buf_load(&self.held, held)
        buf_load(&self.recent, recent)
        buf_load(&self.published, published)
        self.n = n

    def flush(self):
        """The end of the stream: the confirmations left (as :meth:`push`'s); then a new stream."""
        cdef Py_ssize_t found, a
        out = None
        if self.n:
            found = self.dtw.finish_into(self.found)
            self._sort_found(found)
            for a in range(found):
                self._arrive(&self.found[a])
            out = self._decide(self.n - 1, True)
            self.dtw._reset()
        self.dtw.active[:] = self.initial
        if self.automata is not None:
            self.automata.flush()
        self.seg_s[:] = -1
        self.seg_e[:] = -2
        self.hits[:, :] = -1
        self.last_pub[:, :] = -1
        self.spent[:] = -1
        self.hit_frames = [()] * self.n_gated
        buf_clear(&self.held)
        buf_clear(&self.recent)
        buf_clear(&self.published)
        self.n = 0
        return out

    cdef bint _rival(self, const Candidate *x, const Candidate *y) noexcept nogil:
        return (self.compete or self.owner[x.member] == self.owner[y.member]) and same_motion(
            x.start, x.end, y.start, y.end)

    cdef int _arrive(self, Candidate *y) except -1:
        """A new candidate: remembered as a rival; held unless something before it beats it or it is
        a motion already published; a held one it beats is dropped. A candidate beaten by another
        class's, or the same motion as a detection published, is spent (:meth:`_spend`), as is a
        held one dropped for another class's."""
        cdef Py_ssize_t i, kept
        cdef Candidate x
        cdef bint beaten = False
        cdef int64_t k = self.owner[y.member]
        cdef int64_t *row
        for i in range(buf_len(&self.recent)):
            get(buf_row(&self.recent, i), &x)
            if before(&x, y) and self._rival(&x, y):
                beaten = True
                if self.owner[x.member] != k:
                    self._spend(y)
                    break
        put(buf_append(&self.recent), y)
        for i in range(buf_len(&self.published)):
            row = buf_row(&self.published, i)
            if (self.compete or row[2] == k) and same_motion(y.start, y.end, row[0], row[1]):
                self._spend(y)
                return 0
        if beaten:
            return 0
        kept = 0
        for i in range(buf_len(&self.held)):
            get(buf_row(&self.held, i), &x)
            if not (before(y, &x) and self._rival(&x, y)):
                put(buf_row(&self.held, kept), &x)
                kept += 1
            elif self.owner[x.member] != k:
                self._spend(&x)
        self.held.n = self.held.head + kept
        put(buf_append(&self.held), y)
        return 0

    cdef void _spend(self, const Candidate *x) noexcept nogil:
        """``x``'s motion is decided (published, or lost to another class or to a detection): its
        class's progress (:meth:`progress`) no longer follows paths that start by ``x``'s start, so
        a bar does not stand on a motion already told or explained, and the next one rises."""
        cdef int64_t k = self.owner[x.member]
        if x.start > self.spent[k]:
            self.spent[k] = x.start

    cdef list _decide(self, int64_t j, bint ended):
        """The held candidates that frame ``j`` (the stream's last, if it ``ended``) makes final:
        those published, in the order (end, start, class), as confirmations."""
        cdef Py_ssize_t i, kept = 0, final = 0, a, b, g, h = buf_len(&self.held)
        cdef Candidate x, y
        cdef int64_t k
        cdef int64_t *row
        self.scratch = reserve(self.scratch, &self.scratch_cap, h)
        for i in range(h):
            get(buf_row(&self.held, i), &x)
            if ended or j > x.end + self.hold or not self.dtw.blocks_c(
                    x.cost, x.start, x.end, self.lo[x.member], self.hi[x.member]):
                self.scratch[final] = x
                final += 1
            else:
                put(buf_row(&self.held, kept), &x)
                kept += 1
        self.held.n = self.held.head + kept
        if not final:
            return None
        for a in range(1, final):  # a stable sort by (end, start, class)
            y = self.scratch[a]
            b = a - 1
            while b >= 0 and (
                self.scratch[b].end > y.end
                or (self.scratch[b].end == y.end and (
                    self.scratch[b].start > y.start
                    or (self.scratch[b].start == y.start
                        and self.owner[self.scratch[b].member] > self.owner[y.member])))):
                self.scratch[b + 1] = self.scratch[b]
                b -= 1
            self.scratch[b + 1] = y
        out = None
        for a in range(final):
            x = self.scratch[a]
            k = self.owner[x.member]
            g = self.slot[k]
            if g >= 0:
                self.last_pub[g, 0] = x.start  # for progress: which keyframe hit gave a detection
                self.last_pub[g, 1] = x.end
                self.last_pub[g, 2] = j
            self._spend(&x)
            row = buf_append(&self.published)
            row[0] = x.start
            row[1] = x.end
            row[2] = k
            if out is None:
                out = []
            out.append((k, x.start, x.end, x.cost, x.member))
        return out

    def progress(self, double floor):
        """How far each class's motion has got at the last frame pushed (call it after every push
        of a stream whose progress is followed: it also keeps each gated class's last whole
        keyframe hit). Per class under way — a gated class with keyframes matched, another at a
        position of at least ``floor`` — in class order: (class, template, row, D, frames): the template whose
        :meth:`StreamDTW.progress` row, on paths that start after the class's last spent candidate
        (:meth:`_spend`), is furthest along as a share of its length (ties: the lower mean cost
        D·M/(row + 1), then the first), -1, -1, :data:`INF` if none has one; and for a
        gated class the frames of its keyframes found: those of its last whole hit while it is
        held, else those of the automaton's most advanced partial match
        (:meth:`~daemon._automaton.AutomatonCore.partial`), else (). A whole hit is held from the
        frame that completes it to the frame at which a detection of its class that overlaps its
        range R(M) is published (inclusive), or until it can give none: its range no longer grows,
        no held candidate of the class overlaps it, and no path within τ in the DTW's last two
        columns starts by its end (:meth:`StreamDTW.reaches_c`)."""
        cdef int64_t j = self.n - 1, d, best_d, m, best_m
        cdef Py_ssize_t k, u, i, g, best_u, best_i
        cdef double cost, best_cost
        cdef StreamDTW dtw = self.dtw
        out = []
        if j < 0:
            return out
        for g in range(self.n_gated):
            self._follow_hit(g, j)
        for k in range(self.n_classes):
            best_u = best_i = -1
            best_d = INF
            best_m = 1
            best_cost = 0.0
            for u in range(self.cls_lo[k], self.cls_hi[k]):
                i = dtw.progress_c(u, self.spent[k], &d)
                if i < 0:
                    continue
                m = dtw.lengths[u]
                cost = (<double> d) * m / (i + 1)
                if best_u < 0 or (i + 1) * best_m > (best_i + 1) * m or (
                        (i + 1) * best_m == (best_i + 1) * m and cost < best_cost):
                    best_u, best_i, best_d, best_m, best_cost = u, i, d, m, cost
            g = self.slot[k]
            frames = ()
            if g >= 0:
                frames = self.hit_frames[g] if self.hits[g, HIT_LIVE] == 1 else self.automata.core(g).partial()
            # a gated class is under way only on keyframe evidence: its gate, not its template,
            # decides, and a loose template's path stays within τ through much unrelated motion
            if frames or (g < 0 and best_u >= 0 and (<double> (best_i + 1)) / best_m >= floor):
                out.append((k, best_u, best_i, best_d, frames))
        return out

    cdef void _follow_hit(self, Py_ssize_t g, int64_t j) except *:
        """Gated class ``g``'s last whole hit after frame ``j`` (:meth:`progress`)."""
        cdef int64_t[:, ::1] h = self.hits
        core = self.automata.core(g)
        if h[g, HIT_RELEASE] == 1:  # its detection was published at the frame before
            h[g, HIT_LIVE] = 0
            h[g, HIT_RELEASE] = 0
        found = core.hit()
        if found is not None and found[0] == j:
            h[g, HIT_LIVE] = 1
            h[g, HIT_T] = j
            h[g, HIT_FIRST] = found[1]
            h[g, HIT_LO] = found[2]
            h[g, HIT_END] = j
            h[g, HIT_RELEASE] = 0
            self.hit_frames[g] = found[3]
        elif h[g, HIT_LIVE] == 1 and (h[g, HIT_FIRST], h[g, HIT_LO]) in core.reached:
            h[g, HIT_END] = j  # its range still grows
        if h[g, HIT_LIVE] != 1:
            return
        if self.last_pub[g, 2] >= h[g, HIT_T] and self.last_pub[g, 0] <= h[g, HIT_END] and (
                h[g, HIT_FIRST] <= self.last_pub[g, 1]):
            h[g, HIT_RELEASE] = 1  # still reported at this frame, the detection's
        elif h[g, HIT_END] < j and not self._may_give(g):
            h[g, HIT_LIVE] = 0

    cdef bint _may_give(self, Py_ssize_t g) noexcept:
        """Whether gated class ``g``'s last hit may still overlap a detection: a held candidate
        of its class overlaps its range, or a path in the DTW may still end one that does."""
        cdef int64_t k = -1, first = self.hits[g, HIT_FIRST], end = self.hits[g, HIT_END]
        cdef Py_ssize_t i, c
        cdef Candidate x
        for c in range(self.n_classes):
            if self.slot[c] == g:
                k = c
                break
        for i in range(buf_len(&self.held)):
            get(buf_row(&self.held, i), &x)
            if self.owner[x.member] == k and x.start <= end and first <= x.end:
                return True
        return self.dtw.reaches_c(self.cls_lo[k], self.cls_hi[k], end)

    cdef void _forget(self, int64_t j) noexcept:
        """Drop what no candidate after frame ``j`` can be compared with: rivals and published
        detections that end more than ``memory`` frames back."""
        cdef int64_t forget = j - self.memory
        while buf_len(&self.recent) and buf_row(&self.recent, 0)[1] < forget:
            self.recent.head += 1
        while buf_len(&self.published) and buf_row(&self.published, 0)[1] < forget:
            self.published.head += 1
