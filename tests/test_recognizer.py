"""The live recogniser: pushed frame by frame it equals its batch twin ``detect`` on every real
recording; the candidate/confirmation stage equals a slow reading of its definition on random code
streams; one motion gives one detection per class while a repetition right after gives another;
bad frames raise :class:`FrameError` and change nothing."""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from functools import cache
from pathlib import Path

import numpy as np
import numpy.typing as npt
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from daemon.library import given as given_tau
from daemon.dtw import Match, local_minima, retrieval_cost, subsequence_dtw, subsequence_matches
from daemon.features import SET_SLICES
from daemon.keyframes import KeyframeQuery
from daemon.library import ClassTemplate, Library, default_library_path, load_library
from daemon.recognizer import (
    CodeRecognizer,
    Detection,
    FrameError,
    Recognizer,
    detect,
    detect_positions,
    keep_apart,
    plans,
)
from daemon.recordings import joint_positions, native_rate, read_recording
from daemon.templates import MotionTemplate
from daemon.types import FEATURE_SETS, N_FEATURES, FeatureSet
from replay import JOINT_NAMES, Motion
from tests.helpers import hdm05_clip, pair_id, recording_pairs, small_library, takes
from tests.naive import keyframe_matches
from tests.synth import LOW_BITS, queries, stream_codes, streams

SESSION = "test"


@pytest.fixture(scope="module")
def library(tmp_path_factory: pytest.TempPathFactory) -> Library:
    return small_library(tmp_path_factory.mktemp("lib"))


@cache
def motion(asf: Path, amc: Path) -> Motion:
    return read_recording(asf, amc)


def pushed(recognizer: Recognizer, m: Motion) -> list[Detection]:
    out = [
        d
        for number, channels in zip(m.frames.tolist(), m.channels, strict=True)
        for d in recognizer.push(number, channels)
    ]
    return out + recognizer.flush()


@pytest.fixture(scope="module")
def shipped() -> Library:
    return load_library(default_library_path())


@pytest.mark.parametrize("pair", recording_pairs(), ids=pair_id)
def test_push_equals_detect(pair: tuple[Path, Path], shipped: Library) -> None:
    """With the shipped library's 18 classes (learned and published keyframes)."""
    library = shipped
    m = read_recording(*pair)
    rate = native_rate(m)
    recognizer = Recognizer.for_skeleton(library, m.skeleton, rate, stream="s", session=SESSION)
    got = pushed(recognizer, m)
    assert got == detect(m, library, rate, stream="s", session=SESSION)
    for d in got:
        assert d.start_frame <= d.end_frame <= d.emitted_at_frame
        assert d.cost <= d.tau
    assert len({d.id for d in got}) == len(got)
    assert pushed(recognizer, m) == got  # flush started a fresh stream


def test_positions_in_any_joint_order(library: Library) -> None:
    """Joint positions announced in another order, with a joint the features do not use, give the
    detections of the channels they came from; the batch twin on positions agrees."""
    asf, amc = hdm05_clip("dg", "squat1Reps", takes("squat1Reps", "dg")[0])
    m = motion(asf, amc)
    rate = native_rate(m)
    positions = joint_positions(m)  # (N, 26, 3) cm
    order = np.random.default_rng(3).permutation(len(JOINT_NAMES))
    names = [JOINT_NAMES[i] for i in order] + ["prop"]
    frames = np.concatenate([positions[:, order], np.zeros((len(m), 1, 3))], axis=1)
    recognizer = Recognizer.for_positions(library, names, rate, session=SESSION)
    got = [
        d for n, f in zip(m.frames.tolist(), frames, strict=True) for d in recognizer.push(n, f)
    ] + recognizer.flush()
    assert got
    assert got == detect(m, library, rate, session=SESSION)
    assert got == detect_positions(positions, m.frames, library, rate, session=SESSION)


def test_one_motion_one_detection_and_a_repetition_right_after(library: Library) -> None:
    """A dg squat gives one squat detection per class variant; the same squat twice in a row gives
    two, the second after the first."""
    asf, amc = hdm05_clip("dg", "squat1Reps", takes("squat1Reps", "dg")[0])
    m = motion(asf, amc)
    rate = native_rate(m)
    once = [d for d in detect(m, library, rate, session=SESSION) if d.class_name.startswith("squat")]
    assert sorted(d.class_name for d in once) == ["squat1Reps", "squat1Reps.published"]
    n = len(m)
    twice = Motion(
        m.source, m.skeleton, m.header, np.arange(1, 2 * n + 1), np.concatenate([m.channels, m.channels])
    )
    found = [d for d in detect(twice, library, rate, session=SESSION) if d.class_name == "squat1Reps"]
    assert len(found) == 2
    for d, (first, last) in zip(found, [(1, n), (n + 1, 2 * n)], strict=True):  # mostly in its copy
        assert 2 * (min(last, d.end_frame) - max(first, d.start_frame) + 1) > d.end_frame - d.start_frame + 1


def test_keep_apart() -> None:
    a, b, c = Match(0, 10, 0.05), Match(5, 15, 0.02), Match(9, 20, 0.04)
    assert keep_apart([a, b], []) == [b]  # 6 of 11 frames shared: one motion, the cheaper kept
    assert keep_apart([a, c], []) == [a, c]  # 2 frames shared: the next repetition
    assert keep_apart([a, Match(10, 10, 0.01)], []) == [Match(10, 10, 0.01)]  # all of the shorter
    assert keep_apart([a, c], [(4, 6)]) == [c]  # one already emitted stands
    assert keep_apart([c, a, Match(30, 40, 0.09)], [(38, 50)]) == [a, c, Match(30, 40, 0.09)]


# ------------------------------------------------------------------ candidates and confirmation


def random_class(name: str, query: KeyframeQuery, rng: np.random.Generator, tau: float) -> ClassTemplate:
    m = int(rng.integers(2, 7))
    values = np.full((N_FEATURES, m), 0.5)
    for fs in FEATURE_SETS:  # random streams vary the first LOW_BITS features of each set
        low = SET_SLICES[fs].start
        values[low : low + LOW_BITS] = rng.choice([0.0, 0.5, 1.0], size=(LOW_BITS, m))
        values[low + LOW_BITS : SET_SLICES[fs].stop] = rng.choice(
            [0.0, 0.5], size=(SET_SLICES[fs].stop - low - LOW_BITS, m), p=[0.2, 0.8]
        )
    template = MotionTemplate(values, rng.uniform(0.6, 2.2, size=m))
    return ClassTemplate(
        name,
        template,
        template,
        template,
        dataclasses.replace(query, name=name),
        tau,
        0.1,
        "toolbox",
        1,
        (),
        given_tau(tau),
    )


def float_matches(cls: ClassTemplate, frames: npt.NDArray[np.float64], lo: int, hi: int) -> list[Match]:
    """Float DTW of ``cls``'s expanded template over ``frames[:, lo..hi]``: the local minima at or below
    its τ, suppressed, in stream frames."""
    plan = plans(Library(30.0, {cls.name: cls}))[0]
    cost = retrieval_cost(plan.values, plan.weights, frames[:, lo : hi + 1])
    return [Match(m.start + lo, m.end + lo, m.cost) for m in subsequence_matches(cost, cls.tau, "toolbox")]


def rival_minima(cls: ClassTemplate, frames: npt.NDArray[np.float64], last: int) -> list[Match]:
    """Float DTW of ``cls``'s expanded template over the stream's ``frames[:, 0..last]``: every local
    minimum at or below its τ, not suppressed."""
    plan = plans(Library(30.0, {cls.name: cls}))[0]
    sub = subsequence_dtw(retrieval_cost(plan.values, plan.weights, frames[:, : last + 1]), "toolbox")
    return local_minima(sub.delta, sub.start, cls.tau)


def reference(
    codes: list[int], cls: ClassTemplate, max_gap: int, others: Sequence[ClassTemplate] = ()
) -> list[tuple[str, int, int, float, int]]:
    """The definition read slowly: every keyframe match by brute force (Def. 4.4-4.6, gaps capped),
    its window R(M) widened by the plan's left and right frames, ending ``right`` frames after the
    match's first complete frame and after every ``period`` frames more that its range reaches
    (the last ``window`` frames; cut at the stream's end), the widest of those ending at one frame;
    float DTW over each, local minima at or below τ suppressed, then by cost those that share at
    most half of the shorter one's frames with every one kept before; of those, the ones no class of
    ``others`` beats: its float subsequence DTW over the stream up to the frame the confirmation
    comes out at has no local minimum (the last frame's compared with the one before only) ending
    at or after the confirmation's start, at or below its τ and below the confirmation's cost,
    whose match shares more than half of the shorter one's frames with it. Each as (class, start,
    end, cost, frame it comes out at)."""
    assert cls.keyframes is not None
    sets = {
        fs: [
            (c >> SET_SLICES[fs].start) & ((1 << (SET_SLICES[fs].stop - SET_SLICES[fs].start)) - 1)
            for c in codes
        ]
        for fs in FEATURE_SETS
    }
    plan = plans(Library(30.0, {cls.name: cls}), max_gap_s=max_gap / 30.0)[0]
    frames = np.array(
        [[(c >> i) & 1 for i in range(N_FEATURES)] for c in codes], dtype=np.float64
    ).T  # (39, n)
    n = len(codes)
    starts: dict[int, int] = {}  # window end: its start, the widest of the windows ending there
    for first, at, last in keyframe_matches(sets, cls.keyframes, max_gap):
        for t in range(at, last + 1, plan.period):
            a = max(0, first - plan.left, t + plan.right - plan.window + 1)
            starts[t + plan.right] = min(a, starts.get(t + plan.right, a))
    windows = sorted(starts.items())
    kept: list[tuple[int, int]] = []
    out = []

    def one_motion(x: tuple[int, int], y: tuple[int, int]) -> bool:
        shared = set(range(x[0], x[1] + 1)) & set(range(y[0], y[1] + 1))
        return 2 * len(shared) > min(x[1] - x[0], y[1] - y[0]) + 1

    for end, a in windows:
        b = min(end, n - 1)
        apart: list[tuple[int, int]] = []
        confirmed = []
        for m in sorted(float_matches(cls, frames, a, b), key=lambda m: (m.cost, m.start)):
            if all(not one_motion((m.start, m.end), r) for r in kept + apart):
                apart.append((m.start, m.end))
                beaten = any(
                    c.end >= m.start and c.cost < m.cost and one_motion((m.start, m.end), (c.start, c.end))
                    for q in others
                    for c in rival_minima(q, frames, b)
                )
                if not beaten:
                    kept.append((m.start, m.end))
                    confirmed.append((cls.name, m.start, m.end, m.cost, b))
        out += sorted(confirmed, key=lambda c: c[1])
    return out


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    streams(),
    queries(),
    queries(),
    st.integers(0, 2**32 - 1),
    st.sampled_from([0.05, 0.2, 0.5]),
    st.integers(1, 8),
    st.booleans(),
)
def test_confirmations_equal_the_definition(
    codes: dict[FeatureSet, list[int]],
    q1: KeyframeQuery,
    q2: KeyframeQuery,
    seed: int,
    tau: float,
    max_gap: int,
    compete: bool,
) -> None:
    rng = np.random.default_rng(seed)
    classes = {n: random_class(n, q, rng, tau) for n, q in (("a", q1), ("b", q2))}
    stream = stream_codes(codes)
    class_plans = plans(Library(30.0, classes), max_gap_s=max_gap / 30.0)
    recognizer = CodeRecognizer(class_plans, 30.0, compete=compete)
    got = [(p.name, m.start, m.end, m.cost, j) for j, c in enumerate(stream) for p, m in recognizer.push(c)]
    got += [(p.name, m.start, m.end, m.cost, len(stream) - 1) for p, m in recognizer.flush()]
    for name, cls in classes.items():
        others = [c for n, c in classes.items() if n != name] if compete else []
        assert [g for g in got if g[0] == name] == reference(stream, cls, max_gap, others)
    for _, _, end, _, emitted in got:
        assert end <= emitted  # never before its last frame was seen


# ------------------------------------------------------------------------------- bad frames


BAD = ("short", "long", "nan", "inf", "repeat", "back", "jump", "float", "text")


@settings(max_examples=25, deadline=None)
@given(st.lists(st.tuples(st.integers(0, 178), st.sampled_from(BAD)), max_size=8))
def test_bad_frames_change_nothing(library: Library, bad: list[tuple[int, str]]) -> None:
    asf, amc = hdm05_clip("dg", "squat1Reps", takes("squat1Reps", "dg")[0])
    m = motion(asf, amc)
    rate = native_rate(m)
    clean = pushed(Recognizer.for_skeleton(library, m.skeleton, rate, session=SESSION), m)
    recognizer = Recognizer.for_skeleton(library, m.skeleton, rate, session=SESSION)
    before = {i: [kind for j, kind in bad if j == i] for i in range(len(m))}
    got: list[Detection] = []
    for i, (number, channels) in enumerate(zip(m.frames.tolist(), m.channels, strict=True)):
        for kind in before[i]:
            problem, wrong_number, wrong = damaged(kind, i, number, channels)
            if problem is None:
                continue
            with pytest.raises(FrameError, match=r"\bframe\b") as caught:
                recognizer.push(wrong_number, wrong)  # type: ignore[arg-type]
            assert caught.value.problem == problem
        got += recognizer.push(number, channels)
    assert got + recognizer.flush() == clean


def damaged(kind: str, i: int, number: int, channels: np.ndarray) -> tuple[str | None, object, object]:
    """The frame ``kind`` makes of frame ``i`` (number, channels) and the problem it must raise;
    None where the kind makes no bad frame there (no previous frame to repeat or jump from)."""
    bad = channels.copy()
    if kind == "short":
        return "shape", number, channels[:-1]
    if kind == "long":
        return "shape", number, np.append(channels, 0.0)
    if kind in ("nan", "inf"):
        bad[i % len(bad)] = np.nan if kind == "nan" else -np.inf
        return "non_finite", number, bad
    if kind == "float":
        return "type", float(number), channels
    if kind == "text":
        return "type", str(number), channels
    if i == 0:  # the first frame may have any number
        return None, number, channels
    if kind == "jump":
        return "jump", number + 1 + i % 3, channels
    return ("repeat", number - 1, channels) if kind == "repeat" else ("back", number - 2 - i % 3, channels)
