"""MQTT: subscriptions in over one connection, publications out over another, the pair mended
together; publishing is built on paho-mqtt's documented external-loop API, reading on gmqtt's
public API (:class:`_Reader`: it takes a message for half paho's CPU, ``bench/bench_mqtt_intake.py``).

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
type byte, its length and the rest; no public API changes that: hence the reader.) Why not gmqtt
for both: it has no public acknowledgement of a QoS 1 publication, which the outbox needs.

The connections: one paho client (:class:`_Connection`) and, when there are subscriptions, one
gmqtt client (:class:`_Reader`, as the client id with ``-in`` appended) per connection, both made
again after either is lost, with a capped exponential back-off, subscribing again on every connect.
The reader's session is persistent (``clean_session=False`` with a fixed client id), so the broker
keeps the subscriptions and queued QoS 1 messages across the daemon's reconnects and, with
persistence on, its own restarts; the publishing connection's session is then a clean one (a
session kept from a daemon that subscribed on it would deliver everything a second time). Reliable
messages (detections: QoS 1) go through an outbox and leave it only when the broker acknowledged
them; what was not acknowledged when the connection dropped is sent again after the reconnect
(a consumer may see a repeat: detections carry an event id). With :meth:`MqttTransport.announce`,
the "online" status is published retained on every connect, the "offline" one is the retained last
will, and a planned close publishes "offline" itself before disconnecting (a clean disconnect
suppresses the will). The incoming queue is bounded (``mqtt.queue``) and fair between streams
(:class:`~protocols.fair.FairQueue`): when it is full the oldest message of the stream holding the
most is dropped (counted), so one stream's flood does not crowd out the others.

Start-up: the daemon's transport (``startup_s``: ``mqtt.startup_s``) is not entered until it is
connected; a broker that does not answer within that time, or refuses the connection, is a
:class:`~protocols.transport.StartupError` naming ``mqtt.url``, before the daemon says "online".
After that first connection it reconnects for ever. One daemon per instance and client id:
:class:`_Presence`.
"""

from __future__ import annotations

import asyncio
import contextlib
import itertools
import logging
import math
import socket
import ssl
import threading
import time
import uuid
from collections import OrderedDict, deque
from collections.abc import AsyncIterator, Callable, Sequence
from dataclasses import dataclass, replace
from types import TracebackType
from typing import TYPE_CHECKING, Any

import gmqtt
import msgpack
import paho.mqtt.client as paho
from gmqtt.mqtt.constants import MQTTv311
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
GMQTT_LOG = logging.getLogger("mocapd.mqtt.reader")
"""gmqtt's logger for the reading connection: only errors (its warnings and info lines say a
connection was lost or made, which the transport logs itself)."""
GMQTT_LOG.setLevel(logging.ERROR)
logging.getLogger("gmqtt").setLevel(logging.ERROR)  # the loggers of its modules


SUBSCRIPTIONS = (("mocap/+/skeleton", 1), ("mocap/+/pose", 0), ("mocap/+/frame", 0))
"""What a daemon taking poses in over MQTT subscribes to: skeletons reliably (they are retained),
poses and frame messages as they come."""
PROBE_S = 0.5
"""How long a starting daemon waits, once it asked, for another daemon of its instance or client id
to answer (:class:`_Presence`)."""
CONTESTED_S = 10.0
"""How long after its main connection was lost a live daemon gives way to a claim that beats its
own (:class:`_Presence`). A daemon whose client id another takes over loses its connection first;
at any other time a claim is a message anyone on the broker can send, which must not stop it."""
PINGS = "mocapd/+/ping"
"""Where daemons ask who else is there: every daemon's guard hears every instance's questions, since
two instances may share a client id."""
STEADY_S = 10.0
"""A connection that lasted less than this does not reset the reconnect back-off, so a client id
that something else takes over again and again (not a mocapd: its guard would see that) is taken
back at most once per ``mqtt.reconnect_max_s``, not four times a second."""
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
NEVER_S = 1e9
"""The delay put on gmqtt's own reconnecting (:class:`_Reader`): longer than any daemon runs."""
MISC_EVERY_S = 1.0
"""How often paho's ``loop_misc`` runs (keepalive pings, and noticing a broker that stopped
answering them)."""


class MqttLost(Exception):
    """A connection could not be made, or ended (the message says why); the transport makes
    another. ``refused``: the broker refused it (trying again will not do at start)."""

    def __init__(self, why: str, *, refused: bool = False) -> None:
        super().__init__(why)
        self.refused = refused


TRANSIENT_REFUSALS = frozenset({"Server unavailable"})
"""The broker refusals (paho's names of MQTT 3.1.1's CONNACK codes) that may mend by themselves."""


class _Pending:
    """What a connection awaits the broker's answer to, by message id: acknowledgements of QoS 1
    publications, answers to (un)subscriptions."""

    def __init__(self, loop: asyncio.AbstractEventLoop) -> None:
        self._loop = loop
        self._by_id: dict[int, asyncio.Future[None]] = {}

    def __len__(self) -> int:
        return len(self._by_id)

    def add(self, mid: int) -> asyncio.Future[None]:
        done = self._by_id[mid] = self._loop.create_future()
        return done

    def answer(self, mid: int) -> None:
        done = self._by_id.pop(mid, None)
        if done is not None and not done.done():
            done.set_result(None)

    async def wait(self, mid: int, what: str, timeout_s: float) -> None:
        """Wait for the answer to request ``mid`` (``what``), at most ``timeout_s`` (MqttLost after)."""
        try:
            async with asyncio.timeout(timeout_s):
                await self.add(mid)
        except TimeoutError:
            raise MqttLost(f"{what}: the broker did not answer") from None

    def fail(self, why: MqttLost) -> None:
        """The connection ended: everything awaited fails with ``why``."""
        waiting, self._by_id = self._by_id, {}
        for done in waiting.values():
            if not done.done():
                done.set_exception(why)


@dataclass(frozen=True)
class _Broker:
    """Where and how a connection reaches the broker: address, keepalive in seconds, credentials
    and TLS."""

    host: str
    port: int
    keepalive_s: int
    username: str | None
    password: str | None
    tls: ssl.SSLContext | None


class _Connection:
    """One connection to the broker, from connect to its end: a paho client driven by the running
    event loop through paho's external-loop API. Enter it to connect (MqttLost if that fails),
    leave it to disconnect cleanly; :attr:`lost` is done when the connection ended (with MqttLost
    saying why, unless it was this side's clean disconnect). ``deliver(topic, payload)`` takes
    every message received, on the event loop."""

    def __init__(
        self,
        broker: _Broker,
        *,
        client_id: str,
        clean_session: bool,
        will: Outgoing | None,
        deliver: Callable[[str, bytes], None],
        timeout_s: float,
    ) -> None:
        self._loop = asyncio.get_running_loop()
        self._thread = threading.get_ident()
        self._broker = broker
        self._deliver = deliver
        self.timeout_s = timeout_s
        self._connected: asyncio.Future[None] = self._loop.create_future()
        self.lost: asyncio.Future[None] = self._loop.create_future()
        for future in (self._connected, self.lost):
            future.add_done_callback(_retrieved)
        self._waiting = _Pending(self._loop)
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
        if broker.username is not None:
            mqtt.username_pw_set(broker.username, broker.password)
        if broker.tls is not None:
            mqtt.tls_set_context(broker.tls)
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
        b = self._broker
        self.mqtt.connect(b.host, b.port, b.keepalive_s)

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
        qos = 1 if message.reliable else 0
        info = self.mqtt.publish(message.topic, message.payload, qos=qos, retain=message.retain)
        if info.rc == MQTTErrorCode.MQTT_ERR_SUCCESS and not info.is_published():
            return self._waiting.add(info.mid)
        done = self._loop.create_future()
        if info.rc != MQTTErrorCode.MQTT_ERR_SUCCESS:
            done.set_exception(MqttLost(f"publishing: {paho.error_string(info.rc)}"))
        else:
            done.set_result(None)
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
        await self._waiting.wait(mid, what, self.timeout_s)

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
            refused = reason.getName() not in TRANSIENT_REFUSALS
            self._connected.set_exception(
                MqttLost(f"the broker refused the connection: {reason}", refused=refused)
            )
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
        self._waiting.fail(failure)

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
        self._waiting.answer(mid)

    def _subscription_answered(
        self,
        client: paho.Client,
        userdata: Any,
        mid: int,
        reasons: list[ReasonCode],
        properties: Properties | None,
    ) -> None:
        self._progress += 1
        self._waiting.answer(mid)


class _Reader:
    """One connection that only takes messages in, from connect to its end, over gmqtt's public
    API (``Client``, ``on_message``, ``on_subscribe``, ``on_unsubscribe``, ``on_disconnect``): an
    asyncio protocol that parses every packet a read brought, where paho reads each packet with
    several ``recv`` calls (the intake's largest cost: ``bench/bench_mqtt_intake.py``). It has the
    interface of :class:`_Connection` less publishing (the transport publishes on paho's).

    gmqtt mends a lost connection by itself, once at least even with ``reconnect_retries`` 0, and
    always as a persistent session under the same client id; the transport makes a new connection
    of its own instead, so gmqtt's attempt is put off for :data:`NEVER_S` (``reconnect_delay``) and
    never made: a client stays asleep in it until the event loop ends, one per lost connection."""

    def __init__(
        self,
        broker: _Broker,
        *,
        client_id: str,
        clean_session: bool,
        deliver: Callable[[str, bytes], None],
        timeout_s: float,
    ) -> None:
        self._loop = asyncio.get_running_loop()
        self._broker = broker
        self._deliver = deliver
        self.timeout_s = timeout_s
        self.lost: asyncio.Future[None] = self._loop.create_future()
        self.lost.add_done_callback(_retrieved)
        self._waiting = _Pending(self._loop)
        client = gmqtt.Client(client_id, clean_session=clean_session, logger=GMQTT_LOG)
        client.set_config({"reconnect_retries": 0, "reconnect_delay": NEVER_S})
        if broker.username is not None:
            client.set_auth_credentials(broker.username, broker.password)
        client.on_message = self._message_arrived
        client.on_subscribe = self._answered
        client.on_unsubscribe = self._answered
        client.on_disconnect = self._ended
        self.client = client

    async def __aenter__(self) -> _Reader:
        b = self._broker
        try:
            async with asyncio.timeout(self.timeout_s):
                await self.client.connect(
                    b.host, b.port, ssl=b.tls or False, keepalive=b.keepalive_s, version=MQTTv311
                )
        except BaseException as e:
            await self._close()
            if isinstance(e, gmqtt.MQTTConnectError):
                refused = "unavailable" not in e.message  # as TRANSIENT_REFUSALS for paho
                raise MqttLost(f"the broker refused the connection: {e.message}", refused=refused) from None
            if isinstance(e, TimeoutError):
                raise MqttLost("the broker did not answer the connect") from None
            if isinstance(e, OSError | ValueError):  # ValueError: a certificate that does not match
                raise MqttLost(str(e) or type(e).__name__) from None
            raise
        return self

    async def __aexit__(
        self, kind: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        await self._close()

    async def _close(self) -> None:
        """A clean disconnect, or the socket closed if the connection is already gone."""
        with contextlib.suppress(Exception):
            await asyncio.wait_for(self.client.disconnect(), CLOSE_S)
        self._end(MqttLost("closed"))

    async def serve(self) -> None:
        """Wait until the connection ends (gmqtt pings the broker, and closes a connection that
        heard nothing for twice the keepalive); raises MqttLost saying why."""
        await self.lost
        raise MqttLost("disconnected")

    async def subscribe(self, topic: str, qos: int) -> None:
        await self._request(self.client.subscribe(topic, qos=qos), f"subscribing to {topic}")

    async def unsubscribe(self, topic: str) -> None:
        await self._request(self.client.unsubscribe(topic), f"unsubscribing from {topic}")

    async def _request(self, mid: int, what: str) -> None:
        if self.lost.done():
            raise MqttLost(f"{what}: the connection ended")
        await self._waiting.wait(mid, what, self.timeout_s)

    def _answered(self, client: gmqtt.Client, mid: int, *rest: Any) -> None:
        self._waiting.answer(mid)

    def _message_arrived(
        self, client: gmqtt.Client, topic: str | bytes, payload: bytes, qos: int, properties: Any
    ) -> int:
        if isinstance(topic, str):  # bytes: not UTF-8, not a topic mocapd could have subscribed to
            self._deliver(topic, payload)
        return 0

    def _ended(self, client: gmqtt.Client, packet: Any, exc: BaseException | None = None) -> None:
        self._end(MqttLost(f"connection lost ({exc or 'the broker closed it'})"))

    def _end(self, why: MqttLost) -> None:
        if not self.lost.done():
            self.lost.set_exception(why)
        self._waiting.fail(why)


class MqttTransport:
    """An MQTT connection to the broker of ``settings`` (``url``, credentials, TLS files, queue
    bounds, keepalive, reconnect back-off; ``daemon.config.MqttConfig``): ``subscribe`` (topic, QoS)
    pairs in, publications out, as ``client_id`` (fixed: the persistent session is the broker's
    record of it). With ``presence`` (the instance name), a starting transport first makes sure no
    other daemon of that instance or client id is on the broker, and keeps the next one out
    (:class:`_Presence`). ``clean_session``: a session the broker forgets when the connection ends
    (an observer's, such as ``mocapd view``'s, which wants nothing kept for it while it is away).
    ``startup_s``: entering waits at most this long for the first connection (StartupError after
    it, or at once if the broker refuses); None: entering does not wait, the connection is made
    in the background."""

    name = "mqtt"

    def __init__(
        self,
        settings: MqttConfig,
        *,
        client_id: str,
        subscribe: Sequence[tuple[str, int]],
        presence: str | None,
        clean_session: bool = False,
        startup_s: float | None = None,
    ) -> None:
        self.host, self.port, tls = parse_mqtt_url(settings.url)
        self.startup_s = startup_s
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
        self._guard: _Presence | None = None
        self._failed: asyncio.Future[None] | None = None  # with StartupError: this daemon must stop
        self.last_error: str | None = None
        """Why the last connection failed or ended."""
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

    def connection_to(
        self,
        context: ssl.SSLContext | None,
        *,
        client_id: str,
        clean_session: bool,
        will: Outgoing | None,
        deliver: Callable[[str, bytes], None],
        timeout_s: float,
    ) -> _Connection:
        return _Connection(
            self._broker(context),
            client_id=client_id,
            clean_session=clean_session,
            will=will,
            deliver=deliver,
            timeout_s=timeout_s,
        )

    def reader_to(self, context: ssl.SSLContext | None, *, timeout_s: float) -> _Reader:
        """The connection the subscriptions are taken on: as ``client_id`` with ``-in`` appended,
        with the transport's kind of session."""
        return _Reader(
            self._broker(context),
            client_id=f"{self.client_id}-in",
            clean_session=self.clean_session,
            deliver=self._deliver,
            timeout_s=timeout_s,
        )

    def _broker(self, context: ssl.SSLContext | None) -> _Broker:
        s = self.settings
        return _Broker(self.host, self.port, s.keepalive_s, s.username, s.password, context)

    async def __aenter__(self) -> MqttTransport:
        context = self._tls_context()
        loop = asyncio.get_running_loop()
        self._failed = loop.create_future()
        self._failed.add_done_callback(_retrieved)
        deadline = None if self.startup_s is None else loop.time() + self.startup_s
        try:
            async with asyncio.timeout_at(deadline):
                if self.presence is not None:
                    self._guard = _Presence(self, context, self.presence)
                    await self._guard.claim()
                self._runner = asyncio.create_task(self._run(context), name=f"mqtt {self.host}:{self.port}")
                if deadline is not None:
                    await self._first_connection()
        except TimeoutError:
            await self._stopped()
            why = self.last_error or "the broker did not answer"
            raise StartupError(
                "mqtt.url", f"{self.url}: no connection within {self.startup_s:g} s (mqtt.startup_s): {why}"
            ) from None
        except BaseException:
            await self._stopped()
            raise
        return self

    async def _first_connection(self) -> None:
        """Wait until the connection is up; StartupError if the transport failed first."""
        assert self._failed is not None
        connected = asyncio.ensure_future(self._connected.wait())
        waited: list[asyncio.Future[Any]] = [connected, self._failed]
        try:
            await asyncio.wait(waited, return_when=asyncio.FIRST_COMPLETED)
        finally:
            connected.cancel()
        if self._failed.done():
            self._failed.result()  # raises why

    async def __aexit__(
        self, kind: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        """Drain the outbox (at most ``drain_s`` seconds), publish "offline", disconnect; a
        transport that failed (another daemon has the instance now) publishes nothing."""
        deadline = time.monotonic() + self.drain_s
        if not self.failed:
            while self._outbox and self._connected.is_set() and time.monotonic() < deadline:
                await asyncio.sleep(0.01)
            connection = self._connection
            if self._offline is not None and connection is not None and self._connected.is_set():
                with contextlib.suppress(MqttLost, TimeoutError):
                    await asyncio.wait_for(
                        connection.publish(self._offline), max(0.1, deadline - time.monotonic())
                    )
        await self._stopped()

    async def _stopped(self) -> None:
        """The connection and the guard's ended (cleanly: leaving a connection disconnects it, so
        the broker publishes no will)."""
        tasks = [t for t in self._tasks() if t is not None]
        for task in tasks:
            task.cancel()
        for task in tasks:
            with contextlib.suppress(asyncio.CancelledError):
                await task
        self._runner = None
        self._guard = None

    def _tasks(self) -> tuple[asyncio.Task[None] | None, asyncio.Task[None] | None]:
        """The connection's task and the guard's."""
        return self._runner, None if self._guard is None else self._guard.runner

    @property
    def failure(self) -> asyncio.Future[None]:
        """Done, with the StartupError that says why, when this transport must not go on (from
        entering it)."""
        assert self._failed is not None
        return self._failed

    @property
    def failed(self) -> bool:
        """Whether this transport must not go on (:meth:`fatal` says why)."""
        return self._failed is not None and self._failed.done()

    def give_up(self, error: StartupError) -> None:
        """Stop for good because of ``error``: no more connecting, and leaving publishes nothing."""
        if self._failed is None or self._failed.done():
            return
        self._failed.set_exception(error)
        current = asyncio.current_task()
        for task in self._tasks():
            if task is not None and task is not current:
                task.cancel()  # leaving its connection disconnects it cleanly: no will

    async def fatal(self) -> None:
        """Wait while the transport may go on; raise the StartupError that says why it must not
        (another daemon of the instance or the client id was there first: :class:`_Presence`).
        The daemon runs this beside its other tasks, and stops with status 2 when it raises."""
        assert self._failed is not None
        await asyncio.shield(self._failed)  # cancelling the wait must not cancel the future

    async def _run(self, context: ssl.SSLContext | None) -> None:
        delay = self.settings.reconnect_min_s
        while not self.failed:
            # publishing, the will and "online" on paho's connection; the subscriptions, if any,
            # on a reader's (:class:`_Reader`), whose session is the one the broker keeps
            reader = self.reader_to(context, timeout_s=TIMEOUT_S) if self.subscriptions else None
            connection = self.connection_to(
                context,
                client_id=self.client_id,
                clean_session=self.clean_session or reader is not None,
                will=self._offline,
                deliver=self._deliver,
                timeout_s=TIMEOUT_S,
            )
            began: float | None = None
            refused = False
            try:
                async with contextlib.AsyncExitStack() as stack:
                    await stack.enter_async_context(connection)
                    subscriber = connection if reader is None else await stack.enter_async_context(reader)
                    began = time.monotonic()
                    self._connection = connection
                    self.connects += 1
                    if self._online is not None:
                        await self._settled(connection, connection.publish(self._online))
                    for topic, qos in self.subscriptions:
                        await subscriber.subscribe(topic, qos)
                    self._problem = None
                    self._connected.set()
                    LOG.info(
                        "mqtt connected", extra={"fields": {"broker": self.url, "connects": self.connects}}
                    )
                    async with asyncio.TaskGroup() as tasks:
                        tasks.create_task(connection.serve(), name="mqtt connection")
                        if reader is not None:
                            tasks.create_task(reader.serve(), name="mqtt reader")
                        tasks.create_task(self._sender(connection), name="mqtt sender")
                        tasks.create_task(self._asker(subscriber), name="mqtt skeleton requests")
            except* MqttLost as group:
                lost = group.exceptions[0]
                assert isinstance(lost, MqttLost)
                self.last_error = str(lost)
                refused = lost.refused and self.connects == 0 and self.startup_s is not None
                self._problem = f"mqtt: {lost} (reconnecting)"
                if not refused:
                    LOG.warning("mqtt lost", extra={"fields": {"broker": self.url, "error": str(lost)}})
            finally:
                self._connected.clear()
                self._connection = None
            if refused:  # at start: trying again will not do
                self.give_up(StartupError("mqtt.url", f"{self.url}: {self.last_error}"))
                return
            if began is not None and time.monotonic() - began >= STEADY_S:
                delay = self.settings.reconnect_min_s
            wait = delay
            if began is not None and self._guard is not None and self._guard.contested():
                # the client id may have been taken by another daemon: its answer comes before
                # this one would take the client id back
                wait = max(delay, PROBE_S)
            if self._failed is not None:
                await asyncio.wait([self._failed], timeout=wait)
            delay = min(2 * delay, self.settings.reconnect_max_s)

    @staticmethod
    async def _settled(connection: _Connection, done: asyncio.Future[None]) -> None:
        try:
            async with asyncio.timeout(connection.timeout_s):
                await done
        except TimeoutError:
            raise MqttLost("the broker did not acknowledge") from None

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

    async def _asker(self, connection: _Connection | _Reader) -> None:
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


@dataclass(frozen=True)
class Claim:
    """What a daemon's guard says of it on ``mocapd/<instance>/ping`` and ``.../pong``: its
    instance, its client id, its ``rank`` (when it started, in microseconds since the epoch, 17
    digits, then a random part: the lower started first) and whether it is ``live`` (it asked, and
    kept the instance)."""

    instance: str
    client_id: str
    rank: str
    live: bool

    def beats(self, other: Claim) -> bool:
        """Whether this daemon keeps the instance and client id against ``other``: a live one
        against one still starting, else the one that started first (by its own clock; the random
        part breaks ties). Every daemon decides alike from the same two claims."""
        if self.live != other.live:
            return self.live
        return self.rank < other.rank

    def message(self, kind: str, to: str | None = None) -> bytes:
        """A ``ping`` (``to`` None) or a ``pong`` answering the daemon of rank ``to``: msgpack."""
        body: dict[str, object] = {
            "v": 1,
            "type": kind,
            "instance": self.instance,
            "client_id": self.client_id,
            "rank": self.rank,
            "live": self.live,
        }
        if to is not None:
            body["to"] = to
        out: bytes = msgpack.packb(body)
        return out


MAX_CLAIM_BYTES = 1024
"""A ping or pong longer than this is not a mocapd's (and not unpacked)."""


def read_claim(payload: bytes, kind: str) -> tuple[Claim, str | None] | None:
    """The claim of a ``ping`` or ``pong`` (``kind``) and whom a pong answers; None for anything
    else (an older mocapd's ping is random bytes, which it wants echoed)."""
    if len(payload) > MAX_CLAIM_BYTES:
        return None
    try:
        body = msgpack.unpackb(payload)
    except Exception:  # any bytes may come: what is not msgpack is not a claim
        return None
    if not isinstance(body, dict) or body.get("v") != 1 or body.get("type") != kind:
        return None
    words = [body.get(k) for k in ("instance", "client_id", "rank")]
    to = body.get("to")
    live = body.get("live")
    if not all(isinstance(w, str) for w in words) or not isinstance(live, bool):
        return None
    if (kind == "pong") != isinstance(to, str):
        return None
    instance, client_id, rank = (str(w) for w in words)
    return Claim(instance, client_id, rank, live), to if isinstance(to, str) else None


class _Presence:
    """One daemon per instance and per client id on a broker. Two daemons with one client id take
    it from each other for ever (the broker gives it to the newest connection, the other reconnects
    at once), and two of one instance overwrite each other's retained status.

    The guard has a connection of its own (client id ``<client id>-presence-<random>``, a clean
    session) for the daemon's whole life, subscribed to every instance's ``mocapd/+/ping`` and its
    own ``mocapd/<instance>/pong`` (QoS 1 both ways). Starting, it asks: it publishes a ``ping``
    with its :class:`Claim`, and if nothing that :meth:`Claim.beats` it answers within
    :data:`PROBE_S`, it is live and the daemon takes its client id. Every guard answers every ping
    of a daemon that shares its instance or client id with a ``pong`` of its own claim, and gives
    way when either says a claim that beats its own: a starting daemon to a live one, two starting
    at once to the one that started first, and two live ones (a host cut off from the broker, a
    process stopped, while another started) likewise. Since each was subscribed before it asked,
    of two daemons asking at once each hears the other's ping or its answer: both decide, and
    alike. A live guard asks again whenever its connection comes back and whenever the broker
    closes the daemon's main connection, which is what a client id taken over looks like.

    A live daemon gives way only within :data:`CONTESTED_S` of losing its main connection (a
    daemon that took its client id answers its question in that time): a claim heard at any other
    time is logged and ignored, since anyone who may publish on ``mocapd/#`` could send one.

    Giving way before it is live, a daemon is refused at start; after, it stops: either way with
    :class:`StartupError` (``service.instance``, or ``mqtt.client_id`` for another instance's
    daemon on the same client id), having published nothing more (the status topic is the other's
    now). An older mocapd answers a ping by echoing it: an echo is a live daemon's answer, and a
    ping that is not a claim is echoed for it."""

    def __init__(self, transport: MqttTransport, context: ssl.SSLContext | None, instance: str) -> None:
        self.transport = transport
        self.context = context
        token = uuid.uuid4().hex[:16]
        self.me = Claim(instance, transport.client_id, f"{time.time_ns() // 1000:017d}-{token}", False)
        self.client_id = f"{transport.client_id}-presence-{token[:8]}"
        self.ping_topic = f"mocapd/{instance}/ping"
        self.pong_topic = f"mocapd/{instance}/pong"
        self.runner: asyncio.Task[None] | None = None
        self._connection: _Connection | None = None
        self._live: asyncio.Future[None] | None = None
        self._asked: set[bytes] = set()  # the pings sent: an older mocapd answers with the same bytes
        self._lost_at = -math.inf  # when the main connection was last lost (monotonic)
        self._ignored_at = -math.inf  # when a claim was last logged as ignored

    async def claim(self) -> None:
        """Connect and ask; return once nothing beat this daemon's claim for :data:`PROBE_S` (it is
        live from then on, and the guard stays connected); StartupError if something did, or the
        broker refused the connection. The caller bounds how long it waits for a broker."""
        failed = self.transport.failure
        self._live = asyncio.get_running_loop().create_future()
        self.runner = asyncio.create_task(self._run(), name="mqtt presence")
        await asyncio.wait([self._live, failed], return_when=asyncio.FIRST_COMPLETED)
        if failed.done():
            failed.result()  # raises why

    def contested(self) -> bool:
        """The daemon's main connection was lost (its client id may have been taken by another
        daemon): ask again, and for :data:`CONTESTED_S` give way to a claim that beats this one's.
        False if the guard is not connected."""
        self._lost_at = time.monotonic()
        return self.ask()

    def _may_give_way(self) -> bool:
        """Whether a claim that beats this daemon's may stop it now (see the class docstring)."""
        if not self.me.live or time.monotonic() - self._lost_at <= CONTESTED_S:
            return True
        if time.monotonic() - self._ignored_at >= CONTESTED_S:
            self._ignored_at = time.monotonic()
            LOG.warning(
                "claim ignored",
                extra={
                    "fields": {
                        "field": "service.instance",
                        "reason": "a claim to this daemon's instance or client id while its connection "
                        "was not contested (publishing on mocapd/# should be for daemons only)",
                    }
                },
            )
        return False

    def ask(self) -> bool:
        """Ask again whether another daemon is there (this one's client id may have been taken); False
        if the guard is not connected."""
        connection = self._connection
        if connection is None:
            return False
        ping = self.me.message("ping")
        self._asked.add(ping)
        connection.publish(Outgoing(self.ping_topic, ping, reliable=True)).add_done_callback(_retrieved)
        return True

    async def _run(self) -> None:
        t = self.transport
        delay = t.settings.reconnect_min_s
        while not t.failed:
            connection = t.connection_to(
                self.context,
                client_id=self.client_id,
                clean_session=True,
                will=None,
                deliver=self._heard,
                timeout_s=TIMEOUT_S,
            )
            began: float | None = None
            try:
                async with connection:
                    began = time.monotonic()
                    await connection.subscribe(PINGS, 1)
                    await connection.subscribe(self.pong_topic, 1)
                    self._connection = connection
                    self.ask()
                    if not self.me.live:
                        await asyncio.wait([connection.lost], timeout=PROBE_S)
                        if not connection.lost.done() and not t.failed:
                            self.me = replace(self.me, live=True)
                            assert self._live is not None
                            self._live.set_result(None)
                    await connection.serve()
            except MqttLost as lost:
                t.last_error = str(lost)
                if lost.refused and not self.me.live and t.startup_s is not None:
                    t.give_up(StartupError("mqtt.url", f"{t.url}: {lost}"))
                    return
                if self.me.live:
                    LOG.warning("mqtt presence lost", extra={"fields": {"broker": t.url, "error": str(lost)}})
            finally:
                self._connection = None
            if began is not None and time.monotonic() - began >= STEADY_S:
                delay = t.settings.reconnect_min_s
            await asyncio.sleep(delay)
            delay = min(2 * delay, t.settings.reconnect_max_s)

    def _heard(self, topic: str, payload: bytes) -> None:
        """A ping (of any instance) or a pong (to this instance's daemons)."""
        connection = self._connection
        if self.transport.failed or connection is None:
            return  # a daemon that gave way answers nobody
        if topic == self.pong_topic:
            if payload in self._asked:  # an older mocapd, live, echoed the question
                if self._may_give_way():
                    self._give_way(None)
                return
            said = read_claim(payload, "pong")
            if said is not None and said[1] == self.me.rank and self._shares(said[0]):
                rival = said[0]
                self._meet(rival)
                if self.me.live and not rival.live and not self.transport.failed:
                    self.ask()  # it asked before this one was live: it must hear that it is now
            return
        said = read_claim(payload, "ping")
        if said is None:
            if topic == self.ping_topic:  # an older mocapd starting: it wants its bytes back
                connection.publish(Outgoing(self.pong_topic, payload)).add_done_callback(_retrieved)
            return
        rival = said[0]
        asker = topic.split("/")[1]  # the topic level its subscription matched: a valid one
        if rival.rank == self.me.rank or rival.instance != asker or not self._shares(rival):
            return
        answer = Outgoing(f"mocapd/{asker}/pong", self.me.message("pong", rival.rank), reliable=True)
        connection.publish(answer).add_done_callback(_retrieved)
        self._meet(rival)

    def _shares(self, rival: Claim) -> bool:
        return rival.instance == self.me.instance or rival.client_id == self.me.client_id

    def _meet(self, rival: Claim) -> None:
        if rival.beats(self.me) and self._may_give_way():
            self._give_way(rival)

    def _give_way(self, rival: Claim | None) -> None:
        """Another daemon has the instance or the client id: this one stops
        (:meth:`MqttTransport.give_up`)."""
        me, url = self.me, self.transport.url
        advice = "give each daemon an instance of its own"
        if rival is not None and rival.instance != me.instance:
            setting = "mqtt.client_id"
            why = (
                f"{me.client_id!r} is the client id of a daemon of instance {rival.instance!r} on {url} "
                "already; give each daemon a client id of its own"
            )
        elif rival is None or (rival.live and not me.live):
            setting = "service.instance"
            why = (
                f"{me.instance!r} is served by a live daemon on {url} already (client id "
                f"{me.client_id}); {advice}"
            )
        elif not rival.live:
            setting = "service.instance"
            why = (
                f"{me.instance!r} is claimed by another daemon starting on {url} at the same time, which "
                f"started first (client id {me.client_id}); {advice}"
            )
        else:
            setting = "service.instance"
            why = (
                f"{me.instance!r} is served by another live daemon on {url}, which started before this "
                f"one (client id {me.client_id}); this one stops; {advice}"
            )
        LOG.error(
            "gave way", extra={"fields": {"field": setting, "reason": why, "rival": rival and rival.rank}}
        )
        self.transport.give_up(StartupError(setting, why))


def _retrieved(future: asyncio.Future[None]) -> None:
    """A done callback for a future nobody awaits: its failure is taken, not reported as lost."""
    if not future.cancelled():
        future.exception()


def transport(settings: MqttConfig, *, instance: str, source: bool, sink: bool) -> MqttTransport:
    """The daemon's MQTT transport (:class:`protocols.transport.Factory`): as ``mocapd-<instance>``
    unless ``settings.client_id`` says otherwise, subscribed to :data:`SUBSCRIPTIONS` if it is a
    source, making sure it is the only daemon of ``instance`` and of its client id, and connected
    within ``settings.startup_s`` of its start."""
    return MqttTransport(
        settings,
        client_id=settings.client_id or f"mocapd-{instance}",
        subscribe=SUBSCRIPTIONS if source else (),
        presence=instance,
        startup_s=settings.startup_s,
    )
