# cython: language_level=3, boundscheck=False, wraparound=False, initializedcheck=False, cdivision=True
"""A stream's frame step in compiled code, from a checked frame to the index-rate code the keyframe
automata take: forward kinematics (or the announced joint order), the features and the decimation
(daemon/recognizer.py says what each step is). One call per frame, or one call for one frame of
many streams (the bank)."""

from libc.math cimport isfinite
from libc.stdint cimport int64_t

import numpy as np

from daemon._features cimport FeatureCore
from replay._kinematics cimport FrameKinematics

NOTHING = -1
"""No index-rate code this frame (the features' delay, or a frame the decimation skips)."""
NON_FINITE = -2
"""A standard joint is not finite (after forward kinematics)."""


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


def push_channels_many(list streams, const double[::1] channels, const double[::1] cos,
                       const double[::1] sin):
    """:meth:`LiveStream.push_channels` of one frame of each of ``streams``, their channels side by
    side in ``channels`` (and the cosines and sines): the codes, in order."""
    cdef Py_ssize_t at = 0, k
    cdef LiveStream s
    cdef list out = []
    for k in range(len(streams)):
        s = <LiveStream> streams[k]
        if at + s.width > channels.shape[0] or channels.shape[0] != cos.shape[0] or cos.shape[0] != sin.shape[0]:
            raise ValueError("the streams' channels do not fit the arrays")
        out.append(s._channels(&channels[at], &cos[at], &sin[at]))
        at += s.width
    return out
