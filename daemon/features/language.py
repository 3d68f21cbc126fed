"""The signal language the feature catalog is written in (reference facts, sections a and 0).

A *signal* is a real-valued function of the joint positions per frame, built from a few geometric
primitives (:data:`Signal`); a :class:`Test` compares one with a loose threshold ``T1`` and a strict
``T2``, each a multiple of a :data:`Reference` length; a :class:`Feature` is true where all its
tests hold. :class:`BodyLengths` are the reference lengths, measured on a motion's first frame, so
that features do not change with the actor's size, position or heading.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal

import numpy as np

from daemon.types import FeatureSet, FloatArray

Reference = Literal["h_R", "h_L", "shoulder_width", "hip_width", "chest", "body", "one"]
"""The body length a threshold is a multiple of (:class:`BodyLengths`); ``one``: absolute units."""
Op = Literal[">=", ">", "<=", "<", "within"]
"""How a test compares its signal with a threshold; ``within``: inside a (low, high) pair, ends
included."""


@dataclass(frozen=True)
class Plane:
    """Signed distance of ``q`` from the plane through ``a``, ``b``, ``c`` with normal
    ``unit((a - c) x (b - c))``, measured from the fixture ``c``."""

    a: str
    b: str
    c: str
    q: str


@dataclass(frozen=True)
class NormalPlane:
    """Signed distance of ``q`` from the plane through ``c`` with normal ``unit(b - a)``."""

    a: str
    b: str
    c: str
    q: str


@dataclass(frozen=True)
class PlaneVelocity:
    """Velocity of ``q - c`` (smoothed over ``window_ms``) along the normal of :class:`Plane` (a, b, c)."""

    a: str
    b: str
    c: str
    q: str
    window_ms: float


@dataclass(frozen=True)
class NormalPlaneVelocity:
    """Velocity of ``q - c`` (smoothed over ``window_ms``) along ``unit(b - a)``."""

    a: str
    b: str
    c: str
    q: str
    window_ms: float


@dataclass(frozen=True)
class Speed:
    """Norm of the smoothed velocity of ``q``."""

    q: str
    window_ms: float


@dataclass(frozen=True)
class JointAngle:
    """Angle in degrees at ``b`` between ``a - b`` and ``c - b``."""

    a: str
    b: str
    c: str


@dataclass(frozen=True)
class SegmentAngle:
    """Angle in degrees between the segments ``p1 - p2`` and ``p3 - p4``."""

    p1: str
    p2: str
    p3: str
    p4: str


@dataclass(frozen=True)
class AngleToVertical:
    """Angle in degrees between ``b - a`` and the up axis (+y)."""

    a: str
    b: str


@dataclass(frozen=True)
class HeightAboveLowest:
    """``y(q)`` minus the lowest ``y`` over the toolbox's name map, leaving out ``exclude``."""

    q: str
    exclude: tuple[str, ...] = ()


@dataclass(frozen=True)
class VerticalExtent:
    """Highest minus lowest ``y`` over the toolbox's name map."""


@dataclass(frozen=True)
class HorizontalExtent:
    """Largest pairwise distance in the xz plane among ``joints``."""

    joints: tuple[str, ...]


@dataclass(frozen=True)
class Difference:
    """``first - second``."""

    first: Signal
    second: Signal


@dataclass(frozen=True)
class Absolute:
    signal: Signal


Signal = (
    Plane
    | NormalPlane
    | PlaneVelocity
    | NormalPlaneVelocity
    | Speed
    | JointAngle
    | SegmentAngle
    | AngleToVertical
    | HeightAboveLowest
    | VerticalExtent
    | HorizontalExtent
    | Difference
    | Absolute
)


@dataclass(frozen=True)
class Test:
    """``signal op T x reference`` for ``T`` in ``(t1, t2)``; for ``within``, ``t1``/``t2`` are
    (low, high) pairs in absolute units."""

    signal: Signal
    op: Op
    t1: float | tuple[float, float]
    t2: float | tuple[float, float]
    reference: Reference = "one"


@dataclass(frozen=True)
class Feature:
    """One boolean feature: true where all of its ``tests`` hold (track by track)."""

    name: str
    feature_set: FeatureSet
    tests: tuple[Test, ...]


# ---------------------------------------------------------------------------------- references


def _distance(a: Sequence[float], b: Sequence[float]) -> float:
    dx, dy, dz = a[0] - b[0], a[1] - b[1], a[2] - b[2]
    return math.sqrt(dx * dx + dy * dy + dz * dz)


@dataclass(frozen=True)
class BodyLengths:
    """Reference lengths measured on the first frame (reference facts, section 0)."""

    h_R: float
    h_L: float
    shoulder_width: float
    hip_width: float
    chest: float
    body: float

    def get(self, reference: Reference) -> float:
        return 1.0 if reference == "one" else float(getattr(self, reference))


REFERENCE_PAIRS: dict[str, tuple[tuple[str, str], ...]] = {
    "h_R": (("relbow", "rshoulder"),),
    "h_L": (("lshoulder", "lelbow"),),
    "shoulder_width": (("rshoulder", "lshoulder"),),
    "hip_width": (("rhip", "lhip"),),
    "chest": (("chest", "neck"),),
    "body": (
        ("rankle", "rknee"),
        ("rknee", "rhip"),
        ("root", "belly"),
        ("belly", "chest"),
        ("chest", "neck"),
        ("neck", "head"),
        ("head", "headtop"),
    ),
}
"""Each body length (but ``one``) as the joint pairs whose distances it sums."""


def body_lengths(frame: FloatArray, joint_names: Sequence[str]) -> BodyLengths:
    """Body lengths of one pose ``frame`` shape ``(J, 3)``."""
    idx = {n: i for i, n in enumerate(joint_names)}
    pose = np.asarray(frame, dtype=np.float64).tolist()

    def length(pairs: tuple[tuple[str, str], ...]) -> float:
        total = 0.0
        for a, b in pairs:
            total = total + _distance(pose[idx[a]], pose[idx[b]])
        return total

    return BodyLengths(**{name: length(pairs) for name, pairs in REFERENCE_PAIRS.items()})
