from libc.stdint cimport int64_t


cdef class FrameKinematics:
    cdef int64_t[::1] nodes, chans
    cdef unsigned char[::1] first
    cdef double[:, ::1] axes, offsets
    cdef double[::1] orientation, position
    cdef int64_t[:, ::1] translation, pairs
    cdef double[:, ::1] rot, pos
    cdef int64_t[::1] joint_nodes
    cdef readonly Py_ssize_t n_nodes, width
    cdef readonly double scale

    cdef void _check(self, const double[::1] channels, const double[::1] cos, const double[::1] sin) except *
    cdef void local(self, const double *cos, const double *sin, double *rot) noexcept nogil
    cdef void forward(self, const double *channels, const double *cos, const double *sin, bint scaled,
                      double *out) noexcept nogil
    cdef bint joints_into(self, const double *channels, const double *cos, const double *sin,
                          double *out) noexcept nogil
    cdef void joints_many(self, Py_ssize_t n, const double **channels, const double **cos,
                          const double **sin, double **out, bint *finite, double *scratch) noexcept nogil
