"""Cuts scored against true boundaries (daemon.behaviours.scoring): each cut and each boundary
counts once."""

from __future__ import annotations

from daemon.behaviours.scoring import match_boundaries
from daemon.types import Band


def test_each_cut_and_boundary_counts_once() -> None:
    bands = [Band(100, 90, 110), Band(120, 110, 130)]
    assert match_boundaries([], bands) == 0
    assert match_boundaries([100, 101, 102], bands) == 1  # three cuts, one boundary in reach
    assert match_boundaries([110], bands) == 1  # in both bands: one boundary found
    assert match_boundaries([109, 111], bands) == 2  # each takes its own
    assert match_boundaries([110, 119], bands) == 2  # 119 takes 120 first; 110 then takes 100
    assert match_boundaries([89, 131], bands) == 0
