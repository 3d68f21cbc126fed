"""Behaviour segmentation (Barbič, Safonova, Pan, Faloutsos, Hodgins, Pollard: *Segmenting Motion
Capture Data into Distinct Behaviors*, GI 2004): cut a long take where one behaviour (walk, jump,
punch, ...) ends and the next begins, with no training.

**Representation** (§3). Each frame is the rotation of every joint relative to its parent as a unit
quaternion ``(w, x, y, z)``, treated as a vector of length 4; root position and root orientation are
left out. The joints are, as many as the paper's hierarchy had (14, ``R^56``), the spine, head, arms,
legs and feet of the CMU/HDM05 skeleton (:data:`PAPER_BONES`, in ``:bonedata`` order), so a frame is
a vector of ``D = 56``; :class:`JointRotations` takes any other set of bones with a rotation dof (all
28 of CMU's: ``D = 112``). A bone's quaternion is ``C_k M_k C_k^T`` (its dof rotations about its
axes, :meth:`replay.kinematics.KinematicModel.local_rotations`); writing it in the bone's own axes
instead (``M_k``) changes each 4-vector by a fixed orthogonal map, which leaves every quantity below
unchanged. ``q`` and ``-q`` are the same rotation, so the signs are made consistent over time: the
first frame's quaternion has its first non-zero component positive (``w > 0`` for any rotation short
of 180°), and every later one is negated when its dot product with the previous frame's *raw*
quaternion is negative, on top of the previous frame's sign: ``f_t = f_(t-1) * sign(q_t . q_(t-1))``
with ``sign(0) = +1``. Then consecutive output quaternions always have a non-negative dot product
(``f_t f_(t-1) q_t . q_(t-1) = |q_t . q_(t-1)|``), and the batch is a cumulative product of ±1, so the
stream (:class:`RotationStream`, which keeps the previous frame's raw quaternions and signs) gives
the batch's vectors bit for bit.

**Frame counts in seconds.** Every window of the paper is given in seconds (the paper's frames at its
120 Hz) and scaled to the stream's ``rate``: ``round(seconds * rate)`` frames.

**Incremental statistics.** A segment's frames are folded in as a count ``n``, the first frame ``o``,
``s1 = sum (x - o)`` and ``s2 = sum (x - o)(x - o)^T``, in blocks (``s2 += Y^T Y``); the centred
scatter is ``s2 - s1 s1^T / n`` (the paper's ``D^T D``, whose eigenvalues are the ``σ_j²`` of Eq. 4).
Measuring from the first frame keeps the subtraction well conditioned and makes a stream that stands
still give a scatter of exactly zero. Eigenvalues come from ``eigvalsh``/``eigh`` of that ``D x D``
matrix when a method needs them; no SVD of the frames is ever taken.

**PCA** (§3.1, online): :class:`PcaSegmenter` and its batch twin :func:`pca_segment`.
**PPCA** (§3.2): the forward pass is online, a cut known ``Δ + T - 1`` frames after its frame
(:class:`PpcaSegmenter`, batch twin :func:`ppca_forward`); :func:`ppca_segment` alternates forward
and backward passes until a pass finds no new cut. **GMM** (§3.3, batch only): :func:`gmm_segment`.

Every method returns :class:`Boundary` values: ``frame`` is the 0-based index (into the frames given
or pushed) of the *first frame of the new behaviour*. The streams follow :mod:`daemon.stages`
(``push(frame) -> list[Boundary]``, ``flush() -> list[Boundary]`` then a fresh stream, bounded state)
and return exactly what their batch twins return for the same frames. Input that is not finite is a
``ValueError`` naming the frame. Pure: numpy in, frozen dataclasses out; no I/O.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal, TypeVar

import numpy as np
import numpy.typing as npt

from daemon.types import Band, FloatArray, IntArray
from replay.asf import ROTATION_DOFS, Skeleton
from replay.kinematics import KinematicModel

Method = Literal["pca", "ppca", "gmm"]
METHODS: tuple[Method, ...] = ("pca", "ppca", "gmm")


@dataclass(frozen=True)
class Boundary:
    """A cut between two behaviours. ``frame``: 0-based index of the first frame of the new
    behaviour (the previous one ends at ``frame - 1``); ``method``; ``score``: the method's signal at
    the cut (PCA: how far the error derivative ``d_i`` lies above the mean of the earlier ones, in
    standard deviations; PPCA: how far ``H`` rose from its valley to the peak; GMM: the mean log
    likelihood ratio, in nats per frame, of the new segment's frames under their cluster against the
    previous segment's); ``emitted``: the index of the last frame that had to be seen to know the cut
    (what an online method had been pushed when it returned it; ``N - 1`` for a batch-only cut)."""

    frame: int
    method: Method
    score: float
    emitted: int


def _count(seconds: float, rate: float, name: str, minimum: int = 1) -> int:
    if not math.isfinite(seconds):
        raise ValueError(f"{name} must be a finite number of seconds, got {seconds}")
    frames = round(seconds * rate)
    if frames < minimum:
        raise ValueError(f"{name} = {seconds:g} s is {frames} frames at {rate:g} Hz; it must be >= {minimum}")
    return frames


def _check_rate(rate: float) -> float:
    if not (math.isfinite(rate) and rate > 0):
        raise ValueError(f"rate must be a positive number of frames per second, got {rate}")
    return float(rate)


def _check_fraction(value: float, name: str) -> None:
    if not 0.0 < value < 1.0:
        raise ValueError(f"{name} must lie strictly between 0 and 1, got {value}")


# -------------------------------------------------------------------------------- representation


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
                raise ValueError(f"{skeleton.source}: no rotating bone {', '.join(missing)}")
            rotating = [k for k in rotating if names[k] in bones]
        self.nodes: tuple[int, ...] = tuple(rotating)
        if not self.nodes:
            raise ValueError(f"{skeleton.source}: the skeleton has no bone with a rotation dof")
        self.bones: tuple[str, ...] = tuple(skeleton.node_names[k] for k in self.nodes)
        self.dims = 4 * len(self.nodes)
        self.width = len(skeleton.channel_names)
        self.index = np.array(self.nodes, dtype=np.intp)

    def raw(self, channels: npt.ArrayLike) -> FloatArray:
        """The bones' quaternions as forward kinematics gives them (signs not made consistent):
        ``channels`` shape ``(N, C)`` (radians, :attr:`Skeleton.channel_names` layout) gives shape
        ``(N, J, 4)``. ``ValueError`` on a wrong shape or a value that is not finite."""
        c = np.asarray(channels, dtype=np.float64)
        if c.ndim != 2 or c.shape[1] != self.width:
            raise ValueError(f"channels must have shape (N, {self.width}), got {c.shape}")
        _check_finite(c, "channels")
        out: FloatArray = self.model.local_rotations(c)[:, self.index]
        return out

    def __call__(self, channels: npt.ArrayLike) -> FloatArray:
        """The frame vectors of a whole recording: ``channels`` shape ``(N, C)`` gives ``(N, D)``."""
        q = self.raw(channels)
        return consistent_signs(q).reshape(q.shape[0], self.dims)

    def stream(self) -> RotationStream:
        """A new per-frame stream of this representation."""
        return RotationStream(self)


class RotationStream:
    """:class:`JointRotations` one frame at a time, equal bit for bit to the batch: keeps the
    previous frame's raw quaternions and signs (shape ``(J, 4)`` and ``(J,)``). A stage
    (:mod:`daemon.stages`): ``push`` returns the one vector, ``flush`` nothing and starts over."""

    def __init__(self, rotations: JointRotations) -> None:
        self.rotations = rotations
        self._t = 0
        self._local = np.empty((rotations.model.n_nodes, 4))
        self._previous: FloatArray | None = None
        self._signs: FloatArray | None = None

    def frame(self, channels: npt.ArrayLike) -> FloatArray:
        """One frame: ``channels`` shape ``(C,)`` gives shape ``(D,)``; ``ValueError`` (the state
        unchanged) on a wrong shape or a value that is not finite."""
        row = np.asarray(channels, dtype=np.float64)
        if row.shape != (self.rotations.width,):
            raise ValueError(
                f"frame {self._t}: channels must have shape ({self.rotations.width},), got {row.shape}"
            )
        if not np.isfinite(row).all():
            raise ValueError(f"frame {self._t}: channels have a value that is not finite")
        self._t += 1
        q = self.rotations.model.local_rotations_frame(row, self._local)[self.rotations.index]
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


# -------------------------------------------------------------------------- shared statistics


def _check_finite(values: FloatArray, what: str) -> None:
    if values.size and not np.isfinite(values).all():
        bad = np.argwhere(~np.isfinite(values))[0]
        where = f"frame {int(bad[0])}" if values.ndim > 1 else "the frame"
        raise ValueError(f"{what}: {where} has a value that is not finite ({values[tuple(bad)]})")


def _check_frames(frames: npt.ArrayLike) -> FloatArray:
    x = np.ascontiguousarray(frames, dtype=np.float64)
    if x.ndim != 2 or x.shape[1] < 1:
        raise ValueError(f"frames must have shape (N, D) with D >= 1, got {x.shape}")
    _check_finite(x, "frames")
    return x


class _FrameCheck:
    """Validates pushed frames: shape ``(D,)`` fixed by the first, finite; returns a copy."""

    def __init__(self) -> None:
        self.dims: int | None = None

    def __call__(self, frame: npt.ArrayLike, index: int) -> FloatArray:
        x = np.array(frame, dtype=np.float64)
        if x.ndim != 1 or x.shape[0] < 1 or (self.dims is not None and x.shape[0] != self.dims):
            want = f"({self.dims},)" if self.dims is not None else "(D,) with D >= 1"
            raise ValueError(f"frame {index} must have shape {want}, got {x.shape}")
        if not np.isfinite(x).all():
            raise ValueError(f"frame {index} has a value that is not finite")
        self.dims = x.shape[0]
        return x


class _Moments:
    """A segment's frames so far: count ``n``, first frame ``origin`` ``(D,)``, ``s1 = sum (x - o)``
    ``(D,)`` and ``s2 = sum (x - o)(x - o)^T`` ``(D, D)``."""

    def __init__(self) -> None:
        self.n = 0
        self.origin = np.zeros(0)
        self.s1 = np.zeros(0)
        self.s2 = np.zeros((0, 0))

    def add(self, block: FloatArray) -> None:
        """Fold in ``block`` shape ``(m, D)``."""
        if self.n == 0:
            self.origin = block[0].copy()
            d = block.shape[1]
            self.s1, self.s2 = np.zeros(d), np.zeros((d, d))
        y = block - self.origin
        self.s1 += y.sum(axis=0)
        self.s2 += y.T @ y
        self.n += block.shape[0]

    def mean(self) -> FloatArray:
        """Eq. 1's centre of motion ``(D,)``."""
        out: FloatArray = self.origin + self.s1 / self.n
        return out

    def scatter(self) -> FloatArray:
        """The centred scatter ``sum (x - mean)(x - mean)^T`` ``(D, D)``: Eq. 4's ``D^T D``."""
        out: FloatArray = self.s2 - np.outer(self.s1, self.s1) / self.n
        return out


def spectrum(scatter: FloatArray) -> FloatArray:
    """The eigenvalues ``σ_j²`` of a scatter matrix ``(D, D)`` in increasing order, rounding below
    zero clipped: shape ``(D,)``."""
    out: FloatArray = np.maximum(np.linalg.eigvalsh(scatter), 0.0)
    return out


def dimension(eigenvalues: FloatArray, tau: float) -> int:
    """Eq. 6's rule: the smallest ``r`` with ``E_r = sum_(j<=r) σ_j² / sum σ_j² > tau``, the
    eigenvalues ``(D,)`` given in increasing order; 0 when they are all zero (nothing to keep)."""
    cumulative = np.cumsum(eigenvalues[::-1])
    total = float(cumulative[-1])
    if total <= 0.0:
        return 0
    r = int(np.searchsorted(cumulative, tau * total, side="right")) + 1
    return min(r, int(eigenvalues.shape[0]))


def projection_error(eigenvalues: FloatArray, r: int) -> float:
    """Eq. 5: the sum of the ``D - r`` discarded ``σ_j²`` (eigenvalues ``(D,)`` increasing)."""
    return float(eigenvalues[: eigenvalues.shape[0] - r].sum())


# ------------------------------------------------------------------------------------------- PCA


@dataclass(frozen=True)
class PcaFrames:
    """:class:`PcaParams` in frames at one rate: ``k``, ``ell`` (ℓ), ``i0``, ``step`` (frames
    between error evaluations; it divides ``k`` and ``ell``)."""

    k: int
    ell: int
    i0: int
    step: int


@dataclass(frozen=True)
class PcaParams:
    """§3.1's parameters; the windows in seconds, the paper's frames at 120 Hz in brackets: ``k``
    the frames that fix the dimension ``r`` (240), ``ell`` the lag ℓ of the derivative ``d_i = e_i -
    e_(i-ℓ)`` (60), ``i0`` the frames before the first test (300), ``tau`` (τ, Eq. 6) and ``k_sigma``
    (kσ: a cut where ``d_i`` exceeds the mean of the earlier ``d_j`` by more than ``kσ`` standard
    deviations).

    ``step`` is not the paper's: the seconds between two evaluations of the error ``e_i`` (one
    eigen-decomposition each; the derivative, its mean and deviation and the test are then taken on
    that grid). ``None`` evaluates every frame, as the paper does. It must divide ``k`` and ``ell``."""

    k: float = 2.0
    ell: float = 0.5
    i0: float = 2.5
    tau: float = 0.9
    k_sigma: float = 3.0
    step: float | None = None

    def frames(self, rate: float) -> PcaFrames:
        """The windows in frames at ``rate`` Hz; ``ValueError`` if they are not usable."""
        rate = _check_rate(rate)
        _check_fraction(self.tau, "tau")
        if not (math.isfinite(self.k_sigma) and self.k_sigma >= 0):
            raise ValueError(f"k_sigma must be a non-negative number, got {self.k_sigma}")
        ell = _count(self.ell, rate, "ell")
        k = _count(self.k, rate, "k", ell + 1)
        i0 = _count(self.i0, rate, "i0", 0)
        step = 1 if self.step is None else _count(self.step, rate, "step")
        if k % step or ell % step:
            raise ValueError(f"step ({step} frames) must divide k ({k}) and ell ({ell})")
        return PcaFrames(k, ell, i0, step)


PCA_PAPER = PcaParams()
"""§3.1's parameters: k = 240, ℓ = 60, i₀ = 300 frames at 120 Hz, τ = 0.9, kσ = 3, every frame."""

PCA_GRID = PcaParams(step=0.5)
"""§3.1's parameters with the error evaluated every ℓ frames only (one ``eigvalsh`` per ℓ frames
instead of one per frame: some 30 times faster; the derivative's statistics then rest on fewer,
non-overlapping values)."""


@dataclass(frozen=True)
class _PcaPoint:
    """One evaluation: segment ``count``, error ``e``; derivative ``d``, the test's ``threshold``
    (mean + kσ std of the earlier ``d``; NaN when not tested) and the cut's ``score`` (None: no cut)."""

    count: int
    error: float
    d: float
    threshold: float
    score: float | None


class _PcaRun:
    """§3.1 over one segment (from the start or the last cut): the moments, the dimension ``r``
    (from the first ``k`` frames), the errors of the last ℓ frames and the running mean and
    deviation of the derivatives (Welford). Fed blocks of ``step`` frames."""

    def __init__(self, p: PcaParams, f: PcaFrames) -> None:
        self.p, self.f = p, f
        self.moments = _Moments()
        self.r: int | None = None
        self.early: list[tuple[int, FloatArray]] = []  # spectra at counts k - ℓ .. k - step (r unknown)
        self.errors: dict[int, float] = {}
        self.n_d, self.mean_d, self.m2_d = 0, 0.0, 0.0

    def feed(self, block: FloatArray) -> _PcaPoint | None:
        self.moments.add(block)
        f, c = self.f, self.moments.n
        if c < f.k - f.ell or c % f.step:
            return None
        eigenvalues = spectrum(self.moments.scatter())
        if self.r is None:
            if c < f.k:
                self.early.append((c, eigenvalues))
                return None
            self.r = dimension(eigenvalues, self.p.tau)
            self.errors = {cc: projection_error(lam, self.r) for cc, lam in self.early}
            self.early = []
        e = projection_error(eigenvalues, self.r)
        self.errors[c] = e
        d = e - self.errors.pop(c - f.ell)
        threshold, score = math.nan, None
        if c > f.i0 and self.n_d:
            std = math.sqrt(self.m2_d / self.n_d)
            threshold = self.mean_d + self.p.k_sigma * std
            if std > 0.0 and d > threshold:
                score = (d - self.mean_d) / std
        if score is None:
            self.n_d += 1
            delta = d - self.mean_d
            self.mean_d += delta / self.n_d
            self.m2_d += delta * (d - self.mean_d)
        return _PcaPoint(c, e, d, threshold, score)


def _pca_boundary(point: _PcaPoint, start: int) -> Boundary | None:
    if point.score is None:
        return None
    frame = start + point.count - 1
    return Boundary(frame, "pca", point.score, frame)


class PcaSegmenter:
    """§3.1 online: push frame vectors ``(D,)`` (e.g. :class:`RotationStream`'s) at ``rate`` Hz;
    each push returns the cut it found ([] or one :class:`Boundary`, at the frame just pushed, the
    frame the paper assigns the cut to and restarts at). ``flush`` returns [] (a cut is never
    pending) and starts a new stream.

    For each segment (from the first frame, then from each cut, which is the new segment's first
    frame): ``r`` is the smallest dimension with ``E_r > τ`` over its first ``k`` frames (Eq. 6);
    ``e_i`` is the projection error of its first ``i`` frames onto their best ``r``-dimensional
    hyperplane (Eq. 5, the ``D - r`` smallest eigenvalues of their scatter), from ``i = k - ℓ``;
    ``d_i = e_i - e_(i-ℓ)`` from ``i = k``; for ``i > i0`` a cut falls on frame ``i`` when ``d_i >
    mean + kσ std`` of all earlier ``d_j`` of the segment (population deviation, which must be > 0:
    derivatives that were all equal, as in a stream that stood still, give no evidence yet). The
    paper tests one-sided ("rises sharply above").

    State: the moments (``D² + 2D`` floats), the spectra at the ``ℓ / step`` evaluations before
    ``r`` is known (``D`` floats each), then the last ``ℓ / step`` errors, and fewer than ``step``
    frames. Work: one ``eigvalsh`` of ``D x D`` per ``step`` frames from frame ``k - ℓ`` of a
    segment on (the paper's: every frame)."""

    def __init__(self, rate: float, *, params: PcaParams = PCA_PAPER) -> None:
        self.rate = _check_rate(rate)
        self.params = params
        self.frames = params.frames(rate)
        self._reset()

    def _reset(self) -> None:
        self._check = _FrameCheck()
        self._t = 0
        self._start = 0
        self._run = _PcaRun(self.params, self.frames)
        self._pending: list[FloatArray] = []

    def push(self, frame: npt.ArrayLike, /) -> list[Boundary]:
        x = self._check(frame, self._t)
        self._t += 1
        self._pending.append(x)
        if len(self._pending) < self.frames.step:
            return []
        block = np.array(self._pending)
        self._pending = []
        point = self._run.feed(block)
        cut = None if point is None else _pca_boundary(point, self._start)
        if cut is None:
            return []
        # The paper restarts at the cut frame: it is the new segment's first frame.
        self._start = cut.frame
        self._run = _PcaRun(self.params, self.frames)
        self._pending = [x]
        if self.frames.step == 1:
            self._run.feed(x[None])
            self._pending = []
        return [cut]

    def flush(self) -> list[Boundary]:
        self._reset()
        return []


@dataclass(frozen=True)
class PcaResult:
    """:func:`pca_analysis`: the ``boundaries`` and the signal at every evaluation, each ``(M,)``:
    ``frame`` (the index of the frame evaluated), ``segment`` (which segment it belongs to: 0 before
    the first cut, ...), the error ``error`` (Eq. 5), its derivative ``d`` and the test's
    ``threshold`` (mean + kσ std of the segment's earlier derivatives; NaN where not tested);
    ``dimensions``, the ``r`` of each segment that got one."""

    boundaries: list[Boundary]
    frame: IntArray
    segment: IntArray
    error: FloatArray
    d: FloatArray
    threshold: FloatArray
    dimensions: list[int]


def pca_analysis(frames: npt.ArrayLike, rate: float, *, params: PcaParams = PCA_PAPER) -> PcaResult:
    """§3.1 over a whole recording, ``frames`` shape ``(N, D)``: what :class:`PcaSegmenter` returns
    for the same frames pushed one by one, with the signal."""
    x = _check_frames(frames)
    f = params.frames(rate)
    out: list[Boundary] = []
    rows: list[tuple[int, int, float, float, float]] = []
    dimensions: list[int] = []
    start, n = 0, x.shape[0]
    while True:
        run, a, cut = _PcaRun(params, f), start, None
        while a + f.step <= n and cut is None:
            point = run.feed(x[a : a + f.step])
            a += f.step
            if point is not None:
                rows.append((start + point.count - 1, len(out), point.error, point.d, point.threshold))
                cut = _pca_boundary(point, start)
        if run.r is not None:
            dimensions.append(run.r)
        if cut is None:
            break
        out.append(cut)
        start = cut.frame
    table = np.array(rows, dtype=np.float64).reshape(-1, 5)
    index = table[:, :2].astype(np.int64)
    return PcaResult(out, index[:, 0], index[:, 1], table[:, 2], table[:, 3], table[:, 4], dimensions)


def pca_segment(frames: npt.ArrayLike, rate: float, *, params: PcaParams = PCA_PAPER) -> list[Boundary]:
    """§3.1's cuts of ``frames`` shape ``(N, D)`` at ``rate`` Hz: the batch twin of
    :class:`PcaSegmenter` (equal to pushing the frames one by one, then flushing)."""
    return pca_analysis(frames, rate, params=params).boundaries


# ------------------------------------------------------------------------------------------ PPCA


@dataclass(frozen=True)
class PpcaFrames:
    """:class:`PpcaParams` in frames at one rate: ``window`` (T), ``delta`` (Δ) and ``shortest``."""

    window: int
    delta: int
    shortest: int


@dataclass(frozen=True)
class PpcaParams:
    """§3.2's parameters; windows in seconds, the paper's frames at 120 Hz in brackets: ``window``
    T, the look-ahead frames whose mean Mahalanobis distance is ``H`` and the first ``K`` (150);
    ``delta`` Δ, the step of ``K`` (10); ``rise`` R, how far a peak of ``H`` must rise above the
    valley before it to be a cut (15); ``tau`` τ for the dimension (0.95).

    ``shortest`` is not the paper's rule but its assumption made one: the shortest behaviour, a
    peak at ``K`` below it is no cut (the segment before would be shorter). None, the default, is
    ``2 T``: the paper chooses T as "half of the anticipated number of frames in the smallest
    behavior". ``0`` gives the algorithm as published (:data:`PPCA_PUBLISHED`), where a segment may
    be as short as T. Chosen on ``bench.dev_segmentation``'s takes, not on the reported files.

    ``min_variance`` is not the paper's: a floor on the variances of the model's covariance ``C``
    (Eq. 9), so that ``C`` stays invertible when the first ``K`` frames do not vary at all (a
    stream standing still; then ``σ² = 0``). It is far below what joint rotations vary by in
    practice (1e-10 is a quaternion component's standard deviation of 1e-5, about 0.001°)."""

    window: float = 1.25
    delta: float = 1 / 12
    rise: float = 15.0
    tau: float = 0.95
    min_variance: float = 1e-10
    shortest: float | None = None

    def frames(self, rate: float) -> PpcaFrames:
        """The windows in frames at ``rate`` Hz; ``ValueError`` if they are not usable."""
        rate = _check_rate(rate)
        _check_fraction(self.tau, "tau")
        if not (math.isfinite(self.rise) and self.rise >= 0):
            raise ValueError(f"rise must be a non-negative number, got {self.rise}")
        if not (math.isfinite(self.min_variance) and self.min_variance > 0):
            raise ValueError(f"min_variance must be a positive number, got {self.min_variance}")
        window = _count(self.window, rate, "window", 2)
        delta = _count(self.delta, rate, "delta")
        if delta > window:
            raise ValueError(f"delta ({delta} frames) must not exceed window ({window} frames)")
        shortest = 2 * window if self.shortest is None else _count(self.shortest, rate, "shortest", 0)
        return PpcaFrames(window, delta, shortest)


PPCA_DEFAULT = PpcaParams()
"""§3.2's parameters (T = 150, Δ = 10 frames at 120 Hz, R = 15, τ = 0.95) and behaviours of at
least 2 T."""

PPCA_PUBLISHED = PpcaParams(shortest=0.0)
"""§3.2 exactly as published: its parameters, and a cut wherever a peak qualifies."""


class _PpcaRun:
    """§3.2 over one segment: the moments of its first ``K`` frames and what the peak test needs
    (the valley: the lowest local minimum of ``H`` so far; the ``H`` before the previous one; the
    previous ``H`` and its ``K``)."""

    def __init__(self, p: PpcaParams, f: PpcaFrames) -> None:
        self.p, self.f = p, f
        self.moments = _Moments()
        self.valley = math.inf
        self.before: float | None = None
        self.previous: tuple[int, float] | None = None

    @property
    def k(self) -> int:
        return self.moments.n

    def absorb(self, block: FloatArray) -> None:
        self.moments.add(block)

    def h(self, window: FloatArray) -> float:
        """Eq. 10: the mean Mahalanobis distance of ``window`` ``(T, D)`` under the PPCA model of
        the first ``K`` frames (Eqs. 7-9: mean ``x̄``; ``C = V Σ̃² V^T / (K - 1)`` where ``Σ̃²`` keeps
        the ``r`` largest ``σ_j²`` and replaces the others by their mean ``σ²``). A frame's distance is
        ``sqrt((x - x̄)^T C^-1 (x - x̄))``, "in units of standard deviation from the mean" as the
        paper says (the square root is missing from Eq. 10 as our copy of the text renders it):
        a frame of the model's own distribution is about ``sqrt(D)`` away, so R = 15 is a clear
        change. The squared form runs at 10² to 10⁴ within one behaviour here and moves by more than 15
        between two values of K, so nearly every bump of ``H`` became a cut (docs/segmentation.md)."""
        eigenvalues, vectors = np.linalg.eigh(self.moments.scatter())
        eigenvalues = np.maximum(eigenvalues, 0.0)
        r = dimension(eigenvalues, self.p.tau)
        dropped = eigenvalues.shape[0] - r
        variances = eigenvalues.copy()
        if dropped:
            variances[:dropped] = eigenvalues[:dropped].mean()
        variances = np.maximum(variances / (self.k - 1), self.p.min_variance)
        z = (window - self.moments.mean()) @ vectors
        return float(np.sqrt((z * z / variances).sum(axis=1)).sum() / window.shape[0])

    def observe(self, h: float) -> tuple[int, float] | None:
        """Take ``H`` at the current ``K``: the previous ``(K, rise)`` if it was a peak (``H`` rose
        into it and falls after it) at least R above a valley before it, else None. A valley is a
        local minimum (``H`` fell into it and does not fall after it), as in the paper's "a valley
        in H is followed by a peak": a segment whose ``H`` only rises from its first value has
        none, and is not cut until ``H`` has fallen and risen again. A peak at ``K`` below the
        shortest behaviour is passed over."""
        found = None
        if self.previous is not None:
            k, last = self.previous
            if self.before is not None:
                if self.before > last <= h:
                    self.valley = min(self.valley, last)
                elif self.before < last > h and last - self.valley >= self.p.rise and k >= self.f.shortest:
                    found = (k, last - self.valley)
            self.before = last
        self.previous = (self.k, h)
        return found


@dataclass(frozen=True)
class _PpcaCut:
    frame: int
    score: float
    emitted: int


def _ppca_pass(
    x: FloatArray, p: PpcaParams, f: PpcaFrames, trace: list[tuple[int, int, float]] | None = None
) -> list[_PpcaCut]:
    """One forward pass of §3.2 over ``x`` ``(n, D)``: ``K = T``; ``H`` of frames ``K .. K + T - 1``;
    ``K += Δ``; a cut at the first peak of ``H`` rising R above its valley, after which the search
    restarts at the cut. ``trace`` collects ``(frame K of the segment, segment, H)``."""
    out: list[_PpcaCut] = []
    start, n, t = 0, x.shape[0], f.window
    while start + t <= n:
        run = _PpcaRun(p, f)
        run.absorb(x[start : start + t])
        cut = None
        while start + run.k + t <= n:
            k = run.k
            h = run.h(x[start + k : start + k + t])
            if trace is not None:
                trace.append((start + k, len(out), h))
            peak = run.observe(h)
            if peak is not None:
                cut = _PpcaCut(start + peak[0], peak[1], start + k + t - 1)
                break
            run.absorb(x[start + k : start + k + f.delta])
        if cut is None:
            break
        out.append(cut)
        start = cut.frame
    return out


class PpcaSegmenter:
    """§3.2's forward pass online: push frame vectors ``(D,)`` at ``rate`` Hz; a push returns the
    cut that became known ([] or one :class:`Boundary`). A cut at frame ``c`` (the first frame of the
    new behaviour, ``K`` frames after the segment's start, at the peak of ``H``) is known when the
    ``H`` after the peak has been computed: at frame ``c + Δ + T - 1``, its ``emitted``. ``flush``
    returns [] (a rise without a fall is no peak) and starts a new stream.

    Returns exactly :func:`ppca_forward` of the same frames: the forward pass only. The backward
    passes of :func:`ppca_segment` need the whole recording and are not online.

    State: the moments of the first ``K`` frames (``D² + 2D`` floats) and the frames from ``K - Δ``
    on (at most ``2T`` frames; ``K`` grows, the window of ``T`` frames slides)."""

    def __init__(self, rate: float, *, params: PpcaParams = PPCA_DEFAULT) -> None:
        self.rate = _check_rate(rate)
        self.params = params
        self.frames = params.frames(rate)
        self._reset()

    def _reset(self) -> None:
        self._check = _FrameCheck()
        self._t = 0
        self._start = 0
        self._base = 0  # the index of self._kept[0]
        self._kept: list[FloatArray] = []
        self._run = _PpcaRun(self.params, self.frames)

    def _slice(self, a: int, b: int) -> FloatArray:
        return np.array(self._kept[a - self._base : b - self._base])

    def _drop_before(self, a: int) -> None:
        del self._kept[: a - self._base]
        self._base = a

    def push(self, frame: npt.ArrayLike, /) -> list[Boundary]:
        x = self._check(frame, self._t)
        self._t += 1
        self._kept.append(x)
        t, out = self.frames.window, []
        while True:
            run, start = self._run, self._start
            seen = self._t - start
            if run.k == 0:
                if seen < t:
                    break
                run.absorb(self._slice(start, start + t))
                continue
            if seen < run.k + t:
                break
            k = run.k
            h = run.h(self._slice(start + k, start + k + t))
            peak = run.observe(h)
            if peak is not None:
                cut = start + peak[0]
                out.append(Boundary(cut, "ppca", peak[1], start + k + t - 1))
                self._start = cut
                self._run = _PpcaRun(self.params, self.frames)
                self._drop_before(cut)
                continue
            run.absorb(self._slice(start + k, start + k + self.frames.delta))
            self._drop_before(start + run.k - self.frames.delta)
        return out

    def flush(self) -> list[Boundary]:
        self._reset()
        return []


def ppca_forward(frames: npt.ArrayLike, rate: float, *, params: PpcaParams = PPCA_DEFAULT) -> list[Boundary]:
    """§3.2's forward pass over ``frames`` shape ``(N, D)`` at ``rate`` Hz: the batch twin of
    :class:`PpcaSegmenter` (equal to pushing the frames one by one, then flushing)."""
    x = _check_frames(frames)
    return [Boundary(c.frame, "ppca", c.score, c.emitted) for c in _ppca_pass(x, params, params.frames(rate))]


@dataclass(frozen=True)
class PpcaResult:
    """:func:`ppca_analysis`: the ``boundaries`` of all passes (by frame), ``passes`` (how many ran,
    forward first, alternating), and the first forward pass's signal, each ``(M,)``: ``frame`` the
    first frame of each look-ahead window (``K`` frames after its segment's start), ``segment`` the
    segment it belongs to (0 before the first cut of that pass, ...), ``h`` its ``H``."""

    boundaries: list[Boundary]
    passes: int
    frame: IntArray
    segment: IntArray
    h: FloatArray


def ppca_analysis(frames: npt.ArrayLike, rate: float, *, params: PpcaParams = PPCA_DEFAULT) -> PpcaResult:
    """§3.2 in full over ``frames`` shape ``(N, D)``: a forward pass (:func:`ppca_forward`); then
    passes alternate direction, each run separately inside every segment the cuts so far leave (a
    backward pass runs the forward algorithm on the segment's frames reversed, so a cut at ``p``
    frames from the segment's end is frame ``end - p``), until a pass adds no cut (never before one
    backward pass has run). A later forward pass on the segments of an earlier one finds nothing new,
    so this is the paper's "alternating ... until convergence". Cuts found after the first pass have
    ``emitted = N - 1``."""
    x = _check_frames(frames)
    f = params.frames(rate)
    n = x.shape[0]
    trace: list[tuple[int, int, float]] = []
    cuts = {c.frame: Boundary(c.frame, "ppca", c.score, c.emitted) for c in _ppca_pass(x, params, f, trace)}
    passes, forward = 1, False
    while True:
        passes += 1
        edges = [0, *sorted(cuts), n]
        found: list[Boundary] = []
        for a, b in itertools.pairwise(edges):
            part = x[a:b] if forward else np.ascontiguousarray(x[a:b][::-1])
            for c in _ppca_pass(part, params, f):
                found.append(Boundary(a + c.frame if forward else b - c.frame, "ppca", c.score, n - 1))
        cuts.update((b.frame, b) for b in found)
        if not found:
            break
        forward = not forward
    table = np.array(trace, dtype=np.float64).reshape(-1, 3)
    index = table[:, :2].astype(np.int64)
    return PpcaResult([cuts[c] for c in sorted(cuts)], passes, index[:, 0], index[:, 1], table[:, 2])


def ppca_segment(frames: npt.ArrayLike, rate: float, *, params: PpcaParams = PPCA_DEFAULT) -> list[Boundary]:
    """§3.2's cuts of ``frames`` shape ``(N, D)`` at ``rate`` Hz, forward and backward passes
    alternating until no new cut (:func:`ppca_analysis`)."""
    return ppca_analysis(frames, rate, params=params).boundaries


# ------------------------------------------------------------------------------------------- GMM


@dataclass(frozen=True)
class GmmParams:
    """§3.3's parameters: ``variance`` the share of variance the PCA keeps (0.9), ``clusters`` k
    (4), ``min_length`` the seconds below which a segment is merged into its neighbours (1 s = 120
    frames). Not in the paper: ``seed`` of the initial means (one random frame from each of k
    consecutive parts of the recording, the paper's slightly better initialisation),
    ``regularizer`` added to every covariance's diagonal relative to the data's mean variance per
    dimension (so no covariance is ever singular), and EM's stopping rule: ``max_iterations``, or a
    gain of the mean log likelihood below ``tolerance`` nats per frame."""

    variance: float = 0.9
    clusters: int = 4
    min_length: float = 1.0
    seed: int = 0
    regularizer: float = 1e-6
    max_iterations: int = 200
    tolerance: float = 1e-6

    def check(self, rate: float) -> int:
        """The minimum length in frames at ``rate`` Hz; ``ValueError`` if a parameter is unusable."""
        rate = _check_rate(rate)
        if not 0.0 < self.variance <= 1.0:
            raise ValueError(f"variance must lie in (0, 1], got {self.variance}")
        if self.clusters < 1 or self.max_iterations < 1:
            raise ValueError("clusters and max_iterations must be at least 1")
        if not (self.regularizer > 0 and self.tolerance >= 0):
            raise ValueError("regularizer must be positive and tolerance non-negative")
        return _count(self.min_length, rate, "min_length", 0)


GMM_PAPER = GmmParams()
"""§3.3's parameters: PCA to 90 % of the variance, k = 4, segments under 1 s merged."""


@dataclass(frozen=True)
class GmmResult:
    """:func:`gmm_analysis`: the ``boundaries``; ``labels`` ``(N,)`` after merging and
    ``raw_labels`` ``(N,)`` (each frame's most likely cluster); ``dims`` the PCA's components;
    ``iterations`` of EM; ``log_likelihood`` its final mean per frame."""

    boundaries: list[Boundary]
    labels: IntArray
    raw_labels: IntArray
    dims: int
    iterations: int
    log_likelihood: float


def _log_densities(y: FloatArray, means: FloatArray, covariances: FloatArray) -> FloatArray:
    """``log N(y_i | m_j, Σ_j)``: ``y`` ``(N, d)``, ``means`` ``(k, d)``, ``covariances`` ``(k, d,
    d)`` give ``(N, k)``."""
    n, d = y.shape
    out = np.empty((n, means.shape[0]))
    for j in range(means.shape[0]):
        lower = np.linalg.cholesky(covariances[j])
        z = np.linalg.solve(lower, (y - means[j]).T)
        out[:, j] = -0.5 * ((z * z).sum(axis=0) + d * math.log(2 * math.pi)) - np.log(np.diag(lower)).sum()
    return out


def merge_short_runs(labels: npt.ArrayLike, min_length: int) -> IntArray:
    """§3.3's heuristic on ``labels`` shape ``(N,)``, giving shape ``(N,)``: while a run of equal
    labels is shorter than ``min_length`` frames (and not the only run), the shortest (the first of
    equals) is split in two halves that take the labels of the runs before and after it (the first
    ``floor(length / 2)`` frames the one before); a run at either end joins its one neighbour whole."""
    out = np.array(labels, dtype=np.int64).reshape(-1)
    while True:
        starts = np.flatnonzero(np.concatenate([[True], out[1:] != out[:-1]]))
        ends = np.concatenate([starts[1:], [out.shape[0]]])
        lengths = ends - starts
        if starts.shape[0] < 2 or lengths.min() >= min_length:
            return out
        i = int(np.argmin(lengths))
        a, b = int(starts[i]), int(ends[i])
        if i == 0:
            out[a:b] = out[b]
        elif i == starts.shape[0] - 1:
            out[a:b] = out[a - 1]
        else:
            middle = a + (b - a) // 2
            out[a:middle] = out[a - 1]
            out[middle:b] = out[b]


def gmm_analysis(frames: npt.ArrayLike, rate: float, *, params: GmmParams = GMM_PAPER) -> GmmResult:
    """§3.3 over ``frames`` shape ``(N, D)`` at ``rate`` Hz: project the centred frames onto the
    fewest principal components that keep ``variance`` of the total (Eq. 6's rule with ``τ =
    variance``); fit a mixture of ``clusters`` full-covariance Gaussians by EM (the standard updates
    the paper refers to, its ref. [8]; the means started at one seeded random frame from each of
    ``clusters`` consecutive parts, every covariance at the data's, equal weights); label each frame
    with its most likely cluster; merge runs shorter than ``min_length`` (:func:`merge_short_runs`);
    a boundary at every change of label. Deterministic for a given seed. Fewer frames than clusters,
    or frames that do not vary, give one segment and no boundary."""
    x = _check_frames(frames)
    min_length = params.check(rate)
    n = x.shape[0]
    none = np.zeros(n, dtype=np.int64)
    # Measured from the first frame, frames that do not vary centre to exactly zero.
    shifted = x - x[0] if n else x
    centred = shifted - shifted.mean(axis=0) if n else x
    eigenvalues, vectors = np.linalg.eigh(centred.T @ centred)
    eigenvalues = np.maximum(eigenvalues, 0.0)
    dims = dimension(eigenvalues, params.variance) if params.variance < 1 else int((eigenvalues > 0).sum())
    k = params.clusters
    if n < max(k, 2) or dims == 0:
        return GmmResult([], none, none.copy(), dims, 0, 0.0)
    y = centred @ vectors[:, ::-1][:, :dims]
    spread = np.cov(y, rowvar=False).reshape(dims, dims)
    ridge = params.regularizer * float(np.trace(spread)) / dims * np.eye(dims)
    rng = np.random.default_rng(params.seed)
    parts = np.linspace(0, n, k + 1).astype(np.int64)
    means = y[[int(rng.integers(parts[j], parts[j + 1])) for j in range(k)]]
    covariances = np.repeat((spread + ridge)[None], k, axis=0)
    weights = np.full(k, 1.0 / k)
    previous, iterations, tiny = -math.inf, 0, np.finfo(np.float64).tiny
    while iterations < params.max_iterations:
        iterations += 1
        joint = _log_densities(y, means, covariances) + np.log(np.maximum(weights, tiny))
        top = joint.max(axis=1, keepdims=True)
        norm = top[:, 0] + np.log(np.exp(joint - top).sum(axis=1))
        responsibilities = np.exp(joint - norm[:, None])
        likelihood = float(norm.mean())
        mass = responsibilities.sum(axis=0)
        weights = mass / n
        safe = np.maximum(mass, tiny)
        means = (responsibilities.T @ y) / safe[:, None]
        for j in range(k):
            deviation = y - means[j]
            covariances[j] = (responsibilities[:, j, None] * deviation).T @ deviation / safe[j] + ridge
        if likelihood - previous < params.tolerance:
            break
        previous = likelihood
    densities = _log_densities(y, means, covariances)
    raw = np.argmax(densities + np.log(np.maximum(weights, tiny)), axis=1).astype(np.int64)
    labels = merge_short_runs(raw, min_length)
    changes = np.flatnonzero(labels[1:] != labels[:-1]) + 1
    edges = [0, *changes.tolist(), n]
    boundaries = []
    for i, c in enumerate(changes.tolist()):
        new, old = int(labels[c]), int(labels[c - 1])
        segment = densities[c : edges[i + 2]]
        score = float((segment[:, new] - segment[:, old]).mean())
        boundaries.append(Boundary(c, "gmm", score, n - 1))
    return GmmResult(boundaries, labels, raw, dims, iterations, likelihood)


def gmm_segment(frames: npt.ArrayLike, rate: float, *, params: GmmParams = GMM_PAPER) -> list[Boundary]:
    """§3.3's cuts of ``frames`` shape ``(N, D)`` at ``rate`` Hz (batch only; :func:`gmm_analysis`)."""
    return gmm_analysis(frames, rate, params=params).boundaries


# -------------------------------------------------------------------------------------- dispatch

Params = PcaParams | PpcaParams | GmmParams
_P = TypeVar("_P", PcaParams, PpcaParams, GmmParams)


def match_boundaries(cuts: Sequence[int], bands: Sequence[Band]) -> int:
    """How many true boundaries ``bands`` the ``cuts`` (frames of new behaviours) find, each cut and
    each boundary used once: the pairs (cut, boundary) with the cut in the boundary's band, taken
    greedily by increasing distance from the cut to the boundary's frame."""
    pairs = sorted(
        (abs(c - b.frame), i, j) for i, c in enumerate(cuts) for j, b in enumerate(bands) if b.lo <= c <= b.hi
    )
    used_cuts: set[int] = set()
    used_bands: set[int] = set()
    for _, i, j in pairs:
        if i not in used_cuts and j not in used_bands:
            used_cuts.add(i)
            used_bands.add(j)
    return len(used_cuts)


def segment(
    frames: npt.ArrayLike, rate: float, method: Method, *, params: Params | None = None
) -> list[Boundary]:
    """The cuts of ``frames`` shape ``(N, D)`` at ``rate`` Hz by ``method`` (batch; PPCA with all its
    passes), with ``params`` (the method's parameter class; None: the paper's)."""
    if method == "pca":
        return pca_segment(frames, rate, params=_params(params, PcaParams, PCA_PAPER))
    if method == "ppca":
        return ppca_segment(frames, rate, params=_params(params, PpcaParams, PPCA_DEFAULT))
    if method == "gmm":
        return gmm_segment(frames, rate, params=_params(params, GmmParams, GMM_PAPER))
    raise ValueError(f"unknown segmentation method {method!r}: pca, ppca or gmm")


def analyse(
    frames: npt.ArrayLike, rate: float, method: Method, *, params: Params | None = None
) -> PcaResult | PpcaResult | GmmResult:
    """:func:`segment` with the method's signal (:func:`pca_analysis`, :func:`ppca_analysis`,
    :func:`gmm_analysis`): the same cuts in ``.boundaries``."""
    if method == "pca":
        return pca_analysis(frames, rate, params=_params(params, PcaParams, PCA_PAPER))
    if method == "ppca":
        return ppca_analysis(frames, rate, params=_params(params, PpcaParams, PPCA_DEFAULT))
    if method == "gmm":
        return gmm_analysis(frames, rate, params=_params(params, GmmParams, GMM_PAPER))
    raise ValueError(f"unknown segmentation method {method!r}: pca, ppca or gmm")


def online_segmenter(
    rate: float, method: Method, *, params: Params | None = None
) -> PcaSegmenter | PpcaSegmenter:
    """A streaming segmenter for ``method`` at ``rate`` Hz: PCA, or PPCA's forward pass; GMM has
    none (``ValueError``)."""
    if method == "pca":
        return PcaSegmenter(rate, params=_params(params, PcaParams, PCA_PAPER))
    if method == "ppca":
        return PpcaSegmenter(rate, params=_params(params, PpcaParams, PPCA_DEFAULT))
    raise ValueError(f"segmentation method {method!r} has no online form (pca and ppca do)")


def _params(given: Params | None, kind: type[_P], default: _P) -> _P:
    if given is None:
        return default
    if not isinstance(given, kind):
        raise ValueError(f"parameters {type(given).__name__} do not fit {kind.__name__}")
    return given
