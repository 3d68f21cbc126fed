# cython: language_level=3, boundscheck=False, wraparound=False, initializedcheck=False, cdivision=True
"""A stream's frame step in compiled code, from a checked frame to the index-rate code the keyframe
automata take: forward kinematics (or the announced joint order), the features and the decimation
(daemon/recognizer.py says what each step is). One call per frame, or one call for one frame of
many streams (the bank)."""

from cpython.buffer cimport PyBUF_C_CONTIGUOUS, PyBUF_FORMAT, PyBuffer_Release, PyObject_GetBuffer
from cpython.mem cimport PyMem_Free, PyMem_Malloc
from libc.math cimport isfinite
from libc.stdint cimport int64_t, uint64_t
from libc.string cimport memcpy

import numpy as np

from daemon._dtw cimport Competition
from daemon._features cimport FeatureCore
from replay._kinematics cimport FrameKinematics

NOTHING = -1
"""No index-rate code this frame (the features' delay, or a frame the decimation skips)."""
NON_FINITE = -2
"""A standard joint is not finite (after forward kinematics)."""
NON_FINITE_CHANNELS = -3
"""A channel is not finite (the frame was not stepped)."""


cdef class LiveStream:
    """One stream: ``kinematics`` (channel frames; None for joint positions, gathered by ``order``,
    the flat index of each standard joint coordinate in the frame), its ``features`` (thresholds
    from ``lengths(rows)``, a callable, on the first frame) and every ``step``-th feature vector
    passed on."""

    cdef readonly object kinematics
    cdef FrameKinematics _kinematics
    cdef readonly FeatureCore features
    cdef object lengths
    cdef object rows_array
    cdef double[::1] rows
    cdef int64_t[::1] order
    cdef readonly Py_ssize_t width
    cdef readonly int64_t step, seen
    cdef public bint started  # whether the stream has had a frame (then ``last`` is its number)
    cdef public int64_t last
    cdef object stage
    cdef Competition competition

    def __init__(self, kinematics, FeatureCore features, lengths, order, Py_ssize_t width, int64_t step):
        self.kinematics = kinematics
        self._kinematics = kinematics
        self.features = features
        self.lengths = lengths
        self.rows_array = np.zeros(features.code.n_rows)
        self.rows = self.rows_array
        self.order = np.ascontiguousarray(order if order is not None else [], dtype=np.int64)
        if kinematics is None and self.order.shape[0] != features.code.n_rows:
            raise ValueError("joint positions need the place of every standard joint coordinate")
        self.width = width
        self.step = step
        self.seen = 0
        self.started = False
        self.last = 0
        self.stage = None
        self.competition = None

    def attach(self, stage, Competition competition):
        """The class stage its index-rate codes go to in :func:`push_many`: ``stage`` (Python: its
        ``start(number)``, ``found(number, confirmations)`` and, without ``competition``,
        ``push(number, code)``) and its compiled ``competition`` (None: the stage has no class)."""
        self.stage = stage
        self.competition = competition

    def push_channels(self, const double[::1] channels, const double[::1] cos, const double[::1] sin):
        """A checked channel frame (finite, ``width`` values) with its half angles' cosines and sines:
        the index-rate code it gives, :data:`NOTHING` or :data:`NON_FINITE`."""
        if channels.shape[0] != self.width or cos.shape[0] != self.width or sin.shape[0] != self.width:
            raise ValueError(f"{self.width} channels expected")
        return self._channels(&channels[0], &cos[0], &sin[0])

    def push_positions(self, const double[::1] positions):
        """A checked positions frame, flat (``3j + c`` in the announced order): as
        :meth:`push_channels`."""
        if positions.shape[0] != self.width:
            raise ValueError(f"{self.width} coordinates expected")
        return self._positions(&positions[0])

    def flush(self):
        """The codes the end of the stream gives (the features' last frames, decimated); then a fresh
        stream."""
        out = []
        for code in self.features.flush():
            if self.seen % self.step == 0:
                out.append(code)
            self.seen += 1
        self.seen = 0
        return out

    cdef int64_t _channels(self, const double *channels, const double *cos, const double *sin):
        cdef bint finite
        with nogil:
            finite = self._kinematics.joints_into(channels, cos, sin, &self.rows[0])
        return self._advance() if finite else NON_FINITE

    cdef int64_t _positions(self, const double *positions):
        cdef Py_ssize_t i
        cdef double v
        cdef bint finite = True
        for i in range(self.order.shape[0]):
            v = positions[self.order[i]]
            self.rows[i] = v
            if not isfinite(v):
                finite = False
        return self._advance() if finite else NON_FINITE

    cdef int64_t _advance(self):
        if self.features.n == 0:
            self.features.set_thresholds(self.lengths(self.rows_array))
        cdef int64_t code = self.features.push_ptr(&self.rows[0])
        if code < 0:
            return NOTHING
        self.seen += 1
        return code if (self.seen - 1) % self.step == 0 else NOTHING


cdef inline bint fast_values(object frame, LiveStream s, Py_buffer *view):
    """Whether ``frame`` exposes C-contiguous native doubles of the stream's shape (``view`` then
    holds them, to release); else the checks in Python decide."""
    try:
        PyObject_GetBuffer(frame, view, PyBUF_C_CONTIGUOUS | PyBUF_FORMAT)
    except (TypeError, ValueError, BufferError):  # not a buffer, or not a contiguous one
        return False
    cdef bint ok = view.format != NULL and view.format[0] == b'd' and view.format[1] == 0
    if ok:
        if s._kinematics is not None:
            ok = view.ndim == 1 and view.shape[0] == s.width
        else:
            ok = view.ndim == 2 and view.shape[0] * 3 == s.width and view.shape[1] == 3
    if not ok:
        PyBuffer_Release(view)
    return ok


def push_many(list frames, refused):
    """The live path's per-frame step of one frame ``(recogniser, number, values)`` each of distinct
    :class:`daemon.recognizer.Recognizer` s (their ``_live`` a :class:`LiveStream` with its stage
    attached): the frames checked (a consecutive int number and C-contiguous doubles of the
    stream's shape here, anything else by the recogniser's ``_check``, which refuses or converts),
    the channel frames gathered side by side and the cosines and sines of their half angles taken in
    one numpy call each, each frame stepped (forward kinematics, features, decimation) and its
    index-rate code pushed to its compiled competition. Python runs per frame only for a refusal,
    a stream's first frame and a confirmation. ``refused``: the exception class ``_check`` raises
    for a frame it refuses. Returns (detections, [(position, the refusal)])."""
    cdef Py_ssize_t n = len(frames), i, k, taken = 0, total = 0, at
    cdef Py_ssize_t *pos = <Py_ssize_t *> PyMem_Malloc((n + 1) * sizeof(Py_ssize_t))
    cdef int64_t *nums = <int64_t *> PyMem_Malloc((n + 1) * sizeof(int64_t))
    cdef int64_t *codes = <int64_t *> PyMem_Malloc((n + 1) * sizeof(int64_t))
    cdef Py_ssize_t *offs = <Py_ssize_t *> PyMem_Malloc((n + 1) * sizeof(Py_ssize_t))
    cdef Py_buffer view
    cdef LiveStream s
    cdef bint fast, finite
    cdef int64_t num = 0, code
    cdef const double *src
    cdef double[::1] flat, cos, sin
    cdef list errors = [], detections = [], kept = []
    if pos == NULL or nums == NULL or codes == NULL or offs == NULL:
        PyMem_Free(pos)
        PyMem_Free(nums)
        PyMem_Free(codes)
        PyMem_Free(offs)
        raise MemoryError()
    try:
        for i in range(n):
            r, number, frame = <tuple> frames[i]
            s = <LiveStream> r._live
            if s._kinematics is not None:
                total += s.width
        flat_array = np.empty(max(1, total))
        flat = flat_array
        total = 0
        # the checks; the positions frames stepped, the channel frames gathered
        for i in range(n):
            r, number, frame = <tuple> frames[i]
            s = <LiveStream> r._live
            fast = False
            if s.started and type(number) is int:
                try:
                    num = number
                    fast = num == s.last + 1
                except OverflowError:
                    pass
            if fast:
                fast = fast_values(frame, s, &view)
            if not fast:
                try:
                    checked, values = r._check(number, frame)
                except refused as e:
                    errors.append((i, e))
                    continue
                try:
                    num = checked
                except OverflowError:
                    errors.append((i, refused(f"frame number {checked} is out of range", "type", stream=r.stream)))
                    continue
                if not fast_values(values, s, &view):
                    raise AssertionError("a checked frame is C-contiguous doubles of the stream's shape")
            src = <const double *> view.buf
            if s._kinematics is None:
                code = s._positions(src)
            else:
                finite = True
                for k in range(s.width):
                    if not isfinite(src[k]):
                        finite = False
                        break
                code = NOTHING if finite else NON_FINITE - 1
                if finite:
                    memcpy(&flat[total], src, s.width * sizeof(double))
                offs[taken] = total
                total += s.width
            PyBuffer_Release(&view)
            pos[taken] = i
            nums[taken] = num
            codes[taken] = code
            taken += 1
        if total:
            half = np.multiply(flat_array[:total], 0.5)
            cos = np.cos(half)
            sin = np.sin(half)
        # the channel frames stepped; each frame's code to its stage, in the order of the frames
        for k in range(taken):
            i = pos[k]
            r = (<tuple> frames[i])[0]
            s = <LiveStream> r._live
            code = codes[k]
            if s._kinematics is not None and code == NOTHING:
                at = offs[k]
                code = s._channels(&flat[at], &cos[at], &sin[at])
            num = nums[k]
            if code < NOTHING:
                errors.append((i, r._refusal(num, code)))
                continue
            if not s.started:
                s.stage.start(num)
                s.started = True
            s.last = num
            if code == NOTHING:
                continue
            if s.competition is not None:
                found = s.competition.push_c(<uint64_t> code)
                if found is not None:
                    detections += s.stage.found(num, found)
            else:
                detections += s.stage.push(num, code)
    finally:
        PyMem_Free(pos)
        PyMem_Free(nums)
        PyMem_Free(codes)
        PyMem_Free(offs)
    if len(errors) > 1:
        errors.sort(key=_position)
    return detections, errors


def _position(item):
    return item[0]
