# cython: language_level=3, boundscheck=False, wraparound=False, initializedcheck=False, cdivision=True
"""The compiled feature program of daemon.features run on doubles: a register machine for the
straight-line arithmetic (one operation per instruction, in the program's order, IEEE doubles with
numpy's semantics: x/0 gives inf or nan, minimum and maximum propagate nan), the threshold tests, and
a stream's steady step (velocity points, telescoped window sums, hysteresis) over a ring of poses."""

from libc.math cimport fabs, isnan, sqrt
from libc.string cimport memcpy
from libc.stdint cimport int64_t, uint64_t

import numpy as np

# opcodes and comparisons (daemon.features.assembler writes them)
cdef enum:
    OP_ADD = 0
    OP_SUB = 1
    OP_MUL = 2
    OP_DIV = 3
    OP_SQRT = 4
    OP_ABS = 5
    OP_MIN = 6
    OP_MAX = 7
    OP_CONST = 8
    CMP_LT = 0
    CMP_LE = 1
    CMP_GT = 2
    CMP_GE = 3


cdef class Bytecode:
    """A feature program: ``ops`` ``(n, 4)`` (opcode, destination register, operand registers;
    MIN/MAX take a start and a count in ``args``, CONST an index in ``consts``; registers
    0..n_rows-1 hold the pose components, the next n_points the smoothed velocities), ``tests``
    ``(t, 5)`` (track 0 =
    loose, 1 = strict; feature bit; register; comparison; threshold slot), ``points`` ``(3K, 2)``
    (the pose components whose difference is a velocity point, -1 for none) and ``windows``
    ``(W, 4)`` (frames after t of the window sum's top and bottom point rows, the point components
    ``first``..``end``) with their ``scales`` (rate / L)."""

    def __init__(self, ops, args, consts, tests, points, windows, scales, Py_ssize_t registers,
                 Py_ssize_t n_rows, Py_ssize_t n_slots):
        cdef Py_ssize_t i
        op_table = np.ascontiguousarray(ops, dtype=np.int32).reshape(-1, 4)
        test_table = np.ascontiguousarray(tests, dtype=np.int32).reshape(-1, 5)
        self._keep = (op_table, test_table)  # the structs below point into these
        cdef int[:, ::1] o = op_table
        cdef int[:, ::1] t = test_table
        self.n_ops = o.shape[0]
        self.ops = <Op *> &o[0, 0] if self.n_ops else NULL
        self.n_tests = t.shape[0]
        self.tests_ = <Test *> &t[0, 0] if self.n_tests else NULL
        self.args = np.ascontiguousarray(args, dtype=np.int64)
        self.consts = np.ascontiguousarray(consts, dtype=np.float64)
        self.points = np.ascontiguousarray(points, dtype=np.int64).reshape(-1, 2)
        self.windows = np.ascontiguousarray(windows, dtype=np.int64).reshape(-1, 4)
        self.scales = np.ascontiguousarray(scales, dtype=np.float64)
        self.registers = registers
        self.n_rows = n_rows
        self.n_points = self.points.shape[0]
        self.n_slots = n_slots
        self.present[0] = 0
        self.present[1] = 0
        for i in range(self.n_tests):
            self.present[self.tests_[i].track] |= (<uint64_t>1) << self.tests_[i].bit

    cdef void run(self, const double *P, const double *S, const double *T, double *r,
                  uint64_t *f1, uint64_t *f2) noexcept nogil:
        cdef Py_ssize_t i, k
        cdef Op o
        cdef Test t
        cdef double x, y
        cdef bint ok
        cdef uint64_t fail[2]
        memcpy(r, P, self.n_rows * sizeof(double))
        memcpy(r + self.n_rows, S, self.n_points * sizeof(double))
        for i in range(self.n_ops):
            o = self.ops[i]
            if o.op == OP_ADD:
                r[o.dst] = r[o.a] + r[o.b]
            elif o.op == OP_SUB:
                r[o.dst] = r[o.a] - r[o.b]
            elif o.op == OP_MUL:
                r[o.dst] = r[o.a] * r[o.b]
            elif o.op == OP_DIV:
                r[o.dst] = r[o.a] / r[o.b]
            elif o.op == OP_SQRT:
                r[o.dst] = sqrt(r[o.a])
            elif o.op == OP_ABS:
                r[o.dst] = fabs(r[o.a])
            elif o.op == OP_MIN:
                # numpy's minimum.reduce: pairwise from the left, nan wins
                x = r[self.args[o.a]]
                for k in range(1, o.b):
                    y = r[self.args[o.a + k]]
                    if not (x < y or isnan(x)):
                        x = y
                r[o.dst] = x
            elif o.op == OP_MAX:
                x = r[self.args[o.a]]
                for k in range(1, o.b):
                    y = r[self.args[o.a + k]]
                    if not (x > y or isnan(x)):
                        x = y
                r[o.dst] = x
            else:
                r[o.dst] = self.consts[o.a]
        fail[0] = 0
        fail[1] = 0
        for i in range(self.n_tests):
            t = self.tests_[i]
            x = r[t.register]
            y = T[t.slot]
            if t.cmp == CMP_LT:
                ok = x < y
            elif t.cmp == CMP_LE:
                ok = x <= y
            elif t.cmp == CMP_GT:
                ok = x > y
            else:
                ok = x >= y
            if not ok:
                fail[t.track] |= (<uint64_t>1) << t.bit
        f1[0] = self.present[0] & ~fail[0]
        f2[0] = self.present[1] & ~fail[1]


    cdef void run_many(self, Py_ssize_t n, const double **P, const double **S, const double **T,
                       double *r, uint64_t *f1, uint64_t *f2) noexcept nogil:
        """:meth:`run` of ``n`` frames at once (each its pose ``P[s]``, smoothed velocities ``S[s]``
        and thresholds ``T[s]``; its bits into ``f1[s]``, ``f2[s]``), every instruction over all of
        them: register k of frame s in ``r[k * n + s]`` (``registers * n`` doubles). Each frame's
        operations are :meth:`run`'s in its order, so its bits are the same."""
        cdef Py_ssize_t i, k, j, rows = self.n_rows
        cdef Op o
        cdef Test t
        cdef double x, y
        cdef double *d
        cdef const double *a
        cdef const double *b
        cdef uint64_t bit
        cdef uint64_t *fail
        cdef Py_ssize_t slot
        cdef const int64_t *args = &self.args[0] if self.args.shape[0] else NULL
        for j in range(n):
            for i in range(rows):
                r[i * n + j] = P[j][i]
            for i in range(self.n_points):
                r[(rows + i) * n + j] = S[j][i]
            f1[j] = 0
            f2[j] = 0
        for i in range(self.n_ops):
            o = self.ops[i]
            d = &r[o.dst * n]
            a = &r[o.a * n]
            b = &r[o.b * n]
            if o.op == OP_ADD:
                for j in range(n):
                    d[j] = a[j] + b[j]
            elif o.op == OP_SUB:
                for j in range(n):
                    d[j] = a[j] - b[j]
            elif o.op == OP_MUL:
                for j in range(n):
                    d[j] = a[j] * b[j]
            elif o.op == OP_DIV:
                for j in range(n):
                    d[j] = a[j] / b[j]
            elif o.op == OP_SQRT:
                for j in range(n):
                    d[j] = sqrt(a[j])
            elif o.op == OP_ABS:
                for j in range(n):
                    d[j] = fabs(a[j])
            elif o.op == OP_MIN:
                for j in range(n):
                    x = r[args[o.a] * n + j]
                    for k in range(1, o.b):
                        y = r[args[o.a + k] * n + j]
                        if not (x < y or isnan(x)):
                            x = y
                    d[j] = x
            elif o.op == OP_MAX:
                for j in range(n):
                    x = r[args[o.a] * n + j]
                    for k in range(1, o.b):
                        y = r[args[o.a + k] * n + j]
                        if not (x > y or isnan(x)):
                            x = y
                    d[j] = x
            else:
                x = self.consts[o.a]
                for j in range(n):
                    d[j] = x
        for i in range(self.n_tests):  # f1, f2 collect the failures first
            t = self.tests_[i]
            a = &r[t.register * n]
            bit = (<uint64_t>1) << t.bit
            fail = f1 if t.track == 0 else f2
            slot = t.slot
            if t.cmp == CMP_LT:
                for j in range(n):
                    if not (a[j] < T[j][slot]):
                        fail[j] |= bit
            elif t.cmp == CMP_LE:
                for j in range(n):
                    if not (a[j] <= T[j][slot]):
                        fail[j] |= bit
            elif t.cmp == CMP_GT:
                for j in range(n):
                    if not (a[j] > T[j][slot]):
                        fail[j] |= bit
            else:
                for j in range(n):
                    if not (a[j] >= T[j][slot]):
                        fail[j] |= bit
        for j in range(n):
            f1[j] = self.present[0] & ~f1[j]
            f2[j] = self.present[1] & ~f2[j]


cdef inline Py_ssize_t mirror(Py_ssize_t j, Py_ssize_t m) noexcept nogil:
    """``j`` reflected into [0, m) with the edge repeated, periodically (padarray's 'symmetric')."""
    cdef Py_ssize_t r = j % (2 * m)
    if r < 0:
        r += 2 * m
    return r if r < m else 2 * m - 1 - r


cdef class FeatureCore:
    """One stream's features for a :class:`Bytecode` (the algorithm of
    :class:`daemon.features.FeatureStream`): ``ring`` ``(keep, 3J + 3K)`` holds frame f in row
    f mod keep (its pose components, then its velocity points); ``n`` poses stored, the vectors of
    the first ``emitted`` frames emitted, ``previous`` the last emitted code (the hysteresis'
    memory); the stream's flat thresholds. A frame whose velocity windows reach past either end of
    the stream has them mirrored there, as :func:`daemon.features.velocity.smooth` does."""

    def __init__(self, Bytecode code, Py_ssize_t keep, Py_ssize_t latency):
        self.code = code
        self.keep = keep
        self.latency = latency
        self.ring = np.zeros((keep, code.n_rows + code.n_points))
        self._ring = self.ring
        self._thresholds = np.zeros(max(1, code.n_slots))
        self._regs = np.zeros(max(1, code.registers))
        self._smoothed = np.zeros(max(1, code.n_points))
        self.reset()

    def set_thresholds(self, thresholds):
        """The stream's thresholds, flat in the program's slot order."""
        t = np.ascontiguousarray(thresholds, dtype=np.float64).copy()
        if t.shape[0] != self.code.n_slots:
            raise ValueError(f"{self.code.n_slots} thresholds expected")
        self._thresholds = t if t.shape[0] else np.zeros(1)

    def reset(self):
        self.n = 0
        self.emitted = 0
        self.previous = 0

    def state(self):
        """What :meth:`restore` needs to go on as this stream would: (n, emitted, previous, the
        thresholds and the ring as float64 bytes)."""
        return (self.n, self.emitted, self.previous, np.asarray(self._thresholds).tobytes(), self.ring.tobytes())

    def restore(self, state):
        """Take over a :meth:`state` of a core of the same program and ``keep``; ValueError naming
        the part that does not fit."""
        n, emitted, previous, thresholds, ring = state
        t = np.frombuffer(thresholds, dtype=np.float64)
        r = np.frombuffer(ring, dtype=np.float64)
        if t.shape[0] != max(1, self.code.n_slots):
            raise ValueError(f"features: {max(1, self.code.n_slots)} thresholds expected, got {t.shape[0]}")
        if r.shape[0] != self.ring.size:
            raise ValueError(f"features: a ring of {self.ring.size} values expected, got {r.shape[0]}")
        if not 0 <= emitted <= n or not 0 <= previous < (1 << 64):
            raise ValueError("features: frames emitted must lie between 0 and those stored")
        self.ring[...] = r.reshape(self.ring.shape)
        self._thresholds = t.copy()
        self.n = n
        self.emitted = emitted
        self.previous = previous

    def push(self, const double[::1] rows):
        """Hold the next pose (finite components, flat ``3j + c``); the code of the frame that became
        final (``latency`` frames back), or -1."""
        cdef Bytecode c = self.code
        if rows.shape[0] != c.n_rows:
            raise ValueError(f"{c.n_rows} pose components expected")
        cdef int64_t code
        with nogil:
            code = self.push_ptr(&rows[0])
        return code

    cdef int64_t push_ptr(self, const double *rows) noexcept nogil:
        """:meth:`push` of ``n_rows`` components at ``rows``."""
        self._store(rows)
        cdef int64_t t = self.n - 1 - self.latency
        if t < 0:
            return -1
        self._emit(t, self.n)
        return <int64_t> self.previous

    def flush(self):
        """The codes of the frames not yet emitted, their windows mirrored at the stream's end; then
        a fresh stream."""
        out = []
        cdef int64_t t, n = self.n
        for t in range(self.emitted, n):
            with nogil:
                self._emit(t, n)
            out.append(self.previous)
        self.reset()
        return out

    cdef void _store(self, const double *rows) noexcept nogil:
        cdef Py_ssize_t i
        cdef double *out = &self._ring[self.n % self.keep, 0]
        for i in range(self.code.n_rows):
            out[i] = rows[i]
        for i in range(self.code.n_points):
            if self.code.points[i, 1] < 0:
                out[self.code.n_rows + i] = rows[self.code.points[i, 0]]
            else:
                out[self.code.n_rows + i] = rows[self.code.points[i, 0]] - rows[self.code.points[i, 1]]
        self.n += 1

    cdef double *_point_row(self, int64_t f) noexcept nogil:
        return &self._ring[f % self.keep, self.code.n_rows]

    cdef void _emit(self, int64_t t, int64_t n) noexcept nogil:
        """Frame ``t`` of ``n`` frames: its smoothed velocities, tracks and hysteresis."""
        cdef uint64_t f1, f2
        self._smooth(t, n)
        self.code.run(&self._ring[t % self.keep, 0], &self._smoothed[0], &self._thresholds[0], &self._regs[0], &f1, &f2)
        self.finish(t, f1, f2)

    cdef int64_t prepare(self, const double *rows) noexcept nogil:
        """:meth:`push_ptr` up to the program: the pose stored and the smoothed velocities of the
        frame that becomes final; that frame (-1: none yet). :meth:`Bytecode.run_many` of
        :meth:`pose`, :meth:`smoothed` and :meth:`thresholds`, then :meth:`finish`, is the rest."""
        self._store(rows)
        cdef int64_t t = self.n - 1 - self.latency
        if t >= 0:
            self._smooth(t, self.n)
        return t

    cdef const double *pose(self, int64_t t) noexcept nogil:
        return &self._ring[t % self.keep, 0]

    cdef const double *smoothed(self) noexcept nogil:
        return &self._smoothed[0]

    cdef const double *thresholds(self) noexcept nogil:
        return &self._thresholds[0]

    cdef int64_t finish(self, int64_t t, uint64_t f1, uint64_t f2) noexcept nogil:
        """Frame ``t``'s tracks ``f1``, ``f2`` through the hysteresis: its code."""
        self.previous = f2 | (self.previous & f1)
        self.emitted = t + 1
        return <int64_t> self.previous

    cdef void _smooth(self, int64_t t, int64_t n) noexcept nogil:
        """Frame ``t``'s smoothed velocities (of ``n`` frames) into ``_smoothed``."""
        cdef Py_ssize_t w, i, k, big_l, h, first, end, m
        cdef double scale, acc
        cdef double *top
        cdef double *bottom
        for w in range(self.code.windows.shape[0]):
            h = 1 - self.code.windows[w, 1]
            big_l = self.code.windows[w, 0] - self.code.windows[w, 1]
            first = self.code.windows[w, 2]
            end = self.code.windows[w, 3]
            scale = self.code.scales[w]
            if h - 1 <= t < n - big_l + h - 1:  # the window sum telescopes
                top = self._point_row(t + big_l - h + 1)
                bottom = self._point_row(t - h + 1)
                for i in range(first, end):
                    self._smoothed[i] = (top[i] - bottom[i]) * scale
            elif n < 2:
                for i in range(first, end):
                    self._smoothed[i] = 0.0
            else:  # forward differences at mirrored indices, summed in order
                for i in range(first, end):
                    acc = 0.0
                    for k in range(big_l):
                        m = t + k - (h - 1)
                        m = mirror(mirror(m, big_l), n) if n < big_l else mirror(m, n)
                        if m > n - 2:
                            m = n - 2
                        if k == 0:
                            acc = self._point_row(m + 1)[i] - self._point_row(m)[i]
                        else:
                            acc = acc + (self._point_row(m + 1)[i] - self._point_row(m)[i])
                    self._smoothed[i] = acc * scale
