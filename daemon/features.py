"""The 39 boolean relational features (thesis Table 5.1; MRC05 section 3), as data, and their batch
evaluation.

Every feature is a *signal* (a real-valued function of the joint positions per frame, built from a
few geometric primitives) compared with two thresholds: a loose ``T1`` giving the track ``f1`` and a
strict ``T2`` giving ``f2``. The hysteresis of the toolbox's ``features_combine_robust`` (reference
facts, section b) combines them: ``out(t) = f2(t) or (out(t-1) and f1(t))``, ``out(0) = 0``. Every
threshold is a multiple of a body length measured at the first frame, so features do not change with
the actor's size, position or heading. Definitions: ``../shared/reference/bonn-toolbox-facts.md``
sections a and 0.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np
import numpy.typing as npt

from replay.joints import TOOLBOX_JOINTS

FloatArray = npt.NDArray[np.float64]
BoolArray = npt.NDArray[np.bool_]
FeatureSet = Literal["lower", "upper", "mix"]
Reference = Literal["h_R", "h_L", "shoulder_width", "hip_width", "chest", "body", "one"]
Op = Literal[">=", ">", "<=", "<", "within"]


# ---------------------------------------------------------------------------------------- signals


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


def _feature(name: str, feature_set: FeatureSet, *tests: Test) -> Feature:
    return Feature(name, feature_set, tests)


_HIP_AXIS = ("lhip", "rhip")
_TORSO_FORWARD = ("neck", "rhip", "lhip")  # plane(neck, rhip, lhip), fixture lhip: normal points forward
_NAME_MAP_XZ = ("lankle", "rankle", "lwrist", "rwrist", "headtop", "root")

CATALOG: tuple[Feature, ...] = (
    # lower (AK_lower), global 1-12
    _feature(
        "footRightBackRelLegLeft",
        "lower",
        Test(Plane("root", "lhip", "lankle", "rankle"), ">=", 0.0, 0.375, "h_R"),
    ),
    _feature(
        "footLeftBackRelLegRight",
        "lower",
        Test(Plane("root", "rankle", "rhip", "lankle"), ">=", 0.0, 0.375, "h_R"),
    ),
    _feature("footRightRaisedRelYBodyMin", "lower", Test(HeightAboveLowest("rtoes"), ">=", 1.0, 1.2, "h_R")),
    _feature("footLeftRaisedRelYBodyMin", "lower", Test(HeightAboveLowest("ltoes"), ">=", 1.0, 1.2, "h_R")),
    _feature(
        "feetApartRelHips",
        "lower",
        Test(Absolute(NormalPlane("lhip", "rhip", "lankle", "rankle")), ">=", 1.8, 2.1, "h_R"),
    ),
    _feature("kneeRightBent", "lower", Test(JointAngle("rhip", "rknee", "rankle"), "<=", 120.0, 110.0)),
    _feature("kneeLeftBent", "lower", Test(JointAngle("lhip", "lknee", "lankle"), "<=", 120.0, 110.0)),
    _feature(
        "footCrossover",
        "lower",
        Test(
            Difference(
                NormalPlane("lhip", "rhip", "lhip", "rankle"), NormalPlane("lhip", "rhip", "lhip", "lankle")
            ),
            "<=",
            0.0,
            -0.125,
            "hip_width",
        ),
    ),
    _feature(
        "feetMoveTogetherRelHips",
        "lower",
        Test(
            Difference(
                NormalPlaneVelocity(*_HIP_AXIS, "rhip", "lankle", 100.0),
                NormalPlaneVelocity(*_HIP_AXIS, "rhip", "rankle", 100.0),
            ),
            ">=",
            1.3,
            1.5,
            "h_R",
        ),
    ),
    _feature(
        "feetMoveApartRelHips",
        "lower",
        Test(
            Difference(
                NormalPlaneVelocity(*_HIP_AXIS, "rhip", "rankle", 100.0),
                NormalPlaneVelocity(*_HIP_AXIS, "rhip", "lankle", 100.0),
            ),
            ">=",
            1.3,
            1.5,
            "h_R",
        ),
    ),
    _feature(
        "footRightHighVel",
        "lower",
        Test(Speed("rtoes", 100.0), ">=", 2.0, 2.5, "h_R"),
        Test(Speed("rankle", 100.0), ">=", 2.0, 2.5, "h_R"),
    ),
    _feature(
        "footLeftHighVel",
        "lower",
        Test(Speed("ltoes", 100.0), ">=", 2.0, 2.5, "h_R"),
        Test(Speed("lankle", 100.0), ">=", 2.0, 2.5, "h_R"),
    ),
    # upper (AK_upper), global 13-26
    _feature(
        "handRightToFrontRelTorso",
        "upper",
        Test(PlaneVelocity(*_TORSO_FORWARD, "rwrist", 250.0), ">", 1.3, 1.8, "h_L"),
    ),
    _feature(
        "handLeftToFrontRelTorso",
        "upper",
        Test(PlaneVelocity(*_TORSO_FORWARD, "lwrist", 250.0), ">", 1.3, 1.8, "h_L"),
    ),
    _feature(
        "handRightRaisedRelSpine",
        "upper",
        Test(NormalPlane("chest", "neck", "neck", "rwrist"), ">=", 0.0, 0.2, "chest"),
    ),
    _feature(
        "handLeftRaisedRelSpine",
        "upper",
        Test(NormalPlane("chest", "neck", "neck", "lwrist"), ">=", 0.0, 0.2, "chest"),
    ),
    _feature(
        "handRightToTopRelSpine",
        "upper",
        Test(NormalPlaneVelocity("chest", "neck", "neck", "rwrist", 250.0), ">", 1.3, 1.8, "h_L"),
    ),
    _feature(
        "handLeftToTopRelSpine",
        "upper",
        Test(NormalPlaneVelocity("chest", "neck", "neck", "lwrist", 250.0), ">", 1.3, 1.8, "h_L"),
    ),
    _feature(
        "elbowRightBent", "upper", Test(JointAngle("rshoulder", "relbow", "rwrist"), "<=", 120.0, 110.0)
    ),
    _feature("elbowLeftBent", "upper", Test(JointAngle("lshoulder", "lelbow", "lwrist"), "<=", 120.0, 110.0)),
    _feature(
        "handsApartRelShoulders",
        "upper",
        Test(
            Absolute(NormalPlane("lshoulder", "rshoulder", "lwrist", "rwrist")),
            ">=",
            2.0,
            2.5,
            "shoulder_width",
        ),
    ),
    _feature(
        "handsMoveTogether",
        "upper",
        Test(NormalPlaneVelocity("lwrist", "rwrist", "rwrist", "lwrist", 100.0), ">=", 1.2, 1.4, "h_R"),
    ),
    _feature(
        "handRightMoveApartRelRoot",
        "upper",
        Test(NormalPlaneVelocity("rwrist", "root", "rwrist", "root", 0.0), ">=", 1.2, 1.4, "h_R"),
    ),
    _feature(
        "handLeftMoveApartRelRoot",
        "upper",
        Test(NormalPlaneVelocity("lwrist", "root", "lwrist", "root", 0.0), ">=", 1.2, 1.4, "h_R"),
    ),
    _feature("handRightHighVel", "upper", Test(Speed("rfingers", 100.0), ">=", 2.0, 2.5, "h_R")),
    _feature("handLeftHighVel", "upper", Test(Speed("lfingers", 100.0), ">=", 2.0, 2.5, "h_R")),
    # mix (AK_mix), global 27-39
    _feature(
        "humerusRightAbductRelSpine",
        "mix",
        Test(SegmentAngle("neck", "root", "relbow", "rshoulder"), "<", 155.0, 150.0),
    ),
    _feature(
        "humerusLeftAbductRelSpine",
        "mix",
        Test(SegmentAngle("neck", "root", "lelbow", "lshoulder"), "<", 155.0, 150.0),
    ),
    _feature(
        "femurRightAbductRelSpine",
        "mix",
        Test(SegmentAngle("neck", "root", "rhip", "rknee"), ">", 45.0, 50.0),
    ),
    _feature(
        "femurLeftAbductRelSpine", "mix", Test(SegmentAngle("neck", "root", "lhip", "lknee"), ">", 45.0, 50.0)
    ),
    _feature(
        "rootBehindFeetLeftRightNeck",
        "mix",
        Test(Plane("lankle", "neck", "rankle", "root"), "<", -0.35, -0.5, "h_R"),
    ),
    _feature(
        "spineHorizontalRelY",
        "mix",
        Test(AngleToVertical("root", "neck"), "within", (60.0, 120.0), (70.0, 110.0)),
    ),
    _feature(
        "handRightLowRelYBodyMin",
        "mix",
        Test(HeightAboveLowest("rfingers", ("rfingers", "rwrist")), "<", 1.4, 1.2, "h_R"),
    ),
    _feature(
        "handLeftLowRelYBodyMin",
        "mix",
        Test(HeightAboveLowest("lfingers", ("lfingers", "lwrist")), "<", 1.4, 1.2, "h_R"),
    ),
    _feature(
        "shouldersRotatedRightRelHip",
        "mix",
        Test(
            Difference(
                Plane("rhip", "lhip", "neck", "lshoulder"), Plane("rhip", "lhip", "neck", "rshoulder")
            ),
            ">",
            0.35,
            0.40,
            "h_L",
        ),
    ),
    _feature(
        "shouldersRotatedLeftRelHip",
        "mix",
        Test(
            Difference(
                Plane("rhip", "lhip", "neck", "lshoulder"), Plane("rhip", "lhip", "neck", "rshoulder")
            ),
            "<",
            -0.35,
            -0.40,
            "h_L",
        ),
    ),
    _feature("bodyExtentRelY", "mix", Test(VerticalExtent(), "<=", 0.9, 0.8, "body")),
    _feature(
        "bodyExtentExtremitiesRelXZ", "mix", Test(HorizontalExtent(_NAME_MAP_XZ), ">=", 3.0, 3.25, "h_R")
    ),
    _feature("rootHighVel", "mix", Test(Speed("root", 0.0), ">=", 2.0, 2.3, "h_R")),
)

FEATURE_NAMES: tuple[str, ...] = tuple(f.name for f in CATALOG)
SET_SLICES: dict[FeatureSet, slice] = {"lower": slice(0, 12), "upper": slice(12, 26), "mix": slice(26, 39)}


# ------------------------------------------------------------------------------ generic arithmetic
# Every signal is written once, on 3-vectors given as component triples whose entries are Python
# floats (one frame: the incremental path) or float64 arrays (all frames: the batch path). Only +, -,
# *, / and sqrt occur, each correctly rounded, in one fixed order, so both paths give the same bits.
# Angles are compared through their cosines (arccos is decreasing), which keeps transcendental
# functions, whose last bit can depend on the vector code path, out of the features.

Num = Any
Vec = Sequence[Num] | FloatArray


def _sub(a: Vec, b: Vec) -> Vec:
    return (a[0] - b[0], a[1] - b[1], a[2] - b[2])


def _dot(a: Vec, b: Vec) -> Num:
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


def _cross(a: Vec, b: Vec) -> Vec:
    return (a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0])


@dataclass(frozen=True)
class _Ops:
    sqrt: Callable[[Num], Num]
    minimum: Callable[[list[Num]], Num]
    maximum: Callable[[list[Num]], Num]


_FLOAT_OPS = _Ops(math.sqrt, min, max)
_ARRAY_OPS = _Ops(np.sqrt, np.minimum.reduce, np.maximum.reduce)

Poses = Sequence[Vec]
"""Joint positions: ``P[j]`` is the component triple of joint ``j``."""
SignalFn = Callable[[Poses, Sequence[Vec], _Ops], Num]


def window_frames(window_ms: float, frame_rate: float) -> int:
    """Velocity window length L in frames: ``ceil(W / 1000 * fs)``, at least 1 (reference facts, 0)."""
    return max(1, math.ceil(window_ms / 1000.0 * frame_rate))


@dataclass(frozen=True)
class _Trajectory:
    """``P(q) - P(c)`` (or ``P(q)`` when ``c`` is None) smoothed over a window of ``big_l`` frames
    ending ``big_l - h`` frames after the current one."""

    q: int
    c: int | None
    big_l: int

    @property
    def h(self) -> int:
        return math.ceil(self.big_l / 2)

    @property
    def lead(self) -> int:
        """Frames after ``t`` whose positions the smoothed velocity at ``t`` needs."""
        return self.big_l - self.h + 1

    def point(self, poses: Poses) -> Vec:
        p = poses[self.q]
        return p if self.c is None else _sub(p, poses[self.c])


# ---------------------------------------------------------------------------------- velocities


def _mirror(j: npt.NDArray[np.intp], m: int) -> npt.NDArray[np.intp]:
    """Indices ``j`` reflected into ``[0, m)`` with the edge repeated, periodically (``padarray``'s
    'symmetric' for pads of any size)."""
    r = np.mod(j, 2 * m)
    out: npt.NDArray[np.intp] = np.where(r < m, r, 2 * m - 1 - r)
    return out


def _is_interior(t: int, n: int, big_l: int, h: int) -> bool:
    return h - 1 <= t <= n - big_l + h - 2


def _edge_indices(t: npt.NDArray[np.intp], n: int, big_l: int, h: int) -> npt.NDArray[np.intp]:
    """For frames ``t`` shape ``(E,)`` of an ``n``-frame trajectory (``n >= 2``), the indices ``m``
    shape ``(E, L)`` of the forward differences ``x(m+1) - x(m)`` in their smoothing windows, mirrored
    as the toolbox does (reference facts, section 0, step 3): ``v(n-1) = v(n-2)``, ``padarray``
    'symmetric' at both ends, and for ``n < L`` a first symmetric padding of ``v`` up to length L."""
    j = t[:, None] + np.arange(big_l)[None, :] - (h - 1)
    m = _mirror(_mirror(j, big_l), n) if n < big_l else _mirror(j, n)
    out: npt.NDArray[np.intp] = np.minimum(m, n - 2)
    return out


def _smooth(x: FloatArray, big_l: int, frame_rate: float) -> FloatArray:
    """Smoothed velocity of ``x`` shape ``(3, N)``, shape ``(3, N)`` (reference facts, section 0).

    Away from the ends the window sum of forward differences telescopes to ``x(t+L-h+1) - x(t-h+1)``;
    near the ends the mirrored differences are summed one after another. :class:`FeatureStream` does
    the same per frame."""
    n = x.shape[1]
    out = np.zeros_like(x)
    if n < 2:
        return out
    h = math.ceil(big_l / 2)
    if n > big_l:
        out[:, h - 1 : n - big_l + h - 1] = (x[:, big_l:] - x[:, : n - big_l]) / big_l * frame_rate
    t = np.arange(n)
    edge = t[(t < h - 1) | (t > n - big_l + h - 2)]
    if edge.size:
        m = _edge_indices(edge, n, big_l, h)
        d = x[:, 1:] - x[:, :-1]
        acc = d[:, m[:, 0]]
        for k in range(1, big_l):
            acc = acc + d[:, m[:, k]]
        out[:, edge] = acc / big_l * frame_rate
    return out


def smoothed_velocity(x: FloatArray, window_ms: float, frame_rate: float) -> FloatArray:
    """Velocity of the trajectory ``x`` shape ``(N, 3)`` in units per second, box-averaged over a
    centred window of ``L = window_frames(window_ms)`` frames: forward differences
    ``v(t) = x(t+1) - x(t)`` (``v(N) = v(N-1)``), then the mean of ``v(t+1-h .. t+L-h)`` with
    ``h = ceil(L/2)``, indices mirrored at both ends (Matlab's ``padarray(..., 'symmetric')``).
    Returns shape ``(N, 3)``."""
    x = np.ascontiguousarray(np.asarray(x, dtype=np.float64).T)
    return _smooth(x, window_frames(window_ms, frame_rate), frame_rate).T


# ---------------------------------------------------------------------------------- compilation


@dataclass(frozen=True)
class _CompiledTest:
    feature: int
    value: SignalFn
    op: Op
    t1: float | tuple[float, float]
    t2: float | tuple[float, float]
    reference: Reference


_COS_OP: dict[Op, Op] = {"<=": ">=", "<": ">", ">=": "<=", ">": "<", "within": "within"}


def _cos_threshold(t: float | tuple[float, float]) -> float | tuple[float, float]:
    if isinstance(t, tuple):
        return (math.cos(math.radians(t[1])), math.cos(math.radians(t[0])))
    return math.cos(math.radians(t))


class _Program:
    """The catalog bound to a joint order and a frame rate: one closure per distinct signal, the
    velocity trajectories they need, and the tests."""

    def __init__(self, joint_names: tuple[str, ...], frame_rate: float) -> None:
        if not (math.isfinite(frame_rate) and frame_rate > 0):
            raise ValueError(f"frame rate must be a positive number, got {frame_rate}")
        index = {name: i for i, name in enumerate(joint_names)}
        missing = sorted({j for j in _catalog_joints() if j not in index})
        if missing:
            raise ValueError(f"joint positions lack the joints {', '.join(missing)}")
        self.joint_names = joint_names
        self.frame_rate = frame_rate
        self.index = index
        self.name_map = [index[n] for n in TOOLBOX_JOINTS]
        self.trajectories: list[_Trajectory] = []
        cache: dict[Signal, tuple[SignalFn, bool]] = {}
        tests: list[_CompiledTest] = []
        for k, feature in enumerate(CATALOG):
            for test in feature.tests:
                if test.signal not in cache:
                    cache[test.signal] = self._compile(test.signal)
                fn, cosine = cache[test.signal]
                op, t1, t2 = test.op, test.t1, test.t2
                if cosine:
                    op, t1, t2 = _COS_OP[op], _cos_threshold(t1), _cos_threshold(t2)
                tests.append(_CompiledTest(k, fn, op, t1, t2, test.reference))
        self.tests = tuple(tests)
        self.lead = max((tr.lead for tr in self.trajectories), default=0)

    def _trajectory(self, q: str, c: str | None, window_ms: float) -> int:
        fixture = None if c is None else self.index[c]
        tr = _Trajectory(self.index[q], fixture, window_frames(window_ms, self.frame_rate))
        if tr not in self.trajectories:
            self.trajectories.append(tr)
        return self.trajectories.index(tr)

    def _compile(self, signal: Signal) -> tuple[SignalFn, bool]:
        """The signal as a closure ``(P, S, ops) -> value``, and whether the value is a cosine."""
        ix = self.index
        match signal:
            case Plane(a, b, c, q) | PlaneVelocity(a, b, c, q):
                ia, ib, ic, iq = ix[a], ix[b], ix[c], ix[q]
                if isinstance(signal, PlaneVelocity):
                    k = self._trajectory(q, c, signal.window_ms)

                    def plane_velocity(p: Poses, s: Sequence[Vec], ops: _Ops) -> Num:
                        n = _cross(_sub(p[ia], p[ic]), _sub(p[ib], p[ic]))
                        return _dot(n, s[k]) / ops.sqrt(_dot(n, n))

                    return plane_velocity, False

                def plane(p: Poses, s: Sequence[Vec], ops: _Ops) -> Num:
                    n = _cross(_sub(p[ia], p[ic]), _sub(p[ib], p[ic]))
                    return _dot(n, _sub(p[iq], p[ic])) / ops.sqrt(_dot(n, n))

                return plane, False
            case NormalPlane(a, b, c, q):
                ia, ib, ic, iq = ix[a], ix[b], ix[c], ix[q]

                def normal_plane(p: Poses, s: Sequence[Vec], ops: _Ops) -> Num:
                    n = _sub(p[ib], p[ia])
                    return _dot(n, _sub(p[iq], p[ic])) / ops.sqrt(_dot(n, n))

                return normal_plane, False
            case NormalPlaneVelocity(a, b, c, q, w):
                ia, ib = ix[a], ix[b]
                k = self._trajectory(q, c, w)

                def normal_plane_velocity(p: Poses, s: Sequence[Vec], ops: _Ops) -> Num:
                    n = _sub(p[ib], p[ia])
                    return _dot(n, s[k]) / ops.sqrt(_dot(n, n))

                return normal_plane_velocity, False
            case Speed(q, w):
                k = self._trajectory(q, None, w)

                def speed(p: Poses, s: Sequence[Vec], ops: _Ops) -> Num:
                    return ops.sqrt(_dot(s[k], s[k]))

                return speed, False
            case JointAngle(a, b, c) | SegmentAngle(a, b, c, _):
                if isinstance(signal, JointAngle):
                    i1, i2, i3, i4 = ix[a], ix[b], ix[c], ix[b]
                else:
                    i1, i2, i3, i4 = ix[signal.p1], ix[signal.p2], ix[signal.p3], ix[signal.p4]

                def cos_angle(p: Poses, s: Sequence[Vec], ops: _Ops) -> Num:
                    u, v = _sub(p[i1], p[i2]), _sub(p[i3], p[i4])
                    return _dot(u, v) / ops.sqrt(_dot(u, u) * _dot(v, v))

                return cos_angle, True
            case AngleToVertical(a, b):
                ia, ib = ix[a], ix[b]

                def cos_to_vertical(p: Poses, s: Sequence[Vec], ops: _Ops) -> Num:
                    u = _sub(p[ib], p[ia])
                    return u[1] / ops.sqrt(_dot(u, u))

                return cos_to_vertical, True
            case HeightAboveLowest(q, exclude):
                iq = ix[q]
                keep = [i for n, i in zip(TOOLBOX_JOINTS, self.name_map, strict=True) if n not in exclude]

                def height(p: Poses, s: Sequence[Vec], ops: _Ops) -> Num:
                    return p[iq][1] - ops.minimum([p[i][1] for i in keep])

                return height, False
            case VerticalExtent():
                everyone = self.name_map

                def extent(p: Poses, s: Sequence[Vec], ops: _Ops) -> Num:
                    ys = [p[i][1] for i in everyone]
                    return ops.maximum(ys) - ops.minimum(ys)

                return extent, False
            case HorizontalExtent(joints):
                idx = [ix[j] for j in joints]
                pairs = [(a, b) for n, a in enumerate(idx) for b in idx[n + 1 :]]

                def spread(p: Poses, s: Sequence[Vec], ops: _Ops) -> Num:
                    d2 = []
                    for a, b in pairs:
                        dx, dz = p[a][0] - p[b][0], p[a][2] - p[b][2]
                        d2.append(dx * dx + dz * dz)
                    return ops.sqrt(ops.maximum(d2))

                return spread, False
            case Difference(first, second):
                (f, cf), (g, cg) = self._compile(first), self._compile(second)
                if cf or cg:
                    raise ValueError("differences of angles are not supported")

                def difference(p: Poses, s: Sequence[Vec], ops: _Ops) -> Num:
                    return f(p, s, ops) - g(p, s, ops)

                return difference, False
            case Absolute(inner):
                f, cosine = self._compile(inner)
                if cosine:
                    raise ValueError("absolute values of angles are not supported")

                def absolute(p: Poses, s: Sequence[Vec], ops: _Ops) -> Num:
                    return abs(f(p, s, ops))

                return absolute, False
        raise TypeError(f"unknown signal {signal!r}")

    def thresholds(self, lengths: BodyLengths) -> list[tuple[Num, Num]]:
        """``(T1, T2)`` of every test in absolute units."""
        out: list[tuple[Num, Num]] = []
        for test in self.tests:
            scale = lengths.get(test.reference)
            if test.op == "within":
                out.append((test.t1, test.t2))
            else:
                assert not isinstance(test.t1, tuple) and not isinstance(test.t2, tuple)
                out.append((test.t1 * scale, test.t2 * scale))
        return out


def _catalog_joints() -> set[str]:
    names: set[str] = set(TOOLBOX_JOINTS)
    for feature in CATALOG:
        for test in feature.tests:
            stack: list[Any] = [test.signal]
            while stack:
                s = stack.pop()
                for value in vars(s).values():
                    if isinstance(value, str):
                        names.add(value)
                    elif isinstance(value, tuple):
                        names.update(v for v in value if isinstance(v, str))
                    elif not isinstance(value, int | float):
                        stack.append(value)
    return names


_PROGRAMS: dict[tuple[tuple[str, ...], float], _Program] = {}


def _program(joint_names: Sequence[str], frame_rate: float) -> _Program:
    key = (tuple(joint_names), float(frame_rate))
    if key not in _PROGRAMS:
        _PROGRAMS[key] = _Program(*key)
    return _PROGRAMS[key]


def latency_frames(frame_rate: float) -> int:
    """How many frames after frame ``t`` arrives :class:`FeatureStream` can emit its vector: the
    longest velocity window's look-ahead ``L - ceil(L/2) + 1`` (16 at 120 Hz, 5 at 30 Hz)."""
    return max(_Trajectory(0, None, window_frames(w, frame_rate)).lead for w in _windows())


def _windows() -> set[float]:
    out: set[float] = set()
    for feature in CATALOG:
        for test in feature.tests:
            stack: list[Any] = [test.signal]
            while stack:
                s = stack.pop()
                if hasattr(s, "window_ms"):
                    out.add(s.window_ms)
                stack.extend(v for v in vars(s).values() if not isinstance(v, str | int | float | tuple))
    return out


# ---------------------------------------------------------------------------------- references


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


_BODY_CHAIN = (
    ("rankle", "rknee"),
    ("rknee", "rhip"),
    ("root", "belly"),
    ("belly", "chest"),
    ("chest", "neck"),
    ("neck", "head"),
    ("head", "headtop"),
)


def body_lengths(frame: FloatArray, joint_names: Sequence[str]) -> BodyLengths:
    """Body lengths of one pose ``frame`` shape ``(J, 3)``."""
    idx = {n: i for i, n in enumerate(joint_names)}
    pose = np.asarray(frame, dtype=np.float64).tolist()

    def d(a: str, b: str) -> float:
        u = _sub(pose[idx[a]], pose[idx[b]])
        return math.sqrt(_dot(u, u))

    body = 0.0
    for a, b in _BODY_CHAIN:
        body = body + d(a, b)
    return BodyLengths(
        h_R=d("relbow", "rshoulder"),
        h_L=d("lshoulder", "lelbow"),
        shoulder_width=d("rshoulder", "lshoulder"),
        hip_width=d("rhip", "lhip"),
        chest=d("chest", "neck"),
        body=body,
    )


# ---------------------------------------------------------------------------------- thresholds


def _compare(values: Num, op: Op, threshold: Num) -> Num:
    if op == "within":
        lo, hi = threshold
        return (values >= lo) & (values <= hi)
    if op == ">=":
        return values >= threshold
    if op == ">":
        return values > threshold
    if op == "<=":
        return values <= threshold
    return values < threshold


def hysteresis(f1: BoolArray, f2: BoolArray) -> BoolArray:
    """``out(t) = f2(t) or (out(t-1) and f1(t))`` along axis 0, ``out(-1) = 0`` (nested tracks, f2 => f1;
    reference facts, section b).

    Vectorised: a frame is on iff the last frame at or before it where f2 holds is reachable through
    an unbroken run of f1."""
    n = f1.shape[0]
    idx = np.arange(n)[:, None] * np.ones(f1.shape[1:], dtype=np.intp)[None]
    last_f2 = np.maximum.accumulate(np.where(f2, idx, -1), axis=0)
    last_break = np.maximum.accumulate(np.where(~f1 & ~f2, idx, -1), axis=0)
    on: BoolArray = (last_f2 >= 0) & (last_f2 > last_break)
    return on


def _check_positions(positions: FloatArray, n_joints: int) -> FloatArray:
    p = np.asarray(positions, dtype=np.float64)
    if p.ndim != 3 or p.shape[1:] != (n_joints, 3):
        raise ValueError(f"positions must have shape (N, {n_joints}, 3), got {p.shape}")
    if not np.isfinite(p).all():
        bad = int(np.argwhere(~np.isfinite(p))[0][0])
        raise ValueError(f"positions are not finite at frame index {bad}")
    return p


def feature_tracks(
    positions: FloatArray, joint_names: Sequence[str], frame_rate: float, lengths: BodyLengths | None = None
) -> tuple[BoolArray, BoolArray]:
    """The loose and strict tracks ``(f1, f2)`` of ``positions`` shape ``(N, J, 3)``, each ``(N, 39)``."""
    program = _program(joint_names, frame_rate)
    p = _check_positions(positions, len(program.joint_names))
    n = p.shape[0]
    f1 = np.ones((n, len(CATALOG)), dtype=bool)
    f2 = np.ones((n, len(CATALOG)), dtype=bool)
    if n == 0:
        return f1, f2
    comp = np.ascontiguousarray(p.transpose(1, 2, 0))  # (J, 3, N): each component a contiguous row
    poses: Poses = list(comp)
    velocities = [_smooth(np.asarray(tr.point(poses)), tr.big_l, frame_rate) for tr in program.trajectories]
    thresholds = program.thresholds(lengths or body_lengths(p[0], program.joint_names))
    values: dict[SignalFn, Num] = {}
    with np.errstate(invalid="ignore", divide="ignore"):
        for test, (t1, t2) in zip(program.tests, thresholds, strict=True):
            if test.value not in values:
                values[test.value] = test.value(poses, velocities, _ARRAY_OPS)
            v = values[test.value]
            f1[:, test.feature] &= _compare(v, test.op, t1)
            f2[:, test.feature] &= _compare(v, test.op, t2)
    return f1, f2


def features(positions: FloatArray, joint_names: Sequence[str], frame_rate: float = 120.0) -> BoolArray:
    """The 39 features of a whole motion: ``positions`` shape ``(N, J, 3)`` (joints named by
    ``joint_names``) gives a boolean matrix shape ``(N, 39)`` in :data:`FEATURE_NAMES` order."""
    f1, f2 = feature_tracks(positions, joint_names, frame_rate)
    return hysteresis(f1, f2)


# ---------------------------------------------------------------------------------- streaming


class FeatureStream:
    """The 39 features of a stream, one pose at a time: the incremental twin of :func:`features`.

    ``push(pose)`` with ``pose`` shape ``(J, 3)`` returns the vectors that became final, each a bool
    array shape ``(39,)``: the vector of frame ``t`` comes out when frame ``t + latency`` arrives
    (``latency`` = :func:`latency_frames`, 16 frames = 133 ms at 120 Hz, because the 250 ms velocity
    windows are centred), and :meth:`flush` returns the last ``latency`` vectors when the stream ends
    (the windows are then mirrored at the end, exactly as in the batch) and makes the object ready
    for a new stream. Body lengths are measured on the first pose. Memory is bounded: the last
    ``latency + L`` poses. The output equals :func:`features` on the same frames bit for bit: both run
    the same arithmetic in the same order, on Python floats here and on arrays there."""

    def __init__(self, joint_names: Sequence[str], frame_rate: float = 120.0) -> None:
        self._program = _program(joint_names, frame_rate)
        self.latency = self._program.lead
        self._keep = self.latency + max((tr.h for tr in self._program.trajectories), default=1) + 1
        self._reset()

    def _reset(self) -> None:
        self._history: deque[tuple[list[list[float]], list[Vec]]] = deque(maxlen=self._keep)
        self._n = 0
        self._emitted = 0
        self._thresholds: list[tuple[Num, Num]] = []
        self._previous = [False] * len(CATALOG)

    def push(self, pose: FloatArray) -> list[BoolArray]:
        """Add the next pose; return the vectors that became final (at most one)."""
        program = self._program
        p = np.asarray(pose, dtype=np.float64)
        if p.shape != (len(program.joint_names), 3):
            raise ValueError(f"pose must have shape ({len(program.joint_names)}, 3), got {p.shape}")
        if not np.isfinite(p).all():
            raise ValueError(f"pose {self._n} is not finite")
        rows: list[list[float]] = p.tolist()
        if self._n == 0:
            self._thresholds = program.thresholds(body_lengths(p, program.joint_names))
        self._history.append((rows, [tr.point(rows) for tr in program.trajectories]))
        self._n += 1
        t = self._n - 1 - self.latency
        return [] if t < 0 else [self._emit(t, self._n)]

    def flush(self) -> list[BoolArray]:
        """End the stream: the vectors of its last frames, then a fresh state."""
        n = self._n
        out = [self._emit(t, n) for t in range(self._emitted, n)]
        self._reset()
        return out

    def _velocity(self, k: int, tr: _Trajectory, t: int, n: int) -> Vec:
        """Smoothed velocity of trajectory ``k`` at frame ``t`` of ``n`` frames (as :func:`_smooth`)."""
        base = n - len(self._history)
        big_l, h, fs = tr.big_l, tr.h, self._program.frame_rate
        if _is_interior(t, n, big_l, h):
            a, b = self._history[t + big_l - h + 1 - base][1][k], self._history[t - h + 1 - base][1][k]
            return ((a[0] - b[0]) / big_l * fs, (a[1] - b[1]) / big_l * fs, (a[2] - b[2]) / big_l * fs)
        if n < 2:
            return (0.0, 0.0, 0.0)
        acc: Vec = (0.0, 0.0, 0.0)
        for j, m in enumerate(_edge_indices(np.array([t]), n, big_l, h)[0].tolist()):
            d = _sub(self._history[m + 1 - base][1][k], self._history[m - base][1][k])
            acc = d if j == 0 else (acc[0] + d[0], acc[1] + d[1], acc[2] + d[2])
        return (acc[0] / big_l * fs, acc[1] / big_l * fs, acc[2] / big_l * fs)

    def _emit(self, t: int, n: int) -> BoolArray:
        program = self._program
        rows = self._history[t - (n - len(self._history))][0]
        velocities = [self._velocity(k, tr, t, n) for k, tr in enumerate(program.trajectories)]
        try:
            values: list[Num] = self._values(rows, velocities, _FLOAT_OPS)
        except ZeroDivisionError:  # a degenerate pose: evaluate as the batch does, to nan
            with np.errstate(invalid="ignore", divide="ignore"):
                columns = [np.array(r)[:, None] for r in rows]
                values = self._values(columns, [np.array(v)[:, None] for v in velocities], _ARRAY_OPS)
        f1 = [True] * len(CATALOG)
        f2 = [True] * len(CATALOG)
        for test, v, (t1, t2) in zip(program.tests, values, self._thresholds, strict=True):
            f1[test.feature] = f1[test.feature] and bool(_compare(v, test.op, t1))
            f2[test.feature] = f2[test.feature] and bool(_compare(v, test.op, t2))
        self._previous = [b2 or (prev and b1) for b1, b2, prev in zip(f1, f2, self._previous, strict=True)]
        self._emitted = t + 1
        return np.array(self._previous, dtype=bool)

    def _values(self, rows: Poses, velocities: Sequence[Vec], ops: _Ops) -> list[Num]:
        cache: dict[SignalFn, Num] = {}
        out = []
        for test in self._program.tests:
            if test.value not in cache:
                cache[test.value] = test.value(rows, velocities, ops)
            out.append(cache[test.value])
        return out
