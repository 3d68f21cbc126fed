"""The keyframe search of thesis ch. 4 run on a stream, one index-rate frame at a time.

:class:`KeyframeAutomaton` is the streaming twin of :func:`daemon.keyframes.keyframe_search` over one
document: pushed the frames of a recording, then flushed, it emits exactly the Ω^Z components
(Def. 4.7/4.8) the batch search returns for that recording, each as soon as no later frame can change
it.

How. Keyframe k's list Λ_k (post-segmented, section 4.2.4) is the maximal runs of frames whose code
lies in V_k; the run containing the newest frame is *open* (its end is not known yet). A *partial
match* is a tuple of runs (r_1, ..., r_k) that Alg. 4.1/4.2 would extend: each r_j meets the window
[lo_{j-1} + dmin, hi_{j-1} + dmax] its predecessor allows (the ``allowedRange`` of Alg. 4.2), with
lo_j = max(s_j, lo_{j-1} + dmin) and hi_j = min(e_j, hi_{j-1} + dmax). The automaton links a run to a
partial match at the first frame of the run inside the partial match's window — which is the frame
being pushed, so lo_j is that frame — and a partial match of all K keyframes is a match M. Its
hit-relevant range R(M) (Def. 4.6) is (first, hi_K) with first = max_j (lo_j - Σ_{i<j} dmax_i), the
closed form of the backward pass of :func:`daemon.keyframes.match_ranges`; an open run's end is the
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

Pure: integers in, frozen dataclasses out.
"""

from __future__ import annotations

from dataclasses import dataclass

from daemon.features import SET_SLICES
from daemon.keyframes import KeyframeQuery, omega_z, query_bounds

_OPEN = -1


@dataclass(frozen=True)
class Component:
    """An Ω^Z component: index-rate frames ``start``..``end`` (inclusive, counted from the stream's
    first frame), emitted after frame ``emitted_at`` was pushed (the stream's last frame for those a
    flush emits)."""

    start: int
    end: int
    emitted_at: int


class _Run:
    """A maximal run of frames in one keyframe's set; ``end`` is ``_OPEN`` while it lasts."""

    __slots__ = ("end", "start")

    def __init__(self, start: int) -> None:
        self.start = start
        self.end = _OPEN


class _Partial:
    """Runs of keyframes 1..k, ``lo`` = lo_k, ``first`` = the lower bound of R's start so far, and
    the last run of keyframe k + 1 linked to it (each run is linked once)."""

    __slots__ = ("first", "linked", "lo", "runs")

    def __init__(self, runs: tuple[_Run, ...], lo: int, first: int) -> None:
        self.runs = runs
        self.lo = lo
        self.first = first
        self.linked: _Run | None = None


def _grows(reach: int | None, t: int) -> bool:
    """Whether something that reaches at most frame ``reach`` (None: no bound yet) can still reach a
    frame after ``t``."""
    return reach is None or reach > t


class KeyframeAutomaton:
    """Ω^Z components of ``query`` over a stream of index-rate frames at ``rate`` Hz.

    ``push(code)`` takes one frame's 39 features as a code (bit i = feature i, the lower, upper and
    mix sets side by side as in :func:`daemon.retrieval.frame_codes`) and returns the components that
    became final; ``flush()`` ends the stream, returns the rest and starts a new stream (frames
    counted from 0 again). ``max_gap``: the cap of unbounded gaps in frames (required when the
    query has one)."""

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
        self.query = query
        self._masks = [kf.mask << SET_SLICES[kf.feature_set].start for kf in query.keyframes]
        self._values = [kf.value << SET_SLICES[kf.feature_set].start for kf in query.keyframes]
        self._dmin = [lo for lo, _ in bounds]
        self._dmax: list[int] = [hi for _, hi in bounds if hi is not None]
        reach = [0]
        for d in self._dmax:
            reach.append(reach[-1] + d)
        self._reach = reach  # Σ_{i<j} dmax_i for j = 0..K-1
        self.latency = max(1, reach[-1])
        """A component ending at frame e is emitted no later than after frame e + latency."""
        if period < 0:
            raise ValueError(f"the period must not be negative, got {period}")
        self.period = period
        self.components = components
        """Whether Ω^Z components are emitted; without, only :attr:`reached` (and a match is dropped
        as soon as its range can no longer grow)."""
        self._reset()

    def _reset(self) -> None:
        self.reached: list[tuple[int, int]] = []
        """(start of R(M), first frame of keyframe K) of every match whose range reaches the frame
        just pushed, t, at t = that first frame + k·period: the match completed (k = 0) or, with a
        ``period``, its last keyframe still holds k periods later (its range still grows)."""
        self._t = 0
        self._open: list[_Run | None] = [None] * len(self._masks)
        self._partials: list[list[_Partial]] = [[] for _ in self._dmax]
        self._matches: list[_Partial] = []
        self._idle = True

    @property
    def state_size(self) -> int:
        """Partial matches and matches held (the state apart from one open run per keyframe)."""
        return sum(len(p) for p in self._partials) + len(self._matches)

    def push(self, code: int) -> list[Component]:
        t = self._t
        self._t += 1
        if self._idle and all(code & m != v for m, v in zip(self._masks, self._values, strict=True)):
            if self.reached:
                self.reached = []
            return []  # nothing held and no keyframe here: nothing can change
        self.reached = []
        last = len(self._masks) - 1
        for k, (mask, value) in enumerate(zip(self._masks, self._values, strict=True)):
            run = self._open[k]
            if code & mask != value:
                if run is not None:
                    run.end = t - 1
                    self._open[k] = None
                continue
            if run is None:
                run = self._open[k] = _Run(t)
            if k == 0:
                if run.start == t:
                    self._add(_Partial((run,), t, t), 0, last)
                continue
            gap = k - 1
            dmin, dmax = self._dmin[gap], self._dmax[gap]
            for p in self._partials[gap]:
                if p.linked is run or t < p.lo + dmin or t > self._hi(p.runs, t) + dmax:
                    continue
                p.linked = run
                lo = max(run.start, p.lo + dmin)
                self._add(_Partial((*p.runs, run), lo, max(p.first, lo - self._reach[k])), k, last)
        if self.period:
            for m in self._matches:
                if t > m.lo and (t - m.lo) % self.period == 0 and self._hi(m.runs, t) == t:
                    self.reached.append((m.first, m.lo))
        self._expire(t)
        if self.components:
            out = self._emit(t)
        else:
            out = []
            if self._matches:
                self._matches = [m for m in self._matches if _grows(self._max_hi(m.runs), t)]
        self._idle = not self._matches and not any(self._partials) and all(r is None for r in self._open)
        return out

    def flush(self) -> list[Component]:
        t = self._t - 1
        for run in self._open:
            if run is not None:
                run.end = t
        ranges = [self._range(m, t) for m in self._matches] if self.components else []
        self._reset()
        return [Component(s, e, t) for s, e in omega_z(ranges)]

    def _add(self, partial: _Partial, k: int, last: int) -> None:
        if k == last:
            self._matches.append(partial)
            self.reached.append((partial.first, partial.lo))
        else:
            self._partials[k].append(partial)

    def _hi(self, runs: tuple[_Run, ...], t: int) -> int:
        """hi_k of the runs at frame ``t`` (an open run ends at ``t`` so far)."""
        hi = t if runs[0].end == _OPEN else runs[0].end
        for run, dmax in zip(runs[1:], self._dmax, strict=False):
            hi = min(t if run.end == _OPEN else run.end, hi + dmax)
        return hi

    def _max_hi(self, runs: tuple[_Run, ...]) -> int | None:
        """The largest hi_k the runs can still reach (None: unbounded, the first run is open)."""
        hi = None if runs[0].end == _OPEN else runs[0].end
        for run, dmax in zip(runs[1:], self._dmax, strict=False):
            cap = None if hi is None else hi + dmax
            end = None if run.end == _OPEN else run.end
            hi = cap if end is None else end if cap is None else min(end, cap)
        return hi

    def _range(self, match: _Partial, t: int) -> tuple[int, int]:
        return match.first, self._hi(match.runs, t)

    def _expire(self, t: int) -> None:
        for k, partials in enumerate(self._partials):
            dmax = self._dmax[k]
            keep = []
            for p in partials:
                reach = self._max_hi(p.runs)
                if _grows(None if reach is None else reach + dmax, t):
                    keep.append(p)
            self._partials[k] = keep

    def _emit(self, t: int) -> list[Component]:
        if not self._matches:
            return []
        bound = t + 1
        for k, partials in enumerate(self._partials):
            floor = t + 1 - self._reach[k + 1]
            for p in partials:
                bound = min(bound, max(p.first, floor))
        ranges = []
        for m in self._matches:
            start, end = self._range(m, t)
            if end == t:
                reach = self._max_hi(m.runs)
                if reach is None or reach > t:
                    bound = min(bound, start)
            ranges.append((start, end))
        out: list[Component] = []
        for start, end in omega_z(ranges):
            if end >= bound:
                break
            out.append(Component(start, end, t))
        if out:
            cut = out[-1].end
            self._matches = [m for m, r in zip(self._matches, ranges, strict=True) if r[0] > cut]
        return out
