"""The live recogniser: poses of one stream in, detections out, one frame at a time.

Per frame (DESIGN.md, the data flow): AMC-style channels go through forward kinematics (or joint
positions arrive as they are), :class:`~daemon.features.FeatureStream` gives the 39 features,
every k-th frame is kept for the library's rate (30 Hz from 120 Hz), and the frame's code (bit i =
feature i) goes to every class's :class:`~daemon.automaton.KeyframeAutomaton`. Each keyframe
*match* it completes (a hit of every keyframe within the stiffness windows, Alg. 4.1) is a
candidate: its hit-relevant range R(M) (Def. 4.6), widened as
:func:`daemon.retrieval.keyframe_extension` widens keyframe ranges for ranking (the template's
columns before the first and after the last keyframe, times 1.5), is confirmed by subsequence DTW of the
class's quantised motion template (thesis §3.4, the retrieval cost and steps of
:func:`daemon.retrieval.template_search`) as soon as the window's last frame has arrived. Every local
minimum at or below the class's τ, after the toolbox's suppression, is a confirmation; its range is
the DTW match, not the keyframe range. Matches, not Ω^Z components, start confirmation: a component
is final only Σ dmax frames after its end, and a long series of repetitions whose ranges touch is one
component that would be confirmed only when the series ends.

One motion, one detection per class: two confirmations of a class that share more than half of the
shorter one's frames are one motion (:func:`same_motion`). Among those confirmed together the
cheaper is kept; one that is the same motion as a detection already emitted is dropped (that one
was published and cannot be taken back). A repetition right after the last is reported, even if
the two share the frame or two of the pose between them. One motion, one class (``compete``): a
confirmation is dropped when another class's template fits the same motion more cheaply
(:class:`CodeRecognizer`).

Latency. A detection comes out when the index-rate frame ``right`` frames after its match's last
keyframe has been pushed, i.e. at most :attr:`Recognizer.latency_frames` native frames after that
keyframe (the features' delay of 16 frames at 120 Hz plus ``right`` index frames).

Bounded state. The features keep 33 poses at 120 Hz, each automaton the query's span, and the
stream one ring of its recent codes as long as the widest window (Σ dmax + left + right + 1); with
``compete``, three DTW columns per class and each class's Δ over that ring.

:func:`detect` is the batch twin: features of the whole recording in one vectorised pass, then the
same candidate and confirmation logic; it equals pushing the frames one by one (tests).
"""

from __future__ import annotations

import math
import uuid
import weakref
from collections import deque
from collections.abc import Collection, Sequence
from dataclasses import dataclass
from itertools import islice
from typing import Any, Literal

import numpy as np
import numpy.typing as npt

from daemon._automaton import AutomatonSet
from daemon._dtw import StreamDTW
from daemon._live import NON_FINITE, LiveStream
from daemon.automaton import KeyframeAutomaton
from daemon.dtw import (
    Match,
    RetrievalTables,
    Steps,
    pack,
    retrieval_tables,
    subsequence_minima,
    suppress,
    threshold,
)
from daemon.errors import MocapdError
from daemon.features import FeatureStream, decimation_factor, features, latency_frames
from daemon.keyframes import query_bounds
from daemon.library import ClassTemplate, Library
from daemon.recordings import joint_positions
from daemon.retrieval import keyframe_extension
from daemon.templates import expand
from daemon.types import (
    DEFAULT_MAX_GAP_S,
    MAX_NATIVE_RATE,
    FloatArray,
    IntArray,
)
from replay import JOINT_NAMES, KinematicModel, Motion, Skeleton

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
class ClassPlan:
    """What a stream needs of one class, at the library's rate: the expanded quantised template
    (``values`` shape ``(39, M)``, ``weights`` ``(M,)``, its cost ``tables``), τ, the DTW steps, the
    keyframe query with its gap cap, a match's window widening (``left``, ``right``) and ``span``,
    the most frames a match's range reaches before its last keyframe (Σ dmax)."""

    template: ClassTemplate
    values: FloatArray
    weights: FloatArray
    tables: RetrievalTables
    max_gap: int
    left: int
    right: int
    span: int

    @property
    def name(self) -> str:
        return self.template.name

    @property
    def tau(self) -> float:
        return self.template.tau

    @property
    def steps(self) -> Steps:
        return self.template.steps

    @property
    def window(self) -> int:
        """The most frames a window spans: a match's whole range, widened."""
        return self.span + self.left + self.right + 1

    @property
    def period(self) -> int:
        """Frames between the windows of a match whose last keyframe keeps holding (half a window)."""
        return max(1, self.window // 2)

    def automaton(self, rate: float) -> KeyframeAutomaton:
        assert self.template.keyframes is not None
        return KeyframeAutomaton(self.template.keyframes, rate, self.max_gap, self.period, components=False)


_PLANS: dict[tuple[int, tuple[str, ...] | None, float], tuple[weakref.ref[Library], tuple[ClassPlan, ...]]]
_PLANS = {}


def plans(
    library: Library, classes: Collection[str] | None = None, *, max_gap_s: float = DEFAULT_MAX_GAP_S
) -> tuple[ClassPlan, ...]:
    """The plans of ``classes`` (None: all, in the library's order); ValueError for a class without
    keyframes (it could never be a candidate) or a gap cap out of range. Made once per library
    object and settings (a stream joining a service costs no template preparation)."""
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
        if cls.keyframes is None:
            raise ValueError(f"class {name} has no keyframes: learn it with --keyframes to recognise it live")
        t = expand(cls.quantised)
        max_gap = max(1, round(max_gap_s * rate))
        left, right = keyframe_extension(cls.keyframes, cls.quantised.length, rate)
        span = sum(hi for _, hi in query_bounds(cls.keyframes, rate, max_gap) if hi is not None)
        tables = retrieval_tables(t.values, t.weights)
        out.append(ClassPlan(cls, t.values, t.weights, tables, max_gap, left, right, span))
    return tuple(out)


def ring_size(class_plans: Sequence[ClassPlan]) -> int:
    """Index-rate frames a stream keeps: the widest window of any class."""
    return max((p.window for p in class_plans), default=1)


def confirm(plan: ClassPlan, codes: npt.NDArray[np.uint64]) -> list[Match]:
    """The DTW confirmations of ``plan``'s class in a window of codes shape ``(n,)``: local minima of
    the subsequence DTW (compiled, :func:`daemon.dtw.subsequence_minima`) at or below τ, suppressed
    as the toolbox does (window columns)."""
    return suppress(subsequence_minima(plan.tables, codes, plan.tau, plan.steps))


def same_motion(a: tuple[int, int], b: tuple[int, int]) -> bool:
    """Whether two ranges (inclusive) of one class are one motion: they share more than half of the
    shorter one's frames. DTW matches of consecutive repetitions may share a frame or two of the
    pose between them (it fits the end of one template and the start of the next)."""
    shared = min(a[1], b[1]) - max(a[0], b[0]) + 1
    return 2 * shared > min(a[1] - a[0], b[1] - b[0]) + 1


def keep_apart(hits: Sequence[Match], published: Sequence[tuple[int, int]]) -> list[Match]:
    """``hits`` by increasing cost, each kept unless it is the :func:`same_motion` as one kept or
    ``published``; sorted by start."""
    taken = list(published)
    kept = []
    for m in sorted(hits, key=lambda m: (m.cost, m.start)):
        if not any(same_motion((m.start, m.end), r) for r in taken):
            kept.append(m)
            taken.append((m.start, m.end))
    return sorted(kept, key=lambda m: m.start)


class _ClassTrack:
    """One class on one stream: the windows waiting for their last frame (in the order they are
    confirmed) and the ranges emitted that a later window could still overlap."""

    __slots__ = ("pending", "plan", "published")

    def __init__(self, plan: ClassPlan) -> None:
        self.plan = plan
        self.pending: deque[tuple[int, int]] = deque()
        self.published: list[tuple[int, int]] = []


class CodeRecognizer:
    """Candidates and confirmations over a stream of index-rate frame codes: ``push(code)`` returns
    the confirmations it made, as (class plan, match in stream frames); ``flush()`` ends the stream.
    The part of :class:`Recognizer` after the features, shared with :func:`detect`.

    Each keyframe match (Alg. 4.1's matches, as the automaton completes them) opens a window, its
    range R(M) so far widened by the plan's ``left`` and ``right`` frames (its last ``window``
    frames), confirmed when its last frame arrives: ``right`` frames after the match's last keyframe,
    whatever comes after. While the last keyframe keeps holding (a long run, e.g. a pose shared by
    a series of repetitions), the match opens another window every ``period`` frames. The windows a
    class opens at one frame are one window, the widest.

    With ``compete`` (the default), classes compete for a motion: a confirmation is dropped when
    another class's template matches the same motion more cheaply. Every class's template runs as
    a subsequence DTW over the whole stream, one column per frame (:class:`daemon._dtw.StreamDTW`,
    the cells of :func:`confirm`'s pass); a confirmation ``m`` of one class due at frame ``j`` is
    beaten when another class's Δ has a local minimum (below the frame before, not above the frame
    after if it has come) at some frame from ``m.start`` to ``j``, at or below that class's τ and
    below ``m``'s cost, whose match is the :func:`same_motion` as ``m``. A class's own detector
    cannot tell a squat from a knee raise; the cheaper template is the better explanation."""

    def __init__(self, class_plans: Sequence[ClassPlan], rate: float, *, compete: bool = True) -> None:
        self.plans = tuple(class_plans)
        self.rate = rate
        self._ring: deque[int] = deque(maxlen=ring_size(self.plans))
        self._compete = (
            StreamDTW(
                [
                    (p.tables.masks, p.tables.values, p.tables.tables, threshold(p.tau), p.steps == "toolbox")
                    for p in self.plans
                ],
                ring_size(self.plans) + 1,
            )
            if compete and len(self.plans) > 1
            else None
        )
        self._tracks = [_ClassTrack(p) for p in self.plans]
        # every class's automaton, stepped in one compiled call per frame
        self._automata = AutomatonSet([p.automaton(rate).core for p in self.plans])
        self._next_due = _NEVER  # the earliest frame a pending window is due at
        self._n = 0

    @property
    def frames(self) -> int:
        """Index-rate frames pushed since the stream began."""
        return self._n

    def push(self, code: int) -> list[tuple[ClassPlan, Match]]:
        j = self._n
        self._n += 1
        self._ring.append(code)
        if self._compete is not None:
            self._compete.push(code)
        for k, reached in self._automata.push(code):
            track = self._tracks[k]
            p = track.plan
            end = j + p.right
            track.pending.append(
                (min(max(0, first - p.left, end - p.window + 1) for first, _ in reached), end)
            )
            self._next_due = min(self._next_due, end)
        return [] if j < self._next_due else self._confirm(j, False)

    def flush(self) -> list[tuple[ClassPlan, Match]]:
        self._automata.flush()
        out = self._confirm(self._n - 1, True)
        for track in self._tracks:
            track.published.clear()
        self._ring.clear()
        if self._compete is not None:
            self._compete.reset()
        self._n = 0
        return out

    def _confirm(self, j: int, ended: bool) -> list[tuple[ClassPlan, Match]]:
        """Every window due at frame ``j`` (all, if the stream ``ended``) confirmed and kept apart
        from its class's detections."""
        base = self._n - len(self._ring)
        out = []
        rivals = self._compete
        self._next_due = _NEVER
        for k, track in enumerate(self._tracks):
            pending = track.pending
            if pending and (ended or pending[0][1] <= j):
                p = track.plan
                # no later window starts before this one: its match completes after j - right
                track.published = [r for r in track.published if r[1] >= j - p.right - p.span - p.left]
                while pending and (ended or pending[0][1] <= j):
                    a, b = pending.popleft()
                    b = min(b, j)
                    if a < base:  # cannot happen: ring_size covers every window
                        raise AssertionError(f"window {a}..{b} left the ring (from {base})")
                    window = np.fromiter(islice(self._ring, a - base, b - base + 1), np.uint64, b - a + 1)
                    shifted = [Match(m.start + a, m.end + a, m.cost) for m in confirm(p, window)]
                    for m in keep_apart(shifted, track.published):
                        if rivals is not None and rivals.beaten(k, m.start, m.end, threshold(m.cost)):
                            continue
                        track.published.append((m.start, m.end))
                        out.append((p, m))
            if pending:
                self._next_due = min(self._next_due, pending[0][1])
        return out


_NEVER = 1 << 62


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
        self._codes = CodeRecognizer(self._plans, library.rate, compete=compete)
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
        """Native frames from a keyframe match's last keyframe to its confirmation, at most: the
        features' delay, then the widest right widening of a class at the library's rate."""
        return self._features_latency + max((p.right for p in self._plans), default=0) * self._step

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

    def _detections(self, found: Sequence[tuple[ClassPlan, Match]], number: int) -> list[Detection]:
        first = self._first
        assert first is not None
        return [make_detection(self.session, self.stream, p, m, first, self._step, number) for p, m in found]


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


def make_detection(
    session: str, stream: str, plan: ClassPlan, m: Match, first: int, step: int, number: int
) -> Detection:
    """A confirmation ``m`` (index-rate frames) as a :class:`Detection` in the source's frame
    numbers: index frame j covers native frames ``first + j·step`` .. ``first + (j+1)·step - 1``,
    the end capped by the frame ``number`` being pushed (the features' delay makes it later than
    every covered frame but at the stream's end)."""
    start = first + m.start * step
    end = min(first + (m.end + 1) * step - 1, number)
    key = f"{session}/{stream}/{plan.name}/{start}/{end}"
    return Detection(
        str(uuid.uuid5(uuid.NAMESPACE_URL, key)), stream, plan.name, start, end, m.cost, plan.tau, number
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
    recognizer = CodeRecognizer(plans(library, classes, max_gap_s=max_gap_s), library.rate, compete=compete)
    first, last = int(numbers[0]), int(numbers[-1])
    delay = latency_frames(native_rate)
    out = []
    for j, code in enumerate(codes):
        # index frame j's features come out when native frame j·step + delay is pushed
        number = min(first + j * step + delay, last)
        out += [make_detection(session, stream, p, m, first, step, number) for p, m in recognizer.push(code)]
    out += [make_detection(session, stream, p, m, first, step, last) for p, m in recognizer.flush()]
    return out
