"""Behaviour segmentation by a Gaussian mixture (daemon.behaviours.gmm; Barbič et al. 2004, §3.3):
separated behaviours found deterministically, and the merging of segments shorter than the
shortest behaviour."""

from __future__ import annotations

import itertools

import numpy as np
from hypothesis import given
from hypothesis import strategies as st

from daemon.behaviours.gmm import GmmParams, gmm_analysis, gmm_segment, merge_short_runs
from tests.behaviour_data import SETTINGS, regimes


def test_the_minimum_length_is_seconds_scaled_to_the_rate() -> None:
    assert GmmParams().check(120.0) == 120


def test_gmm_finds_separated_behaviours_deterministically() -> None:
    x = regimes(11, 6, [90, 120, 100, 110])
    got = gmm_analysis(x, 30.0)
    assert [b.frame for b in got.boundaries] == [90, 210, 310]
    assert all(b.score > 0 and b.emitted == len(x) - 1 for b in got.boundaries)
    again = gmm_analysis(x, 30.0)
    assert again.boundaries == got.boundaries and np.array_equal(again.raw_labels, got.raw_labels)
    assert [b.frame for b in gmm_segment(x, 30.0, params=GmmParams(seed=5))] == [90, 210, 310]


def test_short_runs_are_split_between_their_neighbours() -> None:
    labels = [0] * 200 + [1] * 51 + [2] * 200
    merged = merge_short_runs(labels, 120)
    assert merged.tolist() == [0] * 225 + [2] * 226
    assert merge_short_runs([3] * 50 + [0] * 200, 120).tolist() == [0] * 250
    assert merge_short_runs([0] * 200 + [3] * 50, 120).tolist() == [0] * 250
    assert merge_short_runs([1] * 30 + [2] * 40, 120).tolist() == [2] * 70
    assert merge_short_runs([], 120).tolist() == []


@SETTINGS
@given(st.lists(st.integers(0, 3), max_size=300), st.integers(0, 40))
def test_merged_runs_are_long_enough(labels: list[int], min_length: int) -> None:
    merged = merge_short_runs(labels, min_length).tolist()
    assert len(merged) == len(labels)
    assert set(merged) <= set(labels)
    runs = [len(list(g)) for _, g in itertools.groupby(merged)]
    assert len(runs) <= 1 or min(runs) >= min_length
