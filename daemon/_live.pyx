# cython: language_level=3, boundscheck=False, wraparound=False, initializedcheck=False, cdivision=True
"""The live path's frame step in compiled code: a stream's state (:class:`LiveStream`: the
decimation, forward kinematics or the announced joint order, the features, and the class stage's
compiled competition it hands its index-rate codes to), and :func:`push_many`, one frame of each of
many streams in one call, in passes over all of them, forward kinematics and the feature program by
blocks of streams (daemon/recognizer.py says what each step is)."""

from cpython.buffer cimport PyBUF_C_CONTIGUOUS, PyBUF_FORMAT, PyBuffer_Release, PyObject_GetBuffer
from cpython.mem cimport PyMem_Free, PyMem_Malloc, PyMem_Realloc
from cpython.ref cimport PyObject
from libc.math cimport isfinite
from libc.stdint cimport int64_t, uint64_t
from libc.string cimport memcpy

import numpy as np

from daemon._dtw cimport Competition
from daemon._features cimport Bytecode, FeatureCore
from replay._kinematics cimport FrameKinematics

cdef enum:
    C_NOTHING = -1
    C_NON_FINITE = -2
    C_NON_FINITE_CHANNELS = -3

NOTHING = C_NOTHING
"""No index-rate code this frame (the features' delay, or a frame the decimation leaves)."""
NON_FINITE = C_NON_FINITE
"""A standard joint is not finite (after forward kinematics)."""
NON_FINITE_CHANNELS = C_NON_FINITE_CHANNELS
"""A channel is not finite (the frame was not stepped)."""


cdef class LiveStream:
    """One stream: of every ``step``-th frame from the first, or with ``per`` > 1 of frame
    ``round(j·step/per)`` for each index frame ``j`` (the index frames; the others are counted and
    left; :class:`daemon.frames.FrameClock`), the pose by ``kinematics`` (channel frames; None for joint positions,
    gathered by ``order``, the flat index of each standard joint coordinate in the frame) into its
    ``features`` at the index rate (thresholds from ``lengths(rows)``, a callable, on the first
    frame), whose every vector is an index-rate code."""

    cdef readonly object kinematics
    cdef FrameKinematics _kinematics
    cdef readonly FeatureCore features
    cdef object lengths
    cdef object rows_array
    cdef double[::1] rows
    cdef object before_array
    cdef double[::1] before  # with per > 1: the pose of the frame before an index frame's instant
    cdef int64_t[::1] order
    cdef readonly Py_ssize_t width
    cdef readonly int64_t step, per, seen
    cdef public bint started  # whether the stream has had a frame (then ``last`` is its number)
    cdef int64_t mark  # the last push_many call with a frame of the stream
    cdef public int64_t last
    cdef object stage
    cdef Competition competition

    def __init__(
        self, kinematics, FeatureCore features, lengths, order, Py_ssize_t width, int64_t step, int64_t per=1
    ):
        self.kinematics = kinematics
        self._kinematics = kinematics
        self.features = features
        self.lengths = lengths
        self.rows_array = np.zeros(features.code.n_rows)
        self.rows = self.rows_array
        self.before_array = np.zeros(features.code.n_rows)
        self.before = self.before_array
        self.order = np.ascontiguousarray(order if order is not None else [], dtype=np.int64)
        if kinematics is None and self.order.shape[0] != features.code.n_rows:
            raise ValueError("joint positions need the place of every standard joint coordinate")
        self.width = width
        if not step >= per >= 1:
            raise ValueError(f"live stream: step {step} and per {per} need step >= per >= 1")
        self.step = step
        self.per = per
        self.seen = 0
        self.started = False
        self.last = 0
        self.mark = 0
        self.stage = None
        self.competition = None

    def attach(self, stage, Competition competition):
        """The class stage its index-rate codes go to in :func:`push_many`: ``stage`` (Python: its
        ``start(number)``, ``found(number, confirmations)`` and, without ``competition``,
        ``push(number, code)``) and its compiled ``competition`` (None: the stage has no class)."""
        self.stage = stage
        self.competition = competition

    def state(self):
        """What :meth:`restore` needs to go on as this stream would, but for its features' and its
        competition's own states: (frames taken since the decimation began, started, last), and with
        ``per`` > 1 the pose kept for the next index frame's instant (bytes)."""
        if self.per == 1:
            return (self.seen, self.started, self.last)
        return (self.seen, self.started, self.last, self.before_array.tobytes())

    def restore(self, state):
        if len(state) != (3 if self.per == 1 else 4):
            raise ValueError("live stream: a state of another rate")
        seen, started, last = state[:3]
        if seen < 0:
            raise ValueError("live stream: frames seen must be >= 0")
        if self.per > 1:
            kept = np.frombuffer(state[3], dtype=np.float64)
            if kept.shape[0] != self.before.shape[0]:
                raise ValueError("live stream: a kept pose of another size")
            self.before_array[:] = kept
        self.seen = seen
        self.started = started
        self.last = last

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
        """The codes the end of the stream gives (the features' last index frames); then a fresh
        stream."""
        out = list(self.features.flush())
        self.seen = 0
        return out

    cdef bint _keeps(self):
        """Whether the stream's next frame is an index frame's: the first at or after its instant
        (daemon.frames.FrameClock)."""
        if self.per == 1:
            return self.seen % self.step == 0
        return (self.seen * self.per // self.step) * self.step > (self.seen - 1) * self.per

    cdef bint _precedes(self):
        """Whether the frame after the next is an index frame's whose instant lies between them
        (the next frame's pose is then kept to blend)."""
        cdef int64_t j
        if self.per == 1:
            return False
        j = (self.seen + 1) * self.per // self.step
        return j * self.step > self.seen * self.per and (j * self.step) % self.per != 0

    cdef bint _needs(self):
        """Whether the next frame's pose is computed."""
        return self._keeps() or self._precedes()

    cdef void _blend(self):
        """The frame's pose in ``rows``: kept if the next index frame's instant follows it; made the
        pose at the index frame's instant if that lies before it, ``before + w·(pose - before)`` with
        ``w`` = the instant's fraction of a frame, as :func:`daemon.features.sample_poses` does."""
        cdef Py_ssize_t k
        cdef int64_t r = 0
        cdef double w, v
        cdef bint keep
        if self.per == 1:
            return
        keep = self._precedes()
        if self._keeps():
            r = ((self.seen * self.per // self.step) * self.step) % self.per
        if r == 0 and not keep:
            return
        w = <double> r / <double> self.per
        for k in range(self.rows.shape[0]):
            v = self.rows[k]
            if r != 0:
                self.rows[k] = self.before[k] + w * (v - self.before[k])
            if keep:
                self.before[k] = v

    cdef int64_t _channels(self, const double *channels, const double *cos, const double *sin):
        cdef bint keep = self._keeps()
        if self._needs():
            if not self._pose_channels(channels, cos, sin):
                return C_NON_FINITE
            self._blend()
        self.seen += 1
        return self._advance() if keep else C_NOTHING

    cdef int64_t _positions(self, const double *positions):
        cdef bint keep = self._keeps()
        if not self._pose_positions(positions):  # every frame's joints checked, as push_many does
            return C_NON_FINITE
        self._blend()
        self.seen += 1
        return self._advance() if keep else C_NOTHING

    cdef bint _pose_channels(self, const double *channels, const double *cos, const double *sin):
        """Forward kinematics of a channel frame into ``rows``: whether every joint is finite."""
        return self._kinematics.joints_into(channels, cos, sin, &self.rows[0])

    cdef bint _pose_positions(self, const double *positions):
        """A positions frame's standard joints into ``rows``: whether every one is finite."""
        cdef Py_ssize_t i
        cdef double v
        cdef bint finite = True
        for i in range(self.order.shape[0]):
            v = positions[self.order[i]]
            self.rows[i] = v
            if not isfinite(v):
                finite = False
        return finite

    cdef int64_t _prepare(self):
        """The pose in ``rows`` to the features up to their program (:meth:`FeatureCore.prepare`):
        the frame that becomes final (-1: none)."""
        if self.features.n == 0:
            self.features.set_thresholds(self.lengths(self.rows_array))
        return self.features.prepare(&self.rows[0])

    cdef int64_t _advance(self):
        """The index frame's pose in ``rows`` to the features: the code that became final, or
        :data:`NOTHING`."""
        if self.features.n == 0:
            self.features.set_thresholds(self.lengths(self.rows_array))
        cdef int64_t code = self.features.push_ptr(&self.rows[0])
        return C_NOTHING if code < 0 else code


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


cdef enum:
    BLOCK = 32  # frames per block of forward kinematics or of the feature program (registers: 32 x ~6 KB)

cdef int64_t _tick = 0  # push_many's calls: a stream marked with this one has a frame in it
cdef double *_registers = NULL  # the register block of run_many, grown as needed (the GIL guards it)
cdef Py_ssize_t _registers_size = 0


cdef double *registers(Py_ssize_t size) except NULL:
    global _registers, _registers_size
    cdef double *grown
    if size > _registers_size:
        grown = <double *> PyMem_Realloc(_registers, size * sizeof(double))
        if grown == NULL:
            raise MemoryError()
        _registers = grown
        _registers_size = size
    return _registers


def push_many(list frames, refused, dict streams=None):
    """The live path's per-frame step of one frame ``(recogniser, number, values)`` each of distinct
    :class:`daemon.recognizer.Recognizer` s (their ``_live`` a :class:`LiveStream` with its stage
    attached), in passes over all of them: (1) the checks (a consecutive int number and
    C-contiguous doubles of the stream's shape here, anything else by the recogniser's ``_check``,
    which refuses or converts), the channel frames gathered side by side, the positions frames'
    standard joints taken; (2) the cosines and sines of the channels' half angles in one numpy call
    each; (3) forward kinematics, up to :data:`BLOCK` frames of one skeleton at a time, each step
    over all of them (:meth:`FrameKinematics.joints_many`); (4) each pose into its features' ring,
    with the smoothed velocities of the frame that became final; (5) the feature program over those
    frames, by blocks of one program, each instruction over all of them
    (:meth:`Bytecode.run_many`); (6) each frame's hysteresis and, for an index-rate code, its
    compiled competition. Steps (2) to (5) take the index frames alone (each stream's every
    ``step``-th frame; at a rate the library's does not divide, the frames around their instants,
    blended); the others are checked and counted. Python runs per frame only for a refusal, a
    stream's first frame and a confirmation. ``refused``: the exception class ``_check`` raises for
    a frame it refuses. With ``streams`` (name to recogniser) the frames are ``(name, number,
    values)``. ValueError, before anything is done, for a recogniser (or name) with two frames or a
    name not in ``streams``. Returns (detections, [(position, the refusal)])."""
    cdef Py_ssize_t n = len(frames), i, k, j, taken = 0, total = 0, at, pending = 0, block, first
    cdef Py_ssize_t *pos = <Py_ssize_t *> PyMem_Malloc((n + 1) * sizeof(Py_ssize_t))
    cdef int64_t *nums = <int64_t *> PyMem_Malloc((n + 1) * sizeof(int64_t))
    cdef int64_t *codes = <int64_t *> PyMem_Malloc((n + 1) * sizeof(int64_t))
    cdef int64_t *ts = <int64_t *> PyMem_Malloc((n + 1) * sizeof(int64_t))
    cdef Py_ssize_t *offs = <Py_ssize_t *> PyMem_Malloc((n + 1) * sizeof(Py_ssize_t))
    cdef Py_ssize_t *waiting = <Py_ssize_t *> PyMem_Malloc((n + 1) * sizeof(Py_ssize_t))
    cdef uint64_t *f1 = <uint64_t *> PyMem_Malloc((n + 1) * sizeof(uint64_t))
    cdef uint64_t *f2 = <uint64_t *> PyMem_Malloc((n + 1) * sizeof(uint64_t))
    cdef char *keeps = <char *> PyMem_Malloc((n + 1) * sizeof(char))
    cdef PyObject **lives = <PyObject **> PyMem_Malloc((n + 1) * sizeof(PyObject *))
    cdef const double *P[BLOCK]
    cdef const double *S[BLOCK]
    cdef const double *T[BLOCK]
    cdef uint64_t g1[BLOCK]
    cdef uint64_t g2[BLOCK]
    cdef Py_ssize_t which[BLOCK]
    cdef const double *C[BLOCK]
    cdef const double *CO[BLOCK]
    cdef const double *SI[BLOCK]
    cdef double *OUT[BLOCK]
    cdef bint fine[BLOCK]
    cdef FrameKinematics kinematics
    cdef Py_buffer view
    cdef LiveStream s
    cdef FeatureCore features
    cdef Bytecode program
    cdef bint fast, finite
    cdef int64_t num = 0, code, t
    cdef const double *src
    cdef double[::1] flat, cos, sin
    cdef list errors = [], detections = [], recognisers = [None] * n, unknown = None
    cdef bint twice = False
    global _tick
    try:
        if (pos == NULL or nums == NULL or codes == NULL or ts == NULL or offs == NULL or waiting == NULL
                or f1 == NULL or f2 == NULL or keeps == NULL or lives == NULL):
            raise MemoryError()
        # (0) the recognisers, each once
        _tick += 1
        for i in range(n):
            r = (<tuple?> frames[i])[0]
            if streams is not None:
                r = streams.get(r)
                if r is None:
                    if unknown is None:
                        unknown = []
                    unknown.append((<tuple> frames[i])[0])
                    continue
            recognisers[i] = r
            s = <LiveStream?> r._live
            lives[i] = <PyObject *> s  # borrowed: ``recognisers`` holds them
            if s.mark == _tick:
                twice = True
            s.mark = _tick
            if s._kinematics is not None and s._needs():  # only the poses index frames take are computed
                total += s.width
        if twice or (unknown is not None and len(set(unknown)) != len(unknown)):
            raise ValueError("at most one frame per stream in one push")
        if unknown is not None:
            raise ValueError(f"streams not in the bank: {', '.join(map(repr, unknown))}")
        flat_array = np.empty(max(1, total))
        flat = flat_array
        total = 0
        # (1) the checks; the channel frames gathered, the positions frames' joints taken
        for i in range(n):
            _, number, frame = <tuple> frames[i]
            r = recognisers[i]
            s = <LiveStream> lives[i]
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
            keeps[taken] = s._needs()
            if s._kinematics is None:
                code = C_NOTHING if s._pose_positions(src) else C_NON_FINITE
            else:
                finite = True
                for k in range(s.width):
                    if not isfinite(src[k]):
                        finite = False
                        break
                code = C_NOTHING if finite else C_NON_FINITE_CHANNELS
                if keeps[taken]:
                    if finite:
                        memcpy(&flat[total], src, s.width * sizeof(double))
                    offs[taken] = total
                    total += s.width
            PyBuffer_Release(&view)
            pos[taken] = i
            nums[taken] = num
            codes[taken] = code
            taken += 1
        # (2) the half angles' cosines and sines, numpy's (the batch's) functions
        if total:
            half = np.multiply(flat_array[:total], 0.5)
            cos = np.cos(half)
            sin = np.sin(half)
        # (3) the channel frames' forward kinematics, BLOCK frames of one skeleton at a time
        for k in range(taken):
            if codes[k] == C_NOTHING and keeps[k] and (<LiveStream> lives[pos[k]])._kinematics is not None:
                waiting[pending] = k
                pending += 1
        first = 0
        while first < pending:
            kinematics = (<LiveStream> lives[pos[waiting[first]]])._kinematics
            block = 0
            j = first
            while j < pending and block < BLOCK:
                k = waiting[j]
                if k >= 0:
                    s = <LiveStream> lives[pos[k]]
                    if s._kinematics is kinematics:
                        at = offs[k]
                        C[block] = &flat[at]
                        CO[block] = &cos[at]
                        SI[block] = &sin[at]
                        OUT[block] = &s.rows[0]
                        which[block] = k
                        block += 1
                        waiting[j] = -1
                j += 1
            kinematics.joints_many(block, C, CO, SI, OUT, fine, registers((7 * kinematics.n_nodes + 2 * kinematics.width) * block))
            for j in range(block):
                if not fine[j]:
                    codes[which[j]] = C_NON_FINITE
            while first < pending and waiting[first] < 0:
                first += 1
        # (4) the poses into the features
        pending = 0
        for k in range(taken):
            ts[k] = -1
            if codes[k] != C_NOTHING or not keeps[k]:
                continue
            s = <LiveStream> lives[pos[k]]
            s._blend()
            if not s._keeps():
                continue
            ts[k] = s._prepare()
            if ts[k] >= 0:
                waiting[pending] = k
                pending += 1
        # (5) the feature program over the frames that became final, BLOCK at a time, by program
        first = 0
        while first < pending:
            program = (<LiveStream> lives[pos[waiting[first]]]).features.code
            block = 0
            j = first
            while j < pending and block < BLOCK:
                k = waiting[j]
                if k >= 0:
                    features = (<LiveStream> lives[pos[k]]).features
                    if features.code is program:
                        P[block] = features.pose(ts[k])
                        S[block] = features.smoothed()
                        T[block] = features.thresholds()
                        which[block] = k
                        block += 1
                        waiting[j] = -1
                j += 1
            program.run_many(block, P, S, T, registers(program.registers * block), g1, g2)
            for j in range(block):
                f1[which[j]] = g1[j]
                f2[which[j]] = g2[j]
            while first < pending and waiting[first] < 0:
                first += 1
        # (6) each frame's code to its stage, in the order of the frames
        for k in range(taken):
            i = pos[k]
            s = <LiveStream> lives[i]
            code = codes[k]
            num = nums[k]
            if code < C_NOTHING:
                errors.append((i, recognisers[i]._refusal(num, code)))
                continue
            if not s.started:
                s.stage.start(num)
                s.started = True
            s.last = num
            s.seen += 1
            t = ts[k]
            if t < 0:
                continue
            code = s.features.finish(t, f1[k], f2[k])
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
        PyMem_Free(ts)
        PyMem_Free(offs)
        PyMem_Free(waiting)
        PyMem_Free(f1)
        PyMem_Free(f2)
        PyMem_Free(keeps)
        PyMem_Free(lives)
    if len(errors) > 1:
        errors.sort(key=_position)
    return detections, errors


def _position(item):
    return item[0]
