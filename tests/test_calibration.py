"""Learning how each class is recognised (issue 20): the τ choice on hand-made cost lists and as a
property (with its position towards the next wrong detection), the fold groups, the left-out
streams, the detections of a fold (survivors, outcomes, scores) against slow references on random
candidates, the thresholds found again with the rivals' τ, the position chosen by nested folds, two
styles of a class, the keyframe gate, the whole calibration on real HDM05 clips of three actors
(and of one), the training manifest's ``actor`` column, library version 4 and the loading of
versions 2 and 3, and ``mocapd learn`` / ``mocapd search --library`` using the calibrated τ unless
told otherwise."""

from __future__ import annotations

import dataclasses
import json
import math
import random
import re
from collections.abc import Sequence
from itertools import pairwise
from pathlib import Path

import numpy as np
import numpy.typing as npt
import pytest
from hypothesis import given as hypothesis_given
from hypothesis import settings
from hypothesis import strategies as st

from daemon.dtw import fixed, pack, retrieval_cost, subsequence_dtw
from daemon.features import SET_SLICES
from daemon.keyframes import KeyframeQuery, gap_bounds, query_bounds
from daemon.learn.calibration import (
    CAP,
    DEFAULT_POSITION,
    MIN_KEPT,
    MIN_MEMBER,
    POSITIONS,
    ROUNDS,
    SLACKS,
    SPARES,
    TAKE_GROUPS,
    WIDER,
    Calibrated,
    Candidate,
    Choice,
    Fold,
    GateReport,
    KeyframeTrial,
    calibrate,
    choose_gate,
    choose_position,
    choose_spare,
    choose_tau,
    choose_wider,
    clip_costs,
    clip_sets,
    designs,
    fold_stream,
    groups,
    kept_in_a_row,
    keyframes_kept,
    make_fold,
    outcomes,
    scored,
    settle_modes,
    stream_candidates,
    survivors,
    thresholds,
    two_clusters,
    windows_f1,
)
from daemon.learn.library import learn_class, save_library
from daemon.learn.templates import Generalisation, automatic_keyframes, learn, learn_hard
from daemon.library import DTW, GATED, GIVEN, Calibration, Library, LibraryFormatError, load_library
from daemon.recordings import ManifestError, read_examples, read_manifest, read_training_manifest
from daemon.search.store import build_index, save_index
from daemon.templates import expand
from daemon.types import DEFAULT_INDEX_RATE, DEFAULT_MAX_GAP_S, FEATURE_SETS, BoolArray, FeatureSet
from tests.helpers import (
    HDM_AMC,
    HDM_ASF,
    assert_ok,
    hdm05_clip,
    hits_json,
    mocapd,
    takes,
    write_manifest,
    write_training,
)
from tests.naive import (
    FoldCandidate,
    GateFold,
    keyframe_matches,
    ref_local_minima,
    slow_extent,
    slow_gate,
    slow_outcomes,
    slow_scored,
    slow_survivors,
    slow_windows,
)
from tests.synth import queries, stream_codes, streams

CLIPS = [
    ("squat1Reps", "bd", 1),
    ("squat1Reps", "bd", 2),
    ("squat1Reps", "bk", 13),
    ("squat1Reps", "bk", 14),
    ("squat1Reps", "dg", 25),
    ("squat1Reps", "dg", 26),
    ("hopBothLegs1hops", "bd", 1),
    ("hopBothLegs1hops", "bd", 2),
    ("hopBothLegs1hops", "bk", 13),
    ("hopBothLegs1hops", "bk", 14),
    ("hopBothLegs1hops", "dg", 22),
    ("hopBothLegs1hops", "dg", 23),
]
"""2 classes x 3 actors x 2 clips: small enough to learn every fold in a few seconds."""

Labelled = dict[str, list[tuple[str, BoolArray]]]


def actor_rows(clips: list[tuple[str, str, int]], actor: bool = True) -> list[str]:
    rows = []
    for c, a, t in clips:
        asf, amc = hdm05_clip(a, c, t)
        rows.append(f"{c},{asf},{amc},{a}" if actor else f"{c},{asf},{amc}")
    return rows


def write_clips(path: Path, clips: list[tuple[str, str, int]] = CLIPS) -> Path:
    return write_training(path, actor_rows(clips), "class,asf,amc,actor")


def by_actor(manifest: Path) -> Labelled:
    return {name: [(clip.actor, m) for clip, m in items] for name, items in read_examples(manifest).items()}


@pytest.fixture(scope="module")
def manifest(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return write_clips(tmp_path_factory.mktemp("calibration") / "clips.csv")


@pytest.fixture(scope="module")
def labelled(manifest: Path) -> Labelled:
    return by_actor(manifest)


@pytest.fixture(scope="module")
def calibrated(labelled: Labelled) -> Calibrated:
    """Every class calibrated over the three actors (keyframes learned in every fold)."""
    return calibrate(labelled, groups_are="actors")


# ------------------------------------------------------------------------------------ choosing τ


def test_tau_at_the_best_f1_with_full_recall_midway_to_the_next_negative() -> None:
    # 4 positives: recall >= 0.95 needs all of them, so the threshold is at least 0.09
    choice = choose_tau([0.02, 0.04, 0.05, 0.09], [0.03, 0.12, 0.5], fallback=0.1)
    assert choice is not None and choice.feasible
    assert choice.tau == pytest.approx((0.09 + 0.12) / 2)
    assert (choice.recall, choice.precision) == (1.0, 0.8)
    assert choice.f1 == pytest.approx(2 * 4 / (2 * 4 + 1 + 0))


def test_tau_position_moves_it_towards_the_next_negative() -> None:
    for position in (0.0, 0.25, 0.75):
        choice = choose_tau([0.02, 0.04, 0.05, 0.09], [0.03, 0.12, 0.5], fallback=0.1, position=position)
        assert choice is not None and choice.tau == pytest.approx(0.09 + position * 0.03)
        assert (choice.recall, choice.precision) == (1.0, 0.8)
    # no negative above: the position does not matter, the fallback does
    for position in (0.0, 0.9):
        choice = choose_tau([0.02, 0.09], [0.01], fallback=0.1, position=position)
        assert choice is not None and choice.tau == 0.1
    for position in (1.0, -0.1, math.nan):
        with pytest.raises(ValueError, match="position must lie in"):
            choose_tau([0.02], [0.1], fallback=0.1, position=position)


def test_tau_prefers_precision_when_the_recall_allows() -> None:
    # 20 positives: one may be missed (19/20 = 0.95); missing the costliest drops 3 negatives
    positives = [0.01 * i for i in range(1, 20)] + [0.5]
    choice = choose_tau(positives, [0.3, 0.4, 0.45, 0.8], fallback=0.1)
    assert choice is not None and choice.feasible
    assert choice.tau == pytest.approx((0.19 + 0.3) / 2)
    assert (choice.recall, choice.precision) == (0.95, 1.0)


def test_tau_ties_go_to_the_larger_cost_and_no_negative_above_keeps_the_fallback() -> None:
    # at 0.1: TP 1, FP 0, FN 1 -> F1 2/3; at 0.3: TP 2, FP 2, FN 0 -> F1 2/3
    choice = choose_tau([0.1, 0.3], [0.2, 0.25], min_recall=0.5, fallback=0.05)
    assert choice is not None and choice.f1 == pytest.approx(2 / 3)
    assert choice.tau == 0.3 and choice.recall == 1.0
    choice = choose_tau([0.1, 0.3], [0.2, 0.25], min_recall=0.5, fallback=0.4)
    assert choice is not None and choice.tau == 0.4


def test_tau_when_the_recall_is_out_of_reach_or_nothing_matches() -> None:
    choice = choose_tau([0.05, math.inf], [0.2], fallback=0.1)
    assert choice is not None and not choice.feasible
    assert choice.tau == pytest.approx(0.125) and (choice.recall, choice.precision) == (0.5, 1.0)
    assert choose_tau([math.inf, math.inf], [0.2], fallback=0.1) is None
    assert choose_tau([], [0.2], fallback=0.1) is None


costs = st.lists(st.integers(0, 40).map(lambda i: i / 40) | st.just(math.inf), max_size=30)
positions = st.sampled_from([0.0, *POSITIONS]) | st.integers(0, 99).map(lambda i: i / 100)


@settings(max_examples=300, deadline=None)
@hypothesis_given(costs, costs, st.sampled_from([0.5, 0.8, 0.95, 1.0]), positions)
def test_tau_is_the_best_f1_subject_to_the_recall(
    positives: list[float], negatives: list[float], min_recall: float, position: float
) -> None:
    choice = choose_tau(positives, negatives, min_recall=min_recall, fallback=0.1, position=position)
    if not any(math.isfinite(p) for p in positives):
        assert choice is None
        return
    assert choice is not None and choice.tau >= 0

    def score(t: float) -> tuple[float, float, float]:
        tp = sum(p <= t for p in positives)
        fp = sum(n <= t for n in negatives)
        return tp / len(positives), tp / max(tp + fp, 1), 2 * tp / (2 * tp + fp + len(positives) - tp)

    recall, precision, f1 = score(choice.tau)
    assert (recall, precision, f1) == pytest.approx((choice.recall, choice.precision, choice.f1))
    feasible = [t for t in set(positives + negatives) if math.isfinite(t) and score(t)[0] >= min_recall]
    assert choice.feasible == bool(feasible)
    if feasible:
        assert recall >= min_recall
        assert f1 >= max(score(t)[2] for t in feasible) - 1e-12
    else:
        assert choice.tau >= max(p for p in positives if math.isfinite(p))
    # τ sits ``position`` of the way from the positive cost it needs to the next negative cost
    cost = max(p for p in positives if p <= choice.tau)
    above = [n for n in negatives if cost < n < math.inf]  # an unmatched negative is no limit
    if above:
        assert choice.tau == pytest.approx(cost + position * (min(above) - cost))
        assert position == 0 or choice.tau > cost
    else:
        assert choice.tau == max(cost, 0.1)


# ------------------------------------------------------------------------------------ the groups


def test_groups_are_the_actors_when_there_are_two() -> None:
    actors = ["bd", "bk", "bd", "bd"]
    assert groups(actors, ["a", "a", "b", "a"]) == (actors, "actors")


def test_groups_of_one_actor_deal_each_class_into_takes() -> None:
    classes = ["a", "a", "b", "a", "a", "b", "c", "a"]
    labels, what = groups(["bd"] * len(classes), classes)
    assert labels == ["take 1", "take 2", "take 1", "take 3", "take 1", "take 2", "take 1", "take 2"]
    assert "one actor" in what and f"at most {TAKE_GROUPS}" in what and "groups" in what
    assert len(set(labels)) <= TAKE_GROUPS
    # every group holds some of each class that has at least 3 examples
    for group in set(labels):
        assert "a" in [c for c, g in zip(classes, labels, strict=True) if g == group]


# ------------------------------------------------------------------------------- a fold's stream


def test_fold_stream_joins_the_group_in_an_order_shuffled_by_its_name() -> None:
    rng = np.random.default_rng(7)
    made: dict[str, list[tuple[str, BoolArray]]] = {}
    for name, group_of in (("a", "xxyx"), ("b", "yx"), ("c", "yyyy"), ("d", "xxxx")):
        made[name] = [(g, rng.random((int(rng.integers(3, 9)), 39)) < 0.5) for g in group_of]
    for group in ("x", "y"):
        codes, truth = fold_stream(made, group)
        again = fold_stream(made, group)  # deterministic
        assert again[0].tolist() == codes.tolist() and again[1] == truth
        items = [(k, m) for k, name in enumerate(made) for g, m in made[name] if g == group]
        expected = list(items)
        random.Random(group).shuffle(expected)
        assert [k for k, _, _ in truth] == [k for k, _ in expected]
        assert truth[0][1] == 0 and truth[-1][2] == len(codes) - 1
        for (_, _, last), (_, first, _) in pairwise(truth):
            assert first == last + 1  # contiguous
        for (k, first, last), (c, m) in zip(truth, expected, strict=True):
            assert k == c and last - first + 1 == len(m)
        np.testing.assert_array_equal(codes, pack(np.concatenate([m for _, m in expected])))
        assert sorted(len(m) for _, m in expected) == sorted(b - a + 1 for _, a, b in truth)
    # the shuffle depends on the group's name: the same examples under two names
    same = {"a": [(g, m) for _, m in made["d"] for g in ("p", "q")]}
    assert fold_stream(same, "p")[0].tolist() != fold_stream(same, "q")[0].tolist()
    codes, truth = fold_stream(made, "z")
    assert codes.shape == (0,) and codes.dtype == np.uint64 and truth == []


# ------------------------------------------------------------------ the detections of a fold


COSTS = (0.05, 0.1, 0.2, 0.3)
TAUS = (0.05, 0.1, 0.15, 0.2, 0.3)

FoldParts = tuple[list[FoldCandidate], list[int], list[tuple[int, int, int]], frozenset[int], int]


@st.composite
def fold_parts(draw: st.DrawFn, owner: list[int] | None = None) -> FoldParts:
    """Random candidates (costs from a small set, to force ties), templates owned by classes (every
    class has one, some a second), a stream of contiguous motions and the classes learned."""
    if owner is None:
        n = draw(st.integers(1, 3))
        owner = list(range(n)) + draw(st.lists(st.integers(0, n - 1), max_size=2))
    n = max(owner) + 1
    length = draw(st.integers(1, 40))
    cuts = sorted(draw(st.sets(st.integers(1, length - 1), max_size=5))) if length > 1 else []
    bounds = [0, *cuts, length]
    truth = [(draw(st.integers(0, n - 1)), a, b - 1) for a, b in pairwise(bounds)]
    learned = frozenset(draw(st.sets(st.integers(0, n - 1))))
    drawn = draw(
        st.lists(
            st.tuples(
                st.sampled_from(COSTS),
                st.integers(0, length - 1),
                st.integers(0, len(owner) - 1),
                st.integers(0, length - 1),
            ),
            max_size=25,
        )
    )
    candidates = [(c, max(a, b), t, min(a, b)) for c, a, t, b in drawn]
    return candidates, owner, truth, learned, length


def taus_for(templates: int) -> st.SearchStrategy[list[float | None]]:
    return st.lists(st.none() | st.sampled_from(TAUS), min_size=templates, max_size=templates)


def as_fold(parts: FoldParts, group: str = "g") -> Fold:
    candidates, owner, truth, learned, length = parts
    return fold_of(group, list(truth), list(candidates), owner, learned, length)


@pytest.mark.slow
@settings(max_examples=300, deadline=None)
@hypothesis_given(st.data())
def test_survivors_outcomes_and_scores_match_the_slow_references(data: st.DataObject) -> None:
    parts = data.draw(fold_parts())
    candidates, owner, truth, learned, _ = parts
    taus = data.draw(taus_for(len(owner)))
    fold = as_fold(parts)
    assert list(fold.candidates) == sorted(candidates)
    assert survivors(fold, taus).tolist() == slow_survivors(candidates, owner, taus)
    assert outcomes(fold, taus) == slow_outcomes(candidates, owner, truth, learned, taus)
    assert scored(fold, taus) == slow_scored(candidates, owner, truth, learned, taus)
    for k in range(max(owner) + 1):
        assert scored(fold, taus, k) == slow_scored(candidates, owner, truth, learned, taus, k)


def fold_of(
    group: str,
    truth: list[tuple[int, int, int]],
    candidates: list[FoldCandidate],
    owner: Sequence[int] = (0, 1),
    learned: frozenset[int] = frozenset({0, 1}),
    length: int | None = None,
) -> Fold:
    if length is None:
        length = max([b for _, _, b in truth] + [c[1] for c in candidates]) + 1
    return make_fold(
        group,
        np.zeros(length, dtype=np.uint64),
        truth,
        owner,
        [Candidate(*c) for c in candidates],
        learned,
        {},
    )


def test_thresholds_without_rivals_are_each_templates_best_tau() -> None:
    """No two candidates share a frame: every template's τ is :func:`choose_tau` on its costs."""
    one = fold_of(
        "one",
        [(0, 0, 9), (1, 10, 19), (0, 20, 29)],
        [(0.05, 9, 0, 0), (0.12, 19, 1, 10), (0.2, 39, 0, 30), (0.3, 49, 1, 40)],
    )
    two = fold_of("two", [(0, 0, 9), (1, 10, 19)], [(0.08, 9, 0, 0), (0.09, 19, 1, 10), (0.11, 29, 0, 20)])
    for position in POSITIONS:
        got = thresholds([one, two], position=position, fallback=0.1)
        a = choose_tau([0.05, math.inf, 0.08], [0.2, 0.11], fallback=0.1, position=position)
        b = choose_tau([0.12, 0.09], [0.3], fallback=0.1, position=position)
        assert got == [a, b]
        assert a is not None and not a.feasible  # one of A's three motions never matched
        assert b is not None and b.tau == pytest.approx(0.12 + position * 0.18)


def test_thresholds_are_found_again_with_the_rivals_tau() -> None:
    """Class A's wrong candidate (0.1) lies on class B's motion, cheaper than B's right one (0.2). It
    beats B's only once A's τ is known (0.15: A needs its 0.15 motion), so B's τ comes from the
    rounds after the first: B then finds one of its two motions."""
    fold = fold_of(
        "g",
        [(1, 0, 19), (0, 30, 49), (1, 60, 79), (0, 90, 109)],
        [(0.05, 49, 0, 30), (0.15, 109, 0, 90), (0.1, 19, 0, 0), (0.2, 19, 1, 0), (0.08, 79, 1, 60)],
    )
    first = [choose_tau([0.05, 0.15], [0.1], fallback=0.1), choose_tau([0.2, 0.08], [], fallback=0.1)]
    assert outcomes(fold, [None, None]) == ([[0.05, 0.15], [0.2, 0.08]], [[0.1], []])
    assert first[0] is not None and first[0].tau == 0.15 and first[1] is not None and first[1].tau == 0.2
    assert ROUNDS >= 2
    got = thresholds([fold], fallback=0.1)
    assert got == [first[0], choose_tau([math.inf, 0.08], [], fallback=0.1)]
    assert got[1] is not None and (got[1].tau, got[1].recall, got[1].feasible) == (0.1, 0.5, False)


@pytest.mark.slow
@settings(max_examples=100, deadline=None)
@hypothesis_given(st.data())
def test_thresholds_are_rounds_of_choose_tau_on_the_slow_outcomes(data: st.DataObject) -> None:
    first = data.draw(fold_parts())
    owner = first[1]
    parts = [first, *data.draw(st.lists(fold_parts(owner=owner), max_size=2))]
    position = data.draw(st.sampled_from(POSITIONS))
    taus: list[float | None] = [None] * len(owner)
    expected: list[Choice | None] = []
    for _ in range(ROUNDS):
        pos: list[list[float]] = [[] for _ in owner]
        neg: list[list[float]] = [[] for _ in owner]
        for candidates, _, truth, learned, _ in parts:
            p, q = slow_outcomes(candidates, owner, truth, learned, taus)
            for t in range(len(owner)):
                pos[t] += p[t]
                neg[t] += q[t]
        expected = [
            choose_tau(pos[t], neg[t], fallback=0.1, position=position) if pos[t] else None
            for t in range(len(owner))
        ]
        taus = [None if c is None else c.tau for c in expected]
    assert thresholds([as_fold(p) for p in parts], position=position, fallback=0.1) == expected


# ------------------------------------------------------------------------ the position of τ


def slow_position(folds: list[FoldParts]) -> tuple[float, dict[float, float]]:
    """Every position's F1 over the folds, each scored with the τ the other folds give, by loops."""
    f1 = {}
    for position in POSITIONS:
        tp = fp = fn = 0
        for i, (candidates, owner, truth, learned, _) in enumerate(folds):
            rest = [as_fold(p) for j, p in enumerate(folds) if j != i]
            taus = [None if c is None else c.tau for c in thresholds(rest, position=position, fallback=0.1)]
            a, b, c = slow_scored(candidates, owner, truth, learned, taus)
            tp, fp, fn = tp + a, fp + b, fn + c
        f1[position] = 2 * tp / max(2 * tp + fp + fn, 1)
    best = sorted(POSITIONS, key=lambda p: (-f1[p], abs(p - DEFAULT_POSITION)))[0]
    return best, f1


def one_class(motions: list[float], wrong: list[float]) -> FoldParts:
    """A fold of one class: a motion every 10 frames matched at each of ``motions``' costs, then the
    ``wrong`` candidates, each on frames of its own."""
    candidates = [(c, 10 * i + 9, 0, 10 * i) for i, c in enumerate(motions)]
    truth = [(0, 10 * i, 10 * i + 9) for i in range(len(motions))]
    at = 10 * len(motions)
    candidates += [(c, at + 10 * i + 9, 0, at + 10 * i) for i, c in enumerate(wrong)]
    return candidates, [0], truth, frozenset({0}), at + 10 * len(wrong)


@pytest.mark.parametrize(
    ("held", "best"),
    [
        # a new person's motion costs more than the others': only τ far from their motions finds it
        (one_class([0.24], [0.4]), 0.75),
        # a new person's wrong detection just above the others' motions: only τ near them keeps it out
        (one_class([0.12], [0.17]), 0.25),
        # every position scores the same: the default
        (one_class([0.1], [0.3]), DEFAULT_POSITION),
    ],
)
def test_position_with_the_best_f1_on_folds_left_out(held: FoldParts, best: float) -> None:
    folds = [one_class([0.1], [0.3]), one_class([0.1], [0.3]), held]
    got = choose_position([as_fold(p) for p in folds], fallback=0.1)
    assert got == slow_position(folds)
    assert got[0] == best
    assert (len(set(got[1].values())) == 1) == (best == DEFAULT_POSITION)


def test_position_needs_two_folds() -> None:
    assert choose_position([], fallback=0.1) == (DEFAULT_POSITION, {})
    assert choose_position([as_fold(one_class([0.24], [0.4]))], fallback=0.1) == (DEFAULT_POSITION, {})


@settings(max_examples=60, deadline=None)
@hypothesis_given(st.data())
def test_position_is_the_best_of_the_nested_folds(data: st.DataObject) -> None:
    first = data.draw(fold_parts())
    folds = [first, *data.draw(st.lists(fold_parts(owner=first[1]), min_size=1, max_size=2))]
    assert choose_position([as_fold(p) for p in folds], fallback=0.1) == slow_position(folds)


# -------------------------------------------------------------------------------- two styles


def style(on: range, frames: int, rng: np.random.Generator, flips: int = 4) -> BoolArray:
    """``frames`` frames with the features ``on`` set, a few entries flipped."""
    m = np.zeros((frames, 39), dtype=bool)
    m[:, list(on)] = True
    for _ in range(flips):
        m[rng.integers(frames), rng.integers(39)] ^= True
    return m


def test_two_clusters_split_two_styles() -> None:
    rng = np.random.default_rng(3)
    a, b = range(0, 20), range(19, 39)
    order = "AABABBAB"
    examples = [style(a if s == "A" else b, int(rng.integers(15, 25)), rng) for s in order]
    assert two_clusters(examples) == tuple(int(s == "B") for s in order)
    # the cluster of the first example is 0, whichever style it is
    swapped = "BAABBAAB"
    examples = [style(a if s == "A" else b, int(rng.integers(15, 25)), rng) for s in swapped]
    assert two_clusters(examples) == tuple(int(s == "A") for s in swapped)


def test_two_clusters_none_when_a_style_is_too_small() -> None:
    rng = np.random.default_rng(4)
    a, b = range(0, 20), range(19, 39)
    assert MIN_MEMBER == 3
    five = [style(a if i % 2 else b, 20, rng) for i in range(2 * MIN_MEMBER - 1)]
    assert two_clusters(five) is None  # too few examples for two clusters of 3
    lone = [style(a, 20, rng) for _ in range(6)] + [style(b, 20, rng)]
    assert two_clusters(lone) is None  # the other style has one example
    assert two_clusters(lone, smallest=1) == (0, 0, 0, 0, 0, 0, 1)


# ---------------------------------------------------------------------------- real clips, folds


def test_clip_costs_are_the_best_subsequence_dtw_costs(labelled: Labelled) -> None:
    squats = [m for _, m in labelled["squat1Reps"]]
    template = learn(squats[:2], keyframes=0).quantised
    clips = squats[2:] + [m for _, m in labelled["hopBothLegs1hops"]] + [squats[0][:5]]
    got = clip_costs(template, clips, "toolbox")
    t = expand(template)
    for clip, cost in zip(clips, got, strict=True):
        delta = subsequence_dtw(retrieval_cost(t.values, t.weights, clip.T.astype(float)), "toolbox").delta
        assert cost == delta.min()
    assert got[-1] == math.inf  # 5 frames cannot hold a template with steps of slope at most 2
    assert fixed(got[:-1]).max() > 0


def unpack(codes: npt.NDArray[np.uint64]) -> BoolArray:
    """Packed codes back to ``(N, 39)`` frames, bit by bit."""
    return np.asarray([[(int(c) >> i) & 1 == 1 for i in range(39)] for c in codes], dtype=bool).reshape(
        -1, 39
    )


def test_stream_candidates_are_the_local_minima_up_to_the_cap(labelled: Labelled) -> None:
    """A squat template over hops, random frames, inverted squats and squats: every local minimum
    of its subsequence DTW (computed independently, float costs) at or below :data:`CAP`, none above."""
    template = learn([m for g, m in labelled["squat1Reps"] if g != "dg"], keyframes=0).quantised
    rng = np.random.default_rng(5)
    squats = [m for g, m in labelled["squat1Reps"] if g == "dg"]
    hops = [m for _, m in labelled["hopBothLegs1hops"]]
    frames = np.concatenate([*hops, rng.random((80, 39)) < 0.5, *(~m for m in squats), *squats])
    got = stream_candidates(template, pack(frames), "toolbox", 4)
    t = expand(template)
    dtw = subsequence_dtw(retrieval_cost(t.values, t.weights, frames.T.astype(float)), "toolbox")
    minima = ref_local_minima(dtw.delta, dtw.start, math.inf)
    assert got == [Candidate(m.cost, m.end, 4, m.start) for m in minima if m.cost <= CAP]
    assert any(x.cost > 0.3 for x in got) and any(CAP < m.cost < math.inf for m in minima)
    assert stream_candidates(template, np.zeros(0, dtype=np.uint64), "toolbox", 4) == []


@pytest.mark.slow
def test_calibration_leaves_each_actor_out(labelled: Labelled, calibrated: Calibrated) -> None:
    names = list(labelled)
    found = calibrated.folds
    assert [f.group for f in found] == ["bd", "bk", "dg"] and calibrated.groups == "actors"
    for f in found:
        codes, truth = fold_stream(labelled, f.group)
        np.testing.assert_array_equal(f.codes, codes)
        assert f.truth == tuple(truth) and f.owner == (0, 1) and f.learned == {0, 1}
        frames = unpack(f.codes)
        for k, name in enumerate(names):
            # the template of the other actors' examples, run over the stream independently
            template = expand(learn([m for g, m in labelled[name] if g != f.group], keyframes=0).quantised)
            dtw = subsequence_dtw(
                retrieval_cost(template.values, template.weights, frames.T.astype(float)), "toolbox"
            )
            expected = [
                Candidate(m.cost, m.end, k, m.start) for m in ref_local_minima(dtw.delta, dtw.start, CAP)
            ]
            assert [x for x in f.candidates if x.template == k] == sorted(expected)
            assert expected, (f.group, name)
            trials = f.trials[k]
            assert [t.generalisation for t in trials] == list(designs(3))
            assert all(t.positives.shape == (2,) for t in trials)
    # τ: the position by nested folds, the thresholds over all folds
    assert (calibrated.position, dict(calibrated.position_f1)) == choose_position(found)
    assert calibrated.position in POSITIONS and set(calibrated.position_f1) == set(POSITIONS)
    choices = thresholds(found, position=calibrated.position)
    taus = [None if c is None else c.tau for c in choices]
    for k, name in enumerate(names):
        cc = calibrated.classes[name]
        c, choice = cc.calibration, choices[k]
        assert choice is not None and cc.members is None and cc.second is None
        assert (c.tau, c.recall, c.precision) == (choice.tau, choice.recall, choice.precision)
        assert c.calibrated and c.folds == 3 and c.positives == 6
        assert c.negatives == sum(len(outcomes(f, taus)[1][k]) for f in found)
        assert (
            c.recall is not None and 0 <= c.recall <= 1 and c.precision is not None and 0 <= c.precision <= 1
        )
        assert c.method.startswith("left-out streams of 3 folds (actors): ")
        assert f"{calibrated.position:g} of the way to the next wrong detection" in c.method
        assert cc.keyframes is None or cc.keyframes.generalisation in designs(3)
        assert cc.reason
        # keyframes first: the stream-wide DTW only where no design holds on the left-out motions
        held = [f for f in found if any(c == k for c, _, _ in f.truth) and k in f.learned]
        gate, reason = choose_gate(held, k, taus, spare=calibrated.spare, wider=calibrated.wider)
        assert (cc.keyframes, cc.reason) == (gate, reason)
    # the spare mismatches: the fewest whose nested-fold share of motions kept reaches MIN_KEPT
    assert (calibrated.spare, dict(calibrated.spare_kept)) == choose_spare(found, taus)
    shares = [calibrated.spare_kept[s] for s in SPARES]
    assert shares == sorted(shares)  # a keyframe that tolerates more misses no more motions
    reaching = [s for s in SPARES if calibrated.spare_kept[s] >= MIN_KEPT]
    assert calibrated.spare == (reaching[0] if reaching else SPARES[-1])
    # the windows' spare width: the fewest steps whose nested-fold share of motions kept reaches MIN_KEPT
    assert (calibrated.wider, dict(calibrated.wider_kept)) == choose_wider(found, taus)
    assert set(calibrated.wider_kept) == set(WIDER) and all(
        0 <= x <= 1 for x in calibrated.wider_kept.values()
    )
    reaching = [s for s in WIDER if calibrated.wider_kept[s] >= MIN_KEPT]
    assert calibrated.wider == (reaching[0] if reaching else WIDER[-1])


def test_a_class_without_a_fold_keeps_the_given_tau(labelled: Labelled) -> None:
    """One actor's examples only, grouped by actor: no fold, every τ given."""
    one = {name: [("bd", m) for g, m in items if g == "bd"] for name, items in labelled.items()}
    got = calibrate(one, tau=0.07, keyframes=0)
    assert got.folds == () and (got.position, got.position_f1) == (DEFAULT_POSITION, {})
    for cc in got.classes.values():
        assert cc.calibration == Calibration(0.07, f"{GIVEN} (no fold: nothing to calibrate on)")
        assert (cc.keyframes, cc.reason) == (None, "no keyframes asked for: stream-wide DTW")


# ------------------------------------------------------------------------------ the keyframe gate


def gate_of(
    found: Sequence[Fold], k: int, taus: Sequence[float | None], spare: int = 0
) -> tuple[Generalisation, float, int] | None:
    """:func:`slow_gate` of real folds, their parts as plain values."""
    return slow_gate(
        [
            GateFold(
                [(x.cost, x.end, x.template, x.start) for x in f.candidates],
                f.owner,
                f.truth,
                f.codes.tolist(),
                [(t.generalisation, t.query, t.positives.tolist(), t.length, t.extent) for t in f.trials[k]],
            )
            for f in found
        ],
        k,
        taus,
        MIN_KEPT,
        DEFAULT_INDEX_RATE,
        max(1, round(DEFAULT_MAX_GAP_S * DEFAULT_INDEX_RATE)),
        spare,
        SLACKS,
    )


GATE_REASON = (
    r"keyframes first: \d keyframes, up to \d mismatch(es)?, windows \d+ frames wider: opened on (\d+)/(\d+) "
    r"left-out motions and "
    r"\d+\.\d% of other motions' frames \(\d+\.\d matches a minute of them\), (\d+) -> (\d+) wrong detections"
)


@pytest.mark.parametrize(
    ("held", "k", "taus"),
    [
        ((0, 1, 2), 1, [None, 0.3]),
        ((0, 1, 2), 0, [0.3, None]),
        ((0, 1, 2), 1, [None, 0.2]),
        ((0,), 1, [None, 0.15]),
        ((0, 1, 2), 0, [0.1, 0.1]),
    ],
)
def test_gate_against_its_definition_on_real_folds(
    calibrated: Calibrated, held: tuple[int, ...], k: int, taus: list[float | None]
) -> None:
    found = [calibrated.folds[i] for i in held]
    gate, why = choose_gate(found, k, taus)
    literal = gate_of(found, k, taus)
    if literal is None:
        assert gate is None and why.startswith("no keyframes held on the left-out motions"), why
        return
    assert gate is not None and gate.generalisation == literal[0] and gate.others == pytest.approx(literal[1])
    assert gate.slack == literal[2]
    shape = re.fullmatch(GATE_REASON, why)
    assert shape is not None, why
    opened, motions, wrong, wrong_gated = map(int, shape.groups()[1:])
    assert (opened, motions, wrong, wrong_gated) == (gate.opened, gate.motions, gate.wrong, gate.wrong_gated)
    assert opened >= MIN_KEPT * motions and wrong_gated <= wrong
    # with a spare mismatch the gates are ranked as they will run, widened where that still holds
    wide, why_wide = choose_gate(found, k, taus, spare=1)
    literal_wide = gate_of(found, k, taus, spare=1)
    assert wide is not None and literal_wide is not None and why_wide.startswith("keyframes first: ")
    assert wide.generalisation == literal_wide[0] and wide.others == pytest.approx(literal_wide[1])
    assert wide.slack == literal_wide[2]
    assert wide.opened >= MIN_KEPT * wide.motions


def slow_f1_in_windows(
    found: Sequence[Fold], taus: list[float | None], gates: dict[int, GateReport], first: set[int]
) -> float:
    """Every class's F1 over the folds read directly: a candidate of a class of ``first`` exists
    only inside one of its windows (brute-force keyframe matches, :func:`tests.naive.slow_windows`);
    a detection is an existing candidate not beaten by an existing one before it (same motion, of
    its class or within its own τ), within its τ; right when half of it lies in a motion of its
    class."""
    tp = fp = fn = 0
    for f in found:
        sets = {
            fs: [(int(c) >> SET_SLICES[fs].start) & ((1 << (SET_SLICES[fs].stop - SET_SLICES[fs].start)) - 1)
                 for c in f.codes]
            for fs in FEATURE_SETS
        }  # fmt: skip
        spans: dict[int, list[tuple[int, int]]] = {}
        for k in first:
            trial = next(
                (t for t in f.trials.get(k, ()) if t.generalisation == gates[k].generalisation), None
            )
            if trial is None:
                continue
            before, after = slow_extent(trial.query, trial.length, gates[k].slack, trial.extent)
            back = sum(hi or 0 for _, hi in query_bounds(trial.query, 30.0, 60)) + before
            matches = [(a, at) for a, at, _ in keyframe_matches(sets, trial.query, 60)]
            spans[k] = [(a, b) for a, b, _, _ in slow_windows(matches, before, after, back)]
        ordered = sorted((x.cost, x.end, x.template, x.start) for x in f.candidates)
        exists = [
            f.owner[t] not in spans or any(a <= start and end <= b for a, b in spans[f.owner[t]])
            for _, end, t, start in ordered
        ]
        found_motions, wrong = set(), 0
        for i, (cost, end, t, start) in enumerate(ordered):
            if not exists[i] or taus[t] is None or cost > taus[t]:  # type: ignore[operator]
                continue
            beaten = any(
                exists[j]
                and (f.owner[t2] == f.owner[t] or (taus[t2] is not None and c2 <= taus[t2]))  # type: ignore[operator]
                and 2 * (min(end, e2) - max(start, s2) + 1) > min(end - start, e2 - s2) + 1
                for j, (c2, e2, t2, s2) in enumerate(ordered[:i])
            )
            if beaten:
                continue
            motion = next(
                (
                    m
                    for m, (c, a, b) in enumerate(f.truth)
                    if c == f.owner[t] and 2 * (min(end, b) - max(start, a) + 1) >= end - start + 1
                ),
                None,
            )
            if motion is None:
                wrong += 1
            else:
                found_motions.add(motion)
        motions = [m for m, (c, _, _) in enumerate(f.truth) if c in f.learned]
        hit = sum(m in found_motions for m in motions)
        tp, fp, fn = tp + hit, fp + wrong, fn + len(motions) - hit
    return 2 * tp / (2 * tp + fp + fn) if tp else 0.0


@pytest.mark.parametrize("taus", [[0.3, 0.3], [0.15, 0.4], [0.4, 0.12]])
def test_modes_settled_by_every_class_f1(calibrated: Calibrated, taus: list[float | None]) -> None:
    """windows_f1 against its definition read directly for every set of classes keyframes first;
    settle_modes: every gated class keyframes first, then one by one set to stream-wide DTW where
    every class's F1 over the folds rises."""
    found = list(calibrated.folds)
    gates = {}
    for k in (0, 1):
        gate, _ = choose_gate(found, k, taus)
        if gate is not None:
            gates[k] = gate
    assert gates
    for first in ({0, 1}, {0}, {1}, set()):
        first &= set(gates)
        assert windows_f1(found, taus, gates, first) == pytest.approx(
            slow_f1_in_windows(found, taus, gates, first)
        )
    first = set(gates)
    now = slow_f1_in_windows(found, taus, gates, first)
    expected = {}
    for k in sorted(gates):
        score = slow_f1_in_windows(found, taus, gates, first - {k})
        if score > now:
            expected[k] = (now, score)
            first, now = first - {k}, score
    got = settle_modes(found, taus, gates)
    assert got.keys() == expected.keys()
    for k, (a, b) in got.items():
        assert (a, b) == pytest.approx(expected[k]) and b > a


@settings(max_examples=60, deadline=None)
@hypothesis_given(st.lists(streams(shortest=1, longest=25), min_size=1, max_size=5), queries(tolerant=True))
def test_kept_in_a_row_is_a_match_completed_inside_each(
    examples: list[dict[FeatureSet, list[int]]], query: KeyframeQuery
) -> None:
    """kept_in_a_row against its definition: the examples back to back as one stream, every
    keyframe match by brute force (gaps capped at 60 frames), an example kept when a match is
    complete (its first frame of the last keyframe) inside it."""
    joined = {fs: [c for e in examples for c in e[fs]] for fs in FEATURE_SETS}
    ends = np.cumsum([len(e["lower"]) for e in examples])
    done = [False] * len(examples)
    for _, at, _ in keyframe_matches(joined, query, 60):
        done[int(np.searchsorted(ends, at, side="right"))] = True
    codes = [np.array(stream_codes(e), dtype=np.uint64) for e in examples]
    assert kept_in_a_row(query, codes, 30.0, 60).tolist() == done


def test_a_design_that_misses_a_left_out_motion_is_not_chosen(calibrated: Calibrated) -> None:
    """The gate's design is chosen again once its keyframes are said to miss a left-out motion (of
    the first class with a gate that holds): the next one holds, and it is what the definition
    gives."""
    taus: list[float | None] = [None, 0.3]
    held = [
        (k, g) for k in range(len(calibrated.classes)) if (g := choose_gate(calibrated.folds, k, taus)[0])
    ]
    assert held
    k, first = held[0]
    missing = [
        dataclasses.replace(
            f,
            trials={
                **f.trials,
                k: tuple(
                    dataclasses.replace(t, positives=np.zeros_like(t.positives))
                    if t.generalisation == first.generalisation
                    else t
                    for t in f.trials[k]
                ),
            },
        )
        for f in calibrated.folds
    ]
    second, _ = choose_gate(missing, k, taus)
    literal = gate_of(missing, k, taus)
    assert second is not None and literal is not None
    assert second.generalisation != first.generalisation and second.generalisation == literal[0]


def test_no_gate_without_folds_or_keyframes_that_hold() -> None:
    fold = fold_of("g", [(0, 0, 9)], [(0.05, 9, 0, 0)], owner=(0,), learned=frozenset({0}))
    assert choose_gate([fold], 0, [0.1]) == (None, "no fold to learn keyframes on: stream-wide DTW")
    assert choose_gate([], 0, [0.1]) == (None, "no fold to learn keyframes on: stream-wide DTW")
    trial = KeyframeTrial(designs(3)[0], None, np.array([True, False]))  # type: ignore[arg-type]
    with_trials = make_fold(
        "g", fold.codes, fold.truth, fold.owner, fold.candidates, fold.learned, {0: (trial,)}
    )
    assert choose_gate([with_trials], 0, [0.1]) == (
        None,
        "no keyframes held on the left-out motions (the best kept 50% in its worst fold): stream-wide DTW",
    )


@pytest.mark.parametrize(
    "g",
    [
        designs(3)[0],
        Generalisation(2, 1.0, 2, 3),
        Generalisation(1, 0.5, 0, 1),
        Generalisation(2, 1.0, 2, 4, 5, 2),
    ],
)
def test_generalised_keyframes_keep_every_training_clip(labelled: Labelled, g: Generalisation) -> None:
    hops = [m for _, m in labelled["hopBothLegs1hops"]]
    hard = learn_hard(hops).template
    query = automatic_keyframes(hard, hops, 3, "hop", 30.0, g)
    assert keyframes_kept(query, clip_sets(hops), 30.0).all()
    fixed = [sum(v != 0.5 for v in k.values) for k in query.keyframes]
    assert g.fixed is None or max(fixed) <= g.fixed


def test_a_margin_widens_every_gap(labelled: Labelled) -> None:
    hops = [m for _, m in labelled["hopBothLegs1hops"]]
    hard = learn_hard(hops).template
    thesis = automatic_keyframes(hard, hops, 3, "hop", 30.0)
    wide = automatic_keyframes(hard, hops, 3, "hop", 30.0, Generalisation(margin=1.0))
    assert [k.values for k in wide.keyframes] == [k.values for k in thesis.keyframes]
    for (d0, s0), (d1, s1) in zip(thesis.gaps(30.0), wide.gaps(30.0), strict=True):
        lo0, hi0 = gap_bounds(d0, s0)
        lo1, hi1 = gap_bounds(d1, s1)
        assert lo1 <= lo0 and (hi1 is None or (hi0 is not None and hi1 >= hi0))
        assert (lo1, hi1) != (lo0, hi0)


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"window": -1}, "window, margin, min_gap and mismatches must not be negative"),
        ({"margin": math.nan}, "window, margin, min_gap and mismatches must not be negative"),
        ({"mismatches": -1}, "window, margin, min_gap and mismatches must not be negative"),
        ({"fixed": 0}, "fixed must be at least 1, got 0"),
        ({"count": 0}, "count must be at least 1, got 0"),
    ],
)
def test_generalisation_values_checked(kwargs: dict[str, float], message: str) -> None:
    with pytest.raises(ValueError, match=re.escape(message)):
        Generalisation(**kwargs)  # type: ignore[arg-type]


# ----------------------------------------------------------------------------------- actor column


def test_actor_column_present_and_absent(tmp_path: Path) -> None:
    rows = read_training_manifest(write_clips(tmp_path / "a.csv", CLIPS[:3]))
    assert [r.actor for r in rows] == ["bd", "bd", "bk"]
    plain = write_training(tmp_path / "b.csv", actor_rows(CLIPS[:3], actor=False), "class,asf,amc")
    rows = read_training_manifest(plain)
    asf_bd, asf_bk = hdm05_clip("bd", "squat1Reps", 1)[0], hdm05_clip("bk", "squat1Reps", 13)[0]
    assert [r.actor for r in rows] == [str(asf_bd.resolve())] * 2 + [str(asf_bk.resolve())]
    # relative paths written differently name the same person
    (tmp_path / "sub").mkdir()
    rel = Path("..") / Path(*[".."] * len(tmp_path.parts)) / HDM_ASF.relative_to("/")
    lines = [f"squat1Reps,{HDM_ASF},{HDM_AMC}", f"squat1Reps,sub/{rel},{HDM_AMC}"]
    rows = read_training_manifest(write_training(tmp_path / "c.csv", lines, "class,asf,amc"))
    assert rows[0].actor == rows[1].actor == str(HDM_ASF.resolve())
    clips = [clip for clip, _ in read_examples(tmp_path / "a.csv")["squat1Reps"]]
    assert [c.actor for c in clips] == ["bd", "bd", "bk"]


@pytest.mark.parametrize(
    ("cell", "message"),
    [
        ("", "the 'actor' field is blank: name the person of every row, or leave out the column"),
        ("bad\x07name", "actor 'bad\\x07name': at most 200 printable characters"),
        ("x" * 201, f"actor '{'x' * 60}': at most 200 printable characters"),
    ],
)
def test_actor_column_errors_name_file_and_line(tmp_path: Path, cell: str, message: str) -> None:
    good = f"squat1Reps,{HDM_ASF},{HDM_AMC},bd"
    path = write_training(
        tmp_path / "m.csv", [good, f"squat1Reps,{HDM_ASF},{HDM_AMC},{cell}"], "class,asf,amc,actor"
    )
    with pytest.raises(ManifestError, match=f"^{re.escape(str(path))}:3: {re.escape(message)}"):
        read_training_manifest(path)


# --------------------------------------------------------------------------------------- library


@pytest.fixture(scope="module")
def library(manifest: Path, calibrated: Calibrated) -> Library:
    """squat1Reps as calibration learned it (stream-wide DTW, no keyframes), hopBothLegs1hops with
    a τ given and keyframes (gated)."""
    examples = read_examples(manifest)
    squat = calibrated.classes["squat1Reps"]
    return Library(
        30.0,
        {
            "squat1Reps": learn_class(
                "squat1Reps",
                examples["squat1Reps"],
                keyframes=0,
                calibration=squat.calibration,
                mode=DTW,
                mode_reason=squat.reason,
            ),
            "hopBothLegs1hops": learn_class("hopBothLegs1hops", examples["hopBothLegs1hops"], tau=0.08),
        },
    )


def test_library_v4_keeps_the_calibration_and_mode(library: Library, tmp_path: Path) -> None:
    save_library(library, tmp_path / "lib")
    meta = json.loads((tmp_path / "lib" / "library.json").read_text())
    assert meta["version"] == 4
    squat, hop = meta["classes"]["squat1Reps"], meta["classes"]["hopBothLegs1hops"]
    assert squat["calibration"]["folds"] == 3 and squat["training"][2]["actor"] == "bk"
    assert (squat["mode"], squat["mode_reason"], squat["members"], squat["keyframes"]) == (
        "dtw",
        library.classes["squat1Reps"].mode_reason,
        [],
        [],
    )
    assert squat["mode_reason"] and hop["mode"] == "keyframes" and hop["keyframes"]
    assert hop["calibration"] == {
        "method": GIVEN,
        "folds": 0,
        "positives": 0,
        "negatives": 0,
        "recall": None,
        "precision": None,
    }
    loaded = load_library(tmp_path / "lib")
    for name, cls in library.classes.items():
        got = loaded.classes[name]
        assert got.calibration == cls.calibration == cls.provenance
        assert (got.tau, got.training, got.mode, got.mode_reason) == (
            cls.tau,
            cls.training,
            cls.mode,
            cls.mode_reason,
        )
        assert got.keyframes == cls.keyframes and got.variants == ()
    assert loaded.classes["squat1Reps"].provenance.calibrated
    assert loaded.classes["hopBothLegs1hops"].tau == 0.08


def test_library_v3_loads_with_modes_resolved(library: Library, tmp_path: Path) -> None:
    """A version 3 library has no mode: a class with keyframes is gated by them, one without is
    found by the stream-wide DTW; fields of version 4 in it are refused."""
    save_library(library, tmp_path / "lib")
    path = tmp_path / "lib" / "library.json"
    meta = json.loads(path.read_text())
    meta["version"] = 3
    for entry in meta["classes"].values():
        for key in ("mode", "mode_reason", "members"):
            del entry[key]
    path.write_text(json.dumps(meta))
    loaded = load_library(tmp_path / "lib")
    squat, hop = loaded.classes["squat1Reps"], loaded.classes["hopBothLegs1hops"]
    assert (hop.mode, hop.mode_reason) == (GATED, "") and hop.keyframes == library.classes[
        "hopBothLegs1hops"
    ].keyframes
    assert (squat.mode, squat.keyframes) == (DTW, None)
    assert squat.calibration == library.classes["squat1Reps"].calibration and squat.provenance.calibrated
    meta["classes"]["squat1Reps"]["mode"] = "dtw"
    path.write_text(json.dumps(meta))
    with pytest.raises(LibraryFormatError, match=r"classes\.squat1Reps\.mode: unknown field"):
        load_library(tmp_path / "lib")


def test_library_v2_still_loads(library: Library, tmp_path: Path) -> None:
    save_library(library, tmp_path / "lib")
    path = tmp_path / "lib" / "library.json"
    meta = json.loads(path.read_text())
    meta["version"] = 2
    for entry in meta["classes"].values():
        for key in ("calibration", "mode", "mode_reason", "members"):
            del entry[key]
        for clip in entry["training"]:
            del clip["actor"]
    path.write_text(json.dumps(meta))
    loaded = load_library(tmp_path / "lib")
    squat = loaded.classes["squat1Reps"]
    assert squat.tau == library.classes["squat1Reps"].tau
    assert squat.provenance == Calibration(squat.tau, f"{GIVEN} (a version 2 library)")
    assert [c.actor for c in squat.training] == [c.asf for c in squat.training]
    np.testing.assert_array_equal(squat.quantised.values, library.classes["squat1Reps"].quantised.values)
    assert squat.mode == DTW and loaded.classes["hopBothLegs1hops"].mode == GATED
    # fields of version 3 in a version 2 library are refused, as unknown fields are
    meta["classes"]["squat1Reps"]["calibration"] = {}
    path.write_text(json.dumps(meta))
    with pytest.raises(LibraryFormatError, match=r"classes\.squat1Reps\.calibration: unknown field"):
        load_library(tmp_path / "lib")


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ({"calibration": None}, "classes.squat1Reps.calibration: must be a mapping, got nothing"),
        ({"calibration/recall": None}, "classes.squat1Reps.calibration.recall: a calibrated tau (folds > 0)"),
        ({"calibration/precision": 1.5}, "classes.squat1Reps.calibration.precision: must be"),
        ({"calibration/folds": -1}, "classes.squat1Reps.calibration.folds: must be"),
        ({"calibration/method": ""}, "classes.squat1Reps.calibration.method: must be a non-empty string"),
        ({"mode_reason": 3}, "classes.squat1Reps.mode_reason: must be a string"),
        ({"members": {}}, "classes.squat1Reps.members: must be a list"),
    ],
)
def test_library_v4_calibration_errors_name_the_field(
    library: Library, tmp_path: Path, change: dict[str, object], message: str
) -> None:
    save_library(library, tmp_path / "lib")
    path = tmp_path / "lib" / "library.json"
    meta = json.loads(path.read_text())
    assert meta["version"] == 4
    for key, value in change.items():
        node = meta["classes"]["squat1Reps"]
        *parents, last = key.split("/")
        for p in parents:
            node = node[p]
        node[last] = value
    path.write_text(json.dumps(meta))
    with pytest.raises(LibraryFormatError, match=f"^{re.escape(str(path))}: {re.escape(message)}"):
        load_library(tmp_path / "lib")


# ------------------------------------------------------------------------------------------- CLI


@pytest.mark.slow
def test_learn_calibrates_and_search_uses_the_class_tau(
    manifest: Path, labelled: Labelled, tmp_path: Path
) -> None:
    # with a given τ of 0.13, a class with no wrong detection above its positives keeps 0.13
    learn_args: list[str | Path] = [
        "learn",
        "--manifest",
        manifest,
        "--out",
        tmp_path / "lib",
        "--keyframes",
        "0",
    ]
    result = mocapd(*learn_args, "--tau", "0.13")
    assert result.returncode == 0, result.stderr
    library = load_library(tmp_path / "lib")
    expected = calibrate(labelled, tau=0.13, keyframes=0)
    for name in ("squat1Reps", "hopBothLegs1hops"):
        cls, want = library.classes[name], expected.classes[name]
        assert cls.calibration == want.calibration and cls.tau == want.calibration.tau
        assert (cls.mode, cls.mode_reason, cls.keyframes) == (DTW, want.reason, None)
    squat = library.classes["squat1Reps"]
    assert squat.provenance.calibrated and squat.tau != 0.1
    assert "actors:     3" in result.stdout
    assert f"folds:      3 (actors left out); tau placed {expected.position:g} of the way" in result.stdout
    assert (
        f"squat1Reps: stream-wide DTW (no keyframes asked for: stream-wide DTW); tau {squat.tau:.4g} "
        f"calibrated: recall {squat.provenance.recall:.2f}, precision {squat.provenance.precision:.2f} on 6 "
        "left-out motions" in result.stdout
    )

    db = write_manifest(tmp_path / "db.csv", [hdm05_clip("dg", "squat1Reps", 27)], extra=False)
    save_index(build_index(read_manifest(db)), tmp_path / "idx")
    search: list[str | Path] = [
        "search",
        "--index",
        tmp_path / "idx",
        "--library",
        tmp_path / "lib",
        "--class",
        "squat1Reps",
    ]
    shown = mocapd(*search)
    assert_ok(shown)
    assert f"tau {squat.tau:g} calibrated, toolbox steps" in shown.stdout.splitlines()[0]
    overridden = mocapd(*search, "--tau", "0.5")
    assert_ok(overridden)
    assert "tau 0.5 --tau, toolbox steps" in overridden.stdout.splitlines()[0]
    default = hits_json(mocapd(*search, "--json").stdout)
    explicit = hits_json(mocapd(*search, "--json", "--tau", repr(squat.tau)).stdout)
    assert default == explicit and all(float(str(h["cost"])) <= squat.tau + 1e-6 for h in default)
    assert default

    result = mocapd(*learn_args, "--no-calibrate")
    assert result.returncode == 0, result.stderr
    library = load_library(tmp_path / "lib")
    assert all(
        c.provenance == Calibration(0.1, f"{GIVEN} (--no-calibrate)") for c in library.classes.values()
    )
    assert "squat1Reps: stream-wide DTW; tau 0.1 given, not calibrated (--no-calibrate)" in result.stdout
    assert "folds:" not in result.stdout
    given_run = mocapd(*search)
    assert "tau 0.1 given, toolbox steps" in given_run.stdout.splitlines()[0]


@pytest.mark.slow
def test_learn_with_one_actor_calibrates_on_groups_of_takes(tmp_path: Path) -> None:
    clips = [(c, "bd", t) for c in ("squat1Reps", "hopBothLegs1hops") for t in takes(c, "bd")[:3]]
    manifest = write_clips(tmp_path / "bd.csv", clips)
    result = mocapd("learn", "--manifest", manifest, "--out", tmp_path / "lib")
    assert result.returncode == 0, result.stderr
    assert "actors:     1" in result.stdout
    assert "folds:      3 (groups of one person's examples (one actor: at most 3) left out)" in result.stdout
    examples = read_examples(manifest)
    names = [n for n, items in examples.items() for _ in items]
    labels, what = groups([clip.actor for items in examples.values() for clip, _ in items], names)
    assert sorted(set(labels)) == ["take 1", "take 2", "take 3"]
    it = iter(labels)
    expected = calibrate(
        {n: [(next(it), m) for _, m in items] for n, items in examples.items()}, groups_are=what
    )
    assert [f.group for f in expected.folds] == ["take 1", "take 2", "take 3"]
    # nested folds over one person's takes say nothing of a new person: τ in the middle of the gap
    assert (expected.position, dict(expected.position_f1)) == (DEFAULT_POSITION, {})
    assert f"tau placed {DEFAULT_POSITION:g} of the way" in result.stdout
    library = load_library(tmp_path / "lib")
    for name, cls in library.classes.items():
        c = cls.provenance
        assert c.calibrated and c.folds == 3 and c.positives == 3
        assert c.method.startswith("left-out streams of 3 folds (groups of one person's examples")
        assert c == expected.classes[name].calibration
        assert cls.mode_reason == expected.classes[name].reason
        assert cls.mode == (DTW if expected.classes[name].keyframes is None else GATED)
