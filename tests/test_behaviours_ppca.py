"""Behaviour segmentation by probabilistic PCA (daemon.behaviours.ppca; Barbič et al. 2004, §3.2):
the windows in seconds, the forward pass and its signal ``H`` against a slow reference that reads
the paper literally, the peak test on sequences with ties, the backward passes, the stream equal to
the forward pass on random data (on real recordings: tests/test_behaviours.py) and returning each
cut when its peak is confirmed."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st

from daemon.behaviours.ppca import (
    PPCA_DEFAULT,
    PPCA_PUBLISHED,
    PpcaFrames,
    PpcaParams,
    PpcaSegmenter,
    _PpcaRun,
    ppca_analysis,
    ppca_forward,
    ppca_segment,
)
from daemon.stages import run
from tests.behaviour_data import PPCA_SMALL, RATE, SETTINGS, Regimes, regime_cases, regimes
from tests.naive import slow_peak, slow_ppca_forward, slow_ppca_segment


def test_windows_are_seconds_scaled_to_the_rate() -> None:
    assert PPCA_DEFAULT.frames(120.0) == PpcaFrames(150, 10, 450)
    assert PPCA_DEFAULT.frames(240.0) == PpcaFrames(300, 20, 900)
    assert PPCA_PUBLISHED.frames(120.0) == PpcaFrames(150, 10, 0)
    for wrong in (
        PpcaParams(delta=2.0),
        PpcaParams(window=0.001),
        PpcaParams(min_variance=0.0),
        PpcaParams(shortest=-1.0),
        PpcaParams(shortest=math.nan),
    ):
        with pytest.raises(ValueError):
            wrong.frames(120.0)


@SETTINGS
@given(regime_cases(dims=(2, 5), lengths=(20, 90)), st.floats(1.0, 40.0), st.sampled_from([None, 0, 25]))
def test_ppca_forward_pass_equals_the_paper_read_literally(
    case: Regimes, rise: float, shortest: int | None
) -> None:
    """The running moments and the eigen-decomposition of their scatter give the ``H`` that an SVD
    of the first ``K`` frames and Eqs. 7-10 give, hence the same peaks and cuts."""
    x = regimes(*case)
    params = PpcaParams(
        window=1.5, delta=0.2, rise=rise, shortest=None if shortest is None else shortest / RATE
    )
    cuts, trace = slow_ppca_forward(x, 15, 2, rise, 0.95, 45 if shortest is None else shortest)
    got = ppca_analysis(x, RATE, params=params)
    forward = ppca_forward(x, RATE, params=params)
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
    state = _PpcaRun(params, params.frames(RATE))
    for i, h in enumerate(hs):
        state.moments.n = i  # K, the index here
        peak = state.observe(float(h))
        assert peak == slow_peak([(k, float(v)) for k, v in enumerate(hs[: i + 1])], rise, shortest)
        if peak is not None:
            break


@settings(deadline=None, max_examples=10, suppress_health_check=[HealthCheck.too_slow])
@given(regime_cases(dims=(2, 4), lengths=(20, 80), runs=(2, 4)))
def test_ppca_passes_equal_the_slow_passes(case: Regimes) -> None:
    x = regimes(*case)
    got = ppca_segment(x, RATE, params=PPCA_SMALL)
    assert [b.frame for b in got] == slow_ppca_segment(x, 15, 2, 15.0, 0.95, 30)
    forward = ppca_forward(x, RATE, params=PPCA_SMALL)
    assert set(forward) <= set(got)  # the forward pass's cuts are kept as they are
    assert all(b.emitted == len(x) - 1 for b in set(got) - set(forward))


def test_the_backward_pass_finds_a_narrow_behaviour_after_a_wide_one() -> None:
    """§3.2's rare case: frames of a narrow distribution inside a wide one look likely under the
    wide model, so the forward pass misses the change; the backward pass finds it."""
    rng = np.random.default_rng(1)
    x = np.concatenate([rng.normal(size=(120, 4)), 0.05 * rng.normal(size=(120, 4))])
    assert ppca_forward(x, RATE, params=PPCA_SMALL) == []
    result = ppca_analysis(x, RATE, params=PPCA_SMALL)
    assert [abs(b.frame - 120) <= 4 for b in result.boundaries] == [True]
    assert result.passes == 3  # forward, backward (one cut), forward again (none new)
    assert ppca_forward(x[::-1].copy(), RATE, params=PPCA_SMALL)[0].frame == 240 - result.boundaries[0].frame


@SETTINGS
@given(
    regime_cases(dims=(1, 5), lengths=(5, 90)),
    st.floats(0.0, 40.0),
    st.integers(0, 300),
    st.sampled_from([None, 0.0]),
)
def test_the_ppca_stream_equals_the_forward_pass(
    case: Regimes, rise: float, split: int, shortest: float | None
) -> None:
    x = regimes(*case)
    params = PpcaParams(window=1.5, delta=0.2, rise=rise, shortest=shortest)
    stream = PpcaSegmenter(RATE, params=params)
    split = min(split, len(x))
    for piece in (x[:split], x[split:]):
        assert run(stream, piece) == ppca_forward(piece, RATE, params=params)


def test_the_ppca_stream_returns_a_cut_when_its_peak_is_confirmed() -> None:
    rng = np.random.default_rng(2)
    x = np.concatenate([0.05 * rng.normal(size=(80, 4)), rng.normal(size=(80, 4))])  # narrow, then wide
    stream = PpcaSegmenter(RATE, params=PPCA_SMALL)
    seen = [(i, b) for i, row in enumerate(x) for b in stream.push(row)]
    assert [abs(b.frame - 80) <= 4 for _, b in seen] == [True]
    for i, b in seen:
        assert b.emitted == i == b.frame + 2 + 15 - 1  # Δ + T - 1 frames after the cut
