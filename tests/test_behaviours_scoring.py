"""Cuts scored against true boundaries (daemon.behaviours.scoring): each cut and each boundary
counts once."""

from __future__ import annotations

from hypothesis import given
from hypothesis import strategies as st

from daemon.behaviours.scoring import match_boundaries, pair_boundaries
from daemon.types import Band


def test_each_cut_and_boundary_counts_once() -> None:
    bands = [Band(100, 90, 110), Band(120, 110, 130)]
    assert match_boundaries([], bands) == 0
    assert match_boundaries([100, 101, 102], bands) == 1  # three cuts, one boundary in reach
    assert match_boundaries([110], bands) == 1  # in both bands: one boundary found
    assert match_boundaries([109, 111], bands) == 2  # each takes its own
    assert match_boundaries([110, 119], bands) == 2  # 119 takes 120 first; 110 then takes 100
    assert match_boundaries([89, 131], bands) == 0


def test_the_pairs_say_which_cut_found_which_boundary() -> None:
    bands = [Band(100, 90, 110), Band(120, 110, 130)]
    assert pair_boundaries([110, 119], bands) == {1: 1, 0: 0}
    assert pair_boundaries([100, 101, 102], bands) == {0: 0}  # 101 and 102: false cuts
    assert pair_boundaries([89, 131], bands) == {}  # two false cuts, both boundaries missed


@given(
    st.lists(st.integers(0, 400), max_size=12),
    st.lists(st.tuples(st.integers(0, 400), st.integers(0, 40), st.integers(0, 40)), max_size=8),
)
def test_pairs_are_one_to_one_within_bands(cuts: list[int], spans: list[tuple[int, int, int]]) -> None:
    bands = [Band(f, f - a, f + b) for f, a, b in spans]
    pairs = pair_boundaries(cuts, bands)
    assert len(set(pairs.values())) == len(pairs) == match_boundaries(cuts, bands)
    assert all(bands[j].lo <= cuts[i] <= bands[j].hi for i, j in pairs.items())
    # greedy by distance: a cut left out has no free band in reach
    free = set(range(len(bands))) - set(pairs.values())
    assert not any(
        bands[j].lo <= c <= bands[j].hi for i, c in enumerate(cuts) if i not in pairs for j in free
    )
