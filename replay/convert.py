"""ASF/AMC recordings as BVH (issue 35, "A BVH writer"): the same skeleton and motion in the BVH
conventions of :mod:`replay.bvh`, so that reading the file back gives the AMC's joint positions.

An ASF bone is a segment from its parent's end to its own; a BVH joint is a point whose rotation
turns what hangs below it. So bone ``k`` becomes the BVH joint ``k`` at the bone's *start* (its
``OFFSET`` is the parent bone's vector ``direction * length``), with the bone's local rotation
``C_k M_k C_k^T`` (:class:`replay.kinematics.KinematicModel`) as three Euler channels; the bone's
end is its first child joint or, for a leaf, its ``End Site``. The root carries its position (the
ASF ``position`` plus the AMC translation) and ``O M_root``. Lengths are written in centimetres
(ASF length / ``:units length`` x 2.54, as mocapd's joint positions), angles in degrees.

Each joint's Euler order is the one of the six that keeps the middle angle furthest from ±90°
over the recording (the Euler angles of a rotation near gimbal lock lose digits; the rotation
they give back does not, in the best order). The built-in rig map ``asf``
(:data:`replay.rigs.BUILT_IN`) reads the standard joints of such a file back by bone name.
"""

from __future__ import annotations

import itertools

import numpy as np
import numpy.typing as npt

from daemon.types import FloatArray
from replay.amc import Motion
from replay.bvh import BvhHierarchy, BvhJoint, BvhMotion
from replay.kinematics import KinematicModel, quaternion_matrix

_ORDERS = tuple("".join(p) for p in itertools.permutations("XYZ"))
_AXIS = {"X": 0, "Y": 1, "Z": 2}


def euler_angles(matrices: FloatArray, order: str) -> FloatArray:
    """Angles ``(a, b, c)`` in radians with ``R = R_a(a) @ R_b(b) @ R_c(c)`` about the axes of
    ``order`` (three distinct axes, the BVH channel order): ``matrices`` shape ``(N, 3, 3)`` gives
    shape ``(N, 3)``; the middle angle in ``[-π/2, π/2]``."""
    i, j, k = (_AXIS[a] for a in order)
    e = 1.0 if (j - i) % 3 == 1 else -1.0  # +1 for the cyclic orders XYZ, YZX, ZXY
    r = matrices
    first = np.arctan2(-e * r[:, j, k], r[:, k, k])
    middle = np.arctan2(e * r[:, i, k], np.hypot(r[:, i, i], r[:, i, j]))
    # The last angle from what the first two leave, R_c = R_b(-middle) @ R_a(-first) @ R: near the
    # pole the first is ill-determined (only first ± last is), and this keeps the product exact.
    rest = _about(j, -middle) @ _about(i, -first) @ r
    last = np.arctan2(rest[:, (k + 2) % 3, (k + 1) % 3], rest[:, (k + 1) % 3, (k + 1) % 3])
    return np.stack([first, middle, last], axis=1)


def _about(axis: int, angles: FloatArray) -> FloatArray:
    """Rotations by ``angles`` shape ``(M,)`` about one coordinate axis: shape ``(M, 3, 3)``."""
    p, q = (axis + 1) % 3, (axis + 2) % 3
    out = np.zeros((len(angles), 3, 3))
    out[:, axis, axis] = 1.0
    out[:, p, p] = out[:, q, q] = np.cos(angles)
    out[:, q, p] = np.sin(angles)
    out[:, p, q] = -np.sin(angles)
    return out


def euler_order(matrices: FloatArray) -> str:
    """The Euler order whose middle angle's sine ``|R[i, k]|`` stays smallest over the frames."""
    worst = {o: float(np.max(np.abs(matrices[:, _AXIS[o[0]], _AXIS[o[2]]]), initial=0.0)) for o in _ORDERS}
    return min(_ORDERS, key=lambda o: (worst[o], _ORDERS.index(o)))


def _point(values: FloatArray) -> tuple[float, float, float]:
    return float(values[0]), float(values[1]), float(values[2])


def motion_to_bvh(motion: Motion, rate: float) -> BvhMotion:
    """The AMC ``motion`` at ``rate`` Hz as BVH (module docstring): one row a frame of the motion
    (an AMC that skips frame numbers is written without them: BVH frames are consecutive)."""
    skeleton = motion.skeleton
    model = KinematicModel(skeleton)
    local = model.local_rotations(motion.channels)  # (N, nodes, 4)
    n, nodes = local.shape[0], local.shape[1]
    cm = 2.54 / skeleton.length_unit
    vectors = [np.zeros(3)] + [np.asarray(b.direction) * b.length * cm for b in skeleton.bones]
    children: dict[int, list[int]] = {}
    for k in range(1, nodes):
        children.setdefault(skeleton.parents[k], []).append(k)

    root_positions = model.positions(motion.channels, "cm")[:, 0]
    joints: list[BvhJoint] = []
    columns: list[FloatArray] = []
    names = skeleton.node_names

    def emit(k: int, parent: int) -> None:
        matrices = quaternion_matrix(local[:, k].T)  # (N, 3, 3)
        order = euler_order(matrices)
        rotations = tuple(f"{a}rotation" for a in order)
        at = len(joints)
        if k == 0:
            offset = _point(np.asarray(skeleton.root.position) * cm)
            joints.append(
                BvhJoint(names[0], -1, offset, ("Xposition", "Yposition", "Zposition", *rotations), 0)
            )
            columns.append(root_positions)
        else:
            offset = _point(vectors[skeleton.parents[k]])
            joints.append(BvhJoint(names[k], parent, offset, rotations, 0))
        columns.append(np.degrees(euler_angles(matrices, order)))
        for c in children.get(k, []):
            emit(c, at)
        if not children.get(k):
            end = _point(vectors[k])
            joints.append(BvhJoint(f"{names[k]}/end", at, end, (), 0, end_site=True))

    emit(0, -1)
    channels = np.concatenate(columns, axis=1) if n else np.zeros((0, sum(len(j.channels) for j in joints)))
    hierarchy = BvhHierarchy(motion.source, tuple(joints))
    return BvhMotion(motion.source, hierarchy, 1.0 / rate, np.ascontiguousarray(channels))


def asf_nodes(hierarchy: BvhHierarchy, names: tuple[str, ...]) -> npt.NDArray[np.intp]:
    """For each ASF node of ``names`` (:attr:`replay.asf.Skeleton.node_names`), the index among a
    :func:`motion_to_bvh` hierarchy's nodes of the point at the node's end (the root itself; a bone's
    first child joint, or its End Site): to compare positions node for node."""
    index = {j.name: k for k, j in enumerate(hierarchy.joints)}
    out = [index["root"]]
    for name in names[1:]:
        k = index[name]
        out.append(next(c for c, j in enumerate(hierarchy.joints) if j.parent == k))
    return np.array(out, dtype=np.intp)
