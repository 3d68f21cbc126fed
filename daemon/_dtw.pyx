# cython: language_level=3, boundscheck=False, wraparound=False, initializedcheck=False, cdivision=True
"""Compiled subsequence DTW of a quantised template against packed frame codes (see daemon/dtw.py).

The recursion of :func:`daemon.dtw.subsequence_fixed` cell by cell, column by column, on the same
int64 fixed-point costs with the same tie order, so the results are the same integers; the cell
costs come from the template's retrieval tables (popcount of the differing fixed bits)."""

from libc.stdint cimport int64_t, uint64_t

import numpy as np

cdef extern from *:
    int popcount "__builtin_popcountll"(unsigned long long) nogil

cdef int64_t INF = (<int64_t>1) << 46
cdef int64_t NO_START = -1


cdef inline int64_t clamp(int64_t x) noexcept nogil:
    return INF if x > INF else x


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
    cdef const int64_t *tab = &tables[0, 0]
    cdef Py_ssize_t width = tables.shape[1]
    cdef int64_t c, a1, a2, a3, d, s, e_diag, e_left, e_down
    cdef uint64_t code
    cdef bint blk
    for i in range(m):
        p1_d[i] = INF
        p1_s[i] = NO_START
        p2_d[i] = INF
        p2_s[i] = NO_START
    for j in range(n):
        code = codes[j]
        blk = blocked[j] != 0
        for i in range(m):
            cur_c[i] = INF if blk else tab[i * width + popcount((code ^ values[i]) & masks[i])]
        d = cur_c[0]
        cur_d[0] = d
        cur_s[0] = j if d < INF else NO_START
        if toolbox:
            for i in range(1, m):
                c = cur_c[i]
                a1 = p1_d[i - 1]  # (i-1, j-1)
                a2 = p2_d[i - 1]  # (i-1, j-2)
                a3 = p1_d[i - 2] if i >= 2 else INF  # (i-2, j-1)
                if a1 <= a2 and a1 <= a3:
                    d = clamp(a1 + c)
                    s = p1_s[i - 1]
                elif a2 <= a3:
                    d = clamp(a2 + c)
                    s = p2_s[i - 1]
                else:
                    d = clamp(a3 + 2 * c)
                    s = p1_s[i - 2]
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
    (start, end, Δ) in column order."""
    delta_out, start_out = subsequence_codes(masks, values, tables, codes, blocked, toolbox)
    cdef int64_t[::1] delta = delta_out, start = start_out
    cdef Py_ssize_t n = codes.shape[0], j
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
