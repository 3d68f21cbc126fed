"""The live recogniser: poses of one stream in, detections out, one frame at a time.

Per frame (DESIGN.md, the data flow): every k-th frame is kept for the library's rate (30 Hz from
120 Hz; the others are counted and left); a kept frame's AMC-style channels go through forward
kinematics (or joint positions arrive as they are), :class:`~daemon.features.FeatureStream` at the
library's rate gives the 39 features of the kept poses (:func:`daemon.features.sampled_features`:
the same bits at any native rate the library's divides), and the frame's code (bit i = feature i)
goes to :class:`CodeRecognizer`. Keyframes first: a class in mode ``keyframes`` advances
its keyframe automaton (:class:`~daemon.automaton.KeyframeAutomaton`, thesis Alg. 4.1 on the runs of
equal codes, with stiffness windows); a completed match opens a window around its range R(M)
(:func:`window_extent`), and the class's templates run a subsequence DTW (thesis Alg. 3.2 with free
start; the retrieval cost and steps of :func:`daemon.search.retrieval.template_search`) over that
window only, its local minima within τ the class's candidates. A class in mode ``dtw`` runs its DTW
over the whole stream. A candidate beaten by a cheaper one of the same motion (:func:`same_motion`)
is dropped, and one that is not is held until no open template can still end a cheaper match of its
motion (or ``hold_s``), then published. Published detections are never taken back.

Latency. A detection comes out one index frame after its last frame (the frame that shows Δ's
minimum) once the features' delay (5 index frames, 20 frames at 120 Hz) has passed, or later while
it is held: at most :attr:`Recognizer.latency_frames` native frames after its last frame.

Bounded state. The features keep 10 poses at 30 Hz, each automaton the query's span, the DTW
three columns per template and the codes of the longest window's look-back, and the candidates of
the last :func:`reach` frames.

One live path. :class:`Recognizer` is the one per-stream engine: its state is compiled (a
:class:`~daemon._live.LiveStream`: forward kinematics, features, decimation; its
:class:`ClassStage`'s :class:`CodeRecognizer`, whose work is a :class:`~daemon._dtw.Competition`),
its Python the checks of an unusual frame, the refusals and the detections' ids and frame numbers
(:class:`ClassStage` with the stream's :class:`~daemon.frames.FrameClock`).
:meth:`Recognizer.push_many` advances any number of recognisers by one frame each in one compiled
call (:func:`daemon._live.push_many`: the frames stepped in passes over all of them, forward
kinematics and the feature program by blocks of streams, each step over the block); a frame's
operations are the same whatever block it is in. :meth:`Recognizer.push` is that call for one
frame, :meth:`daemon.bank.RecognizerBank.push` that of its streams' frames. The settings shared by
every stream are one :class:`~daemon.types.RecognitionSettings`. :func:`detect` is the batch twin:
the features of the whole recording in one vectorised pass, then the same class stage and clock; it
equals pushing the frames one by one (tests).
"""

from __future__ import annotations

import hashlib
import uuid
import weakref
import zlib
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from itertools import accumulate
from typing import Any, Literal

import msgpack
import numpy as np
import numpy.typing as npt

from daemon._automaton import AutomatonSet
from daemon._dtw import Competition, StreamDTW
from daemon._live import NON_FINITE, LiveStream, push_many
from daemon.automaton import KeyframeAutomaton
from daemon.dtw import SCALE, Match, RetrievalTables, Steps, pack, retrieval_tables, threshold
from daemon.errors import InputError, MocapdError
from daemon.features import FeatureStream, sampled_features
from daemon.frames import FrameClock, bridge_frames, bridged_runs, check_native_rate, motion_runs
from daemon.keyframes import KeyframeQuery, query_bounds
from daemon.library import GATED, ClassTemplate, Library
from daemon.templates import expand
from daemon.types import DEFAULT_BRIDGE_S, FloatArray, IntArray, RecognitionSettings
from replay import JOINT_NAMES, KinematicModel, Motion, Skeleton
from replay.kinematics import joint_positions

DEFAULT_SETTINGS = RecognitionSettings()
"""``config.yaml``'s defaults, all classes."""

FrameProblem = Literal["shape", "non_finite", "type", "repeat", "back", "jump"]


STATE_VERSION = 2
"""The form of :meth:`Recognizer.state`; a state of another is refused."""


class StateError(MocapdError, ValueError):
    """A recogniser's state (:meth:`Recognizer.state`) that this recogniser cannot go on from."""


class FrameError(MocapdError, ValueError):
    """A frame the recogniser refuses, with ``problem`` (``shape``: wrong joint or channel count;
    ``non_finite``: NaN or inf, also after forward kinematics; ``type``: a frame number that is not
    an integer; ``repeat``, ``back``, ``jump``: a frame number equal to, before, or more than one
    after the previous one). The stream's state is unchanged: the next good frame goes on."""

    def __init__(self, reason: str, problem: FrameProblem, *, stream: str = "") -> None:
        super().__init__(reason, field=f"stream {stream!r}" if stream else "")
        self.problem = problem


@dataclass(frozen=True)
class Detection:
    """A confirmed motion: ``class_name`` performed over the source's frames ``start_frame`` ..
    ``end_frame`` (its own frame numbers at its native rate), DTW ``cost`` at or below the class's
    ``tau``, emitted when frame ``emitted_at_frame`` was pushed (the stream's last frame for those a
    flush emits). ``id`` is unique: a hash of the recogniser's session, the stream, the class and
    the range."""

    id: str
    stream: str
    class_name: str
    start_frame: int
    end_frame: int
    cost: float
    tau: float
    emitted_at_frame: int

    def as_json(self) -> dict[str, Any]:
        """The fields as a JSON object (``class`` for ``class_name``)."""
        return {
            "id": self.id,
            "stream": self.stream,
            "class": self.class_name,
            "start_frame": self.start_frame,
            "end_frame": self.end_frame,
            "cost": self.cost,
            "tau": self.tau,
            "emitted_at_frame": self.emitted_at_frame,
        }


@dataclass(frozen=True)
class MemberPlan:
    """One template of a class, prepared: the expanded quantised template (``values`` shape
    ``(39, M)``, ``weights`` ``(M,)``), its cost ``tables`` and its τ."""

    values: FloatArray
    weights: FloatArray
    tables: RetrievalTables
    tau: float

    @property
    def length(self) -> int:
        return int(self.weights.shape[0])


@dataclass(frozen=True)
class ClassPlan:
    """What a stream needs of one class, at the library's rate: its templates (``members``, the
    class's own first), whether its keyframes propose its windows (``gated``: keyframes first) and
    the keyframe query's gap cap in frames."""

    template: ClassTemplate
    members: tuple[MemberPlan, ...]
    gated: bool
    max_gap: int

    @property
    def name(self) -> str:
        return self.template.name

    @property
    def tau(self) -> float:
        return self.template.tau

    @property
    def steps(self) -> Steps:
        return self.template.steps

    def automaton(self, rate: float) -> KeyframeAutomaton:
        """The class's keyframe automaton reporting every match at the frame that completes it."""
        assert self.template.keyframes is not None
        return gate_automaton(self.template.keyframes, rate, self.max_gap)

    def extent(self) -> tuple[int, int]:
        """(before, after): the frames a window of the class opens before a keyframe match's range
        and stays open after the frame that completes it (:func:`window_extent`)."""
        t = self.template
        assert t.keyframes is not None
        return window_extent(t.keyframes, t.hard.length, t.slack, t.extent)

    def back(self, rate: float) -> int:
        """How far before the frame that completes a match its window may open: the match's span
        (the gaps' upper bounds) and :meth:`extent`'s before."""
        assert self.template.keyframes is not None
        return look_back(self.template.keyframes, rate, self.max_gap, self.extent()[0])


def look_back(query: KeyframeQuery, rate: float, max_gap: int, before: int) -> int:
    """How far before the frame that completes a match of ``query`` its window may open: the
    match's span (the gaps' upper bounds, unbounded ones capped at ``max_gap``) and ``before``."""
    return sum(hi or 0 for _, hi in query_bounds(query, rate, max_gap)) + before


def window_extent(
    query: KeyframeQuery, length: int, slack: int, extent: tuple[int, int] | None = None
) -> tuple[int, int]:
    """(before, after) of a keyframe-first class's windows, in frames: the ``extent`` its training
    examples need (:func:`learned_extent`), or without one, the template's geometry — its first
    keyframe at template column p_1 and its last at p_K of ``length`` columns, and a DTW path with
    the toolbox's steps taking at most two frames per column, the motion starts at most 2 p_1
    frames before its first keyframe's frame and ends at most 2 (length - 1 - p_K) after its last
    keyframe's; ``slack`` frames more on each side (learned by folds,
    :func:`daemon.learn.calibration.choose_gate`)."""
    if extent is not None:
        return extent[0] + slack, extent[1] + slack
    first, last = query.keyframes[0].position, query.keyframes[-1].position
    return 2 * max(0, first) + slack, 2 * max(0, length - 1 - last) + slack


def learned_extent(
    query: KeyframeQuery, examples: Sequence[Sequence[int]], rate: float, max_gap: int
) -> tuple[int, int] | None:
    """The spread of the training examples' timings around their keyframe matches: over the
    examples (each its index-rate codes) in which ``query`` completes a match, the most frames from
    the example's first frame to the R(M) start of its first completed match (before) and from the
    frame that completes it to the example's last frame (after), so that the window of that match
    (:func:`windows`) holds the whole example; None if no example has a match."""
    before = after = -1
    for codes in examples:
        found = completions(query, rate, max_gap, codes)
        if found:
            first, j = min(found, key=lambda m: (m[1], m[0]))
            before, after = max(before, first), max(after, len(codes) - 1 - j)
    return None if before < 0 else (before, after)


def gate_automaton(query: KeyframeQuery, rate: float, max_gap: int) -> KeyframeAutomaton:
    """The automaton of a keyframe-first class: every match reported at the frame that completes
    it, with the start of its hit-relevant range R(M) (period 0, no Ω^Z components)."""
    return KeyframeAutomaton(query, rate, max_gap, 0, components=False)


def completions(
    query: KeyframeQuery, rate: float, max_gap: int, codes: Sequence[int]
) -> list[tuple[int, int]]:
    """(start of R(M), frame) of every keyframe match of ``query`` over index-rate ``codes``, at the
    frame that completes it, in order."""
    automaton = gate_automaton(query, rate, max_gap)
    out = []
    for j, code in enumerate(codes):
        automaton.push(code)
        out += [(first, j) for first, _ in automaton.reached]
    return out


def windows(
    found: Sequence[tuple[int, int]], before: int, after: int, back: int
) -> list[tuple[int, int, int, int]]:
    """The windows a keyframe-first class opens for matches ``found`` ((start of R(M), frame that
    completes it), in order of frame): (first frame, last frame, frame it opened at, the first frame
    its candidates may end at). The matches completed at frame j ask for frames
    max(min first - ``before``, j - ``back``, 0) .. j + ``after``; while the class's window is open
    (its last frame is j - 1 or later) that extends its end, else a new window opens there: the DTW
    runs over it from its first frame (so its minima up to frame j - 1 are found at j), and its
    candidates end after the last window's frames, which were searched already."""
    out: list[list[int]] = []
    by_frame: dict[int, int] = {}
    for first, j in found:
        a = max(first - before, j - back, 0)
        by_frame[j] = min(by_frame.get(j, a), a)
    for j, a in sorted(by_frame.items()):
        b = j + after
        if out and out[-1][1] >= j - 1:
            out[-1][1] = max(out[-1][1], b)
        else:
            out.append([a, b, j, max(a, out[-1][1] + 1) if out else a])
    return [(s, e, at, lowest) for s, e, at, lowest in out]


def keyframe_windows(
    query: KeyframeQuery,
    extent: tuple[int, int],
    rate: float,
    max_gap: int,
    found: Sequence[tuple[int, int]],
) -> list[tuple[int, int, int, int]]:
    """The :func:`windows` a keyframe-first class with ``query`` and windows of ``extent`` (before,
    after: :func:`window_extent`) opens over index-rate codes whose keyframe matches are ``found``
    (their :func:`completions`), as the live recogniser opens them."""
    before, after = extent
    return windows(found, before, after, look_back(query, rate, max_gap, before))


_PLANS: dict[
    tuple[int, tuple[str, ...] | None, float, str], tuple[weakref.ref[Library], tuple[ClassPlan, ...]]
]
_PLANS = {}


def plans(library: Library, settings: RecognitionSettings = DEFAULT_SETTINGS) -> tuple[ClassPlan, ...]:
    """The plans of the settings' classes (None: all, in the library's order) with their gap cap,
    keyframes first as the settings' ``mode`` says.
    Made once per library object and settings (a stream joining a service costs no template
    preparation)."""
    key = (id(library), settings.classes, float(settings.max_gap_s), settings.mode)
    held = _PLANS.get(key)
    if held is not None and held[0]() is library:
        return held[1]
    names = list(library.classes) if settings.classes is None else list(settings.classes)
    made = _make_plans(library, names, settings.max_gap(library.rate), settings.mode)
    _PLANS[key] = (weakref.ref(library, lambda _: _PLANS.pop(key, None)), made)
    return made


def _make_plans(library: Library, names: Sequence[str], max_gap: int, mode: str) -> tuple[ClassPlan, ...]:
    out = []
    for name in names:
        cls = library.get(name)
        members = []
        for template, tau in cls.members:
            t = expand(template)
            members.append(MemberPlan(t.values, t.weights, retrieval_tables(t.values, t.weights), tau))
        gated = cls.mode == GATED if mode == "library" else mode == GATED and cls.keyframes is not None
        out.append(ClassPlan(cls, tuple(members), gated, max_gap))
    return tuple(out)


def reach(class_plans: Sequence[ClassPlan], hold: int, rate: float = 30.0) -> int:
    """Index-rate frames before the frame that emits it that a detection may start at, at most: a
    match spans at most twice its template's columns (the toolbox's steps; longer matches under the
    thesis' are forgotten as rivals after that long too), or starts in a window that opened at most
    :meth:`ClassPlan.back` frames before the frame that found it; then it is held ``hold`` frames
    after that frame."""
    span = max((2 * m.length for p in class_plans for m in p.members), default=1)
    back = max((p.back(rate) for p in class_plans if p.gated), default=0)
    return max(span, back) + hold + 2


def same_motion(a: tuple[int, int], b: tuple[int, int]) -> bool:
    """Whether two ranges (inclusive) are one motion: they share more than half of the shorter
    one's frames. DTW matches of consecutive repetitions may share a frame or two of the pose
    between them (it fits the end of one template and the start of the next)."""
    shared = min(a[1], b[1]) - max(a[0], b[0]) + 1
    return 2 * shared > min(a[1] - a[0], b[1] - b[0]) + 1


Confirmation = tuple[ClassPlan, Match, float]
"""A detection in index-rate frames: its class, its match and the τ of the template that made it."""


class CodeRecognizer:
    """Detections over a stream of index-rate frame codes: ``push(code)`` returns the confirmations
    it made, ``flush()`` ends the stream. The part of :class:`Recognizer` after the features, shared
    with :func:`detect`.

    The algorithm below runs compiled, in :class:`daemon._dtw.Competition` (:attr:`core`), on C
    arrays; :meth:`push` and :meth:`flush` turn what it confirms into :data:`Confirmation`.

    *Windows (keyframes first).* A class in mode ``keyframes`` runs its keyframe automaton (Alg.
    4.1's matches, :class:`~daemon.automaton.KeyframeAutomaton`: runs of codes in each keyframe's
    set, partial matches held within their stiffness windows) and reports each match at the frame j
    that completes it, with the start of its hit-relevant range R(M). The matches completed at j ask
    for the frames from (the earliest R(M) start) - before to j + after (:meth:`ClassPlan.extent`):
    if the class's window covered frame j - 1, its end moves there; else a new window opens, and the
    class's templates' DTW columns are computed from its first frame up to j - 1 from the codes kept
    (their minima there found at j; those ending in the last window's frames were searched
    already and are skipped). Outside its windows a template's column is empty. A class in mode
    ``dtw`` has one window: the stream (:func:`windows`).

    *Candidates.* Each template runs a subsequence DTW over its windows, one column per frame
    (:class:`daemon._dtw.StreamDTW`; thesis Alg. 3.2 with free start, the retrieval cost and steps of
    :func:`daemon.search.retrieval.template_search`). Each local minimum of its Δ at or below its τ
    (below the frame before, not above the frame after; Δ infinite outside the window) is a
    candidate, known one frame after its end or when its window opens. The candidates of a frame
    arrive in the order (cost, end, template, start).

    *One motion, one detection.* A candidate is beaten by any candidate that arrived before it,
    comes before it in that order and is the :func:`same_motion`: of another class when classes
    ``compete`` (the cheaper template is the better explanation), of its own class always (one
    detection per motion). A candidate that is not beaten is held until no template can still end
    a match that would beat it (:meth:`daemon._dtw.StreamDTW.blocks`: costs only grow along a DTW
    path, so a cell already above its cost cannot; a template outside its windows has no cell), or
    until ``hold`` frames after the frame that found it, whichever comes first; then it is
    published, unless it is the same motion as a detection already published (after the hold ran
    out). Candidates are remembered for :func:`reach` frames."""

    def __init__(
        self, class_plans: Sequence[ClassPlan], rate: float, settings: RecognitionSettings = DEFAULT_SETTINGS
    ) -> None:
        self.plans = tuple(class_plans)
        self.rate = rate
        self.compete = compete = settings.compete
        self.hold = hold = settings.hold(rate)
        self._owner = [k for k, p in enumerate(self.plans) for _ in p.members]
        first = list(accumulate((len(p.members) for p in self.plans), initial=0))
        # the templates a candidate's rivals come from: all, or its own class's
        self._rivals = [(0, len(self._owner)) if compete else (first[k], first[k + 1]) for k in self._owner]
        self._taus = [m.tau for p in self.plans for m in p.members]
        self.taus = tuple(self._taus)
        """Each template's τ, in the order of :attr:`core`'s templates (the plans' members)."""
        self.lengths = tuple(m.length for p in self.plans for m in p.members)
        """Each template's columns, in that order."""
        self.names = tuple(p.name for p in self.plans)
        self.keyframes = tuple(
            len(p.template.keyframes.keyframes) if p.gated and p.template.keyframes else 0 for p in self.plans
        )
        """Each class's keyframes gating it (0: none)."""
        dtw = (
            StreamDTW(
                [
                    (m.tables.masks, m.tables.values, m.tables.tables, threshold(m.tau), p.steps == "toolbox")
                    for p in self.plans
                    for m in p.members
                ]
            )
            if self.plans
            else None
        )
        gated = [k for k, p in enumerate(self.plans) if p.gated]
        automata = AutomatonSet([self.plans[k].automaton(rate).core for k in gated]) if gated else None
        self._core = (
            Competition(
                dtw,
                self._owner,
                [lo for lo, _ in self._rivals],
                [hi for _, hi in self._rivals],
                compete,
                hold,
                reach(self.plans, hold, rate),
                automata,
                gated,
                [self.plans[k].extent()[0] for k in gated],
                [self.plans[k].extent()[1] for k in gated],
                max((self.plans[k].back(rate) for k in gated), default=0),
            )
            if dtw is not None
            else None
        )
        self._n = 0

    @property
    def frames(self) -> int:
        """Index-rate frames pushed since the stream began."""
        return self._n if self._core is None else self._core.n

    @property
    def core(self) -> Competition | None:
        """The compiled competition (None without classes): what :meth:`push` runs."""
        return self._core

    def push(self, code: int) -> list[Confirmation]:
        if self._core is None:
            self._n += 1
            return []
        found = self._core.push(code)
        return self.confirmations(found) if found else []

    def restore_frames(self, frames: int) -> None:
        """Without classes, the one state: the frames pushed (:attr:`frames`)."""
        if type(frames) is not int or frames < 0:
            raise ValueError("frames pushed must be an int >= 0")
        self._n = frames

    def flush(self) -> list[Confirmation]:
        if self._core is None:
            self._n = 0
            return []
        found = self._core.flush()
        return self.confirmations(found) if found else []

    def confirmations(self, found: Sequence[tuple[int, int, int, int, int]]) -> list[Confirmation]:
        """The compiled competition's confirmations (class, start, end, fixed-point cost, template)
        as :data:`Confirmation`."""
        return [(self.plans[k], Match(s, e, cost / SCALE), self._taus[u]) for k, s, e, cost, u in found]


Step = tuple[list[Detection], list[tuple[int, FrameError]]]
"""What :meth:`Recognizer.push_many` gave: the detections, and the refused frames as (position
among the frames pushed, :class:`FrameError`) in order."""


class ClassStage:
    """The live path after the features, for one stream: its index-rate codes in, detections in its
    own frame numbers out. :class:`CodeRecognizer` finds the confirmations; the stream's
    :class:`~daemon.frames.FrameClock` puts them in its frame numbers, and its ``session`` and
    ``stream`` name make each detection's id. One motion at a time: :meth:`start` at its first
    frame, :meth:`push` each code with the frame whose push gave it, :meth:`flush` at its end. Both
    :class:`Recognizer` (codes from its compiled frame step) and :func:`detect` (codes from one
    vectorised pass) go through it."""

    def __init__(
        self,
        class_plans: Sequence[ClassPlan],
        index_rate: float,
        settings: RecognitionSettings,
        clock: FrameClock,
        *,
        stream: str,
        session: str,
    ) -> None:
        self.codes = CodeRecognizer(class_plans, index_rate, settings)
        self.clock = clock
        self.stream = stream
        self.session = session
        self.first: int | None = None
        """The frame number of the motion's first frame (None: no motion under way)."""
        self.watch: Callable[[int], None] | None = None
        """Called with the frame number after each code :meth:`flush` pushes (progress follows the
        codes the end of a motion gives: :class:`daemon.progress.StreamProgress`)."""

    def start(self, first: int) -> None:
        """A motion begins at frame ``first``."""
        self.first = first

    def push(self, number: int, code: int) -> list[Detection]:
        """The motion's next index-rate ``code``, given by the push of frame ``number``: the
        detections it completed."""
        found = self.codes.push(code)
        return [self._detection(c, number) for c in found] if found else []

    def found(self, number: int, found: Sequence[tuple[int, int, int, int, int]]) -> list[Detection]:
        """The detections of what the compiled competition (:attr:`CodeRecognizer.core`) confirmed at
        the push of frame ``number`` (:func:`daemon._live.push_many` pushes to it directly)."""
        return [self._detection(c, number) for c in self.codes.confirmations(found)]

    def flush(self, last: int | None, codes: Sequence[int] = ()) -> list[Detection]:
        """The motion ends at frame ``last`` (None: it had no frame) with its last ``codes``: the
        remaining detections; then no motion is under way."""
        out = []
        for code in codes:
            out += self.push(last or 0, code)
            if self.watch is not None:
                self.watch(last or 0)
        found = self.codes.flush()
        if last is not None:
            out += [self._detection(c, last) for c in found]
        self.first = None
        return out

    def _detection(self, found: Confirmation, number: int) -> Detection:
        """A confirmation (index-rate frames) as a :class:`Detection` in the stream's frame numbers,
        emitted at frame ``number``: :meth:`~daemon.frames.FrameClock.span` of its index frames."""
        plan, m, tau = found
        assert self.first is not None
        start, end = self.clock.span(self.first, m.start, m.end, number)
        key = f"{self.session}/{self.stream}/{plan.name}/{start}/{end}"
        return Detection(
            str(uuid.uuid5(uuid.NAMESPACE_URL, key)), self.stream, plan.name, start, end, m.cost, tau, number
        )


class Recognizer:
    """Detections of the library's classes on one stream, one frame at a time: the live path's one
    per-stream engine (:class:`~daemon.bank.RecognizerBank` holds many, :func:`detect` shares its
    :class:`ClassStage`).

    Make it with :meth:`for_skeleton` (frames are AMC-style channel vectors, shape ``(C,)`` in the
    skeleton's channel order, angles in radians as :mod:`replay` reads them) or
    :meth:`for_positions` (frames are joint positions, shape ``(J, 3)`` in the announced joint order,
    any length unit: the features are scale-free). ``push(number, frame)`` takes the source's frame
    number (consecutive) and returns the detections that were emitted; ``flush()`` ends the stream,
    returns the rest and starts a new stream. Bad frames raise :class:`FrameError` and change
    nothing. ``settings`` are those of every stream; ``stream`` and ``session`` (None: a new one)
    name this one in its detections' ids."""

    def __init__(
        self,
        library: Library,
        native_rate: float,
        *,
        settings: RecognitionSettings = DEFAULT_SETTINGS,
        stream: str = "",
        session: str | None = None,
        model: KinematicModel | None = None,
        joint_names: Sequence[str] | None = None,
    ) -> None:
        self.clock = FrameClock.of(native_rate, library.rate)
        self.stream = stream
        self.library = library
        self.native_rate = native_rate
        self.settings = settings
        self.session = uuid.uuid4().hex if session is None else session
        self.model = model
        self.joint_names = None if model is not None or joint_names is None else tuple(joint_names)
        if model is not None:
            self._width = len(model.skeleton.channel_names)
        else:
            if joint_names is None:
                raise ValueError("give a kinematic model (channels) or the joint names (positions)")
            self._width = len(joint_names)
            self._joint_order = joint_order(joint_names)
        self._plans = plans(library, settings)
        step, per = self.clock.step, self.clock.per
        features = FeatureStream(JOINT_NAMES, native_rate * per / step)  # on the index frames' poses alone
        if model is not None:
            self._shape: tuple[int, ...] = (self._width,)
            self._live = LiveStream(
                model.frame_kinematics, features.core, features.thresholds_of, None, self._width, step, per
            )
        else:
            self._shape = (self._width, 3)
            order = (3 * self._joint_order[:, None] + np.arange(3)).reshape(-1)
            self._live = LiveStream(
                None, features.core, features.thresholds_of, order, 3 * self._width, step, per
            )
        self._stage = ClassStage(
            self._plans, library.rate, settings, self.clock, stream=stream, session=self.session
        )
        self._live.attach(self._stage, self._stage.codes.core)

    def state(self) -> bytes:
        """The stream's whole state, as bytes another worker's recogniser of the same stream and
        input (:meth:`restored`) goes on from, giving the detections, ids included, that this one
        would: the session, the motion's first frame, and the compiled stages' own (the features'
        ring, thresholds (multiples of body lengths measured on the stretch's first pose) and
        hysteresis, the decimation, the DTW columns, the automata's runs and partial matches, the
        candidates held and remembered; daemon/_features.pyx, daemon/_live.pyx, daemon/_dtw.pyx,
        daemon/_automaton.pyx). msgpack, zlib-compressed."""
        core = self._stage.codes.core
        return zlib.compress(
            msgpack.packb(
                {
                    "version": STATE_VERSION,
                    "shape": self._shape_key(),
                    "session": self.session,
                    "first": self._stage.first,
                    "live": self._live.state(),
                    "features": self._live.features.state(),
                    "codes": self._stage.codes.frames if core is None else core.state(),
                }
            ),
            1,
        )

    def restored(self, state: bytes) -> Recognizer:
        """A recogniser of the same stream and input as this one (:meth:`fresh`) in ``state`` (what
        :meth:`state` gave, here or in another process with the same library and settings):
        :class:`StateError` if it is damaged or of another library, settings, rate or input, and
        this recogniser is unchanged either way."""
        try:
            got = msgpack.unpackb(zlib.decompress(state))
        except (zlib.error, ValueError, msgpack.UnpackException) as e:
            raise StateError(f"not a recogniser's state ({e})", field="state") from None
        if not isinstance(got, dict):
            raise StateError("not a recogniser's state", field="state")
        if got.get("version") != STATE_VERSION:
            version = got.get("version")
            raise StateError(f"version {version!r}, expected {STATE_VERSION}", field="state.version")
        if got.get("shape") != self._shape_key():
            raise StateError(
                "of another library, settings, rate or input than this stream's", field="state.shape"
            )
        r = self.fresh(got["session"])
        try:
            r._stage.first = got["first"]
            r._live.restore(got["live"])
            r._live.features.restore(got["features"])
            core = r._stage.codes.core
            if core is None:
                r._stage.codes.restore_frames(got["codes"])
            else:
                core.restore(got["codes"])
        except (KeyError, TypeError, ValueError) as e:
            raise StateError(str(e), field="state") from None
        return r

    def _shape_key(self) -> str:
        """What a state must have been taken under to fit this recogniser: a digest of the input
        (rate, width, shape), the settings, and the classes' plans (names, gating, templates'
        lengths and τ; the library's templates themselves are the cluster's to keep the same)."""
        codes = self._stage.codes
        key = (
            self.native_rate,
            self._shape,
            (self.clock.step, self.clock.per),
            repr(self.settings),
            codes.names,
            codes.keyframes,
            codes.lengths,
            codes.taus,
            self._live.features.ring.shape,
        )
        return hashlib.sha256(repr(key).encode()).hexdigest()[:32]

    @property
    def _last(self) -> int | None:
        """The frame number of the stream's last frame (None: no frame since it began)."""
        return self._live.last if self._live.started else None

    @classmethod
    def for_skeleton(
        cls,
        library: Library,
        skeleton: Skeleton,
        native_rate: float,
        *,
        settings: RecognitionSettings = DEFAULT_SETTINGS,
        stream: str = "",
        session: str | None = None,
    ) -> Recognizer:
        """Frames of AMC-style channels of ``skeleton`` (forward kinematics per frame)."""
        check_native_rate(native_rate)
        model = skeleton_model(skeleton)
        return cls(library, native_rate, settings=settings, stream=stream, session=session, model=model)

    def fresh(self, session: str | None = None) -> Recognizer:
        """A new recogniser of the same stream and input (its kinematic model shared, not made
        again), under ``session`` (None: a new one)."""
        return Recognizer(
            self.library,
            self.native_rate,
            settings=self.settings,
            stream=self.stream,
            session=session,
            model=self.model,
            joint_names=self.joint_names,
        )

    @classmethod
    def for_positions(
        cls,
        library: Library,
        joint_names: Sequence[str],
        native_rate: float,
        *,
        settings: RecognitionSettings = DEFAULT_SETTINGS,
        stream: str = "",
        session: str | None = None,
    ) -> Recognizer:
        """Frames of joint positions in the order ``joint_names``, which must name every standard
        joint (:data:`replay.JOINT_NAMES`; others are ignored)."""
        return cls(
            library, native_rate, settings=settings, stream=stream, session=session, joint_names=joint_names
        )

    @property
    def plans(self) -> tuple[ClassPlan, ...]:
        return self._plans

    @property
    def stage(self) -> ClassStage:
        """The stream's class stage (its index-rate codes, detections in its frame numbers)."""
        return self._stage

    @property
    def reach(self) -> int:
        """Index-rate frames before the one that emits it that a detection may start at, at most
        (:func:`reach`)."""
        return reach(self._plans, self._stage.codes.hold, self.library.rate)

    @property
    def latency_frames(self) -> int:
        """Native frames from a detection's last frame to its emission, at most: the features'
        delay, the frame after it that shows Δ's minimum, then the hold."""
        return self.clock.lag(self._stage.codes.hold + 2)

    def push(self, number: int, frame: npt.ArrayLike) -> list[Detection]:
        """Add frame ``number``; the detections it completed. The step of :meth:`push_many` for this
        one frame."""
        detections, errors = push_many([(self, number, frame)], FrameError)
        if errors:
            raise errors[0][1]
        return detections

    def flush(self) -> list[Detection]:
        """End the stream: the remaining detections, then a fresh stream (frame numbers start anew)."""
        last = self._last
        self._live.started = False
        return self._stage.flush(last, self._live.flush())

    @staticmethod
    def push_many(frames: Sequence[tuple[Recognizer, object, npt.ArrayLike]]) -> Step:
        """The live path's per-frame step: one frame ``(recogniser, number, values)`` of each of any
        number of distinct recognisers (ValueError, nothing done, for one twice), in one compiled
        call (:func:`daemon._live.push_many`): each frame is checked (number, type, shape;
        :meth:`_check` for all but the usual frame), the channel frames' finiteness checked and the
        cosines and sines of their half angles (forward kinematics, :mod:`replay.kinematics`) taken
        in one numpy call each over all of them, forward kinematics and the feature program run by
        blocks of frames (a pose that is not finite after forward kinematics is refused:
        :meth:`_refusal`), and each index-rate code pushed to its recogniser's compiled competition
        (:attr:`CodeRecognizer.core`). Returns the detections (in the order of the frames, each
        recogniser's in its order) and the refused frames (each changed nothing)."""
        return push_many(frames if isinstance(frames, list) else list(frames), FrameError)

    def _refusal(self, number: int, code: int) -> FrameError:
        """The refusal of frame ``number`` whose compiled step gave ``code`` (below
        :data:`~daemon._live.NOTHING`): a channel or a joint position that is not finite."""
        return (non_finite_pose if code == NON_FINITE else non_finite_channels)(number, self.stream)

    def _check(self, number: object, frame: npt.ArrayLike) -> tuple[int, FloatArray]:
        """The frame number and the frame's values (contiguous float64) if their number, type and
        shape are right, else :class:`FrameError`."""
        last = self._last
        if type(number) is int and last is not None and number == last + 1:
            n = number  # the usual case, without the checks' calls
        else:
            n = check_number(number, last, self.stream)
        values = frame_values(n, frame, self.stream)
        if values.shape != self._shape:
            if self.model is not None:
                check_channels(n, values, self._width, self.stream)
            check_positions(n, values, self._width, self.stream)
        return n, values


def skeleton_model(skeleton: Skeleton) -> KinematicModel:
    """The forward kinematics of ``skeleton``; an error naming the bones the standard joints lack."""
    model = KinematicModel(skeleton)
    model.joints(np.zeros((len(skeleton.node_names), 3)))
    return model


def joint_order(joint_names: Sequence[str]) -> npt.NDArray[np.intp]:
    """Where each standard joint (:data:`replay.JOINT_NAMES`) stands among announced ``joint_names``,
    shape ``(26,)``; ValueError if one is missing or a name repeats."""
    names = list(joint_names)
    missing = [j for j in JOINT_NAMES if j not in names]
    if missing:
        raise InputError(f"the joints must include {', '.join(missing)}")
    if len(set(names)) != len(names):
        raise InputError("a joint is named twice")
    return np.array([names.index(j) for j in JOINT_NAMES], dtype=np.intp)


def check_number(number: object, last: int | None, stream: str) -> int:
    """``number`` as an int if it is one and follows ``last`` (None: the stream's first frame), else
    :class:`FrameError` (``type``, ``repeat``, ``back``, ``jump``)."""
    if isinstance(number, bool) or not isinstance(number, int | np.integer):
        raise FrameError(f"frame number {number!r} is not an integer", "type", stream=stream)
    number = int(number)
    if last is not None and number != last + 1:
        problem: FrameProblem = "repeat" if number == last else "back" if number < last else "jump"
        raise FrameError(
            f"frame {number} after frame {last} ({problem}): frames must be consecutive",
            problem,
            stream=stream,
        )
    return number


def frame_values(number: int, frame: npt.ArrayLike, stream: str) -> FloatArray:
    """The frame as float64 (any shape), or :class:`FrameError` (``shape``) if it is not numbers."""
    try:
        return np.ascontiguousarray(frame, dtype=np.float64)
    except (TypeError, ValueError):
        raise FrameError(f"frame {number}: not an array of numbers", "shape", stream=stream) from None


def check_channels(number: int, values: FloatArray, width: int, stream: str) -> None:
    """A channel frame has shape ``(width,)`` (else ``shape``)."""
    if values.shape != (width,):
        raise FrameError(
            f"frame {number}: {width} channels expected, got shape {values.shape}", "shape", stream=stream
        )


def check_positions(number: int, values: FloatArray, width: int, stream: str) -> None:
    """A positions frame has shape ``(width, 3)`` (else ``shape``)."""
    if values.shape != (width, 3):
        raise FrameError(
            f"frame {number}: ({width}, 3) joint positions expected, got shape {values.shape}",
            "shape",
            stream=stream,
        )


def non_finite_channels(number: int, stream: str) -> FrameError:
    """The error for a channel frame with a value that is not finite."""
    return FrameError(f"frame {number}: a channel is not finite", "non_finite", stream=stream)


def non_finite_pose(number: int, stream: str) -> FrameError:
    """The error for a frame whose standard joints (after forward kinematics) are not finite."""
    return FrameError(f"frame {number}: a joint position is not finite", "non_finite", stream=stream)


def detect(
    motion: Motion,
    library: Library,
    native_rate: float,
    *,
    settings: RecognitionSettings = DEFAULT_SETTINGS,
    stream: str = "",
    session: str = "",
    bridge_s: float = DEFAULT_BRIDGE_S,
) -> list[Detection]:
    """The batch twin of :class:`Recognizer` (as the service's stream table feeds it): every
    detection of ``motion`` (read at ``native_rate`` Hz) in the order the recogniser emits them,
    equal to pushing its frames one by one with the same settings and ``session``. Frames missing
    from ``motion`` are taken as the stream table takes lost poses (:func:`motion_runs`)."""
    return [
        d
        for run in motion_runs(motion, native_rate, bridge_s)
        for d in detect_positions(
            joint_positions(run),
            run.frames,
            library,
            native_rate,
            settings=settings,
            stream=stream,
            session=session,
        )
    ]


def detect_positions(
    positions: FloatArray,
    numbers: IntArray,
    library: Library,
    native_rate: float,
    *,
    settings: RecognitionSettings = DEFAULT_SETTINGS,
    stream: str = "",
    session: str = "",
    bridge_s: float = DEFAULT_BRIDGE_S,
) -> list[Detection]:
    """:func:`detect` of standard joint positions shape ``(N, 26, 3)`` with frame numbers ``(N,)``
    (increasing; gaps bridged as :func:`detect`'s). The features of all frames of a run come from
    one vectorised pass (:func:`daemon.features.features`, the batch twin of the live path's
    :class:`~daemon.features.FeatureStream`), decimated by the live path's
    :class:`~daemon.frames.FrameClock`; the codes go through the live path's :class:`ClassStage`,
    each with the frame whose push would give it (:meth:`~daemon.frames.FrameClock.known`)."""
    out: list[Detection] = []
    for run_numbers, run in bridged_runs(numbers, positions, bridge_frames(bridge_s, native_rate)):
        codes, stage = recording_stage(run, library, native_rate, settings, stream=stream, session=session)
        clock = stage.clock
        first, last = int(run_numbers[0]), int(run_numbers[-1])
        stage.start(first)
        out += [d for j, code in enumerate(codes) for d in stage.push(clock.known(first, j, last), code)]
        out += stage.flush(last)
    return out


def recording_stage(
    positions: FloatArray,
    library: Library,
    native_rate: float,
    settings: RecognitionSettings = DEFAULT_SETTINGS,
    *,
    stream: str = "",
    session: str = "",
) -> tuple[list[int], ClassStage]:
    """What the batch twins take a recording's standard joint positions ``(N, 26, 3)`` through: its
    index-rate codes, from one vectorised feature pass (:func:`daemon.features.features`) decimated
    by the live path's :class:`~daemon.frames.FrameClock`, and the live path's :class:`ClassStage`
    for them (not started)."""
    clock = FrameClock.of(native_rate, library.rate)
    codes: list[int] = pack(
        sampled_features(positions, JOINT_NAMES, native_rate, clock.step, clock.per)
    ).tolist()
    stage = ClassStage(
        plans(library, settings), library.rate, settings, clock, stream=stream, session=session
    )
    return codes, stage
