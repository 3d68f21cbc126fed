"""Per-class calibration (issue 12): the τ choice on hand-made cost lists and as a property, the
leave-one-actor-out folds on real HDM05 clips of three actors, the training manifest's ``actor``
column, library version 3 and the loading of version 2, and ``mocapd learn`` / ``mocapd search
--library`` using the calibrated τ unless told otherwise."""

from __future__ import annotations

import dataclasses
import json
import math
import re
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given as hypothesis_given
from hypothesis import settings
from hypothesis import strategies as st

from daemon.calibration import (
    GENERALISATIONS,
    GIVEN,
    MOST_GENERAL,
    Calibration,
    calibrate_class,
    choose_generalisation,
    choose_tau,
    clip_costs,
    clip_sets,
    keyframes_kept,
    retention,
)
from daemon.dtw import fixed, retrieval_cost, subsequence_dtw
from daemon.index_store import build_index, save_index
from daemon.keyframes import gap_bounds
from daemon.library import Library, LibraryFormatError, learn_class, load_library, save_library
from daemon.recordings import ManifestError, read_examples, read_manifest, read_training_manifest
from daemon.templates import Generalisation, automatic_keyframes, expand, learn, learn_hard
from tests.helpers import (
    HDM_AMC,
    HDM_ASF,
    assert_ok,
    hdm05_clip,
    hits_json,
    mocapd,
    write_manifest,
    write_training,
)

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


def actor_rows(clips: list[tuple[str, str, int]], actor: bool = True) -> list[str]:
    rows = []
    for c, a, t in clips:
        asf, amc = hdm05_clip(a, c, t)
        rows.append(f"{c},{asf},{amc},{a}" if actor else f"{c},{asf},{amc}")
    return rows


def write_clips(path: Path, clips: list[tuple[str, str, int]] = CLIPS) -> Path:
    return write_training(path, actor_rows(clips), "class,asf,amc,actor")


@pytest.fixture(scope="module")
def manifest(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return write_clips(tmp_path_factory.mktemp("calibration") / "clips.csv")


# ------------------------------------------------------------------------------------ choosing τ


def test_tau_at_the_best_f1_with_full_recall_midway_to_the_next_negative() -> None:
    # 4 positives: recall >= 0.95 needs all of them, so the threshold is at least 0.09
    choice = choose_tau([0.02, 0.04, 0.05, 0.09], [0.03, 0.12, 0.5], fallback=0.1)
    assert choice is not None and choice.feasible
    assert choice.tau == pytest.approx((0.09 + 0.12) / 2)
    assert (choice.recall, choice.precision) == (1.0, 0.8)
    assert choice.f1 == pytest.approx(2 * 4 / (2 * 4 + 1 + 0))


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


@settings(max_examples=300, deadline=None)
@hypothesis_given(costs, costs, st.sampled_from([0.5, 0.8, 0.95, 1.0]))
def test_tau_is_the_best_f1_subject_to_the_recall(
    positives: list[float], negatives: list[float], min_recall: float
) -> None:
    choice = choose_tau(positives, negatives, min_recall=min_recall, fallback=0.1)
    if not any(math.isfinite(p) for p in positives):
        assert choice is None
        return
    assert choice is not None and choice.tau > 0

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


# ------------------------------------------------------------------------------- real clips, folds


def test_clip_costs_are_the_best_subsequence_dtw_costs(manifest: Path) -> None:
    examples = read_examples(manifest)
    squats = [m for _, m in examples["squat1Reps"]]
    template = learn(squats[:2], keyframes=0).quantised
    clips = squats[2:] + [m for _, m in examples["hopBothLegs1hops"]] + [squats[0][:5]]
    got = clip_costs(template, clips, "toolbox")
    t = expand(template)
    for clip, cost in zip(clips, got, strict=True):
        delta = subsequence_dtw(retrieval_cost(t.values, t.weights, clip.T.astype(float)), "toolbox").delta
        assert cost == delta.min()
    assert got[-1] == math.inf  # 5 frames cannot hold a template with steps of slope at most 2
    assert fixed(got[:-1]).max() > 0


def test_calibration_leaves_each_actor_out(manifest: Path) -> None:
    examples = read_examples(manifest)
    labelled = {name: [(clip.actor, m) for clip, m in items] for name, items in examples.items()}
    found = calibrate_class(labelled, "squat1Reps", tau=0.1)
    c = found.calibration
    assert [f.actor for f in found.folds] == ["bd", "bk", "dg"]
    assert (c.folds, c.positives, c.negatives) == (3, 6, 6)
    assert c.calibrated and c.method.startswith("leave-one-actor-out over 3 actors (3 folds): best F1")
    assert c.recall is not None and c.recall >= 0.95 and c.precision is not None
    pos = np.concatenate([f.positive_costs for f in found.folds])
    neg = np.concatenate([f.negative_costs for f in found.folds])
    choice = choose_tau(pos, neg, fallback=0.1)
    assert choice is not None and (c.tau, c.recall, c.precision) == (
        choice.tau,
        choice.recall,
        choice.precision,
    )
    # fold "dg": the template of the bd/bk squats, costed over dg's clips
    dg = found.folds[2]
    template = learn([m for a, m in labelled["squat1Reps"] if a != "dg"], keyframes=0).quantised
    np.testing.assert_array_equal(
        dg.positive_costs,
        clip_costs(template, [m for a, m in labelled["squat1Reps"] if a == "dg"], "toolbox"),
    )
    assert [t.generalisation for t in dg.trials] == list(GENERALISATIONS)
    assert all(t.positives.shape == (2,) and 0 <= t.negatives <= 2 for t in dg.trials)
    # the keyframe generalisation chosen keeps >= 0.95 of the left-out clips in every fold if any
    # does, with the fewest clips of other classes; else the most general one
    kept = {g: min(retention(found.folds, g)) for g in GENERALISATIONS}
    if max(kept.values()) >= 0.95:
        others = {
            g: sum(t.negatives for f in found.folds for t in f.trials if t.generalisation == g)
            for g in GENERALISATIONS
        }
        assert kept[found.keyframes] >= 0.95
        assert others[found.keyframes] == min(others[g] for g in GENERALISATIONS if kept[g] >= 0.95)
    else:
        assert found.keyframes == MOST_GENERAL


def test_generalisation_when_the_folds_show_nothing(manifest: Path) -> None:
    """No generalisation keeps enough of a left-out actor's clips (here: squats scored against
    other classes' clips only): the most general is taken, not the thesis' exact rule."""
    examples = read_examples(manifest)
    labelled = {name: [(clip.actor, m) for clip, m in items] for name, items in examples.items()}
    found = calibrate_class(labelled, "squat1Reps", tau=0.1)
    empty = [
        dataclasses.replace(
            f,
            trials=tuple(dataclasses.replace(t, positives=np.zeros_like(t.positives)) for t in f.trials),
        )
        for f in found.folds
    ]
    assert choose_generalisation(empty) == MOST_GENERAL
    assert choose_generalisation([]) == MOST_GENERAL
    assert MOST_GENERAL in GENERALISATIONS


def test_one_actor_keeps_the_given_tau(manifest: Path) -> None:
    examples = read_examples(manifest)
    labelled = {name: [("bd", m) for _, m in items] for name, items in examples.items()}
    found = calibrate_class(labelled, "squat1Reps", tau=0.07)
    assert found.folds == ()
    assert found.calibration == Calibration(0.07, f"{GIVEN} (one actor: no leave-one-actor-out)")
    assert not found.calibration.calibrated
    assert found.keyframes == MOST_GENERAL  # nothing shows how a new person differs: be general


@pytest.mark.parametrize(
    "g", [GENERALISATIONS[0], Generalisation(2, 1.0, 2, 3), Generalisation(1, 0.5, 0, 1)]
)
def test_generalised_keyframes_keep_every_training_clip(manifest: Path, g: Generalisation) -> None:
    examples = read_examples(manifest)
    hops = [m for _, m in examples["hopBothLegs1hops"]]
    hard = learn_hard(hops).template
    query = automatic_keyframes(hard, hops, 3, "hop", 30.0, g)
    assert keyframes_kept(query, clip_sets(hops), 30.0).all()
    fixed = [sum(v != 0.5 for v in k.values) for k in query.keyframes]
    assert g.fixed is None or max(fixed) <= g.fixed


def test_a_margin_widens_every_gap(manifest: Path) -> None:
    hops = [m for _, m in read_examples(manifest)["hopBothLegs1hops"]]
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
        ({"window": -1}, "window, margin and min_gap must not be negative"),
        ({"margin": math.nan}, "window, margin and min_gap must not be negative"),
        ({"fixed": 0}, "fixed must be at least 1, got 0"),
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
def library(manifest: Path) -> Library:
    examples = read_examples(manifest)
    labelled = {name: [(clip.actor, m) for clip, m in items] for name, items in examples.items()}
    squat = calibrate_class(labelled, "squat1Reps").calibration
    return Library(
        30.0,
        {
            "squat1Reps": learn_class("squat1Reps", examples["squat1Reps"], calibration=squat),
            "hopBothLegs1hops": learn_class("hopBothLegs1hops", examples["hopBothLegs1hops"], tau=0.08),
        },
    )


def test_library_v3_keeps_the_calibration(library: Library, tmp_path: Path) -> None:
    save_library(library, tmp_path / "lib")
    meta = json.loads((tmp_path / "lib" / "library.json").read_text())
    assert meta["version"] == 3
    squat = meta["classes"]["squat1Reps"]
    assert squat["calibration"]["folds"] == 3 and squat["training"][2]["actor"] == "bk"
    assert meta["classes"]["hopBothLegs1hops"]["calibration"] == {
        "method": GIVEN,
        "folds": 0,
        "positives": 0,
        "negatives": 0,
        "recall": None,
        "precision": None,
    }
    loaded = load_library(tmp_path / "lib")
    for name, cls in library.classes.items():
        assert loaded.classes[name].calibration == cls.calibration == cls.provenance
        assert loaded.classes[name].tau == cls.tau and loaded.classes[name].training == cls.training
    assert loaded.classes["squat1Reps"].tau == loaded.classes["squat1Reps"].provenance.tau != 0.1


def test_library_v2_still_loads(library: Library, tmp_path: Path) -> None:
    save_library(library, tmp_path / "lib")
    path = tmp_path / "lib" / "library.json"
    meta = json.loads(path.read_text())
    meta["version"] = 2
    for entry in meta["classes"].values():
        del entry["calibration"]
        for clip in entry["training"]:
            del clip["actor"]
    path.write_text(json.dumps(meta))
    loaded = load_library(tmp_path / "lib")
    squat = loaded.classes["squat1Reps"]
    assert squat.tau == library.classes["squat1Reps"].tau
    assert squat.provenance == Calibration(squat.tau, f"{GIVEN} (a version 2 library)")
    assert [c.actor for c in squat.training] == [c.asf for c in squat.training]
    np.testing.assert_array_equal(squat.quantised.values, library.classes["squat1Reps"].quantised.values)
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
    ],
)
def test_library_v3_calibration_errors_name_the_field(
    library: Library, tmp_path: Path, change: dict[str, object], message: str
) -> None:
    save_library(library, tmp_path / "lib")
    path = tmp_path / "lib" / "library.json"
    meta = json.loads(path.read_text())
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


def test_learn_calibrates_and_search_uses_the_class_tau(manifest: Path, tmp_path: Path) -> None:
    result = mocapd("learn", "--manifest", manifest, "--out", tmp_path / "lib", "--keyframes", "0")
    assert result.returncode == 0, result.stderr
    library = load_library(tmp_path / "lib")
    examples = read_examples(manifest)
    labelled = {name: [(clip.actor, m) for clip, m in items] for name, items in examples.items()}
    for name in ("squat1Reps", "hopBothLegs1hops"):
        expected = calibrate_class(labelled, name, keyframes=0).calibration
        assert library.classes[name].calibration == expected and library.classes[name].tau == expected.tau
    squat = library.classes["squat1Reps"]
    assert "actors:     3" in result.stdout
    assert f"squat1Reps {squat.tau:.4g} calibrated: recall " in result.stdout

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

    result = mocapd(
        "learn", "--manifest", manifest, "--out", tmp_path / "lib", "--keyframes", "0", "--no-calibrate"
    )
    assert result.returncode == 0, result.stderr
    library = load_library(tmp_path / "lib")
    assert all(
        c.provenance == Calibration(0.1, f"{GIVEN} (--no-calibrate)") for c in library.classes.values()
    )
    assert "squat1Reps 0.1 given, not calibrated (--no-calibrate)" in result.stdout
    given_run = mocapd(*search)
    assert "tau 0.1 given, toolbox steps" in given_run.stdout.splitlines()[0]
