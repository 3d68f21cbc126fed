"""The 39 relational features: equal to the original toolbox's in every frame, and primitives against slow
references."""

from __future__ import annotations

import csv

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from daemon.features import FEATURE_NAMES, SET_SLICES, features, hysteresis, smoothed_velocity
from replay import JOINT_NAMES
from tests.helpers import DATA, ORACLE, ORACLE_CLIPS, joints_cm
from tests.naive import slow_hysteresis, slow_velocity


def clip_features(clip: str) -> np.ndarray:
    asf, amc = ORACLE_CLIPS[clip]
    return features(joints_cm(DATA / asf, DATA / amc), JOINT_NAMES, 120.0)


@pytest.mark.parametrize("clip", sorted(ORACLE_CLIPS))
def test_features_match_toolbox(clip: str) -> None:
    with open(ORACLE / f"{clip}.features.csv", newline="") as f:
        rows = csv.reader(f)
        header = next(rows)
        oracle = np.array([[int(v) for v in row[1:]] for row in rows], dtype=bool)
    assert tuple(header[1:]) == FEATURE_NAMES
    ours = clip_features(clip)
    assert ours.shape == oracle.shape
    # every cell: a threshold moved by 2 degrees flips only a few frames of one feature
    differing = {
        name: np.flatnonzero(ours[:, f] != oracle[:, f]).tolist()
        for f, name in enumerate(FEATURE_NAMES)
        if np.any(ours[:, f] != oracle[:, f])
    }
    assert not differing, "features differing from the toolbox (0-based frames): " + "; ".join(
        f"{name}: {len(frames)} frames {frames[:10]}{' ...' if len(frames) > 10 else ''}"
        for name, frames in differing.items()
    )


def test_catalog_sets() -> None:
    assert len(FEATURE_NAMES) == 39
    assert [s.stop - s.start for s in SET_SLICES.values()] == [12, 14, 13]


@settings(max_examples=300, deadline=None)
@given(st.lists(st.tuples(st.booleans(), st.booleans()), min_size=1, max_size=60))
def test_hysteresis_equals_the_recurrence(pairs: list[tuple[bool, bool]]) -> None:
    f2 = [b for _, b in pairs]
    f1 = [a or b for a, b in pairs]  # nested tracks: f2 implies f1
    got = hysteresis(np.array(f1)[:, None], np.array(f2)[:, None])[:, 0]
    assert got.tolist() == slow_hysteresis(f1, f2)


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
