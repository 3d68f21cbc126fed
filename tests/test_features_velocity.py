"""Smoothed velocities (daemon/features/velocity.py) against a slow reference that mirrors the
forward differences one index at a time (:func:`tests.naive.slow_velocity`)."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from daemon.features import smoothed_velocity
from tests.naive import slow_velocity


@settings(max_examples=200, deadline=None)
@given(
    hnp.arrays(np.float64, st.tuples(st.integers(2, 50), st.just(3)), elements=st.floats(-100, 100)),
    st.sampled_from([0.0, 50.0, 100.0, 250.0]),
    st.sampled_from([30.0, 120.0]),
)
def test_smoothed_velocity_equals_slow_reference(x: np.ndarray, window_ms: float, fs: float) -> None:
    assert np.allclose(
        smoothed_velocity(x, window_ms, fs), slow_velocity(x, window_ms, fs), rtol=1e-9, atol=1e-7
    )
