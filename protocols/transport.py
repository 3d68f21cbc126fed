"""The one small interface every transport implements, and the registry config names them from.

A :class:`Transport` owns its connections (``async with transport:``); its :meth:`Transport.source`
yields :class:`Incoming` messages (a ``Source``) and its :meth:`Transport.sink` publishes
:class:`Outgoing` ones (a ``Sink``); either may be absent (stdout has no source). Publishing never
blocks the caller for long: a transport that cannot send drops (ZeroMQ at its high-water mark) or
queues (MQTT, bounded) and says so in :meth:`Transport.dropped`. :attr:`Transport.problem` is None
while the transport is connected and serving, else why not (``/healthz`` reports it).

The implementations are in :mod:`protocols.zeromq`, :mod:`protocols.mqtt` and :mod:`protocols.stdout`;
each is the only code that touches its sockets, and makes its transport of its configuration section
with a module-level ``transport`` function (a :class:`Factory`). The configuration names the module
of each section (``daemon.config.Config``); :func:`make` imports it only when the transport is used,
so an unused transport's library is not.
"""

from __future__ import annotations

import importlib
import time
from collections.abc import AsyncIterator
from dataclasses import dataclass
from types import TracebackType
from typing import Any, Protocol

from daemon.errors import MocapdError


class Throttle:
    """A log line that may go out at most once every ``every_s`` seconds: :meth:`due` says whether
    one may now (the first always may) and how many were held back since the last."""

    def __init__(self, every_s: float = 10.0) -> None:
        self.every_s = every_s
        self._last = 0.0
        self._quiet = 0

    def due(self) -> int | None:
        """None: not now (counted as held back); else the lines held back since the last."""
        now = time.monotonic()
        if self._last and now - self._last < self.every_s:
            self._quiet += 1
            return None
        self._last, quiet, self._quiet = now, self._quiet, 0
        return quiet


class StartupError(MocapdError):
    """A transport cannot start because of its settings or its surroundings (an address in use, an
    endpoint it cannot parse, a key file it cannot read): ``setting`` (also ``field``) names the
    configuration field (e.g. ``zmq.poses``), ``reason`` says what is wrong; ``str``: ``setting:
    reason``. Raised by entering a transport, before anything is published."""

    def __init__(self, setting: str, reason: str) -> None:
        super().__init__(reason, field=setting)
        self.setting = setting


STATE_TOPIC = "cluster:state/"
"""Cluster mode: the topic, with the stream's id after it, of a stream's state from the checkpoint a
taken partition was read from, which the service resumes the stream from before its next message.
No publisher can send it: the cluster transport gives a buffer's messages ``mocap/`` or ``nats:``
topics."""


@dataclass(frozen=True)
class Incoming:
    """A message received on ``topic`` at ``received`` (``time.time()``)."""

    topic: str
    payload: bytes
    received: float


@dataclass(frozen=True)
class Outgoing:
    """A message to publish: ``retain`` (MQTT: the broker keeps the last one for late subscribers)
    and ``reliable`` (MQTT: QoS 1, kept until the broker acknowledges it, resent after a
    reconnect); ``key``: the message's id (a detection's or boundary's), on which a transport that
    can de-duplicates (cluster: a key already published by any worker is not published again);
    ``relay``: a message only a transport with neither a broker nor retained messages publishes
    (ZeroMQ; over MQTT and NATS clients have both): a publisher's skeleton or pose passed on for
    viewers (``zmq.relay_per_s``); ``reminder``: the daemon's status said again (every
    :data:`~protocols.messages.STATUS_REMINDER_S`), for subscribers that joined since and for those
    that judge by it that the daemon still lives (``mocapd view``): ZeroMQ and MQTT publish it,
    stdout does not print it, and NATS does not send it (cluster mode's liveness is etcd's)."""

    topic: str
    payload: bytes
    retain: bool = False
    reliable: bool = False
    key: str | None = None
    relay: bool = False
    reminder: bool = False


class Source(Protocol):
    def __aiter__(self) -> AsyncIterator[Incoming]: ...


class Sink(Protocol):
    async def publish(self, message: Outgoing) -> None: ...


class Transport(Protocol):
    """A connection owner: enter it to connect (or bind), leave it to close with linger."""

    name: str

    def announce(self, online: Outgoing, offline: Outgoing) -> None:
        """Publish ``online`` when connected (every time, for a transport that reconnects) and
        ``offline`` when closing (and, where the transport has one, as its last will)."""

    async def __aenter__(self) -> Transport: ...

    async def __aexit__(
        self, kind: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None: ...

    def source(self) -> Source | None: ...

    def sink(self) -> Sink | None: ...

    def ask_skeleton(self, stream: str) -> None:
        """Poses came for ``stream``, whose skeleton is unknown: have it sent again where the
        transport can (MQTT: subscribe to its retained skeleton again); elsewhere nothing."""

    def drain_within(self, seconds: float) -> None:
        """Leaving (``__aexit__``) may take at most ``seconds`` to deliver what is queued (MQTT: the
        outbox and "offline"; ZeroMQ: the linger)."""

    @property
    def problem(self) -> str | None: ...

    @property
    def pending(self) -> int:
        """Messages published but not yet delivered (MQTT: the outbox); 0 for a transport that
        holds none."""

    def dropped(self) -> dict[str, int]: ...


class Factory(Protocol):
    """A transport module's ``transport`` function: the transport of its configuration section
    (``settings``) for the daemon ``instance``, taking poses in if ``source`` and publishing if
    ``sink``."""

    def __call__(self, settings: Any, *, instance: str, source: bool, sink: bool) -> Transport: ...


def make(module: str, settings: Any, *, instance: str, source: bool, sink: bool) -> Transport:
    """The transport that ``module`` (e.g. ``protocols.mqtt``) makes of ``settings``."""
    factory: Factory = importlib.import_module(module).transport
    return factory(settings, instance=instance, source=source, sink=sink)
