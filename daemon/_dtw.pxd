from libc.stdint cimport int64_t, uint64_t


cdef struct Candidate:
    # a local minimum of one template's stream-wide delta, ordered by (cost, end, member, start)
    int64_t cost
    int64_t end
    int64_t member
    int64_t start


cdef struct Buf:
    # a growable FIFO of rows of ``stride`` int64: rows head .. n - 1 are held
    int64_t *data
    Py_ssize_t head
    Py_ssize_t n
    Py_ssize_t cap
    Py_ssize_t stride


cdef class StreamDTW:
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
    cdef int64_t[:, ::1] highest  # (templates, 3): each slot's highest written row (-1: none)
    cdef unsigned char[::1] active  # per template: whether it computes columns (else they are empty)

    cdef void _reset(self) noexcept nogil
    cdef int64_t _last(self, Py_ssize_t t, int64_t f) noexcept nogil
    cdef int64_t _start(self, Py_ssize_t t, int64_t f) noexcept nogil
    cdef void _compute(self, Py_ssize_t t, uint64_t code, int64_t f) noexcept nogil
    cdef void _clear(self, Py_ssize_t t) noexcept nogil
    cdef bint _minimum(self, Py_ssize_t t, int64_t e, Candidate *out) noexcept nogil
    cdef Py_ssize_t push_into(self, uint64_t code, Candidate *out) noexcept nogil
    cdef Py_ssize_t replay_into(self, Py_ssize_t t, int64_t a, int64_t lowest, const uint64_t *ring,
                                Py_ssize_t cap, Candidate *out) noexcept nogil
    cdef Py_ssize_t finish_into(self, Candidate *out) noexcept nogil
    cdef bint blocks_c(self, int64_t cost, int64_t start, int64_t end, Py_ssize_t lo,
                       Py_ssize_t hi) noexcept nogil
    cdef Py_ssize_t progress_c(self, Py_ssize_t t, int64_t since, int64_t *d) noexcept nogil
    cdef bint reaches_c(self, Py_ssize_t lo, Py_ssize_t hi, int64_t end) noexcept nogil


cdef class Competition:
    cdef readonly StreamDTW dtw
    cdef readonly object automata
    cdef readonly bint compete
    cdef readonly int64_t hold, memory, n
    cdef int64_t[::1] owner, lo, hi, slot, gated_of
    cdef Py_ssize_t n_gated
    cdef Candidate *found  # a frame's minima (one per template, and those of the windows it opens)
    cdef Py_ssize_t found_cap
    cdef Candidate *scratch  # the held candidates a frame makes final
    cdef Py_ssize_t scratch_cap
    cdef Buf held, recent, published
    cdef uint64_t[::1] ring  # the codes of the last ``back`` + 1 frames, frame f at f % len
    cdef int64_t back  # how far back a window may open
    cdef int64_t[::1] before, after  # per gated class: its windows' frames before and after a match
    cdef int64_t[::1] seg_s, seg_e  # per gated class: its window (first, last frame; last < -1: none)
    cdef unsigned char[::1] initial  # per template: whether it computes columns at a stream's start
    cdef int64_t[::1] cls_lo, cls_hi  # per class: its templates lo .. hi - 1
    cdef Py_ssize_t n_classes
    cdef int64_t[:, ::1] hits  # per gated class: its last whole keyframe hit (progress; HIT_* fields)
    cdef list hit_frames  # per gated class: that hit's keyframe frames
    cdef int64_t[:, ::1] last_pub  # per gated class: start, end, frame of its last detection published
    cdef int64_t[::1] spent  # per class: the last frame a candidate of it ended (-1: none yet)

    cdef list push_c(self, uint64_t code)
    cdef Py_ssize_t _open(self, Py_ssize_t g, int64_t a, int64_t b, int64_t j, Py_ssize_t found) except -1
    cdef void _sort_found(self, Py_ssize_t found) noexcept nogil
    cdef Py_ssize_t gated_class(self, Py_ssize_t g) noexcept nogil
    cdef bint _rival(self, const Candidate *x, const Candidate *y) noexcept nogil
    cdef int _arrive(self, Candidate *y) except -1
    cdef void _spend(self, const Candidate *x) noexcept nogil
    cdef list _decide(self, int64_t j, bint ended)
    cdef void _forget(self, int64_t j) noexcept
    cdef void _follow_hit(self, Py_ssize_t g, int64_t j) except *
    cdef bint _may_give(self, Py_ssize_t g) noexcept
