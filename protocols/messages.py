"""The wire (DESIGN.md, "The wire"; schema for other languages in ``protocols/README.md``).

Every message is a msgpack map with ``"v": 1`` and a ``"type"``: ``skeleton`` (a stream announces
what its poses carry), ``pose`` (one frame), ``frame`` (one capture frame of several streams, packed
as arrays), ``detection`` (a recognised motion), ``boundary`` (a
behaviour cut), ``progress`` (how far the motions under way on a stream have got) and ``status``
(a daemon instance online or offline). :func:`encode` writes one,
:func:`decode` reads one and validates it completely — type, version, every field's type, the
shape and finiteness of the pose arrays, a maximum size — raising :class:`WireError` with one
reason code on anything else. Topics (:func:`topic`, :func:`parse_topic`) are the MQTT topic words,
also the first frame of a ZeroMQ multipart message.

Pure: bytes in, frozen dataclasses out; no sockets.
"""

from __future__ import annotations

import functools
import itertools
import math
import re
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Literal, get_args

import msgpack
import numpy as np
import numpy.typing as npt

from daemon.errors import MocapdError, printable

VERSION = 1
DEFAULT_MAX_BYTES = 1 << 20
"""The largest message :func:`decode` accepts by default (1 MiB: an embedded ASF is ~20 KiB)."""

Reason = Literal["undecodable", "oversize", "version", "type", "schema", "shape", "non_finite"]
REASONS: tuple[Reason, ...] = get_args(Reason)
Units = Literal["m", "cm", "mm", "in", "asf"]
Up = Literal["y", "z"]
AngleUnit = Literal["deg", "rad"]
State = Literal["online", "offline"]
Kind = Literal["skeleton", "pose", "detection", "boundary", "progress", "status"]

STATUS_REMINDER_S = 5
"""A daemon publishes its ``online`` status again this often on ZeroMQ and MQTT, so a status not
heard for two such periods is of a daemon gone without a word, or of none (``mocapd view``: stale)."""
STREAM_ID = re.compile(r"[A-Za-z0-9_:@-]{1,128}")
"""A stream or instance id: one MQTT topic level (no ``/``, ``+``, ``#``) and one NATS subject
token (no ``.``, which would split the subject cluster mode routes by), at most 128 characters."""
ID_RULE = "letters, digits, _:@-, at most 128"
EPOCH = re.compile(r"[A-Za-z0-9_.:@-]{1,64}")
"""A run of a source (a random id it draws when it starts): letters, digits, ``_.:@-``, at most 64."""
MAX_SEQ = (1 << 53) - 1
"""The largest sequence number (exact in every JSON and float consumer)."""
MAX_CLASSES = 256
"""The most classes one progress message reports."""
MAX_KEYFRAMES = 64
"""The most keyframes a class's progress counts."""
MAX_SEGMENT_DETECTIONS = 64
"""The most detections a boundary message lists for the behaviour that ended."""
MAX_DEPTH = 8
"""The deepest nesting of maps and lists a message may have (a progress message has 4)."""
MAX_SUBJECTS = 4096
"""The most poses one frame message carries."""


class WireError(MocapdError, ValueError):
    """A message that cannot be used: ``reason``, one of :data:`REASONS` (the reason code it is
    counted under), and ``detail``, what was wrong; ``str``: ``reason: detail``."""

    reason: Reason

    def __init__(self, reason: Reason, detail: str) -> None:
        super().__init__(reason)
        self.detail = detail

    def _reason(self) -> str:
        return printable(f"{self.reason}: {self.detail}")


@dataclass(frozen=True)
class SkeletonMessage:
    """A stream's announcement. Positions streams: ``joints`` (names, in the order of every pose's
    coordinates; mocapd's standard joints, or a rig's names a rig map fits, :mod:`replay.rigs`),
    ``up`` axis and length ``units``.
    Channel streams: ``asf``, the text of an ASF file; poses then carry AMC-style channels in its
    channel order, angles in ``angle_unit``. BVH streams: ``bvh``, the ``HIERARCHY`` section of a
    BVH file (a rig a built-in map fits, :mod:`replay.rigs`); poses then carry its channel rows as
    a BVH file's ``MOTION`` lines do (degrees, lengths in ``units``), ``up`` the axis it stands
    along, so that a bridge forwards a BVH broadcast unchanged. ``rate``: frames per second. ``epoch``:
    the run of the source (None: not said), see :class:`PoseMessage`."""

    stream: str
    rate: float
    joints: tuple[str, ...] | None = None
    up: Up = "y"
    units: Units = "cm"
    asf: str | None = None
    angle_unit: AngleUnit = "deg"
    epoch: str | None = None
    bvh: str | None = None

    @property
    def kind(self) -> Literal["positions", "channels", "bvh"]:
        return "channels" if self.asf is not None else "bvh" if self.bvh is not None else "positions"


@dataclass(frozen=True)
class PoseMessage:
    """One frame of ``stream``: its sequence number ``seq`` (consecutive from any start, at most
    :data:`MAX_SEQ`), the source's timestamp ``time`` (seconds since the Unix epoch) and either
    ``positions`` ``(J, 3)`` (float32 on the wire) or ``channels`` ``(C,)`` (float64 on the wire).
    ``epoch``: the run of the source that sent it (a random id drawn when the source starts, None:
    not said), so that a restarted source, which numbers from its start again, is a new run and not
    an old one going backwards."""

    stream: str
    seq: int
    time: float
    positions: npt.NDArray[np.float32] | None = None
    channels: npt.NDArray[np.float64] | None = None
    epoch: str | None = None


@dataclass(frozen=True, eq=False)
class FrameMessage:
    """One capture frame (or a few) of several streams, as a capture system sends it (every subject
    in one packet), from ``source`` (an id: its topic's level). Per subject i of S: ``streams[i]``,
    ``seq[i]`` and ``time[i]`` as a :class:`PoseMessage`'s, and ``counts[i]`` values of ``values``
    (subject after subject: float32 positions, 3 per joint, or float64 channels, by ``kind``).
    ``epoch``: the source's run, every subject's. A subject may come more than once (a few frames
    of it, in order). Arrays ``(S,)``: ``seq`` uint64, ``time`` float64, ``counts`` int64.

    :func:`decode` checks the message as a whole (a bad one is refused whole); each subject's own
    faults (:meth:`poses`) refuse that subject alone."""

    source: str
    streams: tuple[str, ...]
    seq: npt.NDArray[np.uint64]
    time: npt.NDArray[np.float64]
    counts: npt.NDArray[np.int64]
    values: npt.NDArray[Any]
    kind: Literal["positions", "channels"]
    epoch: str | None = None

    def poses(self) -> list[PoseMessage | WireError]:
        """Per subject, in order, its pose, or why it is refused, as a pose message of its own would
        be (:func:`decode`, the first fault in its order): an id that is not one (``schema``), a
        sequence number beyond :data:`MAX_SEQ` (``schema``), a time not finite (``non_finite``), no
        values or positions not in threes (``shape``), a value not finite (``non_finite``).
        Checked over the arrays at once; a Python step per subject only to make its pose."""
        bad, at = self.faults()
        seqs, stamps, epoch, values = self.seq.tolist(), self.time.tolist(), self.epoch, self.values
        out: list[PoseMessage | WireError] = []
        for i, stream in enumerate(self.streams):
            if (bad is not None and bad[i]) or not is_id(stream):
                out.append(self.refusal(i))
            elif self.kind == "positions":  # a subject's offset need not be a multiple of 3
                out.append(
                    PoseMessage(
                        stream, seqs[i], stamps[i], values[at[i] : at[i + 1]].reshape(-1, 3), None, epoch
                    )
                )
            else:
                out.append(PoseMessage(stream, seqs[i], stamps[i], None, values[at[i] : at[i + 1]], epoch))
        return out

    def faults(self) -> tuple[list[bool] | None, list[int]]:
        """Per subject whether its seq, time, count or values are at fault (:meth:`poses`; None:
        none is; its id is not judged here), and where each subject's values start in
        :attr:`values` (S + 1 offsets, the last the end)."""
        starts = np.zeros(len(self.counts) + 1, dtype=np.int64)
        np.cumsum(self.counts, out=starts[1:])
        finite = np.isfinite(self.values)
        faulty = (self.seq > MAX_SEQ) | ~np.isfinite(self.time)
        faulty |= (self.counts == 0) | (self.counts % (3 if self.kind == "positions" else 1) != 0)
        if not finite.all():  # the non-finite values before each offset, differenced per subject
            before = np.zeros(len(finite) + 1, dtype=np.int64)
            np.cumsum(~finite, out=before[1:])
            faulty |= before[starts[1:]] > before[starts[:-1]]
        return (faulty.tolist() if faulty.any() else None), starts.tolist()

    def refusal(self, i: int) -> WireError:
        """Why subject ``i`` is refused (:meth:`poses`; one :meth:`faults` or its id found)."""
        stream, seq, stamp = self.streams[i], int(self.seq[i]), float(self.time[i])
        a = int(self.counts[:i].sum())
        b = a + int(self.counts[i])
        where = f"frame.streams[{i}]"
        if not is_id(stream):
            return WireError("schema", f"{where}: {describe(stream)} is not an id ({ID_RULE})")
        if seq > MAX_SEQ:
            return WireError("schema", f"{where}: seq must be at most {MAX_SEQ}, got {seq}")
        if not math.isfinite(stamp):
            return WireError("non_finite", f"{where} {stream}: time is not finite")
        if b == a or (b - a) % (3 if self.kind == "positions" else 1):
            what = f"{b - a} values is not a whole number of positions" if b > a else "no values"
            return WireError("shape", f"{where} {stream}: {what}")
        return WireError("non_finite", f"{where} {stream}: a value is not finite")


def frame_of(poses: list[PoseMessage], source: str, epoch: str | None = None) -> FrameMessage:
    """The frame message of ``poses`` (all positions or all channels) from ``source``."""
    positions = [p.positions for p in poses]
    channels = [p.channels for p in poses]
    if all(a is not None for a in positions):
        kind: Literal["positions", "channels"] = "positions"
        parts = [np.asarray(a, dtype="<f4").reshape(-1) for a in positions if a is not None]
    elif all(a is not None for a in channels):
        kind = "channels"
        parts = [np.asarray(a, dtype="<f8") for a in channels if a is not None]
    else:
        raise ValueError("a frame message carries positions or channels, not both")
    return FrameMessage(
        source,
        tuple(p.stream for p in poses),
        np.array([p.seq for p in poses], dtype=np.uint64),
        np.array([p.time for p in poses], dtype=np.float64),
        np.array([len(a) for a in parts], dtype=np.int64),
        np.concatenate(parts),
        kind,
        epoch,
    )


@dataclass(frozen=True)
class EndMessage:
    """The end of a run of ``stream``: its last pose was ``seq`` (of run ``epoch``, None: not
    said). Sent on the stream's pose topic, after its last pose, so it arrives after them: a daemon
    recognises what it holds of the stream, publishes its last detections at once and forgets it
    (without it they wait until the stream has been silent for ``service.idle_s``)."""

    stream: str
    seq: int
    epoch: str | None = None


@dataclass(frozen=True)
class DetectionMessage:
    """A detection (:class:`daemon.recognizer.Detection`'s fields; frames are the stream's sequence
    numbers), ``source_time``: the timestamp of the pose whose arrival emitted it, ``emit_time``:
    when the daemon published it (seconds since the Unix epoch). ``id`` is unique per detection: a
    consumer drops a repeat (QoS 1 may deliver twice)."""

    id: str
    stream: str
    class_name: str
    start_frame: int
    end_frame: int
    cost: float
    tau: float
    emitted_at_frame: int
    source_time: float
    emit_time: float


@dataclass(frozen=True)
class SegmentDetection:
    """A detection inside a behaviour that ended (:class:`BoundaryMessage`): its class and frames."""

    class_name: str
    start_frame: int
    end_frame: int


@dataclass(frozen=True)
class BoundaryMessage:
    """A behaviour boundary: ``stream`` cut before ``frame`` by ``method``, with its ``score``; the
    behaviour that ended there began at ``start`` (None: not said) and held the ``detections``
    published before the boundary that lie wholly inside it (at most :data:`MAX_SEGMENT_DETECTIONS`,
    the latest)."""

    id: str
    stream: str
    frame: int
    method: str
    score: float
    emit_time: float
    start: int | None = None
    detections: tuple[SegmentDetection, ...] = ()


@dataclass(frozen=True)
class ClassProgress:
    """How far a motion of class ``class_name`` under way has got: of its ``keyframes`` (n; 0 for a
    class without a keyframe gate), the sequence numbers at which keyframes 1..k were ``matched``
    (k <= n, the most advanced match in progress; n: a whole keyframe hit), and ``position`` in
    [0, 1] along its template of the stream-wide DTW's path ending at the current frame, whose
    mean cost per template column is ``cost`` (comparable with the class's ``tau``)."""

    class_name: str
    keyframes: int
    matched: tuple[int, ...]
    position: float
    cost: float
    tau: float


@dataclass(frozen=True)
class ProgressMessage:
    """The classes under way on ``stream`` when the pose of sequence number ``frame`` (taken at
    ``source_time``) was recognised (none: nothing is under way), published at ``emit_time``."""

    stream: str
    frame: int
    classes: tuple[ClassProgress, ...]
    source_time: float
    emit_time: float


@dataclass(frozen=True)
class StatusMessage:
    """A daemon ``instance`` going ``online`` or ``offline``: its ``version``, the ``streams`` it
    holds and when it ``started`` (seconds since the Unix epoch)."""

    instance: str
    state: State
    version: str
    streams: int
    started: float


Message = (
    SkeletonMessage
    | PoseMessage
    | FrameMessage
    | EndMessage
    | DetectionMessage
    | BoundaryMessage
    | ProgressMessage
    | StatusMessage
)

TOPIC_OF: dict[type[Any], str] = {
    SkeletonMessage: "skeleton",
    PoseMessage: "pose",
    EndMessage: "pose",  # after the poses, in their order
    DetectionMessage: "detections",
    BoundaryMessage: "boundaries",
    ProgressMessage: "progress",
}
"""The topic word of each per-stream message: ``mocap/<stream>/<word>``."""
FRAME_WORD = "frame"
"""A frame message's topic word: ``mocap/<source>/frame``."""


def topic(message: Message) -> str:
    """The topic a message is published on: ``mocap/<stream>/<word>``, ``mocap/<source>/frame`` or
    ``mocapd/<instance>/status``."""
    if isinstance(message, StatusMessage):
        return f"mocapd/{message.instance}/status"
    if isinstance(message, FrameMessage):
        return f"mocap/{message.source}/{FRAME_WORD}"
    return f"mocap/{message.stream}/{TOPIC_OF[type(message)]}"


def parse_topic(name: str) -> tuple[str, str] | None:
    """(stream, word) of a per-stream topic ``mocap/<stream>/<word>``, None for any other topic."""
    parts = name.split("/")
    if len(parts) != 3 or parts[0] != "mocap" or not STREAM_ID.fullmatch(parts[1]):
        return None
    return parts[1], parts[2]


# ------------------------------------------------------------------------------------- encoding


def encode(message: Message) -> bytes:
    """The msgpack bytes of ``message`` (arrays packed little-endian)."""
    body: dict[str, Any] = {"v": VERSION}
    if isinstance(message, SkeletonMessage):
        body |= {"type": "skeleton", "stream": message.stream, "rate": float(message.rate)}
        if message.epoch is not None:
            body["epoch"] = message.epoch
        if message.asf is not None:
            body |= {"asf": message.asf, "angle_unit": message.angle_unit}
        elif message.bvh is not None:
            body |= {"bvh": message.bvh, "up": message.up, "units": message.units}
        else:
            assert message.joints is not None
            body |= {"joints": list(message.joints), "up": message.up, "units": message.units}
    elif isinstance(message, PoseMessage):
        body |= {"type": "pose", "stream": message.stream, "seq": message.seq, "time": float(message.time)}
        if message.epoch is not None:
            body["epoch"] = message.epoch
        if message.positions is not None:
            body["positions"] = np.ascontiguousarray(message.positions, dtype="<f4").tobytes()
        else:
            assert message.channels is not None
            body["channels"] = np.ascontiguousarray(message.channels, dtype="<f8").tobytes()
    elif isinstance(message, FrameMessage):
        body |= {
            "type": "frame",
            "source": message.source,
            "streams": list(message.streams),
            "seq": np.ascontiguousarray(message.seq, dtype="<u8").tobytes(),
            "time": np.ascontiguousarray(message.time, dtype="<f8").tobytes(),
            "counts": np.ascontiguousarray(message.counts, dtype="<u4").tobytes(),
            message.kind: np.ascontiguousarray(
                message.values, dtype="<f4" if message.kind == "positions" else "<f8"
            ).tobytes(),
        }
        if message.epoch is not None:
            body["epoch"] = message.epoch
    elif isinstance(message, EndMessage):
        body |= {"type": "end", "stream": message.stream, "seq": message.seq}
        if message.epoch is not None:
            body["epoch"] = message.epoch
    elif isinstance(message, DetectionMessage):
        body |= {
            "type": "detection",
            "id": message.id,
            "stream": message.stream,
            "class": message.class_name,
            "start_frame": message.start_frame,
            "end_frame": message.end_frame,
            "cost": float(message.cost),
            "tau": float(message.tau),
            "emitted_at_frame": message.emitted_at_frame,
            "source_time": float(message.source_time),
            "emit_time": float(message.emit_time),
        }
    elif isinstance(message, BoundaryMessage):
        body |= {
            "type": "boundary",
            "id": message.id,
            "stream": message.stream,
            "frame": message.frame,
            "method": message.method,
            "score": float(message.score),
            "emit_time": float(message.emit_time),
        }
        if message.start is not None:
            body["start"] = message.start
            body["detections"] = [
                {"class": d.class_name, "start_frame": d.start_frame, "end_frame": d.end_frame}
                for d in message.detections
            ]
    elif isinstance(message, ProgressMessage):
        body |= {
            "type": "progress",
            "stream": message.stream,
            "frame": message.frame,
            "classes": [
                {
                    "class": c.class_name,
                    "keyframes": c.keyframes,
                    "matched": list(c.matched),
                    "position": float(c.position),
                    "cost": float(c.cost),
                    "tau": float(c.tau),
                }
                for c in message.classes
            ],
            "source_time": float(message.source_time),
            "emit_time": float(message.emit_time),
        }
    else:
        body |= {
            "type": "status",
            "instance": message.instance,
            "state": message.state,
            "version": message.version,
            "streams": message.streams,
            "started": float(message.started),
        }
    out: bytes = msgpack.packb(body, use_bin_type=True)
    return out


# ------------------------------------------------------------------------------------- decoding


def decode(payload: bytes, max_bytes: int = DEFAULT_MAX_BYTES) -> Message:
    """The message in ``payload``; :class:`WireError` (with its reason) for anything that is not a
    valid message of this version at most ``max_bytes`` long."""
    if len(payload) > max_bytes:
        raise WireError("oversize", f"{len(payload)} bytes, at most {max_bytes}")
    try:
        body = msgpack.unpackb(payload, raw=False, strict_map_key=True, use_list=True)
    except Exception as e:  # msgpack raises several unrelated types for bad bytes
        raise WireError("undecodable", f"not msgpack ({type(e).__name__})") from None
    if not isinstance(body, dict):
        raise WireError("schema", f"a message is a map, got {type(body).__name__}")
    version = body.get("v")
    if type(version) is not int:
        raise WireError("version", f"'v' must be the integer {VERSION}, got {describe(version)}")
    if version != VERSION:
        raise WireError("version", f"version {version} (this daemon speaks {VERSION})")
    kind = body.get("type")
    if kind == "pose":
        pose = _plain_pose(body)
        if pose is not None:
            return pose
    if not _shallow(body):
        raise WireError("schema", f"nested deeper than {MAX_DEPTH} maps and lists")
    if not isinstance(kind, str) or kind not in _READERS:
        raise WireError("type", f"unknown type {describe(kind)} (one of {', '.join(_READERS)})")
    return _READERS[kind](_Fields(body, kind))


def describe(value: object) -> str:
    """A bad value for a refusal's detail, by its type and size: a scalar as itself, a string by its
    first characters and length, a container by its length. Never the value's repr, which for a
    container is unbounded in size and, nested deep enough, raises RecursionError."""
    if value is None or type(value) in (bool, int, float):
        return str(value)
    if isinstance(value, str):
        head = printable(value[:40])
        return f"'{head}'" if len(value) <= 40 else f"'{head}…' ({len(value)} characters)"
    if isinstance(value, bytes | list | dict):
        unit = {bytes: "byte", list: "item", dict: "entry"}[type(value)]
        return f"{type(value).__name__} of {len(value)} {unit}{'' if len(value) == 1 else 's'}"
    return type(value).__name__


def _shallow(body: dict[str, Any]) -> bool:
    """Whether ``body`` nests maps and lists at most :data:`MAX_DEPTH` deep (iteratively: the
    depth a hostile message can reach must not reach Python's recursion limit anywhere)."""
    level: list[Any] = [body]
    for _ in range(MAX_DEPTH):
        deeper = [
            inner
            for outer in level
            for inner in (outer.values() if isinstance(outer, dict) else outer)
            if isinstance(inner, dict | list)
        ]
        if not deeper:
            return True
        level = deeper
    return False


_POSE_KEYS = (
    {"v", "type", "stream", "seq", "time", "positions"},
    {"v", "type", "stream", "seq", "time", "channels"},
    {"v", "type", "stream", "seq", "time", "positions", "epoch"},
    {"v", "type", "stream", "seq", "time", "channels", "epoch"},
)


@functools.lru_cache(maxsize=4096)
def is_id(text: str) -> bool:
    """Whether ``text`` is a valid stream or instance id (:data:`STREAM_ID`)."""
    return STREAM_ID.fullmatch(text) is not None


def _plain_pose(body: dict[str, Any]) -> PoseMessage | None:
    """The pose in ``body`` if it is a valid one, checked in as few steps as the live path can
    afford; None for anything else, which the field-by-field reader then describes."""
    keys = body.keys()
    positions = keys == _POSE_KEYS[0] or keys == _POSE_KEYS[2]
    if not positions and keys != _POSE_KEYS[1] and keys != _POSE_KEYS[3]:
        return None
    stream, seq, stamp = body["stream"], body["seq"], body["time"]
    epoch = body.get("epoch")
    if epoch is not None and (type(epoch) is not str or not EPOCH.fullmatch(epoch)):
        return None
    data = body["positions" if positions else "channels"]
    if (
        type(stream) is not str
        or type(seq) is not int
        or seq < 0
        or seq > MAX_SEQ
        or type(stamp) not in (float, int)
        or not math.isfinite(stamp)
        or type(data) is not bytes
        or not data
        or len(data) % (12 if positions else 8)
        or not is_id(stream)
    ):
        return None
    a = np.frombuffer(data, dtype="<f4" if positions else "<f8")
    if not math.isfinite(float(a.sum())) and not np.isfinite(a).all():  # one reduction if finite
        return None
    if positions:
        return PoseMessage(stream, seq, float(stamp), positions=a.reshape(-1, 3), epoch=epoch)
    return PoseMessage(stream, seq, float(stamp), channels=a, epoch=epoch)


class _Fields:
    """The fields of one message body, each taken once; left-overs are a schema error."""

    def __init__(self, body: dict[str, Any], kind: str) -> None:
        self.body = body
        self.kind = kind
        self.seen = {"v", "type"}

    def fail(self, name: str, what: str, reason: Reason = "schema") -> WireError:
        return WireError(reason, f"{self.kind}.{name}: {what}")

    def take(self, name: str, default: Any = ..., *, required: bool = True) -> Any:
        self.seen.add(name)
        if name in self.body:
            return self.body[name]
        if default is not ... or not required:
            return None if default is ... else default
        raise self.fail(name, "missing")

    def text(self, name: str, pattern: re.Pattern[str] | None = None, default: Any = ...) -> str:
        value = self.take(name, default)
        if not isinstance(value, str):
            raise self.fail(name, f"must be a string, got {type(value).__name__}")
        if pattern is not None and not pattern.fullmatch(value):
            raise self.fail(name, f"{describe(value)} is not an id ({ID_RULE})")
        return value

    def integer(self, name: str, low: int | None = None, high: int | None = None) -> int:
        value = self.take(name)
        if type(value) is not int:
            raise self.fail(name, f"must be an integer, got {type(value).__name__}")
        if low is not None and value < low:
            raise self.fail(name, f"must be at least {low}, got {value}")
        if high is not None and value > high:
            raise self.fail(name, f"must be at most {high}, got {value}")
        return value

    def epoch(self) -> str | None:
        """The optional ``epoch``: None or an id."""
        value = self.take("epoch", required=False)
        if value is None:
            return None
        if not isinstance(value, str) or not EPOCH.fullmatch(value):
            what = "letters, digits, _.:@-, at most 64"
            raise self.fail("epoch", f"{describe(value)} is not an epoch ({what})")
        return value

    def number(self, name: str, *, positive: bool = False) -> float:
        value = self.take(name)
        if type(value) not in (int, float):
            raise self.fail(name, f"must be a number, got {type(value).__name__}")
        if not math.isfinite(value):
            raise self.fail(name, f"must be finite, got {value}", "non_finite")
        if positive and value <= 0:
            raise self.fail(name, f"must be positive, got {value}")
        return float(value)

    def choice(self, name: str, options: tuple[str, ...], default: Any = ...) -> str:
        value = self.text(name, default=default)
        if value not in options:
            raise self.fail(name, f"{describe(value)} is not one of {', '.join(options)}")
        return value

    def array(self, name: str, dtype: str, width: int) -> npt.NDArray[Any]:
        """A packed little-endian array of ``dtype`` whose length is a multiple of ``width``, finite."""
        value = self.take(name)
        if not isinstance(value, bytes):
            raise self.fail(name, f"must be bytes (packed {dtype}), got {type(value).__name__}")
        size = np.dtype(dtype).itemsize
        if not value or len(value) % (size * width):
            raise self.fail(name, f"{len(value)} bytes is not a whole number of {width} x {dtype}", "shape")
        a = np.frombuffer(value, dtype=dtype)
        if not np.isfinite(a).all():
            raise self.fail(
                name, f"value {int(np.flatnonzero(~np.isfinite(a))[0])} is not finite", "non_finite"
            )
        return a

    def packed(self, name: str, dtype: str, n: int) -> npt.NDArray[Any]:
        """A packed little-endian array of exactly ``n`` ``dtype`` (not checked for finiteness)."""
        value = self.take(name)
        if not isinstance(value, bytes):
            raise self.fail(name, f"must be bytes (packed {dtype}), got {type(value).__name__}")
        size = np.dtype(dtype).itemsize
        if len(value) != n * size:
            raise self.fail(name, f"{len(value)} bytes, expected {n} x {dtype} ({n * size})", "shape")
        return np.frombuffer(value, dtype=dtype)

    def done(self) -> None:
        extra = sorted(str(k) for k in self.body if k not in self.seen)
        if extra:
            raise WireError("schema", f"{self.kind}: unknown field(s) {', '.join(extra)[:120]}")


def _skeleton(f: _Fields) -> SkeletonMessage:
    stream = f.text("stream", STREAM_ID)
    rate = f.number("rate", positive=True)
    epoch = f.epoch()
    asf = f.take("asf", required=False)
    joints = f.take("joints", required=False)
    bvh = f.take("bvh", required=False)
    if [asf, joints, bvh].count(None) != 2:
        raise f.fail(
            "joints", "a skeleton carries either 'joints' (positions), 'asf' (channels) or 'bvh' (channels)"
        )
    if bvh is not None:
        if not isinstance(bvh, str) or not bvh.strip():
            raise f.fail("bvh", "must be the text of a BVH hierarchy")
        up = f.choice("up", get_args(Up), "y")
        units = f.choice("units", get_args(Units), "cm")
        f.done()
        return SkeletonMessage(stream, rate, up=up, units=units, bvh=bvh, epoch=epoch)  # type: ignore[arg-type]
    if asf is not None:
        if not isinstance(asf, str) or not asf.strip():
            raise f.fail("asf", "must be the text of an ASF file")
        unit = f.choice("angle_unit", get_args(AngleUnit), "deg")
        f.done()
        return SkeletonMessage(stream, rate, asf=asf, angle_unit=unit, epoch=epoch)  # type: ignore[arg-type]
    if not isinstance(joints, list) or not joints or not all(isinstance(j, str) and j for j in joints):
        raise f.fail("joints", "must be a non-empty list of joint names")
    if len(set(joints)) != len(joints):
        raise f.fail("joints", "a joint is named twice")
    up = f.choice("up", get_args(Up), "y")
    units = f.choice("units", get_args(Units), "cm")
    f.done()
    return SkeletonMessage(stream, rate, tuple(joints), up, units, epoch=epoch)  # type: ignore[arg-type]


def _pose(f: _Fields) -> PoseMessage:
    stream = f.text("stream", STREAM_ID)
    seq = f.integer("seq", low=0, high=MAX_SEQ)
    time = f.number("time")
    epoch = f.epoch()
    has_positions, has_channels = "positions" in f.body, "channels" in f.body
    if has_positions == has_channels:
        raise f.fail("positions", "a pose carries either 'positions' or 'channels'")
    if has_positions:
        positions = f.array("positions", "<f4", 3).reshape(-1, 3)
        f.done()
        return PoseMessage(stream, seq, time, positions=positions, epoch=epoch)
    channels = f.array("channels", "<f8", 1)
    f.done()
    return PoseMessage(stream, seq, time, channels=channels, epoch=epoch)


def _frame(f: _Fields) -> FrameMessage:
    """A frame message checked as a whole: its subjects' own faults are :meth:`FrameMessage.poses`'."""
    source = f.text("source", STREAM_ID)
    streams = f.take("streams")
    if not isinstance(streams, list) or not 0 < len(streams) <= MAX_SUBJECTS:
        raise f.fail("streams", f"must be a list of 1 to {MAX_SUBJECTS} stream ids, got {describe(streams)}")
    if not all(type(s) is str for s in streams):
        raise f.fail("streams", "must be a list of strings")
    n = len(streams)
    seq = f.packed("seq", "<u8", n)  # beyond MAX_SEQ: the subject's refusal
    stamps = f.packed("time", "<f8", n)
    counts = f.packed("counts", "<u4", n).astype(np.int64)
    epoch = f.epoch()
    has_positions, has_channels = "positions" in f.body, "channels" in f.body
    if has_positions == has_channels:
        raise f.fail("positions", "a frame carries either 'positions' or 'channels'")
    kind: Literal["positions", "channels"] = "positions" if has_positions else "channels"
    values = f.packed(kind, "<f4" if has_positions else "<f8", int(counts.sum()))
    f.done()
    return FrameMessage(source, tuple(streams), seq, stamps.astype(np.float64), counts, values, kind, epoch)


def _end(f: _Fields) -> EndMessage:
    out = EndMessage(f.text("stream", STREAM_ID), f.integer("seq", low=0, high=MAX_SEQ), f.epoch())
    f.done()
    return out


def _detection(f: _Fields) -> DetectionMessage:
    out = DetectionMessage(
        f.text("id"),
        f.text("stream", STREAM_ID),
        f.text("class"),
        f.integer("start_frame"),
        f.integer("end_frame"),
        f.number("cost"),
        f.number("tau"),
        f.integer("emitted_at_frame"),
        f.number("source_time"),
        f.number("emit_time"),
    )
    f.done()
    return out


def _boundary(f: _Fields) -> BoundaryMessage:
    head = (f.text("id"), f.text("stream", STREAM_ID), f.integer("frame"), f.text("method"))
    score, emitted = f.number("score"), f.number("emit_time")
    start: int | None = None
    found: list[SegmentDetection] = []
    if "start" in f.body:
        start = f.integer("start", high=head[2])
        entries = f.take("detections")
        if not isinstance(entries, list) or len(entries) > MAX_SEGMENT_DETECTIONS:
            raise f.fail("detections", f"must be a list of at most {MAX_SEGMENT_DETECTIONS} maps")
        for k, entry in enumerate(entries):
            if not isinstance(entry, dict):
                raise f.fail(f"detections[{k}]", f"must be a map, got {type(entry).__name__}")
            d = _Fields(entry, f"boundary.detections[{k}]")
            d.seen.clear()
            found.append(SegmentDetection(d.text("class"), d.integer("start_frame"), d.integer("end_frame")))
            d.done()
    out = BoundaryMessage(*head, score, emitted, start, tuple(found))
    f.done()
    return out


def _progress(f: _Fields) -> ProgressMessage:
    stream = f.text("stream", STREAM_ID)
    frame = f.integer("frame", low=0, high=MAX_SEQ)
    entries = f.take("classes")
    if not isinstance(entries, list) or len(entries) > MAX_CLASSES:
        raise f.fail("classes", f"must be a list of at most {MAX_CLASSES} class progress maps")
    classes = []
    for k, entry in enumerate(entries):
        if not isinstance(entry, dict):
            raise f.fail(f"classes[{k}]", f"must be a map, got {type(entry).__name__}")
        c = _Fields(entry, f"progress.classes[{k}]")
        c.seen.clear()
        name = c.text("class")
        if not name or len(name) > 128:
            raise c.fail("class", "must be 1 to 128 characters")
        keyframes = c.integer("keyframes", low=0, high=MAX_KEYFRAMES)
        matched = c.take("matched")
        if (
            not isinstance(matched, list)
            or len(matched) > keyframes
            or not all(type(m) is int and 0 <= m <= MAX_SEQ for m in matched)
            or any(b < a for a, b in itertools.pairwise(matched))
        ):
            raise c.fail("matched", f"must be at most {keyframes} ascending sequence numbers")
        position = c.number("position")
        if not 0.0 <= position <= 1.0:
            raise c.fail("position", f"must be within [0, 1], got {position}")
        cost = c.number("cost")
        if cost < 0:
            raise c.fail("cost", f"must not be negative, got {cost}")
        tau = c.number("tau", positive=True)
        c.done()
        classes.append(ClassProgress(name, keyframes, tuple(matched), position, cost, tau))
    out = ProgressMessage(stream, frame, tuple(classes), f.number("source_time"), f.number("emit_time"))
    f.done()
    return out


def _status(f: _Fields) -> StatusMessage:
    out = StatusMessage(
        f.text("instance", STREAM_ID),
        f.choice("state", get_args(State)),  # type: ignore[arg-type]
        f.text("version"),
        f.integer("streams", low=0),
        f.number("started"),
    )
    f.done()
    return out


_READERS: dict[str, Callable[[_Fields], Message]] = {
    "skeleton": _skeleton,
    "pose": _pose,
    "frame": _frame,
    "end": _end,
    "detection": _detection,
    "boundary": _boundary,
    "progress": _progress,
    "status": _status,
}
