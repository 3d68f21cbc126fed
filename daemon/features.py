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
from dataclasses import dataclass
from typing import Literal

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


# -------------------------------------------------------------------------------------- primitives


def _unit(v: FloatArray) -> FloatArray:
    norm = np.linalg.norm(v, axis=-1, keepdims=True)
    with np.errstate(invalid="ignore", divide="ignore"):
        out: FloatArray = v / norm
    return out


def _dot(a: FloatArray, b: FloatArray) -> FloatArray:
    out: FloatArray = np.einsum("...i,...i->...", a, b)
    return out


def _angle(u: FloatArray, v: FloatArray) -> FloatArray:
    cos = _dot(u, v) / (np.linalg.norm(u, axis=-1) * np.linalg.norm(v, axis=-1))
    out: FloatArray = np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))
    return out


def window_frames(window_ms: float, frame_rate: float) -> int:
    """Velocity window length L in frames: ``ceil(W / 1000 * fs)``, at least 1 (reference facts, 0)."""
    return max(1, math.ceil(window_ms / 1000.0 * frame_rate))


def _mirror(j: npt.NDArray[np.intp], m: int) -> npt.NDArray[np.intp]:
    """Indices ``j`` reflected into ``[0, m)`` with the edge repeated, periodically (``padarray``'s
    'symmetric' for pads of any size)."""
    r = np.mod(j, 2 * m)
    out: npt.NDArray[np.intp] = np.where(r < m, r, 2 * m - 1 - r)
    return out


def smoothed_velocity(x: FloatArray, window_ms: float, frame_rate: float) -> FloatArray:
    """Velocity of the trajectory ``x`` shape ``(N, 3)`` in units per second, box-averaged over a
    centred window: forward differences ``v(t) = x(t+1) - x(t)`` (``v(N) = v(N-1)``), then the mean of
    ``v(t+1-h .. t+L-h)`` with ``h = ceil(L/2)``, indices mirrored at both ends (Matlab's
    ``padarray(..., 'symmetric')``). Returns shape ``(N, 3)``."""
    n = x.shape[0]
    big_l = window_frames(window_ms, frame_rate)
    if n == 1:
        return np.zeros_like(x)
    v = np.empty_like(x)
    v[:-1] = x[1:] - x[:-1]
    v[-1] = v[-2]
    if big_l == 1:
        return v * frame_rate
    h = math.ceil(big_l / 2)
    before, after = h - 1, big_l - h
    if n < big_l:
        v = v[_mirror(np.arange(big_l), n)]
    padded = v[_mirror(np.arange(-before, v.shape[0] + after), v.shape[0])]
    csum = np.concatenate([np.zeros((1, 3)), np.cumsum(padded, axis=0)])
    out: FloatArray = (csum[big_l : big_l + n] - csum[:n]) / big_l * frame_rate
    return out


class _Context:
    def __init__(self, positions: FloatArray, joint_names: tuple[str, ...], frame_rate: float) -> None:
        self.p = positions
        self.index = {n: i for i, n in enumerate(joint_names)}
        self.frame_rate = frame_rate
        self._map = np.array([self.index[n] for n in TOOLBOX_JOINTS], dtype=np.intp)

    def __call__(self, name: str) -> FloatArray:
        out: FloatArray = self.p[:, self.index[name]]
        return out

    def name_map_y(self, exclude: tuple[str, ...] = ()) -> FloatArray:
        keep = [i for n, i in zip(TOOLBOX_JOINTS, self._map, strict=True) if n not in exclude]
        out: FloatArray = self.p[:, keep, 1]
        return out


def evaluate_signal(signal: Signal, ctx: _Context) -> FloatArray:
    """The signal's value per frame, shape ``(N,)``."""
    p = ctx
    match signal:
        case Plane(a, b, c, q):
            n = _unit(np.cross(p(a) - p(c), p(b) - p(c)))
            return _dot(n, p(q) - p(c))
        case NormalPlane(a, b, c, q):
            return _dot(_unit(p(b) - p(a)), p(q) - p(c))
        case PlaneVelocity(a, b, c, q, w):
            n = _unit(np.cross(p(a) - p(c), p(b) - p(c)))
            return _dot(n, smoothed_velocity(p(q) - p(c), w, p.frame_rate))
        case NormalPlaneVelocity(a, b, c, q, w):
            return _dot(_unit(p(b) - p(a)), smoothed_velocity(p(q) - p(c), w, p.frame_rate))
        case Speed(q, w):
            out: FloatArray = np.linalg.norm(smoothed_velocity(p(q), w, p.frame_rate), axis=-1)
            return out
        case JointAngle(a, b, c):
            return _angle(p(a) - p(b), p(c) - p(b))
        case SegmentAngle(p1, p2, p3, p4):
            return _angle(p(p1) - p(p2), p(p3) - p(p4))
        case AngleToVertical(a, b):
            return _angle(p(b) - p(a), np.array([0.0, 1.0, 0.0]))
        case HeightAboveLowest(q, exclude):
            out = p(q)[:, 1] - p.name_map_y(exclude).min(axis=1)
            return out
        case VerticalExtent():
            y = p.name_map_y()
            out = y.max(axis=1) - y.min(axis=1)
            return out
        case HorizontalExtent(joints):
            xz = np.stack([p(j)[:, [0, 2]] for j in joints], axis=1)
            d = np.linalg.norm(xz[:, :, None] - xz[:, None, :], axis=-1)
            out = d.reshape(d.shape[0], -1).max(axis=1)
            return out
        case Difference(first, second):
            out = evaluate_signal(first, ctx) - evaluate_signal(second, ctx)
            return out
        case Absolute(inner):
            out = np.abs(evaluate_signal(inner, ctx))
            return out
    raise TypeError(f"unknown signal {signal!r}")


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


def body_lengths(frame: FloatArray, joint_names: tuple[str, ...]) -> BodyLengths:
    """Body lengths of one pose ``frame`` shape ``(J, 3)``."""
    idx = {n: i for i, n in enumerate(joint_names)}

    def d(a: str, b: str) -> float:
        return float(np.linalg.norm(frame[idx[a]] - frame[idx[b]]))

    chain = [("rankle", "rknee"), ("rknee", "rhip"), ("root", "belly"), ("belly", "chest"), ("chest", "neck")]
    chain += [("neck", "head"), ("head", "headtop")]
    return BodyLengths(
        h_R=d("relbow", "rshoulder"),
        h_L=d("lshoulder", "lelbow"),
        shoulder_width=d("rshoulder", "lshoulder"),
        hip_width=d("rhip", "lhip"),
        chest=d("chest", "neck"),
        body=sum(d(a, b) for a, b in chain),
    )


# ---------------------------------------------------------------------------------- thresholds


def _compare(values: FloatArray, op: Op, threshold: float | tuple[float, float], scale: float) -> BoolArray:
    if op == "within":
        assert isinstance(threshold, tuple)
        lo, hi = threshold
        out: BoolArray = (values >= lo) & (values <= hi)
        return out
    assert not isinstance(threshold, tuple)
    t = threshold * scale
    if op == ">=":
        return values >= t
    if op == ">":
        return values > t
    if op == "<=":
        return values <= t
    return values < t


def hysteresis(f1: BoolArray, f2: BoolArray) -> BoolArray:
    """``out(t) = f2(t) or (out(t-1) and f1(t))`` along axis 0, ``out(-1) = 0`` (nested tracks, f2 => f1).

    Vectorised: a frame is on iff the last frame at or before it where f2 holds is reachable through
    an unbroken run of f1."""
    n = f1.shape[0]
    idx = np.arange(n)[:, None] * np.ones(f1.shape[1:], dtype=np.intp)[None]
    last_f2 = np.maximum.accumulate(np.where(f2, idx, -1), axis=0)
    last_break = np.maximum.accumulate(np.where(~f1 & ~f2, idx, -1), axis=0)
    on: BoolArray = (last_f2 >= 0) & (last_f2 > last_break)
    return on


def feature_tracks(
    positions: FloatArray, joint_names: tuple[str, ...], frame_rate: float, lengths: BodyLengths | None = None
) -> tuple[BoolArray, BoolArray]:
    """The loose and strict tracks ``(f1, f2)``, each shape ``(N, 39)``."""
    ctx = _Context(positions, joint_names, frame_rate)
    lengths = lengths or body_lengths(positions[0], joint_names)
    n = positions.shape[0]
    f1 = np.ones((n, len(CATALOG)), dtype=bool)
    f2 = np.ones((n, len(CATALOG)), dtype=bool)
    cache: dict[Signal, FloatArray] = {}
    for k, feature in enumerate(CATALOG):
        for test in feature.tests:
            if test.signal not in cache:
                cache[test.signal] = evaluate_signal(test.signal, ctx)
            values = cache[test.signal]
            scale = lengths.get(test.reference)
            f1[:, k] &= _compare(values, test.op, test.t1, scale)
            f2[:, k] &= _compare(values, test.op, test.t2, scale)
    return f1, f2


def features(positions: FloatArray, joint_names: tuple[str, ...], frame_rate: float = 120.0) -> BoolArray:
    """The 39 features of a whole motion: ``positions`` shape ``(N, J, 3)`` (joints named by
    ``joint_names``) gives a boolean matrix shape ``(N, 39)`` in :data:`FEATURE_NAMES` order."""
    f1, f2 = feature_tracks(positions, joint_names, frame_rate)
    return hysteresis(f1, f2)
