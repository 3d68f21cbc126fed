"""Many streams' recognisers in one: each :meth:`RecognizerBank.push` advances any number of streams
by one frame each in vectorised passes (DESIGN.md, "Scale").

Per call: the frames are checked as :class:`~daemon.recognizer.Recognizer` checks them (a bad frame
is reported as ``(stream, FrameError)`` and changes nothing); the channel frames of all streams whose
skeletons share one topology go through forward kinematics together (:class:`_KinematicGroup`: the
node order and dof layout are shared, each stream's bone offsets, axes, orientation, root position
and unit are a column of per-stream arrays); then the 39 features of every stream of one frame rate
come out of one evaluation of the compiled feature program on arrays with a stream axis
(:class:`_FeatureGroup`: per-stream thresholds, a per-stream ring of recent poses and velocity
points, per-stream hysteresis). Streams near their start (whose velocity windows still reach before
the first frame) run their own :class:`~daemon.features.FeatureStream` until it is steady, and a
stream that leaves is flushed through one resumed from its ring, so the edges are computed exactly as
the one-stream recogniser computes them. After the features, each stream keeps every k-th vector and
advances its own :class:`~daemon.recognizer.CodeRecognizer` (Python, once per index-rate frame);
the DTW windows due in one push are confirmed in one pass per class over the windows of all
streams side by side (:func:`~daemon.recognizer.confirm_many`).

Every operation is elementwise with the same operands in the same order as the one-stream path (the
features' compiled program runs on Python floats there and on arrays here with the same bits), so
the detections equal those of one :class:`~daemon.recognizer.Recognizer` per stream bit for bit:
same ids (with the same session), ranges, costs and ``emitted_at_frame``.

Bounded state: per stream a ring of ``keep`` poses (32 at 120 Hz) and the code recogniser's bounded
rings; the arrays hold one column per stream slot, freed slots are reused, and their capacity is
the most streams held at once (rounded up to a power of two, at least 8).

Pure: numpy in, dataclasses out; no I/O.
"""

from __future__ import annotations

import uuid
from collections.abc import Collection, Hashable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from daemon.features import _ARRAY_OPS, _FLOAT_OPS, FeatureState, FeatureStream, _program, decimation_factor
from daemon.library import Library
from daemon.recognizer import (
    ClassPlan,
    CodeRecognizer,
    Detection,
    Due,
    FrameError,
    check_native_rate,
    check_number,
    check_positions,
    confirm_many,
    frame_values,
    joint_order,
    make_detection,
    non_finite_channels,
    non_finite_pose,
    plans,
    vector_code,
)
from daemon.types import DEFAULT_MAX_GAP_S, FloatArray
from replay import JOINT_NAMES, KinematicModel, Skeleton
from replay.kinematics import _qmul, _qrot

IntpArray = npt.NDArray[np.intp]
Frame = tuple[str, int, npt.ArrayLike]
"""One stream's next frame: (stream, frame number, channels ``(C,)`` or joint positions ``(J, 3)``)."""

_MIN_CAPACITY = 8


@dataclass(frozen=True)
class BankResult:
    """What one :meth:`RecognizerBank.push` gave: the detections emitted (in the order of the frames
    pushed, each stream's in the order its recogniser emits them) and the refused frames as
    (stream, :class:`FrameError`), in the order of the frames."""

    detections: tuple[Detection, ...]
    errors: tuple[tuple[str, FrameError], ...]


class _Slots:
    """Column indices of per-stream arrays: ``take`` a free one, ``give`` it back; ``capacity``
    doubles when all are taken."""

    def __init__(self) -> None:
        self.capacity = 0
        self.free: list[int] = []
        self.used = 0

    def take(self) -> tuple[int, bool]:
        """A free slot, and whether the capacity grew (the arrays must then be grown)."""
        grew = not self.free
        if grew:
            old = self.capacity
            self.capacity = max(_MIN_CAPACITY, 2 * old)
            self.free = list(range(self.capacity - 1, old - 1, -1))
        self.used += 1
        return self.free.pop(), grew

    def give(self, slot: int) -> None:
        self.used -= 1
        self.free.append(slot)


def _grow(a: npt.NDArray[Any], capacity: int, axis: int) -> npt.NDArray[Any]:
    """``a`` with its ``axis`` extended (zeros) to ``capacity``."""
    pad = [(0, 0)] * a.ndim
    pad[axis] = (0, capacity - a.shape[axis])
    return np.pad(a, pad)


# ------------------------------------------------------------------------------ forward kinematics


def topology(model: KinematicModel) -> Hashable:
    """What the stacked forward kinematics of ``model``'s skeleton shares with others: node count,
    channel layout, the rotation dofs per slot, the root translation channels, the hierarchy's levels
    and the standard joints' nodes. Skeletons with equal keys differ only in their per-stream
    constants (bone offsets and axes, root orientation and position, length unit)."""
    joints = model._joint_nodes
    return (
        model.n_nodes,
        len(model.skeleton.channel_names),
        tuple((tuple(nodes.tolist()), tuple(chans.tolist())) for nodes, chans, _ in model._slots),
        tuple(model._translation),
        tuple((tuple(nodes.tolist()), tuple(parents.tolist())) for nodes, parents in model._levels),
        None if joints is None else tuple(joints.tolist()),
    )


class _KinematicGroup:
    """Forward kinematics of streams whose skeletons share one :func:`topology`, one frame each,
    stream axis last: the operations of :meth:`KinematicModel.positions` (frames axis last there)
    with each stream's constants as a column of arrays shaped ``(..., capacity)``."""

    def __init__(self, model: KinematicModel) -> None:
        self.width = len(model.skeleton.channel_names)
        self.n_nodes = model.n_nodes
        self.structure = [(nodes, chans) for nodes, chans, _ in model._slots]
        self.translation = list(model._translation)
        self.levels = list(model._levels)
        assert model._joint_nodes is not None
        self.joint_nodes = model._joint_nodes
        self.slots = _Slots()
        self.axes = [np.zeros((3, len(nodes), 0)) for nodes, _ in self.structure]  # (3, n, cap) per slot
        self.offsets = np.zeros((3, self.n_nodes, 0))  # (3, nodes, cap)
        self.orientation = np.zeros((4, 0))  # (4, cap)
        self.root = np.zeros((3, 0))  # (3, cap)
        self.cm = np.zeros(0)  # (cap,)

    def add(self, model: KinematicModel) -> int:
        slot, grew = self.slots.take()
        if grew:
            cap = self.slots.capacity
            self.axes = [_grow(a, cap, 2) for a in self.axes]
            self.offsets = _grow(self.offsets, cap, 2)
            self.orientation = _grow(self.orientation, cap, 1)
            self.root = _grow(self.root, cap, 1)
            self.cm = _grow(self.cm, cap, 0)
        for mine, (_, _, axes) in zip(self.axes, model._slots, strict=True):
            mine[:, :, slot] = axes[:, :, 0]
        self.offsets[:, :, slot] = model._offsets[:, :, 0]
        self.orientation[:, slot] = model._orientation
        self.root[:, slot] = model._root_position
        self.cm[slot] = 2.54 / model.skeleton.length_unit
        return slot

    def remove(self, slot: int) -> None:
        self.slots.give(slot)

    def joints(self, channels: FloatArray, slots: IntpArray) -> FloatArray:
        """Standard joints in cm, shape ``(S, 26, 3)``, of ``channels`` shape ``(S, C)`` (finite), stream
        ``i`` with the constants of slot ``slots[i]``. Rotations are four component arrays shape
        ``(nodes, S)``; each step is the elementwise operation of :meth:`KinematicModel.positions_frame`
        (``_qmul``, ``_qrot``) on whole levels of the hierarchy."""
        n = channels.shape[0]
        half = 0.5 * channels.T  # (C, S)
        cos, sin = np.cos(half), np.sin(half)
        rot = np.zeros((4, self.n_nodes, n))
        rot[0] = 1.0
        for slot, ((nodes, chans), axes) in enumerate(zip(self.structure, self.axes, strict=True)):
            s = sin[chans]
            u = axes[:, :, slots]  # (3, n, S)
            elementary = (cos[chans], s * u[0], s * u[1], s * u[2])
            if slot == 0:
                rot[:, nodes] = elementary
            else:
                rot[:, nodes] = _qmul(elementary, rot[:, nodes])
        rot[:, 0] = _qmul(self.orientation[:, slots], rot[:, 0])
        pos = np.empty((3, self.n_nodes, n))
        pos[:, 0] = self.root[:, slots]
        for axis, chan in self.translation:
            pos[axis, 0] += channels[:, chan]
        offsets = self.offsets[:, :, slots]  # (3, nodes, S)
        for nodes, parents in self.levels:
            r = _qmul(rot[:, parents], rot[:, nodes])
            rot[:, nodes] = r
            d = _qrot(r, offsets[:, nodes])
            pp = pos[:, parents]
            pos[:, nodes] = (pp[0] + d[0], pp[1] + d[1], pp[2] + d[2])
        with np.errstate(over="ignore", invalid="ignore"):  # a huge channel: refused as non-finite
            pos *= self.cm[slots]
        out: FloatArray = pos[:, self.joint_nodes].transpose(2, 1, 0)
        return out


# ------------------------------------------------------------------------------------- features


class _FeatureGroup:
    """The steady streams of one frame rate: per slot a ring of the last ``keep`` poses (flat
    components, then velocity points), ``ring`` shape ``(capacity, keep, 3J + 3K)``; frames pushed
    ``count`` and the last code ``previous`` shape ``(capacity,)``; thresholds shape
    ``(capacity, T)`` (those that scale with the body; the absolute ones are shared)."""

    def __init__(self, frame_rate: float) -> None:
        self.frame_rate = frame_rate
        self.program = _program(JOINT_NAMES, frame_rate)
        probe = FeatureStream(JOINT_NAMES, frame_rate)
        self.keep = probe.keep
        self.latency = probe.latency
        self.steady_after = probe.steady_after
        self.n_rows = 3 * len(JOINT_NAMES)
        self.width = self.n_rows + 3 * len(self.program.trajectories)
        self.windows = [
            (big_l - h + 1, 1 - h, self.n_rows + first, self.n_rows + end, frame_rate / big_l)
            for big_l, h, first, end in self.program.windows
        ]
        shared = self.program.thresholds(_UNIT_LENGTHS)
        self.scaled = [k for k, t in enumerate(shared) if not isinstance(t, tuple)]
        self.shared: list[Any] = [t if isinstance(t, tuple) else None for t in shared]
        self.slots = _Slots()
        self.ring = np.zeros((0, self.keep, self.width))
        self.count = np.zeros(0, dtype=np.int64)
        self.previous = np.zeros(0, dtype=np.int64)
        self.thresholds = np.zeros((0, len(self.scaled)))

    def add(self, state: FeatureState) -> int:
        """Take over a stream (steady: ``n >= steady_after``) from its state."""
        slot, grew = self.slots.take()
        if grew:
            cap = self.slots.capacity
            self.ring = _grow(self.ring, cap, 0)
            self.count = _grow(self.count, cap, 0)
            self.previous = _grow(self.previous, cap, 0)
            self.thresholds = _grow(self.thresholds, cap, 0)
        base = state.n - len(state.history)
        for f, (rows, points) in enumerate(state.history, base):
            self.ring[slot, f % self.keep, : self.n_rows] = rows
            self.ring[slot, f % self.keep, self.n_rows :] = points
        self.count[slot] = state.n
        self.previous[slot] = state.previous
        self.thresholds[slot] = [state.thresholds[k] for k in self.scaled]
        return slot

    def state(self, slot: int, thresholds: tuple[Any, ...]) -> FeatureState:
        """The state of the stream in ``slot`` as its :class:`FeatureStream` would hold it."""
        n = int(self.count[slot])
        history = tuple(
            (
                self.ring[slot, f % self.keep, : self.n_rows].tolist(),
                self.ring[slot, f % self.keep, self.n_rows :].tolist(),
            )
            for f in range(max(0, n - self.keep), n)
        )
        return FeatureState(n, n - self.latency, int(self.previous[slot]), thresholds, history)

    def remove(self, slot: int) -> None:
        self.slots.give(slot)

    def push_one(self, pose: FloatArray, slot: int, thresholds: tuple[Any, ...]) -> int:
        """:meth:`push` of one stream on Python floats, as :class:`FeatureStream` computes it (fewer
        operations than the array pass for a few streams; the same bits). ``pose`` shape ``(J, 3)``."""
        keep, n_rows, ring = self.keep, self.n_rows, self.ring[slot]
        rows: list[float] = pose.ravel().tolist()
        n = int(self.count[slot])
        ring[n % keep, :n_rows] = rows
        ring[n % keep, n_rows:] = self.program.points(rows)
        self.count[slot] = n + 1
        t = n - self.latency
        held: list[list[float]] = []
        for top, bottom, _, _, _ in self.windows:
            held += [ring[(t + top) % keep, n_rows:].tolist(), ring[(t + bottom) % keep, n_rows:].tolist()]
        smoothed = self.program.interior(held)
        at = ring[t % keep, :n_rows].tolist()
        try:
            f1, f2 = self.program.frame(at, smoothed, thresholds, *_FLOAT_OPS)
        except ZeroDivisionError:  # a degenerate pose: as FeatureStream, evaluate on arrays (to nan)
            with np.errstate(all="ignore"):
                columns, velocities = list(np.array(at)[:, None]), list(np.array(smoothed)[:, None])
                a1, a2 = self.program.frame(columns, velocities, thresholds, *_ARRAY_OPS)
            f1, f2 = int(a1[0]), int(a2[0])
        code = int(f2 | (int(self.previous[slot]) & f1))
        self.previous[slot] = code
        return code

    def push(self, poses: FloatArray, slots: IntpArray) -> list[int]:
        """Add one pose per stream, ``poses`` shape ``(S, J, 3)`` for the streams in ``slots`` shape
        ``(S,)``; the code (bit k = feature k) each emits, for its frame ``latency`` frames back."""
        keep = self.keep
        rows = poses.reshape(len(slots), self.n_rows)  # (S, 3J)
        n = self.count[slots]
        at = n % keep
        with np.errstate(all="ignore"):
            points = np.array(self.program.points(list(np.ascontiguousarray(rows.T))))  # (3K, S)
            self.ring[slots, at, : self.n_rows] = rows
            self.ring[slots, at, self.n_rows :] = points.T
            self.count[slots] = n + 1
            t = n - self.latency  # the frame whose vector is now final
            pose = np.ascontiguousarray(self.ring[slots, t % keep, : self.n_rows].T)  # (3J, S)
            velocities = [
                (
                    self.ring[slots, (t + top) % keep, first:end]
                    - self.ring[slots, (t + bottom) % keep, first:end]
                )
                * scale
                for top, bottom, first, end, scale in self.windows
            ]
            smoothed = np.ascontiguousarray(np.concatenate(velocities, axis=1).T)  # (3K, S)
            scaled = self.thresholds[slots].T  # (T, S)
            thresholds = list(self.shared)
            for row, k in enumerate(self.scaled):
                thresholds[k] = scaled[row]
            f1, f2 = self.program.frame(list(pose), list(smoothed), thresholds, *_ARRAY_OPS)
        code = f2 | (self.previous[slots] & f1)  # the hysteresis, all features at once
        self.previous[slots] = code
        out: list[int] = code.tolist()
        return out


class _UnitLengths:
    """Body lengths of 1, to learn which thresholds scale with the body (those are floats)."""

    def get(self, reference: str) -> float:
        return 1.0


_UNIT_LENGTHS: Any = _UnitLengths()


# --------------------------------------------------------------------------------------- streams


class _Stream:
    """One stream's own state: frame numbers, its input (a kinematic group slot, or a joint order),
    its features (a young :class:`FeatureStream`, or a feature group slot), decimation and codes."""

    __slots__ = (
        "codes",
        "feature_slot",
        "features",
        "first",
        "group",
        "joint_order",
        "kinematic_slot",
        "last",
        "model",
        "name",
        "rate",
        "seen",
        "session",
        "step",
        "thresholds",
        "width",
    )

    def __init__(self, name: str, session: str, rate: float, step: int, codes: CodeRecognizer) -> None:
        self.name = name
        self.session = session
        self.rate = rate
        self.step = step
        self.codes = codes
        self.first: int | None = None
        self.last: int | None = None
        self.seen = 0
        self.group: _KinematicGroup | None = None
        self.model: KinematicModel | None = None
        self.kinematic_slot = -1
        self.joint_order: IntpArray | None = None
        self.width = 0
        self.features: FeatureStream | None = FeatureStream(JOINT_NAMES, rate)
        self.feature_slot = -1
        self.thresholds: tuple[Any, ...] = ()


class RecognizerBank:
    """Recognisers of many streams, advanced together: :meth:`add` a stream (channels of a skeleton,
    or joint positions in a named order, at its native rate), :meth:`push` one frame of each of any
    number of streams, :meth:`remove` a stream (its last detections). Equal, stream by stream, to one
    :class:`~daemon.recognizer.Recognizer` per stream with the same settings and session.

    ``vector_from``: the fewest streams of one skeleton topology (forward kinematics) or of one
    frame rate (features) a push evaluates in one array pass; fewer are evaluated one by one on
    Python floats (the array pass has a fixed cost of about 700 array operations). Both give the
    same bits."""

    def __init__(
        self,
        library: Library,
        *,
        max_gap_s: float = DEFAULT_MAX_GAP_S,
        classes: Collection[str] | None = None,
        vector_from: int = 8,
    ) -> None:
        if vector_from < 1:
            raise ValueError(f"vector_from must be at least 1, got {vector_from}")
        self.library = library
        self._vector_from = vector_from
        self._plans: tuple[ClassPlan, ...] = plans(library, classes, max_gap_s=max_gap_s)
        self._streams: dict[str, _Stream] = {}
        self._kinematics: dict[Hashable, _KinematicGroup] = {}
        self._features: dict[float, _FeatureGroup] = {}

    @property
    def streams(self) -> tuple[str, ...]:
        """The streams in the bank, in the order they were added."""
        return tuple(self._streams)

    @property
    def plans(self) -> tuple[ClassPlan, ...]:
        return self._plans

    @property
    def array_bytes(self) -> int:
        """Bytes of the per-stream arrays (kinematic constants, feature rings): they grow with the
        most streams held at once, never with the frames pushed."""
        total = 0
        for k in self._kinematics.values():
            total += sum(a.nbytes for a in (*k.axes, k.offsets, k.orientation, k.root, k.cm))
        for f in self._features.values():
            total += f.ring.nbytes + f.count.nbytes + f.previous.nbytes + f.thresholds.nbytes
        return total

    def add(
        self,
        stream: str,
        native_rate: float,
        *,
        skeleton: Skeleton | None = None,
        joint_names: Sequence[str] | None = None,
        session: str | None = None,
    ) -> None:
        """Add ``stream``: frames of AMC-style channels of ``skeleton`` (as
        :meth:`Recognizer.for_skeleton`) or of joint positions in the order ``joint_names`` (as
        :meth:`Recognizer.for_positions`); ``session`` as :class:`Recognizer`'s (None: a new one).
        ValueError for a stream already in the bank, both or neither input, or a bad rate."""
        if stream in self._streams:
            raise ValueError(f"stream {stream!r} is already in the bank")
        if (skeleton is None) == (joint_names is None):
            raise ValueError("give a skeleton (channels) or the joint names (positions), not both")
        check_native_rate(native_rate)
        rate = float(native_rate)
        step = decimation_factor(rate, self.library.rate)
        s = _Stream(
            stream,
            uuid.uuid4().hex if session is None else session,
            rate,
            step,
            CodeRecognizer(self._plans, self.library.rate),
        )
        if skeleton is not None:
            model = KinematicModel(skeleton)
            model.joints(np.zeros((len(skeleton.node_names), 3)))  # the standard joints exist, or an error
            key = topology(model)
            group = self._kinematics.get(key)
            if group is None:
                group = self._kinematics[key] = _KinematicGroup(model)
            s.group, s.kinematic_slot, s.width, s.model = group, group.add(model), group.width, model
        else:
            assert joint_names is not None
            s.joint_order = joint_order(joint_names)
            s.width = len(joint_names)
        if rate not in self._features:
            self._features[rate] = _FeatureGroup(rate)
        self._streams[stream] = s

    def remove(self, stream: str) -> list[Detection]:
        """Take ``stream`` out of the bank: its remaining detections (as :meth:`Recognizer.flush`).
        KeyError if it is not in the bank."""
        s = self._streams.pop(stream)
        if s.group is not None:
            s.group.remove(s.kinematic_slot)
        if s.features is None:  # steady: resume its feature stream from the ring, then flush that
            group = self._features[s.rate]
            s.features = FeatureStream(JOINT_NAMES, s.rate)
            s.features.resume(group.state(s.feature_slot, s.thresholds))
            group.remove(s.feature_slot)
        last = s.last
        out = [d for code in _codes(s.features.flush()) for d in self._vector(s, code, last or 0)]
        found = s.codes.flush()
        if last is not None:
            out += self._detections(s, found, last)
        return out

    def push(self, frames: Sequence[Frame]) -> BankResult:
        """Advance each stream named in ``frames`` by its frame: the detections and the refused frames
        (a refused frame changes nothing). ValueError (nothing done) if a stream is not in the bank or
        has more than one frame."""
        names = [f[0] for f in frames]
        if len(set(names)) != len(names):
            raise ValueError("at most one frame per stream in one push")
        unknown = [n for n in names if n not in self._streams]
        if unknown:
            raise ValueError(f"streams not in the bank: {', '.join(map(repr, unknown))}")
        errors: dict[int, FrameError] = {}
        poses: dict[int, FloatArray] = {}  # standard joints (26, 3) by position in frames
        numbers: dict[int, int] = {}
        channel_frames: dict[int, list[tuple[int, FloatArray]]] = {}
        groups: dict[int, _KinematicGroup] = {}
        for i, (name, number, frame) in enumerate(frames):
            s = self._streams[name]
            try:
                numbers[i] = n = check_number(number, s.last, name)
                values = frame_values(n, frame, name)
                if s.group is not None:
                    if values.shape != (s.width,):
                        raise FrameError(
                            f"frame {n}: {s.width} channels expected, got shape {values.shape}",
                            "shape",
                            stream=name,
                        )
                    channel_frames.setdefault(id(s.group), []).append((i, values))
                    groups[id(s.group)] = s.group
                else:
                    check_positions(n, values, s.width, name)
                    poses[i] = values[s.joint_order]
            except FrameError as e:
                errors[i] = e
        for key, items in channel_frames.items():
            self._kinematic_pass(groups[key], items, frames, numbers, poses, errors)
        good = sorted(poses)
        if good:
            stacked = np.stack([poses[i] for i in good])
            finite: list[bool] = np.all(np.isfinite(stacked), axis=(1, 2)).tolist()
            for i, ok in zip(good, finite, strict=True):
                if not ok:
                    errors[i] = non_finite_pose(numbers[i], frames[i][0])
                    del poses[i]
        emitted = self._features_pass(frames, poses)
        index_frames: list[tuple[_Stream, int, list[Due]]] = []
        for i in sorted(poses):
            s = self._streams[frames[i][0]]
            number = numbers[i]
            if s.first is None:
                s.first = number
            s.last = number
            code = emitted.get(i)
            if code is not None and self._kept(s):
                index_frames.append((s, number, s.codes.advance(code)))
        detections = self._confirm(index_frames)
        return BankResult(tuple(detections), tuple((frames[i][0], errors[i]) for i in sorted(errors)))

    def _confirm(self, index_frames: list[tuple[_Stream, int, list[Due]]]) -> list[Detection]:
        """Every window due in this push, one DP pass per class over all streams' windows
        (:func:`~daemon.recognizer.confirm_many`), then each stream's detections in order."""
        by_class: dict[int, list[npt.NDArray[np.uint64]]] = {}
        for _, _, due in index_frames:
            for d in due:
                by_class.setdefault(d.track, []).append(d.codes)
        found = {k: iter(confirm_many(self._plans[k], windows)) for k, windows in by_class.items()}
        out: list[Detection] = []
        for s, number, due in index_frames:
            settled = s.codes.settle(due, [next(found[d.track]) for d in due])
            out += self._detections(s, settled, number)
        return out

    def _kinematic_pass(
        self,
        group: _KinematicGroup,
        items: list[tuple[int, FloatArray]],
        frames: Sequence[Frame],
        numbers: dict[int, int],
        poses: dict[int, FloatArray],
        errors: dict[int, FrameError],
    ) -> None:
        """Forward kinematics of a group's frames ``items`` (position in ``frames``, channels)."""
        channels = np.stack([v for _, v in items])  # (S, C)
        finite = np.all(np.isfinite(channels), axis=1)
        if not finite.all():
            flags: list[bool] = finite.tolist()
            for (i, _), ok in zip(items, flags, strict=True):
                if not ok:
                    errors[i] = non_finite_channels(numbers[i], frames[i][0])
            items = [item for item, ok in zip(items, flags, strict=True) if ok]
            channels = channels[finite]
            if not items:
                return
        streams = [self._streams[frames[i][0]] for i, _ in items]
        if len(items) < self._vector_from:  # one at a time on Python floats: fewer operations
            for s, (i, values) in zip(streams, items, strict=True):
                assert s.model is not None
                with np.errstate(over="ignore", invalid="ignore"):
                    poses[i] = s.model.joints(s.model.positions_frame(values, "cm"))
            return
        joints = group.joints(channels, np.array([s.kinematic_slot for s in streams], dtype=np.intp))
        for k, (i, _) in enumerate(items):
            poses[i] = joints[k]

    def _features_pass(self, frames: Sequence[Frame], poses: dict[int, FloatArray]) -> dict[int, int]:
        """Push each pose to its stream's features: the codes emitted, by position in ``frames``."""
        out: dict[int, int] = {}
        steady: dict[float, list[int]] = {}
        for i in sorted(poses):
            s = self._streams[frames[i][0]]
            young = s.features
            if young is None:
                steady.setdefault(s.rate, []).append(i)
                continue
            for code in _codes(young.push(poses[i])):
                out[i] = code
            group = self._features[s.rate]
            if young.frames >= group.steady_after:
                state = young.state()
                s.thresholds = state.thresholds
                s.feature_slot = group.add(state)
                s.features = None
        for rate, items in steady.items():
            group = self._features[rate]
            if len(items) < self._vector_from:
                for i in items:
                    s = self._streams[frames[i][0]]
                    out[i] = group.push_one(poses[i], s.feature_slot, s.thresholds)
                continue
            slots = np.array([self._streams[frames[i][0]].feature_slot for i in items], dtype=np.intp)
            stacked = np.stack([poses[i] for i in items])
            for i, code in zip(items, group.push(stacked, slots), strict=True):
                out[i] = code
        return out

    def _vector(self, s: _Stream, code: int, number: int) -> list[Detection]:
        return self._detections(s, s.codes.push(code), number) if self._kept(s) else []

    @staticmethod
    def _kept(s: _Stream) -> bool:
        """Whether the stream's next feature vector is one the decimation keeps (every k-th)."""
        t = s.seen
        s.seen += 1
        return t % s.step == 0

    def _detections(self, s: _Stream, found: Sequence[tuple[ClassPlan, Any]], number: int) -> list[Detection]:
        first = s.first
        assert first is not None
        return [make_detection(s.session, s.name, p, m, first, s.step, number) for p, m in found]


def _codes(vectors: Sequence[npt.NDArray[np.bool_]]) -> list[int]:
    return [vector_code(v) for v in vectors]
