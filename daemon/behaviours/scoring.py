"""Scoring cuts against true boundaries, each with the band of frames a cut may fall on to find it
(:class:`daemon.types.Band`): what ``mocapd segment --truth`` and the evaluation count."""

from __future__ import annotations

from collections.abc import Sequence

from daemon.types import Band


def match_boundaries(cuts: Sequence[int], bands: Sequence[Band]) -> int:
    """How many true boundaries ``bands`` the ``cuts`` (frames of new behaviours) find, each cut and
    each boundary used once: the pairs (cut, boundary) with the cut in the boundary's band, taken
    greedily by increasing distance from the cut to the boundary's frame."""
    pairs = sorted(
        (abs(c - b.frame), i, j) for i, c in enumerate(cuts) for j, b in enumerate(bands) if b.lo <= c <= b.hi
    )
    used_cuts: set[int] = set()
    used_bands: set[int] = set()
    for _, i, j in pairs:
        if i not in used_cuts and j not in used_bands:
            used_cuts.add(i)
            used_bands.add(j)
    return len(used_cuts)
