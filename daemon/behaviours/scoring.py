"""Scoring cuts against true boundaries, each with the band of frames a cut may fall on to find it
(:class:`daemon.types.Band`): what ``mocapd segment --truth`` and the evaluation count."""

from __future__ import annotations

from collections.abc import Sequence

from daemon.types import Band


def pair_boundaries(cuts: Sequence[int], bands: Sequence[Band]) -> dict[int, int]:
    """Which true boundary each cut (a frame of a new behaviour) finds, as ``{cut index: band
    index}``, each cut and each boundary used once: the pairs (cut, boundary) with the cut in the
    boundary's band, taken greedily by increasing distance from the cut to the boundary's frame.
    A cut not in it is a false cut; a band not among its values, a missed boundary."""
    pairs = sorted(
        (abs(c - b.frame), i, j) for i, c in enumerate(cuts) for j, b in enumerate(bands) if b.lo <= c <= b.hi
    )
    found: dict[int, int] = {}
    used: set[int] = set()
    for _, i, j in pairs:
        if i not in found and j not in used:
            found[i] = j
            used.add(j)
    return found


def match_boundaries(cuts: Sequence[int], bands: Sequence[Band]) -> int:
    """How many true boundaries ``bands`` the ``cuts`` find (:func:`pair_boundaries`)."""
    return len(pair_boundaries(cuts, bands))
