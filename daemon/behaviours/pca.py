"""§3.1 of Barbič et al. 2004, behaviour segmentation by PCA: a cut where the error of projecting a
segment's frames onto its best ``r``-dimensional hyperplane (Eq. 5, ``r`` by Eq. 6's rule) rises
sharply. Online (:class:`PcaSegmenter`) with a batch twin (:func:`pca_segment`, :func:`pca_analysis`
with the signal) that returns the same cuts.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from daemon.behaviours.common import Boundary, check_fraction, check_frames, check_rate, count_frames
from daemon.behaviours.moments import Moments, dimension, projection_error, spectrum
from daemon.behaviours.online import OnlineSegmenter
from daemon.errors import InputError
from daemon.types import FloatArray, IntArray


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
    that grid). ``None`` evaluates every frame, as the paper does. In frames it is rounded down to
    a divisor of ``k`` and ``ell`` (the grid meets both at any rate)."""

    k: float = 2.0
    ell: float = 0.5
    i0: float = 2.5
    tau: float = 0.9
    k_sigma: float = 3.0
    step: float | None = None

    def frames(self, rate: float) -> PcaFrames:
        """The windows in frames at ``rate`` Hz; ``ValueError`` if they are not usable."""
        rate = check_rate(rate)
        check_fraction(self.tau, "tau")
        if not (math.isfinite(self.k_sigma) and self.k_sigma >= 0):
            raise InputError(f"k_sigma must be a non-negative number, got {self.k_sigma}")
        ell = count_frames(self.ell, rate, "ell")
        k = count_frames(self.k, rate, "k", ell + 1)
        i0 = count_frames(self.i0, rate, "i0", 0)
        most = 1 if self.step is None else count_frames(self.step, rate, "step")
        common = math.gcd(k, ell)
        step = max(d for d in range(1, min(most, common) + 1) if common % d == 0)
        return PcaFrames(k, ell, i0, step)


PCA_PAPER = PcaParams()
"""§3.1's parameters: k = 240, ℓ = 60, i₀ = 300 frames at 120 Hz, τ = 0.9, kσ = 3, every frame."""

PCA_ONLINE = PcaParams(step=1 / 12)
"""What a segmented stream of the daemon runs (:func:`~daemon.behaviours.online_segmenter`): §3.1's
parameters with the error evaluated every 1/12 s (§3.2's Δ; 10 frames at 120 Hz), a cut at most
that late. Chosen on the development set (``bench.dev_segmentation``: F1 0.24 against 0.21 for
every frame), for one ``eigvalsh`` per 10 frames instead of one per frame."""

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
        self.moments = Moments()
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


class PcaSegmenter(OnlineSegmenter[PcaParams, PcaFrames, _PcaRun]):
    """§3.1 online: push frame vectors ``(D,)`` (e.g.
    :class:`~daemon.behaviours.quaternions.RotationStream`'s) at ``rate`` Hz; each push returns the
    cut it found ([] or one :class:`Boundary`, at the frame just pushed, the frame the paper assigns
    the cut to and restarts at). ``flush`` returns [] (a cut is never pending) and starts a new
    stream.

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
        super().__init__(rate, params, params.frames(rate), _PcaRun)

    def _reset(self) -> None:
        super()._reset()
        self._pending: list[FloatArray] = []

    def push(self, frame: npt.ArrayLike, /) -> list[Boundary]:
        x = self._take(frame)
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
        self._restart(cut.frame)
        self._pending = [x]
        if self.frames.step == 1:
            self._run.feed(x[None])
            self._pending = []
        return [cut]


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
    x = check_frames(frames)
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
