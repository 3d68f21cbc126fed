"""Per-class retrieval thresholds learned by leave-one-actor-out (issue 12).

The thesis fixes one cost threshold τ = 0.1 for every class (§3.4, Table 3.1). A template learned
from some people matches a new person's performances at a cost that depends on the class, so each
class's τ is learned from its training data: for every actor holding clips of the class, the class
is learned (:func:`daemon.templates.learn`) from the other actors' clips, and the quantised MT is
matched by subsequence DTW (thesis Alg. 3.2 with free start and end; :mod:`daemon.dtw`, the
retrieval cost and steps of :mod:`daemon.retrieval`) over each of the left-out actor's clips: the
best cost over a clip of the class is a positive, over a clip of another class a negative. Pooled
over the folds, τ is chosen for the best F1 with recall ≥ 0.95 on the positives
(:func:`choose_tau`). The same folds measure how many of the left-out actor's clips the learned
keyframes (thesis ch. 6) keep, a clip being kept when the keyframe search (Alg. 4.1/4.2) over it
returns a component: learned by the thesis' rule they are exact for their training actors and lose
a new actor's clips, so each :class:`~daemon.templates.Generalisation` of :data:`GENERALISATIONS`
is tried and the one keeping ≥ 0.95 of the left-out clips in every fold with the fewest clips of
other classes is chosen (:func:`choose_generalisation`).

Pure: numpy in, frozen dataclasses out; no I/O.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from daemon.dtw import Steps, pack, retrieval_tables, subsequence_codes, to_cost
from daemon.index import SetIndex, build_set_index
from daemon.keyframes import KeyframeQuery, keyframe_search
from daemon.templates import (
    THESIS_KEYFRAMES,
    Generalisation,
    MotionTemplate,
    aligned_frames,
    automatic_keyframes,
    expand,
    learn,
)
from daemon.types import DEFAULT_INDEX_RATE, FEATURE_SETS, BoolArray, FeatureSet, FloatArray

MIN_RECALL = 0.95
SEPARATOR = 2
GIVEN = "given, not calibrated"


@dataclass(frozen=True)
class Calibration:
    """How a class's retrieval threshold ``tau`` was obtained: ``method`` in words, the number of
    leave-one-actor-out ``folds`` (0: τ was given, not calibrated), the pooled ``positives`` and
    ``negatives`` (clips costed) and the ``recall`` and ``precision`` τ gave on them (None when not
    calibrated)."""

    tau: float
    method: str
    folds: int = 0
    positives: int = 0
    negatives: int = 0
    recall: float | None = None
    precision: float | None = None

    @property
    def calibrated(self) -> bool:
        return self.folds > 0


def given(tau: float, why: str = "") -> Calibration:
    """A τ taken as given (``why``: the reason, shown after the method)."""
    return Calibration(tau, f"{GIVEN} ({why})" if why else GIVEN)


@dataclass(frozen=True)
class Choice:
    """A threshold and what it gives on the pooled costs: recall, precision and F1; ``feasible``:
    whether the recall reaches the minimum asked for."""

    tau: float
    recall: float
    precision: float
    f1: float
    feasible: bool


def choose_tau(
    positives: npt.ArrayLike, negatives: npt.ArrayLike, *, min_recall: float = MIN_RECALL, fallback: float
) -> Choice | None:
    """The threshold with the best F1 = 2TP / (2TP + FP + FN) subject to recall TP / P ≥
    ``min_recall``, a hit being a cost ≤ τ. ``positives`` ``(P,)`` and ``negatives`` ``(Q,)`` are
    best-match costs (``inf``: no match at all). None when there is no finite positive.

    The candidates are the finite positive costs: F1 only changes at a cost, and raising τ from a
    positive cost to the next one adds a true positive, which always raises F1, so the best τ sits at
    a positive cost whose next larger cost is a negative's. Ties in F1: the larger cost (more recall
    for a new person). The chosen τ is then moved midway to the next larger negative cost, which
    leaves every count unchanged and keeps the same margin to both sides; with no negative above it,
    τ is the larger of that cost and ``fallback``. If the recall cannot reach ``min_recall`` (too
    many positives never match), τ is the largest finite positive cost, ``feasible`` False."""
    pos = np.sort(np.asarray(positives, dtype=np.float64))
    neg = np.sort(np.asarray(negatives, dtype=np.float64))
    finite = pos[np.isfinite(pos)]
    if finite.size == 0:
        return None
    total = pos.size
    need = math.ceil(min_recall * total - 1e-9)
    candidates = np.unique(finite)
    tp = np.searchsorted(pos, candidates, "right")
    fp = np.searchsorted(neg, candidates, "right")
    f1 = 2 * tp / (2 * tp + fp + (total - tp))
    ok = tp >= need
    best = int(np.flatnonzero(ok & (f1 == f1[ok].max()))[-1]) if ok.any() else len(candidates) - 1
    cost = float(candidates[best])
    above = neg[neg > cost]
    limit = float(above[0]) if above.size else math.inf
    tau = (cost + limit) / 2 if math.isfinite(limit) else max(cost, fallback)
    t, f = int(tp[best]), int(fp[best])
    return Choice(tau, t / total, t / (t + f), float(f1[best]), bool(ok[best]))


# ------------------------------------------------------------------------------------ the costs


def clip_costs(template: MotionTemplate, clips: Sequence[BoolArray], steps: Steps) -> FloatArray:
    """The best subsequence-DTW cost of the quantised ``template`` (expanded by its weights, as
    :func:`daemon.retrieval.template_search` matches it) over each clip, ``(n,)`` for ``n`` clips of
    shape ``(N_i, 39)``: min over b of Δ(b) (thesis Alg. 3.2, free start and end), ``inf`` when no
    path fits (a clip less than half the template long under the toolbox's steps). The clips are
    laid out one after another with blocked columns between them, so one pass costs them all."""
    if not clips:
        return np.zeros(0)
    t = expand(template)
    sizes = np.asarray([len(c) for c in clips], dtype=np.int64)
    offsets = np.concatenate([[0], np.cumsum(sizes + SEPARATOR)]).astype(np.int64)
    codes = np.zeros(int(offsets[-1]), dtype=np.uint64)
    blocked = np.ones(len(codes), dtype=bool)
    for clip, at, size in zip(clips, offsets[:-1], sizes, strict=True):
        codes[at : at + size] = pack(clip)
        blocked[at : at + size] = False
    delta, _ = subsequence_codes(retrieval_tables(t.values, t.weights), codes, blocked, steps)
    cost = to_cost(delta)
    return np.asarray([cost[at : at + size].min() for at, size in zip(offsets[:-1], sizes, strict=True)])


ClipSets = tuple[Mapping[FeatureSet, SetIndex], list[int]]
"""Clips indexed for the keyframe search: the set indexes and each clip's length."""


def clip_sets(clips: Sequence[BoolArray]) -> ClipSets:
    """The feature-set indexes of clips ``(N_i, 39)``, each clip a document."""
    return {s: build_set_index(clips, s) for s in FEATURE_SETS}, [len(c) for c in clips]


def keyframes_kept(query: KeyframeQuery, clips: ClipSets, rate: float) -> npt.NDArray[np.bool_]:
    """For each clip of :func:`clip_sets` at ``rate`` Hz, whether the keyframe search of ``query``
    (thesis Alg. 4.1/4.2, no extension) returns a component in it; shape ``(n,)``."""
    sets, lengths = clips
    if not lengths:
        return np.zeros(0, dtype=bool)
    hits = keyframe_search(sets, lengths, query, rate)
    return np.isin(np.arange(len(lengths)), hits.doc)


GENERALISATIONS = tuple(
    Generalisation(w, r, g, n)
    for n in (None, 5, 3)
    for w in (0, 1, 2)
    for r in (0.0, 0.25, 0.5, 1.0, 2.0)
    for g in (0, 2)
)
"""The keyframe generalisations tried, the thesis' rule first."""

MOST_GENERAL = Generalisation(window=2, margin=2.0, min_gap=0, fixed=3)
"""The most general of :data:`GENERALISATIONS` (fewest fixed features, each stable over the widest
window, gaps widened the most): the keyframes of a class whose folds cannot show that any
generalisation keeps a new person's clips (one actor, or none kept enough in some fold). Keyframes
only pre-select; the template's DTW decides, so a class had better give a few candidates too many
than none."""


# ------------------------------------------------------------------------------------ the folds


@dataclass(frozen=True)
class KeyframeTrial:
    """Keyframes learned with ``generalisation`` in one fold: which of the left-out actor's clips of
    the class they keep (``positives``, ``(P,)``) and how many of its other clips (``negatives``)."""

    generalisation: Generalisation
    positives: npt.NDArray[np.bool_]
    negatives: int


@dataclass(frozen=True)
class Fold:
    """One class with one actor left out: the best costs of the class's template (learned on the
    other actors) over the actor's clips of the class (``positive_costs``, ``(P,)``) and of the other
    classes (``negative_costs``, ``(Q,)``), and the keyframes learned with each of ``generalisations``
    (``trials``; empty when no keyframes are learned)."""

    actor: str
    positive_costs: FloatArray
    negative_costs: FloatArray
    trials: tuple[KeyframeTrial, ...]


@dataclass(frozen=True)
class ClassCalibration:
    """A class's :class:`Calibration`, the keyframe :class:`Generalisation` chosen by
    :func:`choose_generalisation` and the folds both came from."""

    calibration: Calibration
    keyframes: Generalisation
    folds: tuple[Fold, ...]


Labelled = Mapping[str, Sequence[tuple[str, BoolArray]]]
"""Per class, its examples as (actor, ``(N, 39)`` boolean features at the learning rate)."""


def folds(
    examples: Labelled,
    name: str,
    *,
    delta: float = 0.1,
    keyframes: int = 3,
    steps: Steps = "toolbox",
    rate: float = DEFAULT_INDEX_RATE,
    generalisations: Sequence[Generalisation] = GENERALISATIONS,
) -> list[Fold]:
    """The leave-one-actor-out folds of class ``name``: one per actor holding clips of it whose
    other actors hold clips of it too (in order of first appearance)."""
    actors = list(dict.fromkeys(a for a, _ in examples[name]))
    out = []
    for actor in actors:
        training = [m for a, m in examples[name] if a != actor]
        if not training:
            continue
        learned = learn(training, delta=delta, keyframes=0, name=name, rate=rate)
        positives = [m for a, m in examples[name] if a == actor]
        negatives = [m for other, items in examples.items() if other != name for a, m in items if a == actor]
        trials = []
        if keyframes:
            pos_sets, neg_sets = clip_sets(positives), clip_sets(negatives)
            hard = learned.hard.template
            aligned = np.stack([aligned_frames(hard, m) for m in training])
            for g in generalisations:
                query = automatic_keyframes(hard, training, keyframes, name, rate, g, aligned)
                kept = keyframes_kept(query, pos_sets, rate)
                trials.append(KeyframeTrial(g, kept, int(keyframes_kept(query, neg_sets, rate).sum())))
        template = learned.quantised
        out.append(
            Fold(
                actor,
                clip_costs(template, positives, steps),
                clip_costs(template, negatives, steps),
                tuple(trials),
            )
        )
    return out


def retention(found: Sequence[Fold], g: Generalisation) -> list[float]:
    """The share of the left-out clips of the class that the keyframes learned with ``g`` keep,
    fold by fold."""
    return [float(t.positives.mean()) for f in found for t in f.trials if t.generalisation == g]


def choose_generalisation(found: Sequence[Fold], min_kept: float = MIN_RECALL) -> Generalisation:
    """The keyframe generalisation that keeps at least ``min_kept`` of the left-out clips of the
    class in every fold and, among those, the fewest clips of other classes (ties: the earlier one
    tried, the least widened). If none keeps enough in every fold, or there are no folds:
    :data:`MOST_GENERAL`. The thesis' rule when keyframes were not tried (no trials)."""
    if not found:
        return MOST_GENERAL
    tried = [t.generalisation for t in found[0].trials]
    if not tried:
        return THESIS_KEYFRAMES
    scores = []
    for i, g in enumerate(tried):
        others = sum(t.negatives for f in found for t in f.trials if t.generalisation == g)
        scores.append((min(retention(found, g)) >= min_kept, -others, -i))
    best = max(range(len(tried)), key=lambda i: scores[i])
    return tried[best] if scores[best][0] else MOST_GENERAL


def calibrate_class(
    examples: Labelled,
    name: str,
    *,
    tau: float = 0.1,
    delta: float = 0.1,
    keyframes: int = 3,
    steps: Steps = "toolbox",
    rate: float = DEFAULT_INDEX_RATE,
    min_recall: float = MIN_RECALL,
) -> ClassCalibration:
    """Class ``name``'s τ by leave-one-actor-out (:func:`folds`, pooled, :func:`choose_tau`); the
    learning parameters are those the class will be learned with. Falls back to the given ``tau``
    (and says why in the method) when the class's clips come from one actor or no positive ever
    matches."""
    found = folds(examples, name, delta=delta, keyframes=keyframes, steps=steps, rate=rate)
    actors = len({a for a, _ in examples[name]})
    if not found:
        why = "one actor" if actors < 2 else "no fold"
        return ClassCalibration(given(tau, f"{why}: no leave-one-actor-out"), MOST_GENERAL, ())
    generalisation = choose_generalisation(found, min_recall)
    pos = np.concatenate([f.positive_costs for f in found])
    neg = np.concatenate([f.negative_costs for f in found])
    choice = choose_tau(pos, neg, min_recall=min_recall, fallback=tau)
    if choice is None:
        why = f"no left-out clip matched in {len(found)} folds"
        return ClassCalibration(given(tau, why), generalisation, tuple(found))
    rule = f"best F1 with recall >= {min_recall:g}" if choice.feasible else "largest positive cost"
    method = (
        f"leave-one-actor-out over {actors} actors ({len(found)} folds): {rule}, "
        "midway to the next negative cost"
    )
    calibration = Calibration(
        choice.tau, method, len(found), len(pos), len(neg), choice.recall, choice.precision
    )
    return ClassCalibration(calibration, generalisation, tuple(found))


def calibrate(
    examples: Labelled,
    *,
    tau: float = 0.1,
    delta: float = 0.1,
    keyframes: int = 3,
    steps: Steps = "toolbox",
    rate: float = DEFAULT_INDEX_RATE,
    min_recall: float = MIN_RECALL,
) -> dict[str, ClassCalibration]:
    """:func:`calibrate_class` for every class of ``examples``, in their order."""
    return {
        name: calibrate_class(
            examples,
            name,
            tau=tau,
            delta=delta,
            keyframes=keyframes,
            steps=steps,
            rate=rate,
            min_recall=min_recall,
        )
        for name in examples
    }


# ------------------------------------------------------------------- learned vs published keyframes


@dataclass(frozen=True)
class HeldOutKeyframes:
    """Keyframes on one left-out actor's clips: ``kept`` of the ``clips`` of the class hold a hit
    (a keyframe-search component inside the clip) and ``false`` of the ``others`` clips of other
    classes do."""

    actor: str
    kept: int
    clips: int
    false: int
    others: int


def held_out_learned(found: ClassCalibration) -> list[HeldOutKeyframes]:
    """The learned keyframes, generalised as calibration chose (``found.keyframes``), fold by fold:
    in each fold learned on the other actors and run on the left-out actor's clips."""
    out = []
    for f in found.folds:
        for t in f.trials:
            if t.generalisation == found.keyframes:
                kept, n = int(t.positives.sum()), len(t.positives)
                others = len(f.negative_costs)
                out.append(HeldOutKeyframes(f.actor, kept, n, t.negatives, others))
    return out


def held_out_query(
    examples: Labelled,
    name: str,
    query: KeyframeQuery,
    actors: Sequence[str],
    rate: float = DEFAULT_INDEX_RATE,
) -> list[HeldOutKeyframes]:
    """A fixed keyframe ``query`` (e.g. the published one) on the clips :func:`folds` leaves out for
    each of ``actors``: the actor's clips of class ``name`` and of the other classes."""
    out = []
    for actor in actors:
        positives = [m for a, m in examples[name] if a == actor]
        negatives = [m for other, items in examples.items() if other != name for a, m in items if a == actor]
        kept = keyframes_kept(query, clip_sets(positives), rate)
        false = keyframes_kept(query, clip_sets(negatives), rate)
        out.append(HeldOutKeyframes(actor, int(kept.sum()), len(positives), int(false.sum()), len(negatives)))
    return out


def prefer_published(learned: Sequence[HeldOutKeyframes], published: Sequence[HeldOutKeyframes]) -> bool:
    """Whether the published keyframes replace the learned ones: pooled over the same folds, they
    keep at least as many left-out clips of the class and hit no more clips of other classes."""
    kept = sum(h.kept for h in published) >= sum(h.kept for h in learned)
    return kept and sum(h.false for h in published) <= sum(h.false for h in learned)
