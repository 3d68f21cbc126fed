"""Single repetitions inside a labelled run of a repeated exercise (jumping jacks, squats, ...): the
run's period and the frames where one repetition ends and the next begins.

Exercise labels such as mocap6's mark a *run* of many repetitions, while a motion template needs one
repetition per example. A run is cut in three steps:

1. **Signal.** Each frame becomes one vector: the 39 features as 0/1 and, if given, the joint
   positions relative to the root joint (so stepping about on the spot does not count, but the
   heading is kept: a twist turns the hips as well, and removing the hips' heading would remove
   most of the twist). Each part is centred over the run and scaled to a total variance of 1, so the
   two parts weigh the same and the distances below are in units of the run's own spread.
2. **Period.** The difference function ``d(L) = mean_t |x(t + L) - x(t)|² / 2`` (YIN's squared
   difference; ``1 - d(L)`` is the autocorrelation of the centred signal at lag ``L`` for a signal
   of variance 1) is computed for every lag up to ``max_period`` seconds, but at most two thirds of
   the run, so that a run of two repetitions still compares more than half a period. Its local
   minima at lags of at least ``min_period`` seconds are candidate periods. The fundamental is the
   *shortest* candidate whose dip is nearly as deep as the deepest (within ``harmonic_slack`` times
   the largest ``d``): the deepest dip is often at twice or three times the period, and a dip at
   half the period (an alternating exercise's other side, e.g. the left knee after the right) is
   shallower than the period's, because the features and joints of the two sides differ. So one
   repetition of an alternating exercise is a full cycle (left and right). The confidence is how
   far the dip goes below the highest point of ``d`` before it, ``(max d(0..P) - d(P)) / max
   d(0..P)``: near 1 for a clear period, near 0 for an aperiodic signal (white noise has ``d ≈ 1`` at
   every lag; a slow drift has ``d`` rising with the lag and no dip). The default range, 0.4-5 s,
   holds every exercise of mocap6 (a jog cycle 0.7 s, a twist or one-hand toe touch to both sides
   up to 4.3 s).
3. **Cuts.** A repetition starts and ends at the same phase (and, given an ``anchor`` from another
   run of the class, at that run's phase: see :func:`cut_run`). For every frame ``r`` of the run taken
   as the reference phase, its distance profile ``D(r, .)`` has minima where the motion passes
   ``r``'s pose again; a pass counts only at the lowest point within ``reach * P`` on either side
   inside the run and, near an end, only if the distance rises by ``edge_rise`` (of the run's mean
   distance) towards that end (else the true minimum may lie outside the run) or is at most
   ``close`` (a near-exact match: a rest pose held across the end of the run). A cut at a pass earns
   ``match - D(r, c) / mean D`` (positive if closer than ``match`` times the run's mean pairwise
   distance), and dynamic programming (:func:`chains`) picks the chain of cuts with the highest
   total, where two consecutive cuts ``min_spacing * P`` to ``max_spacing * P`` apart bound one
   repetition and pay ``tempo_weight * log²(gap / P)`` for straying from the period, and a longer gap
   (a missed pass) pays ``skip`` and bounds none, rather than guessing a cut. The reference whose
   chain scores best wins: the phase that the motion matches most consistently. Because every
   repetition is cut at a matched pass of one pose, tempo changes between repetitions move the cuts
   with them, instead of accumulating as they would when stepping by the mean period.

Partial repetitions before the first cut and after the last one are dropped, so a run of ``n``
samples with period ``P`` gives about ``n / P - 2`` to ``n / P`` repetitions (fewer if passes were
missed; tempo changes shift the bounds a little). Runs shorter than two minimal periods, constant
runs, signals without a dip in the range and estimates below ``min_confidence`` give no cuts and a
reason, never an error.

Pure: numpy in, frozen dataclasses out; no I/O. Distances take ``O(n²)`` memory for ``n`` samples
(a 40 s run at 30 Hz is 1,200 samples, 11 MB) and the chains ``O(n² P)`` time, so runs are cut at
30 Hz (the 17 mocap6 runs of 13_29, 13_30 and 14_14 take about 1 s in all).
"""

from __future__ import annotations

import dataclasses
import math
from collections import Counter
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from daemon.recordings import ExampleRows, Examples
from daemon.types import N_FEATURES, BoolArray, FloatArray

MIN_PERIOD_S = 0.4
MAX_PERIOD_S = 5.0
MIN_CONFIDENCE = 0.3
HARMONIC_SLACK = 0.25
MATCH = 0.6
MIN_SPACING = 0.7
MAX_SPACING = 1.4
TEMPO_WEIGHT = 2.0
SKIP = 0.5
REACH = 0.2
EDGE_RISE = 0.25
CLOSE = 0.1


@dataclass(frozen=True)
class Period:
    """The period of a run at ``rate`` Hz: ``samples`` (the integer lag, 0 if none was found),
    ``seconds`` (refined between samples by a parabola through the dip) and the ``confidence`` in
    [0, 1]; ``reason`` says why there is none ("" if there is)."""

    samples: int
    seconds: float
    confidence: float
    reason: str = ""

    @property
    def found(self) -> bool:
        return not self.reason


@dataclass(frozen=True)
class Repetition:
    """One repetition: samples ``start .. end`` of the run, both inclusive (``end`` is the next
    repetition's ``start``: both end at the same phase)."""

    start: int
    end: int

    @property
    def length(self) -> int:
        """Samples from the cut to the next cut (``end - start``)."""
        return self.end - self.start


@dataclass(frozen=True)
class Cutting:
    """A run of ``samples`` frames at ``rate`` Hz cut into repetitions: its :class:`Period`, the
    ``reference`` sample whose pose every cut matches (-1 if none), the ``cuts`` (sample indices,
    increasing), the ``repetitions`` between consecutive cuts, and ``mismatch``, the mean distance at
    the cuts relative to the run's mean pairwise distance (0 = the reference pose exactly). ``reason``
    says why there are no repetitions ("" if there are)."""

    samples: int
    rate: float
    period: Period
    reference: int
    cuts: tuple[int, ...]
    repetitions: tuple[Repetition, ...]
    mismatch: float
    reason: str = ""

    @property
    def period_seconds(self) -> float:
        return self.period.seconds


def _scaled(block: FloatArray) -> FloatArray:
    if block.shape[0] == 0:
        return block
    centred = block - block.mean(axis=0)
    variance = float((centred**2).sum(axis=1).mean())
    out: FloatArray = centred / math.sqrt(variance) if variance > 0 else centred
    return out


def run_signal(features: npt.ArrayLike, joints: npt.ArrayLike | None = None, root: int = 0) -> FloatArray:
    """The signal of a run: ``features`` shape ``(n, 39)`` (bool or 0/1) and optionally ``joints``
    shape ``(n, J, 3)`` made relative to joint ``root``, each centred and scaled to a total variance
    of 1 (a constant part stays 0), side by side: shape ``(n, 39 + 3J)``."""
    f = np.asarray(features, dtype=np.float64)
    if f.ndim != 2 or f.shape[1] != N_FEATURES:
        raise ValueError(f"features must have shape (n, {N_FEATURES}), got {f.shape}")
    parts = [_scaled(f)]
    if joints is not None:
        j = np.asarray(joints, dtype=np.float64)
        if j.ndim != 3 or j.shape[0] != f.shape[0] or j.shape[2] != 3 or not 0 <= root < j.shape[1]:
            raise ValueError(f"joints must have shape ({f.shape[0]}, J > {root}, 3), got {j.shape}")
        if not np.all(np.isfinite(j)):
            raise ValueError("joint positions must be finite")
        parts.append(_scaled((j - j[:, root : root + 1]).reshape(j.shape[0], -1)))
    return np.hstack(parts)


def difference_function(signal: npt.ArrayLike, max_lag: int) -> FloatArray:
    """``d(L) = mean_t |x(t + L) - x(t)|² / 2`` for ``L = 0 .. max_lag`` of a signal shape ``(n, d)``
    (``max_lag < n``): shape ``(max_lag + 1,)``."""
    x = np.asarray(signal, dtype=np.float64)
    if not 0 <= max_lag < x.shape[0]:
        raise ValueError(f"max_lag must lie in [0, {x.shape[0]}), got {max_lag}")
    out = np.zeros(max_lag + 1)
    for lag in range(1, max_lag + 1):
        out[lag] = float(((x[lag:] - x[:-lag]) ** 2).sum(axis=1).mean()) / 2
    return out


def estimate_period(
    signal: npt.ArrayLike,
    rate: float,
    *,
    min_period: float = MIN_PERIOD_S,
    max_period: float = MAX_PERIOD_S,
    harmonic_slack: float = HARMONIC_SLACK,
    min_confidence: float = MIN_CONFIDENCE,
) -> Period:
    """The period of a signal shape ``(n, d)`` sampled at ``rate`` Hz, between ``min_period`` and
    ``max_period`` seconds (at most two thirds of the run): step 2 of the module's method."""
    x = np.asarray(signal, dtype=np.float64)
    n = x.shape[0]
    lo = max(2, math.ceil(min_period * rate))
    hi = min(math.floor(max_period * rate), (2 * n) // 3)
    if hi < lo + 1:
        return Period(
            0,
            0.0,
            0.0,
            f"too short: {n} samples ({n / rate:.2f} s) hold no two periods of at least {min_period:g} s",
        )
    d = difference_function(x, hi)
    if not np.any(d > 0):
        return Period(0, 0.0, 0.0, "constant: the run does not move")
    dips = [lag for lag in range(lo, hi) if d[lag - 1] > d[lag] <= d[lag + 1]]
    if not dips:
        return Period(0, 0.0, 0.0, f"aperiodic: no dip between {lo / rate:.2f} and {hi / rate:.2f} s")
    deepest = min(float(d[lag]) for lag in dips)
    lag = min(lag for lag in dips if d[lag] <= deepest + harmonic_slack * float(d.max()))
    peak = float(d[: lag + 1].max())
    confidence = (peak - float(d[lag])) / peak if peak > 0 else 0.0
    a, b, c = float(d[lag - 1]), float(d[lag]), float(d[lag + 1])
    bend = a - 2 * b + c
    offset = 0.5 * (a - c) / bend if bend > 0 else 0.0
    seconds = (lag + offset) / rate
    if confidence < min_confidence:
        return Period(
            lag, seconds, confidence, f"aperiodic: confidence {confidence:.2f} < {min_confidence:g}"
        )
    return Period(lag, seconds, confidence)


def pairwise_distances(signal: npt.ArrayLike) -> FloatArray:
    """Squared distances between all samples of a signal shape ``(n, d)``: shape ``(n, n)``."""
    x = np.asarray(signal, dtype=np.float64)
    sq = (x**2).sum(axis=1)
    out: FloatArray = np.maximum(sq[:, None] + sq[None, :] - 2.0 * (x @ x.T), 0.0)
    return out


def passes(profiles: FloatArray, reach: int, rise: float, close: float) -> npt.NDArray[np.bool_]:
    """Where each row of ``profiles`` shape ``(m, n)`` has a pass: a point no higher than any within
    ``reach`` samples on either side inside the run, and, if the run ends within ``reach``, one
    that the row rises above by at least ``rise`` somewhere between it and that end (else the
    minimum may lie outside the run) or that is itself at most ``close`` (a near-exact match, such
    as a pose held across the run's end). Shape ``(m, n)``."""
    m, n = profiles.shape
    ok = np.ones((m, n), dtype=bool)
    for shift in range(1, reach + 1):
        ok[:, : n - shift] &= profiles[:, : n - shift] <= profiles[:, shift:]
        ok[:, shift:] &= profiles[:, shift:] <= profiles[:, : n - shift]
    for c in range(min(reach, n)):
        for index, ahead in ((c, slice(0, c + 1)), (n - 1 - c, slice(n - 1 - c, n))):
            risen = profiles[:, ahead].max(axis=1) - profiles[:, index] >= rise
            ok[:, index] &= risen | (profiles[:, index] <= close)
    return ok


@dataclass(frozen=True)
class Chain:
    """A chain of cuts for one reference: the ``cuts`` (increasing sample indices), the
    ``repetitions`` between consecutive cuts that are not a skipped gap, and its ``total`` cost."""

    cuts: tuple[int, ...]
    repetitions: tuple[Repetition, ...]
    total: float


def chains(
    costs: FloatArray,
    period: int,
    *,
    min_spacing: float = MIN_SPACING,
    max_spacing: float = MAX_SPACING,
    tempo_weight: float = TEMPO_WEIGHT,
    skip: float = SKIP,
) -> list[Chain]:
    """For every row of ``costs`` shape ``(m, n)`` (the cost of cutting at each of ``n`` samples, one
    row per reference), the chain of cuts ``c_0 < c_1 < ...`` minimising the sum of its cuts' costs
    plus, per gap, ``tempo_weight * log²(gap / period)`` if the gap lies between ``min_spacing`` and
    ``max_spacing`` times ``period`` (the two cuts bound a repetition), or ``skip`` if it is longer (a
    missed pass: no repetition). Dynamic programming over the samples, vectorised over the rows; a
    chain may start and end anywhere, so only cuts of negative cost pay off. One :class:`Chain` per
    row."""
    m, n = costs.shape
    lo = max(1, math.ceil(min_spacing * period))
    hi = max(lo, math.floor(max_spacing * period))
    gaps = np.arange(lo, hi + 1)
    penalty = tempo_weight * np.log(gaps / period) ** 2
    rows = np.arange(m)
    best = costs.astype(np.float64, copy=True)
    previous = np.full((m, n), -1, dtype=np.int64)
    skipped = np.zeros((m, n), dtype=bool)
    low_value = np.full(m, np.inf)  # min of best[:, :c - hi] and where
    low_at = np.full(m, -1, dtype=np.int64)
    for c in range(lo, n):
        far = c - hi - 1
        if far >= 0:
            better = best[:, far] < low_value
            low_value[better] = best[better, far]
            low_at[better] = far
        sources = c - gaps
        valid = sources >= 0
        options = best[:, sources[valid]] + penalty[valid]
        k = options.argmin(axis=1)
        value = options[rows, k]
        source = sources[valid][k]
        jump = low_value + skip < value
        value = np.where(jump, low_value + skip, value)
        source = np.where(jump, low_at, source)
        link = value < 0
        best[link, c] += value[link]
        previous[link, c] = source[link]
        skipped[link, c] = jump[link]
    out = []
    for row in range(m):
        c = int(best[row].argmin())
        cuts = [c]
        reps = []
        while previous[row, c] >= 0:
            b = int(previous[row, c])
            if not skipped[row, c]:
                reps.append(Repetition(b, c))
            cuts.append(b)
            c = b
        out.append(Chain(tuple(cuts[::-1]), tuple(reps[::-1]), float(best[row].min())))
    return out


def cut_run(
    features: npt.ArrayLike,
    rate: float,
    joints: npt.ArrayLike | None = None,
    *,
    root: int = 0,
    min_period: float = MIN_PERIOD_S,
    max_period: float = MAX_PERIOD_S,
    min_confidence: float = MIN_CONFIDENCE,
    match: float = MATCH,
    min_spacing: float = MIN_SPACING,
    max_spacing: float = MAX_SPACING,
    tempo_weight: float = TEMPO_WEIGHT,
    skip: float = SKIP,
    reach: float = REACH,
    edge_rise: float = EDGE_RISE,
    close: float = CLOSE,
    anchor: npt.ArrayLike | None = None,
) -> Cutting:
    """Cut a labelled run into single repetitions (the module's method): ``features`` shape
    ``(n, 39)`` at ``rate`` Hz, ``joints`` (optional) shape ``(n, J, 3)`` at the same rate, in any
    unit, ``root`` the joint they are made relative to. ``anchor`` (optional, shape ``(39,)``) is the
    feature vector of the phase to cut at, e.g. where another run of the class was cut: only the
    frames whose features are nearest to it (Hamming) are tried as the reference, if one of them
    gives repetitions, so that every run of a class starts its repetitions at one phase (a template
    averaged over repetitions cut at different phases blurs). Never raises for short, constant or
    aperiodic runs (the :class:`Cutting` has no repetitions and a ``reason``); raises
    :class:`ValueError` for arrays of the wrong shape or a rate that is not positive."""
    if not (math.isfinite(rate) and rate > 0):
        raise ValueError(f"rate must be a positive number, got {rate!r}")
    signal = run_signal(features, joints, root)
    n = signal.shape[0]
    period = estimate_period(
        signal, rate, min_period=min_period, max_period=max_period, min_confidence=min_confidence
    )
    if not period.found:
        return Cutting(n, rate, period, -1, (), (), math.nan, period.reason)
    distances = pairwise_distances(signal)
    scale = float(distances.mean())
    costs = distances / scale - match
    costs[~passes(distances / scale, max(1, round(reach * period.samples)), edge_rise, close)] = np.inf
    found = chains(
        costs,
        period.samples,
        min_spacing=min_spacing,
        max_spacing=max_spacing,
        tempo_weight=tempo_weight,
        skip=skip,
    )
    references: Sequence[int] = range(n)
    if anchor is not None:
        away = (np.asarray(features, dtype=bool) != np.asarray(anchor, dtype=bool)).sum(axis=1)
        nearest = np.flatnonzero(away == away.min()).tolist()
        if any(found[r].repetitions for r in nearest):
            references = nearest
    reference = min(references, key=lambda r: found[r].total)
    chain = found[reference]
    if not chain.repetitions:
        return Cutting(n, rate, period, -1, (), (), math.nan, "no pose recurs at the period")
    cuts = sorted({c for rep in chain.repetitions for c in (rep.start, rep.end)})
    mismatch = float(distances[reference, cuts].mean()) / scale
    return Cutting(n, rate, period, reference, tuple(cuts), chain.repetitions, mismatch)


# ------------------------------------------------------------------- periodic classes in learning

MAX_TURN_DEG = 45.0
"""An example whose body heading spans more than this is one motion that turns (a walk with a
turn), not a run of one cycle repeated: the cycles of walking, running or waving come back to their
heading. Half a quarter turn, so that a walk's sway (a few tens of degrees) stays below it."""


@dataclass(frozen=True)
class ExampleCut:
    """How one training example of a periodic class is learned: the single repetitions it gives
    (samples of the example, both inclusive; empty: the example is learned whole) and why it gives
    none ("" if it gives some): "turning (…)", "no cycle (…)" or "a single cycle"."""

    repetitions: tuple[Repetition, ...]
    reason: str = ""


def cut_examples(
    examples: Sequence[tuple[npt.ArrayLike, npt.ArrayLike]], rate: float, count: int
) -> tuple[ExampleCut, ...] | None:
    """The first ``count`` single repetitions of each of a class's examples, each ``(features (n,
    39), heading (n,))`` at ``rate`` Hz (:func:`body_heading`), if the class is periodic, else None.

    An example gives repetitions when :func:`cut_run` finds at least two in it and its heading spans
    at most :data:`MAX_TURN_DEG`; the class is periodic when at least half of its examples give
    some. Its other examples stay whole. Every example after the first that gives repetitions is
    cut at the phase of that first one (``anchor``), so that the template averages like with like."""
    cuts: list[ExampleCut] = []
    anchor: BoolArray | None = None
    for features, heading in examples:
        h = np.asarray(heading, dtype=np.float64)
        turn = math.degrees(float(h.max() - h.min())) if h.size else 0.0
        if turn > MAX_TURN_DEG:
            cuts.append(ExampleCut((), f"turning ({turn:.0f}°)"))
            continue
        found = cut_run(features, rate, anchor=anchor)
        if len(found.repetitions) < 2:
            cuts.append(ExampleCut((), f"no cycle ({found.reason})" if found.reason else "a single cycle"))
            continue
        if anchor is None:
            anchor = np.asarray(features, dtype=bool)[found.reference]
        cuts.append(ExampleCut(found.repetitions[:count]))
    return tuple(cuts) if 2 * sum(bool(c.repetitions) for c in cuts) >= len(cuts) and cuts else None


def periodic_examples(
    rows: Mapping[str, Sequence[ExampleRows]],
    rate: float,
    count: int,
    report: Callable[[str], object] | None = None,
) -> Examples:
    """Every class's examples as learning takes them: a periodic class's (:func:`cut_examples`) as
    the first ``count`` single repetitions of each, each then an example of its own whose clip names
    its frames, the others' whole. ``report(line)`` says how each periodic class was cut."""
    out: Examples = {}
    for name, items in rows.items():
        cuts = cut_examples([(e.matrix, e.heading) for e in items], rate, count)
        out[name] = []
        for k, e in enumerate(items):
            pieces = () if cuts is None else cuts[k].repetitions
            out[name] += [
                (
                    dataclasses.replace(
                        e.clip,
                        start_frame=int(e.frames[r.start]),
                        end_frame=int(e.frames[r.end]),
                        frames=r.end - r.start + 1,
                    ),
                    e.matrix[r.start : r.end + 1],
                )
                for r in pieces
            ] or [(e.clip, e.matrix)]
        if report is not None and cuts is not None:
            whole = [c.reason.split(" (")[0] for c in cuts if not c.repetitions]
            why = ", ".join(f"{reason}: {n}" for reason, n in sorted(Counter(whole).items()))
            report(
                f"[repetitions] {name}: {len(cuts) - len(whole)} of {len(cuts)} examples cut into "
                f"{len(out[name]) - len(whole)} single repetitions"
                + (f"; {len(whole)} kept whole ({why})" if whole else "")
            )
    return out
