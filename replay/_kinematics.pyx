# cython: language_level=3, boundscheck=False, wraparound=False, initializedcheck=False, cdivision=True
"""One frame of forward kinematics in compiled code: the operations of
:meth:`replay.kinematics.KinematicModel.positions` (``_qmul``, ``_qrot``) in the same order, on
doubles, so one frame gives the bits the batch gives it. The cosines and sines of the half angles
come from numpy (the batch's functions), the products and sums are done here."""

from libc.math cimport isfinite
from libc.stdint cimport int64_t

import numpy as np


cdef inline void qmul(double aw, double ax, double ay, double az,
                      double bw, double bx, double by, double bz, double *out) noexcept nogil:
    out[0] = ((aw * bw - ax * bx) - ay * by) - az * bz
    out[1] = ((aw * bx + ax * bw) + ay * bz) - az * by
    out[2] = ((aw * by - ax * bz) + ay * bw) + az * bx
    out[3] = ((aw * bz + ax * by) - ay * bx) + az * bw


cdef class FrameKinematics:
    """The tables of one skeleton: rotation dof entries in slot order (``nodes``, ``chans``,
    ``axes`` ``(E, 3)``, ``first``: whether the entry is its node's first dof), the root
    ``orientation`` ``(4,)`` and ``position`` ``(3,)``, root ``translation`` (axis, channel) pairs
    ``(T, 2)``, the (node, parent) ``pairs`` ``(P, 2)`` down the hierarchy, bone ``offsets``
    ``(nodes, 3)``, the nodes of the standard joints and the length ``scale`` (to centimetres)."""

    def __init__(self, nodes, chans, first, axes, orientation, position, translation, pairs, offsets,
                 joint_nodes, double scale):
        self.nodes = np.ascontiguousarray(nodes, dtype=np.int64)
        self.chans = np.ascontiguousarray(chans, dtype=np.int64)
        self.first = np.ascontiguousarray(first, dtype=np.uint8)
        self.axes = np.ascontiguousarray(axes, dtype=np.float64).reshape(-1, 3)
        self.orientation = np.ascontiguousarray(orientation, dtype=np.float64)
        self.position = np.ascontiguousarray(position, dtype=np.float64)
        self.translation = np.ascontiguousarray(translation, dtype=np.int64).reshape(-1, 2)
        self.pairs = np.ascontiguousarray(pairs, dtype=np.int64).reshape(-1, 2)
        self.offsets = np.ascontiguousarray(offsets, dtype=np.float64)
        self.n_nodes = self.offsets.shape[0]
        self.rot = np.zeros((self.n_nodes, 4))
        self.pos = np.zeros((self.n_nodes, 3))
        self.joint_nodes = np.ascontiguousarray(joint_nodes, dtype=np.int64)
        used = np.asarray(chans, dtype=np.int64).tolist() + np.asarray(self.translation[:, 1]).tolist()
        self.width = 1 + max([-1] + used)
        self.scale = scale

    def positions(self, const double[::1] channels, const double[::1] cos, const double[::1] sin,
                  bint scaled, double[:, ::1] out):
        """Every node's position into ``out`` ``(nodes, 3)`` from the frame's ``channels`` ``(C,)``
        and the cosines and sines of their halves; times :attr:`scale` if ``scaled``."""
        if out.shape[0] != self.n_nodes or out.shape[1] != 3:
            raise ValueError(f"out must have shape ({self.n_nodes}, 3)")
        self._check(channels, cos, sin)
        with nogil:
            self.forward(&channels[0], &cos[0], &sin[0], scaled, &out[0, 0])

    def joints(self, const double[::1] channels, const double[::1] cos, const double[::1] sin,
               double[::1] out):
        """The standard joints' positions in centimetres, flat (``3j + c``), into ``out``
        ``(3 * 26,)``; whether every one is finite."""
        if out.shape[0] != 3 * self.joint_nodes.shape[0]:
            raise ValueError(f"out must have shape ({3 * self.joint_nodes.shape[0]},)")
        self._check(channels, cos, sin)
        cdef bint finite
        with nogil:
            finite = self.joints_into(&channels[0], &cos[0], &sin[0], &out[0])
        return finite

    cdef void _check(self, const double[::1] channels, const double[::1] cos, const double[::1] sin) except *:
        if channels.shape[0] != cos.shape[0] or channels.shape[0] != sin.shape[0]:
            raise ValueError("channels, cos and sin must have one entry per channel")
        if channels.shape[0] < max(1, self.width):
            raise ValueError(f"{self.width} channels expected")

    cdef bint joints_into(self, const double *channels, const double *cos, const double *sin,
                          double *out) noexcept nogil:
        """The standard joints in centimetres into ``out`` (``3j + c``); whether all are finite."""
        cdef Py_ssize_t j, c, n = self.joint_nodes.shape[0]
        cdef bint finite = True
        cdef double v
        cdef double *pos = &self.pos[0, 0]
        self.forward(channels, cos, sin, True, pos)
        for j in range(n):
            for c in range(3):
                v = pos[3 * self.joint_nodes[j] + c]
                out[3 * j + c] = v
                if not isfinite(v):
                    finite = False
        return finite

    def local_rotations(self, const double[::1] channels, const double[::1] cos, const double[::1] sin,
                        double[:, ::1] out):
        """Every node's rotation relative to its parent, ``(w, x, y, z)``, into ``out`` ``(nodes, 4)``
        (:meth:`replay.kinematics.KinematicModel.local_rotations` of the one frame)."""
        if out.shape[0] != self.n_nodes or out.shape[1] != 4:
            raise ValueError(f"out must have shape ({self.n_nodes}, 4)")
        self._check(channels, cos, sin)
        with nogil:
            self.local(&cos[0], &sin[0], &out[0, 0])

    cdef void local(self, const double *cos, const double *sin, double *rot) noexcept nogil:
        """Every node's local rotation into ``rot`` (``4k + c``): the batch's ``_local``."""
        cdef Py_ssize_t e, k, c
        cdef double s
        cdef double q[4]
        for k in range(self.n_nodes):
            rot[4 * k + 0] = 1.0
            rot[4 * k + 1] = 0.0
            rot[4 * k + 2] = 0.0
            rot[4 * k + 3] = 0.0
        for e in range(self.nodes.shape[0]):
            k = self.nodes[e]
            c = self.chans[e]
            s = sin[c]
            if self.first[e]:
                rot[4 * k + 0] = cos[c]
                rot[4 * k + 1] = s * self.axes[e, 0]
                rot[4 * k + 2] = s * self.axes[e, 1]
                rot[4 * k + 3] = s * self.axes[e, 2]
            else:
                qmul(cos[c], s * self.axes[e, 0], s * self.axes[e, 1], s * self.axes[e, 2],
                     rot[4 * k + 0], rot[4 * k + 1], rot[4 * k + 2], rot[4 * k + 3], q)
                rot[4 * k + 0] = q[0]
                rot[4 * k + 1] = q[1]
                rot[4 * k + 2] = q[2]
                rot[4 * k + 3] = q[3]
        qmul(self.orientation[0], self.orientation[1], self.orientation[2], self.orientation[3],
             rot[0], rot[1], rot[2], rot[3], q)
        rot[0] = q[0]
        rot[1] = q[1]
        rot[2] = q[2]
        rot[3] = q[3]

    cdef void forward(self, const double *channels, const double *cos, const double *sin, bint scaled,
                      double *out) noexcept nogil:
        """Every node's position into ``out`` (``3k + c``)."""
        cdef Py_ssize_t k, p, i, a
        cdef double w, x, y, z, vx, vy, vz, tx, ty, tz
        cdef double q[4]
        cdef double *rot = &self.rot[0, 0]
        self.local(cos, sin, rot)
        out[0] = self.position[0]
        out[1] = self.position[1]
        out[2] = self.position[2]
        for i in range(self.translation.shape[0]):
            a = self.translation[i, 0]
            out[a] = out[a] + channels[self.translation[i, 1]]
        for i in range(self.pairs.shape[0]):
            k = self.pairs[i, 0]
            p = self.pairs[i, 1]
            qmul(rot[4 * p + 0], rot[4 * p + 1], rot[4 * p + 2], rot[4 * p + 3],
                 rot[4 * k + 0], rot[4 * k + 1], rot[4 * k + 2], rot[4 * k + 3], q)
            w = q[0]
            x = q[1]
            y = q[2]
            z = q[3]
            rot[4 * k + 0] = w
            rot[4 * k + 1] = x
            rot[4 * k + 2] = y
            rot[4 * k + 3] = z
            vx = self.offsets[k, 0]
            vy = self.offsets[k, 1]
            vz = self.offsets[k, 2]
            tx = 2.0 * (y * vz - z * vy)
            ty = 2.0 * (z * vx - x * vz)
            tz = 2.0 * (x * vy - y * vx)
            out[3 * k + 0] = out[3 * p + 0] + ((vx + w * tx) + (y * tz - z * ty))
            out[3 * k + 1] = out[3 * p + 1] + ((vy + w * ty) + (z * tx - x * tz))
            out[3 * k + 2] = out[3 * p + 2] + ((vz + w * tz) + (x * ty - y * tx))
        if scaled:
            for k in range(3 * self.n_nodes):
                out[k] = out[k] * self.scale
