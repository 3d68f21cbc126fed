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
        cdef const int64_t *joint_nodes = &self.joint_nodes[0] if n else NULL
        self.forward(channels, cos, sin, True, pos)
        for j in range(n):
            for c in range(3):
                v = pos[3 * joint_nodes[j] + c]
                out[3 * j + c] = v
                if not isfinite(v):
                    finite = False
        return finite

    cdef void joints_many(self, Py_ssize_t n, const double **channels, const double **cos,
                          const double **sin, double **out, bint *finite, double *scratch) noexcept nogil:
        """:meth:`joints_into` of ``n`` frames of this skeleton at once (frame s: ``channels[s]``,
        ``cos[s]``, ``sin[s]``, its joints into ``out[s]``, whether all are finite into
        ``finite[s]``), every step of :meth:`local` and :meth:`forward` over all of them, frame s of
        a quantity at ``[q n + s]`` in ``scratch``: the node rotations (``4 nodes n`` doubles), the
        positions (``3 nodes n``), the cosines and sines (``2 width n``). Each frame's operations
        are those of :meth:`joints_into` in its order, so its bits are the same."""
        cdef Py_ssize_t e, k, p, c, i, a, j, jj, m = self.nodes.shape[0], nodes_n = self.n_nodes
        cdef Py_ssize_t n_pairs = self.pairs.shape[0], n_trans = self.translation.shape[0]
        cdef Py_ssize_t n_joints = self.joint_nodes.shape[0], width = self.width
        cdef double s, ax, ay, az, aw, bw, bx, by, bz, w, x, y, z, vx, vy, vz, tx, ty, tz, v
        cdef double scale = self.scale
        cdef double *rot = scratch
        cdef double *pos = &scratch[4 * nodes_n * n]
        cdef double *cs = &scratch[7 * nodes_n * n]  # the cosines, channel c of frame j at [c n + j]
        cdef double *sn = &cs[width * n]
        cdef double *r0
        cdef double *r1
        cdef double *r2
        cdef double *r3
        cdef double *q0
        cdef double *q1
        cdef double *q2
        cdef double *q3
        cdef double *p0
        cdef double *p1
        cdef double *p2
        cdef double *o0
        cdef double *o1
        cdef double *o2
        cdef double *cc
        cdef double *ss
        cdef const int64_t *nodes = &self.nodes[0] if m else NULL
        cdef const int64_t *chans = &self.chans[0] if m else NULL
        cdef const unsigned char *first = &self.first[0] if m else NULL
        cdef const double *axes = &self.axes[0, 0] if m else NULL
        cdef const double *orientation = &self.orientation[0]
        cdef const double *position = &self.position[0]
        cdef const double *offsets = &self.offsets[0, 0]
        cdef const int64_t *pairs = &self.pairs[0, 0] if n_pairs else NULL
        cdef const int64_t *translation = &self.translation[0, 0] if n_trans else NULL
        cdef const int64_t *joint_nodes = &self.joint_nodes[0] if n_joints else NULL
        for j in range(n):
            for c in range(width):
                cs[c * n + j] = cos[j][c]
                sn[c * n + j] = sin[j][c]
        # local rotations (local); qmul written out, its operations in its order
        for k in range(nodes_n):
            for j in range(n):
                rot[(4 * k + 0) * n + j] = 1.0
                rot[(4 * k + 1) * n + j] = 0.0
                rot[(4 * k + 2) * n + j] = 0.0
                rot[(4 * k + 3) * n + j] = 0.0
        for e in range(m):
            k = nodes[e]
            c = chans[e]
            ax = axes[3 * e + 0]
            ay = axes[3 * e + 1]
            az = axes[3 * e + 2]
            r0 = &rot[(4 * k + 0) * n]
            r1 = &rot[(4 * k + 1) * n]
            r2 = &rot[(4 * k + 2) * n]
            r3 = &rot[(4 * k + 3) * n]
            cc = &cs[c * n]
            ss = &sn[c * n]
            if first[e]:
                for j in range(n):
                    s = ss[j]
                    r0[j] = cc[j]
                    r1[j] = s * ax
                    r2[j] = s * ay
                    r3[j] = s * az
            else:
                for j in range(n):
                    s = ss[j]
                    aw = cc[j]
                    tx = s * ax
                    ty = s * ay
                    tz = s * az
                    bw = r0[j]
                    bx = r1[j]
                    by = r2[j]
                    bz = r3[j]
                    r0[j] = ((aw * bw - tx * bx) - ty * by) - tz * bz
                    r1[j] = ((aw * bx + tx * bw) + ty * bz) - tz * by
                    r2[j] = ((aw * by - tx * bz) + ty * bw) + tz * bx
                    r3[j] = ((aw * bz + tx * by) - ty * bx) + tz * bw
        r0 = &rot[0]
        r1 = &rot[n]
        r2 = &rot[2 * n]
        r3 = &rot[3 * n]
        aw = orientation[0]
        tx = orientation[1]
        ty = orientation[2]
        tz = orientation[3]
        for j in range(n):
            bw = r0[j]
            bx = r1[j]
            by = r2[j]
            bz = r3[j]
            r0[j] = ((aw * bw - tx * bx) - ty * by) - tz * bz
            r1[j] = ((aw * bx + tx * bw) + ty * bz) - tz * by
            r2[j] = ((aw * by - tx * bz) + ty * bw) + tz * bx
            r3[j] = ((aw * bz + tx * by) - ty * bx) + tz * bw
        # positions down the hierarchy (forward)
        for j in range(n):
            pos[j] = position[0]
            pos[n + j] = position[1]
            pos[2 * n + j] = position[2]
        for i in range(n_trans):
            a = translation[2 * i]
            c = translation[2 * i + 1]
            for j in range(n):
                pos[a * n + j] = pos[a * n + j] + channels[j][c]
        for i in range(n_pairs):
            k = pairs[2 * i]
            p = pairs[2 * i + 1]
            vx = offsets[3 * k + 0]
            vy = offsets[3 * k + 1]
            vz = offsets[3 * k + 2]
            r0 = &rot[(4 * k + 0) * n]
            r1 = &rot[(4 * k + 1) * n]
            r2 = &rot[(4 * k + 2) * n]
            r3 = &rot[(4 * k + 3) * n]
            q0 = &rot[(4 * p + 0) * n]
            q1 = &rot[(4 * p + 1) * n]
            q2 = &rot[(4 * p + 2) * n]
            q3 = &rot[(4 * p + 3) * n]
            p0 = &pos[(3 * p + 0) * n]
            p1 = &pos[(3 * p + 1) * n]
            p2 = &pos[(3 * p + 2) * n]
            o0 = &pos[(3 * k + 0) * n]
            o1 = &pos[(3 * k + 1) * n]
            o2 = &pos[(3 * k + 2) * n]
            for j in range(n):
                aw = q0[j]
                ax = q1[j]
                ay = q2[j]
                az = q3[j]
                bw = r0[j]
                bx = r1[j]
                by = r2[j]
                bz = r3[j]
                w = ((aw * bw - ax * bx) - ay * by) - az * bz
                x = ((aw * bx + ax * bw) + ay * bz) - az * by
                y = ((aw * by - ax * bz) + ay * bw) + az * bx
                z = ((aw * bz + ax * by) - ay * bx) + az * bw
                r0[j] = w
                r1[j] = x
                r2[j] = y
                r3[j] = z
                tx = 2.0 * (y * vz - z * vy)
                ty = 2.0 * (z * vx - x * vz)
                tz = 2.0 * (x * vy - y * vx)
                o0[j] = p0[j] + ((vx + w * tx) + (y * tz - z * ty))
                o1[j] = p1[j] + ((vy + w * ty) + (z * tx - x * tz))
                o2[j] = p2[j] + ((vz + w * tz) + (x * ty - y * tx))
        for k in range(3 * nodes_n * n):
            pos[k] = pos[k] * scale
        # the standard joints (joints_into)
        for j in range(n):
            finite[j] = True
        for jj in range(n_joints):
            for c in range(3):
                o0 = &pos[(3 * joint_nodes[jj] + c) * n]
                for j in range(n):
                    v = o0[j]
                    out[j][3 * jj + c] = v
                    if not isfinite(v):
                        finite[j] = False

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
        cdef Py_ssize_t e, k, c, n = self.nodes.shape[0]
        cdef double s, ax, ay, az
        cdef double q[4]
        # the tables as plain pointers: the compiler need not reload a memoryview's data and strides
        # after every store to rot
        cdef const int64_t *nodes = &self.nodes[0] if n else NULL
        cdef const int64_t *chans = &self.chans[0] if n else NULL
        cdef const unsigned char *first = &self.first[0] if n else NULL
        cdef const double *axes = &self.axes[0, 0] if n else NULL
        cdef const double *orientation = &self.orientation[0]
        for k in range(self.n_nodes):
            rot[4 * k + 0] = 1.0
            rot[4 * k + 1] = 0.0
            rot[4 * k + 2] = 0.0
            rot[4 * k + 3] = 0.0
        for e in range(n):
            k = nodes[e]
            c = chans[e]
            s = sin[c]
            ax = axes[3 * e + 0]
            ay = axes[3 * e + 1]
            az = axes[3 * e + 2]
            if first[e]:
                rot[4 * k + 0] = cos[c]
                rot[4 * k + 1] = s * ax
                rot[4 * k + 2] = s * ay
                rot[4 * k + 3] = s * az
            else:
                qmul(cos[c], s * ax, s * ay, s * az,
                     rot[4 * k + 0], rot[4 * k + 1], rot[4 * k + 2], rot[4 * k + 3], q)
                rot[4 * k + 0] = q[0]
                rot[4 * k + 1] = q[1]
                rot[4 * k + 2] = q[2]
                rot[4 * k + 3] = q[3]
        qmul(orientation[0], orientation[1], orientation[2], orientation[3],
             rot[0], rot[1], rot[2], rot[3], q)
        rot[0] = q[0]
        rot[1] = q[1]
        rot[2] = q[2]
        rot[3] = q[3]

    cdef void forward(self, const double *channels, const double *cos, const double *sin, bint scaled,
                      double *out) noexcept nogil:
        """Every node's position into ``out`` (``3k + c``)."""
        cdef Py_ssize_t k, p, i, a, n_pairs = self.pairs.shape[0], n_trans = self.translation.shape[0]
        cdef double w, x, y, z, vx, vy, vz, tx, ty, tz
        cdef double q[4]
        cdef double *rot = &self.rot[0, 0]
        cdef const int64_t *pairs = &self.pairs[0, 0] if n_pairs else NULL
        cdef const int64_t *translation = &self.translation[0, 0] if n_trans else NULL
        cdef const double *offsets = &self.offsets[0, 0]
        cdef const double *position = &self.position[0]
        self.local(cos, sin, rot)
        out[0] = position[0]
        out[1] = position[1]
        out[2] = position[2]
        for i in range(n_trans):
            a = translation[2 * i]
            out[a] = out[a] + channels[translation[2 * i + 1]]
        for i in range(n_pairs):
            k = pairs[2 * i]
            p = pairs[2 * i + 1]
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
            vx = offsets[3 * k + 0]
            vy = offsets[3 * k + 1]
            vz = offsets[3 * k + 2]
            tx = 2.0 * (y * vz - z * vy)
            ty = 2.0 * (z * vx - x * vz)
            tz = 2.0 * (x * vy - y * vx)
            out[3 * k + 0] = out[3 * p + 0] + ((vx + w * tx) + (y * tz - z * ty))
            out[3 * k + 1] = out[3 * p + 1] + ((vy + w * ty) + (z * tx - x * tz))
            out[3 * k + 2] = out[3 * p + 2] + ((vz + w * tz) + (x * ty - y * tx))
        cdef double scale = self.scale
        if scaled:
            for k in range(3 * self.n_nodes):
                out[k] = out[k] * scale


cdef class BvhFrameKinematics:
    """One frame of :meth:`replay.bvh.BvhKinematics.positions` in the same order of operations:
    per joint (parents first) its ``parent`` (-1: a root), its rotation channels as (axis, column)
    rows ``rotations`` ``(R, 2)`` from ``rot_start[k]`` to ``rot_start[k + 1]``, its position channels
    likewise (``positions``, ``pos_start``), and its ``offsets`` ``(J, 3)``."""

    cdef int64_t[::1] parent
    cdef int64_t[:, ::1] rotations
    cdef int64_t[::1] rot_start
    cdef int64_t[:, ::1] translations
    cdef int64_t[::1] pos_start
    cdef double[:, ::1] offsets
    cdef double[:, ::1] rot
    cdef readonly Py_ssize_t n_joints

    def __init__(self, parent, rotations, rot_start, translations, pos_start, offsets):
        self.parent = np.ascontiguousarray(parent, dtype=np.int64)
        self.rotations = np.ascontiguousarray(rotations, dtype=np.int64).reshape(-1, 2)
        self.rot_start = np.ascontiguousarray(rot_start, dtype=np.int64)
        self.translations = np.ascontiguousarray(translations, dtype=np.int64).reshape(-1, 2)
        self.pos_start = np.ascontiguousarray(pos_start, dtype=np.int64)
        self.offsets = np.ascontiguousarray(offsets, dtype=np.float64).reshape(-1, 3)
        self.n_joints = self.parent.shape[0]
        if (self.rot_start.shape[0] != self.n_joints + 1 or self.pos_start.shape[0] != self.n_joints + 1
                or self.offsets.shape[0] != self.n_joints):
            raise ValueError("BVH kinematics: tables of different joint counts")
        self.rot = np.zeros((self.n_joints, 4))

    def positions(self, const double[::1] row, const double[::1] cos, const double[::1] sin,
                  double[:, ::1] out):
        """Every node's position into ``out`` ``(J, 3)`` from a channel ``row`` and its half angles'
        cosines and sines (numpy's, as the batch computes them)."""
        cdef Py_ssize_t k, i, c, axis, p
        cdef double l[4]
        cdef double e[4]
        cdef double q[4]
        cdef double t[3]
        cdef double w, x, y, z, vx, vy, vz, tx, ty, tz
        if out.shape[0] != self.n_joints or out.shape[1] != 3:
            raise ValueError(f"out must have shape ({self.n_joints}, 3)")
        for k in range(self.n_joints):
            l[0] = 1.0
            l[1] = 0.0
            l[2] = 0.0
            l[3] = 0.0
            for i in range(self.rot_start[k], self.rot_start[k + 1]):
                axis = self.rotations[i, 0]
                c = self.rotations[i, 1]
                e[0] = cos[c]
                e[1] = 0.0
                e[2] = 0.0
                e[3] = 0.0
                e[1 + axis] = sin[c]
                qmul(l[0], l[1], l[2], l[3], e[0], e[1], e[2], e[3], q)
                l[0] = q[0]
                l[1] = q[1]
                l[2] = q[2]
                l[3] = q[3]
            t[0] = self.offsets[k, 0]
            t[1] = self.offsets[k, 1]
            t[2] = self.offsets[k, 2]
            for i in range(self.pos_start[k], self.pos_start[k + 1]):
                t[self.translations[i, 0]] = row[self.translations[i, 1]]
            p = self.parent[k]
            if p < 0:
                self.rot[k, 0] = l[0]
                self.rot[k, 1] = l[1]
                self.rot[k, 2] = l[2]
                self.rot[k, 3] = l[3]
                out[k, 0] = t[0]
                out[k, 1] = t[1]
                out[k, 2] = t[2]
                continue
            w = self.rot[p, 0]
            x = self.rot[p, 1]
            y = self.rot[p, 2]
            z = self.rot[p, 3]
            qmul(w, x, y, z, l[0], l[1], l[2], l[3], q)
            self.rot[k, 0] = q[0]
            self.rot[k, 1] = q[1]
            self.rot[k, 2] = q[2]
            self.rot[k, 3] = q[3]
            vx = t[0]
            vy = t[1]
            vz = t[2]
            tx = 2.0 * (y * vz - z * vy)
            ty = 2.0 * (z * vx - x * vz)
            tz = 2.0 * (x * vy - y * vx)
            out[k, 0] = out[p, 0] + (vx + w * tx + (y * tz - z * ty))
            out[k, 1] = out[p, 1] + (vy + w * ty + (z * tx - x * tz))
            out[k, 2] = out[p, 2] + (vz + w * tz + (x * ty - y * tx))
