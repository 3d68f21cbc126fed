"""The compiler: the catalog (:mod:`daemon.features.catalog`) bound to a joint order and a frame
rate, written once as one straight-line Python function and ``exec``-ed (:class:`Program`), and
read back by the assembler (:mod:`daemon.features.assembler`) as code for the stream's compiled
register machine.

The function reads joint components ``P[3j + c]`` as Python floats (one frame) or as float64 arrays
(all frames: the batch). Only +, -, *, / and sqrt occur, each correctly rounded, in one fixed order,
so every path gives the same bits. Angles are compared through their cosines (arccos is
decreasing), which keeps transcendental functions, whose last bit can depend on the vector code
path, out of the features.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

from daemon.errors import InputError
from daemon.features.assembler import assemble, unsupported
from daemon.features.catalog import CATALOG, catalog_joints, velocity_signals
from daemon.features.language import (
    Absolute,
    AngleToVertical,
    BodyLengths,
    Difference,
    HeightAboveLowest,
    HorizontalExtent,
    JointAngle,
    NormalPlane,
    NormalPlaneVelocity,
    Op,
    Plane,
    PlaneVelocity,
    Reference,
    SegmentAngle,
    Signal,
    Speed,
    VerticalExtent,
)
from daemon.features.velocity import Trajectory, window_frames
from daemon.types import MAX_NATIVE_RATE, N_FEATURES, BoolArray, FloatArray
from replay.joints import TOOLBOX_JOINTS

Num = Any
"""A float (one frame), or a float64 array shape ``(N,)`` (all frames): the compiled function runs
on either."""
Poses = Sequence[Num]
"""Joint positions, flat: ``P[3j + c]`` is component ``c`` of joint ``j`` (a float, or an array over
frames)."""


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


class Program:
    """The catalog bound to a joint order and a frame rate, compiled to Python.

    ``frame(P, S, T, sqrt, minimum, maximum) -> (f1, f2)`` evaluates every test on joint positions
    ``P`` and smoothed velocities ``S`` against the thresholds ``T`` (T1 then T2 of each test), on
    floats or on arrays alike; bit k of ``f1``/``f2`` is feature k's loose/strict track.
    ``points(P)`` gives the velocity trajectories' points (flat, ``3k + c``). ``bytecode`` is the
    same program for the compiled register machine of :mod:`daemon._features` (the streaming path);
    ``slots`` maps each threshold to its place in the machine's flat threshold array."""

    def __init__(self, joint_names: tuple[str, ...], frame_rate: float) -> None:
        if not (math.isfinite(frame_rate) and 0 < frame_rate <= MAX_NATIVE_RATE):
            raise InputError(
                f"frame rate must be a positive number up to {MAX_NATIVE_RATE:g} Hz, got {frame_rate:g}"
            )
        index = {name: i for i, name in enumerate(joint_names)}
        missing = sorted(j for j in catalog_joints() if j not in index)
        if missing:
            raise InputError(f"joint positions lack the joints {', '.join(missing)}")
        self.joint_names = joint_names
        self.frame_rate = frame_rate
        self.index = index
        # Velocity trajectories sorted by window, so that each window's components are one slice of S.
        self.trajectories = sorted(
            {self._trajectory_of(v) for v in velocity_signals()}, key=lambda tr: (tr.big_l, tr.q, tr.c or -1)
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
        points = [
            (3 * tr.q + c, -1 if tr.c is None else 3 * tr.c + c) for tr in self.trajectories for c in range(3)
        ]
        self.bytecode = assemble(
            self.source,
            self.slots,
            sum(2 if isinstance(t, tuple) else 1 for _, t in self.references),
            3 * len(joint_names),
            points,
            self.windows,
            frame_rate,
        )

    def _test(self, value: str, op: Op, reference: Reference, threshold: float | tuple[float, float]) -> str:
        k = len(self.references)
        self.references.append((reference, threshold))
        if op == "within":
            return f"(({value} >= t{k}[0]) & ({value} <= t{k}[1]))"
        return f"({value} {_PY_OP[op]} t{k})"

    def _trajectory_of(self, signal: PlaneVelocity | NormalPlaneVelocity | Speed) -> Trajectory:
        fixture = None if isinstance(signal, Speed) else self.index[signal.c]
        return Trajectory(self.index[signal.q], fixture, window_frames(signal.window_ms, self.frame_rate))

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
                    raise unsupported("a difference of angles")
                return e.var(("-", f, g), f"{f} - {g}"), False
            case Absolute(inner):
                f, is_cosine = self._signal(inner)
                if is_cosine:
                    raise unsupported("the absolute value of an angle")
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


_PROGRAMS: dict[tuple[tuple[str, ...], float], Program] = {}


def compiled(joint_names: Sequence[str], frame_rate: float) -> Program:
    """The :class:`Program` for ``joint_names`` at ``frame_rate``, compiled once per process."""
    key = (tuple(joint_names), float(frame_rate))
    if key not in _PROGRAMS:
        _PROGRAMS[key] = Program(*key)
    return _PROGRAMS[key]


_BITS = np.left_shift(1, np.arange(N_FEATURES, dtype=np.int64))


def unpack(codes: Num) -> BoolArray:
    """Bit ``k`` of ``codes`` (an int, or int64 array shape ``(N,)``) as feature ``k``: shape
    ``(39,)`` or ``(N, 39)``."""
    if isinstance(codes, int):
        bits: BoolArray = (_BITS & codes) != 0
        return bits
    out: BoolArray = (np.asarray(codes, dtype=np.int64)[:, None] & _BITS) != 0
    return out
