"""How each class is recognised, learned from its training data by leaving groups out (issue 20).

The thesis fixes one cost threshold τ = 0.1 for every class (§3.4, Table 3.1) and keyframes exact
for the training clips (ch. 6). A template learned from some people matches a new person at a cost
that depends on the class, and exact keyframes miss a new person's motions; both are learned here
from folds that leave a group out: the people (actors) when the training data names at least two,
otherwise up to :data:`TAKE_GROUPS` groups of one person's examples (:func:`groups`).

For each fold, every class is learned (:func:`daemon.learn.templates.learn`) from the other groups'
examples, and the left-out group's examples of all classes, joined one after another in a
shuffled order, become a stream (:func:`fold_stream`): motions, the transitions between them and
pieces of other motions, as the live recogniser sees them. Each class's template runs as a
subsequence DTW over the whole stream (thesis Alg. 3.2, free start and end; the retrieval cost and
steps of :mod:`daemon.search.retrieval`), and its local minima are *candidates*, as in the live
recogniser (:class:`daemon.recognizer.CodeRecognizer`): a candidate is *beaten* by a cheaper one
(order cost, end, template) of the same motion (more than half of the shorter range shared) of its own
class, or of another class whose τ it is within. What is not beaten is a detection; it is right
when at least half of it lies inside a motion of its class (:func:`outcomes`).

**τ** (:func:`thresholds`): per class, the costs of the right detections (for each motion of the
class the cheapest, ``inf`` if none: its *positives*) and of the wrong ones (*negatives*), pooled
over the folds, give the τ of the best F1 subject to recall ≥ :data:`MIN_RECALL`
(:func:`choose_tau`), placed a fraction ``position`` of the way from the positive cost it needs to
the next negative cost. Whether another class's candidate counts as a rival depends on that class's
τ, so the thresholds are found again with the rivals' τ of the round before (:data:`ROUNDS` rounds,
the first without rivals). The ``position`` is chosen by nested folds (:func:`choose_position`):
each fold's detections are scored with the τ the *other* folds give, for each of
:data:`POSITIONS`, and the one with the best F1 over all classes and folds is taken, so τ is placed
where it carried to a person the thresholds had not seen (over one person's takes, which say
nothing of another person, the middle). A class whose examples fall into two styles gets two
templates, each with its own τ (:func:`two_clusters`, :func:`calibrate`).

**Keyframes** (:func:`choose_gate`): the automaton is a gate that lets a stream-wide match of its
class count only where a keyframe match overlaps it. In each fold the class's keyframes are learned
with each :class:`~daemon.learn.templates.Generalisation` of :data:`GENERALISATIONS` and run over the
fold's stream; a gate must keep at least :data:`MIN_KEPT` of the motions the class finds without
it, in every fold, and keep out some of its wrong detections. A class that makes no wrong detection
in the folds, or whose wrong detections no gate keeps out, is recognised from the stream-wide DTW
alone (mode ``dtw``); the reason is kept.

Pure: numpy in, frozen dataclasses out; no I/O.
"""

from __future__ import annotations

import dataclasses
import math
import random
from collections.abc import Callable, Collection, Mapping, Sequence
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
import numpy.typing as npt

from daemon.dtw import (
    Steps,
    accumulated,
    fixed,
    l1_cost,
    local_minima,
    pack,
    retrieval_tables,
    subsequence_codes,
    to_cost,
)
from daemon.keyframes import KeyframeQuery
from daemon.learn.templates import Generalisation, aligned_frames, automatic_keyframes, learn
from daemon.library import Calibration, given
from daemon.recognizer import completions, keyframe_windows, learned_extent, window_extent
from daemon.search.index import SetIndex, build_set_index
from daemon.search.keyframes import keyframe_search
from daemon.templates import MotionTemplate, expand
from daemon.types import (
    DEFAULT_INDEX_RATE,
    DEFAULT_MAX_GAP_S,
    FEATURE_SETS,
    BoolArray,
    FeatureSet,
    FloatArray,
)

MIN_RECALL = 0.95
MIN_KEPT = 0.98
POSITIONS = (0.25, 0.5, 0.75)
"""Where τ may sit between the positive cost it needs and the next negative cost (0: at the
positive, 1: at the negative); nested folds choose."""
DEFAULT_POSITION = 0.5
ROUNDS = 3
CAP = 0.5
"""Candidates costlier than this are not collected: no τ is chosen above it."""
TAKE_GROUPS = 3
MIN_MEMBER = 3
"""The fewest examples a second template of a class is learned from."""


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
    positives: npt.ArrayLike,
    negatives: npt.ArrayLike,
    *,
    min_recall: float = MIN_RECALL,
    fallback: float,
    position: float = DEFAULT_POSITION,
) -> Choice | None:
    """The threshold with the best F1 = 2TP / (2TP + FP + FN) subject to recall TP / P ≥
    ``min_recall``, a hit being a cost ≤ τ. ``positives`` ``(P,)`` and ``negatives`` ``(Q,)`` are
    best-match costs (``inf``: no match at all). None when there is no finite positive.

    The candidates are the finite positive costs: F1 only changes at a cost, and raising τ from a
    positive cost to the next one adds a true positive, which always raises F1, so the best τ sits at
    a positive cost whose next larger cost is a negative's. Ties in F1: the larger cost (more recall
    for a new person). The chosen τ is then moved the fraction ``position`` of the way to the next
    larger negative cost, which leaves every count unchanged; with no negative above it, τ is the
    larger of that cost and ``fallback``. If the recall cannot reach ``min_recall`` (too many
    positives never match), τ is the largest finite positive cost, ``feasible`` False."""
    if not 0 <= position < 1:
        raise ValueError(f"position must lie in [0, 1), got {position}")
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
    tau = cost + position * (limit - cost) if math.isfinite(limit) else max(cost, fallback)
    t, f = int(tp[best]), int(fp[best])
    return Choice(tau, t / total, t / (t + f), float(f1[best]), bool(ok[best]))


# ------------------------------------------------------------------------------------ the groups


def groups(actors: Sequence[str], classes: Sequence[str]) -> tuple[list[str], str]:
    """The fold group of each example (``actors[i]`` and ``classes[i]``: its person and class) and
    what the groups are: the actors when there are at least two; else the examples of each class
    dealt in turn into up to :data:`TAKE_GROUPS` groups (``"take 1"``, ...), so every group holds
    some of every class that has enough examples."""
    if len(set(actors)) >= 2:
        return list(actors), "actors"
    dealt: dict[str, int] = {}
    out = []
    for name in classes:
        k = dealt.get(name, 0)
        dealt[name] = k + 1
        out.append(f"take {k % TAKE_GROUPS + 1}")
    return out, f"groups of one person's examples (one actor: at most {TAKE_GROUPS})"


# ------------------------------------------------------------------------------------ the folds


class Candidate(NamedTuple):
    """A local minimum of a template's subsequence DTW over a fold's stream: ``cost``, ``end``, the
    template (its index in :attr:`Fold.owner`) and ``start``; ordered as the live recogniser orders
    candidates."""

    cost: float
    end: int
    template: int
    start: int


@dataclass(frozen=True)
class KeyframeTrial:
    """Keyframes learned with ``generalisation`` in one fold: which of the left-out group's
    examples of the class they keep (``positives``, ``(P,)``: a hit in the clip alone and a match
    completed inside it when the examples come back to back, :func:`kept_in_a_row`)."""

    generalisation: Generalisation
    query: KeyframeQuery
    positives: npt.NDArray[np.bool_]
    length: int = 1
    """The columns of the fold's template the keyframes' positions refer to."""
    extent: tuple[int, int] | None = None
    """What the fold's training examples need of a window (:func:`daemon.recognizer.learned_extent`)."""


@dataclass(frozen=True)
class Fold:
    """One group left out: its examples joined into a stream (``codes``) whose motions are
    ``truth`` (class index, first frame, last frame); the class of each template learned from the
    other groups (``owner``; at first template k is class k's, absent when the class has no
    training examples in the fold) and their ``candidates`` over the stream (sorted); per class
    the keyframe ``trials`` (empty when no keyframes are learned)."""

    group: str
    codes: npt.NDArray[np.uint64]
    truth: tuple[tuple[int, int, int], ...]
    owner: tuple[int, ...]
    candidates: tuple[Candidate, ...]
    learned: frozenset[int]
    trials: Mapping[int, tuple[KeyframeTrial, ...]]
    same: npt.NDArray[np.bool_]
    """:func:`rivals` of the candidates."""


def make_fold(
    group: str,
    codes: npt.NDArray[np.uint64],
    truth: Sequence[tuple[int, int, int]],
    owner: Sequence[int],
    candidates: Sequence[Candidate],
    learned: frozenset[int],
    trials: Mapping[int, tuple[KeyframeTrial, ...]],
) -> Fold:
    """A :class:`Fold`, its candidates sorted and their :func:`rivals` found."""
    ordered = tuple(sorted(candidates))
    return Fold(group, codes, tuple(truth), tuple(owner), ordered, learned, trials, rivals(ordered))


Labelled = Mapping[str, Sequence[tuple[str, BoolArray]]]
"""Per class, its examples as (group, ``(N, 39)`` boolean features at the learning rate)."""


def fold_stream(examples: Labelled, group: str) -> tuple[npt.NDArray[np.uint64], list[tuple[int, int, int]]]:
    """The examples of ``group`` of every class, in an order shuffled by the group's name, joined
    into one stream: its packed codes ``(N,)`` and each example's (class index, first, last frame)."""
    names = list(examples)
    items = [(k, m) for k, name in enumerate(names) for g, m in examples[name] if g == group]
    random.Random(group).shuffle(items)
    truth, at = [], 0
    for k, m in items:
        truth.append((k, at, at + len(m) - 1))
        at += len(m)
    codes = pack(np.concatenate([m for _, m in items])) if items else np.zeros(0, dtype=np.uint64)
    return codes, truth


def stream_candidates(
    template: MotionTemplate, codes: npt.NDArray[np.uint64], steps: Steps, index: int
) -> list[Candidate]:
    """The local minima at or below :data:`CAP` of ``template``'s subsequence DTW over ``codes``
    (expanded by its weights, as the live recogniser matches it), as template ``index``'s."""
    if len(codes) == 0:
        return []
    t = expand(template)
    delta, start = subsequence_codes(retrieval_tables(t.values, t.weights), codes, None, steps)
    return [Candidate(m.cost, m.end, index, m.start) for m in local_minima(to_cost(delta), start, CAP)]


def clip_costs(template: MotionTemplate, clips: Sequence[BoolArray], steps: Steps) -> FloatArray:
    """The best subsequence-DTW cost of the quantised ``template`` (expanded by its weights) over
    each clip ``(N_i, 39)``, ``(n,)``: min over b of Δ(b) (thesis Alg. 3.2, free start and end),
    ``inf`` when no path fits. The clips are laid out with two blocked columns between them, so one
    pass costs them all."""
    if not clips:
        return np.zeros(0)
    t = expand(template)
    sizes = np.asarray([len(c) for c in clips], dtype=np.int64)
    offsets = np.concatenate([[0], np.cumsum(sizes + 2)]).astype(np.int64)
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


def kept_in_a_row(
    query: KeyframeQuery, examples: Sequence[npt.NDArray[np.uint64]], rate: float, max_gap: int
) -> npt.NDArray[np.bool_]:
    """For each example (its index-rate codes), whether the live automaton of ``query``
    (:func:`daemon.recognizer.completions`) completes a match inside it when the examples are
    performed back to back, as repetitions come in a take (a keyframe that holds from one repetition
    into the next is one run there, and a clip cut out alone starts every run at its first frame);
    shape ``(n,)``."""
    if not examples:
        return np.zeros(0, dtype=bool)
    codes = np.concatenate(examples).tolist()
    ends = np.cumsum([len(e) for e in examples])
    done = np.zeros(len(examples), dtype=bool)
    for _, j in completions(query, rate, max_gap, codes):
        done[int(np.searchsorted(ends, j, side="right"))] = True
    return done


DESIGNS = tuple(Generalisation(w, r, 2, n) for n in (None, 4) for w in (0, 2) for r in (0.5, 1.0, 2.0))
"""The keyframe designs tried (count and mismatches aside): every feature the hard MT keeps or the
4 it keeps longest, stable over 0 or 2 columns, gaps widened by half, once or twice their spread."""
COUNTS = (-1, 0, 1, 2)
"""The keyframe counts tried, relative to the count asked for."""
MISMATCHES = (0, 1, 2, 3)
"""The mismatches a keyframe may tolerate, tried in this order: the fewest that hold are kept."""


def designs(count: int) -> tuple[Generalisation, ...]:
    """Every :data:`DESIGNS` entry with each count of :data:`COUNTS` (around ``count``, at least 1)
    and each tolerance of :data:`MISMATCHES`, in that order of nesting (tolerance innermost)."""
    counts = sorted({max(1, count + c) for c in COUNTS})
    return tuple(
        dataclasses.replace(d, count=c, mismatches=m) for d in DESIGNS for c in counts for m in MISMATCHES
    )


def folds(
    examples: Labelled,
    *,
    delta: float = 0.1,
    keyframes: int = 3,
    steps: Steps = "toolbox",
    rate: float = DEFAULT_INDEX_RATE,
    generalisations: Sequence[Generalisation] | None = None,
    progress: Callable[[str], object] | None = None,
) -> list[Fold]:
    """One :class:`Fold` per group (in order of first appearance) whose stream holds at least one
    example of a class that the other groups hold examples of too. Keyframes are tried with each of
    ``generalisations`` (default: :func:`designs` around ``keyframes``)."""
    names = list(examples)
    tried = designs(keyframes) if generalisations is None else tuple(generalisations)
    max_gap = max(1, round(DEFAULT_MAX_GAP_S * rate))
    order = list(dict.fromkeys(g for items in examples.values() for g, _ in items))
    out = []
    for group in order:
        codes, truth = fold_stream(examples, group)
        candidates: list[Candidate] = []
        trials: dict[int, tuple[KeyframeTrial, ...]] = {}
        learned = set()
        for k, name in enumerate(names):
            training = [m for g, m in examples[name] if g != group]
            if not training:
                continue
            learned.add(k)
            result = learn(training, delta=delta, keyframes=0, name=name, rate=rate)
            candidates += stream_candidates(result.quantised, codes, steps, k)
            positives = [m for g, m in examples[name] if g == group]
            if keyframes and positives:
                pos_sets = clip_sets(positives)
                hard = result.hard.template
                aligned = np.stack([aligned_frames(hard, m) for m in training])
                made = []
                codes_of = [pack(m).tolist() for m in training]
                in_a_row = [pack(m) for m in positives]
                for g in tried:
                    query = automatic_keyframes(hard, training, keyframes, name, rate, g, aligned)
                    extent = learned_extent(query, codes_of, rate, max_gap)
                    kept = keyframes_kept(query, pos_sets, rate) & kept_in_a_row(
                        query, in_a_row, rate, max_gap
                    )
                    made.append(KeyframeTrial(g, query, kept, hard.length, extent))
                trials[k] = tuple(made)
        if not any(k in learned for k, _, _ in truth):
            continue
        owner = tuple(range(len(names)))
        out.append(make_fold(group, codes, truth, owner, candidates, frozenset(learned), trials))
        if progress is not None:
            progress(
                f"[fold {order.index(group) + 1}/{len(order)}] {group} left out: {len(learned)} classes "
                "learned "
                f"from the others, run over its stream ({len(codes)} frames)"
            )
    return out


def with_members(fold: Fold, k: int, templates: Sequence[MotionTemplate | None], steps: Steps) -> Fold:
    """``fold`` with class ``k``'s templates replaced by ``templates`` (None: a style without
    training examples in the fold: a template without candidates), appended to the fold's
    templates in their order. The replaced templates keep their indices, owned by no class (-1)."""
    owner = [-1 if c == k else c for c in fold.owner]
    kept = [x for x in fold.candidates if fold.owner[x.template] != k]
    for t in templates:
        if t is not None:
            kept += stream_candidates(t, fold.codes, steps, len(owner))
        owner.append(k)
    return make_fold(fold.group, fold.codes, fold.truth, owner, kept, fold.learned, fold.trials)


# -------------------------------------------------------------------------------- the detections


def same_motion(a: tuple[int, int], b: tuple[int, int]) -> bool:
    """:func:`daemon.recognizer.same_motion`: more than half of the shorter range shared."""
    shared = min(a[1], b[1]) - max(a[0], b[0]) + 1
    return 2 * shared > min(a[1] - a[0], b[1] - b[0]) + 1


def inside(start: int, end: int, first: int, last: int) -> bool:
    """At least half of ``start .. end`` lies in ``first .. last``."""
    return 2 * (min(end, last) - max(start, first) + 1) >= end - start + 1


Taus = Sequence[float | None]
"""Per template of a fold, its τ (None: no rival yet, detects nothing)."""


def rivals(c: Sequence[Candidate]) -> npt.NDArray[np.bool_]:
    """Which pairs of candidates (sorted) are the same motion, the later one in the order (row)
    against each one before it (column): shape ``(candidates, candidates)``, lower triangular, made
    in blocks of rows."""
    n = len(c)
    end = np.array([x.end for x in c], dtype=np.int64)
    start = np.array([x.start for x in c], dtype=np.int64)
    out = np.zeros((n, n), dtype=bool)
    for lo in range(0, n, 512):
        hi = min(n, lo + 512)
        shared = (
            np.minimum(end[lo:hi, None], end[None, :]) - np.maximum(start[lo:hi, None], start[None, :]) + 1
        )
        shorter = np.minimum((end - start)[lo:hi, None], (end - start)[None, :]) + 1
        out[lo:hi] = (2 * shared > shorter) & (np.arange(n)[None, :] < np.arange(lo, hi)[:, None])
    return out


def survivors(fold: Fold, taus: Taus, present: npt.NDArray[np.bool_] | None = None) -> npt.NDArray[np.bool_]:
    """Which of the fold's candidates are not beaten when the templates' thresholds are ``taus``:
    beaten by a candidate before it in the order (cost, end, template) that is the same motion
    (:func:`rivals`), of its class or within its own template's τ; shape ``(candidates,)``. With
    ``present`` (shape ``(candidates,)``), only those candidates exist (the others are found by no
    DTW: outside their keyframe-first class's windows), to beat or to survive."""
    c = fold.candidates
    if not c:
        return np.zeros(0, dtype=bool)
    cost = np.array([x.cost for x in c])
    tpl = np.array([x.template for x in c], dtype=np.int64)
    cls = np.asarray(fold.owner, dtype=np.int64)[tpl]
    limit = np.array([math.inf if t is None else t for t in taus], dtype=np.float64)
    rival = np.array([t is not None for t in taus], dtype=bool)
    live = rival[tpl] & (cost <= limit[tpl])
    beats = np.logical_and(fold.same, (cls[:, None] == cls[None, :]) | live[None, :])
    if present is None:
        return np.asarray(~beats.any(axis=1), dtype=bool)
    return np.asarray(present & ~(beats & present[None, :]).any(axis=1), dtype=bool)


def motion_of(fold: Fold, x: Candidate) -> int | None:
    """The index in ``fold.truth`` of the motion of ``x``'s class that holds at least half of it."""
    k = fold.owner[x.template]
    for i, (c, first, last) in enumerate(fold.truth):
        if c == k and inside(x.start, x.end, first, last):
            return i
    return None


def outcomes(fold: Fold, taus: Taus) -> tuple[list[list[float]], list[list[float]]]:
    """Per template, the fold's positives and negatives when the thresholds are ``taus``: the
    candidates that :func:`survivors` keeps are the detections, a detection right when it lies in a
    motion of its class (:func:`motion_of`). Each motion of a learned class is one positive of the
    class's template whose right detection is the cheapest (its cost; ``inf`` of the first template
    if it has none); each wrong detection a negative of its template."""
    keep = survivors(fold, taus)
    best: list[tuple[float, int] | None] = [None] * len(fold.truth)
    negatives: list[list[float]] = [[] for _ in fold.owner]
    for x, ok in zip(fold.candidates, keep, strict=True):
        if ok:
            i = motion_of(fold, x)
            if i is None:
                negatives[x.template].append(x.cost)
            elif best[i] is None or x.cost < best[i][0]:  # type: ignore[index]
                best[i] = (x.cost, x.template)
    positives: list[list[float]] = [[] for _ in fold.owner]
    first: dict[int, int] = {}
    for t, k in enumerate(fold.owner):
        first.setdefault(k, t)
    for (k, _, _), b in zip(fold.truth, best, strict=True):
        if k in fold.learned:
            if b is None:
                positives[first[k]].append(math.inf)
            else:
                positives[b[1]].append(b[0])
    return positives, negatives


def thresholds(
    found: Sequence[Fold],
    *,
    position: float = DEFAULT_POSITION,
    min_recall: float = MIN_RECALL,
    fallback: float = 0.1,
) -> list[Choice | None]:
    """Each template's :func:`choose_tau` over the pooled :func:`outcomes` of ``found`` (folds with
    the same templates), found :data:`ROUNDS` times, each round's rivals within the thresholds of
    the round before (none in the first). None for a template without positives, or whose
    positives never matched."""
    n = len(found[0].owner) if found else 0
    taus: list[float | None] = [None] * n
    choices: list[Choice | None] = [None] * n
    for _ in range(ROUNDS):
        pos: list[list[float]] = [[] for _ in range(n)]
        neg: list[list[float]] = [[] for _ in range(n)]
        for f in found:
            p, q = outcomes(f, taus)
            for t in range(n):
                pos[t] += p[t]
                neg[t] += q[t]
        choices = [
            choose_tau(pos[t], neg[t], min_recall=min_recall, fallback=fallback, position=position)
            if pos[t]
            else None
            for t in range(n)
        ]
        taus = [None if ch is None else ch.tau for ch in choices]
    return choices


def scored(
    fold: Fold, taus: Taus, k: int | None = None, present: npt.NDArray[np.bool_] | None = None
) -> tuple[int, int, int]:
    """True positives, false positives and false negatives of ``fold`` (of class ``k`` only, if
    given) with thresholds ``taus`` (and only the candidates ``present``, :func:`survivors`): a
    motion is found when a detection within its template's τ lies in it, a detection within its τ
    that lies in none is false."""
    keep = survivors(fold, taus, present)
    found, fp = set(), 0
    for x, ok in zip(fold.candidates, keep, strict=True):
        t = taus[x.template]
        if not ok or t is None or x.cost > t or (k is not None and fold.owner[x.template] != k):
            continue
        i = motion_of(fold, x)
        if i is None:
            fp += 1
        else:
            found.add(i)
    motions = [i for i, (c, _, _) in enumerate(fold.truth) if c in fold.learned and (k is None or c == k)]
    tp = sum(i in found for i in motions)
    return tp, fp, len(motions) - tp


def f1(tp: int, fp: int, fn: int) -> float:
    return 2 * tp / max(2 * tp + fp + fn, 1)


def choose_position(
    found: Sequence[Fold], *, min_recall: float = MIN_RECALL, fallback: float = 0.1
) -> tuple[float, dict[float, float]]:
    """The :data:`POSITIONS` entry whose thresholds, chosen without a fold and scored on it, give
    the best F1 summed over the folds (ties: the one nearest :data:`DEFAULT_POSITION`), and the F1
    of each. :data:`DEFAULT_POSITION` with fewer than two folds."""
    if len(found) < 2:
        return DEFAULT_POSITION, {}
    out = {}
    for position in POSITIONS:
        tp = fp = fn = 0
        for i, f in enumerate(found):
            rest = [g for j, g in enumerate(found) if j != i]
            choices = thresholds(rest, position=position, min_recall=min_recall, fallback=fallback)
            a, b, c = scored(f, [None if ch is None else ch.tau for ch in choices])
            tp, fp, fn = tp + a, fp + b, fn + c
        out[position] = f1(tp, fp, fn)
    best = max(POSITIONS, key=lambda p: (out[p], -abs(p - DEFAULT_POSITION)))
    return best, out


# ----------------------------------------------------------------------- more than one template


def dtw_distance(a: BoolArray, b: BoolArray) -> float:
    """The DTW distance (thesis Def. 3.3, l1 cost, steps (1,0), (0,1), (1,1)) of two examples
    ``(N, 39)`` and ``(M, 39)``, divided by N + M."""
    d = accumulated(fixed(l1_cost(a.T.astype(np.float64), b.T.astype(np.float64))))
    return float(to_cost(d[-1, -1])) / (len(a) + len(b))


def two_clusters(examples: Sequence[BoolArray], smallest: int = MIN_MEMBER) -> tuple[int, ...] | None:
    """The examples split into two styles: the two medoids (examples) whose nearer one is nearest,
    summed over all examples (:func:`dtw_distance`), and each example's cluster (0: the first
    example's); None with fewer than ``smallest`` examples in a cluster."""
    n = len(examples)
    if n < 2 * smallest:
        return None
    dist = np.zeros((n, n))
    for i in range(n):
        for j in range(i + 1, n):
            dist[i, j] = dist[j, i] = dtw_distance(examples[i], examples[j])
    best: tuple[float, int, int] | None = None
    for i in range(n):
        for j in range(i + 1, n):
            total = float(np.minimum(dist[i], dist[j]).sum())
            if best is None or total < best[0]:
                best = (total, i, j)
    assert best is not None
    _, i, j = best
    labels = (dist[:, j] < dist[:, i]).astype(int)
    if labels[0] == 1:
        labels = 1 - labels
    if min(np.bincount(labels, minlength=2)) < smallest:
        return None
    return tuple(int(x) for x in labels)


def spread(found: Sequence[Fold], taus: Taus, k: int) -> bool:
    """Whether class ``k``'s left-out costs spread wider than its gap to wrong detections: some
    motion of it found at a cost above one of its wrong detections', or never found."""
    pos: list[float] = []
    neg: list[float] = []
    for f in found:
        p, q = outcomes(f, taus)
        for t, c in enumerate(f.owner):
            if c == k:
                pos += p[t]
                neg += q[t]
    return bool(pos) and (max(pos) == math.inf or (bool(neg) and max(pos) > min(neg)))


# ------------------------------------------------------------------------------------ keyframes


def retention(found: Sequence[Fold], k: int, g: Generalisation) -> list[float]:
    """The share of the left-out examples of class ``k`` in which the keyframes learned with ``g``
    have a hit, fold by fold (folds with such examples)."""
    return [
        float(t.positives.mean())
        for f in found
        for t in f.trials.get(k, ())
        if t.generalisation == g and len(t.positives)
    ]


def detected(fold: Fold, taus: Taus, k: int) -> list[tuple[Candidate, int | None]]:
    """Class ``k``'s detections in ``fold`` at thresholds ``taus`` (its candidates that
    :func:`survivors` keeps, at most their template's τ), each with its motion (:func:`motion_of`;
    None: wrong)."""
    keep = survivors(fold, taus)
    out = []
    for x, ok in zip(fold.candidates, keep, strict=True):
        t = taus[x.template]
        if ok and fold.owner[x.template] == k and t is not None and x.cost <= t:
            out.append((x, motion_of(fold, x)))
    return out


def gated(
    found: Sequence[tuple[Candidate, int | None]], spans: Sequence[tuple[int, int]]
) -> list[tuple[Candidate, int | None]]:
    """The detections inside one of a keyframe-first class's windows ``spans`` (first, last frame):
    those its DTW over the windows finds too."""
    return [(x, i) for x, i in found if any(a <= x.start and x.end <= b for a, b in spans)]


@dataclass(frozen=True)
class Opening:
    """Where a keyframe-first class's windows open over a fold's stream: the windows
    :func:`daemon.recognizer.windows` gives, which frames lie inside one
    (``covered``, shape ``(N,)``) and the frames keyframe matches complete at (``completed``)."""

    windows: tuple[tuple[int, int, int, int], ...]
    covered: npt.NDArray[np.bool_]
    completed: tuple[int, ...]

    @property
    def spans(self) -> list[tuple[int, int]]:
        return [(a, b) for a, b, _, _ in self.windows]


def opening(
    trial: KeyframeTrial, rate: float, max_gap: int, codes: npt.NDArray[np.uint64], slack: int
) -> Opening:
    """The :class:`Opening` of ``trial``'s windows over index-rate ``codes`` ``(N,)`` with ``slack``
    (:func:`daemon.recognizer.window_extent`)."""
    query = trial.query
    found = completions(query, rate, max_gap, codes.tolist())
    extent = window_extent(query, trial.length, slack, trial.extent)
    made = keyframe_windows(query, extent, rate, max_gap, found)
    n = len(codes)
    covered = np.zeros(n, dtype=bool)
    for a, b, _, _ in made:
        covered[a : b + 1] = True
    return Opening(tuple(made), covered, tuple(sorted({j for _, j in found})))


@dataclass(frozen=True)
class GateReport:
    """What a class's keyframes did in the folds: ``opened`` of the ``motions`` of the class left
    out held a keyframe hit; ``others``: the share of the frames of other classes' motions inside
    one of its windows (with ``slack``); ``per_minute``: matches completed inside other classes' motions per
    minute of them; the class's wrong detections without the gate (``wrong``) and with it
    (``wrong_gated``)."""

    generalisation: Generalisation
    opened: int
    motions: int
    others: float
    per_minute: float
    wrong: int
    wrong_gated: int
    slack: int = 0

    def describe(self) -> str:
        g = self.generalisation
        return (
            f"{g.count} keyframes, up to {g.mismatches} mismatch{'es' if g.mismatches != 1 else ''}, "
            f"windows {self.slack} frames wider: "
            f"opened on {self.opened}/{self.motions} left-out motions and {self.others:.1%} of other "
            f"motions' frames ({self.per_minute:.1f} matches a minute of them), {self.wrong} -> "
            f"{self.wrong_gated} wrong detections"
        )


def gate_report(
    found: Sequence[Fold],
    k: int,
    g: Generalisation,
    base: Mapping[str, Sequence[tuple[Candidate, int | None]]],
    *,
    rate: float,
    max_gap: int,
    min_kept: float,
    slack: int = 0,
) -> GateReport | None:
    """What class ``k``'s keyframes learned with ``g`` do in the folds (:class:`GateReport`), or
    None when they do not hold: in some fold they have a hit in fewer than ``min_kept`` of the
    left-out motions of the class (:func:`retention`), or, keeping of the class's detections
    ``base`` (per fold group, :func:`detected`) those inside its windows (:func:`opening` with
    ``slack``) over the fold's stream, find fewer than ``min_kept`` of the motions the stream-wide
    ones find."""
    if min(retention(found, k, g), default=0.0) < min_kept:
        return None  # it misses whole motions already
    wrong = sum(i is None for d in base.values() for _, i in d)
    wrong_g = opened = motions = 0
    other_frames = other_covered = other_matches = 0
    for f in found:
        trial = next((t for t in f.trials.get(k, ()) if t.generalisation == g), None)
        if trial is None:
            continue
        gate = opening(trial, rate, max_gap, f.codes, slack)
        kept = gated(base[f.group], gate.spans)
        found_motions = {i for _, i in base[f.group] if i is not None}
        if len({i for _, i in kept if i is not None}) < math.ceil(min_kept * len(found_motions) - 1e-9):
            return None
        wrong_g += sum(i is None for _, i in kept)
        opened += int(trial.positives.sum())
        motions += len(trial.positives)
        others = np.zeros(len(f.codes), dtype=bool)
        for c, first, last in f.truth:
            if c != k:
                others[first : last + 1] = True
        other_frames += int(others.sum())
        other_covered += int((gate.covered & others).sum())
        other_matches += sum(bool(others[j]) for j in gate.completed)
    share = other_covered / other_frames if other_frames else 0.0
    per_minute = other_matches / (other_frames / rate / 60) if other_frames else 0.0
    return GateReport(g, opened, motions, share, per_minute, wrong, wrong_g, slack)


def choose_gate(
    found: Sequence[Fold],
    k: int,
    taus: Sequence[float | None],
    *,
    rate: float = DEFAULT_INDEX_RATE,
    max_gap_s: float = DEFAULT_MAX_GAP_S,
    min_kept: float = MIN_KEPT,
    spare: int = 0,
    wider: int = 0,
) -> tuple[GateReport | None, str]:
    """The keyframe gate of class ``k`` with what it did in the folds, or None (the stream-wide DTW
    alone), and why. Keyframes first is the rule; the stream-wide DTW only where the class's
    keyframes demonstrably lose left-out motions.

    A keyframe design (:class:`~daemon.learn.templates.Generalisation`, learned in each fold from
    the other groups) *holds* when :func:`gate_report` gives a report at the thresholds ``taus``
    (gap cap ``max_gap_s``) with one of :data:`SLACKS` (the first that holds). Of each design only
    its fewest mismatches that hold count (more only open the gate wider); its windows then open
    ``wider`` steps of :data:`SLACKS` wider and its keyframes tolerate ``spare`` mismatches more (at
    most the most tried, :data:`MISMATCHES`), since a new person differs more than the folds'
    people (:func:`choose_wider`, :func:`choose_spare`). Of these widened gates, the one with the
    fewest wrong detections, then the smallest share of other classes' motion frames inside a
    window, then the earliest tried, is chosen."""
    if not found or not any(f.trials.get(k) for f in found):
        return None, "no fold to learn keyframes on: stream-wide DTW"
    base = {f.group: detected(f, taus, k) for f in found}
    max_gap = max(1, round(max_gap_s * rate))
    tried = list(dict.fromkeys(t.generalisation for f in found for t in f.trials.get(k, ())))
    best: tuple[int, float, int] | None = None
    chosen: GateReport | None = None
    settled: set[Generalisation] = set()
    best_kept = 0.0
    for order, g in enumerate(tried):
        design = dataclasses.replace(g, mismatches=0)
        if design in settled:
            continue
        best_kept = max(best_kept, min(retention(found, k, g), default=0.0))
        report = next(
            (
                r
                for slack in SLACKS
                if (
                    r := gate_report(
                        found, k, g, base, rate=rate, max_gap=max_gap, min_kept=min_kept, slack=slack
                    )
                )
            ),
            None,
        )
        if report is None:
            continue
        settled.add(design)
        if wider:  # windows opened as wide as new people need (choose_wider)
            report = (
                gate_report(
                    found,
                    k,
                    g,
                    base,
                    rate=rate,
                    max_gap=max_gap,
                    min_kept=min_kept,
                    slack=widened(report.slack, wider),
                )
                or report
            )
        if spare:  # ranked as it will run: tolerating the spare mismatches too
            tolerant = dataclasses.replace(g, mismatches=min(g.mismatches + spare, MISMATCHES[-1]))
            report = (
                gate_report(
                    found,
                    k,
                    tolerant,
                    base,
                    rate=rate,
                    max_gap=max_gap,
                    min_kept=min_kept,
                    slack=report.slack,
                )
                or report
            )
        key = (report.wrong_gated, report.others, order)
        if best is None or key < best:
            best, chosen = key, report
    if chosen is None:
        return (
            None,
            f"no keyframes held on the left-out motions (the best kept {best_kept:.0%} in its worst fold): "
            "stream-wide DTW",
        )
    return chosen, f"keyframes first: {chosen.describe()}"


SPARES = (0, 1, 2)
"""The spare mismatches tried by :func:`choose_spare`."""
SLACKS = (0, 3, 6, 12)
"""The slacks tried for a design's windows (frames at the index rate; the fewest that keep the
class's motions are taken)."""
DEFAULT_SLACK = 6
"""The slack of keyframes that no fold chose (given to ``mocapd learn``)."""
DEFAULT_SPARE = 1
"""Spare mismatches without two folds to choose them."""


Inner = list[tuple["Fold", int, GateReport]]
"""Per class and fold: the gate :func:`choose_gate` chooses without that fold (:func:`inner_gates`)."""


def inner_gates(
    found: Sequence[Fold],
    taus: Sequence[float | None],
    *,
    rate: float = DEFAULT_INDEX_RATE,
    max_gap_s: float = DEFAULT_MAX_GAP_S,
    min_kept: float = MIN_KEPT,
) -> Inner:
    """Nested folds: for every class and every fold holding its motions, the gate
    :func:`choose_gate` chooses from the other folds (where one holds)."""
    inner: Inner = []
    for k in sorted({c for f in found for c in f.trials}):
        held = [f for f in found if k in f.trials and k in f.learned]
        for i, f in enumerate(held):
            rest = [h for j, h in enumerate(held) if j != i]
            report, _ = choose_gate(rest, k, taus, rate=rate, max_gap_s=max_gap_s, min_kept=min_kept)
            if report is not None:
                inner.append((f, k, report))
    return inner


def fewest_reaching(
    tried: Sequence[int], kept: Callable[[int], tuple[int, int]], min_kept: float
) -> tuple[int, dict[int, float]]:
    """The first of ``tried`` whose share kept (``kept(x)``: motions kept, motions; 1 without any)
    reaches ``min_kept`` (else the last), with the share of each."""
    shares = {}
    for x in tried:
        held, total = kept(x)
        shares[x] = held / total if total else 1.0
    return next((x for x in tried if shares[x] >= min_kept), tried[-1]), shares


def choose_spare(
    found: Sequence[Fold],
    taus: Sequence[float | None],
    *,
    rate: float = DEFAULT_INDEX_RATE,
    max_gap_s: float = DEFAULT_MAX_GAP_S,
    min_kept: float = MIN_KEPT,
    inner: Inner | None = None,
) -> tuple[int, dict[int, float]]:
    """How many mismatches beyond what the folds need keyframes must tolerate to hold on a group
    never seen, by nested folds: for every class and every fold, the gate :func:`choose_gate`
    chooses without that fold (``inner``: :func:`inner_gates`, made if not given), widened by each
    of :data:`SPARES`, is scored by the share of the fold's left-out motions of the class its
    keyframes hit (pooled over classes and folds); the fewest spare mismatches whose share reaches
    ``min_kept`` are taken (else the most tried), with the share of each. :data:`DEFAULT_SPARE`
    with fewer than two folds."""
    if len(found) < 2:
        return DEFAULT_SPARE, {}
    if inner is None:
        inner = inner_gates(found, taus, rate=rate, max_gap_s=max_gap_s, min_kept=min_kept)

    def kept(spare: int) -> tuple[int, int]:
        held = total = 0
        for f, k, report in inner:
            g = report.generalisation
            wider = dataclasses.replace(g, mismatches=min(g.mismatches + spare, MISMATCHES[-1]))
            trial = next((t for t in f.trials[k] if t.generalisation == wider), None)
            if trial is not None:
                held += int(trial.positives.sum())
                total += len(trial.positives)
        return held, total

    return fewest_reaching(SPARES, kept, min_kept)


WIDER = (0, 1, 2)
"""The steps along :data:`SLACKS` beyond the slack the folds need tried by :func:`choose_wider`."""
DEFAULT_WIDER = 1
"""Steps without two folds to choose them."""


def widened(slack: int, steps: int) -> int:
    """``slack`` (one of :data:`SLACKS`) ``steps`` further along them (at most the widest)."""
    return SLACKS[min(SLACKS.index(slack) + steps, len(SLACKS) - 1)]


def choose_wider(
    found: Sequence[Fold],
    taus: Sequence[float | None],
    *,
    rate: float = DEFAULT_INDEX_RATE,
    max_gap_s: float = DEFAULT_MAX_GAP_S,
    min_kept: float = MIN_KEPT,
    inner: Inner | None = None,
) -> tuple[int, dict[int, float]]:
    """How much wider than the folds need a class's windows must open to hold on a group never
    seen, by nested folds: for every class and every fold, the gate :func:`choose_gate` chooses
    without that fold (``inner``), its slack widened by each of :data:`WIDER` steps of
    :data:`SLACKS`, is scored by the share of the motions of the class that its detections find
    in the fold's stream (:func:`detected`) that they still find inside its windows there (pooled
    over classes and folds); the fewest steps whose share reaches ``min_kept`` are taken (else the
    most tried), with the share of each. :data:`DEFAULT_WIDER` with fewer than two folds."""
    if len(found) < 2:
        return DEFAULT_WIDER, {}
    if inner is None:
        inner = inner_gates(found, taus, rate=rate, max_gap_s=max_gap_s, min_kept=min_kept)
    max_gap = max(1, round(max_gap_s * rate))
    # per inner gate, its trial in the fold and the class's detections there: the same for every step
    held_out = [
        (f, trial, report.slack, detected(f, taus, k))
        for f, k, report in inner
        for trial in [next((t for t in f.trials[k] if t.generalisation == report.generalisation), None)]
        if trial is not None
    ]

    def kept(steps: int) -> tuple[int, int]:
        held = total = 0
        for f, trial, slack, base in held_out:
            gate = opening(trial, rate, max_gap, f.codes, widened(slack, steps))
            held += len({i for _, i in gated(base, gate.spans) if i is not None})
            total += len({i for _, i in base if i is not None})
        return held, total

    return fewest_reaching(WIDER, kept, min_kept)


def present_in_windows(
    fold: Fold, k: int, report: GateReport, *, rate: float, max_gap: int
) -> npt.NDArray[np.bool_]:
    """Which of ``fold``'s candidates the live recogniser finds when class ``k`` is keyframes first
    with ``report``'s keyframes and slack: one of class ``k`` only inside one of its windows over the
    fold's stream (:func:`opening`), every other one; shape ``(candidates,)``."""
    present = np.ones(len(fold.candidates), dtype=bool)
    trial = next((t for t in fold.trials.get(k, ()) if t.generalisation == report.generalisation), None)
    if trial is None:
        return present
    spans = opening(trial, rate, max_gap, fold.codes, report.slack).spans
    for i, x in enumerate(fold.candidates):
        if fold.owner[x.template] == k:
            present[i] = any(a <= x.start and x.end <= b for a, b in spans)
    return present


def windows_f1(
    found: Sequence[Fold],
    taus: Taus,
    gates: Mapping[int, GateReport],
    first: Collection[int],
    *,
    rate: float = DEFAULT_INDEX_RATE,
    max_gap_s: float = DEFAULT_MAX_GAP_S,
    masks: Sequence[Mapping[int, npt.NDArray[np.bool_]]] | None = None,
) -> float:
    """Every class's F1 over the folds (:func:`scored`) when the classes ``first`` are keyframes
    first with their ``gates`` (their candidates only inside their windows,
    :func:`present_in_windows`; ``masks``: those per fold and class, if at hand)."""
    max_gap = max(1, round(max_gap_s * rate))
    tp = fp = fn = 0
    for i, f in enumerate(found):
        present = np.ones(len(f.candidates), dtype=bool)
        for k in first:
            present &= (
                masks[i][k]
                if masks is not None
                else present_in_windows(f, k, gates[k], rate=rate, max_gap=max_gap)
            )
        a, b, c = scored(f, taus, present=present)
        tp, fp, fn = tp + a, fp + b, fn + c
    return f1(tp, fp, fn)


def settle_modes(
    found: Sequence[Fold],
    taus: Taus,
    gates: Mapping[int, GateReport],
    *,
    rate: float = DEFAULT_INDEX_RATE,
    max_gap_s: float = DEFAULT_MAX_GAP_S,
) -> dict[int, tuple[float, float]]:
    """The classes of ``gates`` that keyframes first makes worse for every class together: all of
    them keyframes first, every class's F1 over the folds (:func:`windows_f1`); then, class by
    class in order, one is set to the stream-wide DTW where that raises the F1 (a rival found only
    by its own DTW, when its keyframes do not open, lets a wrong detection of another class
    through; a window that misses a motion loses it). Per class set so: (F1 with it keyframes
    first, F1 without)."""
    max_gap = max(1, round(max_gap_s * rate))
    masks = [
        {k: present_in_windows(f, k, r, rate=rate, max_gap=max_gap) for k, r in gates.items()} for f in found
    ]
    first = set(gates)
    now = windows_f1(found, taus, gates, first, masks=masks)
    out = {}
    for k in sorted(gates):
        score = windows_f1(found, taus, gates, first - {k}, masks=masks)
        if score > now:
            out[k] = (now, score)
            first, now = first - {k}, score
    return out


# ------------------------------------------------------------------------------------ the result


@dataclass(frozen=True)
class ClassCalibration:
    """A class's :class:`Calibration`, its keyframe gate and what it did in the folds (None:
    recognised by the stream-wide DTW alone) and why; with two templates, each example's template
    (``members``, 0 or 1, None: one template) and the second one's calibration."""

    calibration: Calibration
    keyframes: GateReport | None
    reason: str
    members: tuple[int, ...] | None = None
    second: Calibration | None = None


@dataclass(frozen=True)
class Calibrated:
    """Every class's :class:`ClassCalibration`, the folds they came from (with the templates
    chosen), what the groups were, the position of τ with the nested folds' F1 of each, and the
    keyframes' spare mismatches with the nested folds' share of motions kept of each
    (:func:`choose_spare`), and the steps its windows open wider with the nested folds' share of
    motions kept inside them of each (:func:`choose_wider`)."""

    classes: Mapping[str, ClassCalibration]
    folds: tuple[Fold, ...]
    groups: str
    position: float
    position_f1: Mapping[float, float]
    spare: int = 0
    spare_kept: Mapping[int, float] = dataclasses.field(default_factory=dict)
    wider: int = 0
    wider_kept: Mapping[int, float] = dataclasses.field(default_factory=dict)


def _record(
    found: Sequence[Fold],
    taus: Taus,
    t: int,
    choice: Choice,
    groups_are: str,
    position: float,
    min_recall: float,
) -> Calibration:
    pos: list[float] = []
    neg: list[float] = []
    for f in found:
        p, q = outcomes(f, taus)
        pos += p[t]
        neg += q[t]
    rule = f"best F1 with recall >= {min_recall:g}" if choice.feasible else "largest positive cost"
    method = (
        f"left-out streams of {len(found)} folds ({groups_are}): {rule}, {position:g} of the way to the "
        "next wrong detection's cost"
    )
    return Calibration(choice.tau, method, len(found), len(pos), len(neg), choice.recall, choice.precision)


def calibrate(
    examples: Labelled,
    *,
    groups_are: str = "actors",
    tau: float = 0.1,
    delta: float = 0.1,
    keyframes: int = 3,
    steps: Steps = "toolbox",
    rate: float = DEFAULT_INDEX_RATE,
    min_recall: float = MIN_RECALL,
    min_kept: float = MIN_KEPT,
    progress: Callable[[str], object] | None = None,
) -> Calibrated:
    """Every class's τ, templates and gate from the :func:`folds` of ``examples`` (grouped as
    ``groups_are`` says, for the record); the learning parameters are those the classes will be
    learned with.

    1. τ of every class's template: :func:`choose_position`, then :func:`thresholds`.
    2. Two templates for a class whose left-out costs :func:`spread` wider than its gap to wrong
       detections: its examples split by :func:`two_clusters` (all of them, once, so a fold's
       templates are the final ones' styles), in each fold one template learned from the training
       examples of each style, every template's τ found again; kept if the class's F1 over the
       folds (:func:`scored`) rises.
    3. The keyframes' spare mismatches and the windows' spare width (:func:`choose_spare`,
       :func:`choose_wider`, from the same nested folds), then every class's keyframe gate
       (:func:`choose_gate`).

    A class without a fold, or whose left-out motions never matched, keeps the given ``tau`` (and
    says why)."""
    names = list(examples)
    found = folds(examples, delta=delta, keyframes=keyframes, steps=steps, rate=rate, progress=progress)
    # nested folds over one person's takes measure how τ carries to another take of that person,
    # not to another person: there the middle of the gap is taken
    if groups_are == "actors":
        position, position_f1 = choose_position(found, min_recall=min_recall, fallback=tau)
    else:
        position, position_f1 = DEFAULT_POSITION, {}

    def taus_of(folds_: Sequence[Fold]) -> list[float | None]:
        chosen = thresholds(folds_, position=position, min_recall=min_recall, fallback=tau)
        return [None if ch is None else ch.tau for ch in chosen]

    choices = thresholds(found, position=position, min_recall=min_recall, fallback=tau)
    taus: list[float | None] = [None if ch is None else ch.tau for ch in choices]
    members: dict[int, tuple[int, ...]] = {}
    for k, name in enumerate(names):
        if not found or not spread(found, taus, k):
            continue
        labels = two_clusters([m for _, m in examples[name]])
        if labels is None:
            continue
        changed = []
        for f in found:
            styles: list[MotionTemplate | None] = []
            for style in (0, 1):
                training = [
                    m for (g, m), c in zip(examples[name], labels, strict=True) if g != f.group and c == style
                ]
                styles.append(learn(training, delta=delta, keyframes=0).quantised if training else None)
            changed.append(with_members(f, k, styles, steps))
        before = [sum(x) for x in zip(*(scored(f, taus, k) for f in found), strict=True)]
        after_taus = taus_of(changed)
        after = [sum(x) for x in zip(*(scored(f, after_taus, k) for f in changed), strict=True)]
        styles_ok = all(
            any(p and math.isfinite(min(p)) for f in changed for p in [outcomes(f, after_taus)[0][t]])
            for t in range(len(changed[0].owner) - 2, len(changed[0].owner))
        )
        if styles_ok and f1(*after) > f1(*before):
            found, taus = changed, after_taus
            choices = thresholds(found, position=position, min_recall=min_recall, fallback=tau)
            members[k] = labels
            if progress is not None:
                progress(
                    f"[class {k + 1}/{len(names)}] {name}: two styles, F1 over the folds "
                    f"{f1(*before):.2f} -> {f1(*after):.2f}"
                )
    spare, wider = 0, 0
    spare_kept: dict[int, float] = {}
    wider_kept: dict[int, float] = {}
    if keyframes:
        inner = inner_gates(found, taus, rate=rate, min_kept=min_kept) if len(found) >= 2 else []
        spare, spare_kept = choose_spare(found, taus, rate=rate, min_kept=min_kept, inner=inner)
        wider, wider_kept = choose_wider(found, taus, rate=rate, min_kept=min_kept, inner=inner)
    out = {}
    for k, name in enumerate(names):
        held = [f for f in found if any(c == k for c, _, _ in f.truth) and k in f.learned]
        templates = [t for t, c in enumerate(found[0].owner) if c == k] if found else [k]
        if keyframes:
            gate, reason = choose_gate(held, k, taus, rate=rate, min_kept=min_kept, spare=spare, wider=wider)
        else:
            gate, reason = None, "no keyframes asked for: stream-wide DTW"
        records = []
        for t in templates[-2:] if k in members else templates[:1]:
            choice = choices[t] if t < len(choices) else None
            if choice is None:
                why = "no fold" if not held else f"no left-out motion matched in {len(held)} folds"
                records.append(given(tau, f"{why}: nothing to calibrate on"))
            else:
                records.append(_record(held, taus, t, choice, groups_are, position, min_recall))
        out[name] = ClassCalibration(
            records[0],
            gate,
            reason,
            members.get(k),
            records[1] if k in members else None,
        )
    gates = {k: c.keyframes for k, c in enumerate(out.values()) if c.keyframes is not None}
    for k, (kf, dtw) in settle_modes(found, taus, gates, rate=rate).items():
        name = names[k]
        out[name] = dataclasses.replace(
            out[name],
            keyframes=None,
            reason=(
                f"keyframes first lost in the folds (every class's F1 {kf:.3f}, {dtw:.3f} with this class "
                f"by stream-wide DTW; {out[name].reason}): stream-wide DTW"
            ),
        )
    return Calibrated(
        out, tuple(found), groups_are, position, position_f1, spare, spare_kept, wider, wider_kept
    )
