"""``mocapd run --workers N``: one front process and N recognition processes (DESIGN.md, "Scale").

The front owns the daemon's transports exactly as one process would (the ZeroMQ poses and detections
sockets, the MQTT client, stdout, ``/healthz`` and ``/metrics``) and decodes nothing: for each
message it reads the stream id from the topic (``mocap/<stream>/<word>``) and forwards the raw
``[topic, payload]`` to worker :func:`protocols.routing.worker_of` (a stable hash of the id) over a
PUSH socket on ``ipc://``, the pairs one wakeup took for a worker packed into one frame (a msgpack
array ``[topic, payload, topic, payload, ...]``); over ZeroMQ this loop is compiled
(:mod:`protocols._route`: no Python object per message but the topic's bytes for the lookup), in
Python where it cannot be. A worker is a
:class:`~daemon.service.app.Service` whose only transport is :class:`FrontChannel`: it takes those
messages in, decodes, validates and recognises them as the single process does, and sends what it
publishes (detections, boundaries) back to the front, which publishes it on its sinks. Decoding and
recognising cost per pose and parallelise; the front's cost per message is a ZeroMQ receive, a
topic lookup and its share of one send (0.3 µs compiled, about 7 µs in Python); one stream always
takes one path (one PUSH queue, one worker, one PUSH back), so its order is kept. Over MQTT the
front is the MQTT client likewise, forwarding raw payloads by hash (a shared subscription would
hand one stream's messages round-robin to several workers).

A worker that dies is started again, after 0.2 s, doubling up to 10 s while it keeps dying within
10 s of its start. When it is up (it says "ready") the front asks every publisher for its skeleton
(over ZeroMQ a fresh subscription reaching the publishers' XPUB sockets:
:meth:`protocols.zeromq.ZmqTransport.ask_skeletons`); a worker that gets poses of a stream it does
not know asks the front, which asks the transports (MQTT: the retained skeleton again). Poses for a
worker that is down are dropped and counted (``drops{reason="worker_down"}``).

``/metrics`` is the front's: on each scrape it fetches every worker's exposition (each worker serves
its own on a free loopback port, which it tells the front) and sums the series of the same name and
labels, so the series are those of one process, plus ``mocapd_workers``, ``mocapd_worker_up{worker}``
and ``mocapd_worker_restarts_total{worker}``; the transports' series (``transport_up``, ``outbox``,
their drops) are the front's. ``/healthz`` is 503 while a worker is starting or restarting.

Shutdown: SIGTERM, SIGINT or SIGHUP to the front stops its intake and sends SIGTERM to every
worker, which drains as the single process does (within ``service.grace_s``); the front publishes
what they send until the last has exited (a worker still running ``grace_s`` + 2 s later is killed),
then closes its transports. A second signal kills the workers and exits at once. Workers ignore
SIGINT and SIGHUP (a terminal's Ctrl-C or hangup reaches the whole process group: the front
decides) and stop by themselves when the front is gone. Whatever escapes a worker is logged as one
JSON line and ends it with status 70 (:func:`main`); the front starts it again.

The worker processes are ``python -c BOOT ROOT INDEX SETUP`` (:data:`BOOT`; SETUP: the pickled
:class:`WorkerSetup`, in a private temporary directory with the ipc sockets).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import os
import pickle
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from collections import Counter
from collections.abc import AsyncIterator, Iterable
from dataclasses import dataclass, replace
from pathlib import Path
from types import TracebackType
from typing import cast

import msgpack
import zmq
import zmq.asyncio
from prometheus_client import CollectorRegistry, generate_latest
from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily, Metric
from prometheus_client.parser import text_string_to_metric_families
from prometheus_client.registry import Collector

from daemon.config import Config, ConfigError
from daemon.errors import MocapdError
from daemon.library import Library
from daemon.service.app import (
    STATUS_EVERY_S,
    Service,
    configure_logging,
    endpoints_of,
    fatal_of,
    instance_name,
    internal_error,
    on_stop_signals,
    reminder,
    settle_collector,
    transports_of,
)
from daemon.service.metrics import open_http, serve_http
from protocols.messages import StatusMessage, decode, encode, topic
from protocols.routing import Routes, choose, mine, routes_cached, split
from protocols.transport import Incoming, Outgoing, StartupError, Transport
from protocols.zeromq import open_socket, receive

PUBLISH, READY, ASK, STREAMS = b"p", b"r", b"a", b"n"
"""What a worker sends the front, the first frame of each message: ``[p, topic, payload, flags]``
to publish (flags: ``r`` retained, ``q`` reliable, QoS 1, ``p`` a relayed pose or skeleton),
``[r, index, metrics port, pid]`` once it serves, ``[a, stream]`` to have a stream's skeleton sent
again, ``[n, index, streams]`` every second."""
RESTART_MIN_S, RESTART_MAX_S, STEADY_S = 0.2, 10.0, 10.0
"""Restart back-off: from the first, doubling to the second while a worker dies within STEADY_S of
its start."""
DRAIN_MESSAGES = 512
"""The most messages taken per wakeup, so that receiving yields to the other tasks."""
NOBLOCK = int(zmq.NOBLOCK)
"""As a plain int (an enum member costs more than a small message's send)."""
packb = msgpack.Packer(use_bin_type=True).pack
"""The frame of the messages the front sends a worker at once: ``[topic, payload, ...]``, bytes."""


def unpackb(frame: bytes) -> list[bytes]:
    """The ``[topic, payload, ...]`` of a frame :data:`packb` made."""
    out: list[bytes] = msgpack.unpackb(frame, use_list=True)
    return out


YIELD_EVERY = 64
"""Messages the front routes before it lets its other tasks run."""
BOOT = """import signal, sys
signal.signal(signal.SIGINT, signal.SIG_IGN)
signal.signal(signal.SIGHUP, signal.SIG_IGN)
root = sys.argv[1]
if root in sys.path[1:]:
    del sys.path[0]
else:
    sys.path[0] = root
from daemon.service.workers import main
sys.exit(main(sys.argv[2:]))
"""
"""A worker process's program (``python -c BOOT ROOT INDEX SETUP``): SIGINT and SIGHUP ignored
first (a terminal's Ctrl-C or hangup reaches the whole process group: the front decides), this very
code (the directory that holds the front's ``daemon`` package in place of the working directory, or
nothing added where it is already on the path, as an installed package's is), then :func:`main`."""
CONNECT_TIMEOUT_MS = 10_000
"""How long a worker waits for its connection to the front."""
READY_TIMEOUT_S = 60.0
"""How long the front waits for its workers to serve at start."""
WORKER_FAMILIES_SKIPPED = frozenset({"mocapd_transport_up", "mocapd_outbox"})
"""A worker's series about its channel to the front, not the daemon's transports."""


class _Stop(Exception):
    """Raised by the front's shutdown task once everything is published: ends the task group."""


@dataclass(frozen=True)
class WorkerSetup:
    """What every worker process is started with (pickled once into a file)."""

    config: Config
    library: Library
    instance: str
    version: str
    inbound: tuple[str, ...]
    """The front's PUSH endpoint of each worker (``ipc://``)."""
    outbound: str
    """The front's PULL endpoint all workers send to."""
    front_pid: int


# ------------------------------------------------------------------------------------ the worker


class FrontChannel:
    """A worker's one transport (:class:`protocols.transport.Transport`): the raw messages the
    front routes to it in (PULL), what it publishes out to the front (PUSH)."""

    name = "front"

    def __init__(self, setup: WorkerSetup, index: int) -> None:
        self.index = index
        self.inbound = setup.inbound[index]
        self.outbound = setup.outbound
        self.hwm = setup.config.zmq.hwm
        self.linger_ms = max(setup.config.zmq.linger_ms, round(setup.config.service.grace_s * 1000))
        self._ctx: zmq.asyncio.Context | None = None
        self._pull: zmq.asyncio.Socket | None = None
        self._push_socket: zmq.asyncio.Socket | None = None
        self._push: zmq.Socket[bytes] | None = None
        self._dropped = 0

    def announce(self, online: Outgoing, offline: Outgoing) -> None:
        """The front announces the daemon; once connected (the service says "offline" as it stops),
        the streams the status counts go to the front, for its own "offline"."""
        if self._push is not None:
            status = decode(offline.payload)
            if isinstance(status, StatusMessage):
                self.tell(STREAMS, str(self.index).encode(), str(status.streams).encode())

    async def __aenter__(self) -> FrontChannel:
        self._ctx = zmq.asyncio.Context()
        # "ready" only once the front's queue to this worker has its end here: a skeleton the
        # publishers announce when the front says so must not find no one to go to
        pull = self._ctx.socket(zmq.PULL)
        pull.setsockopt(zmq.RCVHWM, self.hwm)
        pull.setsockopt(zmq.LINGER, 0)
        monitor = pull.get_monitor_socket(zmq.EVENT_HANDSHAKE_SUCCEEDED)
        try:
            pull.connect(self.inbound)
            if not await monitor.poll(CONNECT_TIMEOUT_MS):
                raise StartupError("service.workers", f"worker {self.index}: no connection to the front")
        finally:
            pull.disable_monitor()
            monitor.close(linger=0)
        self._pull = pull
        push = open_socket(
            self._ctx, zmq.PUSH, self.outbound, bind=False, hwm=self.hwm, linger_ms=self.linger_ms
        )
        self._push_socket, self._push = push, zmq.Socket.shadow(push.underlying)
        return self

    async def __aexit__(
        self, kind: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        if self._pull is not None:
            self._pull.close(linger=0)
        if self._push_socket is not None:
            self._push_socket.close(linger=self.linger_ms)  # what it publishes reaches the front
        self._pull = self._push_socket = self._push = None
        if self._ctx is not None:
            self._ctx.term()
            self._ctx = None

    def source(self) -> _Inbound | None:
        return None if self._pull is None else _Inbound(self._pull)

    def sink(self) -> FrontChannel | None:
        return None if self._push is None else self

    def tell(self, *frames: bytes) -> None:
        """Send the front ``frames`` (dropped, and counted, if its queue is full)."""
        assert self._push is not None
        try:
            self._push.send_multipart(frames, flags=zmq.NOBLOCK)
        except zmq.Again:
            self._dropped += 1

    async def publish(self, message: Outgoing) -> None:
        self.tell(PUBLISH, message.topic.encode(), message.payload, flags(message))

    def ask_skeleton(self, stream: str) -> None:
        self.tell(ASK, stream.encode())

    def drain_within(self, seconds: float) -> None:
        self.linger_ms = min(self.linger_ms, max(0, round(seconds * 1000)))

    @property
    def pending(self) -> int:
        return 0

    @property
    def problem(self) -> str | None:
        return None if self._ctx is not None else "front: not connected"

    def dropped(self) -> dict[str, int]:
        return {"worker_send_full": self._dropped}


def flags(message: Outgoing) -> bytes:
    """How the front publishes ``message`` for a worker: ``r`` retained, ``q`` reliable (a
    detection, a boundary, a status; a progress event is neither), ``p`` relayed (a pose or a
    skeleton passed on for viewers)."""
    return b"".join(
        f for f, on in ((b"r", message.retain), (b"q", message.reliable), (b"p", message.relay)) if on
    )


class _Inbound:
    """The messages the front routed to this worker, as :class:`Incoming`: each message of the
    front holds one or more ``topic, payload`` pairs (an empty topic: what came was not a
    ``[topic, payload]`` message, which the service refuses as undecodable)."""

    def __init__(self, sock: zmq.asyncio.Socket) -> None:
        self._sock = sock

    async def __aiter__(self) -> AsyncIterator[Incoming]:
        sync: zmq.Socket[bytes] = zmq.Socket.shadow(self._sock.underlying)
        while True:
            await self._sock.poll()
            received = time.time()
            for _ in range(DRAIN_MESSAGES):
                try:
                    parts = unpackb(sync.recv(NOBLOCK))
                except zmq.Again:
                    break
                for i in range(0, len(parts) - 1, 2):
                    name = parts[i]
                    yield Incoming(name.decode("utf-8", "replace"), parts[i + 1], received)


class _Tagged(logging.Filter):
    """Every log line of a worker says which."""

    def __init__(self, index: int) -> None:
        super().__init__()
        self.index = index

    def filter(self, record: logging.LogRecord) -> bool:
        record.fields = {"worker": self.index, **getattr(record, "fields", {})}
        return True


def pin(index: int, workers: int) -> None:
    """Keep worker ``index`` of ``workers`` on one core of those the process may use, when there
    are enough for every worker to have its own: left to migrate, two workers that land on one
    core for a while add their ticks to each other's latency."""
    if not hasattr(os, "sched_getaffinity"):
        return
    cores = sorted(os.sched_getaffinity(0))
    if len(cores) >= workers:
        os.sched_setaffinity(0, {cores[index]})


def tagged_logging(level: str, index: int) -> logging.Logger:
    """:func:`~daemon.service.app.configure_logging` for worker ``index``: its lines say which."""
    logger = configure_logging(level)
    for handler in logger.handlers:
        handler.addFilter(_Tagged(index))
    return logger


def run_worker(setup: WorkerSetup, index: int) -> int:
    """Worker ``index``'s service until SIGTERM (or its front is gone); 0 when everything was
    published within the grace."""
    config = replace(setup.config, metrics=replace(setup.config.metrics, port=0))
    logger = tagged_logging(config.logging.level, index)
    pin(index, len(setup.inbound))

    async def main() -> bool:
        loop = asyncio.get_running_loop()
        stop = asyncio.Event()

        def on_signal() -> None:
            if stop.is_set():
                os._exit(128 + signal.SIGTERM)
            stop.set()

        loop.add_signal_handler(signal.SIGTERM, on_signal)
        channel = FrontChannel(setup, index)
        service = Service(  # the front says the daemon's status, not each worker
            config,
            setup.library,
            [channel],
            instance=setup.instance,
            version=setup.version,
            logger=logger,
            remind=False,
            # the subjects of a frame message are any worker's: every worker's streams remembered
            mine=mine(index, len(setup.inbound), config.service.max_streams * len(setup.inbound)),
        )
        try:
            http = await open_http("127.0.0.1", 0, service.health, service.metrics)
        except OSError as e:
            raise StartupError("service.workers", f"worker {index}: no metrics port: {e}") from None
        port = http.sockets[0].getsockname()[1]

        async def report() -> None:
            channel.tell(READY, str(index).encode(), str(port).encode(), str(os.getpid()).encode())
            while True:
                await asyncio.sleep(1.0)
                channel.tell(STREAMS, str(index).encode(), str(len(service.table.streams)).encode())
                if os.getppid() != setup.front_pid:  # the front is gone: nothing to wait for
                    channel.drain_within(0)
                    stop.set()

        settle_collector()
        return await service.run(stop, [("http", lambda: serve_http(http)), ("report", report)])

    try:
        return 0 if asyncio.run(main()) else 1
    except StartupError as e:  # the front says it did not start; the log line says why
        logger.error("cannot start", extra={"fields": {"setting": e.setting, "reason": str(e)}})
        return 2


# ------------------------------------------------------------------------------------ the front


@dataclass
class Slot:
    """One worker as the front sees it."""

    index: int
    process: subprocess.Popen[bytes] | None = None
    ready: bool = False
    metrics_port: int = 0
    streams: int = 0
    started: float = 0.0
    restarts: int = 0
    backoff: float = 0.0
    next_start: float = 0.0


class Front:
    """The front of ``workers`` recognition processes over the transports ``config`` names."""

    def __init__(
        self,
        config: Config,
        library: Library,
        workers: int,
        *,
        instance: str,
        version: str,
        logger: logging.Logger,
    ) -> None:
        self.config = config
        self.library = library
        self.instance = instance
        self.version = version
        self.log = logger
        self.transports: list[Transport] = transports_of(config, instance)
        self.slots = [Slot(k) for k in range(workers)]
        self.started = time.time()
        self.drops: Counter[str] = Counter()
        self.published = 0
        self.stopping = False
        self._entered = False
        self._inbound: list[zmq.Socket[bytes]] = []
        self._outbound: zmq.asyncio.Socket | None = None
        self._setup_file: Path | None = None
        self._registry = CollectorRegistry()
        self._registry.register(_Own(self))
        for t in self.transports:
            t.announce(self._status("online"), self._status("offline"))

    def _status(self, state: str) -> Outgoing:
        streams = sum(s.streams for s in self.slots)
        message = StatusMessage(self.instance, state, self.version, streams, self.started)  # type: ignore[arg-type]
        return Outgoing(topic(message), encode(message), retain=True, reliable=True)

    def health(self) -> str | None:
        """None while every transport serves and every worker is up, else why not."""
        if self.stopping:
            return "stopping"
        if not self._entered:
            return "starting"
        problem = next((p for t in self.transports if (p := t.problem) is not None), None)
        if problem is not None:
            return problem
        down = [s for s in self.slots if not s.ready]
        if down:
            return f"worker {down[0].index} {'restarting' if down[0].restarts else 'starting'}"
        return None

    # ------------------------------------------------------------------------------- workers

    def _start(self, slot: Slot) -> None:
        assert self._setup_file is not None
        root = str(Path(__file__).resolve().parents[2])
        slot.process = subprocess.Popen(
            [sys.executable, "-c", BOOT, root, str(slot.index), str(self._setup_file)],
            stdin=subprocess.DEVNULL,
            stdout=subprocess.DEVNULL,  # stdout is the stdout sink's; a worker's log lines go to stderr
        )
        slot.started = time.monotonic()
        slot.ready = False

    def _reap(self, slot: Slot) -> int | None:
        """The exit status of ``slot``'s process if it has exited (then the slot is empty)."""
        if slot.process is None or (code := slot.process.poll()) is None:
            return None
        slot.process, slot.ready, slot.streams = None, False, 0
        return code

    async def _supervise(self) -> None:
        reminded = time.monotonic()
        while True:
            await asyncio.sleep(0.1)
            if self.stopping:
                continue
            now = time.monotonic()
            if now - reminded >= STATUS_EVERY_S:
                reminded = now
                await self._publish_all(reminder(self._status("online")))
            for slot in self.slots:
                code = self._reap(slot)
                if code is not None:
                    ran = now - slot.started
                    slot.backoff = (
                        RESTART_MIN_S
                        if ran >= STEADY_S
                        else min(RESTART_MAX_S, max(RESTART_MIN_S, 2 * slot.backoff))
                    )
                    slot.next_start = now + slot.backoff
                    self.log.warning(
                        "worker exited",
                        extra={
                            "fields": {"worker": slot.index, "status": code, "restart_in_s": slot.backoff}
                        },
                    )
                if slot.process is None and now >= slot.next_start:
                    slot.restarts += 1
                    self._start(slot)

    async def _all_ready(self, stop: asyncio.Event) -> None:
        """Wait until every worker says it serves; StartupError if one exits first."""
        assert self._outbound is not None
        deadline = time.monotonic() + READY_TIMEOUT_S
        while not all(s.ready for s in self.slots) and not stop.is_set():
            if time.monotonic() > deadline:
                late = next(s.index for s in self.slots if not s.ready)
                raise StartupError(
                    "service.workers", f"worker {late} did not serve within {READY_TIMEOUT_S:g} s"
                )
            for slot in self.slots:
                process = slot.process
                if process is not None and (code := process.poll()) is not None:
                    raise StartupError(
                        "service.workers",
                        f"worker {slot.index} exited with status {code} before it served (its log is above)",
                    )
            if await self._outbound.poll(100):
                for frames in self._take_all():
                    await self._publish(frames)

    # ------------------------------------------------------------------------------- messages

    async def _route(self, transport: Transport) -> None:
        """The messages of ``transport`` to their workers, never decoded: a ZeroMQ source's routed in
        C where it can be (:meth:`protocols.zeromq.ZmqTransport.router`), else its frames as they
        came (:meth:`~protocols.zeromq.ZmqTransport.raw_source`) by
        :func:`protocols.routing.split`; another transport's topic and payload."""
        socks, slots = self._inbound, self.slots
        n = len(socks)

        def lost(k: int, count: int) -> None:
            self.drops["worker_full" if slots[k].ready else "worker_down"] += count

        cached = routes_cached(self.config.service.max_streams * n)
        router = getattr(transport, "router", None)
        routed = router(socks, choose(n), cached) if router is not None else None
        if router is not None and routed is None:
            fields = {"transport": transport.name, "reason": "the libzmq pyzmq loaded was not found"}
            self.log.warning("routing in Python", extra={"fields": fields})
        if routed is not None:
            async for full in routed:
                for k, count in enumerate(full):
                    if count:
                        lost(k, count)
                await asyncio.sleep(0)
            return
        worker = Routes(n, cached)

        def send(k: int, frames: list[bytes]) -> None:
            """``frames`` (topic, payload, topic, payload, ...) to worker ``k`` as one message of one
            frame (a msgpack array): a frame per pose would cost the front and the worker a
            ZeroMQ message each, twice what they spend on the pose otherwise."""
            try:
                socks[k].send(packb(frames), NOBLOCK)
            except zmq.Again:
                lost(k, len(frames) // 2)

        raw = getattr(transport, "raw_source", None)
        batches = raw() if raw is not None else None
        if batches is not None:
            # what one wakeup took, one message per worker: the queue's wakeup is paid once
            async for batch in batches:
                for k, frames in enumerate(split(batch, worker, n)):
                    if frames:
                        send(k, frames)
                await asyncio.sleep(0)
            return
        source = transport.source()
        assert source is not None
        count = 0
        async for incoming in source:
            name = incoming.topic.encode()
            k = worker(name)
            for to in range(n) if k == n else (k,):  # a frame message: every worker's
                send(to, [name, incoming.payload])
            count += 1
            if count % YIELD_EVERY == 0:
                await asyncio.sleep(0)

    def _take_all(self) -> list[list[bytes]]:
        """What the workers sent that is there now, the control messages handled; the messages to
        publish."""
        assert self._outbound is not None
        sync: zmq.Socket[bytes] = zmq.Socket.shadow(self._outbound.underlying)
        out = []
        for _ in range(DRAIN_MESSAGES):
            frames = receive(sync)
            if frames is None:
                break
            kind = frames[0]
            if kind == PUBLISH and len(frames) == 4:
                out.append(frames)
            elif kind == ASK and len(frames) == 2:
                for t in self.transports:
                    t.ask_skeleton(frames[1].decode())
            elif kind == STREAMS and len(frames) == 3:
                self.slots[int(frames[1])].streams = int(frames[2])
            elif kind == READY and len(frames) == 4:
                slot = self.slots[int(frames[1])]
                if self._pid(slot) != int(frames[3]):  # from a worker that has exited since
                    continue
                slot.ready, slot.metrics_port = True, int(frames[2])
                self.log.info(
                    "worker ready", extra={"fields": {"worker": slot.index, "pid": self._pid(slot)}}
                )
                for t in self.transports:
                    ask = getattr(t, "ask_skeletons", None)
                    if ask is not None:  # every publisher announces again: the new worker learns its streams
                        ask()
        return out

    @staticmethod
    def _pid(slot: Slot) -> int | None:
        return None if slot.process is None else slot.process.pid

    async def _publish(self, frames: list[bytes]) -> None:
        _, name, payload, how = frames
        relay = b"p" in how
        await self._publish_all(
            Outgoing(name.decode(), payload, retain=b"r" in how, reliable=b"q" in how, relay=relay)
        )
        self.published += 1

    async def _publish_all(self, out: Outgoing) -> None:
        for t in self.transports:
            sink = t.sink()
            if sink is not None:
                await sink.publish(out)

    async def _collect(self) -> None:
        assert self._outbound is not None
        while True:
            await self._outbound.poll()
            for frames in self._take_all():
                await self._publish(frames)

    # -------------------------------------------------------------------------------- metrics

    async def exposition(self) -> bytes:
        """The workers' series summed, and the front's (see the module docstring)."""
        ready = [s for s in self.slots if s.ready]
        texts = await asyncio.gather(*(_fetch_metrics(s.metrics_port) for s in ready))
        own = generate_latest(self._registry).decode()
        registry = CollectorRegistry()
        registry.register(_Merged(merged_families([own], [t for t in texts if t is not None])))
        body: bytes = generate_latest(registry)
        return body

    # -------------------------------------------------------------------------------- running

    async def run(self, stop: asyncio.Event) -> bool:
        """Serve until ``stop`` is set, then shut down; True if every worker published everything
        within the grace."""
        http = None
        if self.config.metrics.port:
            host, port = self.config.metrics.host, self.config.metrics.port
            try:
                http = await open_http(host, port, self.health, self.exposition)
            except OSError as e:
                why = os.strerror(e.errno).lower() if e.errno else str(e)
                raise StartupError("metrics.port", f"{host}:{port}: {why}") from None
        clean = True
        async with contextlib.AsyncExitStack() as stack:
            if http is not None:
                stack.push_async_callback(_closed, http)
            for t in self.transports:
                await stack.enter_async_context(t)
            where = Path(tempfile.mkdtemp(prefix="mocapd-workers-"))
            stack.callback(shutil.rmtree, where, True)
            ctx = zmq.asyncio.Context()
            stack.callback(ctx.term)
            stack.callback(self.kill_all)
            hwm = self.config.zmq.hwm
            inbound = tuple(f"ipc://{where}/in-{s.index}" for s in self.slots)
            for endpoint in inbound:
                sock = open_socket(ctx, zmq.PUSH, endpoint, bind=True, hwm=hwm, linger_ms=0)
                stack.callback(sock.close, 0)
                self._inbound.append(zmq.Socket.shadow(sock.underlying))
            self._outbound = open_socket(ctx, zmq.PULL, f"ipc://{where}/out", bind=True, hwm=hwm, linger_ms=0)
            stack.callback(self._outbound.close, 0)
            setup = WorkerSetup(
                self.config,
                self.library,
                self.instance,
                self.version,
                inbound,
                f"ipc://{where}/out",
                os.getpid(),
            )
            self._setup_file = where / "setup.pickle"
            self._setup_file.write_bytes(pickle.dumps(setup, protocol=pickle.HIGHEST_PROTOCOL))
            for slot in self.slots:
                self._start(slot)
            await self._all_ready(stop)
            # the modules and the library are there for good: keep the collector off them, or its
            # full passes over them, set off by the frames forwarded, stall every stream's route
            settle_collector()
            self._entered = True
            self.log.info(
                "online",
                extra={
                    "fields": {
                        "instance": self.instance,
                        "transports": [t.name for t in self.transports],
                        "endpoints": endpoints_of(self.transports),
                        "workers": len(self.slots),
                        "pids": [self._pid(s) for s in self.slots],
                    }
                },
            )
            routes: list[asyncio.Task[None]] = []
            failure: StartupError | None = None
            try:
                async with asyncio.TaskGroup() as group:
                    for t in self.transports:
                        if t.source() is not None:
                            routes.append(group.create_task(self._route(t), name=f"route {t.name}"))
                    for name, fatal in fatal_of(self.transports):
                        group.create_task(fatal(), name=name)
                    group.create_task(self._collect(), name="collect")
                    group.create_task(self._supervise(), name="supervise")
                    if http is not None:
                        group.create_task(serve_http(http), name="http")
                    group.create_task(self._shutdown(stop, routes), name="shutdown")
            except* _Stop as stopped:
                clean = all(isinstance(e, _Stop) and e.args == (True,) for e in stopped.exceptions)
            except* StartupError as group:
                failure = cast(StartupError, group.exceptions[0])
            self.stopping = True
            self.log.info(
                "offline",
                extra={"fields": {"instance": self.instance, "published": self.published, "clean": clean}},
            )
        if failure is not None:  # another daemon took this one's place (the workers were killed)
            raise failure
        return clean

    async def _shutdown(self, stop: asyncio.Event, routes: list[asyncio.Task[None]]) -> None:
        await stop.wait()
        loop = asyncio.get_running_loop()
        self.stopping = True
        self.log.info("stopping", extra={"fields": {"workers": [self._pid(s) for s in self.slots]}})
        for task in routes:
            task.cancel()
        for slot in self.slots:
            if slot.process is not None and slot.process.poll() is None:
                slot.process.send_signal(signal.SIGTERM)
        deadline = loop.time() + self.config.service.grace_s + 2.0
        while any(s.process is not None and s.process.poll() is None for s in self.slots):
            if loop.time() > deadline:
                break
            await asyncio.sleep(0.05)
        clean = True
        for slot in self.slots:
            if slot.process is not None and slot.process.poll() is None:
                slot.process.kill()
                slot.process.wait()
                clean = False
            clean = clean and (slot.process is None or slot.process.returncode == 0)
        # what the workers sent before they exited is in the front's queue: publish all of it
        assert self._outbound is not None
        while await self._outbound.poll(100):
            for frames in self._take_all():
                await self._publish(frames)
        for t in self.transports:  # "offline" says how many streams it held
            t.announce(self._status("online"), self._status("offline"))
        left = max(0.1, deadline - loop.time())
        for t in self.transports:
            t.drain_within(left)
        raise _Stop(clean)

    def kill_all(self) -> None:
        """SIGKILL to every worker still running, and wait for it."""
        for slot in self.slots:
            if slot.process is not None and slot.process.poll() is None:
                slot.process.kill()
                slot.process.wait()


class _Own(Collector):
    """The front's own series: the workers, the transports, the drops of routing."""

    def __init__(self, front: Front) -> None:
        self.front = front

    def collect(self) -> Iterable[Metric]:
        front = self.front
        yield GaugeMetricFamily("mocapd_workers", "Recognition processes", value=len(front.slots))
        up = GaugeMetricFamily("mocapd_worker_up", "1 while a worker serves", labels=["worker"])
        restarts = CounterMetricFamily("mocapd_worker_restarts", "Workers started again", labels=["worker"])
        for slot in front.slots:
            up.add_metric([str(slot.index)], 1.0 if slot.ready else 0.0)
            restarts.add_metric([str(slot.index)], slot.restarts)
        yield up
        yield restarts
        drops = Counter(front.drops)
        for t in front.transports:
            drops.update(t.dropped())
        family = CounterMetricFamily(
            "mocapd_drops", "Poses or messages dropped, by reason", labels=["reason"]
        )
        for key, n in sorted(drops.items()):
            family.add_metric([key], n)
        yield family
        yield GaugeMetricFamily(
            "mocapd_outbox",
            "Detections awaiting the broker's acknowledgement",
            value=sum(t.pending for t in front.transports),
        )
        transports = GaugeMetricFamily(
            "mocapd_transport_up", "1 while a transport serves", labels=["transport"]
        )
        for t in front.transports:
            transports.add_metric([t.name], 1.0 if t.problem is None else 0.0)
        yield transports


class _Merged(Collector):
    def __init__(self, families: list[Metric]) -> None:
        self.families = families

    def collect(self) -> Iterable[Metric]:
        return self.families


def merged_families(own: list[str], workers: list[str]) -> list[Metric]:
    """The metric families of the expositions ``own`` and ``workers``, the samples of one name and
    labels summed (counters, gauges and histogram buckets alike); of the workers' families, those
    about their channel to the front left out."""
    families: dict[str, Metric] = {}
    values: dict[str, dict[tuple[str, tuple[tuple[str, str], ...]], float]] = {}
    for text, skip in [(t, frozenset[str]()) for t in own] + [(t, WORKER_FAMILIES_SKIPPED) for t in workers]:
        for family in text_string_to_metric_families(text):
            if family.name in skip:
                continue
            if family.name not in families:
                families[family.name] = Metric(family.name, family.documentation, family.type)
                values[family.name] = {}
            mine = values[family.name]
            for sample in family.samples:
                key = (sample.name, tuple(sample.labels.items()))
                mine[key] = mine.get(key, 0.0) + sample.value
    for name, family in families.items():
        for (sample_name, labels), value in values[name].items():
            family.add_sample(sample_name, dict(labels), value)
    return list(families.values())


async def _fetch_metrics(port: int, timeout: float = 2.0) -> str | None:
    """A worker's ``/metrics`` text, None if it does not answer in time."""
    try:
        async with asyncio.timeout(timeout):
            reader, writer = await asyncio.open_connection("127.0.0.1", port)
            try:
                writer.write(b"GET /metrics HTTP/1.0\r\nHost: 127.0.0.1\r\n\r\n")
                await writer.drain()
                response = await reader.read()
            finally:
                writer.close()
    except (OSError, TimeoutError):
        return None
    head, _, body = response.partition(b"\r\n\r\n")
    return body.decode() if head.startswith(b"HTTP/1.1 200") else None


async def _closed(server: asyncio.Server) -> None:
    server.close()
    await server.wait_closed()


def serve_workers(config: Config, library: Library, workers: int, *, version: str) -> int:
    """``mocapd run`` with ``workers`` recognition processes until SIGTERM, SIGINT or SIGHUP; the
    exit status: 0 when every worker published everything within the grace, 1 otherwise, 70 on an
    internal error (logged as one JSON line). A transport, the metrics server or a worker that
    cannot start raises :class:`~daemon.config.ConfigError` naming the setting, before "online" is
    published."""
    logger = configure_logging(config.logging.level)
    front = Front(config, library, workers, instance=instance_name(config), version=version, logger=logger)

    async def main() -> bool:
        loop = asyncio.get_running_loop()
        stop = asyncio.Event()

        def on_signal(signum: int) -> None:
            if stop.is_set():  # a second signal: at once
                front.kill_all()
                os._exit(128 + signum)
            logger.info("signal", extra={"fields": {"signal": signal.Signals(signum).name}})
            stop.set()

        on_stop_signals(loop, on_signal)
        return await front.run(stop)

    try:
        return 0 if asyncio.run(main()) else 1
    except StartupError as e:
        raise ConfigError(e.reason, field=e.setting) from None
    except (MocapdError, OSError):
        raise  # bad input or a file: the command line's one line
    except Exception:
        return internal_error(logger)


def main(argv: list[str]) -> int:
    """A worker process: ``argv`` its index and the file of its :class:`WorkerSetup`. Whatever
    escapes the worker is logged as one JSON line (:func:`~daemon.service.app.internal_error`: its
    stderr is the daemon's, where every line is a JSON object) and ends it with
    :data:`~daemon.service.app.EXIT_BUG`; the front starts it again."""
    index, path = int(argv[0]), Path(argv[1])
    logger = tagged_logging("info", index)  # until the setup says the level
    try:
        setup: WorkerSetup = pickle.loads(path.read_bytes())
        return run_worker(setup, index)
    except Exception:
        return internal_error(logger)
