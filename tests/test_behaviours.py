"""Behaviour segmentation as a whole (daemon.behaviours; Barbič et al. 2004; its place among the
packages is tests/test_architecture.py's): both streams equal to their batch twins on real
recordings; every method on the robustness cases of real recordings (standing still, a T-pose, a
clip shorter than the windows, input that is not finite), the streams agreeing with their batch
twins."""

from __future__ import annotations

import math

import numpy as np
import pytest

from daemon import behaviours as bh
from daemon.behaviours import Boundary, JointRotations, PcaSegmenter, PpcaSegmenter
from daemon.stages import Stage, run
from daemon.types import FloatArray
from tests.behaviour_data import REAL, frames, motion

# Each stream is a Stage (mypy checks these).
_PCA: Stage[FloatArray, Boundary] = PcaSegmenter(120.0)
_PPCA: Stage[FloatArray, Boundary] = PpcaSegmenter(120.0)


@pytest.mark.slow
@pytest.mark.parametrize("trial", REAL)
def test_the_streams_equal_their_batch_twins_on_real_recordings(trial: str) -> None:
    x = frames(trial)
    rate = 120.0
    for params in (bh.PCA_PAPER, bh.PCA_GRID):
        expected = bh.pca_segment(x, rate, params=params)
        assert run(PcaSegmenter(rate, params=params), x) == expected
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


def all_methods(x: FloatArray) -> tuple[bh.PcaResult, bh.PpcaResult, bh.GmmResult]:
    """Every method, checking the streams agree and every signal value is a number."""
    pca, ppca, gmm = bh.pca_analysis(x, 120.0), bh.ppca_analysis(x, 120.0), bh.gmm_analysis(x, 120.0)
    assert run(PcaSegmenter(120.0), x) == pca.boundaries
    assert run(PpcaSegmenter(120.0), x) == bh.ppca_forward(x, 120.0)
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
