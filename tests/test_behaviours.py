"""Behaviour segmentation (daemon.behaviours; Barbič et al. 2004): the quaternion representation
(relative to the parent, sign-consistent, the stream equal to the batch bit for bit), PCA and PPCA
against slow references that read the paper literally (an SVD of the explicit frames at every step),
the streams equal to their batch twins on random and on real data, the backward passes, GMM and its
merging of short segments, and the robustness cases on real recordings: standing still, a T-pose, a
clip shorter than the windows, root angles past ±180°, input that is not finite."""

from __future__ import annotations

import functools
import itertools
import math

import numpy as np
import pytest
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st

from daemon import behaviours as bh
from daemon.behaviours import (
    PAPER_BONES,
    Boundary,
    GmmParams,
    JointRotations,
    PcaParams,
    PcaSegmenter,
    PpcaParams,
    PpcaSegmenter,
    RotationStream,
)
from daemon.behaviours.ppca import _PpcaRun
from daemon.mocap6 import trial_recording
from daemon.recordings import read_recording
from daemon.stages import Stage, run
from daemon.types import FloatArray
from replay import Motion
from replay.asf import ROTATION_DOFS
from replay.kinematics import KinematicModel, quaternion_matrix
from tests.helpers import DATA
from tests.naive import slow_pca_segment, slow_peak, slow_ppca_forward, slow_ppca_segment

SETTINGS = settings(deadline=None, max_examples=25, suppress_health_check=[HealthCheck.too_slow])
REAL = ("86_01", "13_29", "13_30", "14_14", "135_06")
"""The files the evaluation uses, and 135_06 (its root angles go past ±180° too)."""

RATE = 10.0
"""Random streams run at 10 Hz so the paper's windows are few frames: PCA k = 20, ℓ = 5, i₀ = 25."""
PPCA_SMALL = PpcaParams(window=1.5, delta=0.2)
"""T = 15, Δ = 2 frames at 10 Hz."""

# Each stream is a Stage (mypy checks these).
_PCA: Stage[FloatArray, Boundary] = PcaSegmenter(120.0)
_PPCA: Stage[FloatArray, Boundary] = PpcaSegmenter(120.0)


@functools.cache
def motion(trial: str) -> Motion:
    return read_recording(*trial_recording(DATA, trial))


@functools.cache
def frames(trial: str) -> FloatArray:
    m = motion(trial)
    out: FloatArray = JointRotations(m.skeleton)(m.channels)
    return out


def regimes(seed: int, dims: int, lengths: list[int]) -> FloatArray:
    """Piecewise stationary random frames ``(sum(lengths), dims)``: each run has its own centre,
    latent dimension and spread, plus a little isotropic noise."""
    rng = np.random.default_rng(seed)
    parts = []
    for n in lengths:
        latent = int(rng.integers(1, dims + 1))
        basis = rng.normal(size=(latent, dims)) * rng.uniform(0.2, 3.0)
        centre = 2.0 * rng.normal(size=dims)
        parts.append(centre + rng.normal(size=(n, latent)) @ basis + 0.05 * rng.normal(size=(n, dims)))
    return np.concatenate(parts)


def pushed(stream: PcaSegmenter | PpcaSegmenter, x: FloatArray) -> list[Boundary]:
    return run(stream, x)


# -------------------------------------------------------------------------------- representation


def test_cmu_frames_are_the_quaternions_of_the_papers_fourteen_joints() -> None:
    skeleton = motion("86_01").skeleton
    rotations = JointRotations(skeleton)
    assert set(rotations.bones) == set(PAPER_BONES) and rotations.dims == 56  # the paper's R^56
    rotating = [b.name for b in skeleton.bones if set(b.dofs) & set(ROTATION_DOFS)]
    every = JointRotations(skeleton, rotating)
    assert len(every.bones) == 28 and every.dims == 112
    assert "root" not in every.bones
    assert not {"lhipjoint", "rhipjoint"} & set(every.bones)  # bones without dofs
    assert {"lfemur", "rtibia", "thorax", "head", "lhumerus", "rfingers"} <= set(every.bones)
    with pytest.raises(ValueError, match="no rotating bone nose"):
        JointRotations(skeleton, ["lfemur", "nose"])


def test_each_quaternion_is_the_bones_rotation_relative_to_its_parent() -> None:
    """The rotation matrix of bone k's quaternion is ``G_parent^T G_k`` of forward kinematics."""
    m = motion("86_01")
    rotations = JointRotations(m.skeleton)
    channels = m.channels[::500]
    q = frames("86_01")[::500].reshape(len(channels), -1, 4)
    glob = KinematicModel(m.skeleton).rotations(channels)
    parents = m.skeleton.parents
    for j, node in enumerate(rotations.nodes):
        local = np.einsum("nji,njk->nik", glob[:, parents[node]], glob[:, node])
        assert np.allclose(quaternion_matrix(q[:, j].T), local, atol=1e-12)


def check_sign_consistency(x: FloatArray, raw: FloatArray) -> None:
    q = x.reshape(raw.shape[0], -1, 4)
    assert np.allclose(np.linalg.norm(q, axis=2), 1.0)
    assert np.all((q == raw) | (q == -raw))
    assert np.all((q[1:] * q[:-1]).sum(axis=2) >= 0.0)
    first = q[0][np.arange(raw.shape[1]), np.argmax(q[0] != 0, axis=1)]
    assert np.all(first > 0)


@pytest.mark.parametrize("trial", REAL)
def test_the_stream_gives_the_batch_frames_bit_for_bit_on_real_recordings(trial: str) -> None:
    m = motion(trial)
    rotations = JointRotations(m.skeleton)
    batch = frames(trial)
    stream = rotations.stream()
    assert np.array_equal(np.array([stream.frame(c) for c in m.channels]), batch)
    raw = rotations.raw(m.channels)
    check_sign_consistency(batch, raw)


@SETTINGS
@given(st.integers(0, 2**32 - 1), st.integers(1, 60), st.integers(0, 40))
def test_the_stream_gives_the_batch_frames_for_random_channels(seed: int, n: int, split: int) -> None:
    """Angles anywhere in ±720° (sign flips galore), a flush in the middle starts a new stream."""
    m = motion("86_01")
    rotations = JointRotations(m.skeleton)
    rng = np.random.default_rng(seed)
    channels = rng.uniform(-4 * np.pi, 4 * np.pi, size=(n, rotations.width))
    channels[rng.random(n) < 0.3] = 0.0  # T-poses: every bone at the identity
    stream: RotationStream = rotations.stream()
    split = min(split, n)
    for piece in (channels[:split], channels[split:]):
        got = [v for c in piece for v in stream.push(c)] + stream.flush()
        expected = rotations(piece)
        assert np.array_equal(np.array(got).reshape(expected.shape), expected)
        if len(piece):
            raw = rotations.raw(piece)
            check_sign_consistency(expected, raw)
            if len(piece) >= 10:  # the raw quaternions do flip, so the rule is exercised
                assert np.any((raw[1:] * raw[:-1]).sum(axis=2) < 0)


@pytest.mark.parametrize("trial", ["86_01", "135_06"])
def test_root_angles_past_180_degrees_change_nothing(trial: str) -> None:
    m = motion(trial)
    names = m.skeleton.channel_names
    root = [i for i, name in enumerate(names) if name in ("root.rx", "root.ry", "root.rz")]
    assert np.abs(m.channels[:, root]).max() > np.pi  # the case is real
    wrapped = m.channels.copy()
    wrapped[:, root] = np.angle(np.exp(1j * wrapped[:, root]))
    wrapped[:, [names.index(f"root.t{a}") for a in "xyz"]] = 0.0
    rotations = JointRotations(m.skeleton)
    assert np.array_equal(rotations(wrapped), frames(trial))
    assert np.all(np.isfinite(frames(trial)))


def test_channels_that_are_not_finite_are_refused() -> None:
    m = motion("86_01")
    rotations = JointRotations(m.skeleton)
    channels = m.channels[:50].copy()
    channels[17, 9] = np.nan
    with pytest.raises(ValueError, match="frame 17"):
        rotations(channels)
    stream = rotations.stream()
    for c in channels[:17]:
        stream.frame(c)
    with pytest.raises(ValueError, match=r"frame 17.*not finite"):
        stream.frame(channels[17])
    with pytest.raises(ValueError, match="shape"):
        stream.frame(channels[18, :-1])
    # The refused frames left the stream as it was.
    rest = np.array([stream.frame(c) for c in channels[18:]])
    good = np.delete(channels, 17, axis=0)
    assert np.array_equal(rest, rotations(good)[17:])


# ------------------------------------------------------------------------------------ parameters


def test_windows_are_seconds_scaled_to_the_rate() -> None:
    assert bh.PCA_PAPER.frames(120.0) == bh.PcaFrames(240, 60, 300, 1)
    assert bh.PCA_PAPER.frames(60.0) == bh.PcaFrames(120, 30, 150, 1)
    assert bh.PCA_GRID.frames(120.0) == bh.PcaFrames(240, 60, 300, 60)
    assert bh.PPCA_DEFAULT.frames(120.0) == bh.PpcaFrames(150, 10, 300)
    assert bh.PPCA_DEFAULT.frames(240.0) == bh.PpcaFrames(300, 20, 600)
    assert bh.PPCA_PUBLISHED.frames(120.0) == bh.PpcaFrames(150, 10, 0)
    assert GmmParams().check(120.0) == 120
    for bad in (PcaParams(step=0.3), PcaParams(tau=1.0), PcaParams(k=0.4), PcaParams(k_sigma=-1)):
        with pytest.raises(ValueError):
            bad.frames(120.0)
    for wrong in (
        PpcaParams(delta=2.0),
        PpcaParams(window=0.001),
        PpcaParams(min_variance=0.0),
        PpcaParams(shortest=-1.0),
        PpcaParams(shortest=math.nan),
    ):
        with pytest.raises(ValueError):
            wrong.frames(120.0)
    with pytest.raises(ValueError, match="rate"):
        PcaSegmenter(0.0)
    with pytest.raises(ValueError, match="online"):
        bh.online_segmenter(120.0, "gmm")
    with pytest.raises(ValueError, match="do not fit"):
        bh.segment(np.zeros((10, 4)), 120.0, "pca", params=PpcaParams())


# ------------------------------------------------------------------------------------------- PCA


def test_pca_equals_the_slow_reference_and_finds_cuts() -> None:
    """A fixed example that has cuts, against the reference that takes an SVD at every frame."""
    x = regimes(7, 4, [60, 70, 80])
    p = PcaParams().frames(RATE)
    cuts, trace = slow_pca_segment(x, p.k, p.ell, p.i0, 0.9, 3.0)
    got = bh.pca_analysis(x, RATE)
    assert len(cuts) >= 1
    assert [b.frame for b in got.boundaries] == [c for c, _ in cuts]
    assert np.allclose([b.score for b in got.boundaries], [s for _, s in cuts], rtol=1e-7)
    assert got.frame.tolist() == [f for f, _, _ in trace]
    assert np.allclose(got.error, [e for _, e, _ in trace], rtol=1e-9, atol=1e-9)
    assert np.allclose(got.d, [d for _, _, d in trace], rtol=1e-7, atol=1e-9)


@SETTINGS
@given(
    st.integers(0, 2**32 - 1),
    st.integers(2, 5),
    st.lists(st.integers(15, 80), min_size=1, max_size=4),
    st.sampled_from([0.8, 0.9, 0.95]),
    st.sampled_from([1.0, 2.0, 3.0]),
)
def test_pca_equals_the_paper_read_literally(
    seed: int, dims: int, lengths: list[int], tau: float, k_sigma: float
) -> None:
    """The running moments and the eigenvalues of the scatter give the errors ``e_i`` an SVD of
    the segment's explicit frames gives, hence the same derivatives, tests and cuts."""
    x = regimes(seed, dims, lengths)
    params = PcaParams(tau=tau, k_sigma=k_sigma)
    p = params.frames(RATE)
    cuts, trace = slow_pca_segment(x, p.k, p.ell, p.i0, tau, k_sigma)
    got = bh.pca_analysis(x, RATE, params=params)
    assert [b.frame for b in got.boundaries] == [c for c, _ in cuts]
    assert all(b.emitted == b.frame and b.method == "pca" for b in got.boundaries)
    assert np.allclose([b.score for b in got.boundaries], [s for _, s in cuts], rtol=1e-6)
    assert got.frame.tolist() == [f for f, _, _ in trace]
    scale = max(1.0, float(np.abs(got.error).max(initial=0.0)))
    assert np.allclose(got.error, [e for _, e, _ in trace], rtol=1e-9, atol=1e-10 * scale)


@SETTINGS
@given(
    st.integers(0, 2**32 - 1),
    st.integers(1, 5),
    st.lists(st.integers(5, 80), min_size=1, max_size=4),
    st.sampled_from([None, 0.1, 0.5]),
    st.integers(0, 300),
)
def test_the_pca_stream_equals_the_batch(
    seed: int, dims: int, lengths: list[int], step: float | None, split: int
) -> None:
    x = regimes(seed, dims, lengths)
    params = PcaParams(step=step)
    stream = PcaSegmenter(RATE, params=params)
    split = min(split, len(x))
    for piece in (x[:split], x[split:]):  # the flush between them starts a new stream
        assert pushed(stream, piece) == bh.pca_segment(piece, RATE, params=params)


# ------------------------------------------------------------------------------------------ PPCA


@SETTINGS
@given(
    st.integers(0, 2**32 - 1),
    st.integers(2, 5),
    st.lists(st.integers(20, 90), min_size=1, max_size=4),
    st.floats(1.0, 40.0),
    st.sampled_from([None, 0, 25]),
)
def test_ppca_forward_pass_equals_the_paper_read_literally(
    seed: int, dims: int, lengths: list[int], rise: float, shortest: int | None
) -> None:
    """The running moments and the eigen-decomposition of their scatter give the ``H`` that an SVD
    of the first ``K`` frames and Eqs. 7-10 give, hence the same peaks and cuts."""
    x = regimes(seed, dims, lengths)
    params = PpcaParams(
        window=1.5, delta=0.2, rise=rise, shortest=None if shortest is None else shortest / RATE
    )
    cuts, trace = slow_ppca_forward(x, 15, 2, rise, 0.95, 30 if shortest is None else shortest)
    got = bh.ppca_analysis(x, RATE, params=params)
    forward = bh.ppca_forward(x, RATE, params=params)
    assert [(b.frame, b.emitted) for b in forward] == [(c, e) for c, _, e in cuts]
    assert np.allclose([b.score for b in forward], [s for _, s, _ in cuts], rtol=1e-7)
    assert got.frame.tolist() == [f for f, _ in trace]
    assert np.allclose(got.h, [h for _, h in trace], rtol=1e-8)


@pytest.mark.slow
@settings(deadline=None, max_examples=3000)
@given(st.lists(st.integers(0, 6), max_size=30), st.integers(0, 4), st.integers(0, 8))
@example([0, 2, 2, 5, 1], 1, 0)  # no valley: H never fell
@example([3, 1, 1, 5, 2], 1, 0)  # a valley where a plateau starts
@example([3, 1, 4, 4, 2, 5, 0], 1, 0)  # a plateau at the top is no peak
@example([3, 1, 4, 2, 5, 0], 1, 3)  # the first peak is too early, the second is a cut
def test_the_peak_test_follows_the_paper(hs: list[int], rise: int, shortest: int) -> None:
    """§3.2's cut: the first peak of ``H`` at least R above a valley before it and at ``K`` no
    shorter than the shortest behaviour, on sequences with many ties (a plateau is no peak, and no
    valley where it starts)."""
    params = PpcaParams(window=1.5, delta=0.2, rise=float(rise), shortest=shortest / RATE)
    run = _PpcaRun(params, params.frames(RATE))
    for i, h in enumerate(hs):
        run.moments.n = i  # K, the index here
        peak = run.observe(float(h))
        assert peak == slow_peak([(k, float(v)) for k, v in enumerate(hs[: i + 1])], rise, shortest)
        if peak is not None:
            break


@settings(deadline=None, max_examples=10, suppress_health_check=[HealthCheck.too_slow])
@given(st.integers(0, 2**32 - 1), st.integers(2, 4), st.lists(st.integers(20, 80), min_size=2, max_size=4))
def test_ppca_passes_equal_the_slow_passes(seed: int, dims: int, lengths: list[int]) -> None:
    x = regimes(seed, dims, lengths)
    got = bh.ppca_segment(x, RATE, params=PPCA_SMALL)
    assert [b.frame for b in got] == slow_ppca_segment(x, 15, 2, 15.0, 0.95, 30)
    forward = bh.ppca_forward(x, RATE, params=PPCA_SMALL)
    assert set(forward) <= set(got)  # the forward pass's cuts are kept as they are
    assert all(b.emitted == len(x) - 1 for b in set(got) - set(forward))


def test_the_backward_pass_finds_a_narrow_behaviour_after_a_wide_one() -> None:
    """§3.2's rare case: frames of a narrow distribution inside a wide one look likely under the
    wide model, so the forward pass misses the change; the backward pass finds it."""
    rng = np.random.default_rng(1)
    x = np.concatenate([rng.normal(size=(120, 4)), 0.05 * rng.normal(size=(120, 4))])
    assert bh.ppca_forward(x, RATE, params=PPCA_SMALL) == []
    result = bh.ppca_analysis(x, RATE, params=PPCA_SMALL)
    assert [abs(b.frame - 120) <= 4 for b in result.boundaries] == [True]
    assert result.passes == 3  # forward, backward (one cut), forward again (none new)
    assert (
        bh.ppca_forward(x[::-1].copy(), RATE, params=PPCA_SMALL)[0].frame == 240 - result.boundaries[0].frame
    )


@SETTINGS
@given(
    st.integers(0, 2**32 - 1),
    st.integers(1, 5),
    st.lists(st.integers(5, 90), min_size=1, max_size=4),
    st.floats(0.0, 40.0),
    st.integers(0, 300),
    st.sampled_from([None, 0.0]),
)
def test_the_ppca_stream_equals_the_forward_pass(
    seed: int, dims: int, lengths: list[int], rise: float, split: int, shortest: float | None
) -> None:
    x = regimes(seed, dims, lengths)
    params = PpcaParams(window=1.5, delta=0.2, rise=rise, shortest=shortest)
    stream = PpcaSegmenter(RATE, params=params)
    split = min(split, len(x))
    for piece in (x[:split], x[split:]):
        assert pushed(stream, piece) == bh.ppca_forward(piece, RATE, params=params)


def test_the_ppca_stream_returns_a_cut_when_its_peak_is_confirmed() -> None:
    rng = np.random.default_rng(2)
    x = np.concatenate([0.05 * rng.normal(size=(80, 4)), rng.normal(size=(80, 4))])  # narrow, then wide
    stream = PpcaSegmenter(RATE, params=PPCA_SMALL)
    seen = [(i, b) for i, row in enumerate(x) for b in stream.push(row)]
    assert [abs(b.frame - 80) <= 4 for _, b in seen] == [True]
    for i, b in seen:
        assert b.emitted == i == b.frame + 2 + 15 - 1  # Δ + T - 1 frames after the cut


# ------------------------------------------------------------------------------- the real files


@pytest.mark.slow
@pytest.mark.parametrize("trial", REAL)
def test_the_streams_equal_their_batch_twins_on_real_recordings(trial: str) -> None:
    x = frames(trial)
    rate = 120.0
    for params in (bh.PCA_PAPER, bh.PCA_GRID):
        expected = bh.pca_segment(x, rate, params=params)
        assert pushed(PcaSegmenter(rate, params=params), x) == expected
    assert len(expected) >= 1
    for ppca in (bh.PPCA_DEFAULT, bh.PPCA_PUBLISHED):
        forward = bh.ppca_forward(x, rate, params=ppca)
        stream, online, kept = PpcaSegmenter(rate, params=ppca), [], 0
        for row in x:
            online += stream.push(row)
            kept = max(kept, len(stream._kept))
        assert online + stream.flush() == forward
        assert kept <= 2 * 150  # bounded: the frames from K - Δ (or the segment's start) on
        assert all(b.emitted == b.frame + 10 + 150 - 1 for b in forward)
    assert len(forward) >= 1


# ------------------------------------------------------------------------------------------- GMM


def test_gmm_finds_separated_behaviours_deterministically() -> None:
    x = regimes(11, 6, [90, 120, 100, 110])
    got = bh.gmm_analysis(x, 30.0)
    assert [b.frame for b in got.boundaries] == [90, 210, 310]
    assert all(b.score > 0 and b.emitted == len(x) - 1 for b in got.boundaries)
    again = bh.gmm_analysis(x, 30.0)
    assert again.boundaries == got.boundaries and np.array_equal(again.raw_labels, got.raw_labels)
    assert [b.frame for b in bh.gmm_segment(x, 30.0, params=GmmParams(seed=5))] == [90, 210, 310]


def test_short_runs_are_split_between_their_neighbours() -> None:
    labels = [0] * 200 + [1] * 51 + [2] * 200
    merged = bh.merge_short_runs(labels, 120)
    assert merged.tolist() == [0] * 225 + [2] * 226
    assert bh.merge_short_runs([3] * 50 + [0] * 200, 120).tolist() == [0] * 250
    assert bh.merge_short_runs([0] * 200 + [3] * 50, 120).tolist() == [0] * 250
    assert bh.merge_short_runs([1] * 30 + [2] * 40, 120).tolist() == [2] * 70
    assert bh.merge_short_runs([], 120).tolist() == []


@SETTINGS
@given(st.lists(st.integers(0, 3), max_size=300), st.integers(0, 40))
def test_merged_runs_are_long_enough(labels: list[int], min_length: int) -> None:
    merged = bh.merge_short_runs(labels, min_length).tolist()
    assert len(merged) == len(labels)
    assert set(merged) <= set(labels)
    runs = [len(list(g)) for _, g in itertools.groupby(merged)]
    assert len(runs) <= 1 or min(runs) >= min_length


# ------------------------------------------------------------------------------------ robustness


def all_methods(x: FloatArray) -> tuple[bh.PcaResult, bh.PpcaResult, bh.GmmResult]:
    """Every method, checking the streams agree and every signal value is a number."""
    pca, ppca, gmm = bh.pca_analysis(x, 120.0), bh.ppca_analysis(x, 120.0), bh.gmm_analysis(x, 120.0)
    assert pushed(PcaSegmenter(120.0), x) == pca.boundaries
    assert pushed(PpcaSegmenter(120.0), x) == bh.ppca_forward(x, 120.0)
    assert np.all(np.isfinite(pca.error)) and np.all(np.isfinite(pca.d)) and np.all(np.isfinite(ppca.h))
    for b in [*pca.boundaries, *ppca.boundaries, *gmm.boundaries]:
        assert math.isfinite(b.score)
    return pca, ppca, gmm


def test_a_recording_that_stands_still_has_no_cut() -> None:
    m = motion("86_01")
    x = JointRotations(m.skeleton)(np.repeat(m.channels[700:701], 900, axis=0))
    pca, ppca, gmm = all_methods(x)
    assert (pca.boundaries, ppca.boundaries, gmm.boundaries) == ([], [], [])
    assert np.all(pca.error == 0.0) and np.all(ppca.h == 0.0)


@pytest.mark.slow
def test_standing_still_inside_a_recording_is_cut_where_it_ends() -> None:
    m = motion("86_01")
    channels = np.concatenate(
        [m.channels[:700], np.repeat(m.channels[700:701], 600, axis=0), m.channels[700:1400]]
    )
    pca, ppca, gmm = all_methods(JointRotations(m.skeleton)(channels))
    for method in (pca.boundaries, ppca.boundaries, gmm.boundaries):
        assert any(1300 <= b.frame <= 1300 + 10 for b in method)


def test_a_t_pose_then_motion_is_cut_where_the_motion_starts() -> None:
    m = motion("86_01")
    channels = np.concatenate([np.zeros((360, m.channels.shape[1])), m.channels[:900]])
    x = JointRotations(m.skeleton)(channels)
    assert np.all(x[:360] == np.tile([1.0, 0.0, 0.0, 0.0], 14))  # every bone at the identity
    pca, ppca, gmm = all_methods(x)
    # PCA needs one non-zero derivative before its deviation is > 0: a frame late.
    assert pca.boundaries[0].frame == 361
    assert ppca.boundaries[0].frame == 360
    # the first walking frames lie nearer the T-pose's cluster than the walk's: within the
    # evaluation's tolerance (0.5 s)
    assert 360 <= gmm.boundaries[0].frame <= 360 + 60


@pytest.mark.parametrize("n", [0, 1, 2, 10, 200])
def test_a_recording_shorter_than_the_windows_has_no_cut(n: int) -> None:
    x = frames("13_30")[:n]
    pca, ppca, gmm = all_methods(x)
    assert (pca.boundaries, ppca.boundaries, gmm.boundaries) == ([], [], [])


def test_frames_that_are_not_finite_are_refused_and_leave_the_stream_as_it_was() -> None:
    x = frames("13_30")[:1000]
    bad = x.copy()
    bad[700, 5] = np.inf
    for method in ("pca", "ppca", "gmm"):
        with pytest.raises(ValueError, match="frame 700"):
            bh.segment(bad, 120.0, method)
    for stream, batch in ((PcaSegmenter(120.0), bh.pca_segment), (PpcaSegmenter(120.0), bh.ppca_forward)):
        got = [b for row in x[:700] for b in stream.push(row)]
        with pytest.raises(ValueError, match=r"frame 700.*not finite"):
            stream.push(bad[700])
        with pytest.raises(ValueError, match="shape"):
            stream.push(x[700, :-1])
        got += [b for row in x[700:] for b in stream.push(row)] + stream.flush()
        assert got == batch(x, 120.0)
        assert len(got) >= 1


def test_the_dispatch_runs_each_method() -> None:
    x = frames("13_30")[:1000]
    assert bh.segment(x, 120.0, "pca") == bh.pca_segment(x, 120.0)
    assert bh.segment(x, 120.0, "ppca", params=PPCA_SMALL) == bh.ppca_segment(x, 120.0, params=PPCA_SMALL)
    assert bh.segment(x, 120.0, "gmm") == bh.gmm_segment(x, 120.0)
    assert isinstance(bh.online_segmenter(120.0, "ppca"), PpcaSegmenter)
