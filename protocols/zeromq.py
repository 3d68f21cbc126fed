"""ZeroMQ: poses in on a SUB socket, detections out on a PUB socket, each message a two-frame
multipart ``[topic, payload]`` (topics as MQTT's, DESIGN.md). Both sockets bind by default (the
daemon is the fixed point; producers and consumers connect); ``connect`` in the endpoint's place
makes one connect instead. Every socket gets its high-water mark before bind/connect and an explicit
linger; publishing never blocks (PUB drops at the high-water mark, as ZeroMQ does). With
``curve_secret_key_file`` (a key pair written by ``zmq.auth.create_certificates``) both sockets are
CURVE servers: traffic is encrypted, and with ``curve_clients_dir`` only the clients whose public
keys are in that directory may connect."""

from __future__ import annotations

import asyncio
import ctypes
import functools
import socket
import time
from collections.abc import AsyncIterator, Callable
from pathlib import Path
from types import TracebackType
from typing import TYPE_CHECKING, TypeVar, cast

import zmq
import zmq.asyncio
import zmq.auth
from zmq.auth.asyncio import AsyncioAuthenticator

from protocols._route import FUNCTIONS, Router
from protocols.transport import Incoming, Outgoing, StartupError
from protocols.urls import split_endpoint, tcp_address

if TYPE_CHECKING:
    from daemon.config import ZmqConfig

PREFIX = b"mocap/"
RESOLVE_S = 10.0
"""The longest start waits for a host to connect to to resolve."""


def open_socket(
    ctx: zmq.asyncio.Context,
    kind: int,
    endpoint: str,
    *,
    bind: bool,
    hwm: int,
    linger_ms: int,
    curve_server_secret: bytes | None = None,
    curve_server_public: bytes | None = None,
) -> zmq.asyncio.Socket:
    """A socket of ``kind`` with its high-water marks and linger set before it binds or connects
    ``endpoint``; a CURVE server when ``curve_server_secret`` is given."""
    sock = ctx.socket(kind)
    sock.setsockopt(zmq.SNDHWM, hwm)
    sock.setsockopt(zmq.RCVHWM, hwm)
    sock.setsockopt(zmq.LINGER, linger_ms)
    if curve_server_secret is not None:
        sock.setsockopt(zmq.CURVE_SECRETKEY, curve_server_secret)
        if curve_server_public is not None:
            sock.setsockopt(zmq.CURVE_PUBLICKEY, curve_server_public)
        sock.setsockopt(zmq.CURVE_SERVER, 1)
    try:
        if bind:
            sock.bind(endpoint)
        else:
            sock.connect(endpoint)
    except BaseException:
        sock.close(linger=0)  # an open socket would keep the context from terminating
        raise
    return sock


class ZmqTransport:
    """The daemon's ZeroMQ side, as ``settings`` say (``daemon.config.ZmqConfig``): the ``poses``
    (SUB) socket if ``source``, the ``detections`` (PUB) socket if ``sink``, ``hwm`` messages queued
    per socket, ``linger_ms`` at close, CURVE."""

    name = "zmq"

    def __init__(self, settings: ZmqConfig, *, source: bool, sink: bool) -> None:
        self.poses = settings.poses if source else None
        self.detections = settings.detections if sink else None
        self.hwm = settings.hwm
        self.linger_ms = settings.linger_ms
        self.curve_secret_key_file = settings.curve_secret_key_file
        self.curve_clients_dir = settings.curve_clients_dir
        self._ctx: zmq.asyncio.Context | None = None
        self._sub: zmq.asyncio.Socket | None = None
        self._pub: zmq.asyncio.Socket | None = None
        self._auth: AsyncioAuthenticator | None = None
        self._dropped = 0
        self._status: tuple[Outgoing, Outgoing] | None = None
        self._asked = 0

    def announce(self, online: Outgoing, offline: Outgoing) -> None:
        """Publish ``online`` once bound and ``offline`` before closing (on the PUB socket)."""
        self._status = (online, offline)

    async def __aenter__(self) -> ZmqTransport:
        self._ctx = zmq.asyncio.Context()
        secret = public = None
        if self.curve_secret_key_file is not None:
            try:
                public, secret = zmq.auth.load_certificate(self.curve_secret_key_file)
            except (OSError, ValueError) as e:
                self._ctx.term()
                self._ctx = None
                why = e.strerror if isinstance(e, OSError) and e.strerror else str(e)
                raise StartupError(
                    "zmq.curve_secret_key_file", f"{self.curve_secret_key_file}: {why}"
                ) from None
            if secret is None:
                self._ctx.term()
                self._ctx = None
                raise StartupError(
                    "zmq.curve_secret_key_file", f"{self.curve_secret_key_file}: not a secret key file"
                )
            auth = AsyncioAuthenticator(self._ctx)
            auth.start()
            clients = self.curve_clients_dir
            auth.configure_curve(domain="*", location=clients if clients else zmq.auth.CURVE_ALLOW_ANY)
            self._auth = auth

        def opened(kind: int, spec: str, setting: str) -> zmq.asyncio.Socket:
            assert self._ctx is not None
            endpoint, bind = split_endpoint(spec)
            try:
                return open_socket(
                    self._ctx,
                    kind,
                    endpoint,
                    bind=bind,
                    hwm=self.hwm,
                    linger_ms=self.linger_ms,
                    curve_server_secret=secret,
                    curve_server_public=public,
                )
            except zmq.ZMQError as e:
                why = zmq.strerror(e.errno).lower() if e.errno is not None else str(e)
                raise StartupError(setting, f"{spec}: {why}") from None

        try:
            for spec, setting in ((self.poses, "zmq.poses"), (self.detections, "zmq.detections")):
                if spec is not None:
                    await _resolvable(spec, setting)
            if self.poses is not None:
                self._sub = opened(zmq.SUB, self.poses, "zmq.poses")
                self._sub.setsockopt(zmq.SUBSCRIBE, PREFIX)
            if self.detections is not None:
                self._pub = opened(zmq.PUB, self.detections, "zmq.detections")
        except BaseException:
            await self.__aexit__(None, None, None)
            raise
        if self._pub is not None and self._status is not None:
            await self.publish(self._status[0])
        return self

    async def __aexit__(
        self, kind: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        if self._pub is not None and self._status is not None:
            await self.publish(self._status[1])
        for sock in (self._sub, self._pub):
            if sock is not None:
                sock.close(linger=self.linger_ms)
        self._sub = self._pub = None
        if self._auth is not None:
            self._auth.stop()
            self._auth = None
        if self._ctx is not None:
            self._ctx.term()
            self._ctx = None

    @property
    def endpoints(self) -> dict[str, str]:
        """The endpoint of each open socket by its setting: where a bound one listens (the port
        ZeroMQ chose for ``:0`` or ``:*``), what a connecting one connects to."""
        out = {}
        for setting, sock in (("zmq.poses", self._sub), ("zmq.detections", self._pub)):
            if sock is not None:
                out[setting] = cast(bytes, sock.getsockopt(zmq.LAST_ENDPOINT)).decode()
        return out

    def source(self) -> _Source | None:
        return None if self._sub is None else _Source(self._sub)

    def router(
        self, sinks: list[zmq.Socket[bytes]], choose: Callable[[bytes], int], cached: int
    ) -> Routed | None:
        """The poses socket's messages routed in C to the PUSH sockets ``sinks`` by ``choose`` (a
        topic's index in ``sinks``, remembered for at most ``cached`` topics), as
        :func:`protocols.routing.split` would: for ``mocapd run --workers``' front; None where the
        compiled router cannot call the libzmq pyzmq loaded."""
        functions = libzmq_functions()
        if self._sub is None or functions is None:
            return None
        return Routed(
            self._sub, Router(functions, self._sub.underlying, [s.underlying for s in sinks], choose, cached)
        )

    def raw_source(self) -> RawSource | None:
        """The poses socket's messages undecoded, a batch of multipart messages (lists of frames)
        per wakeup: for ``mocapd run --workers``' front, which routes them without looking inside."""
        return None if self._sub is None else RawSource(self._sub)

    def sink(self) -> ZmqTransport | None:
        return None if self._pub is None else self

    def ask_skeleton(self, stream: str) -> None:
        """Nothing: a ZeroMQ publisher re-announces when the daemon's subscription reaches it, and
        periodically (``protocols/README.md``, "A stream's life")."""

    def ask_skeletons(self) -> None:
        """Have every connected publisher announce its skeleton again, as when the daemon starts
        (``mocapd run --workers``: a restarted worker): a subscription the publishers' XPUB sockets
        have not seen, at once cancelled (a topic no stream has, so nothing else changes)."""
        if self._sub is None:
            return
        self._asked += 1
        token = b"%s#ask-%d" % (PREFIX, self._asked)
        self._sub.setsockopt(zmq.SUBSCRIBE, token)
        self._sub.setsockopt(zmq.UNSUBSCRIBE, token)

    def drain_within(self, seconds: float) -> None:
        """Linger at most ``seconds`` (and at most ``linger_ms``) at close."""
        self.linger_ms = min(self.linger_ms, max(0, round(seconds * 1000)))

    @property
    def pending(self) -> int:
        """0: what ZeroMQ queues is its own (and dropped at the high-water mark, counted)."""
        return 0

    async def publish(self, message: Outgoing) -> None:
        assert self._pub is not None
        try:
            self._pub.send_multipart([message.topic.encode(), message.payload], flags=zmq.NOBLOCK)
        except zmq.Again:
            self._dropped += 1

    @property
    def problem(self) -> str | None:
        return None if self._ctx is not None else "zmq: not started"

    def dropped(self) -> dict[str, int]:
        return {"zmq_send_full": self._dropped}


async def _resolvable(spec: str, setting: str) -> None:
    """StartupError naming ``setting`` if ``spec`` connects to a TCP host that does not resolve
    (within :data:`RESOLVE_S`): ZeroMQ connects in the background and would retry it for ever,
    silently."""
    endpoint, bind = split_endpoint(spec)
    address = tcp_address(endpoint)
    if bind or address is None:
        return
    host, port = address
    try:
        async with asyncio.timeout(RESOLVE_S):
            await asyncio.get_running_loop().getaddrinfo(host, port, type=socket.SOCK_STREAM)
    except socket.gaierror as e:
        raise StartupError(setting, f"{spec}: cannot resolve {host!r}: {e.strerror}") from None
    except TimeoutError:
        raise StartupError(setting, f"{spec}: {host!r} did not resolve within {RESOLVE_S:g} s") from None


class _Source:
    """The SUB socket's messages: an awaited poll when it is empty, then every message it holds
    received without waiting (on a synchronous shadow of the socket: an awaited receive per
    message costs more than the message)."""

    def __init__(self, sock: zmq.asyncio.Socket) -> None:
        self._sock = sock

    async def __aiter__(self) -> AsyncIterator[Incoming]:
        sync: zmq.Socket[bytes] = zmq.Socket.shadow(self._sock.underlying)
        while True:
            await self._sock.poll()  # readable (POLLIN)
            received = time.time()
            for _ in range(DRAIN_MESSAGES):
                parts = receive(sync)
                if parts is None:
                    break
                if len(parts) != 2:
                    yield Incoming("", b"", received)  # no topic: counted as undecodable by the service
                    continue
                yield Incoming(parts[0].decode("utf-8", "replace"), parts[1], received)


def receive(sync: zmq.Socket[bytes]) -> list[bytes] | None:
    """The next message's frames, None if none is waiting. Each frame received as a
    :class:`zmq.Frame`, whose ``more`` pyzmq reads in C as it receives it, then copied to bytes:
    ``getsockopt(RCVMORE)`` builds an option enum per call and cost three times the receive itself
    for a pose of a few hundred bytes (and ``recv_multipart`` asks it per frame)."""
    try:
        frame = sync.recv(NOBLOCK, copy=False)
    except zmq.Again:
        return None
    parts = [frame.bytes]
    while frame.more:
        frame = sync.recv(NOBLOCK, copy=False)
        parts.append(frame.bytes)
    return parts


T = TypeVar("T")


async def _drained(
    sock: zmq.asyncio.Socket, drain: Callable[[zmq.Socket[bytes]], T | None]
) -> AsyncIterator[T]:
    """What each ``drain`` of the socket's waiting messages gave (None: nothing was waiting), for as
    long as it is read. The socket's file descriptor is watched directly (an awaited poll costs
    more than a small message); it signals an edge, so the socket's events are checked before each
    wait."""
    sync: zmq.Socket[bytes] = zmq.Socket.shadow(sock.underlying)
    loop = asyncio.get_running_loop()
    readable = asyncio.Event()
    fd = sync.fileno()
    loop.add_reader(fd, readable.set)
    try:
        while True:
            got = drain(sync)
            if got is not None:
                yield got
                continue
            readable.clear()
            if not cast(int, sync.getsockopt(zmq.EVENTS)) & zmq.POLLIN:
                await readable.wait()
    finally:
        loop.remove_reader(fd)


class RawSource:
    """The SUB socket's messages as they came (lists of frames), in batches: what it holds when
    it becomes readable (at most :data:`DRAIN_MESSAGES` at a time)."""

    def __init__(self, sock: zmq.asyncio.Socket) -> None:
        self._sock = sock

    def __aiter__(self) -> AsyncIterator[list[list[bytes]]]:
        def batch(sync: zmq.Socket[bytes]) -> list[list[bytes]] | None:
            out = []
            for _ in range(DRAIN_MESSAGES):
                parts = receive(sync)
                if parts is None:
                    break
                out.append(parts)
            return out or None

        return _drained(self._sock, batch)


class Routed:
    """The poses socket's messages routed by :class:`protocols._route.Router` as they come: after
    each drain of what is waiting (at most :data:`DRAIN_MESSAGES`), per sink the messages its full
    queue did not take."""

    def __init__(self, sock: zmq.asyncio.Socket, router: Router) -> None:
        self._sock = sock
        self._router = router

    def __aiter__(self) -> AsyncIterator[list[int]]:
        def routed(sync: zmq.Socket[bytes]) -> list[int] | None:
            taken, full = self._router.drain(DRAIN_MESSAGES)
            return full if taken else None

        return _drained(self._sock, routed)


NOBLOCK = int(zmq.NOBLOCK)
"""As a plain int: a flag as an enum member costs more than a small message's receive."""
DRAIN_MESSAGES = 512
"""The most messages taken per wakeup, so that receiving yields to the other tasks."""


@functools.cache
def libzmq_functions() -> dict[str, int] | None:
    """The addresses of :data:`protocols._route.FUNCTIONS` in the libzmq pyzmq loaded, for the
    compiled router; None where it cannot be found for certain (then the front routes in Python):
    the one shared object named ``libzmq*`` mapped into this process (``/proc/self/maps``, Linux),
    of pyzmq's libzmq version. ``ctypes.CDLL`` of a loaded library's path is that library."""
    try:
        with open("/proc/self/maps", encoding="utf-8", errors="replace") as maps:
            paths = {line.split(None, 5)[-1].strip() for line in maps if "/libzmq" in line}
    except OSError:
        return None
    paths = {p for p in paths if Path(p).name.startswith("libzmq") and ".so" in Path(p).name}
    if len(paths) != 1:
        return None
    try:
        lib = ctypes.CDLL(paths.pop())
        major, minor, patch = ctypes.c_int(), ctypes.c_int(), ctypes.c_int()
        lib.zmq_version(ctypes.byref(major), ctypes.byref(minor), ctypes.byref(patch))
        if (major.value, minor.value, patch.value) != zmq.zmq_version_info():
            return None
        found = {name: ctypes.cast(getattr(lib, name), ctypes.c_void_p).value for name in FUNCTIONS}
    except (OSError, AttributeError):
        return None
    addresses = {name: address for name, address in found.items() if address}
    return addresses if len(addresses) == len(FUNCTIONS) else None


def transport(settings: ZmqConfig, *, instance: str, source: bool, sink: bool) -> ZmqTransport:
    """The daemon's ZeroMQ transport (:class:`protocols.transport.Factory`)."""
    return ZmqTransport(settings, source=source, sink=sink)


def curve_keys(directory: str | Path, name: str) -> tuple[Path, Path]:
    """A new CURVE key pair ``name.key`` (public) and ``name.key_secret`` in ``directory``."""
    public, secret = zmq.auth.create_certificates(str(directory), name)
    return Path(public), Path(secret)
