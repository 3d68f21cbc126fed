"""The keyframe search of thesis ch. 4 run on a stream, one index-rate frame at a time.

:class:`KeyframeAutomaton` is the streaming twin of :func:`daemon.search.keyframes.keyframe_search` over one
document: pushed the frames of a recording, then flushed, it emits exactly the Ω^Z components
(Def. 4.7/4.8) the batch search returns for that recording, each as soon as no later frame can change
it.

How. Keyframe k's list Λ_k (post-segmented, section 4.2.4) is the maximal runs of frames whose code
lies in V_k (for a tolerant keyframe, within its ``mismatches`` of it on the fixed bits); the run
containing the newest frame is *open* (its end is not known yet). A *partial match* is a tuple of
runs (r_1, ..., r_k) that Alg. 4.1/4.2 would extend: each r_j meets the window
[lo_{j-1} + dmin, hi_{j-1} + dmax] its predecessor allows (the ``allowedRange`` of Alg. 4.2), with
lo_j = max(s_j, lo_{j-1} + dmin) and hi_j = min(e_j, hi_{j-1} + dmax). The automaton links a run to a
partial match at the first frame of the run inside the partial match's window — which is the frame
being pushed, so lo_j is that frame — and a partial match of all K keyframes is a match M. Its
hit-relevant range R(M) (Def. 4.6) is (first, hi_K) with first = max_j (lo_j - Σ_{i<j} dmax_i), the
closed form of the backward pass of :func:`daemon.search.keyframes.match_ranges`; an open run's end is the
newest frame, which is also R's end for as long as it can still grow.

When. After frame t, a partial match of keyframes 1..k can only be completed through frames after t,
so any range it yields starts at or after max(first_k, t + 1 - Σ_{i≤k} dmax_i); a match whose end is
the newest frame may still grow. The components of the matches found so far that end before every
such lower bound are final: no later frame can add a range that touches them. Hence the latency
bound: a component ending at frame e is emitted when frame e + max(1, Σ dmax) has been pushed, or
earlier (:attr:`KeyframeAutomaton.latency`). A partial match whose window can no longer reach a future
frame is dropped, so the state is bounded by the query's span, never by the stream's length; for that
every gap needs an upper bound, so gaps with stiffness 0 (unbounded, Def. 4.9) are capped at
``max_gap`` frames, and the batch search is given the same cap (``keyframe_search(max_gap=...)``) to
stay comparable.

Matches. Each push also reports, in :attr:`KeyframeAutomaton.reached`, every match completed at the
pushed frame (its R(M) start and the first frame of its last keyframe) and, with a ``period``, every
match whose range still grows ``period``, ``2 period``, ... frames later; the live recogniser starts
its DTW confirmation from these and runs the automaton with ``components=False`` (no Ω^Z
bookkeeping; a match is dropped once its range can no longer grow).

Pure: integers in, frozen dataclasses out. The frame step is compiled (``daemon/_automaton.pyx``): the
same operations on typed runs and partial matches.
"""

from __future__ import annotations

from dataclasses import dataclass

from daemon._automaton import AutomatonCore
from daemon.features import SET_SLICES
from daemon.keyframes import KeyframeQuery, query_bounds

_OPEN = -1


@dataclass(frozen=True)
class Component:
    """An Ω^Z component: index-rate frames ``start``..``end`` (inclusive, counted from the stream's
    first frame), emitted after frame ``emitted_at`` was pushed (the stream's last frame for those a
    flush emits)."""

    start: int
    end: int
    emitted_at: int


class KeyframeAutomaton:
    """Ω^Z components of ``query`` over a stream of index-rate frames at ``rate`` Hz.

    ``push(code)`` takes one frame's 39 features as a code (bit i = feature i, the lower, upper and
    mix sets side by side as in :func:`daemon.search.retrieval.frame_codes`) and returns the components that
    became final; ``flush()`` ends the stream, returns the rest and starts a new stream (frames
    counted from 0 again). ``max_gap``: the cap of unbounded gaps in frames (required when the
    query has one). The frame step runs in compiled code (:class:`daemon._automaton.AutomatonCore`,
    :attr:`core`), which the live recogniser drives directly."""

    def __init__(
        self,
        query: KeyframeQuery,
        rate: float,
        max_gap: int | None = None,
        period: int = 0,
        components: bool = True,
    ) -> None:
        bounds = query_bounds(query, rate, max_gap)
        if any(hi is None for _, hi in bounds):
            raise ValueError(f"{query.name}: a gap with stiffness 0 needs a maximum gap to be searched live")
        if period < 0:
            raise ValueError(f"the period must not be negative, got {period}")
        dmax = [hi for _, hi in bounds if hi is not None]
        self.query = query
        self.latency = max(1, sum(dmax))
        """A component ending at frame e is emitted no later than after frame e + latency."""
        self.period = period
        self.components = components
        """Whether Ω^Z components are emitted; without, only :attr:`reached` (and a match is dropped
        as soon as its range can no longer grow)."""
        self.core = AutomatonCore(
            [kf.mask << SET_SLICES[kf.feature_set].start for kf in query.keyframes],
            [kf.value << SET_SLICES[kf.feature_set].start for kf in query.keyframes],
            [lo for lo, _ in bounds],
            dmax,
            period,
            components,
            [kf.mismatches for kf in query.keyframes],
        )

    @property
    def reached(self) -> list[tuple[int, int]]:
        """(start of R(M), first frame of keyframe K) of every match whose range reaches the frame
        just pushed, t, at t = that first frame + k·period: the match completed (k = 0) or, with a
        ``period``, its last keyframe still holds k periods later (its range still grows)."""
        return self.core.reached

    @property
    def state_size(self) -> int:
        """Partial matches and matches held (the state apart from one open run per keyframe)."""
        return self.core.state_size

    def push(self, code: int) -> list[Component]:
        t = self.core.frames
        return [Component(s, e, t) for s, e in self.core.push(code)]

    def flush(self) -> list[Component]:
        t = self.core.frames - 1
        return [Component(s, e, t) for s, e in self.core.flush()]
