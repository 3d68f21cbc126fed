"""An observer's subscription to the bus (``mocapd view``): every message of mocapd's topics that the
bus carries, read-only, handed as :class:`~protocols.transport.Incoming` to a callback.

* MQTT (aiomqtt, clean sessions: the broker keeps nothing for an observer that went away): two
  connections, one for the poses (QoS 0) and one for the rest (the retained skeletons and status,
  detections, progress; QoS 1), each with a bounded incoming queue that drops its oldest message
  when full (counted), so that a flood of poses never crowds out a detection. Each connection is
  made again after a loss, with a capped back-off.
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
import ssl
import time
import uuid
from collections import Counter
from collections.abc import Callable, Sequence

import aiomqtt
import zmq
import zmq.asyncio
from zmq.utils.monitor import parse_monitor_message

from protocols.transport import Incoming
from protocols.urls import parse_bus_url, parse_mqtt_url
from protocols.zeromq import RawSource, open_socket

LOG = logging.getLogger("mocapd.watch")
POSE_TOPICS = (("mocap/+/pose", 0),)
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
RECONNECT_MIN_S, RECONNECT_MAX_S = 0.25, 5.0
KEEPALIVE_S = 10
YIELD_EVERY = 64
_monitors = itertools.count()

Deliver = Callable[[Incoming], None]


def _dropping(counts: Counter[str], name: str) -> type[asyncio.Queue[aiomqtt.Message]]:
    """aiomqtt's incoming queue (its documented ``queue_type``) bounded by dropping the oldest
    message, counted in ``counts[name]``, rather than the newest (aiomqtt's own way, logged per
    message)."""

    class DropOldest(asyncio.Queue[aiomqtt.Message]):
        def put_nowait(self, item: aiomqtt.Message) -> None:
            if self.full():
                self.get_nowait()
                counts[name] += 1
            super().put_nowait(item)

    return DropOldest


class Watch:
    """The subscription to the bus at ``url`` (``mqtt://``, ``mqtts://`` or ``zmq+tcp://``;
    :func:`protocols.urls.parse_bus_url`). :meth:`run` delivers until cancelled; :attr:`problem`
    is None while every connection is up, else why not; :attr:`dropped` counts what a full queue
    dropped; :attr:`received` what was delivered."""

    def __init__(self, url: str) -> None:
        self.url = url
        self.kind, self.address = parse_bus_url(url)
        self.received = 0
        self._dropped: Counter[str] = Counter()
        self._problems: dict[str, str | None] = (
            {"poses": "connecting", "events": "connecting"} if self.kind == "mqtt" else {"zmq": "connecting"}
        )
        self._identity = uuid.uuid4().hex[:12]

    @property
    def problem(self) -> str | None:
        problems = [f"{name}: {p}" for name, p in self._problems.items() if p is not None]
        return "; ".join(problems) if problems else None

    @property
    def dropped(self) -> int:
        return sum(self._dropped.values())

    async def run(self, deliver: Deliver) -> None:
        """Deliver every message until cancelled (connections lost are made again)."""
        if self.kind == "zmq":
            await self._zmq(deliver)
            return
        async with asyncio.TaskGroup() as group:
            group.create_task(self._mqtt("poses", POSE_TOPICS, POSE_QUEUE, deliver), name="watch mqtt poses")
            group.create_task(
                self._mqtt("events", EVENT_TOPICS, EVENT_QUEUE, deliver), name="watch mqtt events"
            )

    # ------------------------------------------------------------------------------------ MQTT

    async def _mqtt(self, name: str, topics: Sequence[tuple[str, int]], queue: int, deliver: Deliver) -> None:
        host, port, tls = parse_mqtt_url(self.address)
        delay = RECONNECT_MIN_S
        while True:
            try:
                async with aiomqtt.Client(
                    host,
                    port,
                    identifier=f"mocapd-view-{self._identity}-{name}",
                    clean_session=True,
                    keepalive=KEEPALIVE_S,
                    timeout=10,
                    tls_context=ssl.create_default_context() if tls else None,
                    queue_type=_dropping(self._dropped, name),
                    max_queued_incoming_messages=queue,
                    logger=LOG,
                ) as client:
                    await client.subscribe(list(topics))
                    self._problems[name] = None
                    delay = RECONNECT_MIN_S
                    LOG.info("bus connected", extra={"fields": {"bus": self.url, "connection": name}})
                    n = 0
                    async for message in client.messages:
                        deliver(Incoming(message.topic.value, message.payload, time.time()))
                        self.received += 1
                        n += 1
                        if n % YIELD_EVERY == 0:
                            await asyncio.sleep(0)
            except aiomqtt.MqttError as e:
                self._problems[name] = f"{e} (reconnecting)"
                LOG.warning(
                    "bus lost", extra={"fields": {"bus": self.url, "connection": name, "error": str(e)}}
                )
            await asyncio.sleep(delay)
            delay = min(2 * delay, RECONNECT_MAX_S)

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
