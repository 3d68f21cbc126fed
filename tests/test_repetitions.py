"""Cutting labelled runs into single repetitions (daemon.tools.repetitions) and the mocap6 adapter
(daemon.tools.mocap6): synthetic periodic runs with tempo changes are cut at one phase into k ± 1 pieces,
aperiodic ones are not cut, and the real mocap6 runs of 13_29, 13_30 and 14_14 give repetitions of
plausible length and number."""

from __future__ import annotations

import io
import itertools
import math
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from daemon.errors import FileAccessError
from daemon.plots import repetitions_png
from daemon.recordings import body_heading, read_recording, read_training_manifest
from daemon.tools.mocap6 import (
    CLASSES,
    SEGMENTS,
    TRIALS,
    Mocap6Error,
    TrialCuts,
    cut_trial,
    cut_trials,
    read_segments,
    repetition_rows,
    rows_csv,
    trial_recording,
)
from daemon.tools.repetitions import (
    MAX_TURN_DEG,
    cut_examples,
    cut_run,
    difference_function,
    estimate_period,
    run_signal,
)
from daemon.types import BoolArray, FloatArray, IntArray
from replay import JOINT_NAMES
from replay.kinematics import joint_positions
from tests.helpers import DATA

RATE = 30.0
SETTINGS = settings(deadline=None, max_examples=30, suppress_health_check=[HealthCheck.too_slow])


# ------------------------------------------------------------------------------------- synthetic


def periodic_run(seed: int, period: int, k: int, tempo: float) -> tuple[BoolArray, FloatArray, list[int]]:
    """``k`` repetitions of one random pattern of about ``period`` samples, each at its own tempo
    (length ``period * s``, s uniform in ``1 ± tempo``): features ``(n, 39)``, piecewise constant
    in the pattern's phase, joints ``(n, 4, 3)``, smooth periodic functions of the phase (joint 0,
    the root, still) and the true boundaries (k + 1 sample indices, the first 0, the last n)."""
    rng = np.random.default_rng(seed)
    lengths = [max(4, round(period * rng.uniform(1 - tempo, 1 + tempo))) for _ in range(k)]
    phase = np.concatenate([np.arange(m) / m for m in lengths])
    bounds = [0, *np.cumsum(lengths).tolist()]
    edges = np.sort(rng.uniform(0, 1, size=(39, 4)), axis=1)
    features = ((phase[:, None] >= edges[:, 0]) & (phase[:, None] < edges[:, 1])) | (
        (phase[:, None] >= edges[:, 2]) & (phase[:, None] < edges[:, 3])
    )
    harmonics = np.arange(1, 4)
    coefficients = rng.normal(size=(2, 3, 9)) / harmonics[None, :, None]
    angle = 2 * np.pi * phase[:, None] * harmonics[None, :]
    smooth = np.cos(angle) @ coefficients[0] + np.sin(angle) @ coefficients[1]
    joints = np.zeros((phase.shape[0], 4, 3))
    joints[:, 1:, :] = smooth.reshape(-1, 3, 3)
    return features, joints, bounds


@SETTINGS
@given(st.integers(0, 2**32 - 1), st.integers(15, 45), st.integers(3, 8), st.sampled_from([0.0, 0.05, 0.1]))
def test_periodic_runs_are_cut_into_k_pieces_at_one_phase(
    seed: int, period: int, k: int, tempo: float
) -> None:
    features, joints, bounds = periodic_run(seed, period, k, tempo)
    got = cut_run(features, RATE, joints)
    assert got.reason == ""
    assert abs(got.period.samples - period) <= max(2, tempo * period + 1)
    assert got.period.confidence > 0.5
    assert k - 1 <= len(got.repetitions) <= k + 1
    lengths = np.diff(bounds)
    # Each cut sits at the same fraction of its repetition as the first cut does (± 3 samples).
    which = int(np.searchsorted(bounds, got.cuts[0], side="right")) - 1
    phase = (got.cuts[0] - bounds[which]) / lengths[min(which, k - 1)]
    expected = [b + phase * m for b, m in zip(bounds[:-1], lengths, strict=True)] + [
        bounds[-1] + phase * period
    ]
    for cut in got.cuts:
        assert min(abs(cut - e) for e in expected) <= 3, (got.cuts, expected)
    for rep in got.repetitions:
        assert 0.7 * period * (1 - tempo) - 1 <= rep.length <= 1.4 * period * (1 + tempo) + 1


@SETTINGS
@given(st.integers(0, 2**32 - 1), st.integers(15, 40), st.integers(4, 8))
def test_periodic_features_alone_are_cut_into_k_pieces(seed: int, period: int, k: int) -> None:
    # Without tempo changes: piecewise constant features of repetitions 14, 15, 14, 15 samples long
    # repeat exactly every 29 samples and only roughly every 14.5, so jittered ones are ambiguous
    # (the joints of the test above make them smooth and unambiguous).
    features, _, _ = periodic_run(seed, period, k, 0.0)
    got = cut_run(features, RATE)
    assert got.reason == ""
    assert k - 1 <= len(got.repetitions) <= k + 1
    assert got.period.samples == period
    # Piecewise constant features can pass a similar pose a few samples off at a run's end.
    inner = got.repetitions[1:-1]
    assert all(abs(r.length - period) <= 2 for r in inner)
    assert all(abs(r.length - period) <= 0.3 * period for r in got.repetitions)


# ------------------------------------------------------------------ periodic classes in learning


@SETTINGS
@given(
    st.integers(0, 2**32 - 1),
    st.lists(st.sampled_from(["periodic", "turning", "still"]), min_size=1, max_size=6),
    st.integers(1, 3),
)
def test_a_class_is_cut_when_half_its_examples_repeat_a_cycle_without_turning(
    seed: int, kinds: list[str], count: int
) -> None:
    """Against the rule written out: an example gives repetitions when it repeats a cycle (4 to 8
    times here) and its heading spans at most MAX_TURN_DEG; the class is cut when at least half of
    its examples give some, each then its first ``count``, all at the phase of the first one cut."""
    rng = np.random.default_rng(seed)
    pattern, _, _ = periodic_run(seed, 30, 8, 0.0)
    examples = []
    for i, kind in enumerate(kinds):
        features = pattern[: 30 * int(rng.integers(4, 9))]
        n = len(features)
        sway = np.radians(rng.uniform(-1, 1) * (MAX_TURN_DEG / 3)) * np.sin(np.arange(n) / 7 + i)
        if kind == "still":
            features = np.repeat(features[:1], n, axis=0)
        turn = np.radians(rng.uniform(MAX_TURN_DEG + 5, 180)) * np.arange(n) / (n - 1)
        examples.append((features, sway + (turn if kind == "turning" else 0.0)))
    got = cut_examples(examples, RATE, count)
    if 2 * kinds.count("periodic") < len(kinds):
        assert got is None
        return
    assert got is not None and len(got) == len(kinds)
    for kind, cut in zip(kinds, got, strict=True):
        if kind != "periodic":
            assert cut.repetitions == () and cut.reason
            assert cut.reason.startswith("turning (") == (kind == "turning")
            continue
        assert (len(cut.repetitions), cut.reason) == (count, "")
        assert all(abs(r.length - 30) <= 2 for r in cut.repetitions)
    starts = [examples[i][0][c.repetitions[0].start] for i, c in enumerate(got) if c.repetitions]
    assert all(np.array_equal(s, starts[0]) for s in starts)


def test_body_heading_turns_with_the_hips() -> None:
    """The heading of hips turning a full circle and a half about y, unwrapped: 0 to 3π."""
    angle = np.linspace(0, 3 * np.pi, 50)
    joints = np.zeros((50, 2, 3))
    joints[:, 0, 0], joints[:, 0, 2] = np.cos(angle), np.sin(angle)
    joints[:, :, 1] = 90.0
    assert np.allclose(body_heading(joints, 0, 1), angle)


@SETTINGS
@given(st.integers(0, 2**32 - 1), st.integers(60, 300), st.sampled_from(["white", "walk"]))
def test_aperiodic_runs_give_no_cuts_or_low_confidence(seed: int, n: int, kind: str) -> None:
    rng = np.random.default_rng(seed)
    if kind == "white":
        features = rng.random((n, 39)) < 0.5
        joints = rng.normal(size=(n, 4, 3))
    else:
        walk = np.cumsum(rng.normal(size=(n, 39 + 12)), axis=0)
        features = walk[:, :39] > np.median(walk[:, :39], axis=0)
        joints = walk[:, 39:].reshape(n, 4, 3)
    got = cut_run(features, RATE, joints)
    assert not got.repetitions or got.period.confidence < 0.5, got
    if not got.repetitions:
        assert got.reason.startswith(("aperiodic", "no pose recurs"))


def test_short_constant_and_malformed_runs() -> None:
    short = cut_run(np.random.default_rng(1).random((17, 39)) < 0.5, RATE)
    assert short.repetitions == () and short.reason.startswith("too short: 17 samples (0.57 s)")
    constant = cut_run(np.ones((200, 39), dtype=bool), RATE, np.ones((200, 4, 3)))
    assert constant.repetitions == () and constant.reason == "constant: the run does not move"
    assert cut_run(np.zeros((0, 39), dtype=bool), RATE).reason.startswith("too short: 0 samples")
    with pytest.raises(ValueError, match=r"features must have shape \(n, 39\), got \(10, 38\)"):
        cut_run(np.zeros((10, 38), dtype=bool), RATE)
    with pytest.raises(ValueError, match=r"joints must have shape \(10, J > 0, 3\), got \(9, 4, 3\)"):
        cut_run(np.zeros((10, 39), dtype=bool), RATE, np.zeros((9, 4, 3)))
    with pytest.raises(ValueError, match="joint positions must be finite"):
        cut_run(np.zeros((10, 39), dtype=bool), RATE, np.full((10, 4, 3), np.nan))
    with pytest.raises(ValueError, match="rate must be a positive number, got 0"):
        cut_run(np.zeros((10, 39), dtype=bool), 0)


def test_difference_function_and_period_of_a_sine() -> None:
    t = np.arange(300)
    signal = np.stack([np.sin(2 * np.pi * t / 37.5), np.cos(2 * np.pi * t / 37.5)], axis=1)
    d = difference_function(signal, 100)
    assert d[0] == 0 and d.shape == (101,)
    assert d[19] == pytest.approx(2.0, abs=0.02)  # half a period: opposite points, |Δ|² / 2 = 2
    period = estimate_period(signal, RATE)
    assert period.samples in (37, 38) and period.seconds == pytest.approx(1.25, abs=0.01)
    assert period.confidence > 0.95
    with pytest.raises(ValueError, match=r"max_lag must lie in \[0, 300\), got 300"):
        difference_function(signal, 300)
    scaled = run_signal(np.eye(39, dtype=bool)[np.arange(100) % 39], np.ones((100, 2, 3)))
    assert scaled.shape == (100, 39 + 6)
    assert float((scaled[:, :39] ** 2).sum(axis=1).mean()) == pytest.approx(1.0)


# ------------------------------------------------------------------------------------ real mocap6

EXPECTED_CLASSES = {
    "13_29": ["JumpJack", "Twist", "ArmCircle", "ToeTouchOneHand", "KneeRaise", "Squat"],
    "13_30": ["JumpJack", "Twist", "KneeRaise", "Squat", "Jog"],
    "14_14": ["JumpJack", "Jog", "Squat", "KneeRaise", "ArmCircle", "Twist"],
}


@pytest.fixture(scope="module")
def cuts() -> dict[str, TrialCuts]:
    """The trials cut as the shipped library cuts them: each class at the phase of its first run."""
    return {c.trial: c for _, c in cut_trials(DATA, read_segments(DATA / SEGMENTS), TRIALS)}


@pytest.mark.slow
def test_every_class_is_cut_at_one_phase(cuts: dict[str, TrialCuts]) -> None:
    """Every run of a class is cut where its features are nearest the class's first cut run's
    reference features, unless no such frame gives repetitions (then as if cut alone); cutting a
    trial alone (no anchors) differs for some class."""
    anchors: dict[str, BoolArray] = {}
    for got in cuts.values():
        anchors = {**got.anchors(), **anchors}
    changed = anchored = 0
    segments = read_segments(DATA / SEGMENTS)
    for trial, got in cuts.items():
        alone = cut_trial(read_recording(*trial_recording(DATA, trial)), segments, trial)
        for run, plain in zip(got.runs, alone.runs, strict=True):
            away = (got.features.matrix[run.samples] != anchors[run.segment.label]).sum(axis=1)
            if away[run.cutting.reference] == away.min():
                anchored += 1
            else:
                assert run.cutting == plain.cutting, (trial, run.segment.label)
            changed += plain.cutting.cuts != run.cutting.cuts
    assert changed >= 4 and anchored >= 15  # of 17 runs


@SETTINGS
@given(st.integers(0, 2**32 - 1), st.integers(15, 45), st.integers(3, 8), st.integers(0, 1000))
def test_an_anchor_sets_the_phase(seed: int, period: int, k: int, at: int) -> None:
    features, joints, _ = periodic_run(seed, period, k, 0.0)
    anchor = features[at % len(features)]
    got = cut_run(features, RATE, joints, anchor=anchor)
    away = (features != anchor).sum(axis=1)
    assert got.repetitions and away[got.reference] == away.min()
    free = cut_run(features, RATE, joints)
    assert (got.period, got.samples) == (free.period, free.samples)
    # far from every pose of the run: nothing nearer to choose among but the nearest there is
    assert cut_run(features, RATE, joints, anchor=~anchor).repetitions


def test_the_labels_file_holds_the_seven_classes_in_three_trials() -> None:
    segments = read_segments(DATA / SEGMENTS)
    assert len(segments) == 17
    found = {t: [s.label for s in segments if s.trial == t] for t in TRIALS}
    assert found == EXPECTED_CLASSES
    assert {c for names in found.values() for c in names} == set(CLASSES)
    assert segments[0].line == 2 and segments[0].start_frame == 1 and segments[-1].end_frame == 4653


def test_14_14_is_read_with_subject_13s_skeleton() -> None:
    asf, amc = trial_recording(DATA, "14_14")
    assert asf == DATA / "cmu" / "13" / "13.asf" and amc == DATA / "cmu" / "14" / "14_14.amc.gz"
    assert trial_recording(DATA, "13_30")[0] == DATA / "cmu" / "13" / "13.asf"


def test_every_real_run_gives_repetitions_of_plausible_length_and_number(cuts: dict[str, TrialCuts]) -> None:
    for trial, got in cuts.items():
        assert [r.segment.label for r in got.runs] == EXPECTED_CLASSES[trial]
        for run in got.runs:
            c = run.cutting
            n, period = c.samples, c.period.samples
            assert c.reason == "", (trial, run.segment.label, c.reason)
            assert 0.5 <= c.period_seconds <= 4.5
            assert c.period.confidence >= 0.45
            assert math.floor(n / period) - 2 <= len(c.repetitions) <= math.ceil(n / period), (
                trial,
                run.segment.label,
            )
            for rep in c.repetitions:
                assert 0.7 * period <= rep.length <= 1.4 * period


def test_jumping_jacks_of_13_29(cuts: dict[str, TrialCuts]) -> None:
    (run,) = [r for r in cuts["13_29"].runs if r.segment.label == "JumpJack"]
    c = run.cutting
    assert c.period_seconds == pytest.approx(1.12, abs=0.05)
    assert len(c.repetitions) == 3  # 468 frames = 3.9 s: three whole jacks between four cuts
    assert all(1.0 <= r.length / c.rate <= 1.25 for r in c.repetitions)
    frames = run.amc_frames(cuts["13_29"].features)
    assert all(1 <= a < b <= 468 for a, b in frames)
    assert all(b == a2 for (_, b), (a2, _) in itertools.pairwise(frames))


def _peaks(values: FloatArray, above: float) -> IntArray:
    """The highest point of each stretch of ``values`` shape ``(n,)`` above ``above`` that does not
    touch either end: indices, shape ``(p,)``."""
    high = np.concatenate(([False], values > above, [False])).astype(np.int8)
    starts = np.flatnonzero(np.diff(high) == 1)
    stops = np.flatnonzero(np.diff(high) == -1)
    return np.array(
        [
            a + int(np.argmax(values[a:b]))
            for a, b in zip(starts, stops, strict=True)
            if a > 0 and b < len(values)
        ],
        dtype=np.int64,
    )


def test_one_jumping_jack_and_one_squat_per_repetition(cuts: dict[str, TrialCuts]) -> None:
    """Each JumpJack repetition holds one peak of the wrists above the head, each Squat repetition
    one lowest point of the root more than 20 cm below standing."""
    names = list(JOINT_NAMES)
    for trial, got in cuts.items():
        joints = joint_positions(read_recording(*trial_recording(DATA, trial)))[:: got.features.step]
        wrists = joints[:, [names.index("lwrist"), names.index("rwrist")], 1].min(axis=1)
        signals = {
            "JumpJack": (wrists - joints[:, names.index("headtop"), 1], 0.0),
            "Squat": (-joints[:, 0, 1], 20.0),
        }
        for run in got.runs:
            if run.segment.label not in signals:
                continue
            values, above = signals[run.segment.label]
            values = values[run.samples]
            if run.segment.label == "Squat":
                values = values - values.min()
            peaks = _peaks(values, above)
            assert len(run.cutting.repetitions) >= 1
            for rep in run.cutting.repetitions:
                inside = peaks[(peaks >= rep.start) & (peaks < rep.end)]
                assert len(inside) == 1, (trial, run.segment.label, rep, peaks)


def test_rows_form_a_training_manifest(cuts: dict[str, TrialCuts], tmp_path: Path) -> None:
    rows = []
    for trial, got in cuts.items():
        asf, amc = trial_recording(DATA, trial)
        rows += repetition_rows(got, str(asf), str(amc))
    assert {r.name for r in rows} == set(CLASSES)
    assert {r.actor for r in rows} == set(TRIALS)
    assert all(r.asf.endswith("13.asf") for r in rows)
    segments = read_segments(DATA / SEGMENTS)
    for row in rows:
        (run,) = [
            s for s in segments if s.trial == row.actor and s.start_frame <= row.start_frame <= s.end_frame
        ]
        assert run.label == row.name and row.end_frame <= run.end_frame
    manifest = tmp_path / "reps.csv"
    manifest.write_text(rows_csv(rows), encoding="utf-8")
    read = read_training_manifest(manifest)
    assert [(t.name, t.start_frame, t.end_frame, t.row.extra["actor"]) for t in read] == [
        (r.name, r.start_frame, r.end_frame, r.actor) for r in rows
    ]


def test_cuts_are_drawn(cuts: dict[str, TrialCuts]) -> None:
    got = cuts["13_30"]
    out = io.BytesIO()
    repetitions_png(
        got.features.matrix,
        got.features.frames,
        got.features.rate,
        {"x": np.linspace(0, 1, got.features.frames.shape[0])},
        [(r.segment.start_frame, r.segment.end_frame, r.segment.label) for r in got.runs],
        [f for r in got.runs for f in r.cut_frames(got.features)],
        out,
        "13_30",
    )
    assert out.getvalue().startswith(b"\x89PNG\r\n\x1a\n")


# ----------------------------------------------------------------------------------- bad labels

HEADER = "trial,start_frame,end_frame,label_id,label_name\n"


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("trial,start_frame,label_id,label_name\n", r":1: header lacks the column 'end_frame'"),
        (HEADER + "13_29,1,x,1,JumpJack\n", r":2: end_frame 'x' is not an integer"),
        (HEADER + "13_29,9,3,1,JumpJack\n", r":2: start_frame 9 is after end_frame 3"),
        (HEADER + "13_29,1,3,1\n", r":2: 4 fields, the header has 5"),
        (HEADER + "13_29,1,3,1,\n", r":2: the 'label_name' field is blank"),
        (
            HEADER + "13_29,1,9,1,A\n\n13_29,5,12,2,B\n",
            r":4: trial 13_29: frames 5\.\.12 start before the run of line 2",
        ),
        ("", r":1: empty file: no header"),
    ],
)
def test_bad_labels_name_file_and_line(tmp_path: Path, text: str, message: str) -> None:
    path = tmp_path / "segments.csv"
    path.write_text(text, encoding="utf-8")
    with pytest.raises(Mocap6Error, match=r"segments\.csv" + message):
        read_segments(path)


def test_missing_labels_and_runs_outside_the_recording(tmp_path: Path) -> None:
    with pytest.raises(FileAccessError, match=r"nothing\.csv"):
        read_segments(tmp_path / "nothing.csv")
    path = tmp_path / "segments.csv"
    path.write_text(HEADER + "13_30,1,200,1,JumpJack\n13_30,2400,2500,2,Jog\n", encoding="utf-8")
    motion = read_recording(*trial_recording(DATA, "13_30"))
    with pytest.raises(
        Mocap6Error, match=r"segments\.csv:3: frames 2400\.\.2500 are outside the recording's 1\.\.2465"
    ):
        cut_trial(motion, read_segments(path), "13_30")
