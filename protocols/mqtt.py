"""MQTT: subscriptions in, publications out, over one connection that mends itself; built on
paho-mqtt's documented external-loop API.

Why paho's own API and not aiomqtt's: aiomqtt (2.x; it is built on paho) reads one packet per
readable event and hands every message on through an asyncio.Queue, awaited per message; its public
API has no way to read more per event or to take a message without its queue, and that costs about
twice the CPU per message of what is here, more than the daemon can spare at a hundred 120 Hz
streams (``bench/bench_mqtt_intake.py``; docs/benchmarks.md, "MQTT intake"). What the daemon once
did instead, replacing a socket callback of aiomqtt's and two private methods of paho's, was at the
mercy of any patch release. paho's external-loop API is the documented seam aiomqtt itself uses: the
event loop watches the client's socket (``on_socket_open``, ``on_socket_close``,
``on_socket_register_write``, ``on_socket_unregister_write``) and calls ``loop_read``,
``loop_write`` and ``loop_misc``; messages come through ``on_message`` (``message.topic``,
``message.payload``), acknowledgements through ``on_publish``, ``on_subscribe`` and
``on_unsubscribe``. A readable event reads packets for as long as they keep coming (the socket is
level-triggered: what is left wakes the loop again), so a burst costs one event, and each message
goes straight into the fair queue. (paho still reads a packet with a few small ``recv`` calls, its
type byte, its length and the rest; no public API changes that.)

The connection: one paho client per connection (:class:`_Connection`), made again after every loss
with a capped exponential back-off, subscribing again on every connect. The session is persistent
(``clean_session=False`` with a fixed client id), so the broker keeps the subscriptions and queued
QoS 1 messages across the daemon's reconnects and, with persistence on, its own restarts. Reliable
messages (detections: QoS 1) go through an outbox and leave it only when the broker acknowledged
them; what was not acknowledged when the connection dropped is sent again after the reconnect
(a consumer may see a repeat: detections carry an event id). With :meth:`MqttTransport.announce`,
the "online" status is published retained on every connect, the "offline" one is the retained last
will, and a planned close publishes "offline" itself before disconnecting (a clean disconnect
suppresses the will). The incoming queue is bounded (``mqtt.queue``) and fair between streams
(:class:`~protocols.fair.FairQueue`): when it is full the oldest message of the stream holding the
most is dropped (counted), so one stream's flood does not crowd out the others.
"""

from __future__ import annotations

import asyncio
import contextlib
import itertools
import logging
import socket
import ssl
import threading
import time
import uuid
from collections import OrderedDict, deque
from collections.abc import AsyncIterator, Callable, Sequence
from types import TracebackType
from typing import TYPE_CHECKING, Any

import paho.mqtt.client as paho
from paho.mqtt.enums import CallbackAPIVersion, MQTTErrorCode
from paho.mqtt.properties import Properties
from paho.mqtt.reasoncodes import ReasonCode

from protocols.fair import FairQueue
from protocols.transport import Incoming, Outgoing, StartupError
from protocols.urls import parse_mqtt_url

if TYPE_CHECKING:
    from daemon.config import MqttConfig

LOG = logging.getLogger("mocapd.mqtt")
CLIENT_LOG = logging.getLogger("mocapd.mqtt.client")
"""paho's own logger: only errors (its debug and warning lines say nothing the outbox and /metrics
do not)."""
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
TIMEOUT_S = 10.0
"""The longest a connection waits for the broker to accept it (once TCP and TLS are up: paho's own
connect timeout) and to answer a subscription or the "online" status; past it the connection is
dropped and made again."""
INFLIGHT = 100
"""Reliable messages awaiting the broker's acknowledgement at once (one at a time would pay a round
trip per detection)."""
DRAIN_S = 2.0
"""How long leaving waits for the outbox to empty, unless told otherwise (``drain_within``)."""
CLOSE_S = 1.0
"""How long a clean disconnect waits for the DISCONNECT packet to leave."""
READ_PACKETS = 512
"""The most packets one readable event takes, so that reading yields to the other tasks."""
MISC_EVERY_S = 1.0
"""How often paho's ``loop_misc`` runs (keepalive pings, and noticing a broker that stopped
answering them)."""


class MqttLost(Exception):
    """A connection could not be made, or ended (the message says why); the transport makes
    another."""


class _Connection:
    """One connection to the broker, from connect to its end: a paho client driven by the running
    event loop through paho's external-loop API. Enter it to connect (MqttLost if that fails),
    leave it to disconnect cleanly; :attr:`lost` is done when the connection ended (with MqttLost
    saying why, unless it was this side's clean disconnect). ``deliver(topic, payload)`` takes
    every message received, on the event loop."""

    def __init__(
        self,
        host: str,
        port: int,
        *,
        client_id: str,
        clean_session: bool,
        keepalive_s: int,
        username: str | None,
        password: str | None,
        tls: ssl.SSLContext | None,
        will: Outgoing | None,
        deliver: Callable[[str, bytes], None],
        timeout_s: float,
    ) -> None:
        self._loop = asyncio.get_running_loop()
        self._thread = threading.get_ident()
        self._address = (host, port, keepalive_s)
        self._deliver = deliver
        self.timeout_s = timeout_s
        self._connected: asyncio.Future[None] = self._loop.create_future()
        self.lost: asyncio.Future[None] = self._loop.create_future()
        for future in (self._connected, self.lost):
            future.add_done_callback(_retrieved)
        self._waiting: dict[int, asyncio.Future[None]] = {}  # message id -> its acknowledgement
        self._fd = -1
        self._closed = False
        self._progress = 0  # packets that did something, for the read loop to tell when to stop
        mqtt = paho.Client(
            CallbackAPIVersion.VERSION2,
            client_id=client_id,
            clean_session=clean_session,
            protocol=paho.MQTTv311,
            reconnect_on_failure=False,
        )
        mqtt.enable_logger(CLIENT_LOG)
        mqtt.max_inflight_messages_set(INFLIGHT)
        if username is not None:
            mqtt.username_pw_set(username, password)
        if tls is not None:
            mqtt.tls_set_context(tls)
        if will is not None:
            mqtt.will_set(will.topic, will.payload, qos=1 if will.reliable else 0, retain=will.retain)
        mqtt.on_connect = self._connect_answered
        mqtt.on_disconnect = self._connection_ended
        mqtt.on_message = self._message_arrived
        mqtt.on_publish = self._acknowledged
        mqtt.on_subscribe = self._subscription_answered
        mqtt.on_unsubscribe = self._subscription_answered
        mqtt.on_socket_open = self._socket_opened
        mqtt.on_socket_close = self._socket_closed
        mqtt.on_socket_register_write = self._write_wanted
        mqtt.on_socket_unregister_write = self._write_done
        self.mqtt = mqtt

    async def __aenter__(self) -> _Connection:
        connecting = self._loop.run_in_executor(None, self._connect)  # DNS, TCP and TLS block
        try:
            await asyncio.shield(connecting)
        except asyncio.CancelledError:
            connecting.add_done_callback(self._closed_after)  # whatever it opens is closed
            raise
        except (OSError, ValueError) as e:  # ValueError: a certificate that does not match, a bad host
            raise MqttLost(str(e) or type(e).__name__) from None
        try:
            async with asyncio.timeout(self.timeout_s):
                await asyncio.shield(self._connected)
        except (TimeoutError, MqttLost) as e:
            self._close()
            if isinstance(e, MqttLost):
                raise
            raise MqttLost("the broker did not answer the connect") from None
        except asyncio.CancelledError:
            self._close()
            raise
        return self

    async def __aexit__(
        self, kind: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        """A clean disconnect (the broker does not publish the will) if the connection is still up."""
        try:
            if not self.lost.done() and self.mqtt.disconnect() == MQTTErrorCode.MQTT_ERR_SUCCESS:
                await asyncio.wait([self.lost], timeout=CLOSE_S)
        finally:
            self._close()

    def _connect(self) -> None:
        host, port, keepalive = self._address
        self.mqtt.connect(host, port, keepalive)

    def _closed_after(self, connecting: asyncio.Future[None]) -> None:
        _retrieved(connecting)
        self._close()

    def _close(self) -> None:
        """The socket closed, whatever state the connection is in (once; nothing if paho closed
        it)."""
        if self._closed:
            return
        self._closed = True
        if self.mqtt.socket() is not None:
            with contextlib.suppress(Exception):
                self.mqtt.disconnect()
                self.mqtt.loop_write()  # sends the DISCONNECT and closes the socket, or finds it dead
        sock = self.mqtt.socket()
        if sock is not None:  # could not even write that: let it go
            self._forget_socket()
            sock.close()
        self._end(MqttLost("closed"))

    # ----------------------------------------------------------------------- the socket, on the loop

    def _soon(self, call: Callable[..., object], *args: Any) -> None:
        """``call(*args)`` on the event loop: now if this is its thread, else as soon as it can
        (paho opens the socket, and queues CONNECT, in the thread that connects)."""
        if threading.get_ident() == self._thread:
            call(*args)
        else:
            self._loop.call_soon_threadsafe(call, *args)

    def _socket_opened(self, client: paho.Client, userdata: Any, sock: paho.SocketLike) -> None:
        if isinstance(sock, socket.socket):
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)  # no Nagle delay on small packets
        self._fd = sock.fileno()
        self._soon(self._loop.add_reader, self._fd, self._readable)

    def _socket_closed(self, client: paho.Client, userdata: Any, sock: paho.SocketLike) -> None:
        self._soon(self._forget_socket)

    def _forget_socket(self) -> None:
        if self._fd >= 0:
            self._loop.remove_reader(self._fd)
            self._loop.remove_writer(self._fd)
            self._fd = -1

    def _write_wanted(self, client: paho.Client, userdata: Any, sock: paho.SocketLike) -> None:
        self._soon(self._watch_writable, sock.fileno())

    def _watch_writable(self, fd: int) -> None:
        if fd >= 0 and fd == self._fd:  # not a socket closed since
            self._loop.add_writer(fd, self._writable)

    def _write_done(self, client: paho.Client, userdata: Any, sock: paho.SocketLike) -> None:
        self._soon(self._unwatch_writable)

    def _unwatch_writable(self) -> None:
        if self._fd >= 0:
            self._loop.remove_writer(self._fd)

    def _readable(self) -> None:
        """Read packets while they keep doing something (paho reads one or a few per
        ``loop_read``), at most :data:`READ_PACKETS`. A TLS socket may hold decrypted bytes its file
        descriptor no longer says are there: those are read too, or come back for."""
        mqtt = self.mqtt
        try:
            for _ in range(READ_PACKETS):
                before = self._progress
                if mqtt.loop_read() != MQTTErrorCode.MQTT_ERR_SUCCESS:
                    return  # the connection ended: paho closed it and said why (on_disconnect)
                sock = mqtt.socket()
                buffered = isinstance(sock, ssl.SSLSocket) and sock.pending() > 0
                if sock is None or (self._progress == before and not buffered):
                    return  # nothing more for now; what comes wakes the loop again
            sock = mqtt.socket()
            if isinstance(sock, ssl.SSLSocket) and sock.pending() > 0:
                self._loop.call_soon(self._readable)
        except Exception as e:  # any failure to read ends the connection
            self._fail(f"reading: {e}")

    def _writable(self) -> None:
        try:
            self.mqtt.loop_write()
        except Exception as e:
            self._fail(f"writing: {e}")

    def _fail(self, why: str) -> None:
        """The connection is over for this side (leaving closes the socket): not watched any more."""
        self._forget_socket()
        self._end(MqttLost(why))

    async def serve(self) -> None:
        """Keep the connection alive (``loop_misc``: keepalive pings, and giving up on a broker
        that stopped answering them) until it ends; raises MqttLost saying why."""
        while not self.lost.done():
            rc = self.mqtt.loop_misc()
            if rc != MQTTErrorCode.MQTT_ERR_SUCCESS:
                self._end(MqttLost(paho.error_string(rc)))
                break
            await asyncio.wait([self.lost], timeout=MISC_EVERY_S)
        await self.lost  # raises MqttLost saying why
        raise MqttLost("disconnected")

    # --------------------------------------------------------------------------------- requests

    def publish(self, message: Outgoing) -> asyncio.Future[None]:
        """Hand ``message`` to the connection; the future is done when the broker acknowledged it
        (reliable: QoS 1) or it was written (QoS 0), and fails with MqttLost if the connection ends
        first."""
        done = self._loop.create_future()
        qos = 1 if message.reliable else 0
        info = self.mqtt.publish(message.topic, message.payload, qos=qos, retain=message.retain)
        if info.rc != MQTTErrorCode.MQTT_ERR_SUCCESS:
            done.set_exception(MqttLost(f"publishing: {paho.error_string(info.rc)}"))
        elif info.is_published():
            done.set_result(None)
        else:
            self._waiting[info.mid] = done
        return done

    @property
    def in_flight(self) -> int:
        return len(self._waiting)

    async def subscribe(self, topic: str, qos: int) -> None:
        rc, mid = self.mqtt.subscribe(topic, qos)
        await self._answered(rc, mid, f"subscribing to {topic}")

    async def unsubscribe(self, topic: str) -> None:
        rc, mid = self.mqtt.unsubscribe(topic)
        await self._answered(rc, mid, f"unsubscribing from {topic}")

    async def _answered(self, rc: MQTTErrorCode, mid: int | None, what: str) -> None:
        """Wait for the broker to answer request ``mid`` (at most :attr:`timeout_s`)."""
        if rc != MQTTErrorCode.MQTT_ERR_SUCCESS or mid is None:
            raise MqttLost(f"{what}: {paho.error_string(rc)}")
        done = self._waiting[mid] = self._loop.create_future()
        try:
            async with asyncio.timeout(self.timeout_s):
                await done
        except TimeoutError:
            raise MqttLost(f"{what}: the broker did not answer") from None

    # -------------------------------------------------------------------------- paho's callbacks

    def _connect_answered(
        self,
        client: paho.Client,
        userdata: Any,
        flags: paho.ConnectFlags,
        reason: ReasonCode,
        properties: Properties | None,
    ) -> None:
        self._progress += 1
        if self._connected.done():
            return
        if reason.is_failure:
            self._connected.set_exception(MqttLost(f"the broker refused the connection: {reason}"))
        else:
            self._connected.set_result(None)

    def _connection_ended(
        self,
        client: paho.Client,
        userdata: Any,
        flags: paho.DisconnectFlags,
        reason: ReasonCode,
        properties: Properties | None,
    ) -> None:
        self._end(None if reason == 0 else MqttLost(f"connection lost ({reason})"))

    def _end(self, why: MqttLost | None) -> None:
        """The connection is over: everything waiting on it fails (``why``, or MqttLost)."""
        failure = why or MqttLost("disconnected")
        if not self._connected.done():
            self._connected.set_exception(failure)
        if not self.lost.done():
            if why is None:
                self.lost.set_result(None)
            else:
                self.lost.set_exception(why)
        waiting, self._waiting = self._waiting, {}
        for done in waiting.values():
            if not done.done():
                done.set_exception(failure)

    def _message_arrived(self, client: paho.Client, userdata: Any, message: paho.MQTTMessage) -> None:
        self._progress += 1
        try:
            topic = message.topic
        except UnicodeDecodeError:  # not a topic mocapd could have subscribed to
            return
        payload = message.payload
        self._deliver(topic, payload if isinstance(payload, bytes) else bytes(payload))

    def _acknowledged(
        self, client: paho.Client, userdata: Any, mid: int, reason: ReasonCode, properties: Properties
    ) -> None:
        self._progress += 1
        done = self._waiting.pop(mid, None)
        if done is not None and not done.done():
            done.set_result(None)

    def _subscription_answered(
        self,
        client: paho.Client,
        userdata: Any,
        mid: int,
        reasons: list[ReasonCode],
        properties: Properties | None,
    ) -> None:
        self._progress += 1
        done = self._waiting.pop(mid, None)
        if done is not None and not done.done():
            done.set_result(None)


class MqttTransport:
    """An MQTT connection to the broker of ``settings`` (``url``, credentials, TLS files, queue
    bounds, keepalive, reconnect back-off; ``daemon.config.MqttConfig``): ``subscribe`` (topic, QoS)
    pairs in, publications out, as ``client_id`` (fixed: the persistent session is the broker's
    record of it). With ``presence`` (the instance name), a starting transport first makes sure no
    live daemon of that instance is on the broker, and answers the next one's question itself.
    ``clean_session``: a session the broker forgets when the connection ends (an observer's, such
    as ``mocapd view``'s, which wants nothing kept for it while it is away)."""

    name = "mqtt"

    def __init__(
        self,
        settings: MqttConfig,
        *,
        client_id: str,
        subscribe: Sequence[tuple[str, int]],
        presence: str | None,
        clean_session: bool = False,
    ) -> None:
        self.host, self.port, tls = parse_mqtt_url(settings.url)
        self.clean_session = clean_session
        self.url = settings.url
        self.settings = settings
        self.client_id = client_id
        self.subscriptions = list(subscribe)
        self.tls = tls or settings.ca_file is not None
        self.drain_s = DRAIN_S
        self._online: Outgoing | None = None
        self._offline: Outgoing | None = None
        self._connection: _Connection | None = None
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

    def _tls_context(self) -> ssl.SSLContext | None:
        if not self.tls:
            return None
        context = ssl.create_default_context(cafile=self.settings.ca_file)
        if self.settings.cert_file is not None:
            context.load_cert_chain(self.settings.cert_file, self.settings.key_file)
        return context

    def _connection_to(
        self,
        context: ssl.SSLContext | None,
        *,
        client_id: str,
        clean_session: bool,
        will: Outgoing | None,
        deliver: Callable[[str, bytes], None],
        timeout_s: float,
    ) -> _Connection:
        s = self.settings
        return _Connection(
            self.host,
            self.port,
            client_id=client_id,
            clean_session=clean_session,
            keepalive_s=s.keepalive_s,
            username=s.username,
            password=s.password,
            tls=context,
            will=will,
            deliver=deliver,
            timeout_s=timeout_s,
        )

    async def __aenter__(self) -> MqttTransport:
        context = self._tls_context()
        if self.presence is not None:
            await self._probe(context)
        self._runner = asyncio.create_task(self._run(context), name=f"mqtt {self.host}:{self.port}")
        return self

    async def __aexit__(
        self, kind: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        """Drain the outbox (at most ``drain_s`` seconds), publish "offline", disconnect."""
        deadline = time.monotonic() + self.drain_s
        while self._outbox and self._connected.is_set() and time.monotonic() < deadline:
            await asyncio.sleep(0.01)
        connection = self._connection
        if self._offline is not None and connection is not None and self._connected.is_set():
            with contextlib.suppress(MqttLost, TimeoutError):
                await asyncio.wait_for(
                    connection.publish(self._offline), max(0.1, deadline - time.monotonic())
                )
        if self._runner is not None:
            self._runner.cancel()  # leaving the connection disconnects it cleanly
            with contextlib.suppress(asyncio.CancelledError):
                await self._runner
        self._runner = None

    async def _run(self, context: ssl.SSLContext | None) -> None:
        delay = self.settings.reconnect_min_s
        while True:
            connection = self._connection_to(
                context,
                client_id=self.client_id,
                clean_session=self.clean_session,
                will=self._offline,
                deliver=self._deliver,
                timeout_s=TIMEOUT_S,
            )
            try:
                async with connection:
                    self._connection = connection
                    self.connects += 1
                    if self._online is not None:
                        await self._settled(connection, connection.publish(self._online))
                    for topic, qos in self.subscriptions:
                        await connection.subscribe(topic, qos)
                    if self._ping is not None:
                        await connection.subscribe(self._ping, 0)
                    self._problem = None
                    self._connected.set()
                    LOG.info(
                        "mqtt connected", extra={"fields": {"broker": self.url, "connects": self.connects}}
                    )
                    delay = self.settings.reconnect_min_s
                    async with asyncio.TaskGroup() as tasks:
                        tasks.create_task(connection.serve(), name="mqtt connection")
                        tasks.create_task(self._sender(connection), name="mqtt sender")
                        tasks.create_task(self._asker(connection), name="mqtt skeleton requests")
            except* MqttLost as group:
                self._problem = f"mqtt: {group.exceptions[0]} (reconnecting)"
                LOG.warning(
                    "mqtt lost", extra={"fields": {"broker": self.url, "error": str(group.exceptions[0])}}
                )
            finally:
                self._connected.clear()
                self._connection = None
            await asyncio.sleep(delay)
            delay = min(2 * delay, self.settings.reconnect_max_s)

    @staticmethod
    async def _settled(connection: _Connection, done: asyncio.Future[None]) -> None:
        try:
            async with asyncio.timeout(connection.timeout_s):
                await done
        except TimeoutError:
            raise MqttLost("the broker did not acknowledge") from None

    async def _probe(self, context: ssl.SSLContext | None) -> None:
        """Before taking the client id: ask, with a client id of its own, whether a live daemon
        already answers for ``presence`` (``mocapd/<presence>/ping``, answered on ``.../pong``
        within :data:`PROBE_S`); StartupError if one does. A retained "online" cannot tell: a
        daemon killed leaves it until the broker notices, but a dead daemon answers no ping. No
        broker within the probe's time: nothing is known, the daemon goes on (and waits for it)."""
        assert self.presence is not None and self._ping is not None
        nonce = uuid.uuid4().hex.encode()
        pong = f"mocapd/{self.presence}/pong"
        answered = asyncio.Event()

        def deliver(topic: str, payload: bytes) -> None:
            if topic == pong and payload == nonce:
                answered.set()

        probe = self._connection_to(
            context,
            client_id=f"{self.client_id}-probe-{nonce[:8].decode()}",
            clean_session=True,
            will=None,
            deliver=deliver,
            timeout_s=PROBE_S,
        )
        try:
            async with probe:
                await probe.subscribe(pong, 0)
                probe.publish(Outgoing(self._ping, nonce)).add_done_callback(_retrieved)
                async with asyncio.timeout(PROBE_S):
                    await answered.wait()
        except (MqttLost, TimeoutError):
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

    async def _asker(self, connection: _Connection) -> None:
        """Ask for the skeletons :meth:`ask_skeleton` queued: subscribe to each stream's skeleton
        topic, and a moment later unsubscribe (the wildcard subscription keeps taking it)."""
        while True:
            while not self._to_ask:
                self._ask.clear()
                await self._ask.wait()
            topics = [f"mocap/{self._to_ask.popleft()}/skeleton" for _ in range(len(self._to_ask))]
            for t in topics:
                await connection.subscribe(t, 1)
            await asyncio.sleep(1.0)
            for t in topics:
                await connection.unsubscribe(t)

    def _deliver(self, topic: str, payload: bytes) -> None:
        if topic == self._ping:  # another daemon's probe: this instance is alive
            self._enqueue(Outgoing(f"mocapd/{self.presence}/pong", payload))
            return
        if self._incoming.put(Incoming(topic, payload, time.time())):
            self._dropped_incoming += 1
        self._arrived.set()

    async def _sender(self, connection: _Connection) -> None:
        """Hand the outbox to the connection, up to :data:`INFLIGHT` messages awaiting
        acknowledgement at once; after a reconnect, all of it again."""
        self._to_send = deque(self._outbox)

        def landed(number: int) -> Callable[[asyncio.Future[None]], None]:
            def done(future: asyncio.Future[None]) -> None:
                if not future.cancelled() and future.exception() is None:
                    self._outbox.pop(number, None)
                self._wake.set()  # a slot is free

            return done

        while True:
            while not self._to_send or connection.in_flight >= INFLIGHT:
                self._wake.clear()
                await self._wake.wait()
            number = self._to_send.popleft()
            message = self._outbox.get(number)
            if message is not None:
                connection.publish(message).add_done_callback(landed(number))

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
        is none the message itself is dropped (counted). A relayed pose is not published: MQTT's
        clients hear the publishers on the broker."""
        if not message.relay:
            self._enqueue(message)

    def _enqueue(self, message: Outgoing) -> None:
        if not message.reliable and not self._connected.is_set():
            self._dropped_outbox += 1
            return
        if len(self._outbox) >= self.settings.outbox:
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


def _retrieved(future: asyncio.Future[None]) -> None:
    """A done callback for a future nobody awaits: its failure is taken, not reported as lost."""
    if not future.cancelled():
        future.exception()


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
