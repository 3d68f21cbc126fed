"""Behaviour segmentation by PCA (daemon.behaviours.pca; Barbič et al. 2004, §3.1): the windows in
seconds, the cuts and the signal against a slow reference that reads the paper literally (an SVD of
the explicit frames at every step), the stream equal to its batch twin on random data (on real
recordings: tests/test_behaviours.py)."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from daemon.behaviours.pca import (
    PCA_GRID,
    PCA_ONLINE,
    PCA_PAPER,
    PcaFrames,
    PcaParams,
    PcaSegmenter,
    pca_analysis,
    pca_segment,
)
from daemon.stages import run
from tests.behaviour_data import RATE, SETTINGS, Regimes, regime_cases, regimes
from tests.naive import slow_pca_segment


def test_windows_are_seconds_scaled_to_the_rate() -> None:
    assert PCA_PAPER.frames(120.0) == PcaFrames(240, 60, 300, 1)
    assert PCA_PAPER.frames(60.0) == PcaFrames(120, 30, 150, 1)
    assert PCA_GRID.frames(120.0) == PcaFrames(240, 60, 300, 60)
    # the step rounded down to a divisor of k and ℓ: 10 frames at 120 Hz, 5 at 100 Hz (ℓ = 50)
    assert [PCA_ONLINE.frames(r).step for r in (120.0, 100.0, 30.0)] == [10, 5, 1]
    assert PcaParams(step=0.3).frames(120.0).step == 30
    for bad in (PcaParams(tau=1.0), PcaParams(k=0.4), PcaParams(k_sigma=-1)):
        with pytest.raises(ValueError):
            bad.frames(120.0)
    with pytest.raises(ValueError, match="rate"):
        PcaSegmenter(0.0)


def test_pca_equals_the_slow_reference_and_finds_cuts() -> None:
    """A fixed example that has cuts, against the reference that takes an SVD at every frame."""
    x = regimes(7, 4, [60, 70, 80])
    p = PcaParams().frames(RATE)
    cuts, trace = slow_pca_segment(x, p.k, p.ell, p.i0, 0.9, 3.0)
    got = pca_analysis(x, RATE)
    assert len(cuts) >= 1
    assert [b.frame for b in got.boundaries] == [c for c, _ in cuts]
    assert np.allclose([b.score for b in got.boundaries], [s for _, s in cuts], rtol=1e-7)
    assert got.frame.tolist() == [f for f, _, _ in trace]
    assert np.allclose(got.error, [e for _, e, _ in trace], rtol=1e-9, atol=1e-9)
    assert np.allclose(got.d, [d for _, _, d in trace], rtol=1e-7, atol=1e-9)


@SETTINGS
@given(
    regime_cases(dims=(2, 5), lengths=(15, 80)),
    st.sampled_from([0.8, 0.9, 0.95]),
    st.sampled_from([1.0, 2.0, 3.0]),
)
def test_pca_equals_the_paper_read_literally(case: Regimes, tau: float, k_sigma: float) -> None:
    """The running moments and the eigenvalues of the scatter give the errors ``e_i`` an SVD of
    the segment's explicit frames gives, hence the same derivatives, tests and cuts."""
    x = regimes(*case)
    params = PcaParams(tau=tau, k_sigma=k_sigma)
    p = params.frames(RATE)
    cuts, trace = slow_pca_segment(x, p.k, p.ell, p.i0, tau, k_sigma)
    got = pca_analysis(x, RATE, params=params)
    assert [b.frame for b in got.boundaries] == [c for c, _ in cuts]
    assert all(b.emitted == b.frame and b.method == "pca" for b in got.boundaries)
    assert np.allclose([b.score for b in got.boundaries], [s for _, s in cuts], rtol=1e-6)
    assert got.frame.tolist() == [f for f, _, _ in trace]
    scale = max(1.0, float(np.abs(got.error).max(initial=0.0)))
    assert np.allclose(got.error, [e for _, e, _ in trace], rtol=1e-9, atol=1e-10 * scale)


@SETTINGS
@given(regime_cases(dims=(1, 5), lengths=(5, 80)), st.sampled_from([None, 0.1, 0.5]), st.integers(0, 300))
def test_the_pca_stream_equals_the_batch(case: Regimes, step: float | None, split: int) -> None:
    x = regimes(*case)
    params = PcaParams(step=step)
    stream = PcaSegmenter(RATE, params=params)
    split = min(split, len(x))
    for piece in (x[:split], x[split:]):  # the flush between them starts a new stream
        assert run(stream, piece) == pca_segment(piece, RATE, params=params)
