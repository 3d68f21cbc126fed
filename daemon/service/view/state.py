"""What ``mocapd view`` knows of the bus, and the JSON messages it sends the browsers about it.

Pure: :class:`ViewState` takes the bus's messages (:class:`~protocols.transport.Incoming`, each
decoded with :func:`protocols.messages.decode` and otherwise untrusted) and the clock, and returns
the updates for the browsers (JSON-ready dicts, ``{"type": ...}``); no sockets, no asyncio.

``relayed``: the bus is the daemon's ZeroMQ relay, which thins the poses (``zmq.relay_per_s``);
otherwise MQTT, where every pose is on the broker. On both a daemon says its status again every
:data:`~protocols.messages.STATUS_REMINDER_S`; one not heard for :data:`STALE_PERIODS` of them is
stale.

Per stream: its skeleton, the standard joints (:data:`replay.JOINT_NAMES`, whole millimetres, y up) of
at most ``poses_per_s`` poses a second (the only poses whose joints are computed: gathered by name
for a positions stream, by the package's forward kinematics for a channel stream), the poses
received a second, the lag (arrival - the pose's ``time``), poses missing (sequence gaps beyond
the relay's step), the latest
progress and the last :data:`DETECTIONS_KEPT` detections. A stream appears with its first pose,
detection or progress (a retained skeleton alone is remembered, not shown) and ends after
:data:`IDLE_S` seconds without any of them: it is kept, ended, with its detections (a detection the
daemon sends later, when it forgets the stream, joins them), until :data:`ENDED_KEPT` newer ones
have ended; a pose makes it live again. The session's last :data:`LOG_KEPT` detections, of every
stream, are kept in one log. Everything is bounded: at most ``max_streams`` live streams
(more are refused), :data:`SKELETONS_KEPT` skeletons, :data:`INSTANCES_KEPT` daemon instances, the
last :data:`REFUSED_KEPT` refusals (per reason at most one a second listed, all counted), and text
from the bus cut to :data:`TEXT_CHARS` characters.
"""

from __future__ import annotations

import math
from collections import Counter, OrderedDict, deque
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import numpy.typing as npt

from daemon.errors import InputError, printable
from daemon.recognizer import joint_order, skeleton_model
from protocols.messages import (
    DEFAULT_MAX_BYTES,
    FRAME_WORD,
    STATUS_REMINDER_S,
    STREAM_ID,
    DetectionMessage,
    EndMessage,
    FrameMessage,
    PoseMessage,
    ProgressMessage,
    SkeletonMessage,
    StatusMessage,
    WireError,
    decode,
    parse_topic,
)
from protocols.transport import Incoming
from replay import JOINT_NAMES, MocapFormatError, parse_asf
from replay.amc import DEG
from replay.bvh import parse_bvh_hierarchy
from replay.kinematics import KinematicModel, y_up
from replay.rigs import BUILT_IN, BvhPoses, RigMap, RigPlan, names_plan, standard_joints

Event = dict[str, Any]
"""One JSON message for the browsers."""

IDLE_S = 10.0
"""A stream with no pose, detection or progress for this long has ended."""
ENDED_KEPT = 50
"""Ended streams kept (with their detections); past it the longest ended is dropped (``gone``)."""
LOG_KEPT = 5000
"""Detections of the session kept in its log, newest last."""
MAX_STREAMS = 100
SKELETONS_KEPT = 400
DRAWERS_KEPT = 16
DETECTIONS_KEPT = 50
REFUSED_KEPT = 50
INSTANCES_KEPT = 16
STALE_PERIODS = 2
"""A status reminded every :data:`~protocols.messages.STATUS_REMINDER_S` and not heard for this many
periods is stale: its daemon went without a word (killed, cut off), or it never was one (a bus
client's retained fake)."""
TEXT_CHARS = 200
NEW_RUN_S = 1.0
"""A sequence number back by more than this many seconds of frames (or a new epoch) is a new run."""
GAP_S = 10.0
"""A gap longer than this many seconds of frames is a new run too, not that many poses missing."""

BONES = (
    ("root", "lhip"),
    ("lhip", "lknee"),
    ("lknee", "lankle"),
    ("lankle", "ltoes"),
    ("root", "rhip"),
    ("rhip", "rknee"),
    ("rknee", "rankle"),
    ("rankle", "rtoes"),
    ("root", "belly"),
    ("belly", "chest"),
    ("chest", "neck"),
    ("neck", "head"),
    ("head", "headtop"),
    ("lclavicle", "lshoulder"),
    ("lshoulder", "lelbow"),
    ("lelbow", "lwrist"),
    ("lwrist", "lfingers"),
    ("lwrist", "lthumb"),
    ("rclavicle", "rshoulder"),
    ("rshoulder", "relbow"),
    ("relbow", "rwrist"),
    ("rwrist", "rfingers"),
    ("rwrist", "rthumb"),
)
"""The stick figure: bones between standard joints (the clavicle joints sit on the neck)."""
BONE_INDICES = tuple((JOINT_NAMES.index(a), JOINT_NAMES.index(b)) for a, b in BONES)
TO_CM = {"m": 100.0, "cm": 1.0, "mm": 0.1, "in": 2.54, "asf": 1.0}


def closeness(position: float, cost: float, tau: float) -> float:
    """How near a class is to a detection, in [0, 1], as the page draws its bar: ``position``
    along the template times the share of τ the match's mean ``cost`` leaves, ``1 - cost/τ`` (0
    at or past τ). Only a match that reaches the template's end well within τ is near 1; one at
    position 0 (none within τ, cost = τ) is 0."""
    if not (tau > 0 and math.isfinite(position) and math.isfinite(cost)):
        return 0.0
    return round(min(1.0, max(0.0, position)) * max(0.0, 1.0 - cost / tau), 4)


def text(value: str, limit: int = TEXT_CHARS) -> str:
    """Text from the bus as it may be shown: control characters escaped, at most ``limit`` long."""
    out = printable(value[: limit * 4])
    return out if len(out) <= limit else out[: limit - 1] + "…"


class Drawer:
    """A skeleton's way from a pose to the standard joints (centimetres, y up, shape ``(26, 3)``)."""

    def __init__(self, skeleton: SkeletonMessage, rigs: Sequence[RigMap] = BUILT_IN) -> None:
        self.kind = skeleton.kind
        self.model: KinematicModel | None = None
        self.angles: npt.NDArray[np.intp] | None = None
        self.order: npt.NDArray[np.intp] | None = None
        self.rig: RigPlan | None = None
        self.bvh: BvhPoses | None = None
        try:
            if skeleton.bvh is not None:
                source = f"<skeleton of {skeleton.stream}>"
                self.bvh = BvhPoses(parse_bvh_hierarchy(skeleton.bvh, source), skeleton.up, rigs)
                self.width = self.bvh.width
            elif skeleton.asf is not None:
                parsed = parse_asf(skeleton.asf.splitlines(), f"<skeleton of {skeleton.stream}>")
                self.model = skeleton_model(parsed)
                self.width = len(parsed.channel_names)
                if skeleton.angle_unit == "deg":
                    self.angles = np.asarray(parsed.angle_channels, dtype=np.intp)
            else:
                assert skeleton.joints is not None
                self.width = len(skeleton.joints)
                # a rig's names mapped as the daemon maps them (replay.rigs), the standard ones gathered
                self.rig = names_plan(skeleton.joints, f"<skeleton of {skeleton.stream}>", rigs)
                if self.rig is None:
                    self.order = joint_order(skeleton.joints)
        except (InputError, MocapFormatError) as e:
            raise WireError("schema", f"skeleton: {e}") from None
        self.up = skeleton.up
        self.scale = TO_CM[skeleton.units]

    def joints(self, pose: PoseMessage) -> npt.NDArray[np.float64]:
        """The 26 standard joints of ``pose``, shape ``(26, 3)``; WireError ``shape`` if the pose is
        not of this skeleton."""
        if self.bvh is not None:
            if pose.channels is None or len(pose.channels) != self.width:
                raise WireError("shape", f"a pose of {self.width} channels expected")
            joints: npt.NDArray[np.float64] = self.bvh.joints(pose.channels.astype(np.float64)) * self.scale
            return joints
        if self.model is not None:
            if pose.channels is None or len(pose.channels) != self.width:
                raise WireError("shape", f"a pose of {self.width} channels expected")
            c = pose.channels.astype(np.float64)
            if self.angles is not None:
                c[self.angles] *= DEG
            out: npt.NDArray[np.float64] = self.model.joints(self.model.positions_frame(c, "cm"))
            return out
        if pose.positions is None or len(pose.positions) != self.width:
            raise WireError("shape", f"a pose of {self.width} joints expected")
        if self.rig is not None:
            p = standard_joints(pose.positions.astype(np.float64)[None], self.rig)[0] * self.scale
        else:
            assert self.order is not None
            p = pose.positions[self.order].astype(np.float64) * self.scale
        return y_up(p) if self.up == "z" else p


@dataclass
class StreamView:
    """One live stream as the view holds it."""

    name: str
    seen: float
    skeleton: SkeletonMessage | None = None
    drawer: Drawer | None = None
    epoch: str | None = None
    last_seq: int | None = None
    received: int = 0
    missing: int = 0
    step: int | None = None
    """Over ZeroMQ the daemon relays one pose in ``step`` (``zmq.relay_per_s``): the run's smallest
    sequence gap (None before its first); on MQTT every pose is on the bus."""
    drawn: int = 0
    next_draw: float = 0.0
    window_received: int = 0
    lag_sum: float = 0.0
    lag_n: int = 0
    rate: float = 0.0
    lag: float | None = None
    pose: Event | None = None
    progress: Event | None = None
    ended: bool = False
    detections: deque[Event] = field(default_factory=lambda: deque(maxlen=DETECTIONS_KEPT))
    ids: OrderedDict[str, None] = field(default_factory=OrderedDict)

    def info(self) -> Event:
        s = self.skeleton
        return {
            "type": "stream",
            "stream": self.name,
            "kind": None if s is None else s.kind,
            "rate": None if s is None else s.rate,
            "ended": self.ended,
        }

    def stats(self) -> Event:
        return {
            "stream": self.name,
            "rate": round(self.rate, 1),
            "lag": None if self.lag is None else round(self.lag, 4),
            "missing": self.missing,
            "sampled": self.step or 1,
            "received": self.received,
            "drawn": self.drawn,
        }


class ViewState:
    """The bus as the view sees it (module docstring): :meth:`take` each message, :meth:`tick`
    once a second, :meth:`snapshot` for a browser that connects."""

    def __init__(
        self,
        poses_per_s: float,
        *,
        idle_s: float = IDLE_S,
        max_streams: int = MAX_STREAMS,
        max_bytes: int = DEFAULT_MAX_BYTES,
        rigs: Sequence[RigMap] = BUILT_IN,
        relayed: bool = False,
    ) -> None:
        self.rigs = tuple(rigs)
        self.relayed = relayed
        self.stale_s = STALE_PERIODS * STATUS_REMINDER_S
        self.interval = 1.0 / poses_per_s
        self.poses_per_s = poses_per_s
        self.idle_s = idle_s
        self.max_streams = max_streams
        self.max_bytes = max_bytes
        self.streams: dict[str, StreamView] = {}
        """Live and ended streams, in the order they started or ended (ended ones move last)."""
        self.log: deque[Event] = deque(maxlen=LOG_KEPT)
        self.skeletons: OrderedDict[str, SkeletonMessage] = OrderedDict()
        self.statuses: OrderedDict[str, Event] = OrderedDict()
        self._heard: dict[str, float] = {}
        self.refused: deque[Event] = deque(maxlen=REFUSED_KEPT)
        self.refusals: Counter[str] = Counter()
        self.received = 0
        self._drawers: OrderedDict[tuple[object, ...], Drawer] = OrderedDict()
        self._listed: dict[str, float] = {}
        self._last_tick: float | None = None
        self._made: list[Event] = []  # the streams the message being taken made

    # -------------------------------------------------------------------------------- intake

    def take(self, incoming: Incoming, now: float) -> list[Event]:
        """The browsers' updates from one message of the bus (``now``: a monotonic clock); a message
        that cannot be used is counted and listed (a ``refused`` update), never raised."""
        self.received += 1
        self._made = []
        try:
            out = self._take(incoming, now)
        except WireError as e:
            out = self._refuse(incoming, e.reason, e.detail, now)
        return self._made + out if self._made else out

    def _take(self, incoming: Incoming, now: float) -> list[Event]:
        if not incoming.topic:
            raise WireError("undecodable", "not a [topic, payload] message")
        parts = incoming.topic.split("/")
        if len(parts) == 3 and parts[0] == "mocapd" and parts[2] == "status":
            return self._status(parts[1], incoming, now)
        parsed = parse_topic(incoming.topic)
        if parsed is None:
            raise WireError("schema", "not a topic of mocapd's (mocap/<stream>/<kind>)")
        stream, word = parsed
        if word == FRAME_WORD:
            return self._frame(stream, incoming, now)
        if word not in ("skeleton", "pose", "detections", "progress"):
            return []  # boundaries and the like: not shown
        if word == "skeleton" and not incoming.payload:  # MQTT's way to clear a retained skeleton
            self.skeletons.pop(stream, None)
            return []
        message = decode(incoming.payload, self.max_bytes)
        if word == "pose" and isinstance(message, EndMessage) and message.stream == stream:
            return []  # a run's end: the stream's last pose is shown until it goes quiet
        wanted = {
            "skeleton": SkeletonMessage,
            "pose": PoseMessage,
            "detections": DetectionMessage,
            "progress": ProgressMessage,
        }[word]
        if not isinstance(message, wanted) or isinstance(message, StatusMessage | FrameMessage):
            raise WireError("type", f"a {type(message).__name__} on a {word} topic")
        if message.stream != stream:
            raise WireError("schema", f"a message of stream {message.stream!r} on another stream's topic")
        if isinstance(message, SkeletonMessage):
            return self._skeleton(message)
        if isinstance(message, PoseMessage):
            return self._pose(message, incoming.received, now)
        if isinstance(message, DetectionMessage):
            return self._detection(message, now)
        assert isinstance(message, ProgressMessage)
        return self._progress(message, now)

    def _frame(self, source: str, incoming: Incoming, now: float) -> list[Event]:
        """A frame message's subjects, each as its own pose message would be shown (a subject that
        cannot be used refused alone); a run's end on the source's topic: nothing."""
        message = decode(incoming.payload, self.max_bytes)
        if isinstance(message, EndMessage):
            return []
        if not isinstance(message, FrameMessage):
            raise WireError("type", f"a {type(message).__name__} on a frame topic")
        if message.source != source:
            raise WireError("schema", f"a frame message of {message.source!r} on another source's topic")
        out: list[Event] = []
        for pose in message.poses():
            if isinstance(pose, WireError):
                out += self._refuse(incoming, pose.reason, pose.detail, now)
            else:
                out += self._pose(pose, incoming.received, now)
        return out

    def _status(self, instance: str, incoming: Incoming, now: float) -> list[Event]:
        if not STREAM_ID.fullmatch(instance):
            raise WireError("schema", "not an instance id in the status topic")
        if not incoming.payload:  # a retained status cleared
            self._heard.pop(instance, None)
            return (
                [{"type": "status_gone", "instance": instance}] if self.statuses.pop(instance, None) else []
            )
        message = decode(incoming.payload, self.max_bytes)
        if not isinstance(message, StatusMessage) or message.instance != instance:
            raise WireError("schema", "not the status of the topic's instance")
        event: Event = {
            "type": "status",
            "instance": message.instance,
            "state": message.state,
            "version": text(message.version, 40),
            "streams": message.streams,
            "started": message.started,
            "stale": False,
        }
        self.statuses[instance] = event
        self.statuses.move_to_end(instance)
        self._heard[instance] = now
        out = [event]
        while len(self.statuses) > INSTANCES_KEPT:
            # the least telling goes first: a stale or offline one, else the longest unheard
            gone = next((i for i, e in self.statuses.items() if e["stale"] or e["state"] != "online"), None)
            gone = next(iter(self.statuses)) if gone is None else gone
            del self.statuses[gone]
            self._heard.pop(gone, None)
            out.append({"type": "status_gone", "instance": gone})  # the pages forget it too
        return out

    def _skeleton(self, message: SkeletonMessage) -> list[Event]:
        s = self.streams.get(message.stream)
        if s is not None and s.skeleton == message:
            return []  # announced again
        drawer = self._drawer(message)  # a skeleton it cannot use is refused here, the stream kept
        self.skeletons[message.stream] = message
        self.skeletons.move_to_end(message.stream)
        while len(self.skeletons) > SKELETONS_KEPT:
            self.skeletons.popitem(last=False)
        if s is None:
            return []
        same = s.skeleton is not None and _unepoched(s.skeleton) == _unepoched(message)
        s.drawer, s.skeleton = drawer, message
        return [] if same else [s.info()]

    def _drawer(self, message: SkeletonMessage) -> Drawer:
        """The drawer of ``message`` (many streams announce the same skeleton: made once for the
        last :data:`DRAWERS_KEPT`)."""
        key = (message.asf, message.angle_unit, message.joints, message.up, message.units, message.bvh)
        drawer = self._drawers.pop(key, None) or Drawer(message, self.rigs)
        self._drawers[key] = drawer
        while len(self._drawers) > DRAWERS_KEPT:
            self._drawers.popitem(last=False)
        return drawer

    def _stream(self, name: str, now: float, revive: bool = True) -> StreamView:
        """The stream ``name`` (made if new: its ``stream`` update goes out whatever follows); an
        ended one stays ended unless ``revive`` (a pose: it streams again)."""
        s = self.streams.get(name)
        if s is not None and not (s.ended and revive):
            s.seen = now
            return s
        if sum(not v.ended for v in self.streams.values()) >= self.max_streams:
            raise WireError("schema", f"more than {self.max_streams} streams at once: not shown")
        if s is not None:  # ended, and live again
            s.ended, s.seen = False, now
            self._made.append(s.info())
            return s
        s = self.streams[name] = StreamView(name, now)
        known = self.skeletons.get(name)
        if known is not None:
            s.drawer, s.skeleton = self._drawer(known), known
        self._made.append(s.info())
        return s

    def _pose(self, pose: PoseMessage, arrived: float, now: float) -> list[Event]:
        s = self._stream(pose.stream, now)
        rate = s.skeleton.rate if s.skeleton is not None else 120.0
        last = s.last_seq
        if last is None or pose.epoch != s.epoch or pose.seq < last - NEW_RUN_S * rate:
            s.epoch = pose.epoch  # a new run of its source: numbered afresh
            s.step = None
        elif pose.seq <= last:
            return []  # a repeat, or one overtaken
        elif (gap := pose.seq - last) - 1 <= GAP_S * rate:
            if self.relayed:  # the relay's thinning is not the publisher's loss; what is beyond it is
                s.step = gap if s.step is None else min(s.step, gap)
            s.missing += gap - (s.step or 1)
        s.last_seq = pose.seq
        s.received += 1
        s.window_received += 1
        s.lag_sum += arrived - pose.time
        s.lag_n += 1
        # at most one pose an interval on average; half an interval's slack takes a stream at the
        # limit whole, however its poses jitter
        if now < s.next_draw - 0.5 * self.interval or s.drawer is None:
            return []
        s.next_draw = max(s.next_draw + self.interval, now + 0.5 * self.interval)
        joints = s.drawer.joints(pose)
        if not np.isfinite(joints).all():
            raise WireError("non_finite", "the pose's joints are not finite")
        s.drawn += 1
        s.pose = {
            "type": "pose",
            "stream": s.name,
            "seq": pose.seq,
            "time": pose.time,
            "p": np.rint(joints * 10).astype(np.int32).ravel().tolist(),  # mm: ints cost JSON half
        }
        return [s.pose]

    def _detection(self, d: DetectionMessage, now: float) -> list[Event]:
        s = self._stream(d.stream, now, revive=False)
        if d.id in s.ids:
            return []  # QoS 1 may deliver one twice
        s.ids[d.id] = None
        while len(s.ids) > 4 * DETECTIONS_KEPT:
            s.ids.popitem(last=False)
        event: Event = {
            "type": "detection",
            "stream": s.name,
            "id": text(d.id, 80),
            "class": text(d.class_name, 128),
            "start_frame": d.start_frame,
            "end_frame": d.end_frame,
            "cost": d.cost,
            "tau": d.tau,
            "emitted_at_frame": d.emitted_at_frame,
            "source_time": d.source_time,
            "emit_time": d.emit_time,
        }
        s.detections.append(event)
        self.log.append(event)
        return [event]

    def _progress(self, p: ProgressMessage, now: float) -> list[Event]:
        s = self._stream(p.stream, now, revive=False)
        s.progress = {
            "type": "progress",
            "stream": s.name,
            "frame": p.frame,
            "source_time": p.source_time,
            "emit_time": p.emit_time,
            "classes": [
                {
                    "class": text(c.class_name, 128),
                    "keyframes": c.keyframes,
                    "matched": list(c.matched),
                    "position": c.position,
                    "cost": c.cost,
                    "tau": c.tau,
                    "level": closeness(c.position, c.cost, c.tau),
                }
                for c in p.classes
            ],
        }
        return [s.progress]

    def _refuse(self, incoming: Incoming, reason: str, detail: str, now: float) -> list[Event]:
        self.refusals[reason] += 1
        if now - self._listed.get(reason, -math.inf) < 1.0:
            return []
        self._listed[reason] = now
        event: Event = {
            "type": "refused",
            "topic": text(incoming.topic),
            "reason": reason,
            "detail": text(detail),
            "time": incoming.received,
        }
        self.refused.append(event)
        return [event]

    # ----------------------------------------------------------------------------- the clock

    def tick(self, now: float) -> list[Event]:
        """Once a second: the online statuses not reminded for :attr:`stale_s` marked stale (a
        ``status`` update), the live streams silent for :attr:`idle_s` ended (``ended``) and the
        ended ones past :data:`ENDED_KEPT` dropped (``gone``), then every live stream's rate, lag
        and missing poses (``stats``)."""
        out: list[Event] = []
        for instance, event in self.statuses.items():
            silent = now - self._heard[instance]
            if event["state"] == "online" and not event["stale"] and silent > self.stale_s:
                event["stale"] = True
                out.append(event)
        for name in [n for n, s in self.streams.items() if not s.ended and now - s.seen > self.idle_s]:
            s = self.streams.pop(name)
            s.ended, s.pose = True, None
            self.streams[name] = s  # ended ones in the order they ended
            out.append({"type": "ended", "stream": name})
        ended = [n for n, s in self.streams.items() if s.ended]
        for name in ended[: max(0, len(ended) - ENDED_KEPT)]:
            del self.streams[name]
            out.append({"type": "gone", "stream": name})
        elapsed = None if self._last_tick is None else max(1e-3, now - self._last_tick)
        self._last_tick = now
        for s in self.streams.values():
            if s.ended:
                continue
            if elapsed is not None:
                s.rate = s.window_received / elapsed
            s.lag = s.lag_sum / s.lag_n if s.lag_n else None
            s.window_received, s.lag_sum, s.lag_n = 0, 0.0, 0
        out.append({"type": "stats", "streams": [s.stats() for s in self.streams.values() if not s.ended]})
        return out

    def snapshot(self) -> Event:
        """Everything a browser that connects needs, in one message."""
        return {
            "type": "snapshot",
            "poses_per_s": self.poses_per_s,
            "idle_s": self.idle_s,
            "joints": list(JOINT_NAMES),
            "bones": [list(b) for b in BONE_INDICES],
            "streams": [
                s.info()
                | {
                    "pose": s.pose,
                    "progress": s.progress,
                    "detections": list(s.detections),
                    "stats": s.stats(),
                }
                for s in self.streams.values()
            ],
            "statuses": list(self.statuses.values()),
            "log": list(self.log),
            "refused": list(self.refused),
            "refusals": dict(self.refusals),
        }


def _unepoched(message: SkeletonMessage) -> SkeletonMessage:
    """The skeleton without its run (the same body announced by a restarted source)."""
    return SkeletonMessage(
        message.stream,
        message.rate,
        message.joints,
        message.up,
        message.units,
        message.asf,
        message.angle_unit,
        bvh=message.bvh,
    )


def daemon_health(status: int | None, healthz: str, metrics: str | None) -> Event:
    """The ``health`` update of one poll of the daemon's ``/healthz`` (``status``, None: no answer;
    ``healthz``: its text or why it did not answer) and ``/metrics`` (its prometheus text, None: not
    read): healthy or not and why, the poses it dropped (``mocapd_drops_total``, all reasons and by
    reason) and, where its streams are labelled, each stream's poses in and detections out."""
    from prometheus_client.parser import text_string_to_metric_families

    drops: float | None = None
    by_reason: dict[str, float] = {}
    streams: dict[str, dict[str, float]] = {}
    problem = None
    if metrics is not None:
        try:
            for family in text_string_to_metric_families(metrics):
                for sample in family.samples:
                    if sample.name == "mocapd_drops_total":
                        drops = (drops or 0.0) + sample.value
                        reason = text(str(sample.labels.get("reason", "")), 40)
                        by_reason[reason] = by_reason.get(reason, 0.0) + sample.value
                    elif sample.name in ("mocapd_frames_in_total", "mocapd_detections_out_total"):
                        stream = sample.labels.get("stream")
                        if stream and len(streams) < MAX_STREAMS:
                            key = "frames_in" if sample.name == "mocapd_frames_in_total" else "detections_out"
                            streams.setdefault(text(stream, 128), {})[key] = sample.value
        except ValueError as e:  # not a prometheus exposition
            problem = text(f"/metrics: {e}", 120)
    return {
        "type": "health",
        "healthy": None if status is None else status == 200,
        "text": text(healthz.strip(), 200),
        "drops": drops,
        "drops_by_reason": by_reason,
        "streams": streams,
        "problem": problem,
    }
