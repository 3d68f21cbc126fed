"""Rig maps: a capture rig's joints onto mocapd's 26 standard joints (:data:`replay.JOINT_NAMES`).

A map names, for each standard joint, the rig's nodes that stand for it, in order of preference (the
first the rig has is taken; an End Site whose offset is zero is no point of its own and is passed
over). Names are compared without a namespace (``mixamorig:LeftArm`` is ``LeftArm``). The built-in
maps (:data:`BUILT_IN`) cover the CMU/HDM05 ASF bone names (as :mod:`replay.convert` writes them),
the ``Hips/Spine/Chest/UpperArm_L`` scheme (Bandai Namco Research's
datasets) and the ``LeftUpLeg/LeftLeg/LeftArm/LeftForeArm`` scheme of most BVH exporters and of
Mixamo; :func:`rig_plan` takes the first whose joints a rig has.

Joints a rig lacks are derived, in proportions of the body (Drillis and Contini's segment lengths
as shares of the stature: thigh 0.245, forearm 0.146, hand 0.108, head top above the skull's base
0.130), and each derivation says which of the 39 relational features it reaches:

* ``headtop`` (none in the scheme maps): the head joint plus, along the neck-to-head direction, 0.53
  thigh lengths. It enters the body-length references (the ``body`` chain) and the horizontal
  extent of the body (``_NAME_MAP_XZ``), so the features scaled by them move with its estimate.
* ``lfingers``/``rfingers`` (absent or an End Site at the wrist): the wrist plus, along the
  elbow-to-wrist direction, 0.74 forearm lengths. ``handLeftHighVel``, ``handRightHighVel`` and the
  hands-low features read them: a hand bent at the wrist is taken as straight.
* ``lthumb``/``rthumb`` (when absent): the fingers' point. No feature reads the thumbs.
* the clavicle joints are the neck, as in the Bonn toolbox (not a derivation: the ASF path does so).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from daemon.types import FloatArray, IntArray
from replay.bvh import BvhHierarchy, BvhKinematics, BvhMotion, read_bvh
from replay.errors import MocapFormatError
from replay.joints import JOINT_NAMES
from replay.kinematics import y_up

HEAD_TOP_PER_THIGH = 0.130 / 0.245
FINGERS_PER_FOREARM = 0.108 / 0.146
DERIVABLE = frozenset({"headtop", "lfingers", "rfingers", "lthumb", "rthumb"})


@dataclass(frozen=True)
class RigMap:
    """A rig's name for each standard joint: candidates in order of preference."""

    name: str
    points: Mapping[str, tuple[str, ...]]


def _sided(template: Mapping[str, tuple[str, ...]]) -> dict[str, tuple[str, ...]]:
    """A map's left and right joints from one template: ``{s}`` is ``L``/``R``, ``{side}`` is
    ``Left``/``Right``, ``{x}`` is ``l``/``r``, in the standard name and the candidates alike."""
    out: dict[str, tuple[str, ...]] = {}
    for joint, names in template.items():
        if "{" not in joint:
            out[joint] = names
            continue
        for s, side, x in (("L", "Left", "l"), ("R", "Right", "r")):
            out[joint.format(x=x)] = tuple(n.format(s=s, side=side, x=x) for n in names)
    return out


BUILT_IN: tuple[RigMap, ...] = (
    RigMap(
        "asf",  # CMU/HDM05 bone names, each BVH joint at its bone's start (replay.convert writes them so)
        _sided(
            {
                "root": ("root",),
                "{x}hip": ("{x}femur",),
                "{x}knee": ("{x}tibia",),
                "{x}ankle": ("{x}foot",),
                "{x}toes": ("{x}toes/end",),
                "belly": ("upperback",),
                "chest": ("thorax",),
                "neck": ("lowerneck",),
                "head": ("head",),
                "headtop": ("head/end",),
                "{x}clavicle": ("{x}clavicle",),
                "{x}shoulder": ("{x}humerus",),
                "{x}elbow": ("{x}radius",),
                "{x}wrist": ("{x}hand",),
                "{x}fingers": ("{x}fingers/end",),
                "{x}thumb": ("{x}thumb/end",),
            }
        ),
    ),
    RigMap(
        "upperarm",  # Hips, Spine, Chest, Neck, Head, Shoulder_L, UpperArm_L, ... (Bandai Namco Research)
        _sided(
            {
                "root": ("Hips",),
                "{x}hip": ("UpperLeg_{s}",),
                "{x}knee": ("LowerLeg_{s}",),
                "{x}ankle": ("Foot_{s}",),
                "{x}toes": ("Toes_{s}/end", "Toes_{s}"),
                "belly": ("Spine",),
                "chest": ("Chest",),
                "neck": ("Neck",),
                "head": ("Head",),
                "headtop": ("Head/end",),
                "{x}clavicle": ("Neck",),
                "{x}shoulder": ("UpperArm_{s}",),
                "{x}elbow": ("LowerArm_{s}",),
                "{x}wrist": ("Hand_{s}",),
                "{x}fingers": ("Hand_{s}/end",),
                "{x}thumb": (),
            }
        ),
    ),
    RigMap(
        "leftupleg",  # Hips, LeftUpLeg, LeftLeg, LeftFoot, LeftArm, LeftForeArm, LeftHand (and Mixamo's)
        _sided(
            {
                "root": ("Hips",),
                "{x}hip": ("{side}UpLeg",),
                "{x}knee": ("{side}Leg",),
                "{x}ankle": ("{side}Foot",),
                "{x}toes": ("{side}Toe_End", "{side}ToeBase/end", "{side}ToeBase", "{side}Toe"),
                "belly": ("Spine",),
                "chest": ("Spine2", "Spine1", "Chest"),
                "neck": ("Neck",),
                "head": ("Head",),
                "headtop": ("HeadTop_End", "Head/end"),
                "{x}clavicle": ("Neck",),
                "{x}shoulder": ("{side}Arm",),
                "{x}elbow": ("{side}ForeArm",),
                "{x}wrist": ("{side}Hand",),
                "{x}fingers": ("{side}HandMiddle1", "{side}HandIndex1", "{side}Hand/end"),
                "{x}thumb": ("{side}HandThumb1",),
            }
        ),
    ),
)


def parse_rig_map(value: object, source: str) -> RigMap:
    """A user's rig map from its parsed YAML (``docs/recordings-and-features.md``, "BVH")::

        name: studio-a            # optional (default: the file's name)
        joints:                   # standard joint: the rig's node, or its nodes in order of preference
          root: Hips
          lhip: [LeftUpLeg, L_Thigh]
          ...

    A standard joint it does not name is derived if it can be, else missing from the rig.
    :class:`MocapFormatError` naming ``source`` and the field for anything else."""

    def fail(field: str, reason: str) -> MocapFormatError:
        return MocapFormatError(source, None, f"{field}: {reason}")

    if not isinstance(value, dict):
        raise fail("the rig map", "must be a mapping with 'joints' (and optionally 'name')")
    unknown = sorted(str(k) for k in value if k not in ("name", "joints"))
    if unknown:
        raise fail(unknown[0], "unknown field (the fields are 'name' and 'joints')")
    name = value.get("name", source)
    if not isinstance(name, str) or not name:
        raise fail("name", "must be a non-empty string")
    joints = value.get("joints")
    if not isinstance(joints, dict) or not joints:
        raise fail("joints", "must map standard joints to the rig's node names")
    points: dict[str, tuple[str, ...]] = {}
    for joint, nodes in joints.items():
        if joint not in JOINT_NAMES:
            raise fail(f"joints.{joint}", f"not a standard joint (one of {', '.join(JOINT_NAMES)})")
        listed = [nodes] if isinstance(nodes, str) else nodes
        if not isinstance(listed, list) or not listed or not all(isinstance(n, str) and n for n in listed):
            raise fail(f"joints.{joint}", "must be a node name or a non-empty list of them")
        points[joint] = tuple(bare(n) for n in listed)
    return RigMap(name, points)


def names_plan(names: Sequence[str], source: str, maps: Sequence[RigMap] = BUILT_IN) -> RigPlan | None:
    """How a positions stream's announced joint ``names`` map onto the standard joints: None when
    they include the standard joints' own names (taken as they are), else the plan of the first of
    ``maps`` that fits (every announced joint a point of its own); :class:`MocapFormatError` naming
    ``source`` if none does."""
    if set(JOINT_NAMES) <= set(names):
        return None
    return rig_plan(names, [True] * len(names), source, maps)


def bare(name: str) -> str:
    """A node name without its namespace: ``mixamorig:LeftArm`` is ``LeftArm``."""
    return name.rsplit(":", 1)[-1]


@dataclass(frozen=True)
class RigPlan:
    """A map applied to one rig: for each standard joint (:data:`JOINT_NAMES` order) the index of
    the rig's node that stands for it, or -1 where it is derived (``derived`` names those)."""

    rig: str
    nodes: tuple[int, ...]
    derived: tuple[str, ...]


def rig_plan(
    names: Sequence[str], points: Sequence[bool], source: str, maps: Sequence[RigMap] = BUILT_IN
) -> RigPlan:
    """The plan of the first of ``maps`` that finds every standard joint but the derivable ones
    among a rig's node ``names`` (``points[k]``: whether node ``k`` is a point of its own, not an
    End Site at its joint); :class:`MocapFormatError` naming ``source`` and the joints the nearest
    map misses if none fits."""
    index: dict[str, int] = {}
    for k, name in enumerate(names):
        if points[k]:
            index.setdefault(bare(name), k)
    best: tuple[int, str, list[str]] | None = None
    for rig in maps:
        nodes: list[int] = []
        missing: list[str] = []
        derived: list[str] = []
        for joint in JOINT_NAMES:
            k = next((index[c] for c in rig.points.get(joint, ()) if c in index), -1)
            nodes.append(k)
            if k < 0:
                (derived if joint in DERIVABLE else missing).append(joint)
        if not missing:
            return RigPlan(rig.name, tuple(nodes), tuple(derived))
        if best is None or len(missing) < best[0]:
            best = (len(missing), rig.name, missing)
    assert best is not None
    raise MocapFormatError(
        source,
        None,
        f"no rig map fits its joints: the nearest ({best[1]}) finds no {', '.join(best[2])}",
    )


def standard_joints(positions: FloatArray, plan: RigPlan) -> FloatArray:
    """The standard joints of a rig's node ``positions`` shape ``(N, nodes, 3)``: shape ``(N, 26,
    3)``, those the rig lacks derived (module docstring)."""
    idx = {j: k for k, j in enumerate(JOINT_NAMES)}
    out = np.empty((positions.shape[0], len(JOINT_NAMES), 3))
    for j, k in enumerate(plan.nodes):
        if k >= 0:
            out[:, j] = positions[:, k]

    def joint(name: str) -> FloatArray:
        result: FloatArray = out[:, idx[name]]
        return result

    def along(start: FloatArray, towards: FloatArray, length: FloatArray) -> FloatArray:
        direction = towards - start
        norm = np.linalg.norm(direction, axis=1, keepdims=True)
        unit = np.divide(direction, norm, out=np.zeros_like(direction), where=norm > 0)
        moved: FloatArray = towards + unit * length[:, None]
        return moved

    def distance(a: str, b: str) -> FloatArray:
        d: FloatArray = np.linalg.norm(joint(a) - joint(b), axis=1)
        return d

    derived = set(plan.derived)
    if "headtop" in derived:
        thigh = 0.5 * (distance("lhip", "lknee") + distance("rhip", "rknee"))
        out[:, idx["headtop"]] = along(joint("neck"), joint("head"), HEAD_TOP_PER_THIGH * thigh)
    for x in "lr":
        if f"{x}fingers" in derived:
            forearm = distance(f"{x}elbow", f"{x}wrist")
            out[:, idx[f"{x}fingers"]] = along(
                joint(f"{x}elbow"), joint(f"{x}wrist"), FINGERS_PER_FOREARM * forearm
            )
        if f"{x}thumb" in derived:
            out[:, idx[f"{x}thumb"]] = joint(f"{x}fingers")
    return out


def up_axis(joints: FloatArray) -> str:
    """The axis a recording's standard joints ``(N, 26, 3)`` stand along: ``"z"`` when the median
    root-to-head vector over its frames points most along +z, else ``"y"`` (mocapd's up). A rig
    that lies along its parent's x at rest, as bandai2's, says nothing at rest: its frames do."""
    if not len(joints):
        return "y"
    up = np.median(joints[:, JOINT_NAMES.index("head")] - joints[:, JOINT_NAMES.index("root")], axis=0)
    return "z" if up[2] > abs(up[1]) and up[2] > abs(up[0]) else "y"


def hierarchy_plan(hierarchy: BvhHierarchy, maps: Sequence[RigMap] = BUILT_IN) -> RigPlan:
    """The plan of the first of ``maps`` that fits a BVH hierarchy (an End Site at its joint is no
    point of its own)."""
    joints = hierarchy.joints
    points = [not j.end_site or any(j.offset) for j in joints]
    return rig_plan([j.name for j in joints], points, hierarchy.source, maps)


def bvh_standard_joints(motion: BvhMotion, maps: Sequence[RigMap] = BUILT_IN) -> tuple[FloatArray, RigPlan]:
    """A BVH recording's standard joints, shape ``(N, 26, 3)`` in its own units, Y up (a rig that
    stands along Z, :func:`up_axis`, is turned a quarter about X as a Z-up positions stream is),
    through the first of ``maps`` that fits its rig, and that map's plan."""
    joints, plan, _ = _standard(motion, maps)
    return joints, plan


def _standard(motion: BvhMotion, maps: Sequence[RigMap]) -> tuple[FloatArray, RigPlan, str]:
    """:func:`bvh_standard_joints` and the axis the rig stands along."""
    plan = hierarchy_plan(motion.hierarchy, maps)
    standard = standard_joints(BvhKinematics(motion.hierarchy).positions(motion.channels), plan)
    up = up_axis(standard)
    return (y_up(standard) if up == "z" else standard), plan, up


class BvhPoses:
    """A BVH stream's poses one at a time (the wire's BVH skeletons): a channel row, shape ``(C,)``
    as a ``MOTION`` line holds it, to the standard joints, shape ``(26, 3)``, bit for bit a row of
    :func:`bvh_standard_joints` of the same frames (``up``: the axis the rig stands along, which a
    stream says in advance)."""

    def __init__(self, hierarchy: BvhHierarchy, up: str = "y", maps: Sequence[RigMap] = BUILT_IN) -> None:
        self.kinematics = BvhKinematics(hierarchy)
        self.plan = hierarchy_plan(hierarchy, maps)
        self.width = self.kinematics.width
        self.up = up
        self.rotations = np.array(
            [k for k, name in enumerate(hierarchy.channel_names) if name.endswith("rotation")], dtype=np.intp
        )
        """The columns of a channel row that are angles (degrees)."""

    def joints(self, channels: FloatArray) -> FloatArray:
        p = standard_joints(self.kinematics.positions_frame(channels)[None], self.plan)[0]
        out: FloatArray = y_up(p) if self.up == "z" else p
        return out


@dataclass(frozen=True)
class BvhTake:
    """A BVH recording as mocapd takes it: the file as read (``motion``), its standard ``joints``
    shape ``(N, 26, 3)`` (:func:`bvh_standard_joints`), their ``frames`` numbered from 1, the rig
    map's ``plan`` and the axis ``up`` the rig stands along in the file (its joints are turned to
    Y up)."""

    motion: BvhMotion
    joints: FloatArray
    frames: IntArray
    plan: RigPlan
    up: str = "y"

    @property
    def source(self) -> str:
        return self.motion.source

    @property
    def rate(self) -> float:
        return self.motion.rate


def read_bvh_take(path: str | Path, maps: Sequence[RigMap] = BUILT_IN) -> BvhTake:
    """The BVH file at ``path`` through the first of ``maps`` that fits its rig."""
    motion = read_bvh(path)
    joints, plan, up = _standard(motion, maps)
    frames = np.arange(1, len(joints) + 1, dtype=np.int64)
    return BvhTake(motion, joints, frames, plan, up)
