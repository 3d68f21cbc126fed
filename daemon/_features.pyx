# cython: language_level=3, boundscheck=False, wraparound=False, initializedcheck=False, cdivision=True
"""The compiled feature program of daemon/features.py run on doubles: a register machine for the
straight-line arithmetic (one operation per instruction, in the program's order, IEEE doubles with
numpy's semantics: x/0 gives inf or nan, minimum and maximum propagate nan), the threshold tests, and
a stream's steady step (velocity points, telescoped window sums, hysteresis) over a ring of poses."""

from libc.math cimport fabs, isnan, sqrt
from libc.string cimport memcpy
from libc.stdint cimport int64_t, uint64_t

import numpy as np

# opcodes and comparisons (daemon.features._assemble writes them)
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


cdef struct Op:
    int op, dst, a, b


cdef struct Test:
    int track, bit, register, cmp, slot


cdef class Bytecode:
    """A feature program: ``ops`` ``(n, 4)`` (opcode, destination register, operand registers;
    MIN/MAX take a start and a count in ``args``, CONST an index in ``consts``; registers
    0..n_rows-1 hold the pose components, the next n_points the smoothed velocities), ``tests``
    ``(t, 5)`` (track 0 =
    loose, 1 = strict; feature bit; register; comparison; threshold slot), ``points`` ``(3K, 2)``
    (the pose components whose difference is a velocity point, -1 for none) and ``windows``
    ``(W, 4)`` (frames after t of the window sum's top and bottom point rows, the point components
    ``first``..``end``) with their ``scales`` (rate / L)."""

    cdef object _keep
    cdef Op *ops
    cdef Py_ssize_t n_ops
    cdef Test *tests_
    cdef Py_ssize_t n_tests
    cdef int64_t[::1] args
    cdef double[::1] consts
    cdef int64_t[:, ::1] points
    cdef int64_t[:, ::1] windows
    cdef double[::1] scales
    cdef readonly Py_ssize_t registers, n_rows, n_points, n_slots
    cdef uint64_t[2] present

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


cdef class FeatureCore:
    """One stream's held poses and hysteresis for a :class:`Bytecode`: ``ring`` ``(keep, 3J + 3K)``
    (frame f in row f mod keep: its pose components, then its velocity points), ``n`` poses stored,
    ``previous`` the last emitted code, the stream's flat thresholds."""

    cdef Bytecode code
    cdef public object ring
    cdef double[:, ::1] _ring
    cdef double[::1] _thresholds, _regs, _smoothed
    cdef readonly Py_ssize_t keep, latency
    cdef public int64_t n
    cdef public uint64_t previous

    def __init__(self, Bytecode code, Py_ssize_t keep, Py_ssize_t latency):
        self.code = code
        self.keep = keep
        self.latency = latency
        self.ring = np.zeros((keep, code.n_rows + code.n_points))
        self._ring = self.ring
        self._thresholds = np.zeros(code.n_slots)
        self._regs = np.zeros(max(1, code.registers))
        self._smoothed = np.zeros(max(1, code.n_points))
        self.n = 0
        self.previous = 0

    def set_thresholds(self, thresholds):
        """The stream's thresholds, flat in the program's slot order."""
        self._thresholds = np.ascontiguousarray(thresholds, dtype=np.float64).copy()
        if self._thresholds.shape[0] != self.code.n_slots:
            raise ValueError(f"{self.code.n_slots} thresholds expected")

    def reset(self):
        self.n = 0
        self.previous = 0

    def store(self, const double[::1] rows):
        """Hold the next pose (components flat, ``3j + c``) and its velocity points."""
        cdef Bytecode c = self.code
        if rows.shape[0] != c.n_rows:
            raise ValueError(f"{c.n_rows} pose components expected")
        cdef Py_ssize_t i, row = self.n % self.keep
        cdef double *out = &self._ring[row, 0]
        with nogil:
            for i in range(c.n_rows):
                out[i] = rows[i]
            for i in range(c.n_points):
                if c.points[i, 1] < 0:
                    out[c.n_rows + i] = rows[c.points[i, 0]]
                else:
                    out[c.n_rows + i] = rows[c.points[i, 0]] - rows[c.points[i, 1]]
        self.n += 1

    def steady(self):
        """The code of frame ``n - 1 - latency`` (every velocity window inside the stream, so each
        window sum telescopes to the difference of two held point rows), after the hysteresis."""
        cdef Bytecode c = self.code
        cdef int64_t t = self.n - 1 - self.latency
        cdef Py_ssize_t w, i, top, bottom
        cdef double scale
        cdef uint64_t f1, f2
        cdef Py_ssize_t keep = self.keep, n_rows = c.n_rows
        with nogil:
            for w in range(c.windows.shape[0]):
                top = ((t + c.windows[w, 0]) % keep + keep) % keep
                bottom = ((t + c.windows[w, 1]) % keep + keep) % keep
                scale = c.scales[w]
                for i in range(c.windows[w, 2], c.windows[w, 3]):
                    self._smoothed[i] = (self._ring[top, n_rows + i] - self._ring[bottom, n_rows + i]) * scale
            c.run(&self._ring[t % keep, 0], &self._smoothed[0], &self._thresholds[0], &self._regs[0], &f1, &f2)
            self.previous = f2 | (self.previous & f1)
        return self.previous

    def evaluate(self, const double[::1] rows, const double[::1] smoothed):
        """The loose and strict tracks (bit k = feature k) of a pose ``rows`` with its smoothed
        velocities (flat, ``3k + c``)."""
        cdef Bytecode c = self.code
        if rows.shape[0] != c.n_rows or smoothed.shape[0] != c.n_points:
            raise ValueError(f"{c.n_rows} pose components and {c.n_points} velocities expected")
        cdef uint64_t f1, f2
        cdef const double *s = &smoothed[0] if c.n_points else &self._smoothed[0]
        c.run(&rows[0], s, &self._thresholds[0], &self._regs[0], &f1, &f2)
        return f1, f2
