"""``mocapd run``: the daemon on its transports (DESIGN.md, the data flow; config.yaml says every knob).

Tasks, named, under one :class:`asyncio.TaskGroup`: one intake per source (decode, validate, route
into the :class:`~daemon.service.streams.StreamTable`), the recogniser, the idle evictor and the
``/healthz`` + ``/metrics`` server (and, for ``run --replay``, the replay). Intake only decodes and
queues; recognition runs on the same loop in slices (``service.tick_budget_ms``): each slice pushes
one queued pose of every stream with one through the bank, again and again until the budget is
spent, then yields, so receiving and publishing are never held up longer than a slice, and a burst
or a slow stream only grows the queues, which are bounded (a stream's oldest pose is dropped, never a
detection). Intake yields every few messages too, so a flood cannot starve recognition.

Shutdown (SIGTERM, SIGINT or SIGHUP through ``loop.add_signal_handler``: :data:`STOP_SIGNALS`):
intake stops, every queued pose is recognised and every stream flushed, what that gives is
published, the transports close (MQTT drains its outbox, publishes "offline" and disconnects; ZeroMQ
sockets linger), the metrics server stops; all within ``service.grace_s``, after which what is left
is cancelled. A second signal exits at once.

Every line on stderr is one JSON object (:func:`configure_logging`), an internal error's too: it is
logged with its traceback in a field (:func:`internal_error`) and the daemon exits with
:data:`EXIT_BUG`.
"""

from __future__ import annotations

import asyncio
import contextlib
import ctypes
import ctypes.util
import gc
import json
import logging
import os
import signal
import socket
import sys
import time
from collections import Counter
from collections.abc import Callable, Coroutine, Iterable
from dataclasses import replace
from typing import TYPE_CHECKING, Any, cast

import numpy as np

from daemon.config import Config, ConfigError, transports_named
from daemon.errors import MocapdError, printable
from daemon.library import Library
from daemon.recordings import read_rig_maps
from daemon.service.metrics import Metrics, open_http, serve_http
from daemon.service.streams import Emitted, Refused, StreamTable
from protocols.messages import (
    FRAME_WORD,
    STATUS_REMINDER_S,
    BoundaryMessage,
    EndMessage,
    FrameMessage,
    PoseMessage,
    ProgressMessage,
    SkeletonMessage,
    StatusMessage,
    WireError,
    decode,
    encode,
    parse_topic,
    topic,
)
from protocols.transport import STATE_TOPIC, Incoming, Outgoing, StartupError, Transport, make

if TYPE_CHECKING:
    from daemon.service.cluster import Cluster

EVENTS = (
    "gaps",
    "gap_frames",
    "idle",
    "ended",
    "skeleton_changed",
    "restarts",
    "aligning",
    "handed_over",
    "warmup_suppressed",
)
"""Counts of the stream table that are neither refusals nor drops."""
DROPS = ("lagging",)
"""Taken-in poses not recognised: a full queue; and ``recognizer_<problem>``, the recogniser's refusals."""
YIELD_EVERY = 64
"""Messages an intake takes before it lets the other tasks run."""
STATUS_EVERY_S = STATUS_REMINDER_S
"""How often the daemon's status goes out again (ZeroMQ and MQTT: :func:`reminder`)."""
CATCH_UP_POLL_S = 0.005
"""How often recognition looks whether the cluster transport has read a taken partition's buffer."""
STOP_SIGNALS = (signal.SIGTERM, signal.SIGINT, signal.SIGHUP)
"""The signals that stop the daemon gracefully (:func:`on_stop_signals`). SIGHUP, which a closed
terminal or an operator expecting a reload sends, is a stop too: the daemon reads its configuration
only when it starts."""
EXIT_BUG = 70
"""The exit status of an internal error, the command line's (``daemon.cli.EXIT_BUG``)."""


class _Stop(Exception):
    """Raised by the shutdown task once everything is published: ends the task group."""


class EventLog:
    """Structured warnings, one JSON line per event; per reason the first is logged (with its
    stream) and then at most one every ``every_s`` seconds, saying how many were not; informational
    per-stream events likewise, ``burst`` at a time. Per reason or event, not per stream: a flood of
    new stream ids must not grow the log or the memory."""

    def __init__(self, logger: logging.Logger, every_s: float = 10.0, burst: int = 20) -> None:
        self.logger = logger
        self.every_s = every_s
        self.burst = burst
        self._last: dict[str, float] = {}
        self._quiet: Counter[str] = Counter()
        self._window: dict[str, tuple[float, int]] = {}

    def warn(self, stream: str, reason: str, detail: str) -> None:
        key = reason
        now = time.monotonic()
        last = self._last.get(key)
        if last is not None and now - last < self.every_s:
            self._quiet[key] += 1
            return
        self._last[key] = now
        suppressed = self._quiet.pop(key, 0)
        self.logger.warning(
            "refused",
            extra={
                "fields": {"stream": stream, "reason": reason, "detail": detail, "since_last": suppressed}
            },
        )

    def info(self, event: str, fields: dict[str, Any]) -> None:
        """An informational per-stream event (a skeleton taken, one cleared): per event at most
        ``burst`` lines every ``every_s`` seconds, the next one saying how many were not logged, so
        a few streams are logged in full and a flood of new ids is not."""
        key, now = f"info {event}", time.monotonic()
        start, n = self._window.get(key, (now, 0))
        if now - start >= self.every_s:
            start, n = now, 0
        if n >= self.burst:
            self._quiet[key] += 1
            return
        self._window[key] = (start, n + 1)
        suppressed = self._quiet.pop(key, 0)
        self.logger.info(event, extra={"fields": fields | ({"since_last": suppressed} if suppressed else {})})


class JsonFormatter(logging.Formatter):
    """A log record as one JSON object: time, level, event, and its ``fields``."""

    def format(self, record: logging.LogRecord) -> str:
        body: dict[str, Any] = {
            "ts": round(record.created, 6),
            "level": record.levelname.lower(),
            "event": record.getMessage(),
        }
        body.update(getattr(record, "fields", {}))
        if record.exc_info:
            body["error"] = self.formatException(record.exc_info)
        return json.dumps(body, default=str)


def configure_logging(level: str) -> logging.Logger:
    """The ``mocapd`` logger writing JSON lines to stderr at ``level`` (the service's edge), and
    everything else that would write to stderr on its own routed through it, so that stderr holds
    one JSON object per line: Python's warnings (``logging.captureWarnings``) and any other logger
    (the root's handler). Floating-point overflow and invalid operations in numpy are not warned
    about: the decoder's one-sum finiteness check overflows on huge finite values, and makes NaN of
    infinities of both signs, before its exact check decides."""
    logger = logging.getLogger("mocapd")
    logger.handlers.clear()
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(JsonFormatter())
    logger.addHandler(handler)
    logger.setLevel(level.upper())
    logger.propagate = False
    root = logging.getLogger()
    root.handlers[:] = [handler]
    root.setLevel(logging.WARNING)
    logging.captureWarnings(True)
    np.seterr(over="ignore", invalid="ignore")
    return logger


class Service:
    """One daemon instance over ``transports`` (entered by :meth:`run`) with the library's classes."""

    def __init__(
        self,
        config: Config,
        library: Library,
        transports: list[Transport],
        *,
        instance: str,
        version: str,
        logger: logging.Logger,
        cluster: Cluster | None = None,
        remind: bool = True,
        mine: Callable[[str], bool] | None = None,
    ) -> None:
        self.config = config
        self.cluster = cluster
        self.instance = instance
        self.version = version
        self.log = logger
        self.events = EventLog(logger)
        self.transports = transports
        self.started = time.time()
        self.table = StreamTable(
            library,
            # in cluster mode every worker computes a stream's detection ids alike (per its epoch)
            session="cluster" if cluster is not None else f"{instance}/{self.started:.6f}",
            service=config.service,
            recognizer=config.recognizer,
            segmentation=config.segmentation,
            progress=config.progress,
            cluster=cluster is not None,
            rigs=read_rig_maps(config.replay.rig_maps),
        )
        self.rejects: Counter[str] = Counter()
        self.remind = remind
        self.mine = mine
        """Of a frame message's subjects, whether a stream is this process's (a worker of
        ``--workers N``, which every frame message reaches); None: all are."""
        self.relay_per_s = config.zmq.relay_per_s
        self._relayed: dict[str, tuple[int, float]] = {}  # stream -> its last relayed pose, skeleton
        self._relays: list[Outgoing] = []
        self.metrics = Metrics(config.metrics.stream_labels, self._tallies, self._gauge_values)
        self.stopping = False
        self.published = 0
        self._work = asyncio.Event()
        self._room = asyncio.Event()
        self._publishing = 0  # batches of emitted messages being published
        self._entered = False
        if cluster is not None:
            self.metrics.cluster = self._cluster_series
        for t in transports:
            t.announce(self._status("online"), self._status("offline"))

    def _status(self, state: str) -> Outgoing:
        message = StatusMessage(self.instance, state, self.version, len(self.table.streams), self.started)  # type: ignore[arg-type]
        return Outgoing(topic(message), encode(message), retain=True, reliable=True)

    def health(self) -> str | None:
        """None while every transport is connected and serving, else why not."""
        if self.stopping:
            return "stopping"
        if not self._entered:
            return "starting"
        if self.cluster is not None and (problem := self.cluster.problem) is not None:
            return f"cluster: {problem}"
        return next((p for t in self.transports if (p := t.problem) is not None), None)

    # ---------------------------------------------------------------------------------- intake

    def receive(self, incoming: Incoming) -> list[Emitted]:
        """Decode, validate and route one message; what it completed (a replaced stream's last
        detections). Refusals are counted and logged, never raised; so is any other exception that
        one message sets off (``internal``), so that no message can stop an intake."""
        started = time.perf_counter()
        if incoming.topic.startswith(STATE_TOPIC) and self.cluster is not None:
            self._resume(incoming.topic.removeprefix(STATE_TOPIC), incoming.payload)
            return []
        parsed = parse_topic(incoming.topic)
        stream = parsed[0] if parsed else "?"
        try:
            if not incoming.topic:  # what a transport received was not a [topic, payload] message
                raise WireError("undecodable", "not a [topic, payload] message")
            if parsed is None or parsed[1] not in ("skeleton", "pose", FRAME_WORD):
                raise Refused("topic", f"not a topic mocapd takes: {incoming.topic[:80]!r}")
            if not incoming.payload and parsed[1] == "skeleton":
                self.events.info("skeleton cleared", {"stream": stream})
                self.metrics.messages["clear"] += 1
                return []  # MQTT's way to delete a retained skeleton: nothing to take in
            message = decode(incoming.payload, self.config.service.max_message_bytes)
            if isinstance(message, FrameMessage):
                if parsed[1] != FRAME_WORD or message.source != stream:
                    raise Refused("schema", f"a frame message of {message.source!r} on {incoming.topic!r}")
                self._subjects(message)
                return []
            if not isinstance(message, SkeletonMessage | PoseMessage | EndMessage):
                raise Refused("type", f"a {type(message).__name__} is not taken in")
            on_pose_topic = isinstance(message, PoseMessage | EndMessage)
            if isinstance(message, EndMessage) and parsed[1] == FRAME_WORD:
                # a source of frame messages ends its streams on its own topic, after their frames
                if self.mine is not None and not self.mine(message.stream):
                    return []  # every worker gets it: the stream's owner takes it
            elif message.stream != stream or (parsed[1] == "pose") != on_pose_topic:
                raise Refused(
                    "schema", f"a {type(message).__name__} for {message.stream!r} on {incoming.topic!r}"
                )
            now = time.monotonic()
            if isinstance(message, EndMessage):
                out = self.table.end(message)
                self.metrics.messages["end"] += 1
                self._work.set()  # the stream goes once its queued poses are recognised
                return out
            if isinstance(message, PoseMessage):
                self.table.pose(message, now)
                self.metrics.messages["pose"] += 1  # taken in: a refused message counts in rejects only
                self.metrics.frame_in(stream)
                self._work.set()
                if self.relay_per_s:
                    self._relay(incoming, stream, message.seq, now)
                return []
            known = self.table.streams.get(stream)
            before = None if known is None else known.announced
            out = self.table.skeleton(message, now)
            if self.relay_per_s:
                self._relay(incoming, stream, None, now)
            if known is None and self.cluster is not None and self.cluster.transport.partial(stream):
                self.table.warm_up(stream)  # taken over mid-run from a buffer that lost the run's start
            self.metrics.messages["skeleton"] += 1
            if before != message:  # not a repeated announcement
                self.events.info("skeleton", {"stream": stream, "kind": message.kind, "rate": message.rate})
            return out
        except WireError as e:
            if self._counts(parsed):
                self.rejects[e.reason] += 1
                self.events.warn(stream, e.reason, e.detail)
        except Refused as e:
            self.rejects[e.reason] += 1
            self.events.warn(stream, e.reason, str(e))
            if e.reason == "no_skeleton":
                for t in self.transports:
                    t.ask_skeleton(stream)
        except Exception as e:  # a defect of mocapd's: it costs this one message, never the intake
            self.rejects["internal"] += 1
            self.events.warn(stream, "internal", printable(f"{type(e).__name__}: {e}"[:200]))
        finally:
            self.metrics.stage["decode"].observe(time.perf_counter() - started)
        return []

    def _counts(self, parsed: tuple[str, str] | None) -> bool:
        """Whether a message refused whole is this process's to count: a frame message reaches
        every worker, and the one its source's id routes to counts it."""
        return self.mine is None or parsed is None or parsed[1] != FRAME_WORD or self.mine(parsed[0])

    def _subjects(self, frame: FrameMessage) -> None:
        """Take in a frame message's poses, each as a pose message of its own would be taken (those
        of another worker's streams skipped, refused or not: :attr:`mine`); a subject refused is
        counted by its reason and refuses nothing else."""
        now = time.monotonic()
        taken, refused = self.table.frame(frame, now, self.mine)
        for stream, e in refused:
            self.rejects[e.reason] += 1
            self.events.warn(stream, e.reason, e.detail if isinstance(e, WireError) else str(e))
            if e.reason == "no_skeleton":
                for t in self.transports:
                    t.ask_skeleton(stream)
        if not taken:
            return
        self.metrics.messages["pose"] += len(taken)
        if self.metrics.stream_labels:
            for i in taken:
                self.metrics.frame_in(frame.streams[i])
        else:
            self.metrics.frames_in(len(taken))
        if self.relay_per_s:
            seqs = frame.seq.tolist()
            relayed = [i for i in taken if self._relaying(frame.streams[i], seqs[i], now)]
            poses = frame.poses() if relayed else []
            for i in relayed:
                pose = poses[i]
                assert isinstance(pose, PoseMessage)
                self._relays.append(Outgoing(topic(pose), encode(pose), relay=True))
        self._work.set()

    def _resume(self, stream: str, state: bytes) -> None:
        """Cluster mode: take ``stream`` in ``state``, from the checkpoint its partition was taken
        from (``docs/cluster.md``, "Checkpoints"), unless it is held already (its state here is as
        new); a state refused is counted (``state``) and the stream taken as a truncated history."""
        assert self.cluster is not None
        if stream in self.table.streams:
            return
        try:
            self.table.resume(state, time.monotonic())
        except Refused as e:
            self.rejects[e.reason] += 1
            self.events.warn(stream, e.reason, str(e))
            self.cluster.transport.refused(stream)

    def _relay(self, incoming: Incoming, stream: str, seq: int | None, now: float) -> None:
        """Pass a taken-in pose (``seq``) or skeleton (None) on for viewers (``zmq.relay_per_s``):
        a stream's skeleton at most once a second, its poses at most ``relay_per_s`` a second (every
        ``rate / relay_per_s``-th by sequence number)."""
        if self._relaying(stream, seq, now):
            self._relays.append(Outgoing(incoming.topic, incoming.payload, relay=True))

    def _relaying(self, stream: str, seq: int | None, now: float) -> bool:
        """Whether to pass this pose or skeleton on (:meth:`_relay`), remembered if so."""
        pose, skeleton_at = self._relayed.get(stream, (-1, -1.0))
        if seq is None:
            if skeleton_at >= 0 and now - skeleton_at < 1.0:
                return False
            skeleton_at = now
        else:
            step = max(1, round(self.table.streams[stream].announced.rate / self.relay_per_s))
            if 0 <= pose <= seq < pose + step:
                return False
            pose = seq
        self._relayed[stream] = (pose, skeleton_at)
        return True

    async def _pass_on(self) -> None:
        """The poses and skeletons taken in to pass on, published."""
        relays, self._relays = self._relays, []
        for out in relays:
            await self._send(out)

    async def _send(self, out: Outgoing) -> None:
        """``out`` on every sink."""
        for t in self.transports:
            sink = t.sink()
            if sink is not None:
                await sink.publish(out)

    async def _intake(self, transport: Transport) -> None:
        source = transport.source()
        assert source is not None
        n = 0
        paced = self.cluster is not None
        limit = max(1, self.config.service.queue_frames // 2)
        async for incoming in source:
            await self.publish_all(self.receive(incoming))
            if self._relays:
                await self._pass_on()
            n += 1
            if paced and self.table.queued >= limit:
                # a replayed buffer arrives faster than recognition: wait rather than drop (no stream
                # can queue more than ``limit`` poses, each tick takes one of every stream)
                while self.table.queued >= limit:  # also woken by streams forgotten (handed over)
                    self._room.clear()
                    with contextlib.suppress(TimeoutError):
                        async with asyncio.timeout(CATCH_UP_POLL_S):
                            await self._room.wait()
            elif n % YIELD_EVERY == 0:
                await asyncio.sleep(0)

    # ------------------------------------------------------------------------------ recognition

    async def _recognise(self) -> None:
        budget = self.config.service.tick_budget_ms / 1000
        stage = self.metrics.stage["recognise"]
        while True:
            await self._work.wait()
            self._work.clear()
            deadline = time.perf_counter() + budget
            while self.table.queued:
                c = self.cluster
                while c is not None and (c.transport.catching_up or c.holding):
                    # a partition just taken: read its buffer first, so that it is live sooner; or
                    # the membership paused (docs/cluster.md): keep every state, publish nothing
                    await asyncio.sleep(CATCH_UP_POLL_S)
                started = time.perf_counter()
                emitted, refused = self.table.tick()
                for stream, problem, why in refused:
                    self.events.warn(stream, problem, why)
                done = time.perf_counter()
                stage.observe(done - started)
                await self.publish_all(emitted)
                self._room.set()
                if done > deadline:
                    await asyncio.sleep(0)
                    deadline = time.perf_counter() + budget

    @property
    def settled(self) -> bool:
        """Whether everything the table has emitted has been published, none of it waiting in a
        transport (cluster checkpoints are taken only then)."""
        return not self._publishing and not any(t.pending for t in self.transports)

    async def publish_all(self, emitted: list[Emitted]) -> None:
        """``emitted`` published in turn (:attr:`settled` is false until the last is)."""
        if not emitted:
            return
        self._publishing += 1
        try:
            for e in emitted:
                await self.publish(e)
        finally:
            self._publishing -= 1

    async def publish(self, e: Emitted) -> None:
        started = time.perf_counter()
        message = replace(e.message, emit_time=time.time())
        if isinstance(message, ProgressMessage):  # QoS 0, not retained: the next one supersedes it
            out = Outgoing(topic(message), encode(message))
        else:
            out = Outgoing(topic(message), encode(message), reliable=True, key=message.id)
        await self._send(out)
        self.published += 1
        m = self.metrics
        m.stage["publish"].observe(time.perf_counter() - started)
        if isinstance(message, ProgressMessage):
            m.progress += 1
            return
        if isinstance(message, BoundaryMessage):
            m.boundaries += 1
            self.log.debug(
                "boundary",
                extra={"fields": {"id": message.id, "stream": message.stream, "frame": message.frame}},
            )
            return
        m.detection_out(message.stream)
        if e.arrived > 0:  # from the pose's arrival, on this process's clock: a source's may be anywhere
            m.end_to_end.observe(max(0.0, time.monotonic() - e.arrived))
        self.log.debug(
            "detection",
            extra={"fields": {"id": message.id, "stream": message.stream, "class": message.class_name}},
        )

    async def _housekeeping(self) -> None:
        beats = 0
        while True:
            await asyncio.sleep(1.0)
            beats += 1
            if self.remind and not self.stopping and beats % STATUS_EVERY_S == 0:
                await self._send(reminder(self._status("online")))
            if self.cluster is not None and self.cluster.holding:
                continue  # idle streams go once the membership is sound again (or are handed over)
            now, live = time.monotonic(), dict(self.table.streams)
            waiting = self.cluster.transport.waiting() if self.cluster is not None else frozenset()
            last = self.table.evict_idle(now, self.config.service.idle_s, waiting)
            for name, s in live.items():
                if name not in self.table.streams:  # per stream, throttled like the other such lines
                    fields = {"stream": name, "reason": "idle", "silent_s": round(now - s.seen, 1)}
                    self.events.info("stream forgotten", fields | {"poses": s.received})
            await self.publish_all(last)
            self.metrics.keep(self.table.streams)
            for gone in self._relayed.keys() - self.table.streams.keys():
                del self._relayed[gone]
            release_memory()

    def _tallies(self) -> tuple[Counter[str], Counter[str], Counter[str]]:
        """Rejects, drops and stream events by reason, for /metrics."""
        table = self.table.counts
        dropped = DROPS + tuple(k for k in table if k.startswith("recognizer_"))  # taken-in poses
        rejects = self.rejects + Counter({k: v for k, v in table.items() if k not in EVENTS + dropped})
        drops = Counter({k: table.get(k, 0) for k in dropped})
        for t in self.transports:
            drops.update(t.dropped())
        return rejects, drops, Counter({k: table.get(k, 0) for k in EVENTS})

    def _lag(self) -> float:
        """Seconds the oldest queued pose of any stream has waited (0: none queued)."""
        oldest = self.table.oldest()
        return 0.0 if oldest is None else round(max(0.0, time.time() - oldest), 3)

    def _cluster_series(self) -> list[tuple[str, str, str, float]]:
        c = self.cluster
        assert c is not None
        t, counts = c.transport, self.table.counts
        series = [
            ("partitions", "Partitions this worker owns", "gauge", len(t.owned)),
            ("members", "Live members of the cluster as this worker sees them", "gauge", len(c.members)),
            ("takeovers", "Partitions taken over after the first assignment", "counter", c.takeovers),
            ("replayed_poses", "Messages read from a partition's buffer on taking it", "counter", t.replayed),
            ("duplicates_suppressed", "Detections another worker had published", "counter", t.duplicates),
            ("checkpoints", "Partition checkpoints stored", "counter", t.checkpoints),
            ("resumed_partitions", "Partitions taken, read from a checkpoint", "counter", t.resumed),
            (
                "unbuffered",
                "Messages taken from a partition's subject alone: its buffer lost them or was late",
                "counter",
                t.unbuffered,
            ),
            (
                "warmup_suppressed",
                "Detections suppressed in a taken-over stream's warm-up",
                "counter",
                counts.get("warmup_suppressed", 0),
            ),
        ]
        return [(f"mocapd_cluster_{name}", doc, kind, value) for name, doc, kind, value in series]

    def _gauge_values(self) -> tuple[int, int, int, dict[str, bool]]:
        outbox = sum(t.pending for t in self.transports)
        up = {t.name: t.problem is None for t in self.transports}
        return len(self.table.streams), self.table.queued, outbox, up

    # --------------------------------------------------------------------------------- running

    async def run(
        self, stop: asyncio.Event, extra: Iterable[tuple[str, Callable[[], Coroutine[Any, Any, None]]]] = ()
    ) -> bool:
        """Serve until ``stop`` is set, then shut down (see the module docstring). ``extra``: more
        (name, coroutine function) tasks for the group. True if everything was published within the
        grace."""
        clean = True
        http = None
        if self.config.metrics.port:
            host, port = self.config.metrics.host, self.config.metrics.port
            try:
                http = await open_http(host, port, self.health, self.metrics)
            except OSError as e:
                why = os.strerror(e.errno).lower() if e.errno else str(e)
                raise StartupError("metrics.port", f"{host}:{port}: {why}") from None
        async with contextlib.AsyncExitStack() as stack:
            if http is not None:
                stack.push_async_callback(_closed, http)
            for t in self.transports:
                await stack.enter_async_context(t)
            if self.cluster is not None:
                await stack.enter_async_context(self.cluster)  # left before the transports close
            self._entered = True
            self.log.info(
                "online",
                extra={
                    "fields": {
                        "instance": self.instance,
                        "transports": [t.name for t in self.transports],
                        "endpoints": endpoints_of(self.transports),
                    }
                },
            )
            intakes: list[asyncio.Task[None]] = []
            failure: StartupError | None = None
            try:
                async with asyncio.TaskGroup() as group:
                    for t in self.transports:
                        if t.source() is not None:
                            intakes.append(group.create_task(self._intake(t), name=f"intake {t.name}"))
                    for name, fatal in fatal_of(self.transports):
                        group.create_task(fatal(), name=name)
                    group.create_task(self._recognise(), name="recognise")
                    group.create_task(self._housekeeping(), name="housekeeping")
                    if http is not None:
                        group.create_task(serve_http(http), name="http")
                    if self.cluster is not None:
                        group.create_task(
                            self.cluster.follow(self.table, lambda: self.settled), name="cluster membership"
                        )
                        group.create_task(self.cluster.report(self.table, self._lag), name="cluster status")
                        group.create_task(self.cluster.lead(), name="cluster balance")
                        if self.config.cluster.checkpoint_s > 0:
                            group.create_task(
                                self.cluster.checkpoint(self.table, lambda: self.settled),
                                name="cluster checkpoints",
                            )
                    for name, factory in extra:
                        group.create_task(factory(), name=name)
                    group.create_task(self._shutdown(stop, intakes), name="shutdown")
            except* _Stop:
                pass
            except* TimeoutError:
                clean = False
            except* StartupError as group:
                failure = cast(StartupError, group.exceptions[0])
            self.stopping = True
            self.log.info(
                "offline",
                extra={"fields": {"instance": self.instance, "published": self.published, "clean": clean}},
            )
        if failure is not None:  # another daemon took this one's place: said like a start-up error
            raise failure
        return clean

    async def _shutdown(self, stop: asyncio.Event, intakes: list[asyncio.Task[None]]) -> None:
        await stop.wait()
        deadline = asyncio.get_running_loop().time() + self.config.service.grace_s
        self.stopping = True
        self.log.info(
            "stopping",
            extra={
                "fields": {
                    "queued": self.table.queued,
                    "received": {name: st.received for name, st in self.table.streams.items()},
                }
            },
        )
        if self.cluster is not None:
            # the last checkpoints, then leave (the lease revoked: the others take over at once),
            # then publish nothing: a flush would publish end-of-motion detections the continuing
            # streams do not give
            await self.cluster.hand_over(self.table, lambda: self.settled)
            await self.cluster.leave()
            for task in intakes:
                task.cancel()
            self.table.counts["handed_over"] += len(self.table.streams)
            raise _Stop
        for task in intakes:
            task.cancel()
        for t in self.transports:  # "offline" says how many streams it held
            t.announce(self._status("online"), self._status("offline"))
        async with asyncio.timeout_at(deadline):
            for e in self.table.flush_all():
                await self.publish(e)
        left = max(0.1, deadline - asyncio.get_running_loop().time())
        for t in self.transports:
            t.drain_within(left)
        raise _Stop


def reminder(status: Outgoing) -> Outgoing:
    """``status`` again (``Outgoing.reminder``): for the subscribers that joined since it was
    published where nothing retains it (ZeroMQ), and, on MQTT too, for those that judge by it that
    the daemon still lives (``mocapd view``: one not reminded for two periods is stale, so a
    client's fake retained ``online`` cannot pass for a live daemon for long)."""
    return replace(status, reliable=False, reminder=True)


COLLECTOR_THRESHOLDS = (50_000, 20, 100)
"""The cyclic collector's generation thresholds while the daemon runs (Python's: 700, 10, 10). A
pass is set off by objects allocated and not yet freed, and every few hundred poses held a moment
(a decoded message, a queued pose) set one off that walks the streams' recognisers, made after
start-up and not frozen: 1 to 5 µs a pose (``python -m bench.bench_intake``, 50 subjects a
message: the queueing table's intake 8.6 µs a pose against 3.7 with these), for garbage that is
almost never cyclic."""


def settle_collector() -> None:
    """What exists when the daemon starts (the library, its plans, the modules) is there for good:
    collect once, keep the collector off it (``gc.freeze``), and pass less often from then on
    (:data:`COLLECTOR_THRESHOLDS`)."""
    gc.collect()
    gc.freeze()
    gc.set_threshold(*COLLECTOR_THRESHOLDS)


def release_memory() -> None:
    """Give the heap's free pages back to the system (glibc's ``malloc_trim``;
    elsewhere nothing), once a second: forgotten streams and bursts of messages leave memory free
    but mapped, and a daemon that once held many streams or took a flood would otherwise keep that
    much for good."""
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        trim = libc.malloc_trim
    except (OSError, AttributeError):
        return
    trim(0)


async def _closed(server: asyncio.Server) -> None:
    server.close()
    await server.wait_closed()


def fatal_of(transports: Iterable[Transport]) -> list[tuple[str, Callable[[], Coroutine[Any, Any, None]]]]:
    """(task name, coroutine function) of every transport that can fail for good while it serves
    (``fatal``, raising StartupError: MQTT's client id taken by another daemon), for the daemon's
    task group: when one raises, the daemon stops."""
    return [
        (f"{t.name} guard", fatal) for t in transports if (fatal := getattr(t, "fatal", None)) is not None
    ]


def endpoints_of(transports: Iterable[Transport]) -> dict[str, str]:
    """Where the transports that say so are, by setting (ZeroMQ's sockets: the port it bound for
    ``:0``), for the "online" log line."""
    out: dict[str, str] = {}
    for t in transports:
        out.update(getattr(t, "endpoints", {}))
    return out


def instance_name(config: Config) -> str:
    return config.service.instance or socket.gethostname().split(".")[0] or "mocapd"


def transports_of(config: Config, instance: str) -> list[Transport]:
    """The transports config names (sources and sinks, each made once), in that order."""
    return [
        make(use.module, use.settings, instance=instance, source=use.source, sink=use.sink)
        for use in transports_named(config)
    ]


def serve(
    config: Config,
    library: Library,
    *,
    version: str,
    extra: Callable[[Service, asyncio.Event], Iterable[tuple[str, Callable[[], Coroutine[Any, Any, None]]]]]
    | None = None,
) -> int:
    """Run the service until SIGTERM, SIGINT or SIGHUP (or ``extra``'s tasks set the stop event);
    the exit status: 0 when everything was published within the grace, 1 otherwise, 70 on an
    internal error (logged as one JSON line: :func:`internal_error`). A transport or the metrics
    server that cannot start raises :class:`~daemon.config.ConfigError` naming the setting, before
    "online" is published."""
    logger = configure_logging(config.logging.level)
    clustered = "cluster" in config.service.sources + config.service.sinks
    member = ""
    if clustered:
        from daemon.service.cluster import member_name, needed_seconds

        member = member_name(config.cluster)
        needed = needed_seconds(config.cluster, library, config)
        buffer_s = config.cluster.buffer_s or needed
        if buffer_s < needed:  # allowed (memory is the operator's), but a takeover may lose detections
            logger.warning(
                "buffer too short",
                extra={"fields": {"field": "cluster.buffer_s", "buffer_s": buffer_s, "needed_s": needed}},
            )
        config = replace(config, cluster=replace(config.cluster, buffer_s=buffer_s))
        if not config.service.instance:
            config = replace(config, service=replace(config.service, instance=member))
        logger.info("cluster", extra={"fields": {"member": member, "buffer_s": buffer_s}})
    instance = instance_name(config)

    async def main() -> bool:
        loop = asyncio.get_running_loop()
        stop = asyncio.Event()

        def on_signal(signum: int) -> None:
            if stop.is_set():
                os._exit(128 + signum)  # a second signal: at once
            logger.info("signal", extra={"fields": {"signal": signal.Signals(signum).name}})
            stop.set()

        on_stop_signals(loop, on_signal)
        transports = transports_of(config, instance)
        cluster = None
        if clustered:
            from daemon.service.cluster import Cluster

            (nats,) = [t for t in transports if t.name == "cluster"]
            cluster = Cluster(config.cluster, member, nats, logger)  # type: ignore[arg-type]
        service = Service(
            config,
            library,
            transports,
            instance=instance,
            version=version,
            logger=logger,
            cluster=cluster,
        )
        settle_collector()
        return await service.run(stop, extra(service, stop) if extra is not None else ())

    try:
        return 0 if asyncio.run(main()) else 1
    except StartupError as e:  # before anything was published: the setting, in one line
        raise ConfigError(e.reason, field=e.setting) from None
    except (MocapdError, OSError):
        raise  # bad input or a file: the command line's one line
    except Exception:
        return internal_error(logger)


def on_stop_signals(loop: asyncio.AbstractEventLoop, callback: Callable[[int], None]) -> None:
    """``callback(signum)`` on each of :data:`STOP_SIGNALS` (``loop.add_signal_handler``), except
    SIGHUP where it is ignored (``nohup mocapd run``: it stays ignored)."""
    for signum in STOP_SIGNALS:
        if signum != signal.SIGHUP or signal.getsignal(signum) != signal.SIG_IGN:
            loop.add_signal_handler(signum, callback, signum)


def internal_error(logger: logging.Logger) -> int:
    """The exception being handled (a bug) logged as one JSON line, ``internal error``: the
    exception in ``exception`` (a task group's first), its traceback in ``error``, with or without
    ``--debug``: a running daemon writes nothing else on stderr. :data:`EXIT_BUG`."""
    error = sys.exc_info()[1]
    while isinstance(error, BaseExceptionGroup) and error.exceptions:  # a task group's: the first inside
        error = error.exceptions[0]
    fields = {
        "exception": f"{type(error).__name__}: {error}",
        "bug": "a bug in mocapd: please report this line (docs/command-line.md, 'Reporting bugs')",
    }
    logger.critical("internal error", exc_info=True, extra={"fields": fields})
    return EXIT_BUG
