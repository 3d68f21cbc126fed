"""A cluster worker's reading of its partitions' deliveries (``protocols/nats.py``): a NATS client
connection of its own that speaks the part of the client protocol a push consumer needs (CONNECT,
SUB and UNSUB; MSG and HMSG in; PING and PONG both ways; PUB for flow control; INFO, +OK and -ERR),
so that every byte the server passes on from a publisher is parsed here.

Why not a nats-py subscription: nats-py decodes each delivered message's subject and reply as UTF-8
and reads the status line of its header block before it hands the message over, and an exception
there ends its read loop for good (it logs "nats: encountered error"; the connection stays up and
reads nothing more, for every subscription on it). A publisher decides those bytes: one message on
``mocap.<bytes that are not UTF-8>.pose``, or with a header block whose status line is not UTF-8, or
that is ``NATS/1.0`` alone, is mapped into a partition, stored in its buffer like any other, and
made the worker owning the partition deaf while it kept its lease, and after it every worker that
took the partition over (found by ``bench/fuzz.py --transport nats``;
``tests/test_fuzz_regressions.py``). Here a delivery is bytes in a :class:`Delivery` and the
transport decides, one message at a time, what it is; an exception one message sets off in its
handler is counted (:attr:`Reader.failures`) and costs that message only.

After a lost connection the reader connects again by itself and subscribes every subject again
(the server's push consumers go on delivering once there is interest in their subjects again).
"""

from __future__ import annotations

import asyncio
import collections
import contextlib
import json
import logging
from collections.abc import Awaitable, Callable, Sequence
from dataclasses import dataclass
from types import TracebackType
from urllib.parse import unquote, urlsplit

from protocols.endpoints import each_in_turn
from protocols.transport import Throttle

log = logging.getLogger("mocapd.cluster")

LINE_LIMIT = 1 << 16
"""The longest protocol line taken (the server's ``max_control_line`` is 4 KiB by default)."""
RECONNECT_MIN_S = 0.25
RECONNECT_MAX_S = 2.0
CONNECT_S = 2.0
"""How long a connection attempt (TCP, INFO, CONNECT, the first PONG) may take."""
YIELD_EVERY = 64
"""Lines read before the reader lets the other tasks run: a stream reader returns what it has
buffered without suspending, so a busy connection would otherwise hold the loop (and with it the
lease's keep-alives: a worker whose loop stalls for two thirds of its lease fences itself)."""


class ProtocolError(Exception):
    """The server said something this reader does not understand, or refused it (-ERR)."""


@dataclass(frozen=True, slots=True)
class Delivery:
    """One message as the server delivered it: its subject and reply subject as bytes (the reply
    empty when there is none), its header block (None: none) and its payload."""

    subject: bytes
    reply: bytes
    headers: bytes | None
    data: bytes

    def status(self) -> bytes | None:
        """The status code of the header block's first line (``NATS/1.0 100 Idle Heartbeat``:
        ``b"100"``), None if it has none."""
        if self.headers is None:
            return None
        first = self.headers.split(b"\r\n", 1)[0].split()
        if len(first) >= 2 and first[0] == b"NATS/1.0" and len(first[1]) == 3 and first[1].isdigit():
            return first[1]
        return None

    def header(self, name: bytes) -> bytes | None:
        """The value of header ``name`` (the first, exact name), None if there is none."""
        if self.headers is None:
            return None
        for line in self.headers.split(b"\r\n")[1:]:
            key, sep, value = line.partition(b":")
            if sep and key.strip() == name:
                return value.strip()
        return None


Handler = Callable[[Delivery], Awaitable[None]]


class Reader:
    """Subscriptions on a NATS server of their own (module docstring), entered with
    :meth:`start`, left with :meth:`close`; ``url``: ``nats://[user:password@|token@]host:port``, or
    several servers of one NATS cluster: the first that answers, then, whenever the connection is
    lost, the next in turn (the subscriptions are made again there: the cluster routes a consumer's
    deliveries to whichever server its subscriber is on)."""

    def __init__(self, url: str | Sequence[str], name: str) -> None:
        self.servers: list[tuple[str, int, dict[str, str]]] = []
        for one in [url] if isinstance(url, str) else url:
            parts = urlsplit(one)
            auth: dict[str, str] = {}
            if parts.username and parts.password is not None:
                auth = {"user": unquote(parts.username), "pass": unquote(parts.password)}
            elif parts.username:
                auth = {"auth_token": unquote(parts.username)}
            self.servers.append((parts.hostname or "127.0.0.1", parts.port or 4222, auth))
        self._at = 0  # the server connected to, or tried next
        self.name = name
        self._subs: dict[int, tuple[bytes, Handler]] = {}
        self._sid = 0
        self._writer: asyncio.StreamWriter | None = None
        self._pongs: collections.deque[asyncio.Future[None]] = collections.deque()
        self._task: asyncio.Task[None] | None = None
        self.problem: str | None = "not connected"
        """Why the reader is not connected now, None while it is."""
        self.failures = 0
        """Deliveries whose handler raised (each cost that message only)."""
        self.reconnects = 0
        self._failure_log = Throttle()

    async def start(self, timeout: float = CONNECT_S) -> Reader:
        """Connect (OSError, TimeoutError or :class:`ProtocolError` if the server cannot be reached
        or refuses), then read until :meth:`close`."""
        first = self._at

        async def attempt(k: int, _: object) -> tuple[asyncio.StreamReader, asyncio.StreamWriter]:
            self._at = (first + k) % len(self.servers)
            return await self._open()

        reader, writer = await each_in_turn(self.servers, attempt, timeout, (OSError, ProtocolError))
        self._task = asyncio.create_task(self._run(reader, writer), name="cluster deliveries")
        return self

    async def __aenter__(self) -> Reader:
        return self

    async def __aexit__(
        self, kind: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        await self.close()

    async def close(self) -> None:
        task, self._task = self._task, None
        if task is not None:
            task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await task
        self._disconnected("closed")

    # --------------------------------------------------------------------------- subscriptions

    async def subscribe(self, subject: str, handler: Handler, timeout: float = CONNECT_S) -> int:
        """Deliver every message on ``subject`` to ``handler`` (awaited in turn, on the read loop:
        a handler that waits holds the rest back); once this returns, the server has the
        subscription. The subscription's id."""
        sid = self.register(subject, handler)
        await self.flush(timeout)
        return sid

    def register(self, subject: str, handler: Handler) -> int:
        """:meth:`subscribe` without waiting for the server (nor failing when not connected: the
        subscription is made on the next connection)."""
        self._sid += 1
        sid = self._sid
        self._subs[sid] = (subject.encode(), handler)
        if self._writer is not None:
            self._writer.write(b"SUB %s %d\r\n" % (subject.encode(), sid))
        return sid

    async def unsubscribe(self, sid: int) -> None:
        if self._subs.pop(sid, None) is not None and self._writer is not None:
            self._writer.write(b"UNSUB %d\r\n" % sid)
            with contextlib.suppress(OSError):
                await self._writer.drain()

    def publish(self, subject: bytes, payload: bytes = b"") -> None:
        """Publish ``payload`` on ``subject`` (flow control answers; nothing if not connected)."""
        if self._writer is not None:
            self._writer.write(b"PUB %s %d\r\n%s\r\n" % (subject, len(payload), payload))

    async def flush(self, timeout: float = CONNECT_S) -> None:
        """Return once the server has read everything written so far (a PING answered);
        ConnectionError if not connected, TimeoutError after ``timeout``."""
        writer = self._writer
        if writer is None:
            host, port, _ = self.servers[self._at]
            raise ConnectionError(f"not connected to NATS at {host}:{port}")
        pong: asyncio.Future[None] = asyncio.get_running_loop().create_future()
        self._pongs.append(pong)
        writer.write(b"PING\r\n")
        async with asyncio.timeout(timeout):
            await writer.drain()
            await pong

    # ------------------------------------------------------------------------------ connection

    async def _open(self) -> tuple[asyncio.StreamReader, asyncio.StreamWriter]:
        host, port, auth = self.servers[self._at]
        reader, writer = await asyncio.open_connection(host, port, limit=LINE_LIMIT)
        try:
            line = await reader.readuntil(b"\r\n")
            if not line.startswith(b"INFO "):
                raise ProtocolError(f"the server did not introduce itself: {line[:60]!r}")
            if json.loads(line[5:]).get("tls_required"):
                raise ProtocolError("the server requires TLS, which cluster.nats (nats://) does not speak")
            connect = {
                "verbose": False,
                "pedantic": False,
                "tls_required": False,
                "name": self.name,
                "lang": "python",
                "version": "mocapd",
                "protocol": 1,
                "headers": True,
                "no_responders": True,
                **auth,
            }
            writer.write(b"CONNECT %s\r\n" % json.dumps(connect).encode())
            for sid, (subject, _) in self._subs.items():
                writer.write(b"SUB %s %d\r\n" % (subject, sid))
            writer.write(b"PING\r\n")
            await writer.drain()
            while True:
                line = await reader.readuntil(b"\r\n")
                if line.startswith(b"PONG"):
                    break
                if line.startswith(b"-ERR"):
                    raise ProtocolError(line[4:-2].strip().decode("utf-8", "replace"))
                if line.startswith(b"PING"):
                    writer.write(b"PONG\r\n")
        except BaseException:
            writer.close()
            raise
        self._writer = writer
        self.problem = None
        return reader, writer

    def _disconnected(self, why: str) -> None:
        writer, self._writer = self._writer, None
        if writer is not None:
            writer.close()
        self.problem = why
        while self._pongs:
            pong = self._pongs.popleft()
            if not pong.done():
                pong.set_exception(ConnectionError(why))

    async def _run(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        """Read; after a lost connection, connect again (back-off from 0.25 s doubling to 2 s)."""
        while True:
            try:
                await self._read(reader, writer)
                why = "closed by the server"
            except (OSError, EOFError, ValueError, ProtocolError, asyncio.LimitOverrunError) as e:
                why = f"{type(e).__name__}: {e}"[:200]
            self._disconnected(why)
            log.warning("deliveries disconnected", extra={"fields": {"reader": self.name, "error": why}})
            backoff = RECONNECT_MIN_S
            while True:
                await asyncio.sleep(backoff)
                try:
                    async with asyncio.timeout(CONNECT_S):
                        reader, writer = await self._open()
                    break
                except (OSError, EOFError, ValueError, ProtocolError, asyncio.LimitOverrunError) as e:
                    self.problem = f"{why}; reconnecting: {type(e).__name__}: {e}"[:300]
                    self._at = (self._at + 1) % len(self.servers)
                    if self._at == 0:  # every server tried once: wait longer
                        backoff = min(2 * backoff, RECONNECT_MAX_S)
            self.reconnects += 1
            log.info(
                "deliveries reconnected",
                extra={"fields": {"reader": self.name, "subscriptions": len(self._subs)}},
            )

    async def _read(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        """Until the connection ends: each message to its subscription's handler, PING answered,
        PONG to the oldest :meth:`flush` waiting. Lines are the server's; only subjects, replies,
        header blocks and payloads carry a publisher's bytes, and those are passed on as bytes."""
        readline, readexactly = reader.readuntil, reader.readexactly
        n = 0
        while True:
            n += 1
            if n % YIELD_EVERY == 0:  # data already buffered is read without a suspension
                await asyncio.sleep(0)
            line = await readline(b"\r\n")
            if line.startswith(b"MSG "):
                args = line[4:].split()
                if len(args) not in (3, 4):
                    raise ProtocolError(f"a MSG line of {len(args)} arguments")
                size = int(args[-1])
                body = await readexactly(size + 2)
                reply = args[2] if len(args) == 4 else b""
                await self._deliver(int(args[1]), Delivery(args[0], reply, None, body[:size]))
            elif line.startswith(b"HMSG "):
                args = line[5:].split()  # no reply: two spaces, one token fewer
                if len(args) not in (4, 5):
                    raise ProtocolError(f"an HMSG line of {len(args)} arguments")
                head, size = int(args[-2]), int(args[-1])
                if not 0 <= head <= size:
                    raise ProtocolError(f"a header block of {head} bytes in a message of {size}")
                body = await readexactly(size + 2)
                reply = args[2] if len(args) == 5 else b""
                await self._deliver(int(args[1]), Delivery(args[0], reply, body[:head], body[head:size]))
            elif line.startswith(b"PING"):
                writer.write(b"PONG\r\n")
            elif line.startswith(b"PONG"):
                if self._pongs:
                    pong = self._pongs.popleft()
                    if not pong.done():
                        pong.set_result(None)
            elif line.startswith(b"-ERR"):
                error = line[4:-2].strip().decode("utf-8", "replace")
                log.warning("nats server error", extra={"fields": {"error": error[:200]}})
            elif not line.startswith((b"+OK", b"INFO ")):
                raise ProtocolError(f"not a protocol line: {line[:40]!r}")

    async def _deliver(self, sid: int, delivery: Delivery) -> None:
        entry = self._subs.get(sid)
        if entry is None:  # unsubscribed since
            return
        try:
            await entry[1](delivery)
        except Exception as e:  # a defect of mocapd's: it costs this one message, never the reader
            self.failures += 1
            quiet = self._failure_log.due()
            if quiet is None:
                return
            log.warning(
                "delivery not handled",
                extra={"fields": {"error": f"{type(e).__name__}: {e}"[:200], "since_last": quiet}},
            )
