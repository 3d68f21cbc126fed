from libc.stdint cimport int64_t, uint64_t


cdef struct Op:
    int op, dst, a, b


cdef struct Test:
    int track, bit, register, cmp, slot


cdef class Bytecode:
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

    cdef void run(self, const double *P, const double *S, const double *T, double *r,
                  uint64_t *f1, uint64_t *f2) noexcept nogil
    cdef void run_many(self, Py_ssize_t n, const double **P, const double **S, const double **T,
                       double *r, uint64_t *f1, uint64_t *f2) noexcept nogil


cdef class FeatureCore:
    cdef Bytecode code
    cdef public object ring
    cdef double[:, ::1] _ring
    cdef double[::1] _thresholds, _regs, _smoothed
    cdef readonly Py_ssize_t keep, latency
    cdef readonly int64_t n, emitted
    cdef readonly uint64_t previous

    cdef int64_t push_ptr(self, const double *rows) noexcept nogil
    cdef void _store(self, const double *rows) noexcept nogil
    cdef double *_point_row(self, int64_t f) noexcept nogil
    cdef void _emit(self, int64_t t, int64_t n) noexcept nogil
    cdef void _smooth(self, int64_t t, int64_t n) noexcept nogil
    cdef int64_t prepare(self, const double *rows) noexcept nogil
    cdef const double *pose(self, int64_t t) noexcept nogil
    cdef const double *smoothed(self) noexcept nogil
    cdef const double *thresholds(self) noexcept nogil
    cdef int64_t finish(self, int64_t t, uint64_t f1, uint64_t f2) noexcept nogil
