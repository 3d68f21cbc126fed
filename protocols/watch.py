"""An observer's subscription to the bus (``mocapd view``): every message of mocapd's topics that the
bus carries, read-only, handed as :class:`~protocols.transport.Incoming` to a callback.

* MQTT (the daemon's own transport, :class:`protocols.mqtt.MqttTransport`, on clean sessions: the
  broker keeps nothing for an observer that went away): two connections, one for the poses (QoS 0)
  and one for the rest (the retained skeletons and status, detections, progress; QoS 1), each with
  its bounded queue, fair between streams, that drops the oldest message of the stream holding the
  most when full (counted), so that a flood of poses never crowds out a detection. Each connection
  is made again after a loss, with a capped back-off. (aiomqtt's public API costs twice the CPU a
  message: docs/benchmarks.md, "MQTT intake", and "Live view".)
* ZeroMQ: a SUB socket connected to the daemon's detections PUB socket, subscribed to ``mocap/`` and
  ``mocapd/`` (there the daemon relays its streams' skeletons, and poses where ``zmq.relay_per_s``
  says so, beside its detections, progress and status); its high-water mark bounds what waits, its
  connection state comes from a socket monitor. High-water marks before connect, explicit lingers.

Reading never blocks the callback's owner for long: every :data:`YIELD_EVERY` messages the reader
lets the other tasks run.
"""

from __future__ import annotations

import asyncio
import itertools
import logging
import time
import uuid
from collections.abc import Callable

import zmq
import zmq.asyncio
from zmq.utils.monitor import parse_monitor_message

from protocols.mqtt import MqttTransport
from protocols.transport import Incoming
from protocols.urls import parse_bus_url
from protocols.zeromq import RawSource, open_socket

LOG = logging.getLogger("mocapd.watch")
POSE_TOPICS = (("mocap/+/pose", 0), ("mocap/+/frame", 0))
EVENT_TOPICS = (
    ("mocap/+/skeleton", 1),
    ("mocap/+/detections", 1),
    ("mocap/+/progress", 0),
    ("mocapd/+/status", 1),
)
"""What an MQTT observer subscribes to: the poses on one connection, the rest on the other."""
ZMQ_PREFIXES = (b"mocap/", b"mocapd/")
POSE_QUEUE = 4096
"""Poses waiting on the MQTT poses connection (half a second of 64 streams at 120 Hz)."""
EVENT_QUEUE = 8192
"""Other messages waiting on the MQTT events connection."""
ZMQ_HWM = 10_000
"""Messages the SUB socket holds (ZeroMQ drops past it, at the publisher)."""
RECONNECT_MAX_S = 5.0
KEEPALIVE_S = 10
YIELD_EVERY = 64
_monitors = itertools.count()

Deliver = Callable[[Incoming], None]


class Watch:
    """The subscription to the bus at ``url`` (``mqtt://``, ``mqtts://`` or ``zmq+tcp://``;
    :func:`protocols.urls.parse_bus_url`). :meth:`run` delivers until cancelled; :attr:`problem`
    is None while every connection is up, else why not; :attr:`dropped` counts what a full queue
    dropped; :attr:`received` what was delivered."""

    def __init__(self, url: str, keep: str | None = None) -> None:
        """``keep``: over MQTT, the name of a session the broker keeps for the events connection
        (detections, statuses, skeletons at QoS 1 are queued while the watcher is away, so one that
        restarts with the same name misses none of them); None: clean sessions only."""
        self.url = url
        self.kind, self.address = parse_bus_url(url)
        self.received = 0
        self._problems: dict[str, str | None] = {"zmq": "connecting"}
        self._identity = uuid.uuid4().hex[:12]
        self._transports: dict[str, MqttTransport] = {}
        if self.kind == "mqtt":
            from daemon.config import MqttConfig

            for name, topics, queue in (
                ("poses", POSE_TOPICS, POSE_QUEUE),
                ("events", EVENT_TOPICS, EVENT_QUEUE),
            ):
                settings = MqttConfig(
                    url=self.address, queue=queue, keepalive_s=KEEPALIVE_S, reconnect_max_s=RECONNECT_MAX_S
                )
                kept = keep is not None and name == "events"
                self._transports[name] = MqttTransport(
                    settings,
                    client_id=f"mocapd-view-{keep if kept else self._identity}-{name}",
                    subscribe=topics,
                    presence=None,
                    clean_session=not kept,
                )

    @property
    def problem(self) -> str | None:
        said = {n: t.problem for n, t in self._transports.items()} if self._transports else self._problems
        problems = [f"{name}: {p}" for name, p in said.items() if p is not None]
        return "; ".join(problems) if problems else None

    @property
    def dropped(self) -> int:
        return sum(t.dropped()["mqtt_incoming_full"] for t in self._transports.values())

    async def run(self, deliver: Deliver) -> None:
        """Deliver every message until cancelled (connections lost are made again)."""
        if self.kind == "zmq":
            await self._zmq(deliver)
            return
        async with asyncio.TaskGroup() as group:
            for name in self._transports:
                group.create_task(self._mqtt(name, deliver), name=f"watch mqtt {name}")

    # ------------------------------------------------------------------------------------ MQTT

    async def _mqtt(self, name: str, deliver: Deliver) -> None:
        transport = self._transports[name]
        async with transport:
            n = 0
            async for incoming in transport:
                deliver(incoming)
                self.received += 1
                n += 1
                if n % YIELD_EVERY == 0:
                    await asyncio.sleep(0)

    # ---------------------------------------------------------------------------------- ZeroMQ

    async def _zmq(self, deliver: Deliver) -> None:
        ctx = zmq.asyncio.Context()
        inproc = f"inproc://mocapd-view-monitor-{next(_monitors)}"
        sub = monitor = None
        try:
            sub = ctx.socket(zmq.SUB)
            sub.setsockopt(zmq.RCVHWM, ZMQ_HWM)
            sub.setsockopt(zmq.SNDHWM, ZMQ_HWM)
            sub.setsockopt(zmq.LINGER, 0)
            for prefix in ZMQ_PREFIXES:
                sub.setsockopt(zmq.SUBSCRIBE, prefix)
            sub.monitor(inproc, zmq.EVENT_HANDSHAKE_SUCCEEDED | zmq.EVENT_DISCONNECTED)
            monitor = open_socket(ctx, zmq.PAIR, inproc, bind=False, hwm=1000, linger_ms=0)
            sub.connect(self.address)
            async with asyncio.TaskGroup() as group:
                group.create_task(self._follow(monitor), name="watch zmq monitor")
                group.create_task(self._receive(sub, deliver), name="watch zmq")
        finally:
            if sub is not None:
                sub.disable_monitor()
            for sock in (monitor, sub):
                if sock is not None:
                    sock.close(linger=0)
            ctx.term()

    async def _follow(self, monitor: zmq.asyncio.Socket) -> None:
        """The SUB socket's connection state, from its monitor's events."""
        while True:
            event = parse_monitor_message(await monitor.recv_multipart())["event"]
            if event == zmq.EVENT_HANDSHAKE_SUCCEEDED:
                self._problems["zmq"] = None
                LOG.info("bus connected", extra={"fields": {"bus": self.url}})
            elif event == zmq.EVENT_DISCONNECTED:
                self._problems["zmq"] = f"disconnected from {self.address} (reconnecting)"
                LOG.warning("bus lost", extra={"fields": {"bus": self.url}})

    async def _receive(self, sub: zmq.asyncio.Socket, deliver: Deliver) -> None:
        async for batch in RawSource(sub):
            received = time.time()
            for parts in batch:
                if len(parts) == 2:
                    deliver(Incoming(parts[0].decode("utf-8", "replace"), parts[1], received))
                else:
                    deliver(Incoming("", b"", received))  # not [topic, payload]: refused as undecodable
                self.received += 1
            await asyncio.sleep(0)
