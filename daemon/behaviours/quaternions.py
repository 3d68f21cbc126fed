"""The frame vectors of behaviour segmentation (Barbič et al. 2004, §3): joint rotations as
quaternions with signs consistent over time.

Each frame is the rotation of every joint relative to its parent as a unit quaternion ``(w, x, y,
z)``, treated as a vector of length 4; root position and root orientation are left out. The joints
are, as many as the paper's hierarchy had (14, ``R^56``), the spine, head, arms, legs and feet of the
CMU/HDM05 skeleton (:data:`PAPER_BONES`, in ``:bonedata`` order), so a frame is a vector of ``D =
56``; :class:`JointRotations` takes any other set of bones with a rotation dof (all 28 of CMU's: ``D
= 112``). A bone's quaternion is ``C_k M_k C_k^T`` (its dof rotations about its axes,
:meth:`replay.kinematics.KinematicModel.local_rotations`); writing it in the bone's own axes instead
(``M_k``) changes each 4-vector by a fixed orthogonal map, which leaves every quantity the methods
compute unchanged. ``q`` and ``-q`` are the same rotation, so the signs are made consistent over
time: the first frame's quaternion has its first non-zero component positive (``w > 0`` for any
rotation short of 180°), and every later one is negated when its dot product with the previous
frame's *raw* quaternion is negative, on top of the previous frame's sign: ``f_t = f_(t-1) *
sign(q_t . q_(t-1))`` with ``sign(0) = +1``. Then consecutive output quaternions always have a
non-negative dot product (``f_t f_(t-1) q_t . q_(t-1) = |q_t . q_(t-1)|``), and the batch is a
cumulative product of ±1, so the stream (:class:`RotationStream`, which keeps the previous frame's
raw quaternions and signs) gives the batch's vectors bit for bit.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import numpy.typing as npt

from daemon.behaviours.common import check_finite
from daemon.errors import InputError
from daemon.types import FloatArray
from replay.asf import ROTATION_DOFS, Skeleton
from replay.bvh import ROTATIONS, BvhHierarchy, BvhKinematics
from replay.joints import JOINT_NAMES
from replay.kinematics import KinematicModel
from replay.rigs import RigPlan


def _dot(a: FloatArray, b: FloatArray) -> FloatArray:
    """Dot products of quaternions along the last axis, in one fixed order of operations."""
    w = a[..., 0] * b[..., 0]
    x = a[..., 1] * b[..., 1]
    y = a[..., 2] * b[..., 2]
    z = a[..., 3] * b[..., 3]
    out: FloatArray = ((w + x) + y) + z
    return out


def _step_signs(q: FloatArray, previous: FloatArray) -> FloatArray:
    """-1 where ``q . previous < 0``, else +1: shapes ``(..., 4)`` give ``(...)``."""
    out: FloatArray = np.where(_dot(q, previous) < 0.0, -1.0, 1.0)
    return out


def _canonical_signs(q: FloatArray) -> FloatArray:
    """The sign of each quaternion's first non-zero component: ``(J, 4)`` gives ``(J,)``."""
    lead = q[np.arange(q.shape[0]), np.argmax(q != 0.0, axis=1)]
    out: FloatArray = np.where(lead < 0.0, -1.0, 1.0)
    return out


def consistent_signs(q: FloatArray) -> FloatArray:
    """Quaternions ``q`` shape ``(N, J, 4)`` with signs consistent over time: the first frame's each
    with its first non-zero component positive, then ``q -> -q`` wherever ``q . q_prev < 0``."""
    if q.shape[0] == 0:
        return q.copy()
    signs = np.empty(q.shape[:2])
    signs[0] = _canonical_signs(q[0])
    signs[1:] = _step_signs(q[1:], q[:-1])
    out: FloatArray = q * np.cumprod(signs, axis=0)[..., None]
    return out


PAPER_BONES = (
    "lowerback",
    "upperback",
    "thorax",
    "head",
    "lhumerus",
    "lradius",
    "rhumerus",
    "rradius",
    "lfemur",
    "ltibia",
    "lfoot",
    "rfemur",
    "rtibia",
    "rfoot",
)
"""Fourteen joints, as many as the paper's hierarchy (§3: ``R^56``): the spine, the head, the upper
and lower arms and legs and the feet of the CMU/HDM05 skeleton. The hands, fingers, thumbs, toes,
clavicles and the neck's two bones are left out: they barely move, and a joint that barely moves
gives the models directions of almost no variance, where any noise is a large Mahalanobis
distance."""


class JointRotations:
    """The paper's frame vectors (§3) for one skeleton: ``bones`` (names) are the non-root bones
    with a rotation dof, ``nodes`` their node indices (``index`` as an array), ``dims = 4 *
    len(bones)``; a frame is the bones' sign-consistent quaternions ``(w, x, y, z)`` one after
    another, from the skeleton's forward kinematics ``model``."""

    def __init__(self, skeleton: Skeleton, bones: Sequence[str] | None = None) -> None:
        self.skeleton = skeleton
        self.model = KinematicModel(skeleton)
        rotating = [
            k + 1 for k, bone in enumerate(skeleton.bones) if any(d in ROTATION_DOFS for d in bone.dofs)
        ]
        names = skeleton.node_names
        if bones is None:
            bones = PAPER_BONES if all(b in [names[k] for k in rotating] for b in PAPER_BONES) else None
        if bones is not None:
            missing = [b for b in bones if b not in [names[k] for k in rotating]]
            if missing:
                raise InputError(f"{skeleton.source}: no rotating bone {', '.join(missing)}")
            rotating = [k for k in rotating if names[k] in bones]
        self.nodes: tuple[int, ...] = tuple(rotating)
        if not self.nodes:
            raise InputError(f"{skeleton.source}: the skeleton has no bone with a rotation dof")
        self.bones: tuple[str, ...] = tuple(skeleton.node_names[k] for k in self.nodes)
        self.dims = 4 * len(self.nodes)
        self.width = len(skeleton.channel_names)
        self.index = np.array(self.nodes, dtype=np.intp)
        self._local = np.empty((self.model.n_nodes, 4))

    def local_frame(self, row: FloatArray) -> FloatArray:
        """:meth:`raw` of one checked frame: ``row`` shape ``(C,)`` gives ``(J, 4)``, bit for bit."""
        out: FloatArray = self.model.local_rotations_frame(row, self._local)[self.index]
        return out

    def raw(self, channels: npt.ArrayLike) -> FloatArray:
        """The bones' quaternions as forward kinematics gives them (signs not made consistent):
        ``channels`` shape ``(N, C)`` (radians, :attr:`Skeleton.channel_names` layout) gives shape
        ``(N, J, 4)``. ``ValueError`` on a wrong shape or a value that is not finite."""
        c = np.asarray(channels, dtype=np.float64)
        if c.ndim != 2 or c.shape[1] != self.width:
            raise InputError(f"channels must have shape (N, {self.width}), got {c.shape}")
        check_finite(c, "channels")
        out: FloatArray = self.model.local_rotations(c)[:, self.index]
        return out

    def __call__(self, channels: npt.ArrayLike) -> FloatArray:
        """The frame vectors of a whole recording: ``channels`` shape ``(N, C)`` gives ``(N, D)``."""
        q = self.raw(channels)
        return consistent_signs(q).reshape(q.shape[0], self.dims)

    def stream(self) -> RotationStream:
        """A new per-frame stream of this representation."""
        return RotationStream(self)


RIG_JOINTS = (
    *("belly", "chest", "head", "lshoulder", "lelbow", "rshoulder", "relbow"),
    *("lhip", "lknee", "lankle", "rhip", "rknee", "rankle"),
)
"""The standard joints whose BVH joints turn :data:`PAPER_BONES` (a BVH joint sits at its bone's
start: ``lhumerus`` turns at ``lshoulder``); ``lowerback`` has none of its own (it starts at the
root, whose rotation is the body's)."""


class RigRotations:
    """:class:`JointRotations` of a BVH rig: the frame vectors of the rig's joints that stand for
    :data:`RIG_JOINTS` (through a rig map's ``plan``, :mod:`replay.rigs`) and have rotation channels,
    their local rotations (:meth:`replay.bvh.BvhKinematics.local_rotations`) made sign-consistent."""

    def __init__(self, hierarchy: BvhHierarchy, plan: RigPlan) -> None:
        self.kinematics = BvhKinematics(hierarchy)
        joints = hierarchy.joints
        picked = [plan.nodes[JOINT_NAMES.index(j)] for j in RIG_JOINTS]
        self.nodes = tuple(k for k in picked if k >= 0 and any(c in ROTATIONS for c in joints[k].channels))
        if not self.nodes:
            raise InputError(f"{hierarchy.source}: no joint of the rig has rotation channels")
        self.bones: tuple[str, ...] = tuple(joints[k].name for k in self.nodes)
        self.dims = 4 * len(self.nodes)

    @property
    def width(self) -> int:
        """Channels in a frame."""
        return self.kinematics.width

    def __call__(self, channels: npt.ArrayLike) -> FloatArray:
        """``channels`` shape ``(N, C)`` (a BVH motion's, degrees) gives shape ``(N, D)``."""
        c = np.asarray(channels, dtype=np.float64)
        check_finite(c, "channels")
        q = self.kinematics.local_rotations(c)[:, list(self.nodes)]
        return consistent_signs(q).reshape(q.shape[0], self.dims)

    def local_frame(self, row: FloatArray) -> FloatArray:
        """The rig joints' local rotations of one checked frame: ``row`` shape ``(C,)`` (degrees)
        gives ``(J, 4)``, bit for bit a row of the batch's."""
        out: FloatArray = self.kinematics.local_rotations(row[None])[0, list(self.nodes)]
        return out

    def stream(self) -> RotationStream:
        """A new per-frame stream of this representation."""
        return RotationStream(self)


class RotationStream:
    """:class:`JointRotations` one frame at a time, equal bit for bit to the batch: keeps the
    previous frame's raw quaternions and signs (shape ``(J, 4)`` and ``(J,)``). A stage
    (:mod:`daemon.stages`): ``push`` returns the one vector, ``flush`` nothing and starts over."""

    def __init__(self, rotations: JointRotations | RigRotations) -> None:
        self.rotations = rotations
        self._t = 0
        self._previous: FloatArray | None = None
        self._signs: FloatArray | None = None

    def frame(self, channels: npt.ArrayLike) -> FloatArray:
        """One frame: ``channels`` shape ``(C,)`` gives shape ``(D,)``; ``ValueError`` (the state
        unchanged) on a wrong shape or a value that is not finite."""
        row = np.asarray(channels, dtype=np.float64)
        if row.shape != (self.rotations.width,):
            raise InputError(
                f"frame {self._t}: channels must have shape ({self.rotations.width},), got {row.shape}"
            )
        if not np.isfinite(row).all():
            raise InputError(f"frame {self._t}: channels have a value that is not finite")
        self._t += 1
        q = self.rotations.local_frame(row)
        if self._previous is None or self._signs is None:
            signs = _canonical_signs(q)
        else:
            signs = self._signs * _step_signs(q, self._previous)
        self._previous, self._signs = q, signs
        out: FloatArray = (q * signs[:, None]).reshape(self.rotations.dims)
        return out

    def push(self, channels: FloatArray, /) -> list[FloatArray]:
        return [self.frame(channels)]

    def flush(self) -> list[FloatArray]:
        self._t = 0
        self._previous = self._signs = None
        return []
