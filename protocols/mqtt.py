"""MQTT through aiomqtt (2.x): subscriptions in, publications out, over one connection that mends
itself.

The connection follows aiomqtt's documented reconnect loop: one client, re-entered after every loss
with a capped exponential back-off, subscribing again on every connect. The session is persistent
(``clean_session=False`` with a fixed client id), so the broker keeps the subscriptions and queued
QoS 1 messages across the daemon's reconnects and, with persistence on, its own restarts. Reliable
messages (detections: QoS 1) go through an outbox and leave it only when the broker acknowledged
them; what was not acknowledged when the connection dropped is sent again after the reconnect
(a consumer may see a repeat: detections carry an event id). With :meth:`MqttTransport.announce`,
the "online" status is published retained on every connect, the "offline" one is the retained last
will, and a planned close publishes "offline" itself before disconnecting (a clean disconnect
suppresses the will). The incoming queue is bounded (``queue``) and fair between streams
(:class:`~protocols.fair.FairQueue`): when it is full the oldest message of the stream holding the
most is dropped (counted), so one stream's flood does not crowd out the others.
"""

from __future__ import annotations

import asyncio
import contextlib
import itertools
import logging
import select
import socket
import ssl
import time
import uuid
from collections import OrderedDict, deque
from collections.abc import AsyncIterator, Callable, Sequence
from types import TracebackType
from typing import TYPE_CHECKING, Any

import aiomqtt

from protocols.fair import FairQueue
from protocols.transport import Incoming, Outgoing, StartupError
from protocols.urls import parse_mqtt_url

if TYPE_CHECKING:
    from daemon.config import MqttConfig

LOG = logging.getLogger("mocapd.mqtt")
CLIENT_LOG = logging.getLogger("mocapd.mqtt.client")
"""aiomqtt's and paho's own logger: only errors (their warnings, e.g. "There are 66 pending publish
calls" thousands of times in a fast replay, say nothing the outbox and /metrics do not)."""
CLIENT_LOG.setLevel(logging.ERROR)


SUBSCRIPTIONS = (("mocap/+/skeleton", 1), ("mocap/+/pose", 0))
"""What a daemon taking poses in over MQTT subscribes to: skeletons reliably (they are retained),
poses as they come."""
PROBE_S = 0.5
"""How long a starting daemon waits for another live daemon of its instance to answer."""
ASK_EVERY_S = 5.0
"""The shortest time between two requests for one stream's skeleton."""
ASKED = 1_000
"""Streams whose requests are remembered (the oldest forgotten first): as many as a daemon holds by
default, since a flood of new ids must not grow it."""


class _Client(aiomqtt.Client):
    """aiomqtt's client reading every packet the socket holds when it becomes readable, not one:
    at thousands of poses a second, one packet per event-loop turn falls behind. (The same
    callback as aiomqtt's ``_on_socket_open``, looping while the socket has data.) Each message
    paho parsed goes straight to ``deliver(topic, payload)``: paho's dispatch (two locks and a
    topic-filter search per message, for per-topic callbacks this client never registers) and
    aiomqtt's Message and queue cost a sixth of the daemon at a hundred streams. paho reads a
    packet with three or four ``recv`` calls (the type byte, each byte of its length, the rest);
    here they are served from one large read of the socket (paho's own ``_sock_recv``, so TLS and
    its errors are as paho handles them)."""

    def __init__(self, *args: Any, deliver: Callable[[str, bytes], None], **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self._read = _Buffered(self._client._sock_recv)
        self._client._sock_recv = self._read.recv  # type: ignore[method-assign,assignment]

        def handle(message: Any) -> None:  # paho's MQTTMessage
            try:
                topic = message._topic.decode()
            except UnicodeDecodeError:  # paho drops such a message's topic callbacks too
                return
            payload = message.payload
            deliver(topic, payload if isinstance(payload, bytes) else bytes(payload))

        self._client._handle_on_message = handle  # type: ignore[method-assign]

    def _on_socket_open(self, client: Any, userdata: Any, sock: Any) -> None:
        read = self._read
        read.clear()  # a new connection: nothing of the last one is left to parse

        def callback() -> None:
            try:
                for _ in range(DRAIN_PACKETS):
                    client.loop_read()
                    s = client.socket()
                    if s is None:
                        return
                    if read.pending() or (hasattr(s, "pending") and s.pending() > 0):
                        continue
                    if not select.select([s], [], [], 0)[0]:
                        return
                if read.pending():  # the socket may have nothing more to say: come back for these
                    self._loop.call_soon(callback)
            except Exception as exc:  # aiomqtt's rule: any read error ends the connection
                if not self._disconnected.done():
                    self._disconnected.set_exception(exc)

        def create_misc_task() -> None:
            self._misc_task = self._loop.create_task(self._misc_loop())

        self._loop.call_soon_threadsafe(self._loop.add_reader, sock.fileno(), callback)
        self._loop.call_soon_threadsafe(create_misc_task)


class _Buffered:
    """``recv(n)`` served from reads of ``read(READ_BYTES)`` (which raises as a socket does)."""

    def __init__(self, read: Callable[[int], bytes]) -> None:
        self._fill = read
        self._data = b""
        self._at = 0

    def recv(self, size: int) -> bytes:
        if self._at >= len(self._data):
            self._data, self._at = self._fill(READ_BYTES), 0  # b"": the connection closed
        out = self._data[self._at : self._at + size]
        self._at += len(out)
        return out

    def pending(self) -> int:
        return len(self._data) - self._at

    def clear(self) -> None:
        self._data, self._at = b"", 0


READ_BYTES = 1 << 16


INFLIGHT = 100
"""Reliable messages awaiting the broker's acknowledgement at once (one at a time would pay a round
trip per detection)."""
DRAIN_S = 2.0
"""How long leaving waits for the outbox to empty, unless told otherwise (``drain_within``)."""


DRAIN_PACKETS = 512
"""The most packets one readable event takes, so that reading yields to the other tasks."""


class MqttTransport:
    """An MQTT connection to the broker of ``settings`` (``url``, credentials, TLS files, queue
    bounds, keepalive, reconnect back-off; ``daemon.config.MqttConfig``): ``subscribe`` (topic, QoS)
    pairs in, publications out, as ``client_id`` (fixed: the persistent session is the broker's
    record of it). With ``presence`` (the instance name), a starting transport first makes sure no
    live daemon of that instance is on the broker, and answers the next one's question itself."""

    name = "mqtt"

    def __init__(
        self,
        settings: MqttConfig,
        *,
        client_id: str,
        subscribe: Sequence[tuple[str, int]],
        presence: str | None,
    ) -> None:
        self.host, self.port, tls = parse_mqtt_url(settings.url)
        self.url = settings.url
        self.client_id = client_id
        self.subscriptions = list(subscribe)
        self.username, self.password = settings.username, settings.password
        self.tls = tls or settings.ca_file is not None
        self.ca_file, self.cert_file, self.key_file = settings.ca_file, settings.cert_file, settings.key_file
        self.queue = settings.queue
        self.outbox_size = settings.outbox
        self.keepalive_s = settings.keepalive_s
        self.reconnect = (settings.reconnect_min_s, settings.reconnect_max_s)
        self.drain_s = DRAIN_S
        self._online: Outgoing | None = None
        self._offline: Outgoing | None = None
        self._client: aiomqtt.Client | None = None
        self._runner: asyncio.Task[None] | None = None
        self._incoming = FairQueue(settings.queue)
        self._arrived = asyncio.Event()
        self._outbox: dict[int, Outgoing] = {}  # by number, in order; left when acknowledged
        self._to_send: deque[int] = deque()  # outbox numbers not yet handed to this connection
        self._numbers = itertools.count()
        self._wake = asyncio.Event()
        self._connected = asyncio.Event()
        self._problem: str | None = "mqtt: not connected yet"
        self._dropped_incoming = 0
        self._dropped_outbox = 0
        self.connects = 0
        self.presence = presence
        self._ping = None if presence is None else f"mocapd/{presence}/ping"
        self._asked: OrderedDict[str, float] = OrderedDict()  # stream -> when its skeleton was asked for
        self._to_ask: deque[str] = deque()
        self._ask = asyncio.Event()

    def announce(self, online: Outgoing, offline: Outgoing) -> None:
        """Publish ``online`` on every connect; ``offline`` is the last will and is published before a
        planned close. Call before entering (the will is fixed then); again before leaving, it
        changes what the planned close publishes."""
        self._online, self._offline = online, offline

    def drain_within(self, seconds: float) -> None:
        """Leaving waits at most ``seconds`` for the outbox to empty and "offline" to be acknowledged."""
        self.drain_s = seconds

    async def __aenter__(self) -> MqttTransport:
        context = None
        if self.tls:
            context = ssl.create_default_context(cafile=self.ca_file)
            if self.cert_file is not None:
                context.load_cert_chain(self.cert_file, self.key_file)
        if self.presence is not None:
            await self._probe(context)
        will = None
        if self._offline is not None:
            will = aiomqtt.Will(self._offline.topic, self._offline.payload, qos=1, retain=True)

        self._client = _Client(
            self.host,
            self.port,
            identifier=self.client_id,
            clean_session=False,
            username=self.username,
            password=self.password,
            will=will,
            keepalive=self.keepalive_s,
            tls_context=context,
            deliver=self._deliver,
            max_inflight_messages=INFLIGHT,
            timeout=10,
            socket_options=[(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)],  # no Nagle delay on small packets
            logger=CLIENT_LOG,
        )
        self._runner = asyncio.create_task(self._run(), name=f"mqtt {self.host}:{self.port}")
        return self

    async def __aexit__(
        self, kind: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        """Drain the outbox (at most ``drain_s`` seconds), publish "offline", disconnect."""
        deadline = time.monotonic() + self.drain_s
        while self._outbox and self._connected.is_set() and time.monotonic() < deadline:
            await asyncio.sleep(0.01)
        client = self._client
        if self._offline is not None and client is not None and self._connected.is_set():
            with contextlib.suppress(aiomqtt.MqttError, asyncio.TimeoutError):
                await asyncio.wait_for(
                    self._send(client, self._offline), max(0.1, deadline - time.monotonic())
                )
        if self._runner is not None:
            self._runner.cancel()
            with contextlib.suppress(asyncio.CancelledError, aiomqtt.MqttError):
                await self._runner
        self._runner = None

    async def _run(self) -> None:
        assert self._client is not None
        client = self._client
        delay = self.reconnect[0]
        while True:
            try:
                async with client:
                    self.connects += 1
                    if self._online is not None:
                        await self._send(client, self._online)
                    for topic, qos in self.subscriptions:
                        await client.subscribe(topic, qos=qos)
                    if self._ping is not None:
                        await client.subscribe(self._ping, qos=0)
                    self._problem = None
                    self._connected.set()
                    LOG.info(
                        "mqtt connected", extra={"fields": {"broker": self.url, "connects": self.connects}}
                    )
                    delay = self.reconnect[0]
                    async with asyncio.TaskGroup() as tasks:
                        tasks.create_task(self._sender(client), name="mqtt sender")
                        tasks.create_task(self._reader(client), name="mqtt reader")
                        tasks.create_task(self._asker(client), name="mqtt skeleton requests")
            except* aiomqtt.MqttError as group:
                self._problem = f"mqtt: {group.exceptions[0]} (reconnecting)"
                LOG.warning(
                    "mqtt lost", extra={"fields": {"broker": self.url, "error": str(group.exceptions[0])}}
                )
            self._connected.clear()
            await asyncio.sleep(delay)
            delay = min(2 * delay, self.reconnect[1])

    async def _probe(self, context: ssl.SSLContext | None) -> None:
        """Before taking the client id: ask, with a client id of its own, whether a live daemon
        already answers for ``presence`` (``mocapd/<presence>/ping``, answered on ``.../pong``
        within :data:`PROBE_S`); StartupError if one does. A retained "online" cannot tell: a
        daemon killed leaves it until the broker notices, but a dead daemon answers no ping. No
        broker within the probe's time: nothing is known, the daemon goes on (and waits for it)."""
        assert self.presence is not None and self._ping is not None
        nonce = uuid.uuid4().hex
        pong = f"mocapd/{self.presence}/pong"
        try:
            async with aiomqtt.Client(
                self.host,
                self.port,
                identifier=f"{self.client_id}-probe-{nonce[:8]}",
                clean_session=True,
                username=self.username,
                password=self.password,
                tls_context=context,
                timeout=PROBE_S,
                logger=CLIENT_LOG,
            ) as probe:
                await probe.subscribe(pong, qos=0)
                await probe.publish(self._ping, nonce.encode(), qos=0)
                async with asyncio.timeout(PROBE_S):
                    async for message in probe.messages:
                        if str(message.topic) == pong and message.payload == nonce.encode():
                            break
                    else:
                        return
        except (aiomqtt.MqttError, TimeoutError, OSError):
            return  # no answer, or no broker yet
        raise StartupError(
            "service.instance",
            f"{self.presence!r} is served by a live daemon on {self.url} already (client id "
            f"{self.client_id}); give each daemon an instance of its own",
        )

    def ask_skeleton(self, stream: str) -> None:
        """Subscribe to ``stream``'s skeleton topic again, which makes the broker send its retained
        skeleton (MQTT 3.1.1, 3.8.4); at most once per :data:`ASK_EVERY_S` per stream, the streams
        remembered bounded (:data:`ASKED`)."""
        now = time.monotonic()
        last = self._asked.get(stream)
        if last is not None and now - last < ASK_EVERY_S:
            return
        self._asked[stream] = now
        self._asked.move_to_end(stream)
        while len(self._asked) > ASKED:
            self._asked.popitem(last=False)
        if len(self._to_ask) < ASKED:
            self._to_ask.append(stream)
            self._ask.set()

    async def _asker(self, client: aiomqtt.Client) -> None:
        """Ask for the skeletons :meth:`ask_skeleton` queued: subscribe to each stream's skeleton
        topic, and a moment later unsubscribe (the wildcard subscription keeps taking it)."""
        while True:
            while not self._to_ask:
                self._ask.clear()
                await self._ask.wait()
            topics = [f"mocap/{self._to_ask.popleft()}/skeleton" for _ in range(len(self._to_ask))]
            for t in topics:
                await client.subscribe(t, qos=1)
            await asyncio.sleep(1.0)
            for t in topics:
                await client.unsubscribe(t)

    async def _reader(self, client: aiomqtt.Client) -> None:
        async for _ in client.messages:  # nothing comes (see _Client); raises when the connection is lost
            pass

    def _deliver(self, topic: str, payload: bytes) -> None:
        if topic == self._ping:  # another daemon's probe: this instance is alive
            self._enqueue(Outgoing(f"mocapd/{self.presence}/pong", payload))
            return
        self._put(Incoming(topic, payload, time.time()))

    async def _sender(self, client: aiomqtt.Client) -> None:
        """Hand the outbox to the connection, up to :data:`INFLIGHT` messages awaiting
        acknowledgement at once; after a reconnect, all of it again."""
        self._to_send = deque(self._outbox)
        slots = asyncio.Semaphore(INFLIGHT)

        async def one(number: int, message: Outgoing) -> None:
            try:
                await self._send(client, message)  # MqttError: kept, sent again after the reconnect
                self._outbox.pop(number, None)
            finally:
                slots.release()

        async with asyncio.TaskGroup() as flights:
            while True:
                while not self._to_send:
                    self._wake.clear()
                    await self._wake.wait()
                number = self._to_send.popleft()
                message = self._outbox.get(number)
                if message is None:
                    continue
                await slots.acquire()
                flights.create_task(one(number, message))

    async def _send(self, client: aiomqtt.Client, m: Outgoing) -> None:
        await client.publish(m.topic, m.payload, qos=1 if m.reliable else 0, retain=m.retain)

    def _put(self, message: Incoming) -> None:
        if self._incoming.put(message):
            self._dropped_incoming += 1
        self._arrived.set()

    # ----------------------------------------------------------------------------- the interface

    def source(self) -> MqttTransport:
        return self

    def sink(self) -> MqttTransport:
        return self

    async def __aiter__(self) -> AsyncIterator[Incoming]:
        incoming = self._incoming
        while True:
            while not incoming:
                self._arrived.clear()
                await self._arrived.wait()
            message = incoming.take()
            assert message is not None
            yield message

    async def publish(self, message: Outgoing) -> None:
        """Queue ``message`` for sending (never waits for the network). An unreliable message while
        disconnected is dropped; when the outbox is full the oldest unreliable one goes, or if there
        is none the message itself is dropped (counted)."""
        self._enqueue(message)

    def _enqueue(self, message: Outgoing) -> None:
        if not message.reliable and not self._connected.is_set():
            self._dropped_outbox += 1
            return
        if len(self._outbox) >= self.outbox_size:
            unreliable = next((n for n, queued in self._outbox.items() if not queued.reliable), None)
            if unreliable is None:
                self._dropped_outbox += 1
                return
            del self._outbox[unreliable]
        number = next(self._numbers)
        self._outbox[number] = message
        self._to_send.append(number)
        self._wake.set()

    async def wait_connected(self, timeout: float | None = None) -> None:
        await asyncio.wait_for(self._connected.wait(), timeout)

    @property
    def problem(self) -> str | None:
        return self._problem

    @property
    def pending(self) -> int:
        """Messages in the outbox (not yet acknowledged)."""
        return len(self._outbox)

    def dropped(self) -> dict[str, int]:
        return {
            "mqtt_incoming_full": self._dropped_incoming,
            "mqtt_outbox_full": self._dropped_outbox,
        }


def transport(settings: MqttConfig, *, instance: str, source: bool, sink: bool) -> MqttTransport:
    """The daemon's MQTT transport (:class:`protocols.transport.Factory`): as ``mocapd-<instance>``
    unless ``settings.client_id`` says otherwise, subscribed to :data:`SUBSCRIPTIONS` if it is a
    source, and making sure it is the only live daemon of ``instance``."""
    return MqttTransport(
        settings,
        client_id=settings.client_id or f"mocapd-{instance}",
        subscribe=SUBSCRIPTIONS if source else (),
        presence=instance,
    )
