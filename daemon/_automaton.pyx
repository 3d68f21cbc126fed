# cython: language_level=3, boundscheck=False, wraparound=False, initializedcheck=False, cdivision=True
"""The keyframe automaton's frame step in compiled code: the algorithm of daemon/automaton.py (its
docstring explains it), the same operations in the same order, on typed runs and partial matches."""

from libc.stdint cimport int64_t, uint64_t

from daemon.keyframes import omega_z

cdef extern from *:
    int popcount "__builtin_popcountll"(unsigned long long) nogil

cdef int64_t OPEN = -1
cdef int64_t UNBOUNDED = (<int64_t>1) << 60  # "no bound yet": above every frame, never overflows


cdef class Run:
    """A maximal run of frames in one keyframe's set; ``end`` is OPEN while it lasts."""

    cdef public int64_t start
    cdef public int64_t end

    def __cinit__(self, int64_t start):
        self.start = start
        self.end = OPEN


cdef class Partial:
    """Runs of keyframes 1..k, ``lo`` = lo_k, ``first`` = the lower bound of R's start so far, and
    the last run of keyframe k + 1 linked to it."""

    cdef public tuple runs
    cdef public int64_t lo
    cdef public int64_t first
    cdef public object linked

    def __cinit__(self, tuple runs, int64_t lo, int64_t first):
        self.runs = runs
        self.lo = lo
        self.first = first
        self.linked = None


cdef class AutomatonCore:
    """Keyframes as (mask, value) pairs over the frame code, gap bounds ``dmin``/``dmax`` (every gap
    bounded), ``period`` and ``components`` as :class:`daemon.automaton.KeyframeAutomaton` takes
    them; ``mismatches`` (None: all 0) how many fixed bits of each keyframe a code may miss, so a
    code is in keyframe k's set when popcount((code ^ value) & mask) <= mismatches[k] (for 0: when
    code & mask == value). ``push(code)`` returns the Ω^Z components that became final as (start,
    end) pairs and sets :attr:`reached`; ``flush()`` returns the rest and resets."""

    cdef uint64_t[8] _masks
    cdef uint64_t[8] _values
    cdef int[8] _mismatches
    cdef int64_t[8] _dmin
    cdef int64_t[8] _dmax
    cdef int64_t[8] _reach
    cdef int _k
    cdef public int64_t period
    cdef public bint components
    cdef public list reached
    cdef int64_t _t
    cdef list _open
    cdef list _partials
    cdef list _matches
    cdef bint _idle
    cdef Partial _hit  # the match completed last (what progress reports as a whole hit)
    cdef int64_t _hit_t

    def __init__(self, masks, values, dmin, dmax, int64_t period, bint components, mismatches=None):
        cdef int k
        self._k = len(masks)
        if mismatches is None:
            mismatches = [0] * self._k
        if (
            not 1 <= self._k <= 8 or len(values) != self._k or len(mismatches) != self._k
            or len(dmin) != self._k - 1 or len(dmax) != self._k - 1
        ):
            raise ValueError(
                "1 to 8 keyframes, each with a mask, a value and a number of mismatches, and bounds for every gap"
            )
        for k in range(self._k):
            if values[k] & ~masks[k] or not 0 <= mismatches[k] < max(1, int(masks[k]).bit_count()):
                raise ValueError(
                    f"keyframe {k}: the value must lie within the mask and fewer bits may be missed than the "
                    f"mask fixes (0 if none), got mask {masks[k]:#x}, value {values[k]:#x}, mismatches {mismatches[k]}"
                )
            self._masks[k] = masks[k]
            self._values[k] = values[k]
            self._mismatches[k] = mismatches[k]
        self._reach[0] = 0
        for k in range(self._k - 1):
            self._dmin[k] = dmin[k]
            self._dmax[k] = dmax[k]
            self._reach[k + 1] = self._reach[k] + dmax[k]
        self.period = period
        self.components = components
        self.reset()

    def reset(self):
        self.reached = []
        self._t = 0
        self._open = [None] * self._k
        self._partials = [[] for _ in range(self._k - 1)]
        self._matches = []
        self._idle = True
        self._hit = None
        self._hit_t = -1

    @property
    def state_size(self):
        return sum(len(p) for p in self._partials) + len(self._matches)

    def state(self):
        """What :meth:`restore` needs to go on as this automaton would: (frames, idle, reached, the
        open runs, the partial matches of each gap, the matches, the last hit and its frame, the
        runs). Runs are shared (a partial match links the open run it was extended by, and later
        matches hold the same runs), so they are one list, ``(start, end)`` each, and everything
        else names them by their place in it (-1: none); a partial match is (runs, lo, first,
        linked)."""
        cdef dict places = {}
        cdef list runs = []

        def place(run):
            if run is None:
                return -1
            key = id(run)
            if key not in places:
                places[key] = len(runs)
                runs.append(((<Run> run).start, (<Run> run).end))
            return places[key]

        def partial(p):
            if p is None:
                return None
            cdef Partial q = <Partial> p
            return ([place(r) for r in q.runs], q.lo, q.first, place(q.linked))

        open_ = [place(r) for r in self._open]
        partials = [[partial(p) for p in ps] for ps in self._partials]
        matches = [partial(m) for m in self._matches]
        hit = partial(self._hit)
        return (self._t, self._idle, [list(r) for r in self.reached], open_, partials, matches, hit, self._hit_t, runs)

    def restore(self, state):
        """Take over a :meth:`state` of an automaton of the same keyframes; ValueError if it does
        not fit."""
        t, idle, reached, open_, partials, matches, hit, hit_t, runs = state
        if len(open_) != self._k or len(partials) != self._k - 1:
            raise ValueError(f"automaton: {self._k} keyframes expected, got {len(open_)}")
        made = []
        cdef Run r
        for start, end in runs:
            r = Run(start)
            r.end = end
            made.append(r)

        def run(i):
            if i == -1:
                return None
            if not 0 <= i < len(made):
                raise ValueError(f"automaton: run {i} of {len(made)}")
            return made[i]

        def partial(p):
            if p is None:
                return None
            members, lo, first, linked = p
            q = Partial(tuple(run(i) for i in members), lo, first)
            q.linked = run(linked)
            return q

        self._t = t
        self._idle = idle
        self.reached = [tuple(x) for x in reached]
        self._open = [run(i) for i in open_]
        self._partials = [[partial(p) for p in ps] for ps in partials]
        self._matches = [partial(m) for m in matches]
        self._hit = partial(hit)
        self._hit_t = hit_t

    @property
    def frames(self):
        return self._t

    cpdef list push(self, uint64_t code):
        cdef int64_t t = self._t
        cdef int k, last = self._k - 1, gap
        cdef Run run
        cdef Partial p, m
        cdef int64_t lo, dmin, dmax
        cdef bint hit = False
        self._t += 1
        if self._idle:
            for k in range(self._k):
                if self._in_set(code, k):
                    hit = True
                    break
            if not hit:
                if self.reached:
                    self.reached = []
                return []  # nothing held and no keyframe here: nothing can change
        self.reached = []
        for k in range(self._k):
            run = self._open[k]
            if not self._in_set(code, k):
                if run is not None:
                    run.end = t - 1
                    self._open[k] = None
                continue
            if run is None:
                run = Run(t)
                self._open[k] = run
            if k == 0:
                if run.start == t:
                    self._add(Partial((run,), t, t), 0, last)
                continue
            gap = k - 1
            dmin = self._dmin[gap]
            dmax = self._dmax[gap]
            for p in self._partials[gap]:
                if p.linked is run or t < p.lo + dmin or t > self._hi(p.runs, t) + dmax:
                    continue
                p.linked = run
                lo = max(run.start, p.lo + dmin)
                self._add(Partial(p.runs + (run,), lo, max(p.first, lo - self._reach[k])), k, last)
        if self.period:
            for m in self._matches:
                if t > m.lo and (t - m.lo) % self.period == 0 and self._hi(m.runs, t) == t:
                    self.reached.append((m.first, m.lo))
        self._expire(t)
        cdef list out
        if self.components:
            out = self._emit(t)
        else:
            out = []
            if self._matches:
                self._matches = [m for m in self._matches if self._max_hi(m.runs) > t]
        self._idle = not self._matches and not any(self._partials) and self._closed()
        return out

    cdef inline bint _in_set(self, uint64_t code, int k):
        return popcount((code ^ self._values[k]) & self._masks[k]) <= self._mismatches[k]

    cdef bint _closed(self):
        for r in self._open:
            if r is not None:
                return False
        return True

    def flush(self):
        cdef int64_t t = self._t - 1
        cdef Run run
        cdef Partial m
        for run in self._open:
            if run is not None:
                run.end = t
        ranges = [(m.first, self._hi(m.runs, t)) for m in self._matches] if self.components else []
        self.reset()
        return omega_z(ranges)

    cdef void _add(self, Partial partial, int k, int last):
        if k == last:
            self._matches.append(partial)
            self.reached.append((partial.first, partial.lo))
            self._hit = partial
            self._hit_t = self._t - 1
        else:
            self._partials[k].append(partial)

    cdef tuple _found(self, Partial p):
        """The frames at which keyframes 1..k of ``p`` were found (linked): lo_1 = the first run's
        start, lo_j = max(s_j, lo_{j-1} + dmin_{j-1})."""
        cdef Run run = p.runs[0]
        cdef int64_t lo = run.start
        cdef Py_ssize_t j
        out = [lo]
        for j in range(1, len(p.runs)):
            run = p.runs[j]
            lo = max(run.start, lo + self._dmin[j - 1])
            out.append(lo)
        return tuple(out)

    def partial(self):
        """The frames at which keyframes 1..k were found of the most advanced partial match held
        (k < K keyframes: the most, then the one found first; a whole match is not a partial
        one), ascending; () if none is held."""
        cdef int k
        for k in range(self._k - 2, -1, -1):
            if self._partials[k]:
                return self._found(<Partial> self._partials[k][0])
        return ()

    def hit(self):
        """(frame pushed when it completed, start of R(M), first frame of keyframe K, the frames of
        keyframes 1..K) of the match completed last since the stream began, or None."""
        if self._hit is None:
            return None
        return (self._hit_t, self._hit.first, self._hit.lo, self._found(self._hit))

    cdef int64_t _hi(self, tuple runs, int64_t t):
        """hi_k of the runs at frame ``t`` (an open run ends at ``t`` so far)."""
        cdef Run run = runs[0]
        cdef int64_t hi = t if run.end == OPEN else run.end
        cdef int64_t end
        cdef Py_ssize_t j
        for j in range(1, len(runs)):
            run = runs[j]
            end = t if run.end == OPEN else run.end
            hi = min(end, hi + self._dmax[j - 1])
        return hi

    cdef int64_t _max_hi(self, tuple runs):
        """The largest hi_k the runs can still reach (UNBOUNDED: the first run is open)."""
        cdef Run run = runs[0]
        cdef int64_t hi = UNBOUNDED if run.end == OPEN else run.end
        cdef int64_t cap, end
        cdef Py_ssize_t j
        for j in range(1, len(runs)):
            run = runs[j]
            cap = UNBOUNDED if hi == UNBOUNDED else hi + self._dmax[j - 1]
            end = UNBOUNDED if run.end == OPEN else run.end
            hi = min(end, cap)
        return hi

    cdef void _expire(self, int64_t t):
        cdef int k
        cdef int64_t dmax, reach
        cdef Partial p
        cdef list keep
        for k in range(self._k - 1):
            partials = self._partials[k]
            if not partials:
                continue
            dmax = self._dmax[k]
            keep = []
            for p in partials:
                reach = self._max_hi(p.runs)
                if reach == UNBOUNDED or reach + dmax > t:
                    keep.append(p)
            self._partials[k] = keep

    cdef list _emit(self, int64_t t):
        if not self._matches:
            return []
        cdef int64_t bound = t + 1, floor, start, end, reach
        cdef int k
        cdef Partial p, m
        for k in range(self._k - 1):
            floor = t + 1 - self._reach[k + 1]
            for p in self._partials[k]:
                bound = min(bound, max(p.first, floor))
        ranges = []
        for m in self._matches:
            start = m.first
            end = self._hi(m.runs, t)
            if end == t:
                reach = self._max_hi(m.runs)
                if reach > t:
                    bound = min(bound, start)
            ranges.append((start, end))
        out = []
        for start, end in omega_z(ranges):
            if end >= bound:
                break
            out.append((start, end))
        if out:
            cut = out[len(out) - 1][1]
            self._matches = [m for m, r in zip(self._matches, ranges) if r[0] > cut]
        return out


cdef class AutomatonSet:
    """Several automata (one per class) pushed the same frame code in one call."""

    cdef list _cores
    cdef Py_ssize_t _n

    def __init__(self, cores):
        self._cores = list(cores)
        self._n = len(self._cores)

    def core(self, Py_ssize_t k):
        """Automaton ``k``."""
        return self._cores[k]

    def state(self):
        """Each automaton's :meth:`AutomatonCore.state`."""
        return [(<AutomatonCore> a).state() for a in self._cores]

    def restore(self, state):
        if len(state) != self._n:
            raise ValueError(f"{self._n} automata expected, got {len(state)}")
        for a, s in zip(self._cores, state):
            (<AutomatonCore> a).restore(s)

    def push(self, uint64_t code):
        """Push ``code`` to every automaton; (index, reached) of those whose :attr:`reached` is not
        empty."""
        cdef Py_ssize_t k
        cdef AutomatonCore a
        cdef list out = []
        for k in range(self._n):
            a = <AutomatonCore> self._cores[k]
            a.push(code)
            if a.reached:
                out.append((k, a.reached))
        return out

    def flush(self):
        cdef AutomatonCore a
        for a in self._cores:
            a.flush()
