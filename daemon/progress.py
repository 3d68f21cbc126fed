"""Progress: how far the motions under way on a stream have got (issue 24; the wire's ``progress``
message, ``protocols/README.md``).

After each index-rate code a stream's :class:`~daemon.recognizer.ClassStage` is read
(:func:`read`, from its compiled competition, :meth:`daemon._dtw.Competition.progress`): per class
its keyframes matched so far and its position along its templates. :class:`ProgressStage` turns
those snapshots into events — only changes, rate-limited in the stream's own frames, a change of
the keyframes matched at once — and :class:`StreamProgress` is the two together for one stream.
:func:`detect_progress` is the batch twin: the features of a whole recording in one vectorised
pass, then the same class stage, reading and stage, equal to pushing the frames one by one.

*Keyframes.* For a class gated by a keyframe automaton (n keyframes), the frame numbers at which
keyframes 1..k of its most advanced partial match were found (the frame that linked each, through
the stream's :class:`~daemon.frames.FrameClock` as a detection's frames are); when a whole hit
completes, k = n with that hit's frames, held until the frame at which a detection of the class
that overlaps it is published, or until it can give none. Other classes: n = 0, no frames.

*Position.* Of the class's templates, the furthest column i (of m) of the stream-wide DTW's column
at this index frame whose accumulated cost D(i) is within τ as a mean per template column
(:meth:`daemon._dtw.StreamDTW.progress`), on a path that starts after the class's last spent
candidate (published, or lost to another class or to a detection:
:meth:`daemon._dtw.Competition.progress`): position (i + 1)/m, cost the mean D(i)·m/(i + 1) in a
detection's units (a detection's cost is this at position 1); the template furthest along wins,
ties the cheaper. None within τ: position 0, cost τ.

*Under way.* A class gated by keyframes with a keyframe matched (its gate decides whether its
template's match can be a detection); another at position :data:`FLOOR` or more
(``docs/live-recognition.md`` says how the floor was chosen).

Pure: integers in, frozen dataclasses out; no I/O.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from daemon.dtw import SCALE
from daemon.errors import InputError
from daemon.frames import motion_runs
from daemon.library import Library
from daemon.recognizer import DEFAULT_SETTINGS, ClassStage, Detection, recording_stage
from daemon.types import DEFAULT_BRIDGE_S, FloatArray, IntArray, RecognitionSettings
from replay import Motion
from replay.kinematics import joint_positions

FLOOR = 0.5
"""The position from which a class not gated by keyframes counts as under way (how it was
chosen: ``docs/live-recognition.md``, "Progress events")."""
DEFAULT_PER_S = 10.0
"""Progress events a second of a stream's frames, at most (config ``progress.per_s``)."""


@dataclass(frozen=True)
class ClassState:
    """How far a motion of ``class_name`` has got: of its ``keyframes`` (n; 0 without a keyframe
    gate), the frame numbers at which keyframes 1..k were ``matched`` (ascending; k = n: a whole
    hit), its ``position`` in [0, 1] along its template and that path's mean ``cost`` per template
    column, and the template's ``tau``."""

    class_name: str
    keyframes: int
    matched: tuple[int, ...]
    position: float
    cost: float
    tau: float

    def as_json(self) -> dict[str, Any]:
        """The wire's fields (``class`` for ``class_name``)."""
        return {
            "class": self.class_name,
            "keyframes": self.keyframes,
            "matched": list(self.matched),
            "position": self.position,
            "cost": self.cost,
            "tau": self.tau,
        }


Snapshot = tuple[ClassState, ...]
"""The classes under way at one index frame, sorted by class name."""


@dataclass(frozen=True)
class ProgressEvent:
    """The classes under way (none: nothing is) when frame ``frame`` was recognised."""

    frame: int
    classes: Snapshot

    def as_json(self, stream: str, source_time: float) -> dict[str, Any]:
        """The wire message's fields but ``emit_time``, for ``stream`` and the pose's time."""
        return {
            "type": "progress",
            "stream": stream,
            "frame": self.frame,
            "classes": [c.as_json() for c in self.classes],
            "source_time": source_time,
        }


def min_gap(rate: float, per_s: float) -> int:
    """Frames (sequence numbers) between two rate-limited events at ``rate`` Hz: ceil(rate/per_s)."""
    if not (math.isfinite(per_s) and per_s > 0):
        raise InputError(f"per_s must be a positive number of events a second, got {per_s!r}")
    return max(1, math.ceil(rate / per_s))


def _key(snapshot: Snapshot) -> tuple[tuple[object, ...], ...]:
    """What a change is judged on: cost to 0.001, position to 0.01, the rest exactly."""
    return tuple(
        (c.class_name, c.keyframes, c.matched, round(c.position, 2), round(c.cost, 3), c.tau)
        for c in snapshot
    )


def _matched(snapshot: Snapshot) -> tuple[tuple[str, tuple[int, ...]], ...]:
    """The keyframes matched per class (a class with none as one not under way)."""
    return tuple((c.class_name, c.matched) for c in snapshot if c.matched)


class ProgressStage:
    """One stream's progress events: :meth:`push` each index frame's ``(number, snapshot)`` (its
    sequence number and the classes under way); an event comes out when the snapshot differs from
    the last one emitted (:func:`_key`), at least :func:`min_gap` numbers after the last event,
    except that a change of any class's keyframes matched (a new one, or a reset) comes out at
    once; a change held back comes out at the first push the limit allows if it still differs.
    Once nothing is under way after something was, one empty snapshot. :meth:`flush` ends the
    stream (an empty snapshot if the last event was not one) and starts anew. State: the last
    event's snapshot key and number, whatever the stream's length."""

    def __init__(self, rate: float, per_s: float = DEFAULT_PER_S) -> None:
        self.gap = min_gap(rate, per_s)
        self._key: tuple[tuple[object, ...], ...] = ()
        self._matched: tuple[tuple[str, tuple[int, ...]], ...] = ()
        self._at: int | None = None
        self._last: int | None = None

    def push(self, number: int, snapshot: Snapshot) -> list[ProgressEvent]:
        self._last = number
        key = _key(snapshot)
        if key == self._key:
            return []
        matched = _matched(snapshot)
        if matched == self._matched and self._at is not None and number - self._at < self.gap:
            return []
        self._key, self._matched, self._at = key, matched, number
        return [ProgressEvent(number, snapshot)]

    def flush(self) -> list[ProgressEvent]:
        out = [ProgressEvent(self._last, ())] if self._key and self._last is not None else []
        self._key, self._matched, self._at, self._last = (), (), None, None
        return out


def read(stage: ClassStage, floor: float = FLOOR) -> Snapshot:
    """The classes under way on ``stage``'s stream after its last index frame (position at least
    ``floor`` in (0, 1], or a keyframe matched), by class name; keyframe frames as frame numbers.
    Call it after every index frame of a stream whose progress is followed (it keeps each gated
    class's last whole hit)."""
    core = stage.codes.core
    if core is None or stage.first is None:
        return ()
    found = core.progress(floor)
    if not found:
        return ()
    first, clock, codes = stage.first, stage.clock, stage.codes
    names, counts, lengths, taus, plans_ = (
        codes.names,
        codes.keyframes,
        codes.lengths,
        codes.taus,
        codes.plans,
    )
    out = []
    for k, u, i, d, frames in found:
        matched: tuple[int, ...] = ()
        if frames:
            matched = tuple(clock.start(first, f) for f in frames)
        if u >= 0:
            m = lengths[u]
            out.append(
                ClassState(names[k], counts[k], matched, (i + 1) / m, d * m / ((i + 1) * SCALE), taus[u])
            )
        else:
            tau = plans_[k].tau
            out.append(ClassState(names[k], counts[k], matched, 0.0, tau, tau))
    out.sort(key=lambda c: c.class_name)
    return tuple(out)


class StreamProgress:
    """The progress of one stream's :class:`~daemon.recognizer.ClassStage`: :meth:`observe` after
    each push of frame ``number`` reads it if an index frame came (:func:`read`) into its
    :class:`ProgressStage`; the codes the end of the stream pushes are observed as they are
    (the stage's ``watch``); :meth:`end` when the stream's motion ended (flushed): what those gave
    and the stage's flush. :attr:`frame` is the frame number last observed."""

    def __init__(
        self,
        stage: ClassStage,
        rate: float,
        per_s: float = DEFAULT_PER_S,
        *,
        floor: float = FLOOR,
    ) -> None:
        if not 0 < floor <= 1:
            raise InputError(f"the floor must be a position in (0, 1], got {floor!r}")
        self.stage = stage
        self.events = ProgressStage(rate, per_s)
        self.floor = floor
        self.frame: int | None = None
        self._seen = 0
        self._pending: list[ProgressEvent] = []
        stage.watch = self._watch

    def observe(self, number: int) -> list[ProgressEvent]:
        """Frame ``number`` was pushed: its event, if its index frame's snapshot gives one."""
        core = self.stage.codes.core
        n = self.stage.codes.frames if core is None else core.n
        if n == self._seen:
            return []
        self._seen = n
        self.frame = number
        return self.events.push(number, read(self.stage, self.floor))

    def _watch(self, number: int) -> None:
        self._pending += self.observe(number)

    def end(self) -> list[ProgressEvent]:
        """The stream's motion ended: the events of its last codes, then the stage's flush."""
        out = self._pending + self.events.flush()
        self._pending = []
        self._seen = 0
        return out


def detect_progress(
    motion: Motion,
    library: Library,
    native_rate: float,
    *,
    settings: RecognitionSettings = DEFAULT_SETTINGS,
    stream: str = "",
    session: str = "",
    per_s: float = DEFAULT_PER_S,
    floor: float = FLOOR,
    bridge_s: float = DEFAULT_BRIDGE_S,
) -> list[Detection | ProgressEvent]:
    """The batch twin of a :class:`~daemon.recognizer.Recognizer` followed by
    :class:`StreamProgress`: every detection and progress event of ``motion`` in emission order
    (a push's progress event before its detections; at the end, the events of the codes the end
    gives and the flush's, then the last detections). Frames missing from ``motion`` are taken as
    :func:`daemon.recognizer.detect` takes them (:func:`~daemon.frames.motion_runs`)."""
    return [
        e
        for run in motion_runs(motion, native_rate, bridge_s)
        for e in detect_progress_positions(
            joint_positions(run),
            run.frames,
            library,
            native_rate,
            settings=settings,
            stream=stream,
            session=session,
            per_s=per_s,
            floor=floor,
        )
    ]


def detect_progress_positions(
    positions: FloatArray,
    numbers: IntArray,
    library: Library,
    native_rate: float,
    *,
    settings: RecognitionSettings = DEFAULT_SETTINGS,
    stream: str = "",
    session: str = "",
    per_s: float = DEFAULT_PER_S,
    floor: float = FLOOR,
) -> list[Detection | ProgressEvent]:
    """:func:`detect_progress` of one run of standard joint positions shape ``(N, 26, 3)`` with
    frame numbers ``(N,)`` (consecutive), as :func:`daemon.recognizer.detect_positions` reads them:
    the codes a push of the stream gives through the class stage one by one, those its end gives
    in its flush."""
    if len(positions) == 0:
        return []
    if np.any(np.diff(numbers) != 1):
        raise InputError("frame numbers must be consecutive (daemon.frames.motion_runs bridges gaps)")
    codes, stage = recording_stage(positions, library, native_rate, settings, stream=stream, session=session)
    clock = stage.clock
    follow = StreamProgress(stage, native_rate, per_s, floor=floor)
    first, last = int(numbers[0]), int(numbers[-1])
    pushed = [j for j in range(len(codes)) if clock.start(first, j + clock.lead) <= last]
    stage.start(first)
    out: list[Detection | ProgressEvent] = []
    for j in pushed:
        number = clock.start(first, j + clock.lead)
        detections = stage.push(number, codes[j])
        out += follow.observe(number)
        out += detections
    detections = stage.flush(last, codes[len(pushed) :])
    return out + follow.end() + detections
