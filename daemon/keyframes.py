"""Keyframe queries (thesis ch. 4): keyframes with stiffness, the bounds of their gaps and their
parsing from ``manual-keyframes.json`` entries. The search over an index is
:mod:`daemon.search.keyframes`; the live gate is :mod:`daemon.automaton`.

A keyframe is a {0, 1, ½} vector over one feature set: the set V of every vector that agrees with its
0/1 entries (Def. 4.3); a *tolerant* keyframe (ours: ``mismatches`` m > 0) widens V to every vector
that differs from it in at most m of those entries (Hamming distance <= m on the fixed bits). Gap ``k``
has a nominal distance δ_k (difference of keyframe positions) and a stiffness σ_k; a hit (Def. 4.4)
is frames i_1 <= ... <= i_K with w(i_k) in V_k and σ_k δ_k <= i_{k+1} - i_k <= δ_k / σ_k (no upper
bound when σ_k = 0). Stiffness is read as the decimal it is written as (0.7 = 7/10), so the bounds
⌈σδ⌉ and ⌊δ/σ⌋ of μ (Def. 4.9) are exact.

Positions are index-rate frames. Pure: Python in, frozen dataclasses out.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Sequence
from dataclasses import dataclass
from fractions import Fraction
from pathlib import Path
from typing import Any

from daemon.checks import Checker, number_reason
from daemon.errors import MocapdError
from daemon.features import SET_SLICES
from daemon.types import FEATURE_SETS, FeatureSet


class KeyframeError(MocapdError, ValueError):
    """A keyframe query that cannot be run; the message names the source and the field."""


@dataclass(frozen=True)
class Keyframe:
    """One keyframe: ``values`` over ``feature_set`` (0, 1 or 0.5 = either), the template column
    ``position`` and the stiffness of the gap to the next keyframe (None for the last).
    ``mismatches``: how many of the fixed (0/1) entries a frame may get wrong and still match, 0 to
    the number of fixed entries - 1 (0, the thesis' keyframe, when none is fixed)."""

    feature_set: FeatureSet
    values: tuple[float, ...]
    position: int
    stiffness_to_next: float | None
    mismatches: int = 0

    def __post_init__(self) -> None:
        m = self.mismatches
        if isinstance(m, bool) or not isinstance(m, int) or m < 0 or (m > 0 and m > self.max_mismatches):
            raise ValueError(
                f"mismatches must be an integer in [0, {self.max_mismatches}] for a keyframe with "
                f"{self.mask.bit_count()} fixed entries, got {self.mismatches!r:.60}"
            )

    @property
    def max_mismatches(self) -> int:
        """The largest ``mismatches`` allowed: one less than the fixed entries (at least 0), so that
        a tolerant keyframe still needs one of them right."""
        return max(0, self.mask.bit_count() - 1)

    @property
    def mask(self) -> int:
        """Bits fixed by the keyframe (bit i = feature i of the set)."""
        return sum(1 << i for i, v in enumerate(self.values) if v != 0.5)

    @property
    def value(self) -> int:
        """The fixed bits' values."""
        return sum(1 << i for i, v in enumerate(self.values) if v == 1)

    def matches(self, code: int) -> bool:
        """Whether the frame whose ``feature_set`` code (bit i = feature i of the set) is ``code``
        lies in V: at most ``mismatches`` of the fixed bits differ."""
        return ((code ^ self.value) & self.mask).bit_count() <= self.mismatches


@dataclass(frozen=True)
class KeyframeQuery:
    """Keyframes in search order, positions in frames at ``rate`` Hz."""

    name: str
    keyframes: tuple[Keyframe, ...]
    rate: float
    template_length: int | None = None

    def gaps(self, rate: float) -> list[tuple[int, float]]:
        """(δ_k, σ_k) per gap, δ in frames at ``rate`` (positions rescaled and rounded)."""
        out = []
        for a, b in zip(self.keyframes, self.keyframes[1:], strict=False):
            assert a.stiffness_to_next is not None
            out.append((round((b.position - a.position) * rate / self.rate), a.stiffness_to_next))
        return out


@functools.lru_cache(maxsize=4096)  # a stream's automata are made for every stream that joins
def gap_bounds(delta: int, stiffness: float) -> tuple[int, int | None]:
    """The distances μ allows (Def. 4.9): (⌈σδ⌉, ⌊δ/σ⌋), or (0, None) = unbounded for σ = 0."""
    if delta < 0:
        raise ValueError(f"a keyframe gap must not be negative, got {delta}")
    if not 0 <= stiffness <= 1:
        raise ValueError(f"stiffness must be in [0, 1], got {stiffness}")
    s = Fraction(repr(float(stiffness)))
    if s == 0:
        return 0, None
    return math.ceil(s * delta), math.floor(delta / s)


def query_bounds(
    query: KeyframeQuery, rate: float, max_gap: int | None = None
) -> list[tuple[int, int | None]]:
    """μ's distance bounds (:func:`gap_bounds`) of every gap of ``query`` at ``rate`` Hz; with
    ``max_gap`` (frames at ``rate``), an unbounded gap (σ = 0) allows at most that many frames, so
    that a streaming search (:class:`daemon.automaton.KeyframeAutomaton`) holds a bounded state."""
    if max_gap is not None and max_gap < 0:
        raise ValueError(f"the maximum gap must not be negative, got {max_gap}")
    bounds = [gap_bounds(d, s) for d, s in query.gaps(rate)]
    return [(lo, max_gap if hi is None else hi) for lo, hi in bounds]


# ------------------------------------------------------------------------------- parsing the JSON


def parse_keyframe_queries(obj: Any, source: str | Path) -> dict[str, KeyframeQuery]:
    """The classes of a keyframe file in the schema of ``manual-keyframes.json`` (reference facts,
    section e): ``{"frame_rate_hz": 30, "classes": {name: [{"set", "values", "position",
    "stiffness_to_next"[, "mismatches"]}, ...]}, "template_length": {name: int}}`` (other top-level
    fields are ignored; ``mismatches``, ours, defaults to 0: see :class:`Keyframe`). Errors
    (:class:`KeyframeError`) name ``source`` and the field."""
    check = Checker(source, KeyframeError)
    root = check.mapping(obj, "", ("classes",), others=True)
    rate = check.positive_number(root.get("frame_rate_hz", 30), "frame_rate_hz")
    classes = check.mapping(root["classes"], "classes", others=True)
    if not classes:
        check.fail("classes", "must name at least one class")
    lengths = check.mapping(root.get("template_length", {}), "template_length", others=True)
    out = {}
    for name, items in classes.items():
        length = lengths.get(name)
        if length is not None:
            length = check.integer(length, f"template_length.{name}", minimum=1)
        out[name] = parse_keyframes(items, check, f"classes.{name}", name, rate, length)
    return out


def parse_keyframes(
    items: object, check: Checker, field: str, name: str, rate: float, template_length: int | None = None
) -> KeyframeQuery:
    """One class's list of keyframe entries (``field`` of the file ``check`` reads) as a query."""
    keyframes: list[Keyframe] = []
    entries = check.listing(items, field, nonempty=True)
    for k, item in enumerate(entries):
        here = f"{field}[{k}]"
        last = k == len(entries) - 1
        entry = check.mapping(item, here, ("set", "values", "position"), ("stiffness_to_next", "mismatches"))
        fs: FeatureSet = check.choice(entry["set"], f"{here}.set", FEATURE_SETS)  # type: ignore[assignment]
        n = SET_SLICES[fs].stop - SET_SLICES[fs].start
        values = check.listing(entry["values"], f"{here}.values")
        if len(values) != n:
            check.fail(f"{here}.values", f"must be a list of {n} entries for the {fs} set, got {len(values)}")
        for i, v in enumerate(values):
            if isinstance(v, bool) or v not in (0, 1, 0.5):
                check.fail(f"{here}.values[{i}]", f"must be 0, 1 or 0.5, got {v!r:.60}")
        position = check.integer(entry["position"], f"{here}.position", minimum=None)
        if keyframes and position < keyframes[-1].position:
            check.fail(f"{here}.position", f"{position} is before the previous keyframe's")
        stiffness = entry.get("stiffness_to_next")
        if last:
            if stiffness is not None:
                check.fail(f"{here}.stiffness_to_next", f"the last keyframe has none, got {stiffness!r:.60}")
        else:
            stiffness = check.number(stiffness, f"{here}.stiffness_to_next", low=0, high=1)
        fixed = sum(v != 0.5 for v in values)
        mismatches = entry.get("mismatches", 0)
        if number_reason(mismatches, low=0, high=max(0, fixed - 1), integer=True) is not None:
            check.fail(
                f"{here}.mismatches",
                f"must be an integer in [0, {max(0, fixed - 1)}] (fewer than the keyframe's {fixed} fixed "
                f"entries), got {mismatches!r:.60}",
            )
        keyframes.append(Keyframe(fs, tuple(float(v) for v in values), position, stiffness, mismatches))
    return KeyframeQuery(name, tuple(keyframes), float(rate), template_length)


def omega_z(ranges: Sequence[tuple[int, int]]) -> list[tuple[int, int]]:
    """Ω^Z (Def. 4.8): the ranges sorted, each connected component (ranges sharing a frame with an
    earlier one of the component, Def. 4.7) mapped to (its first start, its largest end)."""
    out: list[tuple[int, int]] = []
    for s, t in sorted(ranges):
        if out and s <= out[-1][1]:
            out[-1] = (out[-1][0], max(out[-1][1], t))
        else:
            out.append((s, t))
    return out
