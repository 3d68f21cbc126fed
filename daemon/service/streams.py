"""The service's stream table: decoded wire messages in, detections out (no sockets, no asyncio).

A stream exists once its skeleton arrived: :meth:`StreamTable.skeleton` makes (or, for a changed
skeleton, remakes) its recogniser in the :class:`~daemon.bank.RecognizerBank`; :meth:`StreamTable.pose`
checks the sequence number and queues the pose (:meth:`StreamTable.frame`: each subject of a frame
message alike); :meth:`StreamTable.tick` takes one queued pose of
every stream that has one into one bank push. Everything refused or dropped is counted by reason in
:attr:`StreamTable.counts`.

A stream's life (``protocols/README.md``). A source that restarts numbers its poses from its start
again: a new *run*. A run is told by the source's ``epoch`` (a random id in its skeleton and poses):
a skeleton or pose with another epoch than the stream's begins a new run (the stream's motion ends,
its recogniser starts anew at the run's first pose), and one of an epoch already replaced is refused
(``stale_epoch``). A source that says no epoch begins a new run when its sequence number goes back by
more than a second of frames; less is ``out_of_order``, the same ``duplicate``. A sequence number
further ahead than the time since the stream's last pose allows (twice its rate, plus a second) is
refused (``implausible``), not taken as a gap, unless the pose after it follows on from it (a real
jump: a gap in a source faster than its announced rate), which is then taken after the gap.

Frame numbers are sequence numbers (:mod:`daemon.frames`). The recogniser takes a motion's frames
consecutively; a stream's sequence numbers may have gaps (poses lost on the way, or dropped here
when its queue is full). A gap of at most ``service.bridge_s`` (in the stream's frames) is bridged:
the missing frames are interpolated between the last frame fed and the pose after the gap
(:func:`daemon.frames.bridge`; channel angles along the shorter arc) and fed before it, so every
later frame, and every index frame, is the one it would have been without the gap. A longer gap ends
the stream's motion: its recogniser is flushed and begins again at the new pose. So a stream gives
the detections of ``mocapd detect`` on the same frames (:func:`daemon.frames.bridged_runs`).

Behaviour boundaries. With a segmentation method (``segmentation`` of the config), every channel
stream (an ASF skeleton's, or a BVH rig's: the channel rows, not the standard joints its recogniser
takes) whose id matches one of its patterns also goes through an online segmenter
(:func:`daemon.behaviours.online_segmenter` on :class:`daemon.behaviours.RotationStream`'s joint
rotations), fed the frames its recogniser took; a cut comes out as a :class:`BoundaryMessage` at the
sequence number where the new behaviour starts. A long gap, a changed skeleton or the stream's end
starts the segmenter anew, as it does the recogniser.
"""

from __future__ import annotations

import dataclasses
import fnmatch
import itertools
import uuid
from collections import Counter, deque
from collections.abc import Callable, Collection, Sequence
from dataclasses import dataclass, field
from typing import Literal, NamedTuple, TypeVar

import msgpack
import numpy as np
import numpy.typing as npt

from daemon.bank import RecognizerBank
from daemon.behaviours import Boundary, JointRotations, PcaSegmenter, PpcaSegmenter, RigRotations
from daemon.behaviours import online_segmenter as make_segmenter
from daemon.config import ProgressConfig, RecognizerConfig, SegmentationConfig, ServiceConfig
from daemon.errors import InputError, MocapdError, printable
from daemon.frames import bridge, bridge_frames
from daemon.library import Library
from daemon.progress import ProgressEvent, StreamProgress
from daemon.recognizer import Detection, Recognizer
from protocols.messages import (
    MAX_SEGMENT_DETECTIONS,
    BoundaryMessage,
    ClassProgress,
    DetectionMessage,
    EndMessage,
    FrameMessage,
    PoseMessage,
    ProgressMessage,
    SegmentDetection,
    SkeletonMessage,
    WireError,
    decode,
    encode,
    is_id,
)
from replay import JOINT_NAMES, MocapFormatError, Skeleton, parse_asf
from replay.amc import DEG
from replay.bvh import parse_bvh_hierarchy
from replay.kinematics import y_up
from replay.rigs import BUILT_IN, BvhPoses, RigMap, RigPlan, names_plan, standard_joints

K = TypeVar("K")
V = TypeVar("V")


class Queued(NamedTuple):
    """One subject of a frame message as the table queues it: a pose message's fields (a pose
    message itself is queued as it is), made for a fraction of a frozen dataclass's cost."""

    stream: str
    seq: int
    time: float
    positions: npt.NDArray[np.float32] | None
    channels: npt.NDArray[np.float64] | None
    epoch: str | None


Pose = PoseMessage | Queued
"""A pose the table queues."""

SKELETONS_KEPT = 64
"""How many announced ASF texts (and BVH hierarchies) the table keeps parsed."""


def _remembered(cache: dict[K, V], key: K, make: Callable[[], V]) -> V:
    """``cache[key]``, made by ``make`` if missing, kept as the most recently used of the last
    :data:`SKELETONS_KEPT` keys (a dict keeps its insertion order: the first is the oldest)."""
    value = cache.pop(key, None)
    if value is None:
        value = make()
    cache[key] = value
    if len(cache) > SKELETONS_KEPT:
        cache.pop(next(iter(cache)))
    return value


class Refused(MocapdError):
    """A message the table does not take: ``reason``, the counter it is refused under, and
    ``detail``, a sentence; ``str``: the sentence."""

    def __init__(self, reason: str, detail: str) -> None:
        super().__init__(reason)
        self.detail = detail

    def _reason(self) -> str:
        return printable(self.detail)


@dataclass(frozen=True)
class _Cut:
    """A cut of a stream's segmenter: the frame the new behaviour begins at, the frame at which the
    cut was known, the segmenter's boundary, and the behaviour that ended (its first frame, and the
    detections published inside it)."""

    frame: int
    known: int
    boundary: Boundary
    start: int
    detections: tuple[SegmentDetection, ...]


class _Segmenting:
    """A stream's behaviour segmentation: its joint rotations (an ASF skeleton's bones, or a BVH
    rig's joints standing for them), the online segmenter, the frame number of the segmenter's
    first frame and of the current behaviour's, and the latest detections published since that
    began (at most :data:`~protocols.messages.MAX_SEGMENT_DETECTIONS`)."""

    def __init__(
        self, rotations: JointRotations | RigRotations, method: Literal["pca", "ppca"], rate: float
    ) -> None:
        self.rotations = rotations.stream()
        self.segmenter: PcaSegmenter | PpcaSegmenter = make_segmenter(rate, method)
        self.first: int | None = None
        self.begins: int | None = None
        self.detections: deque[SegmentDetection] = deque(maxlen=MAX_SEGMENT_DETECTIONS)

    def detected(self, d: DetectionMessage) -> None:
        """A detection of the stream was published."""
        self.detections.append(SegmentDetection(d.class_name, d.start_frame, d.end_frame))

    def push(self, frame: int, channels: np.ndarray) -> list[_Cut]:
        """Frame ``frame``'s channels: the cuts that became known."""
        if self.first is None:
            self.first = self.begins = frame
        return self._cuts(self.first, self.segmenter.push(self.rotations.frame(channels)))

    def restart(self) -> list[_Cut]:
        """The stream's motion ends: what the segmenter still gives, then a fresh one."""
        first = self.first
        cuts = [] if first is None else self._cuts(first, self.segmenter.flush())
        self.rotations.flush()
        self.first = self.begins = None
        self.detections.clear()
        return cuts

    def _cuts(self, first: int, found: list[Boundary]) -> list[_Cut]:
        out = []
        for b in found:
            frame = first + b.frame
            start = first if self.begins is None else self.begins
            inside = tuple(d for d in self.detections if start <= d.start_frame and d.end_frame < frame)
            out.append(_Cut(frame, first + b.emitted, b, start, inside))
            self.begins = frame
            kept = [d for d in self.detections if d.end_frame >= frame]
            self.detections.clear()
            self.detections.extend(kept)
        return out


@dataclass
class _Stream:
    """One stream: its announcement, the skeleton parsed from it (channel streams), the last
    sequence number received and the last fed to the recogniser (and its values), the poses
    waiting, and the frames bridging a gap before the first of them."""

    announced: SkeletonMessage
    skeleton: Skeleton | None
    angles: np.ndarray | None
    """The channels converted from degrees (None: none)."""
    turns: np.ndarray | None = None
    """The channels that are angles, bridged along the shorter arc (None: positions)."""
    last_received: int | None = None
    received: int = 0
    last_fed: int | None = None
    last_values: np.ndarray | None = None
    """The values of frame :attr:`last_fed` (a gap after it is bridged from them)."""
    queue: deque[Pose] = field(default_factory=deque)
    arrived: deque[float] = field(default_factory=deque)
    """When each queued pose was taken in (the ``now`` of :meth:`StreamTable.pose`), in step with
    :attr:`queue`."""
    filling: deque[tuple[int, float, float, np.ndarray, np.ndarray | None]] = field(default_factory=deque)
    """The interpolated frames (frame number, time, arrival, values, channels) of a gap before
    ``queue[0]`` (channels: a segmented BVH stream's, else None)."""
    last_channels: np.ndarray | None = None
    """A segmented BVH stream's channel row of frame :attr:`last_fed` (degrees: what its
    segmentation takes, where the recogniser takes the rig's standard joints)."""
    times: np.ndarray = field(default_factory=lambda: np.zeros(1))
    arrivals: np.ndarray = field(default_factory=lambda: np.zeros(1))
    """When the pose of each recent frame was taken in, a ring like :attr:`times` (the source's
    timestamps)."""
    width: int = 0
    seen: float = 0.0
    generation: int = 0
    segmenting: _Segmenting | None = None
    epoch: str | None = None
    """The source's run (its epoch) whose poses are taken."""
    retired: deque[str] = field(default_factory=lambda: deque(maxlen=8))
    """Epochs replaced by a later run: their poses are refused."""
    posed: float = 0.0
    """When the last pose was taken (for the plausibility of the next sequence number)."""
    jump: tuple[int, float] | None = None
    """The last pose refused as ``implausible`` (seq, when), if none was taken since: a pose that
    follows it plausibly confirms the jump."""
    fed_epoch: str | None = None
    """The epoch of the last pose fed to the recogniser."""
    step: int = 1
    """Native frames per index frame (cluster mode begins a motion at a multiple of it)."""
    rig: RigPlan | None = None
    """A positions stream of a rig's joint names: how its joints map onto the standard ones."""
    bvh: BvhPoses | None = None
    """A BVH stream: its channel rows to the standard joints."""
    warmup: int = 0
    """Native frames a recogniser that starts mid-motion may get wrong: a detection's reach and the
    features' delay."""
    warming: bool = False
    """Whether the stream's history is truncated (taken over from a partial buffer): detections that
    start within :attr:`warmup` frames of its first fed pose are suppressed."""
    suppress_before: int | None = None
    """Detections starting before this sequence number are suppressed (see :attr:`warming`)."""
    progress: StreamProgress | None = None
    """The recogniser's progress (``progress.enabled``), made anew with it."""
    kind: str = "positions"
    """The announcement's kind (``positions``, ``channels``, ``bvh``)."""
    plain: bool = False
    """Whether the recogniser takes a pose's channels as they come (radians of an ASF skeleton)."""
    ready_seq: int = -1
    ready_time: float = 0.0
    ready_arrived: float = 0.0
    ready_values: np.ndarray | None = None
    """The pose :meth:`StreamTable._direct` took for the next tick (its seq, time, arrival and
    values: kept here, not in an object of its own, which would cost a collector's pass a few
    hundred poses)."""


@dataclass(frozen=True)
class Emitted:
    """A detection, a behaviour boundary or a progress event ready for the wire, and when the pose
    that completed it was taken in (the ``now`` of :meth:`StreamTable.pose`, the service's monotonic
    clock; 0: not known), for the latency from arrival to publish. Not the source's timestamp (the
    message's ``source_time``): a source's clock may be anywhere."""

    message: DetectionMessage | BoundaryMessage | ProgressMessage
    arrived: float


def _allowance(rate: float, seconds: float) -> float:
    """The most sequence numbers a source announced at ``rate`` Hz can plausibly have advanced by in
    ``seconds``: twice its rate, plus a second."""
    return 2 * rate * max(0.0, seconds) + rate + 1


class StreamTable:
    """The streams of one service instance (see the module docstring). ``session`` makes detection
    ids unique to this run. As the sections of the configuration say (their defaults if not given):
    ``service`` bounds each stream's waiting poses (``queue_frames``, the oldest dropped) and the
    table (``max_streams``) and sets the bridged gaps (``bridge_s``); ``recognizer`` makes the bank,
    ``segmentation`` the behaviour boundaries.

    ``cluster``: cluster mode (``docs/cluster.md``), where any worker computing a stream must give
    the same detections with the same ids: a detection's session is ``session/<epoch>`` (the
    source's run), not a count of this table's restarts; a motion begins only at a pose whose
    sequence number is a multiple of the decimation step (so every owner takes the same index
    frames); a stream marked :meth:`warm_up` suppresses the detections its truncated history could
    get wrong."""

    def __init__(
        self,
        library: Library,
        *,
        session: str,
        service: ServiceConfig | None = None,
        recognizer: RecognizerConfig | None = None,
        segmentation: SegmentationConfig | None = None,
        progress: ProgressConfig | None = None,
        cluster: bool = False,
        rigs: Sequence[RigMap] = BUILT_IN,
    ) -> None:
        service = ServiceConfig() if service is None else service
        self.rigs = tuple(rigs)
        """The rig maps positions and BVH streams are mapped by, the first that fits."""
        recognizer = RecognizerConfig() if recognizer is None else recognizer
        segmentation = SegmentationConfig() if segmentation is None else segmentation
        self.bank = RecognizerBank(library, recognizer.settings())
        self.session = session
        # a stream's runs in this table, numbered across streams: a stream forgotten (ended, idle)
        # and taken again is not numbered from 0 again, so its detections' ids stay unique
        self._generations = itertools.count()
        self._ending: set[str] = set()
        """Streams whose source said the run ended (an end message): each goes once its queue is empty."""
        self.queue_frames = service.queue_frames
        self.max_streams = service.max_streams
        self.bridge_s = service.bridge_s
        self.library = library
        self.streams: dict[str, _Stream] = {}
        self.counts: Counter[str] = Counter()
        """Refusals and drops by reason, and ``gaps``/``gap_frames``."""
        self.segmentation = segmentation.method
        self.segmented = segmentation.streams
        self.progress = ProgressConfig() if progress is None else progress
        self._queued = 0
        self._skeletons: dict[str, Skeleton] = {}  # by ASF text, least recently announced first
        self._bvhs: dict[tuple[str, str], BvhPoses] = {}  # by BVH hierarchy text and up axis, likewise
        self._waiting: dict[str, _Stream] = {}  # the streams with queued poses, in arrival order
        self._ready: dict[str, _Stream] = {}
        """The streams whose one waiting pose is the next frame of their run, nothing else of theirs
        waiting (:meth:`_direct`): fed by the next tick without a queue."""
        self.cluster = cluster

    def _session(self, generation: int, epoch: str | None) -> str:
        """The session of a stream's detections: per run of the source in cluster mode (every
        worker alike), else per run in this table (:attr:`_Stream.generation`)."""
        return f"{self.session}/{epoch or '-'}" if self.cluster else f"{self.session}/{generation}"

    @staticmethod
    def _horizon(recognizer: Recognizer) -> int:
        """Native frames a detection of ``recognizer`` reaches back at most: the index-rate frames of
        :attr:`~daemon.recognizer.Recognizer.reach`, the features' delay, and margin (the source
        times of so many frames are kept)."""
        return recognizer.clock.lag(recognizer.reach + 2) + 8

    @property
    def queued(self) -> int:
        """Poses waiting in all streams' queues."""
        return self._queued

    # ------------------------------------------------------------------------------------ intake

    def skeleton(self, message: SkeletonMessage, now: float) -> list[Emitted]:
        """Make or remake the stream's recogniser; the last detections of a replaced one."""
        old = self.streams.get(message.stream)
        if old is not None and old.announced == message:
            old.seen = now
            return []  # a repeated (retained or periodic) announcement
        if old is not None and dataclasses.replace(old.announced, epoch=message.epoch) == message:
            self._new_run(old, message.epoch, now)  # the same stream, announced by a new run of its source
            old.announced = message
            return []
        if old is None and len(self.streams) >= self.max_streams:
            raise Refused("too_many_streams", f"the table holds {self.max_streams} streams")
        skeleton = angles = None
        if message.asf is not None:
            try:
                skeleton = self._parsed(message.asf, f"<skeleton of {message.stream}>")
            except MocapFormatError as e:
                raise Refused("skeleton", str(e)) from None
            if message.angle_unit == "deg":
                angles = np.asarray(skeleton.angle_channels, dtype=np.intp)
        rig = bvh = None
        joints = message.joints
        if message.bvh is not None:
            try:
                bvh = self._bvh(message.bvh, message.up, f"<skeleton of {message.stream}>")
            except MocapFormatError as e:
                raise Refused("skeleton", str(e)) from None
            joints = JOINT_NAMES
        elif joints is not None:
            try:  # a rig's names (mixamorig:LeftArm, UpperArm_L, ...): mapped onto the standard joints
                rig = names_plan(joints, f"<skeleton of {message.stream}>", self.rigs)
            except MocapFormatError as e:
                raise Refused("skeleton", str(e)) from None
            if rig is not None:
                joints = JOINT_NAMES
        # everything that can refuse the new skeleton first: a refused one leaves the old stream be
        segmenting = self._segmenting(message, skeleton, bvh)
        generation = next(self._generations)
        try:
            recognizer = self.bank.recognizer(
                message.stream,
                message.rate,
                skeleton=skeleton,
                joint_names=joints,
                session=self._session(generation, message.epoch),  # unique per run
            )
        except (InputError, MocapFormatError) as e:
            raise Refused("skeleton", str(e)) from None
        out = self._remove(message.stream, "skeleton_changed") if old is not None else []
        self.bank.put(message.stream, recognizer)
        horizon = self._horizon(recognizer)
        self.streams[message.stream] = s = _Stream(
            message,
            skeleton,
            angles,
            turns=None if skeleton is None else np.asarray(skeleton.angle_channels, dtype=np.intp),
            times=np.zeros(horizon),
            arrivals=np.zeros(horizon),
            width=(
                len(skeleton.channel_names)
                if skeleton is not None
                else bvh.width
                if bvh is not None
                else len(message.joints or ())
            ),
            seen=now,
            generation=generation,
            segmenting=segmenting,
            epoch=message.epoch,
            step=recognizer.clock.step,
            warmup=recognizer.clock.lag(recognizer.reach),
            rig=rig,
            bvh=bvh,
            kind=message.kind,
            plain=skeleton is not None and angles is None,
        )
        self._follow(s, recognizer)
        return out

    def _follow(self, s: _Stream, recognizer: Recognizer) -> None:
        """Follow the progress of ``s``'s (new) recogniser, if progress events are enabled."""
        if self.progress.enabled:
            s.progress = StreamProgress(recognizer.stage, recognizer.native_rate, self.progress.per_s)

    def warm_up(self, name: str) -> None:
        """``name``'s history here is truncated (cluster mode: taken over mid-run): suppress the
        detections that start within its warm-up of its first fed pose."""
        s = self.streams.get(name)
        if s is not None and s.last_fed is None:
            s.warming = True

    def state(self, name: str, now: float) -> bytes:
        """Stream ``name``'s state at ``now``, from which another worker's table goes on as this one
        would (:meth:`resume`): its announcement, its recogniser's state
        (:meth:`~daemon.recognizer.Recognizer.state`), the sequence numbers received and fed, the
        last frame fed (a gap after it is bridged from it), its runs, its warm-up, and how long it
        has been silent (for its eviction when idle). Taken when
        none of its poses waits (a queued pose is the reader's to deliver again). Not carried:
        the segmenter's and the progress' states (the stream's behaviour boundaries and progress
        begin anew where it is resumed)."""
        s = self.streams[name]
        if self.waiting(name):
            raise ValueError(f"stream {name!r} has poses waiting")
        fed = s.last_fed
        state: bytes = msgpack.packb(
            {
                "announced": encode(s.announced),
                "recognizer": self.bank[name].state(),
                "epoch": s.epoch,
                "retired": list(s.retired),
                "last_received": s.last_received,
                "received": s.received,
                "last_fed": fed,
                "last_values": None if s.last_values is None else s.last_values.astype(np.float64).tobytes(),
                "last_time": None if fed is None else float(s.times[fed % len(s.times)]),
                "fed_epoch": s.fed_epoch,
                "warming": s.warming,
                "suppress_before": s.suppress_before,
                "silent_s": max(0.0, now - s.seen),
            }
        )
        return state

    def oldest(self) -> float | None:
        """The source time of the oldest pose waiting in any stream (None: none waits)."""
        queued = [s.queue[0].time for s in self.streams.values() if s.queue]
        return min([*queued, *(s.ready_time for s in self._ready.values())], default=None)

    def waiting(self, name: str) -> bool:
        """Whether a pose of stream ``name`` waits to be fed (queued, or a frame bridging a gap)."""
        s = self.streams[name]
        return bool(s.queue or s.filling) or name in self._ready

    def resume(self, state: bytes, now: float) -> str:
        """Take a stream in the :meth:`state` another table gave (cluster mode: a partition taken
        over from a checkpoint); its name. :class:`Refused` (``state``) if the state is damaged, of
        a stream held here already, or does not fit this table's library and settings: nothing is
        taken then."""
        try:
            got = msgpack.unpackb(state)
            announced = decode(got["announced"])
            if not isinstance(announced, SkeletonMessage):
                raise TypeError("the announcement is not a skeleton")
            name = announced.stream
            if name in self.streams:
                raise ValueError(f"stream {name!r} is held here already")
            last_values = got["last_values"]
            values = None if last_values is None else np.frombuffer(last_values, dtype=np.float64).copy()
            fields = {k: got[k] for k in ("epoch", "last_received", "received", "last_fed", "fed_epoch")}
            fields |= {"warming": bool(got["warming"]), "suppress_before": got["suppress_before"]}
            retired, last_time, recognizer = got["retired"], got["last_time"], got["recognizer"]
            silent = float(got["silent_s"])
        except (ValueError, TypeError, KeyError, msgpack.UnpackException, MocapdError) as e:
            raise Refused("state", f"not a stream's state: {e}") from None
        self.skeleton(announced, now)
        try:
            self.bank.restore(name, recognizer)
        except MocapdError as e:
            self._remove(name, None)
            raise Refused("state", f"stream {name!r}: {e}") from None
        s = self.streams[name]
        for k, v in fields.items():
            setattr(s, k, v)
        s.retired.extend(retired)
        s.last_values = values
        s.posed = now
        s.seen = now - silent
        if s.last_fed is not None and last_time is not None:
            s.times[s.last_fed % len(s.times)] = last_time
        self._follow(s, self.bank[name])
        return name

    def forget(self, name: str) -> None:
        """Drop ``name`` without publishing anything (cluster mode: another worker owns it now)."""
        if name in self.streams:
            self.counts["handed_over"] += 1
            self._remove(name, None)

    def _new_run(self, s: _Stream, epoch: str | None, now: float) -> None:
        """Poses of ``s`` are of a new run of its source from now on (epoch ``epoch``); refused
        (``stale_epoch``) if that run was replaced already."""
        if epoch is not None and epoch in s.retired:
            raise Refused("stale_epoch", f"epoch {epoch!r} was replaced by {s.epoch!r}")
        if s.epoch is not None and s.epoch != epoch:
            s.retired.append(s.epoch)
        s.epoch = epoch
        s.last_received = None
        s.seen = now
        self._ending.discard(s.announced.stream)  # an end of the run before: this run's poses go on

    def _parsed(self, asf: str, source: str) -> Skeleton:
        """``asf`` parsed, named ``source``: parsed once for the last :data:`SKELETONS_KEPT` texts
        (many streams announce the same skeleton, and every stream again after a restart)."""
        skeleton = _remembered(self._skeletons, asf, lambda: parse_asf(asf.splitlines(), source))
        return dataclasses.replace(skeleton, source=source)

    def _bvh(self, hierarchy: str, up: str, source: str) -> BvhPoses:
        """A BVH stream's poses of ``hierarchy`` (parsed once for the last :data:`SKELETONS_KEPT`
        texts, as ASF texts are)."""
        return _remembered(
            self._bvhs,
            (hierarchy, up),
            lambda: BvhPoses(parse_bvh_hierarchy(hierarchy, source), up, self.rigs),
        )

    def _segmenting(
        self, message: SkeletonMessage, skeleton: Skeleton | None, bvh: BvhPoses | None
    ) -> _Segmenting | None:
        """A segmenter for a channel stream (an ASF skeleton's or a BVH rig's) that the segmentation
        patterns name (None: none)."""
        method = self.segmentation
        if method == "none" or (skeleton is None and bvh is None):
            return None
        if not any(fnmatch.fnmatchcase(message.stream, p) for p in self.segmented):
            return None
        try:
            if bvh is not None:
                return _Segmenting(RigRotations(bvh.kinematics.hierarchy, bvh.plan), method, message.rate)
            assert skeleton is not None
            return _Segmenting(JointRotations(skeleton), method, message.rate)
        except InputError as e:  # a skeleton without rotating bones, windows that do not fit the rate
            raise Refused("skeleton", f"segmentation: {e}") from None

    def pose(self, message: Pose, now: float) -> None:
        """Queue a pose, or :class:`Refused` (``no_skeleton``, ``duplicate``, ``out_of_order``,
        ``implausible``, ``stale_epoch``, ``shape``)."""
        s = self.streams.get(message.stream)
        if s is None:
            raise Refused("no_skeleton", f"stream {message.stream!r} has announced no skeleton")
        kind = s.kind
        if (message.positions is None) != (kind != "positions"):
            raise Refused(
                "shape", f"a {kind} stream got a pose of {'channels' if kind == 'positions' else 'positions'}"
            )
        values = message.channels if message.channels is not None else message.positions
        got = 0 if values is None else len(values)
        width = s.width
        if got != width:
            what = "joints" if kind == "positions" else "channels"
            raise Refused("shape", f"{got} {what}, the skeleton announced {width}")
        if message.epoch is not None and message.epoch != s.epoch:
            if s.epoch is None:
                s.epoch = message.epoch  # the source says its run from now on
            else:
                self._new_run(s, message.epoch, now)
        last = s.last_received
        seq = message.seq
        rate = s.announced.rate
        if last is not None and seq <= last:
            if seq == last:
                raise Refused("duplicate", f"seq {seq} after {last}")
            if last - seq <= rate or message.epoch is not None:
                raise Refused("out_of_order", f"seq {seq} after {last}")
            self._new_run(s, s.epoch, now)  # numbered from its start again: a restarted source
        elif last is not None and seq != last + 1 and seq - last > _allowance(rate, now - s.posed):
            jump, s.jump = s.jump, (seq, now)
            if jump is None or not 0 < seq - jump[0] <= _allowance(rate, now - jump[1]):
                raise Refused(
                    "implausible", f"seq {seq} after {last}: more frames than {now - s.posed:.2f} s hold"
                )
            # the pose before it jumped as far and this one follows it: the source did jump (a
            # gap, or a source faster than it said), so going on from here black-holes nothing
        s.jump = None
        s.last_received = seq
        s.received += 1
        s.seen = s.posed = now
        if (
            s.plain
            and last is not None
            and seq == last + 1
            and last == s.last_fed
            and message.channels is not None
            and self._direct(message.stream, s, message.epoch)
        ):
            self._make_ready(message.stream, s, seq, message.time, now, message.channels)
            return
        if len(s.queue) >= self.queue_frames:
            s.queue.popleft()
            s.arrived.popleft()
            self.counts["lagging"] += 1
            self._queued -= 1
        s.queue.append(message)
        s.arrived.append(now)
        self._queued += 1
        self._waiting.setdefault(message.stream, s)

    def _direct(self, name: str, s: _Stream, epoch: str | None) -> bool:
        """Whether a pose of ``s`` numbered the frame after the last received, which is the last
        fed, skips the queue (:attr:`_ready`): nothing else of the stream waits, and the pose goes
        on the run fed (its epoch none or the one fed). Such a pose is fed by the next tick as a
        queued one would be, with nothing to say before it (:meth:`_follows`)."""
        return (
            not s.queue
            and not s.filling
            and name not in self._ready
            and (epoch is None or epoch == s.fed_epoch)
        )

    def _make_ready(
        self, name: str, s: _Stream, seq: int, stamp: float, now: float, values: np.ndarray
    ) -> None:
        """Hold a pose :meth:`_direct` lets skip the queue for the next tick."""
        s.ready_seq, s.ready_time, s.ready_arrived = seq, stamp, now
        s.ready_values = values
        self._ready[name] = s
        self._queued += 1

    def frame(
        self, frame: FrameMessage, now: float, mine: Callable[[str], bool] | None = None
    ) -> tuple[list[int], list[tuple[str, WireError | Refused]]]:
        """Queue a frame message's poses, each as :meth:`pose` would queue it as a message of its own
        (``mine``: of the streams it says are this table's; None: all): the positions of those
        taken in the frame, and the refused as (stream, :class:`~protocols.messages.WireError` or
        :class:`Refused`), in order. Its arrays checked at once
        (:meth:`~protocols.messages.FrameMessage.faults`); the next frame of a plain stream's run
        (:meth:`_direct`) taken with the few checks left to make."""
        bad, at = frame.faults()
        seqs, stamps, epoch, values = frame.seq.tolist(), frame.time.tolist(), frame.epoch, frame.values
        positions = frame.kind == "positions"
        taken: list[int] = []
        refused: list[tuple[str, WireError | Refused]] = []
        streams = self.streams
        for i, stream in enumerate(frame.streams):
            if mine is not None and not mine(stream):
                continue
            if (bad is not None and bad[i]) or not is_id(stream):
                refused.append((stream, frame.refusal(i)))
                continue
            start, end, seq = at[i], at[i + 1], seqs[i]
            s = streams.get(stream)
            if (
                s is not None
                and s.plain
                and not positions
                and end - start == s.width
                and seq - 1 == s.last_received == s.last_fed
                and (epoch is None or epoch == s.epoch)
                and self._direct(stream, s, epoch)
            ):  # :meth:`pose`'s checks all pass: what it does to such a pose
                s.jump = None
                s.last_received = seq
                s.received += 1
                s.seen = s.posed = now
                self._make_ready(stream, s, seq, stamps[i], now, values[start:end])
                taken.append(i)
                continue
            part = values[start:end]
            if positions:
                entry = Queued(stream, seqs[i], stamps[i], part.reshape(-1, 3), None, epoch)
            else:
                entry = Queued(stream, seqs[i], stamps[i], None, part, epoch)
            try:
                self.pose(entry, now)
            except Refused as e:
                refused.append((stream, e))
                continue
            taken.append(i)
        return taken, refused

    def end(self, message: EndMessage) -> list[Emitted]:
        """The source ended the run: once the stream's queued poses are recognised (now, or in the
        :meth:`tick` that takes its last), its last detections and the stream forgotten
        (``ended``). An end of a stream not held, or of another run than the one taken, changes
        nothing (:class:`Refused` ``stale_epoch`` for a run replaced already)."""
        s = self.streams.get(message.stream)
        if s is None:
            return []
        if message.epoch is not None and message.epoch != s.epoch:
            if message.epoch in s.retired:
                raise Refused("stale_epoch", f"the end of run {message.epoch!r}, replaced already")
            return []
        if s.queue or s.filling or message.stream in self._ready:
            self._ending.add(message.stream)
            return []
        return self._remove(message.stream, "ended")

    # ------------------------------------------------------------------------------ recognition

    def tick(self) -> tuple[list[Emitted], list[tuple[str, str, str]]]:
        """One frame of every stream that has one waiting (a queued pose, or a frame bridging the
        gap before it), through one bank push: the detections, and the frames the recognisers
        refused as (stream, problem, why)."""
        frames = []
        before: dict[str, tuple[int | None, np.ndarray | None, np.ndarray | None]] = {}  # last fed
        bridging: set[str] = set()  # the streams whose frame this tick is an interpolated one
        segmented: dict[str, np.ndarray] = {}  # what each stream's segmentation takes of its frame
        out: list[Emitted] = []
        segmenting = self.segmentation != "none"
        ready, self._ready = self._ready, {}
        for name, s in ready.items():
            seq, stamp, arrived, values = s.ready_seq, s.ready_time, s.ready_arrived, s.ready_values
            assert values is not None
            s.ready_values = None
            before[name] = (s.last_fed, s.last_values, s.last_channels)
            s.last_fed, s.last_values, s.last_channels = seq, values, None
            if segmenting:
                segmented[name] = values
            s.times[seq % len(s.times)] = stamp
            s.arrivals[seq % len(s.arrivals)] = arrived
            frames.append((name, seq, values))
        self._queued -= len(ready)
        for name, s in list(self._waiting.items()):
            if name in ready:
                continue  # fed its ready pose this tick, its queued ones after it
            if s.filling:
                seq, stamp, arrived, values, channels = s.filling.popleft()
                bridging.add(name)
            else:
                pose, arrived = s.queue.popleft(), s.arrived.popleft()
                if not s.queue:
                    del self._waiting[name]
                last = s.last_fed
                if (
                    last is None
                    or pose.seq != last + 1
                    or (pose.epoch is not None and pose.epoch != s.fed_epoch)
                ):
                    out += self._follows(name, s, pose)  # else the next frame of the run: nothing to say
                if self.cluster and s.last_fed is None:
                    if pose.seq % s.step:  # every owner begins a motion at the same index frames
                        self.counts["aligning"] += 1
                        self._queued -= 1
                        continue
                    if s.warming:
                        s.warming = False
                        s.suppress_before = pose.seq + s.warmup
                seq, stamp = pose.seq, pose.time
                values = pose.channels if s.plain and pose.channels is not None else self._values(s, pose)
                channels = None
                if s.bvh is not None and s.segmenting is not None and pose.channels is not None:
                    channels = pose.channels.astype(np.float64)
                if s.last_fed is not None and seq > s.last_fed + 1:
                    self._bridge(name, s, pose, arrived, values, channels)
                    seq, stamp, arrived, values, channels = s.filling.popleft()
                    bridging.add(name)
            self._queued -= 1
            before[name] = (s.last_fed, s.last_values, s.last_channels)
            s.last_fed, s.last_values, s.last_channels = seq, values, channels
            if segmenting:
                segmented[name] = values if channels is None else channels
            s.times[seq % len(s.times)] = stamp
            s.arrivals[seq % len(s.arrivals)] = arrived
            frames.append((name, seq, values))
        if not frames:
            return out, []
        result = self.bank.push(frames)
        refused: list[tuple[str, str, str]] = []
        taken = {name for name, _ in result.errors}  # refused by the recogniser: not fed on
        if self.progress.enabled:  # a tick's progress goes out before its detections
            for name, frame, _ in frames:
                s = self.streams[name]
                if s.progress is not None and name not in taken:
                    out += self._progressed(name, s, s.progress.observe(frame), frame)
        for name, error in result.errors:
            # a taken-in pose the recogniser refused (e.g. positions beyond floating point after
            # forward kinematics): dropped, and as if never fed, so that the next pose bridges it
            # instead of every later one being refused as a jump
            self.counts[f"recognizer_{error.problem}"] += 1
            s = self.streams[name]
            s.last_fed, s.last_values, s.last_channels = before[name]
            why = str(error)
            if name in bridging:  # the last frame fed was usable: the pose after the gap is not
                self._queued -= len(s.filling) + 1
                s.filling.clear()
                dropped = s.queue.popleft()
                s.arrived.popleft()
                if not s.queue:
                    del self._waiting[name]
                why += f" (bridging the gap before pose {dropped.seq}, dropped)"
            refused.append((name, error.problem, why))
        out += self._kept([self._emitted(d) for d in result.detections])
        if self.segmentation != "none":
            for name, frame, _ in frames:
                s = self.streams[name]
                if s.segmenting is not None and name not in taken:
                    found = s.segmenting.push(frame, segmented[name])
                    out += [self._boundary(name, s, cut) for cut in found]
        for name in [n for n in self._ending if not self.streams[n].queue and not self.streams[n].filling]:
            out += self._remove(name, "ended")
        return out, refused

    def _follows(self, name: str, s: _Stream, pose: Pose) -> list[Emitted]:
        """Where ``pose``, the next of ``s`` to be fed, stands: the first of a new run of the source
        or after a gap too long to bridge, it ends the stream's motion (the detections that gives);
        a gap is counted."""
        out: list[Emitted] = []
        if s.last_fed is not None and (
            pose.seq <= s.last_fed or (pose.epoch is not None and pose.epoch != s.fed_epoch)
        ):  # the first pose of a new run of the source
            self.counts["restarts"] += 1
            out += self._restart(name, s, pose.epoch)
        if pose.epoch is not None:
            s.fed_epoch = pose.epoch
        gap = 0 if s.last_fed is None else pose.seq - s.last_fed - 1
        if gap > 0:
            self.counts["gaps"] += 1
            self.counts["gap_frames"] += gap
            if gap > bridge_frames(self.bridge_s, s.announced.rate):
                out += self._restart(name, s, pose.epoch)
        return out

    def _bridge(
        self,
        name: str,
        s: _Stream,
        pose: Pose,
        arrived: float,
        values: np.ndarray,
        channels: np.ndarray | None,
    ) -> None:
        """Queue the frames of the gap between the last frame fed and ``pose`` (taken in at
        ``arrived``, its recogniser input ``values``, a segmented BVH stream's ``channels``),
        interpolated, before ``pose`` itself."""
        assert s.last_fed is not None and s.last_values is not None
        missing = pose.seq - s.last_fed - 1
        fill = bridge(s.last_values, values, missing, s.turns)
        bridged: list[np.ndarray | None] = [None] * missing
        if channels is not None and s.last_channels is not None and s.bvh is not None:
            bridged = list(bridge(s.last_channels, channels, missing, s.bvh.rotations, turn=360.0))
        start = float(s.times[s.last_fed % len(s.times)])
        stamps = start + (pose.time - start) * np.arange(1, missing + 1) / (missing + 1)
        s.filling.extend(
            (seq, stamp, arrived, values, raw)
            for seq, stamp, values, raw in zip(
                range(s.last_fed + 1, pose.seq), stamps.tolist(), fill, bridged, strict=True
            )
        )
        s.queue.appendleft(pose)
        s.arrived.appendleft(arrived)
        self._waiting.setdefault(name, s)
        self._queued += missing  # the pose is queued again: counted already

    def _values(self, s: _Stream, pose: Pose) -> np.ndarray:
        if pose.positions is not None:
            p = pose.positions.astype(np.float64)
            if s.rig is not None and p.shape == (s.width, 3):
                p = standard_joints(p[None], s.rig)[0]
            return y_up(p) if s.announced.up == "z" else p
        assert pose.channels is not None
        if s.bvh is not None:
            return s.bvh.joints(pose.channels)
        assert s.skeleton is not None
        if s.angles is None or len(pose.channels) != len(s.skeleton.channel_names):
            return pose.channels  # radians, or a wrong length the bank refuses
        c = pose.channels.copy()
        c[s.angles] *= DEG  # as the AMC reader converts degrees
        return c

    # ------------------------------------------------------------------------------- the end

    def evict_idle(self, now: float, idle_s: float, waiting: Collection[str] = ()) -> list[Emitted]:
        """Flush and forget the streams silent for more than ``idle_s`` seconds whose poses are
        all recognised, bar those ``waiting`` (messages of theirs wait in a transport: not silent,
        only not taken in yet)."""
        out = []
        for name in [
            n
            for n, s in self.streams.items()
            if now - s.seen > idle_s and not s.queue and n not in waiting and n not in self._ready
        ]:
            out += self._remove(name, "idle")
        return out

    def flush_all(self) -> list[Emitted]:
        """Every stream's last detections (its queued poses first), the table emptied."""
        out = []
        while self.queued:
            out += self.tick()[0]
        for name in list(self.streams):
            out += self._remove(name, None)
        return out

    def _remove(self, name: str, reason: str | None) -> list[Emitted]:
        s = self.streams.pop(name)
        self._ending.discard(name)
        self._queued -= len(s.queue) + len(s.filling) + (self._ready.pop(name, None) is not None)
        self._waiting.pop(name, None)
        if reason is not None:
            self.counts[reason] += 1
        detections = self.bank.remove(name)
        return (
            self._progress_end(name, s)
            + self._kept([self._emitted(d, s) for d in detections], s)
            + self._segments_end(name, s)
        )

    def _progressed(self, name: str, s: _Stream, events: list[ProgressEvent], frame: int) -> list[Emitted]:
        """``events`` of stream ``name`` as progress messages (sequence numbers already), the time
        of frame ``frame``'s pose theirs."""
        if not events:
            return []
        source_time = float(s.times[frame % len(s.times)])
        arrived = float(s.arrivals[frame % len(s.arrivals)])
        return [
            Emitted(
                ProgressMessage(
                    name,
                    e.frame,
                    tuple(
                        ClassProgress(c.class_name, c.keyframes, c.matched, c.position, c.cost, c.tau)
                        for c in e.classes
                    ),
                    source_time,
                    0.0,
                ),
                arrived,
            )
            for e in events
        ]

    def _progress_end(self, name: str, s: _Stream) -> list[Emitted]:
        """The progress events of the end of ``s``'s motion (its recogniser just flushed)."""
        p = s.progress
        if p is None:
            return []
        frame = p.frame
        events = p.end()
        return self._progressed(name, s, events, frame) if frame is not None else []

    def _segments_end(self, name: str, s: _Stream) -> list[Emitted]:
        """The boundaries the end of a stream's motion gives (its segmenter starts anew)."""
        return [] if s.segmenting is None else [self._boundary(name, s, c) for c in s.segmenting.restart()]

    def _restart(self, name: str, s: _Stream, epoch: str | None) -> list[Emitted]:
        """End the stream's motion at a long gap or a new run (``epoch``): its detections so far,
        then a fresh recogniser."""
        s.generation = next(self._generations)
        detections = self.bank.restart(name, session=self._session(s.generation, epoch))
        out = (
            self._progress_end(name, s)
            + self._kept([self._emitted(d) for d in detections])
            + self._segments_end(name, s)
        )
        self._follow(s, self.bank[name])
        s.last_fed = s.last_values = None
        return out

    def _kept(self, emitted: list[Emitted], s: _Stream | None = None) -> list[Emitted]:
        """``emitted`` less the detections of a warming stream (:meth:`warm_up`) that start too early."""
        out = []
        for e in emitted:
            m = e.message
            t = s if s is not None else self.streams.get(m.stream)
            limit = None if t is None else t.suppress_before
            if limit is not None and isinstance(m, DetectionMessage) and m.start_frame < limit:
                self.counts["warmup_suppressed"] += 1
                continue
            if t is not None and t.segmenting is not None and isinstance(m, DetectionMessage):
                t.segmenting.detected(m)
            out.append(e)
        return out

    def _emitted(self, d: Detection, s: _Stream | None = None) -> Emitted:
        s = s if s is not None else self.streams[d.stream]
        source_time = float(s.times[d.emitted_at_frame % len(s.times)])
        arrived = float(s.arrivals[d.emitted_at_frame % len(s.arrivals)])
        message = DetectionMessage(
            d.id,
            d.stream,
            d.class_name,
            d.start_frame,
            d.end_frame,
            d.cost,
            d.tau,
            d.emitted_at_frame,
            source_time,
            0.0,
        )
        return Emitted(message, arrived)

    def _boundary(self, name: str, s: _Stream, cut: _Cut) -> Emitted:
        b = cut.boundary
        key = f"{self._session(s.generation, s.epoch)}/{name}/boundary/{b.method}/{cut.frame}"
        message = BoundaryMessage(
            str(uuid.uuid5(uuid.NAMESPACE_URL, key)),
            name,
            cut.frame,
            b.method,
            b.score,
            0.0,
            cut.start,
            cut.detections,
        )
        return Emitted(message, float(s.arrivals[cut.known % len(s.arrivals)]))
