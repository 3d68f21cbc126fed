"""The 39 relational features: against the original toolbox, and primitives against slow references."""

from __future__ import annotations

import csv
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from daemon.features import FEATURE_NAMES, SET_SLICES, features, hysteresis, smoothed_velocity, window_frames
from replay import JOINT_NAMES
from tests.conftest import DATA, ORACLE, joints_cm
from tests.test_oracle import CLIPS


def clip_features(clip: str) -> np.ndarray:
    asf, amc = CLIPS[clip]
    return features(joints_cm(DATA / asf, DATA / amc), JOINT_NAMES, 120.0)


@pytest.mark.parametrize("clip", sorted(CLIPS))
def test_features_match_toolbox(clip: str) -> None:
    with open(ORACLE / f"{clip}.features.csv", newline="") as f:
        rows = csv.reader(f)
        header = next(rows)
        oracle = np.array([[int(v) for v in row[1:]] for row in rows], dtype=bool)
    assert tuple(header[1:]) == FEATURE_NAMES
    ours = clip_features(clip)
    assert ours.shape == oracle.shape
    per_feature = (ours == oracle).mean(axis=0)
    assert (ours == oracle).mean() >= 0.995
    assert per_feature.min() >= 0.98, dict(zip(FEATURE_NAMES, per_feature.round(4), strict=True))


def test_catalog_sets() -> None:
    assert len(FEATURE_NAMES) == 39
    assert [s.stop - s.start for s in SET_SLICES.values()] == [12, 14, 13]


def slow_hysteresis(f1: list[bool], f2: list[bool]) -> list[bool]:
    out, on = [], False
    for a, b in zip(f1, f2, strict=True):
        on = b or (on and a)
        out.append(on)
    return out


@settings(max_examples=300, deadline=None)
@given(st.lists(st.tuples(st.booleans(), st.booleans()), min_size=1, max_size=60))
def test_hysteresis_equals_the_recurrence(pairs: list[tuple[bool, bool]]) -> None:
    f2 = [b for _, b in pairs]
    f1 = [a or b for a, b in pairs]  # nested tracks: f2 implies f1
    got = hysteresis(np.array(f1)[:, None], np.array(f2)[:, None])[:, 0]
    assert got.tolist() == slow_hysteresis(f1, f2)


def reflect(j: int, m: int) -> int:
    """Index ``j`` mirrored into ``0..m-1``, edge repeated: ..., 1, 0 | 0, 1, ..., m-1 | m-1, m-2, ..."""
    while j < 0 or j >= m:
        j = -j - 1 if j < 0 else 2 * m - j - 1
    return j


def slow_velocity(x: np.ndarray, window_ms: float, fs: float) -> np.ndarray:
    n, big_l = len(x), window_frames(window_ms, fs)
    v = [x[t + 1] - x[t] for t in range(n - 1)] + ([x[n - 1] - x[n - 2]] if n > 1 else [np.zeros(3)])
    if n < big_l:
        v = [v[reflect(j, n)] for j in range(big_l)]
    h = math.ceil(big_l / 2)
    rows = [sum(v[reflect(t + k - h + 1, len(v))] for k in range(big_l)) / big_l * fs for t in range(n)]
    return np.array(rows, dtype=np.float64)


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
