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
    """Subsequence DTW (:func:`subsequence_codes`) of several templates over one stream of codes: each
    template's Δ and start column at the stream's last ``keep`` frames, kept in rings, so that
    :meth:`beaten` can look back over them. Frames are numbered from 0 since the last
    :meth:`reset`. :meth:`push` only keeps the code; the columns are computed in runs of up to
    ``batch`` frames, template by template (a template's columns stay in the cache for the run,
    instead of every template's being fetched again for every frame), and before any question:
    the same integers as one column per frame, since a column depends only on the ones before.
    Only Δ at or below a template's threshold is ever asked for, so a template with the toolbox's
    steps keeps only the cells at or below it (:func:`_pruned_column`; Δ above it reads
    :data:`INF`): a stream that looks nothing like a template costs a few rows per frame, not all.
    State: three columns per template and the rings, whatever the stream's length; the templates'
    tables are the caller's arrays, not copied."""

    cdef list _arrays  # the templates' tables, kept alive for the pointers below
    cdef const uint64_t **_masks
    cdef const uint64_t **_values
    cdef const int64_t **_tables
    cdef Py_ssize_t k, keep, batch, total, most
    cdef readonly int64_t n
    cdef int64_t done  # frames whose columns are computed
    cdef unsigned char[::1] toolbox
    cdef int64_t[::1] lengths, offsets, widths, thresholds
    cdef int64_t[:, ::1] cols  # rows: three (Δ, start) slots used in turn; templates side by side
    cdef int64_t[::1] costs  # one template column's cell costs
    cdef int64_t[:, ::1] highest  # (templates, 3): each slot's highest finite row (pruned templates)
    cdef uint64_t[::1] codes  # ring of the last ``keep`` codes
    cdef int64_t[:, ::1] ring_d, ring_s  # (templates, keep)

    def __cinit__(self):
        self._masks = NULL
        self._values = NULL
        self._tables = NULL

    def __dealloc__(self):
        PyMem_Free(self._masks)
        PyMem_Free(self._values)
        PyMem_Free(self._tables)

    def __init__(self, list templates, Py_ssize_t keep, Py_ssize_t batch=16):
        """``templates``: per template (masks, values, tables, threshold, toolbox): its retrieval
        tables (uint64 ``(M,)``, uint64 ``(M,)``, int64 ``(M, f + 1)``, contiguous), its τ in fixed
        point and whether it takes the toolbox's steps (else the thesis'); ``keep``: frames of Δ and
        starts kept (at least 2); ``batch``: the most frames left uncomputed (at least 1; at most
        ``keep`` are)."""
        if not templates or keep < 2 or batch < 1:
            raise ValueError("a StreamDTW needs templates, keeps at least 2 frames and a batch of at least 1")
        self.k = len(templates)
        self.keep = keep
        self.batch = min(batch, keep)
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
        self.codes = np.zeros(keep, dtype=np.uint64)
        self.ring_d = np.empty((self.k, keep), dtype=np.int64)
        self.ring_s = np.empty((self.k, keep), dtype=np.int64)
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
        self.done = 0

    def push(self, uint64_t code):
        """The next frame's code."""
        self.codes[self.n % self.keep] = code
        self.n += 1
        if self.n - self.done >= self.batch:
            self._catch_up()

    cdef void _catch_up(self) noexcept:
        """Every template's columns for the frames pushed and not yet computed."""
        cdef Py_ssize_t t, o, m, cur, p1, p2, hi
        cdef int64_t f
        with nogil:
            for t in range(self.k):
                o = self.offsets[t]
                m = self.lengths[t]
                for f in range(self.done, self.n):
                    cur = 2 * (f % 3)
                    p1 = 2 * ((f + 2) % 3)
                    p2 = 2 * ((f + 1) % 3)
                    if self.toolbox[t] != 0:
                        hi = self.highest[t, f % 3] = _pruned_column(
                            self._masks[t], self._values[t], self._tables[t], self.widths[t], m,
                            self.codes[f % self.keep], f, self.thresholds[t],
                            self.highest[t, (f + 2) % 3], self.highest[t, (f + 1) % 3],
                            &self.cols[cur, o], &self.cols[cur + 1, o], &self.cols[p1, o],
                            &self.cols[p1 + 1, o], &self.cols[p2, o], &self.cols[p2 + 1, o])
                    else:
                        _column(self._masks[t], self._values[t], self._tables[t], self.widths[t], m,
                                self.codes[f % self.keep], False, False, f, &self.costs[0],
                                &self.cols[cur, o], &self.cols[cur + 1, o], &self.cols[p1, o],
                                &self.cols[p1 + 1, o], &self.cols[p2, o], &self.cols[p2 + 1, o])
                        hi = m - 1
                    # the last row may not have been written this column: finite only if highest
                    self.ring_d[t, f % self.keep] = self.cols[cur, o + m - 1] if hi == m - 1 else INF
                    self.ring_s[t, f % self.keep] = self.cols[cur + 1, o + m - 1] if hi == m - 1 else NO_START
        self.done = self.n

    def delta(self, Py_ssize_t template, int64_t frame):
        """(Δ, start) of ``template`` at ``frame`` (one of the last ``keep`` pushed); a template
        with the toolbox's steps gives (:data:`INF`, -1) where Δ is above its threshold."""
        if not (0 <= template < self.k and self.n - self.keep <= frame < self.n and frame >= 0):
            raise IndexError(f"frame {frame} is not among the last {self.keep} of {self.n}")
        self._catch_up()
        return self.ring_d[template, frame % self.keep], self.ring_s[template, frame % self.keep]

    def beaten(self, Py_ssize_t skip, int64_t start, int64_t end, int64_t cost):
        """Whether a template other than ``skip`` matches the motion of frames ``start .. end`` more
        cheaply than ``cost`` (fixed point): Δ at some frame e from ``start`` to the last pushed is
        a local minimum (below Δ(e - 1), not above Δ(e + 1) if pushed), at most the template's
        threshold and below ``cost``, and its match (start column .. e) shares more than half of the
        shorter range's frames with ``start .. end``. ``start - 1`` must be among the kept frames
        (or ``start`` the stream's first)."""
        cdef int64_t last = self.n - 1, e, d, before, after, s, shared, shorter
        if start > last or start < 0 or (start > 0 and start - 1 < self.n - self.keep) or start > end:
            raise IndexError(f"frames {start}..{end} are not among the last {self.keep} of {self.n}")
        self._catch_up()
        cdef Py_ssize_t t
        for t in range(self.k):
            if t == skip:
                continue
            for e in range(start, last + 1):
                d = self.ring_d[t, e % self.keep]
                if d >= cost or d > self.thresholds[t]:
                    continue
                before = self.ring_d[t, (e - 1) % self.keep] if e > 0 else INF
                after = self.ring_d[t, (e + 1) % self.keep] if e < last else INF
                if not (d < before and d <= after):
                    continue
                s = self.ring_s[t, e % self.keep]
                shared = min(end, e) - max(start, s) + 1
                shorter = min(end - start, e - s) + 1
                if 2 * shared > shorter:
                    return True
        return False
