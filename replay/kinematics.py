"""Forward kinematics of an ASF skeleton with the Acclaim conventions (column vectors).

For bone ``k`` with local frame ``C_k`` (its ``axis`` angles) and motion rotation ``M_k`` (its AMC
dofs, composed in the order the ASF lists them, first applied first)::

    G_k = G_parent(k) @ C_k @ M_k @ C_k.T          # global rotation of bone k
    P_k = P_parent(k) + G_k @ (direction_k * length_k)

with ``G_root = O @ M_root`` (``O`` from the root ``orientation``, ``M_root`` from the root rotation
channels in ``order``) and ``P_root = root translation + root position``. This is ``C M C^-1`` for
column vectors, the same as DESIGN.md's ``L = C^-1 M C`` written for row vectors. ``P_k`` is the
position of node ``k``: the end point of bone ``k``.

Rotations are unit quaternions ``(w, x, y, z)``: ``C R(e_a, t) C.T = R(C e_a, t)``, so a bone's local
rotation is a product of elementary quaternions about its rotated dof axes and needs no products with
``C``. Arrays are component-major (``(4, nodes, N)``) and bones are processed level by level down the
hierarchy, vectorised over frames. Every operation is elementwise, so one frame computed alone gives
bit-for-bit the values it gets inside a batch.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any, Literal

import numpy as np
import numpy.typing as npt

from daemon.types import FloatArray
from replay._kinematics import FrameKinematics
from replay.amc import Motion
from replay.asf import ROTATION_DOFS, TRANSLATION_DOFS, Skeleton
from replay.errors import MocapFormatError
from replay.joints import JOINT_BONE_END, JOINT_NAMES

Unit = Literal["asf", "cm"]
_AXIS = {"X": 0, "Y": 1, "Z": 2}


def _qmul(a: Any, b: Any) -> tuple[Any, Any, Any, Any]:
    """Hamilton product of quaternions given as 4 components (floats or arrays alike)."""
    aw, ax, ay, az = a
    bw, bx, by, bz = b
    return (
        ((aw * bw - ax * bx) - ay * by) - az * bz,
        ((aw * bx + ax * bw) + ay * bz) - az * by,
        ((aw * by - ax * bz) + ay * bw) + az * bx,
        ((aw * bz + ax * by) - ay * bx) + az * bw,
    )


def _qrot(q: Any, v: Any) -> tuple[Any, Any, Any]:
    """Rotate the vector ``v`` (3 components) by the unit quaternion ``q``: ``v + w t + cross(u, t)``
    with ``t = 2 cross(u, v)``."""
    w, x, y, z = q
    vx, vy, vz = v
    tx = 2.0 * (y * vz - z * vy)
    ty = 2.0 * (z * vx - x * vz)
    tz = 2.0 * (x * vy - y * vx)
    return (vx + w * tx + (y * tz - z * ty), vy + w * ty + (z * tx - x * tz), vz + w * tz + (x * ty - y * tx))


def quaternion_multiply(a: FloatArray, b: FloatArray) -> FloatArray:
    """Hamilton product ``a ⊗ b`` of quaternions stored component-first: shapes ``(4, ...)``."""
    return np.stack(np.broadcast_arrays(*_qmul(a, b)))


def quaternion_rotate(q: FloatArray, v: FloatArray) -> FloatArray:
    """Rotate vectors ``v`` shape ``(3, ...)`` by unit quaternions ``q`` shape ``(4, ...)``."""
    return np.stack(np.broadcast_arrays(*_qrot(q, v)))


def quaternion_matrix(q: FloatArray) -> FloatArray:
    """Rotation matrices of unit quaternions: ``q`` shape ``(4, ...)`` gives shape ``(..., 3, 3)``."""
    eye = np.eye(3).reshape(3, 3, *([1] * (q.ndim - 1)))
    columns = quaternion_rotate(q[:, None], eye)  # (3 components, 3 columns, ...)
    return np.moveaxis(columns, (0, 1), (-2, -1))


def euler_quaternion(angles: Sequence[float], order: str) -> FloatArray:
    """Quaternion of Euler ``angles`` (radians) about the axes of ``order`` in application order:
    ``order="XYZ"`` is ``Rz @ Ry @ Rx``. Returns shape ``(4,)``."""
    q = np.array([1.0, 0.0, 0.0, 0.0])
    for axis, angle in zip(order, angles, strict=False):
        e = np.zeros(4)
        e[0] = np.cos(0.5 * angle)
        e[1 + _AXIS[axis]] = np.sin(0.5 * angle)
        q = quaternion_multiply(e, q)
    return q


class KinematicModel:
    """Precomputed forward kinematics of one skeleton.

    Channel vectors are in the layout of :attr:`Skeleton.channel_names` (angles in radians), as the
    AMC readers return them. Positions come out in ASF units, or in centimetres with ``unit="cm"``
    (ASF length / ``:units length`` x 2.54, as the toolbox does).
    """

    def __init__(self, skeleton: Skeleton) -> None:
        self.skeleton = skeleton
        self._width = len(skeleton.channel_names)  # a property that builds the names: asked once
        n_nodes = len(skeleton.bones) + 1
        self.n_nodes = n_nodes
        index = {n: i for i, n in enumerate(skeleton.channel_names)}
        self._orientation = euler_quaternion(skeleton.root.orientation, skeleton.root.axis_order)
        # Columns of C_k are the bone's local axes in the global frame; the root's dofs are not conjugated.
        frames = [np.eye(3)] + [
            quaternion_matrix(euler_quaternion(b.axis, b.axis_order)) for b in skeleton.bones
        ]
        dofs = [skeleton.root.order] + [b.dofs for b in skeleton.bones]
        node_names = skeleton.node_names

        # slot s: every node's s-th rotation dof, as (nodes, channel index, rotated unit axis (3, n, 1))
        self._slots: list[tuple[npt.NDArray[np.intp], npt.NDArray[np.intp], FloatArray]] = []
        for slot in range(3):
            nodes, chans, axes = [], [], []
            for k in range(n_nodes):
                rot = [d for d in dofs[k] if d in ROTATION_DOFS]
                if len(rot) > slot:
                    nodes.append(k)
                    chans.append(index[f"{node_names[k]}.{rot[slot]}"])
                    axes.append(frames[k][:, ROTATION_DOFS.index(rot[slot])])
            if nodes:
                self._slots.append(
                    (
                        np.array(nodes, dtype=np.intp),
                        np.array(chans, dtype=np.intp),
                        np.array(axes).T[:, :, None],
                    )
                )
        self._translation = [
            (axis, index[f"root.{t}"]) for axis, t in enumerate(TRANSLATION_DOFS) if f"root.{t}" in index
        ]
        self._root_position = np.array(skeleton.root.position, dtype=np.float64)
        offsets = np.array([[0.0, 0.0, 0.0]] + [np.array(b.direction) * b.length for b in skeleton.bones])
        self._offsets = offsets.T[:, :, None]  # (3, nodes, 1)

        depth = [0] * n_nodes
        for k in range(1, n_nodes):
            node, d = k, 0
            while node > 0:
                node, d = skeleton.parents[node], d + 1
            depth[k] = d
        self._levels = [
            (np.array(nodes, dtype=np.intp), np.array([skeleton.parents[k] for k in nodes], dtype=np.intp))
            for level in range(1, max(depth, default=0) + 1)
            if (nodes := [k for k in range(1, n_nodes) if depth[k] == level])
        ]
        self._pairs = [
            (int(k), int(p)) for nodes, parents in self._levels for k, p in zip(nodes, parents, strict=True)
        ]
        missing = sorted({b for b in JOINT_BONE_END.values() if b != "root" and b not in node_names})
        self.missing_joint_bones: tuple[str, ...] = tuple(missing)
        self._joint_nodes = (
            np.array([node_names.index(JOINT_BONE_END[j]) for j in JOINT_NAMES], dtype=np.intp)
            if not missing
            else None
        )

        self._cm = 2.54 / skeleton.length_unit
        # The same tables for one frame at a time in compiled code (positions_frame).
        entries = [
            (int(k), int(c), axes[:, i, 0], slot == 0)
            for slot, (nodes, chans, axes) in enumerate(self._slots)
            for i, (k, c) in enumerate(zip(nodes, chans, strict=True))
        ]
        self._frame = FrameKinematics(
            [e[0] for e in entries],
            [e[1] for e in entries],
            [e[3] for e in entries],
            np.array([e[2] for e in entries]).reshape(-1, 3),
            self._orientation,
            self._root_position,
            np.array(self._translation, dtype=np.int64).reshape(-1, 2),
            np.array(self._pairs, dtype=np.int64).reshape(-1, 2),
            offsets,
            [] if self._joint_nodes is None else self._joint_nodes,
            self._cm,
        )

    def _check(self, channels: FloatArray) -> FloatArray:
        channels = np.asarray(channels, dtype=np.float64)
        if channels.ndim != 2 or channels.shape[1] != len(self.skeleton.channel_names):
            raise ValueError(
                f"channels must have shape (N, {len(self.skeleton.channel_names)}), got {channels.shape}"
            )
        return channels

    def _local(self, channels: FloatArray) -> FloatArray:
        """Local rotations ``O M_root`` (node 0) and ``C_k M_k C_k.T``: shape ``(4, nodes, N)``."""
        local = np.zeros((4, self.n_nodes, channels.shape[0]))
        local[0] = 1.0
        angles = channels.T
        for slot, (nodes, chans, axes) in enumerate(self._slots):
            half = 0.5 * angles[chans]
            elementary = np.concatenate([np.cos(half)[None], np.sin(half)[None] * axes])
            local[:, nodes] = elementary if slot == 0 else quaternion_multiply(elementary, local[:, nodes])
        local[:, 0] = quaternion_multiply(self._orientation[:, None], local[:, 0])
        return local

    def _forward(self, channels: FloatArray) -> tuple[FloatArray, FloatArray]:
        """Global rotations ``(4, nodes, N)`` and positions ``(3, nodes, N)`` in ASF units."""
        rot = self._local(channels)
        pos = np.empty((3, self.n_nodes, channels.shape[0]))
        pos[:, 0] = self._root_position[:, None]
        for axis, chan in self._translation:
            pos[axis, 0] += channels[:, chan]
        for nodes, parents in self._levels:
            rot[:, nodes] = quaternion_multiply(rot[:, parents], rot[:, nodes])
            pos[:, nodes] = pos[:, parents] + quaternion_rotate(rot[:, nodes], self._offsets[:, nodes])
        return rot, pos

    def positions(self, channels: FloatArray, unit: Unit = "asf") -> FloatArray:
        """Positions of all nodes: ``channels`` shape ``(N, C)`` gives shape ``(N, nodes, 3)``."""
        _, pos = self._forward(self._check(channels))
        if unit == "cm":
            pos *= self._cm
        return np.ascontiguousarray(pos.transpose(2, 1, 0))

    def local_rotations(self, channels: FloatArray) -> FloatArray:
        """Every node's rotation relative to its parent as a unit quaternion ``(w, x, y, z)``: ``O
        M_root`` for the root, ``C_k M_k C_k.T`` for bone k (so ``G_k = G_parent(k) @ local_k``; the
        identity for a bone without rotation dofs): ``channels`` shape ``(N, C)`` gives shape ``(N,
        nodes, 4)``. Elementwise like the rest, so one frame alone gives its values in a batch."""
        return np.ascontiguousarray(self._local(self._check(channels)).transpose(2, 1, 0))

    def rotations(self, channels: FloatArray) -> FloatArray:
        """Global rotation matrices of all nodes: ``channels`` shape ``(N, C)`` gives ``(N, nodes, 3, 3)``."""
        rot, _ = self._forward(self._check(channels))
        return np.ascontiguousarray(quaternion_matrix(rot.transpose(0, 2, 1)))

    def positions_frame(self, channels: FloatArray, unit: Unit = "asf") -> FloatArray:
        """Positions of all nodes for one frame: ``channels`` shape ``(C,)`` gives shape ``(nodes, 3)``.

        The same operations as :meth:`positions` in the same order, in compiled code
        (:mod:`replay._kinematics`; the half angles' cosines and sines from numpy), so the values are
        bit-for-bit those of the batch."""
        row = np.ascontiguousarray(channels, dtype=np.float64)
        if row.shape != (self._width,):
            raise ValueError(f"channels must have shape ({self._width},), got {row.shape}")
        half = 0.5 * row
        out = np.empty((self.n_nodes, 3))
        self._frame.positions(row, np.cos(half), np.sin(half), unit == "cm", out)
        return out

    def local_rotations_frame(self, channels: FloatArray, out: FloatArray | None = None) -> FloatArray:
        """:meth:`local_rotations` of one frame, in compiled code and bit for bit the batch's:
        ``channels`` shape ``(C,)`` gives shape ``(nodes, 4)`` (into ``out`` if given)."""
        row = np.ascontiguousarray(channels, dtype=np.float64)
        if row.shape != (self._width,):
            raise ValueError(f"channels must have shape ({self._width},), got {row.shape}")
        half = 0.5 * row
        if out is None:
            out = np.empty((self.n_nodes, 4))
        self._frame.local_rotations(row, np.cos(half), np.sin(half), out)
        return out

    @property
    def frame_kinematics(self) -> FrameKinematics:
        """The compiled one-frame kinematics (the live recogniser drives it directly); an error
        naming the missing bones if the skeleton lacks a standard joint."""
        if self._joint_nodes is None:
            self.joints(np.zeros((self.n_nodes, 3)))  # raises naming the missing bones
        return self._frame

    def joints_frame(self, channels: FloatArray, cos: FloatArray, sin: FloatArray, out: FloatArray) -> bool:
        """The standard joints of one frame in centimetres (:meth:`positions_frame` with ``"cm"``,
        then :meth:`joints`) written flat (``3j + c``) into ``out`` shape ``(78,)``; whether every
        coordinate is finite. ``channels`` shape ``(C,)`` and the cosines and sines of their halves
        (``np.cos(0.5 * channels)``, as the batch computes them): contiguous float64."""
        if self._joint_nodes is None:
            self.joints(np.zeros((self.n_nodes, 3)))  # raises naming the missing bones
        finite: bool = self._frame.joints(channels, cos, sin, out)
        return finite

    def joints(self, node_positions: FloatArray) -> FloatArray:
        """Select the standard joints (:data:`replay.joints.JOINT_NAMES`): shape ``(..., nodes, 3)``
        gives shape ``(..., 26, 3)``."""
        if self._joint_nodes is None:
            missing = ", ".join(self.missing_joint_bones)
            raise MocapFormatError(
                self.skeleton.source,
                None,
                f"skeleton has no bone(s) {missing} needed for the standard joint set",
            )
        joints: FloatArray = node_positions[..., self._joint_nodes, :]
        return joints


def y_up(points: FloatArray) -> FloatArray:
    """Points ``(..., 3)`` of a z-up frame in mocapd's y-up one: a quarter turn about x."""
    return np.stack([points[..., 0], points[..., 2], -points[..., 1]], axis=-1)


def joint_positions(motion: Motion, unit: str = "cm") -> FloatArray:
    """The standard joints (:data:`replay.JOINT_NAMES`) of every frame, shape ``(N, 26, 3)``, in
    centimetres or (``"asf"``) the skeleton's own units."""
    model = KinematicModel(motion.skeleton)
    return model.joints(model.positions(motion.channels, "cm" if unit == "cm" else "asf"))
