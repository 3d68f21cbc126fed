"""Forward kinematics of an ASF skeleton with the Acclaim conventions (column vectors).

For bone ``k`` with local frame ``C_k`` (its ``axis`` angles) and motion rotation ``M_k`` (its AMC
dofs, composed in the order the ASF lists them, first applied first)::

    G_k = G_parent(k) @ C_k @ M_k @ C_k.T          # global rotation of bone k
    P_k = P_parent(k) + G_k @ (direction_k * length_k)

with ``G_root = O @ M_root`` (``O`` from the root ``orientation``, ``M_root`` from the root rotation
channels in ``order``) and ``P_root = root translation + root position``. This is
``C M C^-1`` for column vectors, the same as DESIGN.md's ``L = C^-1 M C`` written for row vectors.
``P_k`` is the position of node ``k``: the end point of bone ``k``.

Everything is vectorised over frames; bones are processed level by level down the hierarchy.
3x3 products are written out element by element, so one frame computed alone gives bit-for-bit
the values it gets inside a batch.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Literal

import numpy as np
import numpy.typing as npt

from replay.asf import ROTATION_DOFS, TRANSLATION_DOFS, Skeleton
from replay.joints import JOINT_BONE_END, JOINT_NAMES

FloatArray = npt.NDArray[np.float64]
Unit = Literal["asf", "cm"]
_AXIS = {"X": 0, "Y": 1, "Z": 2}


def matmul3(a: FloatArray, b: FloatArray) -> FloatArray:
    """``a @ b`` for stacks of 3x3 matrices, shapes ``(..., 3, 3)``, with a fixed summation order."""
    return (a[..., :, 0, None] * b[..., None, 0, :] + a[..., :, 1, None] * b[..., None, 1, :]) + a[
        ..., :, 2, None
    ] * b[..., None, 2, :]


def matvec3(a: FloatArray, v: FloatArray) -> FloatArray:
    """``a @ v`` for stacks: ``a`` shape ``(..., 3, 3)``, ``v`` shape ``(..., 3)``."""
    return (a[..., :, 0] * v[..., None, 0] + a[..., :, 1] * v[..., None, 1]) + a[..., :, 2] * v[..., None, 2]


def axis_rotations(axes: npt.NDArray[np.intp], angles: FloatArray) -> FloatArray:
    """Elementary rotations: ``angles`` shape ``(..., B)`` in radians about the axes ``axes`` shape
    ``(B,)`` (0 = x, 1 = y, 2 = z); returns shape ``(..., B, 3, 3)``."""
    c, s = np.cos(angles), np.sin(angles)
    out = np.zeros((*angles.shape, 3, 3), dtype=np.float64)
    b = np.arange(axes.shape[0])
    i, j, k = axes, (axes + 1) % 3, (axes + 2) % 3
    out[..., b, i, i] = 1.0
    out[..., b, j, j] = c
    out[..., b, k, k] = c
    out[..., b, j, k] = -s
    out[..., b, k, j] = s
    return out


def euler_matrix(angles: Sequence[float], order: str) -> FloatArray:
    """Rotation for Euler ``angles`` (radians) about the axes of ``order`` in application order:
    ``order="XYZ"`` gives ``Rz @ Ry @ Rx``. Returns shape ``(3, 3)``."""
    axes = np.array([_AXIS[a] for a in order], dtype=np.intp)
    elementary = axis_rotations(axes, np.asarray(angles, dtype=np.float64)[: len(order)])
    result = np.eye(3)
    for r in elementary:
        result = matmul3(r, result)
    return result


class KinematicModel:
    """Precomputed forward kinematics of one skeleton.

    Channel vectors are in the layout of :attr:`Skeleton.channel_names` (angles in radians), as the
    AMC readers return them. Positions come out in ASF units, or in centimetres with ``unit="cm"``
    (ASF length / ``:units length`` x 2.54, as the toolbox does).

    A bone's local rotation ``C M C.T`` with ``M = R(e_a3, t3) R(e_a2, t2) R(e_a1, t1)`` is computed as
    ``R(C e_a3, t3) R(C e_a2, t2) R(C e_a1, t1)`` (Rodrigues' formula about the rotated axes), which
    needs no products with ``C``.
    """

    def __init__(self, skeleton: Skeleton) -> None:
        self.skeleton = skeleton
        n_nodes = len(skeleton.bones) + 1
        self.n_nodes = n_nodes
        index = {n: i for i, n in enumerate(skeleton.channel_names)}
        self._orientation = euler_matrix(skeleton.root.orientation, skeleton.root.axis_order)
        frames = [np.eye(3)] + [euler_matrix(b.axis, b.axis_order) for b in skeleton.bones]
        dofs = [skeleton.root.order] + [b.dofs for b in skeleton.bones]
        node_names = skeleton.node_names

        # slot s holds every node's s-th rotation dof: (nodes, channel index, K, I - u u^T, u u^T)
        self._slots: list[
            tuple[npt.NDArray[np.intp], npt.NDArray[np.intp], FloatArray, FloatArray, FloatArray]
        ] = []
        for slot in range(3):
            nodes, chans, ks, uus = [], [], [], []
            for k in range(n_nodes):
                rot = [d for d in dofs[k] if d in ROTATION_DOFS]
                if len(rot) <= slot:
                    continue
                u = frames[k][:, ROTATION_DOFS.index(rot[slot])]
                nodes.append(k)
                chans.append(index[f"{node_names[k]}.{rot[slot]}"])
                ks.append(np.array([[0.0, -u[2], u[1]], [u[2], 0.0, -u[0]], [-u[1], u[0], 0.0]]))
                uus.append(np.outer(u, u))
            if nodes:
                uu = np.array(uus)[:, None]
                self._slots.append(
                    (
                        np.array(nodes, dtype=np.intp),
                        np.array(chans, dtype=np.intp),
                        np.array(ks)[:, None],
                        np.eye(3) - uu,
                        uu,
                    )
                )
        self._translation = [
            (axis, index[f"root.{t}"]) for axis, t in enumerate(TRANSLATION_DOFS) if f"root.{t}" in index
        ]
        self._root_position = np.array(skeleton.root.position, dtype=np.float64)
        self._offsets = np.array(
            [[0.0, 0.0, 0.0]] + [np.array(b.direction) * b.length for b in skeleton.bones]
        )

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
        missing = sorted({b for b in JOINT_BONE_END.values() if b != "root" and b not in node_names})
        self.missing_joint_bones: tuple[str, ...] = tuple(missing)
        self._joint_nodes = (
            np.array([node_names.index(JOINT_BONE_END[j]) for j in JOINT_NAMES], dtype=np.intp)
            if not missing
            else None
        )

    def _local_rotations(self, channels: FloatArray) -> FloatArray:
        """``O @ M_root`` for node 0 and ``C_k @ M_k @ C_k.T`` for bone nodes, node-major: ``channels``
        shape ``(N, C)`` gives shape ``(nodes, N, 3, 3)``."""
        n = channels.shape[0]
        local = np.zeros((self.n_nodes, n, 3, 3))
        local[..., [0, 1, 2], [0, 1, 2]] = 1.0
        for slot, (nodes, chans, k, eye_minus_uu, uu) in enumerate(self._slots):
            theta = channels.T[chans][..., None, None]
            # Rodrigues: R(u, t) = u u^T + cos t (I - u u^T) + sin t [u]x
            r = (uu + np.cos(theta) * eye_minus_uu) + np.sin(theta) * k
            local[nodes] = r if slot == 0 else np.matmul(r, local[nodes])
        local[0] = np.matmul(self._orientation, local[0])
        return local

    def positions(self, channels: FloatArray, unit: Unit = "asf") -> FloatArray:
        """Positions of all nodes: ``channels`` shape ``(N, C)`` gives shape ``(N, nodes, 3)``."""
        channels = np.asarray(channels, dtype=np.float64)
        if channels.ndim != 2 or channels.shape[1] != len(self.skeleton.channel_names):
            raise ValueError(
                f"channels must have shape (N, {len(self.skeleton.channel_names)}), got {channels.shape}"
            )
        rot = self._local_rotations(channels)
        pos = np.empty((self.n_nodes, channels.shape[0], 3))
        pos[0] = self._root_position
        for axis, chan in self._translation:
            pos[0, :, axis] += channels[:, chan]
        for nodes, parents in self._levels:
            rot[nodes] = np.matmul(rot[parents], rot[nodes])
            pos[nodes] = pos[parents] + np.matmul(rot[nodes], self._offsets[nodes][:, None, :, None])[..., 0]
        if unit == "cm":
            pos *= 2.54 / self.skeleton.length_unit
        return np.ascontiguousarray(pos.transpose(1, 0, 2))

    def positions_frame(self, channels: FloatArray, unit: Unit = "asf") -> FloatArray:
        """Positions of all nodes for one frame: ``channels`` shape ``(C,)`` gives shape ``(nodes, 3)``."""
        one: FloatArray = self.positions(np.asarray(channels, dtype=np.float64)[None, :], unit)[0]
        return one

    def joints(self, node_positions: FloatArray) -> FloatArray:
        """Select the standard joints (:data:`replay.joints.JOINT_NAMES`): shape ``(..., nodes, 3)``
        gives shape ``(..., 26, 3)``."""
        if self._joint_nodes is None:
            raise ValueError(
                f"{self.skeleton.source}: skeleton has no bone(s) {', '.join(self.missing_joint_bones)} "
                "needed for the standard joint set"
            )
        joints: FloatArray = node_positions[..., self._joint_nodes, :]
        return joints
