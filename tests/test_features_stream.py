"""FeatureStream against its batch twin, latency and decimation (daemon/features/stream.py).

1. Every real recording: :class:`FeatureStream` (one pose at a time, then ``flush``) gives exactly
   :func:`features`, each vector ``latency`` frames after its pose; :class:`Segmenter` on the stream
   gives :func:`segment` on the batch matrix for every feature set, also after 30 Hz decimation
   (:class:`Decimator` vs :func:`decimate`); and the stream equals the batch at 30 Hz too.
2. Random motions (hypothesis): stream == batch bit for bit at many frame rates, for sequences
   shorter than the latency (down to one frame), degenerate poses and huge coordinates; ``flush``
   starts a fresh stream; joint order does not matter; the 14 velocity features equal a slow,
   obviously-correct reference (:func:`slow_velocity`, a plain loop for the hysteresis).
3. Decimation: :class:`Decimator` equals :func:`decimate`.
4. Errors: bad poses, impossible decimation.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np
import numpy.typing as npt
import pytest
from hypothesis import HealthCheck, event, given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from daemon.features import (
    FEATURE_NAMES,
    Decimator,
    FeatureStream,
    decimate,
    decimation_factor,
    feature_tracks,
    features,
    latency_frames,
    sampling_ratio,
)
from daemon.search.segments import Segmenter, segment
from daemon.stages import run
from daemon.types import BoolArray, FeatureSet, FloatArray
from replay import JOINT_NAMES
from tests.helpers import clip, joints_cm, pair_id, recording_pairs, run_segmenter
from tests.naive import slow_hysteresis, slow_velocity_checks

SETS: tuple[FeatureSet, ...] = ("lower", "upper", "mix")
N_JOINTS = len(JOINT_NAMES)
RATES = (120.0, 30.0, 60.0, 24.0, 100.0, 7.5, 1.0, 1000.0)
"""Frame rates for the random tests: the native and target rates, others with other window lengths,
1 Hz (every window one frame) and 1000 Hz (latency 126 frames, longer than every random sequence)."""

BASE = settings(deadline=None, suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])


# ------------------------------------------------------------------------------------ helpers


def run_stream(stream: FeatureStream, positions: FloatArray) -> tuple[BoolArray, list[int], int]:
    """Push every pose of ``positions``, then flush: the output matrix ``(N, 39)``, how many
    vectors each push returned, and how many the flush returned."""
    out: list[BoolArray] = []
    counts: list[int] = []
    for pose in positions:
        got = stream.push(pose)
        for vector in got:
            assert vector.shape == (39,)
            assert vector.dtype == np.bool_
        counts.append(len(got))
        out += got
    tail = stream.flush()
    out += tail
    return np.array(out, dtype=bool).reshape(len(out), 39), counts, len(tail)


def assert_stream_equals_batch(positions: FloatArray, frame_rate: float) -> BoolArray:
    """The stream output equals the batch bit for bit, and the vector of frame ``t`` comes out of
    the push of frame ``t + latency`` (the rest from the flush). Returns the batch matrix."""
    batch = features(positions, JOINT_NAMES, frame_rate)
    stream = FeatureStream(JOINT_NAMES, frame_rate)
    streamed, counts, flushed = run_stream(stream, positions)
    n, latency = len(positions), stream.latency
    assert counts == [int(k >= latency) for k in range(n)]
    assert flushed == min(n, latency)
    assert batch.shape == (n, 39)
    assert streamed.shape == batch.shape
    assert np.array_equal(streamed, batch), np.argwhere(streamed != batch)[:10].tolist()
    return batch


# ------------------------------------------------------------------- 1. every real recording


def test_latency() -> None:
    assert latency_frames(120.0) == FeatureStream(JOINT_NAMES, 120.0).latency == 16
    assert latency_frames(30.0) == FeatureStream(JOINT_NAMES, 30.0).latency == 5


@pytest.mark.slow
@pytest.mark.parametrize("pair", recording_pairs(), ids=pair_id)
def test_recording_stream_equals_batch(pair: tuple[Path, Path]) -> None:
    positions = joints_cm(*pair)
    stream = FeatureStream(JOINT_NAMES, 120.0)
    batch = features(positions, JOINT_NAMES, 120.0)
    streamed, counts, flushed = run_stream(stream, positions)
    n = len(positions)
    assert counts == [int(k >= 16) for k in range(n)]
    assert flushed == min(n, 16)
    assert np.array_equal(streamed, batch), np.argwhere(streamed != batch)[:10].tolist()

    # F-segments of every set, incremental vs batch, at 120 Hz and after decimation to 30 Hz.
    factor = decimation_factor(120.0, 30.0)
    kept = run(Decimator(factor), streamed)
    assert np.array_equal(np.array(kept).reshape(-1, 39), decimate(batch, factor))
    for feature_set in SETS:
        assert run_segmenter(Segmenter(feature_set), streamed) == list(segment(batch, feature_set))
        assert run_segmenter(Segmenter(feature_set), kept) == list(
            segment(decimate(batch, factor), feature_set)
        )

    # The stream at 30 Hz on every 4th pose is the batch at 30 Hz.
    assert_stream_equals_batch(positions[::factor], 30.0)


# ---------------------------------------------------------------------- 2. random motions


KINDS = ("drift", "noise", "window", "hypothesis")


@st.composite
def motions(draw: st.DrawFn, max_frames: int = 80, kinds: Sequence[str] = KINDS) -> FloatArray:
    """Joint positions ``(N, 26, 3)`` in cm, ``1 <= N <= max_frames``, of one of four kinds:

    * ``drift``: a real pose moved by a random walk of every joint plus a common drift, steps from
      0 to 10 cm a frame, so that velocities cross their thresholds and features switch;
    * ``noise``: every coordinate uniform in [-200, 200] (seeded), wild jumps between frames;
    * ``window``: a window of real motion (cmu 13_29) with optional noise;
    * ``hypothesis``: an array drawn by hypothesis, coordinates in [-200, 200]; it fills most cells
      with one value, so degenerate poses (coinciding joints, zero-length normals, divisions by
      zero) are the rule here.
    """
    n = draw(st.integers(1, max_frames), label="frames")
    kind = kinds[draw(st.integers(0, len(kinds) - 1), label="kind")]
    event(f"kind {kind}")
    if kind == "hypothesis":
        values = draw(
            hnp.arrays(np.float64, (n, N_JOINTS, 3), elements=st.floats(-200.0, 200.0, width=64)),
            label="positions",
        )
        out: FloatArray = values
        return out
    rng = np.random.default_rng(draw(st.integers(0, 2**32 - 1), label="seed"))
    if kind == "noise":
        out = rng.uniform(-200.0, 200.0, (n, N_JOINTS, 3))
        return out
    real = clip("13_29")
    if kind == "drift":
        pose = real[draw(st.integers(0, len(real) - 1), label="pose")]
        step = draw(st.sampled_from([0.0, 0.05, 0.5, 1.0, 3.0, 10.0]), label="step")
        walk = np.cumsum(rng.normal(0.0, step, (n, N_JOINTS, 3)), axis=0)
        drift = np.cumsum(rng.normal(0.0, step, (n, 1, 3)), axis=0)
        out = pose[None] + walk + drift
        return out
    start = draw(st.integers(0, len(real) - n), label="start")
    noise = draw(st.sampled_from([0.0, 0.01, 1.0]), label="noise")
    out = real[start : start + n] + rng.normal(0.0, noise, (n, N_JOINTS, 3))
    return out


rates = st.sampled_from(RATES)


MOVING = ("drift", "noise", "window")


@pytest.mark.slow
@settings(BASE, max_examples=200)
@given(motions(kinds=MOVING), rates)
def test_stream_equals_batch(positions: FloatArray, frame_rate: float) -> None:
    batch = assert_stream_equals_batch(positions, frame_rate)
    event(f"features switch: {'yes' if (batch[1:] != batch[:-1]).any() else 'no'}")


@settings(BASE, max_examples=100)
@given(motions(kinds=("hypothesis",)), rates)
def test_stream_equals_batch_on_degenerate_poses(positions: FloatArray, frame_rate: float) -> None:
    """Coinciding joints: zero-length normals and segments, divisions by zero (the stream's
    ``ZeroDivisionError`` fallback must give what the batch's nan gives)."""
    assert_stream_equals_batch(positions, frame_rate)


@settings(BASE, max_examples=100)
@given(
    st.integers(1, 3).flatmap(
        lambda n: hnp.arrays(np.float64, (n, N_JOINTS, 3), elements=st.floats(-50, 50))
    ),
    st.sampled_from([120.0, 30.0, 1.0]),
)
def test_very_short_streams(positions: FloatArray, frame_rate: float) -> None:
    """N = 1, 2, 3: every vector comes from the flush (windows mirrored onto one or two frames)."""
    assert_stream_equals_batch(positions, frame_rate)


def test_empty_stream() -> None:
    stream = FeatureStream(JOINT_NAMES, 120.0)
    assert stream.flush() == []
    assert features(np.zeros((0, N_JOINTS, 3)), JOINT_NAMES).shape == (0, 39)


@settings(BASE, max_examples=100)
@given(motions(), motions(), rates)
def test_flush_resets_the_stream(first: FloatArray, second: FloatArray, frame_rate: float) -> None:
    """After a flush the same object is a fresh stream: body lengths from the new first pose,
    windows mirrored at the new start, hysteresis off, latency counted from the new first frame."""
    stream = FeatureStream(JOINT_NAMES, frame_rate)
    got_first, _, _ = run_stream(stream, first)
    got_second, counts, flushed = run_stream(stream, second)
    assert np.array_equal(got_first, features(first, JOINT_NAMES, frame_rate))
    assert np.array_equal(got_second, features(second, JOINT_NAMES, frame_rate))
    assert counts == [int(k >= stream.latency) for k in range(len(second))]
    assert flushed == min(len(second), stream.latency)


@settings(BASE, max_examples=40)
@given(motions(), rates, st.permutations(range(N_JOINTS)))
def test_joint_order_does_not_matter(positions: FloatArray, frame_rate: float, order: list[int]) -> None:
    names = [JOINT_NAMES[i] for i in order]
    shuffled = positions[:, order]
    expected = features(positions, JOINT_NAMES, frame_rate)
    assert np.array_equal(features(shuffled, names, frame_rate), expected)
    streamed, _, _ = run_stream(FeatureStream(names, frame_rate), shuffled)
    assert np.array_equal(streamed, expected)


@settings(BASE, max_examples=40)
@given(
    st.integers(1, 40).flatmap(
        lambda n: hnp.arrays(
            np.float64,
            (n, N_JOINTS, 3),
            elements=st.sampled_from([0.0, 1.0, -1.0, 1e150, -1e150, 1e300, -1e300, 1.7e308, -1.7e308]),
        )
    ),
    rates,
)
def test_extreme_magnitudes(positions: FloatArray, frame_rate: float) -> None:
    """Finite but huge coordinates (sums and squares overflow to inf, differences of infinities give
    nan) are accepted, and the stream still equals the batch."""
    with np.errstate(over="ignore", invalid="ignore"):  # the batch warns on inf - inf
        assert_stream_equals_batch(positions, frame_rate)


COMPARE: dict[str, Callable[[FloatArray, float], npt.NDArray[np.bool_]]] = {
    ">=": lambda a, b: a >= b,
    ">": lambda a, b: a > b,
}


@pytest.mark.slow
@settings(BASE, max_examples=150)
@given(
    motions(max_frames=50, kinds=MOVING),
    st.sampled_from([120.0, 30.0, 60.0, 24.0, 7.5, 1.0]),
)
def test_velocity_features_equal_a_slow_reference(positions: FloatArray, frame_rate: float) -> None:
    """Tracks and hysteresis of the velocity features, computed slowly from :func:`slow_velocity`,
    equal the batch tracks and the stream output. Cells whose reference signal lies within 1e-9
    (relative) of a threshold, where the slow arithmetic may round the other way, are not
    compared; a feature with such a cell is left out of the hysteresis comparison."""
    first = positions[0]
    lengths = {
        "h_R": math.dist(first[JOINT_NAMES.index("relbow")], first[JOINT_NAMES.index("rshoulder")]),
        "h_L": math.dist(first[JOINT_NAMES.index("lshoulder")], first[JOINT_NAMES.index("lelbow")]),
    }
    f1, f2 = feature_tracks(positions, JOINT_NAMES, frame_rate)
    streamed, _, _ = run_stream(FeatureStream(JOINT_NAMES, frame_rate), positions)
    checks = slow_velocity_checks(positions, frame_rate)
    assert len(checks) == 14
    compared = 0
    with np.errstate(invalid="ignore", divide="ignore"):
        for name, tests in checks.items():
            k = FEATURE_NAMES.index(name)
            loose = np.ones(len(positions), dtype=bool)
            strict = np.ones(len(positions), dtype=bool)
            unsure = np.zeros(len(positions), dtype=bool)
            for signal, op, t1, t2, reference in tests:
                for threshold, track in ((t1, loose), (t2, strict)):
                    limit = threshold * lengths[reference]
                    track &= COMPARE[op](signal, limit)
                    unsure |= ~np.isfinite(signal) | (np.abs(signal - limit) <= 1e-9 * max(1.0, abs(limit)))
            assert np.array_equal(f1[~unsure, k], loose[~unsure]), name
            assert np.array_equal(f2[~unsure, k], strict[~unsure]), name
            if not unsure.any():
                compared += 1
                expected = slow_hysteresis(loose.tolist(), strict.tolist())
                assert streamed[:, k].tolist() == expected, name
    event(f"features compared through the hysteresis: {compared}/14")
    # Non-degenerate random motion comes within 1e-9 of a threshold about never: most features must
    # have been compared in full (guards against a reference that is silently "unsure" everywhere).
    assert compared >= 12


# ---------------------------------------------------------------------------- 3. decimation


@settings(max_examples=100, deadline=None)
@given(hnp.arrays(np.bool_, st.tuples(st.integers(0, 40), st.just(39))), st.integers(1, 6))
def test_decimator_equals_decimate(matrix: BoolArray, factor: int) -> None:
    """Every ``factor``-th vector, the first included, nothing for the others; the flush has nothing
    left and starts a new stream (the second pass is the first again)."""
    decimator = Decimator(factor)
    for _ in range(2):
        passed = [decimator.push(v) for v in matrix]
        assert [i for i, v in enumerate(passed) if v] == list(range(0, len(matrix), factor))
        kept = [v for vs in passed for v in vs]
        assert np.array_equal(np.array(kept).reshape(-1, 39), decimate(matrix, factor))
        assert decimator.flush() == []


# ------------------------------------------------------------------------------------ 4. errors


@pytest.mark.parametrize("shape", [(N_JOINTS - 1, 3), (N_JOINTS,), (N_JOINTS, 2), (1, N_JOINTS, 3), ()])
def test_push_rejects_a_wrong_shape(shape: tuple[int, ...]) -> None:
    stream = FeatureStream(JOINT_NAMES, 120.0)
    with pytest.raises(ValueError, match=rf"pose must have shape \({N_JOINTS}, 3\), got"):
        stream.push(np.zeros(shape))


@pytest.mark.parametrize("value", [math.nan, math.inf, -math.inf])
@pytest.mark.parametrize("frame", [0, 1, 20])
def test_push_rejects_non_finite_values_and_keeps_its_state(value: float, frame: int) -> None:
    """A rejected pose is not part of the stream: the following good poses give the batch result."""
    positions = clip("02_01")[:40]
    stream = FeatureStream(JOINT_NAMES, 120.0)
    out: list[BoolArray] = []
    for t, pose in enumerate(positions):
        if t == frame:
            bad = pose.copy()
            bad[7, 1] = value
            with pytest.raises(ValueError, match=f"pose {frame} is not finite"):
                stream.push(bad)
        out += stream.push(pose)
    out += stream.flush()
    assert np.array_equal(np.array(out), features(positions, JOINT_NAMES))


def test_push_accepts_a_pose_whose_sum_overflows() -> None:
    """Finite coordinates whose sum is inf are finite: the quick sum test must not reject them."""
    stream = FeatureStream(JOINT_NAMES, 120.0)
    pose = np.full((N_JOINTS, 3), 1.7e308)
    assert stream.push(pose) == []
    assert len(stream.flush()) == 1


@pytest.mark.parametrize(
    ("native", "target", "factor"), [(120.0, 120.0, 1), (120.0, 60.0, 2), (120.0, 30.0, 4), (120.0, 24.0, 5)]
)
def test_decimation_factor(native: float, target: float, factor: int) -> None:
    assert decimation_factor(native, target) == factor


@pytest.mark.parametrize("target", [50.0, 70.0, 240.0, 0.0, -30.0, math.nan, math.inf])
def test_decimation_factor_rejects_a_rate_that_does_not_divide(target: float) -> None:
    with pytest.raises(ValueError, match=r"frame rate|divided by a whole number"):
        decimation_factor(120.0, target)


@pytest.mark.parametrize(
    ("native", "target", "ratio"),
    [
        (120.0, 30.0, (4, 1)),
        (100.0, 30.0, (10, 3)),
        (120.0, 50.0, (12, 5)),
        (59.94, 30.0, (999, 500)),
        (30.0, 30.0, (1, 1)),
    ],
)
def test_sampling_ratio_in_lowest_terms(native: float, target: float, ratio: tuple[int, int]) -> None:
    assert sampling_ratio(native, target) == ratio


@pytest.mark.parametrize(
    ("target", "message"),
    [
        (240.0, "above the native"),
        (1e-7, "by more than"),
        (0.0, "positive"),
        (-30.0, "positive"),
        (math.nan, "positive"),
        (math.inf, "positive"),
        (120.0 / 1.0000001, "ratio of whole numbers"),
    ],
)
def test_sampling_ratio_refuses(target: float, message: str) -> None:
    with pytest.raises(ValueError, match=message):
        sampling_ratio(120.0, target)


def test_decimator_rejects_a_factor_below_one() -> None:
    with pytest.raises(ValueError, match="at least 1"):
        Decimator(0)
