"""The 39 boolean relational features (thesis Table 5.1; MRC05 section 3) as data, compiled once into
Python that evaluates them on a whole motion (:func:`features`) or one pose at a time
(:class:`FeatureStream`) with bit-identical results.

Every feature is a *signal* (a real-valued function of the joint positions per frame, built from a
few geometric primitives) compared with two thresholds: a loose ``T1`` giving the track ``f1`` and a
strict ``T2`` giving ``f2``. The hysteresis of the toolbox's ``features_combine_robust`` (reference
facts, section b) combines them: ``out(t) = f2(t) or (out(t-1) and f1(t))``, ``out(0) = 0``. Every
threshold is a multiple of a body length measured at the first frame, so features do not change with
the actor's size, position or heading. Definitions: ``../shared/reference/bonn-toolbox-facts.md``
sections a and 0.
"""

from __future__ import annotations

import ast
import math
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np
import numpy.typing as npt

from daemon._features import Bytecode, FeatureCore
from daemon.types import MAX_NATIVE_RATE, N_FEATURES, BoolArray, FeatureSet, FloatArray
from replay.joints import JOINT_NAMES, TOOLBOX_JOINTS

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
assert len(FEATURE_NAMES) == N_FEATURES == SET_SLICES["mix"].stop


# ------------------------------------------------------------------------------------ arithmetic
# The catalog is compiled (class _Program) into one straight-line Python function that reads joint
# components ``P[3j + c]`` as Python floats (one frame: the stream) or as float64 arrays (all frames:
# the batch). Only +, -, *, / and sqrt occur, each correctly rounded, in one fixed order, so both paths
# give the same bits. Angles are compared through their cosines (arccos is decreasing), which keeps
# transcendental functions, whose last bit can depend on the vector code path, out of the features.

Num = Any
Poses = Sequence[Num]
"""Joint positions, flat: ``P[3j + c]`` is component ``c`` of joint ``j`` (a float, or an array over
frames)."""


# (sqrt, minimum of a list, maximum of a list) for the compiled frame function.
_ARRAY_OPS = (np.sqrt, np.minimum.reduce, np.maximum.reduce)


def _distance(a: Sequence[float], b: Sequence[float]) -> float:
    dx, dy, dz = a[0] - b[0], a[1] - b[1], a[2] - b[2]
    return math.sqrt(dx * dx + dy * dy + dz * dz)


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


# ---------------------------------------------------------------------------------- velocities


def _mirror(j: npt.NDArray[np.intp], m: int) -> npt.NDArray[np.intp]:
    """Indices ``j`` reflected into ``[0, m)`` with the edge repeated, periodically (``padarray``'s
    'symmetric' for pads of any size)."""
    r = np.mod(j, 2 * m)
    out: npt.NDArray[np.intp] = np.where(r < m, r, 2 * m - 1 - r)
    return out


def _interior(n: int, big_l: int, h: int) -> range:
    """The frames of an ``n``-frame trajectory whose whole window lies inside it, so that the window
    sum telescopes to ``x(t+L-h+1) - x(t-h+1)``; the others are edge frames."""
    return range(h - 1, n - big_l + h - 1)


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
    """Smoothed velocity of ``x`` shape ``(k, N)`` (k components of point trajectories), shape ``(k, N)``
    (reference facts, section 0).

    Away from the ends the window sum of forward differences telescopes to ``x(t+L-h+1) - x(t-h+1)``;
    near the ends the mirrored differences are summed one after another. :class:`FeatureStream` does
    the same per frame."""
    n = x.shape[1]
    out = np.zeros_like(x)
    if n < 2:
        return out
    h = math.ceil(big_l / 2)
    inner = _interior(n, big_l, h)
    if len(inner):
        out[:, inner.start : inner.stop] = (x[:, big_l:] - x[:, : n - big_l]) * (frame_rate / big_l)
    t = np.arange(n)
    edge = t[(t < inner.start) | (t >= inner.stop)]
    if edge.size:
        m = _edge_indices(edge, n, big_l, h)
        d = x[:, 1:] - x[:, :-1]
        acc = d[:, m[:, 0]]
        for k in range(1, big_l):
            acc = acc + d[:, m[:, k]]
        out[:, edge] = acc * (frame_rate / big_l)
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


_COS_OP: dict[Op, Op] = {"<=": ">=", "<": ">", ">=": "<=", ">": "<", "within": "within"}
_PY_OP: dict[Op, str] = {"<=": "<=", "<": "<", ">=": ">=", ">": ">"}


def _cos_threshold(t: float | tuple[float, float]) -> float | tuple[float, float]:
    if isinstance(t, tuple):
        return (math.cos(math.radians(t[1])), math.cos(math.radians(t[0])))
    return math.cos(math.radians(t))


class _Emitter:
    """Writes straight-line Python for a set of signals, one assignment per operation, each
    operation written once (common subexpressions such as a plane normal shared by two features are
    computed once). The code reads joints as ``P[3j + c]`` and smoothed velocities as ``S[3k + c]``."""

    def __init__(self) -> None:
        self.lines: list[str] = []
        self._names: dict[tuple[Any, ...], str] = {}

    def var(self, key: tuple[Any, ...], expr: str) -> str:
        if key not in self._names:
            self._names[key] = f"v{len(self._names)}"
            self.lines.append(f"{self._names[key]} = {expr}")
        return self._names[key]

    def component(self, j: int, c: int) -> str:
        return self.var(("P", j, c), f"P[{3 * j + c}]")

    def joint(self, j: int) -> tuple[str, str, str]:
        x, y, z = (self.component(j, c) for c in range(3))
        return x, y, z

    def velocity(self, k: int) -> tuple[str, str, str]:
        x, y, z = (self.var(("S", k, c), f"S[{3 * k + c}]") for c in range(3))
        return x, y, z

    def sub(self, a: Sequence[str], b: Sequence[str]) -> tuple[str, str, str]:
        x, y, z = (self.var(("-", a[c], b[c]), f"{a[c]} - {b[c]}") for c in range(3))
        return x, y, z

    def dot(self, a: Sequence[str], b: Sequence[str]) -> str:
        return self.var(("dot", *a, *b), f"{a[0]} * {b[0]} + {a[1]} * {b[1]} + {a[2]} * {b[2]}")

    def cross(self, a: Sequence[str], b: Sequence[str]) -> tuple[str, str, str]:
        x, y, z = (
            self.var(("x", a[i], b[j], a[j], b[i]), f"{a[i]} * {b[j]} - {a[j]} * {b[i]}")
            for i, j in ((1, 2), (2, 0), (0, 1))
        )
        return x, y, z


class _LazyJoints:
    def __init__(self, emitter: _Emitter, index: dict[str, int]) -> None:
        self._emitter, self._index = emitter, index

    def __getitem__(self, name: str) -> tuple[str, str, str]:
        return self._emitter.joint(self._index[name])


def _compile_error(what: str) -> ValueError:
    return ValueError(f"the catalog uses {what}, which the feature compiler does not support")


class _Program:
    """The catalog bound to a joint order and a frame rate, compiled to Python.

    ``frame(P, S, T, sqrt, minimum, maximum) -> (f1, f2)`` evaluates every test on joint positions
    ``P`` and smoothed velocities ``S`` against the thresholds ``T`` (T1 then T2 of each test), on
    floats or on arrays alike; bit k of ``f1``/``f2`` is feature k's loose/strict track.
    ``points(P)`` gives the velocity trajectories' points (flat, ``3k + c``). ``bytecode`` is the
    same program for the compiled register machine of :mod:`daemon._features` (the streaming path);
    ``slots`` maps each threshold to its place in the machine's flat threshold array."""

    def __init__(self, joint_names: tuple[str, ...], frame_rate: float) -> None:
        if not (math.isfinite(frame_rate) and 0 < frame_rate <= MAX_NATIVE_RATE):
            raise ValueError(
                f"frame rate must be a positive number up to {MAX_NATIVE_RATE:g} Hz, got {frame_rate:g}"
            )
        index = {name: i for i, name in enumerate(joint_names)}
        missing = sorted(j for j in _catalog_joints() if j not in index)
        if missing:
            raise ValueError(f"joint positions lack the joints {', '.join(missing)}")
        self.joint_names = joint_names
        self.frame_rate = frame_rate
        self.index = index
        # Velocity trajectories sorted by window, so that each window's components are one slice of S.
        self.trajectories = sorted(
            {self._trajectory_of(v) for v in _velocity_signals()}, key=lambda tr: (tr.big_l, tr.q, tr.c or -1)
        )
        self.references: list[tuple[Reference, float | tuple[float, float]]] = []
        self._out = _Emitter()
        f1: list[str] = []
        f2: list[str] = []
        for feature in CATALOG:
            loose, strict = [], []
            for test in feature.tests:
                value, cosine = self._signal(test.signal)
                op, t1, t2 = test.op, test.t1, test.t2
                if cosine:
                    op, t1, t2 = _COS_OP[op], _cos_threshold(t1), _cos_threshold(t2)
                loose.append(self._test(value, op, test.reference, t1))
                strict.append(self._test(value, op, test.reference, t2))
            shift = f" << {len(f1)}" if f1 else ""
            f1.append(f"({' & '.join(loose)}){shift}")
            f2.append(f"({' & '.join(strict)}){shift}")
        unpack = ", ".join(f"t{k}" for k in range(len(self.references)))
        body = [f"{unpack}, = T", *self._out.lines, f"return {' | '.join(f1)}, {' | '.join(f2)}"]
        self.source = "def frame(P, S, T, sqrt, minimum, maximum):\n" + "".join(f"    {s}\n" for s in body)
        point_exprs = [
            f"P[{3 * tr.q + c}]" if tr.c is None else f"P[{3 * tr.q + c}] - P[{3 * tr.c + c}]"
            for tr in self.trajectories
            for c in range(3)
        ]
        self.source += f"def points(P):\n    return [{', '.join(point_exprs)}]\n"
        # The windows: (L, h, first, end) with S[first:end] the components smoothed over L frames.
        by_window: dict[int, list[int]] = {}
        for k, tr in enumerate(self.trajectories):
            by_window.setdefault(tr.big_l, []).append(k)
        self.windows = [
            (big_l, self.trajectories[ks[0]].h, 3 * ks[0], 3 * ks[-1] + 3) for big_l, ks in by_window.items()
        ]
        namespace: dict[str, Any] = {}
        exec(compile(self.source, f"<features at {frame_rate:g} Hz>", "exec"), namespace)
        self.frame: Callable[..., tuple[Num, Num]] = namespace["frame"]
        self.points: Callable[[Poses], list[float]] = namespace["points"]
        self.lead = max((tr.lead for tr in self.trajectories), default=0)
        self.slots = _threshold_slots(self.references)
        self.bytecode = _assemble(self)

    def _test(self, value: str, op: Op, reference: Reference, threshold: float | tuple[float, float]) -> str:
        k = len(self.references)
        self.references.append((reference, threshold))
        if op == "within":
            return f"(({value} >= t{k}[0]) & ({value} <= t{k}[1]))"
        return f"({value} {_PY_OP[op]} t{k})"

    def _trajectory_of(self, signal: PlaneVelocity | NormalPlaneVelocity | Speed) -> _Trajectory:
        fixture = None if isinstance(signal, Speed) else self.index[signal.c]
        return _Trajectory(self.index[signal.q], fixture, window_frames(signal.window_ms, self.frame_rate))

    def _velocity(self, signal: PlaneVelocity | NormalPlaneVelocity | Speed) -> tuple[str, str, str]:
        return self._out.velocity(self.trajectories.index(self._trajectory_of(signal)))

    def _signal(self, signal: Signal) -> tuple[str, bool]:
        """Emit the code of ``signal``; return its variable and whether the value is a cosine."""
        e, ix = self._out, self.index
        p = _LazyJoints(e, ix)

        def plane_normal(a: str, b: str, c: str) -> tuple[str, str, str]:
            return e.cross(e.sub(p[a], p[c]), e.sub(p[b], p[c]))

        def along(n: Sequence[str], w: Sequence[str]) -> str:
            return e.var(("/", signal), f"{e.dot(n, w)} / sqrt({e.dot(n, n)})")

        def cosine(u: Sequence[str], v: Sequence[str]) -> str:
            return e.var(("cos", signal), f"{e.dot(u, v)} / sqrt({e.dot(u, u)} * {e.dot(v, v)})")

        match signal:
            case Plane(a, b, c, q):
                return along(plane_normal(a, b, c), e.sub(p[q], p[c])), False
            case PlaneVelocity(a, b, c, _):
                return along(plane_normal(a, b, c), self._velocity(signal)), False
            case NormalPlane(a, b, c, q):
                return along(e.sub(p[b], p[a]), e.sub(p[q], p[c])), False
            case NormalPlaneVelocity(a, b, _, _):
                return along(e.sub(p[b], p[a]), self._velocity(signal)), False
            case Speed():
                s = self._velocity(signal)
                return e.var(("|", signal), f"sqrt({e.dot(s, s)})"), False
            case JointAngle(a, b, c):
                return cosine(e.sub(p[a], p[b]), e.sub(p[c], p[b])), True
            case SegmentAngle(p1, p2, p3, p4):
                return cosine(e.sub(p[p1], p[p2]), e.sub(p[p3], p[p4])), True
            case AngleToVertical(a, b):
                u = e.sub(p[b], p[a])
                return e.var(("cos", signal), f"{u[1]} / sqrt({e.dot(u, u)})"), True
            case HeightAboveLowest(q, exclude):
                ys = ", ".join(e.component(ix[n], 1) for n in TOOLBOX_JOINTS if n not in exclude)
                low = e.var(("min", exclude), f"minimum([{ys}])")
                y = e.component(ix[q], 1)
                return e.var(("-", y, low), f"{y} - {low}"), False
            case VerticalExtent():
                ys = ", ".join(e.component(ix[n], 1) for n in TOOLBOX_JOINTS)
                low, high = e.var(("min", ()), f"minimum([{ys}])"), e.var(("max", ()), f"maximum([{ys}])")
                return e.var(("-", high, low), f"{high} - {low}"), False
            case HorizontalExtent(joints):
                squares = []
                for i, a in enumerate(joints):
                    for b in joints[i + 1 :]:
                        (ax, _, az), (bx, _, bz) = p[a], p[b]
                        dx, dz = e.var(("-", ax, bx), f"{ax} - {bx}"), e.var(("-", az, bz), f"{az} - {bz}")
                        squares.append(e.var(("xz", dx, dz), f"{dx} * {dx} + {dz} * {dz}"))
                return e.var(("|xz", signal), f"sqrt(maximum([{', '.join(squares)}]))"), False
            case Difference(first, second):
                (f, cf), (g, cg) = self._signal(first), self._signal(second)
                if cf or cg:
                    raise _compile_error("a difference of angles")
                return e.var(("-", f, g), f"{f} - {g}"), False
            case Absolute(inner):
                f, is_cosine = self._signal(inner)
                if is_cosine:
                    raise _compile_error("the absolute value of an angle")
                return e.var(("abs", f), f"abs({f})"), False
        raise TypeError(f"unknown signal {signal!r}")

    def thresholds(self, lengths: BodyLengths) -> list[Num]:
        """Every comparison's threshold in absolute units, in the order of ``T``."""
        out: list[Num] = []
        for reference, threshold in self.references:
            if isinstance(threshold, tuple):
                out.append(threshold)
            else:
                out.append(threshold * lengths.get(reference))
        return out

    def flat_thresholds(self, lengths: BodyLengths) -> FloatArray:
        """:meth:`thresholds` flat in the order of :attr:`slots` (a pair takes two)."""
        return np.array(
            [x for t in self.thresholds(lengths) for x in (t if isinstance(t, tuple) else (t,))],
            dtype=np.float64,
        )


def _threshold_slots(references: Sequence[tuple[Reference, float | tuple[float, float]]]) -> list[int]:
    """The first flat threshold slot of each threshold (a pair takes two)."""
    out, at = [], 0
    for _, threshold in references:
        out.append(at)
        at += 2 if isinstance(threshold, tuple) else 1
    return out


_BINARY = {ast.Add: 0, ast.Sub: 1, ast.Mult: 2, ast.Div: 3}
_UNARY = {"sqrt": 4, "abs": 5}
_REDUCE = {"minimum": 6, "maximum": 7}
_CONST = 8
_COMPARE = {ast.Lt: 0, ast.LtE: 1, ast.Gt: 2, ast.GtE: 3}


class _Assembler:
    """The generated ``frame`` function as register-machine code (:class:`daemon._features.Bytecode`):
    every arithmetic node of its syntax tree one instruction, in Python's evaluation order, and every
    threshold comparison one test of a feature bit. The first registers hold the pose components
    ``P`` and the smoothed velocities ``S``; each instruction writes a register of its own."""

    def __init__(self, slots: Sequence[int], n_rows: int, n_points: int) -> None:
        self.slots = slots
        self.n_rows, self.base = n_rows, n_rows + n_points  # registers: P, then S, then results
        self.ops: list[tuple[int, int, int, int]] = []
        self.args: list[int] = []
        self.consts: list[float] = []
        self.names: dict[str, int] = {}
        self.thresholds: dict[str, int] = {}
        self.tests: list[tuple[int, int, int, int, int]] = []

    def emit(self, op: int, a: int, b: int) -> int:
        self.ops.append((op, self.base + len(self.ops), a, b))
        return self.base + len(self.ops) - 1

    def expr(self, node: ast.expr) -> int:
        match node:
            case ast.Name(id=name) if name in self.names:
                return self.names[name]
            case ast.Subscript(value=ast.Name(id="P"), slice=ast.Constant(value=int(i))):
                return i
            case ast.Subscript(value=ast.Name(id="S"), slice=ast.Constant(value=int(i))):
                return self.n_rows + i
            case ast.BinOp(left, op, right) if type(op) in _BINARY:
                a = self.expr(left)
                return self.emit(_BINARY[type(op)], a, self.expr(right))
            case ast.Call(func=ast.Name(id=f), args=[arg]) if f in _UNARY:
                return self.emit(_UNARY[f], self.expr(arg), 0)
            case ast.Call(func=ast.Name(id=f), args=[ast.List(elts=items)]) if f in _REDUCE and items:
                registers = [self.expr(e) for e in items]
                self.args += registers
                return self.emit(_REDUCE[f], len(self.args) - len(registers), len(registers))
            case ast.Constant(value=float(v) | int(v)) if not isinstance(v, bool):
                self.consts.append(float(v))
                return self.emit(_CONST, len(self.consts) - 1, 0)
        raise _compile_error(f"an expression the register machine lacks: {ast.unparse(node)}")

    def threshold(self, node: ast.expr) -> int:
        match node:
            case ast.Name(id=name) if name in self.thresholds:
                return self.slots[self.thresholds[name]]
            case ast.Subscript(value=ast.Name(id=name), slice=ast.Constant(value=int(j))) if j in (0, 1):
                return self.slots[self.thresholds[name]] + j
        raise _compile_error(f"a threshold the register machine lacks: {ast.unparse(node)}")

    def track(self, node: ast.expr, track: int) -> None:
        """The tests of ``(tests) | (tests) << 1 | ...`` for ``track`` (0 loose, 1 strict)."""
        match node:
            case ast.BinOp(left, ast.BitOr(), right):
                self.track(left, track)
                self.track(right, track)
            case ast.BinOp(conjunction, ast.LShift(), ast.Constant(value=int(bit))):
                self.conjunction(conjunction, track, bit)
            case _:
                self.conjunction(node, track, 0)

    def conjunction(self, node: ast.expr, track: int, bit: int) -> None:
        match node:
            case ast.BinOp(left, ast.BitAnd(), right):
                self.conjunction(left, track, bit)
                self.conjunction(right, track, bit)
            case ast.Compare(left, [op], [reference]) if type(op) in _COMPARE:
                self.tests.append(
                    (track, bit, self.expr(left), _COMPARE[type(op)], self.threshold(reference))
                )
            case _:
                raise _compile_error(f"a test the register machine lacks: {ast.unparse(node)}")


def _assemble(program: _Program) -> Bytecode:
    """:class:`_Program`'s ``frame`` as :class:`daemon._features.Bytecode`, with its velocity points
    and window sums."""
    (function,) = [
        f for f in ast.parse(program.source).body if isinstance(f, ast.FunctionDef) and f.name == "frame"
    ]
    unpack, *assignments, result = function.body
    assert isinstance(unpack, ast.Assign) and isinstance(unpack.targets[0], ast.Tuple)
    points = [
        (3 * tr.q + c, -1 if tr.c is None else 3 * tr.c + c) for tr in program.trajectories for c in range(3)
    ]
    n_rows = 3 * len(program.joint_names)
    asm = _Assembler(program.slots, n_rows, len(points))
    for k, name in enumerate(unpack.targets[0].elts):
        assert isinstance(name, ast.Name)
        asm.thresholds[name.id] = k
    for a in assignments:
        assert isinstance(a, ast.Assign) and isinstance(a.targets[0], ast.Name)
        asm.names[a.targets[0].id] = asm.expr(a.value)
    assert isinstance(result, ast.Return) and isinstance(result.value, ast.Tuple)
    for track, node in enumerate(result.value.elts):
        asm.track(node, track)
    windows = [(big_l - h + 1, 1 - h, first, end) for big_l, h, first, end in program.windows]
    return Bytecode(
        asm.ops,
        asm.args,
        asm.consts,
        asm.tests,
        points,
        windows,
        [program.frame_rate / big_l for big_l, _, _, _ in program.windows],
        asm.base + len(asm.ops),
        n_rows,
        sum(2 if isinstance(t, tuple) else 1 for _, t in program.references),
    )


def _subsignals(signal: Any) -> Iterator[Any]:
    yield signal
    for value in vars(signal).values():
        if not isinstance(value, str | int | float | tuple):
            yield from _subsignals(value)


def _velocity_signals() -> set[PlaneVelocity | NormalPlaneVelocity | Speed]:
    return {
        s
        for f in CATALOG
        for t in f.tests
        for s in _subsignals(t.signal)
        if isinstance(s, PlaneVelocity | NormalPlaneVelocity | Speed)
    }


def _signal_joints(signal: Any) -> set[str]:
    names: set[str] = set()
    for s in _subsignals(signal):
        for value in vars(s).values():
            if isinstance(value, str):
                names.add(value)
            elif isinstance(value, tuple):
                names.update(v for v in value if isinstance(v, str))
    return names


def _catalog_joints() -> set[str]:
    return set(TOOLBOX_JOINTS).union(*(_signal_joints(t.signal) for f in CATALOG for t in f.tests))


_PROGRAMS: dict[tuple[tuple[str, ...], float], _Program] = {}


def _program(joint_names: Sequence[str], frame_rate: float) -> _Program:
    key = (tuple(joint_names), float(frame_rate))
    if key not in _PROGRAMS:
        _PROGRAMS[key] = _Program(*key)
    return _PROGRAMS[key]


def latency_frames(frame_rate: float) -> int:
    """How many frames after frame ``t`` arrives :class:`FeatureStream` can emit its vector: the
    longest velocity window's look-ahead ``L - ceil(L/2) + 1`` (16 at 120 Hz, 5 at 30 Hz)."""
    return _program(JOINT_NAMES, frame_rate).lead


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
        return _distance(pose[idx[a]], pose[idx[b]])

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


_BITS = np.left_shift(1, np.arange(N_FEATURES, dtype=np.int64))


def _unpack(codes: Num) -> BoolArray:
    """Bit ``k`` of ``codes`` (an int, or int64 array shape ``(N,)``) as feature ``k``: shape
    ``(39,)`` or ``(N, 39)``."""
    if isinstance(codes, int):
        bits: BoolArray = (_BITS & codes) != 0
        return bits
    out: BoolArray = (np.asarray(codes, dtype=np.int64)[:, None] & _BITS) != 0
    return out


def feature_tracks(
    positions: FloatArray, joint_names: Sequence[str], frame_rate: float, lengths: BodyLengths | None = None
) -> tuple[BoolArray, BoolArray]:
    """The loose and strict tracks ``(f1, f2)`` of ``positions`` shape ``(N, J, 3)``, each ``(N, 39)``."""
    program = _program(joint_names, frame_rate)
    p = _check_positions(positions, len(program.joint_names))
    n = p.shape[0]
    if n == 0:
        return np.ones((0, N_FEATURES), dtype=bool), np.ones((0, N_FEATURES), dtype=bool)
    poses = np.ascontiguousarray(p.reshape(n, -1).T)  # (3J, N): each component a contiguous row
    thresholds = program.thresholds(lengths or body_lengths(p[0], program.joint_names))
    # Degenerate or huge poses give nan/inf signals (features off), as Python floats do in the stream.
    with np.errstate(all="ignore"):
        points = np.array(program.points(list(poses)))  # (3K, N)
        velocities = np.empty_like(points)
        for big_l, _, first, end in program.windows:
            velocities[first:end] = _smooth(points[first:end], big_l, frame_rate)
        f1, f2 = program.frame(list(poses), velocities, thresholds, *_ARRAY_OPS)
    return _unpack(f1), _unpack(f2)


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
    for a new stream. Body lengths are measured on the first pose. Memory is bounded: a ring of the
    last ``latency + L/2 + 1`` poses. The output equals :func:`features` on the same frames bit for
    bit: both run the same program and the same window sums, on arrays there and here in compiled
    code (:class:`daemon._features.FeatureCore`: the program as register-machine code on doubles
    with numpy's arithmetic)."""

    def __init__(self, joint_names: Sequence[str], frame_rate: float = 120.0) -> None:
        self._program = _program(joint_names, frame_rate)
        self.latency = self._program.lead
        self._keep = self.latency + max((tr.h for tr in self._program.trajectories), default=1) + 1
        self._core = FeatureCore(self._program.bytecode, self._keep, self.latency)

    @property
    def frames(self) -> int:
        """Poses pushed since the stream began."""
        return self._core.n

    @property
    def keep(self) -> int:
        """Poses held: the last ``keep`` (``latency + L/2 + 1``)."""
        return self._keep

    @property
    def core(self) -> FeatureCore:
        """The compiled state (the live recogniser steps it directly)."""
        return self._core

    def thresholds_of(self, rows: FloatArray) -> FloatArray:
        """The flat thresholds of a stream whose first pose is ``rows`` (flat, ``3j + c``)."""
        return self._program.flat_thresholds(body_lengths(rows.reshape(-1, 3), self._program.joint_names))

    def push(self, pose: FloatArray) -> list[BoolArray]:
        """Add the next pose; return the vectors that became final (at most one)."""
        program = self._program
        p = np.ascontiguousarray(pose, dtype=np.float64)
        if p.shape != (len(program.joint_names), 3):
            raise ValueError(f"pose must have shape ({len(program.joint_names)}, 3), got {p.shape}")
        rows = p.reshape(-1)
        if not np.isfinite(rows).all():
            raise ValueError(f"pose {self._core.n} is not finite")
        return [] if (code := self.push_rows(rows)) is None else [_unpack(code)]

    def push_rows(self, rows: FloatArray) -> int | None:
        """:meth:`push` of a pose already checked: finite, contiguous float64, flat (``3j + c``,
        shape ``(3J,)``); the vector that became final as a code (bit k = feature k), or None."""
        core = self._core
        if core.n == 0:
            core.set_thresholds(self.thresholds_of(rows))
        code = core.push(rows)
        return None if code < 0 else code

    def flush(self) -> list[BoolArray]:
        """End the stream: the vectors of its last frames, then a fresh state."""
        return [_unpack(code) for code in self.flush_codes()]

    def flush_codes(self) -> list[int]:
        """:meth:`flush` giving codes (bit k = feature k)."""
        return self._core.flush()


# ---------------------------------------------------------------------------------- frame rates


def decimation_factor(native_hz: float, target_hz: float) -> int:
    """How many native frames make one frame at ``target_hz`` (4 for 120 -> 30 Hz); the target must
    divide the native rate."""
    if not (math.isfinite(target_hz) and target_hz > 0):
        raise ValueError(f"target frame rate must be a positive number, got {target_hz}")
    ratio = native_hz / target_hz
    factor = round(ratio) if math.isfinite(ratio) else 0  # a subnormal target overflows the ratio
    if factor < 1 or not math.isclose(native_hz / factor, target_hz, rel_tol=1e-9):
        raise ValueError(f"{target_hz:g} Hz is not the native {native_hz:g} Hz divided by a whole number")
    return factor


def decimate(matrix: BoolArray, factor: int) -> BoolArray:
    """Every ``factor``-th row of ``matrix``, starting with the first (the toolbox's ``1:4:end``, no
    filtering; reference facts, section 0). Batch twin of :class:`Decimator`."""
    out: BoolArray = matrix[::factor]
    return out


class Decimator:
    """``push(vector)`` passes on every ``factor``-th vector, starting with the first (a list of it, or
    an empty list); :meth:`flush` has nothing pending and starts a new stream. The streaming twin of
    :func:`decimate`. State: a frame counter."""

    def __init__(self, factor: int) -> None:
        if factor < 1:
            raise ValueError(f"decimation factor must be at least 1, got {factor}")
        self.factor = factor
        self._n = 0

    def push(self, vector: BoolArray) -> list[BoolArray]:
        keep = self._n % self.factor == 0
        self._n += 1
        return [vector] if keep else []

    def flush(self) -> list[BoolArray]:
        self._n = 0
        return []
