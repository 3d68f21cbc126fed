"""Motion templates (thesis ch. 3): learning soft and hard MTs from example feature matrices,
quantisation, and automatic keyframes from a hard MT (thesis ch. 6).

Templates and examples are as in :mod:`daemon.templates` (:class:`~daemon.templates.MotionTemplate`).

Learning is the iterative, reference-based averaging of thesis §3.3 in the form of the toolbox's
``motionTemplateGenerateDTWIterative``, strategy 5 (reference facts, section d): in every iteration
each current template in turn is the reference, every other one is warped onto its time axis with a
full DTW (:func:`warp`), all are averaged (weighted mean for soft MTs; ⊕ of Def. 3.4 for hard MTs,
eq. 3.4) and the result is balanced, Ω^E ∘ Ω^C ∘ Ω^E (eq. 3.5, :func:`balance`); then all templates
are replaced at once (eq. 3.6). The output is the template whose first reference was the first
example. Hard MTs have DTW distance 0 to every example under c& (Claim 3.1).

Pure: numpy in, frozen dataclasses out; no I/O.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal

import numpy as np
import numpy.typing as npt

from daemon.dtw import and_cost, full_dtw, l1_cost, weighted
from daemon.features import SET_SLICES
from daemon.keyframes import Keyframe, KeyframeQuery, gap_bounds
from daemon.templates import Example, MotionTemplate, as_template, expand
from daemon.types import DEFAULT_INDEX_RATE, FEATURE_SETS, N_FEATURES, FeatureSet, FloatArray, IntArray

Combine = Literal["mean", "oplus"]
"""How columns are merged: the weight-weighted mean (soft MTs) or ⊕ (hard MTs, Def. 3.4)."""

CONTRACT_BELOW = 0.75
KEYFRAME_SCORES = (1, 3)  # points for a 0 entry and for a 1 entry of a hard MT (thesis ch. 6)
STIFFNESS_DIGITS = 3


def _templates(examples: Sequence[Example]) -> list[MotionTemplate]:
    out = [as_template(e) for e in examples]
    if not out:
        raise ValueError("learning a motion template needs at least one example")
    if len({t.features for t in out}) != 1:
        raise ValueError(f"examples differ in their number of features: {sorted({t.features for t in out})}")
    return out


# ------------------------------------------------------------------------------------------- ⊕


def oplus(v: npt.ArrayLike, w: npt.ArrayLike) -> FloatArray:
    """Def. 3.4 (eq. 3.1), elementwise with broadcasting: ``v`` where ``v == w``, else ½."""
    a = np.asarray(v, dtype=np.float64)
    b = np.asarray(w, dtype=np.float64)
    return np.asarray(np.where(a == b, a, 0.5))


def oplus_columns(values: npt.ArrayLike) -> FloatArray:
    """⊕ of all columns of an ``(f, n)`` matrix (n >= 1): shape ``(f,)``; ⊕ is associative and
    commutative, so a row keeps its value iff all its entries are equal."""
    x = np.asarray(values, dtype=np.float64)
    lo, hi = x.min(axis=1), x.max(axis=1)
    return np.asarray(np.where(lo == hi, lo, 0.5))


# ----------------------------------------------------------------------------------- balancing


def contract(t: MotionTemplate, combine: Combine = "mean") -> MotionTemplate:
    """Ω^C (the toolbox's ``contractWeightedVectorSequence``; reference facts, section d). Scanning
    left to right, a column of weight >= 0.75 is kept; a lighter one is merged with the following
    columns until their summed weight reaches 0.75: the merged column is their ``combine`` (weighted
    mean, or ⊕ as Ω^C& does it) with the summed weight.

    If the right border comes first, the group goes into the previous output column:

    * ``"mean"`` reproduces the toolbox's quirk: only the *last input column* of the previous output
      column is re-included (mean and weight over it and the group), so any earlier inputs merged
      into that output column are lost, with their weight; the new weight can even be below 0.75.
    * ``"oplus"`` merges the group into the whole previous output column (⊕, weights added), so the
      result stays a sequence of merges of adjacent columns (proof of Claim 3.1) and keeps the total
      weight.

    With no previous output column (total weight < 0.75) the group becomes one column as it is (the
    toolbox fails there). So every column but possibly the last one weighs >= 0.75 afterwards."""
    values, weights = t.values, t.weights
    n = t.length
    out_values: list[FloatArray] = []
    out_weights: list[float] = []
    out_first: list[int] = []  # first input column of each output column
    i = 0
    while i < n:
        s = float(weights[i])
        if s >= CONTRACT_BELOW:
            out_values.append(values[:, i])
            out_weights.append(s)
            out_first.append(i)
            i += 1
            continue
        j = i
        while s < CONTRACT_BELOW and j + 1 < n:
            j += 1
            s += float(weights[j])
        lo = i
        if s < CONTRACT_BELOW and out_values:
            if combine == "mean":
                lo = i - 1
                s += float(weights[lo])
            else:
                lo = out_first[-1]
                s += out_weights[-1]
            out_values.pop()
            out_weights.pop()
            out_first.pop()
        if combine == "mean":
            merged = np.asarray(values[:, lo : j + 1] @ weights[lo : j + 1] / s)
        else:
            merged = oplus_columns(values[:, lo : j + 1])
        out_values.append(merged)
        out_weights.append(s)
        out_first.append(lo)
        i = j + 1
    return MotionTemplate(np.stack(out_values, axis=1), np.asarray(out_weights))


def balance(t: MotionTemplate, combine: Combine = "mean") -> MotionTemplate:
    """Ω^E ∘ Ω^C ∘ Ω^E (eq. 3.5). Afterwards every weight is < 1.5 and every weight but possibly the
    last is >= 0.75 (the last only falls short after the ``"mean"`` border quirk of :func:`contract`
    or when the total weight is below 0.75)."""
    return expand(contract(expand(t), combine))


# ------------------------------------------------------------------------------------------ warp


def warp(sequence: MotionTemplate, path: IntArray, length: int, combine: Combine = "mean") -> MotionTemplate:
    """Ω^W (thesis §3.3.1): the template W = ``sequence`` mapped onto the time axis of a reference of
    ``length`` columns along a warping path ``(L, 2)`` of (reference column, sequence column) pairs,
    0-based, from (0, 0) to (length-1, K-1) (:attr:`daemon.dtw.Alignment.path` with the reference on
    the rows). Reference facts, section d, "Map W_i back onto V's time axis":

    * reference column ``a`` gets the ``combine`` of the W columns matched to it (weight-weighted
      mean, or ⊕) and the sum of their weights;
    * then for every W column ``b`` matched to ``r_b`` reference columns, the weights of those
      reference columns are divided by ``r_b`` (the toolbox's quirk: the whole accumulated weight,
      including what a neighbouring W column contributed, is divided).

    Result: values ``(f, length)``, weights ``(length,)``."""
    p = np.asarray(path, dtype=np.int64)
    if p.ndim != 2 or p.shape[1] != 2 or not p.shape[0] or p[0, 0] != 0 or p[0, 1] != 0:
        raise ValueError("a warping path must be (L, 2) pairs starting at (0, 0)")
    a, b = p[:, 0], p[:, 1]
    if a[-1] != length - 1 or b[-1] != sequence.length - 1:
        raise ValueError(f"the path ends at {tuple(p[-1])}, not at ({length - 1}, {sequence.length - 1})")
    steps = np.diff(p, axis=0)
    if not (np.all((steps >= 0) & (steps <= 1)) and np.all(steps.sum(axis=1) >= 1)):
        raise ValueError("a warping path moves by (1, 0), (0, 1) or (1, 1)")
    wb = sequence.weights[b]
    starts = np.flatnonzero(np.concatenate([[True], a[1:] != a[:-1]]))
    weights = np.add.reduceat(wb, starts)
    columns = sequence.values[:, b]
    if combine == "mean":
        values = np.add.reduceat(columns * wb, starts, axis=1) / weights
    else:
        lo = np.minimum.reduceat(columns, starts, axis=1)
        hi = np.maximum.reduceat(columns, starts, axis=1)
        values = np.where(lo == hi, lo, 0.5)
    reps = np.bincount(b, minlength=sequence.length).astype(np.float64)
    # unbuffered and in path order (b ascending): the toolbox's division, one W column after another
    np.divide.at(weights, a, reps[b])
    return MotionTemplate(values, weights)


# -------------------------------------------------------------------------------------- averaging


def learning_cost(reference: MotionTemplate, sequence: MotionTemplate, combine: Combine) -> FloatArray:
    """The local cost ``(K_ref, K_seq)`` of learning: the distance of two columns times the mean of
    their weights, ``(w_a + w_b) / 2`` (reference facts, section d). The distance is the mean absolute
    difference over the f features for soft MTs (``"mean"``, ℓ1 of §3.3.3), and c& (eq. 3.2/3.3)
    divided by f for hard MTs (``"oplus"``): both lie in [0, 1], and a 0 stays exactly 0."""
    if combine == "mean":
        dist = l1_cost(reference.values, sequence.values)
    else:
        dist = and_cost(reference.values, sequence.values) / reference.features
    return weighted(dist, reference.weights, sequence.weights)


def average(
    reference: MotionTemplate, others: Sequence[MotionTemplate], combine: Combine
) -> tuple[MotionTemplate, FloatArray]:
    """Ω^A_(X, alpha) (eq. 3.4/3.5) with the reference X: every template of ``others`` is aligned to X
    by full DTW under :func:`learning_cost` (steps (1,0), (0,1), (1,1); ties as in
    :func:`daemon.dtw.full_dtw`) and warped onto X's time axis (:func:`warp`). Then

    * soft (``"mean"``): Z = the weight-weighted mean of X and the warps, column by column;
    * hard (``"oplus"``): Z = X ⊕ Z_1 ⊕ ... ⊕ Z_N;

    the weights are the mean of all weights (gamma of eq. 3.4), and the result is :func:`balance`
    (Z, gamma). Returns it and the DTW cost D(n, m) of each of ``others`` divided by the result's
    total weight, shape ``(len(others),)``."""
    warps = [reference]
    costs = np.zeros(len(others))
    for i, other in enumerate(others):
        alignment = full_dtw(learning_cost(reference, other, combine))
        costs[i] = alignment.cost
        warps.append(warp(other, alignment.path, reference.length, combine))
    weights = np.stack([w.weights for w in warps])  # (N + 1, K)
    total = weights.sum(axis=0)
    values = np.stack([w.values for w in warps])  # (N + 1, f, K)
    if combine == "mean":
        z = np.einsum("nk,nfk->fk", weights, values) / total
    else:
        lo, hi = values.min(axis=0), values.max(axis=0)
        z = np.where(lo == hi, lo, 0.5)
    result = balance(MotionTemplate(z, total / len(warps)), combine)
    return result, costs / result.weights.sum()


@dataclass(frozen=True)
class LearnedTemplate:
    """A learned MT: ``template`` (the one whose first reference was the first example), the number
    of ``iterations`` run, the largest normalised DTW cost over all (sequence, reference) pairs in
    each iteration (``max_costs``, one per iteration) and whether the iteration ``converged`` (soft:
    the maximum fell to the tolerance or stayed unchanged; hard: no template changed) rather than
    hitting the iteration limit."""

    template: MotionTemplate
    iterations: int
    max_costs: tuple[float, ...]
    converged: bool


def _iteration(templates: list[MotionTemplate], combine: Combine) -> tuple[list[MotionTemplate], float]:
    """One step of eq. (3.6): every template in turn as the reference, all replaced at once. Returns
    the new templates and the largest normalised cost (0 counts too: the reference against itself)."""
    new: list[MotionTemplate] = []
    worst = 0.0
    for k, ref in enumerate(templates):
        result, costs = average(ref, templates[:k] + templates[k + 1 :], combine)
        new.append(result)
        if costs.size:
            worst = max(worst, float(costs.max()))
    return new, worst


def learn_soft(
    examples: Sequence[Example], max_iterations: int = 10, tolerance: float = 0.005
) -> LearnedTemplate:
    """A soft MT (thesis §3.3.3) as the toolbox's strategy 5 learns it (reference facts, section d):
    iterate :func:`average` with the weighted mean until ``max_iterations`` are done, the largest
    normalised cost is <= ``tolerance``, or that largest cost is exactly the previous iteration's.
    Values lie in [0, 1]; every weight is < 1.5 and every weight but possibly the last >= 0.75."""
    if max_iterations < 1:
        raise ValueError(f"max_iterations must be at least 1, got {max_iterations}")
    templates = _templates(examples)
    max_costs: list[float] = []
    converged = False
    while len(max_costs) < max_iterations:
        templates, worst = _iteration(templates, "mean")
        previous = max_costs[-1] if max_costs else None
        max_costs.append(worst)
        if worst <= tolerance or worst == previous:
            converged = True
            break
    return LearnedTemplate(templates[0], len(max_costs), tuple(max_costs), converged)


def _same(a: MotionTemplate, b: MotionTemplate) -> bool:
    # weights are sums and quotients of floats: a fixed point may wobble in the last bits
    return (
        a.values.shape == b.values.shape
        and bool(np.array_equal(a.values, b.values))
        and bool(np.allclose(a.weights, b.weights, rtol=0.0, atol=1e-9))
    )


def learn_hard(examples: Sequence[Example], max_iterations: int = 20) -> LearnedTemplate:
    """A hard MT (thesis §3.3.1, eq. 3.4-3.6): iterate :func:`average` with ⊕ until no template
    changes (values equal, weights equal within 1e-9) or ``max_iterations`` are done. The examples
    must be over {0, 1} (or {0, ½, 1}); values stay in {0, ½, 1}, and by Claim 3.1 the result has
    DTW distance 0 under c& to every example after any number of iterations."""
    if max_iterations < 1:
        raise ValueError(f"max_iterations must be at least 1, got {max_iterations}")
    templates = _templates(examples)
    for t in templates:
        if not np.all(np.isin(t.values, (0.0, 0.5, 1.0))):
            raise ValueError("hard MTs are learned from values in {0, 0.5, 1}")
    max_costs: list[float] = []
    converged = False
    while len(max_costs) < max_iterations:
        new, worst = _iteration(templates, "oplus")
        max_costs.append(worst)
        if all(_same(a, b) for a, b in zip(templates, new, strict=True)):
            converged = True
        templates = new
        if converged:
            break
    return LearnedTemplate(templates[0], len(max_costs), tuple(max_costs), converged)


def quantise(t: MotionTemplate, delta: float = 0.1) -> MotionTemplate:
    """The toolbox's ``motionTemplateBool`` (reference facts, section d; thesis §3.3.3): values <=
    ``delta`` become 0, values >= ``1 - delta`` become 1, the rest ½ (don't care); weights kept."""
    if not 0 <= delta < 0.5:
        raise ValueError(f"delta must lie in [0, 0.5), got {delta}")
    v = t.values
    return MotionTemplate(np.where(v <= delta, 0.0, np.where(v >= 1 - delta, 1.0, 0.5)), t.weights)


# ---------------------------------------------------------------------------- automatic keyframes


def keyframe_scores(hard: MotionTemplate) -> FloatArray:
    """Thesis ch. 6: the score of each (feature set, column) of a 39-row hard MT, shape ``(3, K)`` in
    the set order lower, upper, mix: 3 points per 1 entry, 1 per 0 entry, none for ½."""
    _check_feature_count(hard)
    zero, one = KEYFRAME_SCORES
    points = np.where(hard.values == 1, one, np.where(hard.values == 0, zero, 0))
    return np.stack([points[SET_SLICES[s]].sum(axis=0) for s in FEATURE_SETS]).astype(np.float64)


def keyframe_columns(
    hard: MotionTemplate, count: int = 3, frames: IntArray | None = None, min_gap: int = 0
) -> list[tuple[int, FeatureSet]]:
    """The (column, feature set) pairs chosen as keyframes, sorted by column: greedily by score
    (:func:`keyframe_scores`; ties: earlier column, then set order lower, upper, mix), skipping a pair
    whose column is closer than ``max(1, K // (2 * count))`` columns to a chosen one, so the keyframes
    spread over the template and no column is chosen twice; at most ``count`` pairs. With ``frames``
    (shape ``(examples, K)``: the frame of each example aligned to each column, :func:`aligned_frames`)
    a pair is also skipped if in some example it lies fewer than ``min_gap`` frames from a chosen one
    (columns apart in the template may fall on one frame of a fast performance, leaving a gap of 0).
    Pairs scoring 0 (all ½) are not chosen; if every pair scores 0, the result is [(0, "lower")]."""
    if count < 1:
        raise ValueError(f"count must be at least 1, got {count}")
    scores = keyframe_scores(hard)
    k = hard.length
    separation = max(1, k // (2 * count))
    order = sorted(
        ((int(c), int(s)) for s, c in zip(*np.nonzero(scores > 0), strict=True)),
        key=lambda cs: (-scores[cs[1], cs[0]], cs[0], cs[1]),
    )
    chosen: list[tuple[int, FeatureSet]] = []
    for column, s in order:
        if len(chosen) == count:
            break
        if all(abs(column - c) >= separation for c, _ in chosen) and (
            frames is None
            or all(np.abs(frames[:, column] - frames[:, c]).min() >= min_gap for c, _ in chosen)
        ):
            chosen.append((column, FEATURE_SETS[s]))
    if not chosen:
        chosen.append((0, FEATURE_SETS[0]))
    return sorted(chosen)


def aligned_frames(hard: MotionTemplate, example: Example) -> IntArray:
    """For every column of ``hard``, the first frame of ``example`` (an ``(N, f)`` 0/1 matrix or a
    weight-1 template) aligned to it by full DTW under c& (eq. 3.2, thesis steps), shape ``(K,)``,
    non-decreasing. That DTW costs 0 for a hard MT learned from the example (Claim 3.1), so each
    frame agrees with its column on every 0/1 entry; otherwise this raises ValueError."""
    frames = as_template(example)
    if frames.features != hard.features:
        raise ValueError(f"the example has {frames.features} features, the template {hard.features}")
    if not np.all(np.isin(frames.values, (0.0, 1.0))):
        raise ValueError("keyframe positions are located in boolean (0/1) feature matrices")
    alignment = full_dtw(and_cost(hard.values, frames.values))
    if alignment.cost != 0:
        raise ValueError(f"the template's c& DTW distance to the example is {alignment.cost:g}, not 0")
    a, b = alignment.path[:, 0], alignment.path[:, 1]
    first = np.flatnonzero(np.concatenate([[True], a[1:] != a[:-1]]))
    return np.asarray(b[first], dtype=np.int64)


def gap_parameters(shortest: int, longest: int) -> tuple[int, float]:
    """Thesis ch. 6: the keyframe distance δ = √(m·M) and stiffness σ = √(m/M) for observed gaps
    m = ``shortest`` .. M = ``longest`` frames, in the form a :class:`KeyframeQuery` stores: δ rounded
    to an integer (half up), σ a decimal of 3 digits rounded down and then lowered by 0.001 until
    :func:`daemon.keyframes.gap_bounds` (δ, σ) contains [m, M]. m = 0 gives σ = 0 (no upper bound);
    m = M gives (m, 1.0). Example: (4, 16) -> (8, 0.5)."""
    m, big = int(shortest), int(longest)
    if not 0 <= m <= big:
        raise ValueError(f"need 0 <= shortest <= longest, got {shortest}, {longest}")
    delta = math.isqrt(m * big)
    if m * big > delta * delta + delta:  # round half up: √(mM) >= δ + ½ iff mM >= δ² + δ + ¼
        delta += 1
    if m == big:
        return delta, 1.0
    scale = 10**STIFFNESS_DIGITS
    units = math.isqrt(m * scale * scale // big)  # ⌊1000 √(m/M)⌋
    while units > 0:
        lo, hi = gap_bounds(delta, units / scale)
        if lo <= m and hi is not None and hi >= big:
            break
        units -= 1
    return delta, units / scale


@dataclass(frozen=True)
class Generalisation:
    """How far automatic keyframes reach beyond their training actors: a feature is fixed in a
    keyframe only if the hard MT fixes it to the same value in every column within ``window``
    columns of the keyframe's (a new person's timing differs), and at most ``fixed`` of them (None:
    all), those the hard MT keeps longest around the column (a new person's style differs in some);
    observed gaps m .. M become ⌊m / (1 + margin)⌋ .. ⌈M (1 + margin)⌉ before δ and σ are derived (a
    new person's tempo differs); keyframes lie at least ``min_gap`` frames apart in every example;
    ``count`` keyframes (None: the count asked for); a frame matches a keyframe when at most
    ``mismatches`` of its fixed features differ (a new person misses some; capped at one fewer than
    the keyframe fixes). The defaults are the thesis' rule (ch. 6), exact for the training clips."""

    window: int = 0
    margin: float = 0.0
    min_gap: int = 0
    fixed: int | None = None
    count: int | None = None
    mismatches: int = 0

    def __post_init__(self) -> None:
        if self.window < 0 or self.min_gap < 0 or not self.margin >= 0 or self.mismatches < 0:
            raise ValueError(f"window, margin, min_gap and mismatches must not be negative, got {self}")
        if self.fixed is not None and self.fixed < 1:
            raise ValueError(f"fixed must be at least 1, got {self.fixed}")
        if self.count is not None and self.count < 1:
            raise ValueError(f"count must be at least 1, got {self.count}")


THESIS_KEYFRAMES = Generalisation()


def stable_template(hard: MotionTemplate, window: int) -> MotionTemplate:
    """``hard`` with every entry that differs from an entry of the same feature within ``window``
    columns (either side, inside the template) set to ½: shape ``(f, K)`` as ``hard``."""
    values = hard.values
    stable = values.copy()
    k = hard.length
    for shift in range(1, min(window, k - 1) + 1):
        stable[:, shift:][values[:, shift:] != values[:, :-shift]] = 0.5
        stable[:, :-shift][values[:, :-shift] != values[:, shift:]] = 0.5
    return MotionTemplate(stable, hard.weights)


def most_stable(hard: MotionTemplate, column: int, rows: slice, count: int | None) -> FloatArray:
    """The entries ``rows`` of ``hard``'s ``column``, shape ``(rows,)``, with all but the ``count``
    0/1 entries that keep their value over the most columns on both sides (the smaller side counts;
    ties: the earlier feature) set to ½. None: all kept."""
    values = hard.values[rows]
    entries = values[:, column].copy()
    if count is None:
        return entries
    same = values == entries[:, None]  # (rows, K)
    left = np.argmin(np.concatenate([same[:, column::-1], np.zeros((len(entries), 1), bool)], axis=1), axis=1)
    right = np.argmin(np.concatenate([same[:, column:], np.zeros((len(entries), 1), bool)], axis=1), axis=1)
    extent = np.minimum(left, right)
    candidates = [i for i in np.argsort(-extent, kind="stable").tolist() if entries[i] != 0.5]
    entries[candidates[count:]] = 0.5
    return entries


def automatic_keyframes(
    hard: MotionTemplate,
    examples: Sequence[Example],
    count: int = 3,
    name: str = "",
    rate: float = DEFAULT_INDEX_RATE,
    generalisation: Generalisation = THESIS_KEYFRAMES,
    aligned: IntArray | None = None,
) -> KeyframeQuery:
    """Keyframes from a 39-row hard MT (thesis ch. 6): the columns and sets of
    :func:`keyframe_columns`, each keyframe the hard MT's entries of its set at its column. Each
    keyframe is located in every example (:func:`aligned_frames`; ``examples`` are the hard MT's
    training matrices at ``rate`` Hz); gap k's distances over the examples, m_k .. M_k, give
    (δ_k, σ_k) by :func:`gap_parameters`. The first keyframe sits at its column, each next one δ_k
    later; ``template_length`` is the hard MT's length. Every example then contains a hit of the
    query (no false negative on the training set). ``generalisation`` widens this for new people
    (:class:`Generalisation`: fewer fixed features, wider gaps, a minimum gap, its own count,
    mismatches); every training example still contains a hit. ``aligned``: :func:`aligned_frames`
    of every example, shape ``(examples, K)``, if already at hand."""
    if not examples:
        raise ValueError("automatic keyframes need the training examples")
    _check_feature_count(hard)
    g = generalisation
    count = count if g.count is None else g.count
    if aligned is None:
        aligned = np.stack([aligned_frames(hard, e) for e in examples])  # (examples, K)
    source = stable_template(hard, g.window) if g.window else hard
    chosen = keyframe_columns(source, count, aligned, g.min_gap)
    columns = np.asarray([c for c, _ in chosen], dtype=np.int64)
    frames = aligned[:, columns]  # (examples, keyframes)
    gaps = np.diff(frames, axis=1)
    params = [
        gap_parameters(int(lo / (1 + g.margin)), math.ceil(hi * (1 + g.margin)))
        for lo, hi in zip(gaps.min(axis=0), gaps.max(axis=0), strict=True)
    ]
    keyframes = []
    position = int(columns[0])
    for k, (column, feature_set) in enumerate(chosen):
        values = tuple(float(v) for v in most_stable(source, column, SET_SLICES[feature_set], g.fixed))
        stiffness = params[k][1] if k < len(params) else None
        exact = Keyframe(feature_set, values, position, stiffness)
        keyframes.append(dataclasses.replace(exact, mismatches=min(g.mismatches, exact.max_mismatches)))
        if k < len(params):
            position += params[k][0]
    return KeyframeQuery(name, tuple(keyframes), float(rate), hard.length)


def _check_feature_count(t: MotionTemplate) -> None:
    if t.features != N_FEATURES:
        raise ValueError(f"keyframes need a {N_FEATURES}-feature template, got {t.features} features")


# ----------------------------------------------------------------------------------- everything


@dataclass(frozen=True)
class LearnedClass:
    """Everything learned for one motion class: the soft MT, its quantisation (``quantised``), the
    hard MT and the automatic keyframe query (None when none were asked for)."""

    soft: LearnedTemplate
    quantised: MotionTemplate
    hard: LearnedTemplate
    keyframes: KeyframeQuery | None


def learn(
    examples: Sequence[npt.NDArray[np.generic]],
    *,
    delta: float = 0.1,
    keyframes: int = 3,
    name: str = "",
    rate: float = DEFAULT_INDEX_RATE,
    soft_iterations: int = 10,
    tolerance: float = 0.005,
    hard_iterations: int = 20,
    generalisation: Generalisation = THESIS_KEYFRAMES,
) -> LearnedClass:
    """Soft MT (:func:`learn_soft`), its :func:`quantise` by ``delta``, hard MT (:func:`learn_hard`)
    and :func:`automatic_keyframes` (``keyframes`` of them; 0 = none; widened by ``generalisation``)
    from ``(N, 39)`` boolean matrices at ``rate`` Hz."""
    soft = learn_soft(examples, soft_iterations, tolerance)
    hard = learn_hard(examples, hard_iterations)
    query = None
    if keyframes:
        query = automatic_keyframes(hard.template, examples, keyframes, name, rate, generalisation)
    return LearnedClass(soft, quantise(soft.template, delta), hard, query)
