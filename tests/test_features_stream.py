"""The streaming stages against their batch twins, and the properties of the features and segments.

1. Every real recording: :class:`FeatureStream` (one pose at a time, then ``flush``) gives exactly
   :func:`features`, each vector ``latency`` frames after its pose; :class:`Segmenter` on the stream
   gives :func:`segment` on the batch matrix for every feature set, also after 30 Hz decimation
   (:class:`Decimator` vs :func:`decimate`); and the stream equals the batch at 30 Hz too.
2. Random motions (hypothesis): stream == batch bit for bit at many frame rates, for sequences
   shorter than the latency (down to one frame), degenerate poses and huge coordinates; ``flush``
   starts a fresh stream; joint order does not matter; the 14 velocity features equal a slow,
   obviously-correct reference (:func:`slow_velocity`, a plain loop for the hysteresis).
3. Segmentation: :func:`segment_codes` and :class:`Segmenter` equal a plain loop building runs;
   segments tile the sequence; :func:`set_codes` bit ``i`` is feature ``i`` of the set;
   :class:`Decimator` equals :func:`decimate`.
4. Invariance on real motion: translating, rotating about the vertical axis and scaling the joint
   positions leaves the 39-feature matrix unchanged, bit for bit.
5. Errors: bad poses, non-finite positions, impossible decimation.
"""

from __future__ import annotations

import functools
import itertools
import math
from collections.abc import Callable, Iterable, Sequence
from pathlib import Path

import numpy as np
import numpy.typing as npt
import pytest
from hypothesis import HealthCheck, event, given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from daemon.features import (
    FEATURE_NAMES,
    SET_SLICES,
    Decimator,
    FeatureStream,
    decimate,
    decimation_factor,
    feature_tracks,
    features,
    latency_frames,
)
from daemon.segments import Segment, Segmenter, segment, segment_codes, set_codes, vector_code
from daemon.stages import run
from daemon.types import BoolArray, FeatureSet, FloatArray
from replay import JOINT_NAMES
from tests.helpers import joints_cm, pair_id, recording_pairs
from tests.naive import slow_hysteresis, slow_runs, slow_velocity_checks

SETS: tuple[FeatureSet, ...] = ("lower", "upper", "mix")
N_JOINTS = len(JOINT_NAMES)
RATES = (120.0, 30.0, 60.0, 24.0, 100.0, 7.5, 1.0, 1000.0)
"""Frame rates for the random tests: the native and target rates, others with other window lengths,
1 Hz (every window one frame) and 1000 Hz (latency 126 frames, longer than every random sequence)."""

BASE = settings(deadline=None, suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])


# ------------------------------------------------------------------------------------ helpers


@functools.cache
def clip(name: str) -> FloatArray:
    """Joint positions of the recording ``name`` (its :func:`pair_id`), computed once per run."""
    matches = [pair for pair in recording_pairs() if pair_id(pair) == name]
    assert len(matches) == 1, f"no single recording named {name}"
    out = joints_cm(*matches[0])
    out.setflags(write=False)
    return out


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


def run_segmenter(segmenter: Segmenter, vectors: Iterable[BoolArray]) -> list[Segment]:
    """Every segment the segmenter closes on ``vectors`` (at most one a push), then the one its flush
    closes."""
    closed = [segmenter.push(v) for v in vectors] + [segmenter.flush()]
    assert all(len(c) <= 1 for c in closed)
    return [s for c in closed for s in c]


def rotation_y(angle: float) -> FloatArray:
    """Rotation by ``angle`` radians about the vertical y axis."""
    c, s = math.cos(angle), math.sin(angle)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


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


# --------------------------------------------------------------------------- 3. segmentation

codes_lists = st.one_of(
    st.lists(st.integers(0, 3), max_size=60),
    st.lists(st.integers(0, 2**14 - 1), max_size=20),
    st.lists(st.integers(-(2**63), 2**63 - 1), max_size=10),
)


def assert_tiles(segments: Sequence[Segment], codes: Sequence[int]) -> None:
    """Segments cover ``0..N-1`` in order without gaps or overlap, each one constant, consecutive
    codes different."""
    assert [s.start for s in segments[:1]] == ([0] if codes else [])
    assert [s.end for s in segments[-1:]] == ([len(codes) - 1] if codes else [])
    for s in segments:
        assert s.start <= s.end
        assert all(codes[i] == s.code for i in range(s.start, s.end + 1))
    for a, b in itertools.pairwise(segments):
        assert b.start == a.end + 1
        assert a.code != b.code


@settings(max_examples=300, deadline=None)
@given(codes_lists)
def test_segment_codes_equal_slow_runs(codes: list[int]) -> None:
    got = segment_codes(np.array(codes, dtype=np.int64))
    assert got.start.dtype == got.end.dtype == got.code.dtype == np.int64
    assert len(got) == len(slow_runs(codes))
    assert list(got) == slow_runs(codes)
    assert_tiles(list(got), codes)


@st.composite
def vector_sequences(draw: st.DrawFn) -> BoolArray:
    """Feature vectors ``(N, 39)`` picked from a small palette, so that runs occur and different
    vectors often share one set's code."""
    palette = draw(hnp.arrays(np.bool_, (draw(st.integers(1, 4)), 39)))
    picks = draw(st.lists(st.integers(0, len(palette) - 1), max_size=60))
    out: BoolArray = palette[picks].reshape(len(picks), 39)
    return out


@settings(max_examples=200, deadline=None)
@given(vector_sequences(), vector_sequences(), st.sampled_from(SETS))
def test_segmenter_equals_slow_runs(first: BoolArray, second: BoolArray, feature_set: FeatureSet) -> None:
    segmenter = Segmenter(feature_set)
    for matrix in (first, second):  # the second after the flush: a fresh stream, frames from 0
        codes = [vector_code(v, feature_set) for v in matrix]
        got = run_segmenter(segmenter, matrix)
        assert got == slow_runs(codes)
        assert got == list(segment(matrix, feature_set))
        assert_tiles(got, codes)
    assert segmenter.flush() == []


@settings(max_examples=200, deadline=None)
@given(hnp.arrays(np.bool_, st.tuples(st.integers(0, 30), st.just(39))))
def test_set_codes_bits_are_the_set_features(matrix: BoolArray) -> None:
    for feature_set in SETS:
        part = SET_SLICES[feature_set]
        width = part.stop - part.start
        codes = set_codes(matrix, feature_set)
        assert codes.shape == (len(matrix),)
        assert codes.dtype == np.int64
        assert ((codes >= 0) & (codes < 2**width)).all()
        for i in range(width):
            assert np.array_equal((codes >> i) & 1 == 1, matrix[:, part.start + i])
        assert [vector_code(v, feature_set) for v in matrix] == codes.tolist()


def test_set_codes_lsb_is_the_first_feature_of_the_set() -> None:
    for feature_set in SETS:
        vector = np.zeros(39, dtype=bool)
        vector[SET_SLICES[feature_set].start] = True
        assert vector_code(vector, feature_set) == 1
        assert set_codes(vector[None], feature_set).tolist() == [1]
        others = [s for s in SETS if s != feature_set]
        assert [vector_code(vector, s) for s in others] == [0, 0]


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


# -------------------------------------------------------------------- 4. invariance, real motion

# HDM_bk_grabHighR_006 holds the signal value closest to a threshold in the whole data, 02_07 the
# one closest relative to what a transform changes (found by scanning every recording; see
# assert_invariant).
INVARIANCE_CLIPS = ("02_01", "13_29", "HDM_bk_grabHighR_006_120", "02_07")
clips = st.sampled_from(INVARIANCE_CLIPS)
translations = st.tuples(*[st.floats(-1000.0, 1000.0)] * 3)  # cm: anywhere in a 20 m room
angles = st.floats(-math.pi, math.pi)
scales = st.floats(0.25, 4.0)


def assert_invariant(name: str, transformed: FloatArray) -> None:
    """The feature matrix (and the loose and strict tracks) of the transformed clip are those of the
    clip, bit for bit.

    Exact equality is justified, not lucky. The transforms are exact in real arithmetic; their
    rounding changes a signal by at most 2e-12 of its threshold's scale (the body length it is
    measured in; 1 for cosines), the worst being the 1-frame velocities of *MoveApartRelRoot after
    a translation. A scan of all 218 recordings (4 random transforms each: translation up to
    10 m, any rotation about y, scale 0.5 to 2, all three) found no signal closer to a threshold
    than 2.1e-7 of its scale (HDM_bk_grabHighR_006 frame 130, handRightRaisedRelSpine, T1 = 0),
    and the smallest ratio of distance-to-threshold over the change the transform caused was 8e6
    (02_07 frame 280, handLeftMoveApartRelRoot). No cell of f1, f2 or the output flipped."""
    original = clip(name)
    tracks = feature_tracks(original, JOINT_NAMES, 120.0)
    moved = feature_tracks(transformed, JOINT_NAMES, 120.0)
    for before, after in zip(tracks, moved, strict=True):
        assert np.array_equal(before, after), np.argwhere(before != after)[:10].tolist()
    assert np.array_equal(features(transformed, JOINT_NAMES), features(original, JOINT_NAMES))


@settings(max_examples=12, deadline=None)
@given(clips, translations)
def test_translation_invariance(name: str, offset: tuple[float, float, float]) -> None:
    assert_invariant(name, clip(name) + np.array(offset))


@settings(max_examples=12, deadline=None)
@given(clips, angles)
def test_vertical_rotation_invariance(name: str, angle: float) -> None:
    assert_invariant(name, clip(name) @ rotation_y(angle).T)


@settings(max_examples=12, deadline=None)
@given(clips, scales)
def test_scale_invariance(name: str, scale: float) -> None:
    assert_invariant(name, clip(name) * scale)


@settings(max_examples=12, deadline=None)
@given(clips, translations, angles, scales)
def test_rigid_motion_and_scale_invariance(
    name: str, offset: tuple[float, float, float], angle: float, scale: float
) -> None:
    assert_invariant(name, (clip(name) @ rotation_y(angle).T) * scale + np.array(offset))


def test_invariance_clips_exercise_the_features() -> None:
    """The clips are not trivial: between them every feature is on somewhere and off somewhere."""
    matrices = np.concatenate([features(clip(name), JOINT_NAMES) for name in INVARIANCE_CLIPS])
    on: list[bool] = np.asarray(matrices.any(axis=0)).tolist()
    off: list[bool] = np.asarray((~matrices).any(axis=0)).tolist()
    assert all(on) and all(off), [n for n, a, b in zip(FEATURE_NAMES, on, off, strict=True) if not (a and b)]


# ------------------------------------------------------------------------------------ 5. errors


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


@pytest.mark.parametrize("value", [math.nan, math.inf, -math.inf])
@pytest.mark.parametrize("frame", [0, 5, 39])
def test_features_names_the_non_finite_frame(value: float, frame: int) -> None:
    positions = np.array(clip("02_01")[:40])
    positions[frame, 3, 2] = value
    with pytest.raises(ValueError, match=rf"not finite at frame index {frame}$"):
        features(positions, JOINT_NAMES)


@pytest.mark.parametrize("shape", [(10, N_JOINTS - 1, 3), (10, N_JOINTS), (N_JOINTS, 3)])
def test_features_rejects_a_wrong_shape(shape: tuple[int, ...]) -> None:
    with pytest.raises(ValueError, match="positions must have shape"):
        features(np.zeros(shape), JOINT_NAMES)


@pytest.mark.parametrize(
    ("native", "target", "factor"), [(120.0, 120.0, 1), (120.0, 60.0, 2), (120.0, 30.0, 4), (120.0, 24.0, 5)]
)
def test_decimation_factor(native: float, target: float, factor: int) -> None:
    assert decimation_factor(native, target) == factor


@pytest.mark.parametrize("target", [50.0, 70.0, 240.0, 0.0, -30.0, math.nan, math.inf])
def test_decimation_factor_rejects_a_rate_that_does_not_divide(target: float) -> None:
    with pytest.raises(ValueError, match=r"frame rate|divided by a whole number"):
        decimation_factor(120.0, target)


def test_decimator_rejects_a_factor_below_one() -> None:
    with pytest.raises(ValueError, match="at least 1"):
        Decimator(0)
