"""§3.2 of Barbič et al. 2004, behaviour segmentation by probabilistic PCA: a cut where the frames
ahead stop fitting the Gaussian of the segment so far (Eqs. 7-10: the mean Mahalanobis distance
``H`` of the next ``T`` frames peaks after a valley). The forward pass is online, a cut known ``Δ + T
- 1`` frames after its frame (:class:`PpcaSegmenter`, batch twin :func:`ppca_forward`);
:func:`ppca_segment` alternates forward and backward passes until a pass finds no new cut.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from daemon.behaviours.common import Boundary, check_fraction, check_frames, check_rate, count_frames
from daemon.behaviours.moments import Moments, dimension
from daemon.behaviours.online import OnlineSegmenter
from daemon.errors import InputError
from daemon.types import FloatArray, IntArray


@dataclass(frozen=True)
class PpcaFrames:
    """:class:`PpcaParams` in frames at one rate: ``window`` (T), ``delta`` (Δ) and ``shortest``."""

    window: int
    delta: int
    shortest: int


SHORTEST_WINDOWS = 3
"""The shortest behaviour by default, in windows T (:class:`PpcaParams`)."""


@dataclass(frozen=True)
class PpcaParams:
    """§3.2's parameters; windows in seconds, the paper's frames at 120 Hz in brackets: ``window``
    T, the look-ahead frames whose mean Mahalanobis distance is ``H`` and the first ``K`` (150);
    ``delta`` Δ, the step of ``K`` (10); ``rise`` R, how far a peak of ``H`` must rise above the
    valley before it to be a cut (the paper's 15; 20 by default); ``tau`` τ for the dimension (0.95).

    ``shortest`` is not the paper's rule but its assumption made one: the shortest behaviour, a
    peak at ``K`` below it is no cut (the segment before would be shorter). None, the default, is
    :data:`SHORTEST_WINDOWS` T (the paper chooses T as "half of the anticipated number of frames in
    the smallest behavior": 2 T). ``0`` gives the algorithm as published (:data:`PPCA_PUBLISHED`),
    where a segment may be as short as T.

    The defaults R = 20 and 3 T are what leaving one annotated take out chose on the other three,
    in each of the four folds (``python -m bench.eval_segmentation --folds``; docs/segmentation.md).

    ``min_variance`` is not the paper's: a floor on the variances of the model's covariance ``C``
    (Eq. 9), so that ``C`` stays invertible when the first ``K`` frames do not vary at all (a
    stream standing still; then ``σ² = 0``). It is far below what joint rotations vary by in
    practice (1e-10 is a quaternion component's standard deviation of 1e-5, about 0.001°)."""

    window: float = 1.25
    delta: float = 1 / 12
    rise: float = 20.0
    tau: float = 0.95
    min_variance: float = 1e-10
    shortest: float | None = None

    def frames(self, rate: float) -> PpcaFrames:
        """The windows in frames at ``rate`` Hz; ``ValueError`` if they are not usable."""
        rate = check_rate(rate)
        check_fraction(self.tau, "tau")
        if not (math.isfinite(self.rise) and self.rise >= 0):
            raise InputError(f"rise must be a non-negative number, got {self.rise}")
        if not (math.isfinite(self.min_variance) and self.min_variance > 0):
            raise InputError(f"min_variance must be a positive number, got {self.min_variance}")
        window = count_frames(self.window, rate, "window", 2)
        delta = count_frames(self.delta, rate, "delta")
        if delta > window:
            raise InputError(f"delta ({delta} frames) must not exceed window ({window} frames)")
        shortest = (
            SHORTEST_WINDOWS * window
            if self.shortest is None
            else count_frames(self.shortest, rate, "shortest", 0)
        )
        return PpcaFrames(window, delta, shortest)


PPCA_DEFAULT = PpcaParams()
"""§3.2's windows (T = 150, Δ = 10 frames at 120 Hz, τ = 0.95), R = 20 and behaviours of at least
3 T, as the folds over the annotated takes chose them."""

PPCA_PUBLISHED = PpcaParams(rise=15.0, shortest=0.0)
"""§3.2 exactly as published: its parameters (R = 15), and a cut wherever a peak qualifies."""

PPCA_ONLINE = PpcaParams(rise=15.0, shortest=2.5)
"""What the forward pass alone runs with by default (:class:`PpcaSegmenter`, the daemon's online
segmentation): the paper's R = 15 and behaviours of at least 2 T, as before issue 38. Leaving one
annotated take out chose no one setting for the forward pass (R = 20 with 2 T once, R = 10 with
3 T three times), and on the development set the all-pass defaults cost it half its recall."""


class _PpcaRun:
    """§3.2 over one segment: the moments of its first ``K`` frames and what the peak test needs
    (the valley: the lowest local minimum of ``H`` so far; the ``H`` before the previous one; the
    previous ``H`` and its ``K``)."""

    def __init__(self, p: PpcaParams, f: PpcaFrames) -> None:
        self.p, self.f = p, f
        self.moments = Moments()
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


class PpcaSegmenter(OnlineSegmenter[PpcaParams, PpcaFrames, _PpcaRun]):
    """§3.2's forward pass online: push frame vectors ``(D,)`` at ``rate`` Hz; a push returns the
    cut that became known ([] or one :class:`Boundary`). A cut at frame ``c`` (the first frame of the
    new behaviour, ``K`` frames after the segment's start, at the peak of ``H``) is known when the
    ``H`` after the peak has been computed: at frame ``c + Δ + T - 1``, its ``emitted``. ``flush``
    returns [] (a rise without a fall is no peak) and starts a new stream.

    Returns exactly :func:`ppca_forward` of the same frames: the forward pass only. The backward
    passes of :func:`ppca_segment` need the whole recording and are not online.

    State: the moments of the first ``K`` frames (``D² + 2D`` floats) and the frames from ``K - Δ``
    on (at most ``2T`` frames; ``K`` grows, the window of ``T`` frames slides)."""

    def __init__(self, rate: float, *, params: PpcaParams = PPCA_ONLINE) -> None:
        super().__init__(rate, params, params.frames(rate), _PpcaRun)

    def _reset(self) -> None:
        super()._reset()
        self._base = 0  # the index of self._kept[0]
        self._kept: list[FloatArray] = []

    def _slice(self, a: int, b: int) -> FloatArray:
        return np.array(self._kept[a - self._base : b - self._base])

    def _drop_before(self, a: int) -> None:
        del self._kept[: a - self._base]
        self._base = a

    def push(self, frame: npt.ArrayLike, /) -> list[Boundary]:
        self._kept.append(self._take(frame))
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
                self._restart(cut)
                self._drop_before(cut)
                continue
            run.absorb(self._slice(start + k, start + k + self.frames.delta))
            self._drop_before(start + run.k - self.frames.delta)
        return out


def ppca_forward(frames: npt.ArrayLike, rate: float, *, params: PpcaParams = PPCA_ONLINE) -> list[Boundary]:
    """§3.2's forward pass over ``frames`` shape ``(N, D)`` at ``rate`` Hz: the batch twin of
    :class:`PpcaSegmenter` (equal to pushing the frames one by one, then flushing), with the same
    default parameters (:data:`PPCA_ONLINE`)."""
    x = check_frames(frames)
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
    x = check_frames(frames)
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
