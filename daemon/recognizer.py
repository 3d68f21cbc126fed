"""The live recogniser: poses of one stream in, detections out, one frame at a time.

Per frame (DESIGN.md, the data flow): AMC-style channels go through forward kinematics (or joint
positions arrive as they are), :class:`~daemon.features.FeatureStream` gives the 39 features,
every k-th frame is kept for the library's rate (30 Hz from 120 Hz), and the frame's code (bit i =
feature i) goes to :class:`CodeRecognizer`: every template of every class runs as a subsequence DTW
over the whole stream (thesis Alg. 3.2 with free start; the retrieval cost and steps of
:func:`daemon.search.retrieval.template_search`), its local minima within τ are candidates, a candidate
beaten by a cheaper one of the same motion (:func:`same_motion`) is dropped, and one that is not is
held until no template can still end a cheaper match of its motion (or ``hold_s``), then published
unless its class is gated by keyframes (:class:`~daemon.automaton.KeyframeAutomaton`'s matches)
and none overlaps it. Published detections are never taken back.

Latency. A detection comes out one index frame after its last frame (the frame that shows Δ's
minimum) once the features' delay (16 frames at 120 Hz) has passed, or later while it is held: at
most :attr:`Recognizer.latency_frames` native frames after its last frame.

Bounded state. The features keep 33 poses at 120 Hz, each gating automaton the query's span, the DTW
three columns per template, and the candidates and keyframe ranges of the last :func:`reach`
frames.

:func:`detect` is the batch twin: features of the whole recording in one vectorised pass, then the
same class stage; it equals pushing the frames one by one (tests).
"""

from __future__ import annotations

import math
import uuid
import weakref
from collections import deque
from collections.abc import Collection, Sequence
from dataclasses import dataclass
from itertools import accumulate
from typing import Any, Literal, NamedTuple

import numpy as np
import numpy.typing as npt

from daemon._automaton import AutomatonSet
from daemon._dtw import StreamDTW
from daemon._live import NON_FINITE, LiveStream
from daemon.automaton import KeyframeAutomaton
from daemon.dtw import SCALE, Match, RetrievalTables, Steps, pack, retrieval_tables, threshold
from daemon.errors import MocapdError
from daemon.features import FeatureStream, decimation_factor, features, latency_frames
from daemon.keyframes import KeyframeQuery
from daemon.library import GATED, ClassTemplate, Library
from daemon.templates import expand
from daemon.types import (
    DEFAULT_HOLD_S,
    DEFAULT_MAX_GAP_S,
    MAX_NATIVE_RATE,
    FloatArray,
    IntArray,
)
from replay import JOINT_NAMES, KinematicModel, Motion, Skeleton
from replay.kinematics import joint_positions

FrameProblem = Literal["shape", "non_finite", "type", "repeat", "back", "jump"]


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
    class's own first), whether its keyframes gate its matches (``gated``) and the keyframe query's
    gap cap in frames."""

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
        """The class's keyframe automaton reporting every match whose range still grows, each frame."""
        assert self.template.keyframes is not None
        return gate_automaton(self.template.keyframes, rate, self.max_gap)


def gate_automaton(query: KeyframeQuery, rate: float, max_gap: int) -> KeyframeAutomaton:
    """The automaton of a keyframe gate: every match reported at each frame its range R(M) reaches,
    from the frame that completes it while its last keyframe holds (period 1, no Ω^Z components)."""
    return KeyframeAutomaton(query, rate, max_gap, 1, components=False)


def gate_ranges(
    query: KeyframeQuery, rate: float, max_gap: int, codes: Sequence[int]
) -> list[tuple[int, int]]:
    """The ranges a keyframe gate opens over a stream of index-rate ``codes``: (start of R(M),
    frame) for every frame that :func:`gate_automaton` reports a match at, in order."""
    automaton = gate_automaton(query, rate, max_gap)
    out = []
    for j, code in enumerate(codes):
        automaton.push(code)
        out += [(first, j) for first, _ in automaton.reached]
    return out


_PLANS: dict[tuple[int, tuple[str, ...] | None, float], tuple[weakref.ref[Library], tuple[ClassPlan, ...]]]
_PLANS = {}


def plans(
    library: Library, classes: Collection[str] | None = None, *, max_gap_s: float = DEFAULT_MAX_GAP_S
) -> tuple[ClassPlan, ...]:
    """The plans of ``classes`` (None: all, in the library's order); ValueError for a gap cap out of
    range. Made once per library object and settings (a stream joining a service costs no template
    preparation)."""
    if not (math.isfinite(max_gap_s) and max_gap_s > 0):
        raise ValueError(f"max_gap_s must be positive seconds, got {max_gap_s}")
    names = list(library.classes) if classes is None else list(classes)
    key = (id(library), None if classes is None else tuple(names), float(max_gap_s))
    held = _PLANS.get(key)
    if held is not None and held[0]() is library:
        return held[1]
    made = _make_plans(library, names, max_gap_s)
    _PLANS[key] = (weakref.ref(library, lambda _: _PLANS.pop(key, None)), made)
    return made


def _make_plans(library: Library, names: Sequence[str], max_gap_s: float) -> tuple[ClassPlan, ...]:
    rate = library.rate
    out = []
    for name in names:
        cls = library.get(name)
        members = []
        for template, tau in cls.members:
            t = expand(template)
            members.append(MemberPlan(t.values, t.weights, retrieval_tables(t.values, t.weights), tau))
        out.append(ClassPlan(cls, tuple(members), cls.mode == GATED, max(1, round(max_gap_s * rate))))
    return tuple(out)


def reach(class_plans: Sequence[ClassPlan], hold: int) -> int:
    """Index-rate frames before the frame that emits it that a detection may start at, at most: a
    match spans at most twice its template's columns (the toolbox's steps; longer matches under the
    thesis' are forgotten as rivals after that long too), then it is held ``hold`` frames after the
    frame that found it."""
    return max((2 * m.length for p in class_plans for m in p.members), default=1) + hold + 2


def same_motion(a: tuple[int, int], b: tuple[int, int]) -> bool:
    """Whether two ranges (inclusive) are one motion: they share more than half of the shorter
    one's frames. DTW matches of consecutive repetitions may share a frame or two of the pose
    between them (it fits the end of one template and the start of the next)."""
    shared = min(a[1], b[1]) - max(a[0], b[0]) + 1
    return 2 * shared > min(a[1] - a[0], b[1] - b[0]) + 1


class _Candidate(NamedTuple):
    """A local minimum of one template's stream-wide Δ: fixed-point ``cost``, ``end``, the template
    (``member``, numbered over all classes' templates) and ``start``; ordered by (cost, end,
    member), the order in which candidates beat each other."""

    cost: int
    end: int
    member: int
    start: int


Confirmation = tuple[ClassPlan, Match, float]
"""A detection in index-rate frames: its class, its match and the τ of the template that made it."""


class CodeRecognizer:
    """Detections over a stream of index-rate frame codes: ``push(code)`` returns the confirmations
    it made, ``flush()`` ends the stream. The part of :class:`Recognizer` after the features, shared
    with :func:`detect`.

    *Candidates.* Every template of every class runs as a subsequence DTW over the whole stream, one
    column per frame (:class:`daemon._dtw.StreamDTW`; thesis Alg. 3.2 with free start, the retrieval
    cost and steps of :func:`daemon.search.retrieval.template_search`). Each local minimum of a template's
    Δ at or below its τ (below the frame before, not above the frame after) is a candidate, known
    one frame after its end.

    *One motion, one detection.* A candidate is beaten by any candidate that comes before it in the
    order (cost, end, template) and is the :func:`same_motion`: of another class when classes
    ``compete`` (the cheaper template is the better explanation), of its own class always (one
    detection per motion). A candidate that is not beaten is held until no template can still end
    a match that would beat it (:meth:`daemon._dtw.StreamDTW.blocks`: costs only grow along a DTW
    path, so a cell already above its cost cannot), or until ``hold`` frames after the frame that
    found it, whichever comes first; then it is published, unless its class is ``gated`` and no
    keyframe match of the class (below) overlaps it, or it is the same motion as a detection
    already published (after the hold ran out). Candidates and keyframe matches are remembered for
    :func:`reach` frames.

    *The keyframe gate.* A gated class's automaton reports each keyframe match (Alg. 4.1's matches,
    :class:`~daemon.automaton.KeyframeAutomaton`) at the frame that completes it and at every frame
    after while its last keyframe holds, with the start of its hit-relevant range R(M): a candidate
    of the class passes when one of these ranges (start to the frame reported at), reported by the
    time it is decided, shares a frame with it (:func:`gate_ranges`)."""

    def __init__(
        self, class_plans: Sequence[ClassPlan], rate: float, *, compete: bool = True, hold: int = 0
    ) -> None:
        if hold < 0:
            raise ValueError(f"hold must not be negative, got {hold}")
        self.plans = tuple(class_plans)
        self.rate = rate
        self.compete = compete
        self.hold = hold
        self._owner = [k for k, p in enumerate(self.plans) for _ in p.members]
        first = list(accumulate((len(p.members) for p in self.plans), initial=0))
        # the templates a candidate's rivals come from: all, or its own class's
        self._rivals = [(0, len(self._owner)) if compete else (first[k], first[k + 1]) for k in self._owner]
        self._taus = [m.tau for p in self.plans for m in p.members]
        self._dtw = (
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
        self._gated = [k for k, p in enumerate(self.plans) if p.gated]
        self._automata = (
            AutomatonSet([self.plans[k].automaton(rate).core for k in self._gated]) if self._gated else None
        )
        self._windows: dict[int, deque[tuple[int, int]]] = {k: deque() for k in self._gated}
        self._memory = reach(self.plans, hold)
        self._held: list[_Candidate] = []
        self._recent: deque[_Candidate] = deque()
        self._published: deque[tuple[int, int, int]] = deque()  # (start, end, class)
        self._n = 0

    @property
    def frames(self) -> int:
        """Index-rate frames pushed since the stream began."""
        return self._n

    def push(self, code: int) -> list[Confirmation]:
        j = self._n
        if self._dtw is None:
            self._n += 1
            return []
        found = self._dtw.push(code)
        self._n += 1
        if self._automata is not None:
            for i, reached in self._automata.push(code):
                w = self._windows[self._gated[i]]
                for first, _ in reached:
                    if w and w[-1] == (first, j - 1):  # the same match, its range grown by a frame
                        w[-1] = (first, j)
                    else:
                        w.append((first, j))
        if found is not None:
            for c in sorted(_Candidate(d, e, u, s) for u, s, e, d in found):
                self._arrive(c)
        out = self._decide(j, False) if self._held else []
        self._forget(j)
        return out

    def flush(self) -> list[Confirmation]:
        out: list[Confirmation] = []
        if self._dtw is not None and self._n:
            found = self._dtw.finish()
            if found is not None:
                for c in sorted(_Candidate(d, e, u, s) for u, s, e, d in found):
                    self._arrive(c)
            out = self._decide(self._n - 1, True)
            self._dtw.reset()
        if self._automata is not None:
            self._automata.flush()
        for w in self._windows.values():
            w.clear()
        self._held.clear()
        self._recent.clear()
        self._published.clear()
        self._n = 0
        return out

    def _rival(self, x: _Candidate, y: _Candidate) -> bool:
        """Whether ``x`` and ``y`` may beat one another: the same motion, of one class or competing."""
        return (self.compete or self._owner[x.member] == self._owner[y.member]) and same_motion(
            (x.start, x.end), (y.start, y.end)
        )

    def _arrive(self, y: _Candidate) -> None:
        """A new candidate: remembered as a rival; held unless something before it beats it or it is
        a motion already published; a held one it beats is dropped."""
        beaten = any(x < y and self._rival(x, y) for x in self._recent)
        self._recent.append(y)
        k = self._owner[y.member]
        if beaten or any(
            (self.compete or c == k) and same_motion((y.start, y.end), (a, b)) for a, b, c in self._published
        ):
            return
        self._held = [x for x in self._held if not (y < x and self._rival(x, y))]
        self._held.append(y)

    def _decide(self, j: int, ended: bool) -> list[Confirmation]:
        """The held candidates that frame ``j`` (the stream's last, if it ``ended``) makes final:
        those published, in the order (end, start, class)."""
        assert self._dtw is not None
        final, keep = [], []
        for x in self._held:
            lo, hi = self._rivals[x.member]
            if ended or j > x.end + self.hold or not self._dtw.blocks(x.cost, x.start, x.end, lo, hi):
                final.append(x)
            else:
                keep.append(x)
        self._held = keep
        out = []
        for x in sorted(final, key=lambda x: (x.end, x.start, self._owner[x.member])):
            k = self._owner[x.member]
            if k in self._windows and not any(a <= x.end and x.start <= b for a, b in self._windows[k]):
                continue
            self._published.append((x.start, x.end, k))
            out.append((self.plans[k], Match(x.start, x.end, x.cost / SCALE), self._taus[x.member]))
        return out

    def _forget(self, j: int) -> None:
        """Drop what no candidate after frame ``j`` can be compared with: rivals and published
        detections that end more than :func:`reach` frames back (a later candidate cannot overlap
        them), and keyframe matches as long."""
        forget = j - self._memory
        while self._recent and self._recent[0].end < forget:
            self._recent.popleft()
        while self._published and self._published[0][1] < forget:
            self._published.popleft()
        for w in self._windows.values():
            while w and w[0][1] < forget:
                w.popleft()


class Recognizer:
    """Detections of the library's classes on one stream, one frame at a time.

    Make it with :meth:`for_skeleton` (frames are AMC-style channel vectors, shape ``(C,)`` in the
    skeleton's channel order, angles in radians as :mod:`replay` reads them) or
    :meth:`for_positions` (frames are joint positions, shape ``(J, 3)`` in the announced joint order,
    any length unit: the features are scale-free). ``push(number, frame)`` takes the source's frame
    number (consecutive) and returns the detections that were emitted; ``flush()`` ends the stream,
    returns the rest and starts a new stream. Bad frames raise :class:`FrameError` and change
    nothing."""

    def __init__(
        self,
        library: Library,
        native_rate: float,
        *,
        stream: str = "",
        classes: Collection[str] | None = None,
        max_gap_s: float = DEFAULT_MAX_GAP_S,
        compete: bool = True,
        hold_s: float = DEFAULT_HOLD_S,
        session: str | None = None,
        model: KinematicModel | None = None,
        joint_names: Sequence[str] | None = None,
    ) -> None:
        check_native_rate(native_rate)
        self.stream = stream
        self.library = library
        self.native_rate = native_rate
        self.session = uuid.uuid4().hex if session is None else session
        self._step = decimation_factor(native_rate, library.rate)
        self.model = model
        if model is not None:
            self._width = len(model.skeleton.channel_names)
        else:
            if joint_names is None:
                raise ValueError("give a kinematic model (channels) or the joint names (positions)")
            self._width = len(joint_names)
            self._joint_order = joint_order(joint_names)
        self._plans = plans(library, classes, max_gap_s=max_gap_s)
        features = FeatureStream(JOINT_NAMES, native_rate)
        self._features_latency = features.latency
        if model is not None:
            self._shape: tuple[int, ...] = (self._width,)
            self._live = LiveStream(
                model.frame_kinematics, features.core, features.thresholds_of, None, self._width, self._step
            )
        else:
            self._shape = (self._width, 3)
            order = (3 * self._joint_order[:, None] + np.arange(3)).reshape(-1)
            self._live = LiveStream(
                None, features.core, features.thresholds_of, order, 3 * self._width, self._step
            )
        self._codes = CodeRecognizer(
            self._plans, library.rate, compete=compete, hold=hold_frames(hold_s, library.rate)
        )
        self._first: int | None = None  # native frame numbers of the stream's first and last frame
        self._last: int | None = None

    @classmethod
    def for_skeleton(cls, library: Library, skeleton: Skeleton, native_rate: float, **kw: Any) -> Recognizer:
        """Frames of AMC-style channels of ``skeleton`` (forward kinematics per frame)."""
        return cls(library, native_rate, model=skeleton_model(skeleton), **kw)

    @classmethod
    def for_positions(
        cls, library: Library, joint_names: Sequence[str], native_rate: float, **kw: Any
    ) -> Recognizer:
        """Frames of joint positions in the order ``joint_names``, which must name every standard
        joint (:data:`replay.JOINT_NAMES`; others are ignored)."""
        return cls(library, native_rate, joint_names=joint_names, **kw)

    @property
    def plans(self) -> tuple[ClassPlan, ...]:
        return self._plans

    @property
    def latency_frames(self) -> int:
        """Native frames from a detection's last frame to its emission, at most: the features'
        delay, the frame after it that shows Δ's minimum, then the hold."""
        return self._features_latency + (self._codes.hold + 2) * self._step

    def push(self, number: int, frame: npt.ArrayLike) -> list[Detection]:
        """Add frame ``number``; the detections it completed."""
        n, values = self._check(number, frame)
        if self.model is None:
            return self._after(n, self._live.push_positions(values.reshape(-1)))
        if not math.isfinite(values.sum()) and not np.isfinite(values).all():  # one reduction if finite
            raise non_finite_channels(n, self.stream)
        half = 0.5 * values
        return self._after(n, self._live.push_channels(values, np.cos(half), np.sin(half)))

    def flush(self) -> list[Detection]:
        """End the stream: the remaining detections, then a fresh stream (frame numbers start anew)."""
        last = self._last
        out = [d for code in self._live.flush() for d in self._detections(self._codes.push(code), last or 0)]
        found = self._codes.flush()
        if last is not None:
            out += self._detections(found, last)
        self._first = self._last = None
        return out

    def _check(self, number: object, frame: npt.ArrayLike) -> tuple[int, FloatArray]:
        """The frame number and the frame's values (contiguous float64) if their number, type and
        shape are right, else :class:`FrameError`. Channels' finiteness is checked by the caller
        (the bank checks every stream's at once)."""
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

    def _after(self, number: int, code: int) -> list[Detection]:
        """What the compiled frame step gave for frame ``number``: an index-rate code for the classes,
        nothing, or a refusal (the step changed nothing then)."""
        if code == NON_FINITE:
            raise non_finite_pose(number, self.stream)
        if self._first is None:
            self._first = number
        self._last = number
        return [] if code < 0 else self._detections(self._codes.push(code), number)

    def _detections(self, found: Sequence[Confirmation], number: int) -> list[Detection]:
        first = self._first
        assert first is not None
        return [make_detection(self.session, self.stream, c, first, self._step, number) for c in found]


def skeleton_model(skeleton: Skeleton) -> KinematicModel:
    """The forward kinematics of ``skeleton``; an error naming the bones the standard joints lack."""
    model = KinematicModel(skeleton)
    model.joints(np.zeros((len(skeleton.node_names), 3)))
    return model


def check_native_rate(rate: float) -> None:
    """ValueError unless ``rate`` (Hz) is one features are computed at."""
    if not (math.isfinite(rate) and 0 < rate <= MAX_NATIVE_RATE):
        raise ValueError(f"native rate must be in (0, {MAX_NATIVE_RATE:g}] Hz, got {rate}")


def joint_order(joint_names: Sequence[str]) -> npt.NDArray[np.intp]:
    """Where each standard joint (:data:`replay.JOINT_NAMES`) stands among announced ``joint_names``,
    shape ``(26,)``; ValueError if one is missing or a name repeats."""
    names = list(joint_names)
    missing = [j for j in JOINT_NAMES if j not in names]
    if missing:
        raise ValueError(f"the joints must include {', '.join(missing)}")
    if len(set(names)) != len(names):
        raise ValueError("a joint is named twice")
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
    """The error :func:`check_channels` raises for non-finite channels."""
    return FrameError(f"frame {number}: a channel is not finite", "non_finite", stream=stream)


def non_finite_pose(number: int, stream: str) -> FrameError:
    """The error for a frame whose standard joints (after forward kinematics) are not finite."""
    return FrameError(f"frame {number}: a joint position is not finite", "non_finite", stream=stream)


def hold_frames(hold_s: float, rate: float) -> int:
    """The hold in frames at ``rate`` Hz; ValueError unless ``hold_s`` is seconds >= 0."""
    if not (math.isfinite(hold_s) and hold_s >= 0):
        raise ValueError(f"hold_s must be seconds >= 0, got {hold_s}")
    return round(hold_s * rate)


def make_detection(
    session: str, stream: str, found: Confirmation, first: int, step: int, number: int
) -> Detection:
    """A confirmation (index-rate frames) as a :class:`Detection` in the source's frame numbers:
    index frame j covers native frames ``first + j·step`` .. ``first + (j+1)·step - 1``, the end
    capped by the frame ``number`` being pushed (the features' delay makes it later than every
    covered frame but at the stream's end)."""
    plan, m, tau = found
    start = first + m.start * step
    end = min(first + (m.end + 1) * step - 1, number)
    key = f"{session}/{stream}/{plan.name}/{start}/{end}"
    return Detection(
        str(uuid.uuid5(uuid.NAMESPACE_URL, key)), stream, plan.name, start, end, m.cost, tau, number
    )


def detect(
    motion: Motion,
    library: Library,
    native_rate: float,
    *,
    stream: str = "",
    classes: Collection[str] | None = None,
    max_gap_s: float = DEFAULT_MAX_GAP_S,
    compete: bool = True,
    hold_s: float = DEFAULT_HOLD_S,
    session: str = "",
) -> list[Detection]:
    """The batch twin of :class:`Recognizer`: every detection of ``motion`` (read at ``native_rate``
    Hz) in the order the recogniser emits them, equal to pushing its frames one by one with the same
    ``session``. Features come from one vectorised pass over the whole recording."""
    return detect_positions(
        joint_positions(motion),
        motion.frames,
        library,
        native_rate,
        stream=stream,
        classes=classes,
        max_gap_s=max_gap_s,
        compete=compete,
        hold_s=hold_s,
        session=session,
    )


def detect_positions(
    positions: FloatArray,
    numbers: IntArray,
    library: Library,
    native_rate: float,
    *,
    stream: str = "",
    classes: Collection[str] | None = None,
    max_gap_s: float = DEFAULT_MAX_GAP_S,
    compete: bool = True,
    hold_s: float = DEFAULT_HOLD_S,
    session: str = "",
) -> list[Detection]:
    """:func:`detect` of standard joint positions shape ``(N, 26, 3)`` with frame numbers ``(N,)``
    (consecutive)."""
    n = len(positions)
    if n == 0:
        return []
    step = decimation_factor(native_rate, library.rate)
    matrix = features(positions, JOINT_NAMES, native_rate)[::step]  # (n_index, 39)
    codes = pack(matrix).tolist()
    recognizer = CodeRecognizer(
        plans(library, classes, max_gap_s=max_gap_s),
        library.rate,
        compete=compete,
        hold=hold_frames(hold_s, library.rate),
    )
    first, last = int(numbers[0]), int(numbers[-1])
    delay = latency_frames(native_rate)
    out = []
    for j, code in enumerate(codes):
        # index frame j's features come out when native frame j·step + delay is pushed
        number = min(first + j * step + delay, last)
        out += [make_detection(session, stream, c, first, step, number) for c in recognizer.push(code)]
    out += [make_detection(session, stream, c, first, step, last) for c in recognizer.flush()]
    return out
