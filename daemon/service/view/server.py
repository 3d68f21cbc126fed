"""``mocapd view``'s server: the bus watched (:mod:`protocols.watch`), its messages kept in a
:class:`~daemon.service.view.state.ViewState`, and a web page (aiohttp) that shows them live.

Routes: ``/`` the page and ``/static/`` its script and style (shipped in the package, nothing
fetched from elsewhere); ``/ws`` one WebSocket per browser tab: a ``snapshot`` on connect, then the
updates as they come (``stream``, ``gone``, ``poses``, ``progress``, ``detection``, ``status``,
``refused``, ``stats``, ``bus``, ``health``; docs/view.md); ``/api/status`` a small JSON of the
clients connected, the streams and the bus. Each client has a writer task: its pending poses are
one per stream (a newer pose replaces one not yet sent: coalesced, counted), sent at most
:data:`POSE_BATCHES_PER_S` times a second in one ``poses`` message; its other updates queue up to
:data:`MAX_PENDING`, past which they are dropped and the client is sent a fresh snapshot instead,
so a slow client never grows the server's memory. A tab that closes ends its tasks and its state.

Callers (:class:`Gate`): ``/ws`` and ``/api/`` answer only a request whose ``Host`` names the
served address (on loopback: ``127.0.0.1``, ``localhost`` or ``[::1]`` with the port; beyond it any
name, since the token guards it) and whose ``Origin``, when it has one (a browser always sends it on
a WebSocket), is that same host (another site's page, or one reached by DNS rebinding, is refused
403); with a token (``--token``; served beyond loopback, one is made and logged with a warning if
none is given), only one that carries it (``?token=``, as the page passes on its own URL's, or
``Authorization: Bearer``; else 401). The page and its static files hold no data and are served to
anyone. No response names the server's software.

Tasks, named, under one :class:`asyncio.TaskGroup`: the bus, the clock (once a second: stats, idle
streams dropped, the bus state), the daemon's health (``--metrics``: ``/healthz`` and ``/metrics``
every second) and the shutdown, which on SIGTERM/SIGINT closes every WebSocket (at most
:data:`GRACE_S`) and stops the HTTP server.
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import hashlib
import hmac
import itertools
import json
import logging
import os
import secrets
import signal
import socket
import time
from collections import Counter, deque
from collections.abc import Awaitable, Callable, Sequence
from pathlib import Path
from typing import Any

import aiohttp
from aiohttp import web

from daemon.errors import UsageError
from daemon.service.view.settings import ViewSettings
from daemon.service.view.state import Event, ViewState, daemon_health
from protocols.transport import Incoming
from protocols.watch import Watch
from replay.rigs import BUILT_IN, RigMap

STATIC = Path(__file__).resolve().parent / "static"
MAX_PENDING = 512
"""Updates (poses aside) a client may have waiting; past it, a snapshot replaces them."""
POSE_BATCHES_PER_S = 60
SEND_BUFFER = 64 * 1024
"""A client socket's kernel send buffer: a slow client backs up into its coalesced poses soon, not
into megabytes of stale ones the kernel would hold (its default grows to 4 MiB)."""
GRACE_S = 2.0
POLL_S = 1.0
HEARTBEAT_S = 10.0
SECURITY = {
    "Content-Security-Policy": (
        "default-src 'none'; script-src 'self'; style-src 'self'; img-src 'self'; connect-src 'self'; "
        "base-uri 'none'; form-action 'none'; frame-ancestors 'none'"
    ),
    "X-Content-Type-Options": "nosniff",
    "Referrer-Policy": "no-referrer",
    "Cache-Control": "no-store",
}
"""On every response: the page may load only its own script and style and talk only to its server
(the page never puts bus text into HTML anyway)."""


LOOPBACK_NAMES = ("127.0.0.1", "localhost", "[::1]")


class Gate:
    """Who may call ``/ws`` and ``/api/`` of a view serving ``settings`` on ``port`` (the module
    docstring): :meth:`refusal` of a request's headers and token."""

    def __init__(self, settings: ViewSettings, port: int) -> None:
        self.token = settings.token
        self.hosts: frozenset[str] | None = None  # None: any Host (beyond loopback: the token guards)
        if settings.loopback:
            names = {*LOOPBACK_NAMES, settings.host.lower()}
            self.hosts = frozenset({f"{n}:{port}" for n in names} | (set(names) if port == 80 else set()))

    def refusal(self, host: str | None, origin: str | None, token: str | None) -> tuple[int, str] | None:
        """None if a request with these ``Host``, ``Origin`` and token may go on, else its status
        and why."""
        host = (host or "").lower()
        if not host or (self.hosts is not None and host not in self.hosts):
            return 403, "Host is not the served address"
        if origin is not None and origin.lower() not in (f"http://{host}", f"https://{host}"):
            return 403, "Origin is not the served address"
        if self.token is not None and not (
            token is not None and hmac.compare_digest(token.encode(), self.token.encode())
        ):
            return 401, "a token is needed (the page's URL ?token=...)"
        return None


class _Stop(Exception):
    """Raised by the shutdown task once the clients are closed: ends the task group."""


class Client:
    """One browser tab's WebSocket and what waits to be sent to it."""

    def __init__(self, ws: web.WebSocketResponse, number: int, peer: str) -> None:
        self.ws = ws
        self.number = number
        self.peer = peer
        self.events: deque[Event] = deque()
        self.poses: dict[str, Event] = {}
        self.resync = True  # the first thing sent is a snapshot
        self.wake = asyncio.Event()
        self.wake.set()
        self.coalesced = 0
        self.resyncs = 0
        self.sent = 0

    def push(self, event: Event) -> None:
        kind = event["type"]
        if kind == "pose":
            if self.poses.pop(event["stream"], None) is not None:
                self.coalesced += 1
            self.poses[event["stream"]] = event
        elif not self.resync:
            if len(self.events) >= MAX_PENDING:
                self.events.clear()
                self.resync = True
                self.resyncs += 1
            else:
                self.events.append(event)
            if kind == "gone":
                self.poses.pop(event["stream"], None)
        self.wake.set()

    def describe(self) -> dict[str, Any]:
        return {
            "number": self.number,
            "peer": self.peer,
            "pending_events": len(self.events),
            "pending_poses": len(self.poses),
            "coalesced": self.coalesced,
            "resyncs": self.resyncs,
            "sent": self.sent,
        }


class ViewServer:
    """The view of ``settings``: :meth:`run` until the stop event is set."""

    def __init__(
        self,
        settings: ViewSettings,
        *,
        version: str,
        logger: logging.Logger,
        rigs: Sequence[RigMap] = BUILT_IN,
    ) -> None:
        self.settings = settings
        self.version = version
        self.log = logger
        # the same view (this machine, this port) restarted resumes its broker session: the
        # detections published while it was away are queued for it
        where = f"{socket.gethostname()}:{settings.port}"
        keep = hashlib.sha256(where.encode()).hexdigest()[:12] if settings.port else None
        self.watch = Watch(settings.bus, keep=keep)
        self.state = ViewState(settings.poses_per_s, rigs=rigs, relayed=self.watch.kind == "zmq")
        self.clients: dict[int, Client] = {}
        self.gate: Gate | None = None
        self.callers_refused: Counter[str] = Counter()
        self._refusal_logged: dict[str, float] = {}
        self.health: Event | None = None
        self._numbers = itertools.count(1)
        self._bus_said: tuple[Any, ...] | None = None
        self.url = ""

    # ------------------------------------------------------------------------------ the bus

    def deliver(self, incoming: Incoming) -> None:
        for event in self.state.take(incoming, time.monotonic()):
            self.broadcast(event)

    def broadcast(self, event: Event) -> None:
        for client in self.clients.values():
            client.push(event)

    def bus(self) -> Event:
        w = self.watch
        return {
            "type": "bus",
            "url": w.url,
            "kind": w.kind,
            "connected": w.problem is None,
            "problem": w.problem,
            "received": w.received,
            "dropped": w.dropped,
            "refused": sum(self.state.refusals.values()),
        }

    def snapshot(self) -> Event:
        return self.state.snapshot() | {
            "bus": self.bus(),
            "health": self.health,
            "metrics": self.settings.metrics,
            "version": self.version,
        }

    def status(self) -> dict[str, Any]:
        """``/api/status``."""
        return {
            "version": self.version,
            "clients": len(self.clients),
            "client_details": [c.describe() for c in self.clients.values()],
            "streams": sorted(n for n, s in self.state.streams.items() if not s.ended),
            "ended": sorted(n for n, s in self.state.streams.items() if s.ended),
            "bus": self.bus(),
            "health": self.health,
            "refusals": dict(self.state.refusals),
            "callers_refused": dict(self.callers_refused),
            "poses_per_s": self.settings.poses_per_s,
        }

    async def _clock(self) -> None:
        while True:
            await asyncio.sleep(1.0)
            for event in self.state.tick(time.monotonic()):
                self.broadcast(event)
            bus = self.bus()
            said = (bus["connected"], bus["problem"])
            if said != self._bus_said:
                self._bus_said = said
                self.log.info("bus", extra={"fields": {"url": bus["url"], "problem": bus["problem"]}})
            self.broadcast(bus)

    async def _poll_health(self, base: str) -> None:
        timeout = aiohttp.ClientTimeout(total=2 * POLL_S)
        async with aiohttp.ClientSession(timeout=timeout) as session:
            while True:
                status, healthz, metrics = None, "", None
                try:
                    async with session.get(f"{base}/healthz") as r:
                        status, healthz = r.status, await r.text()
                    async with session.get(f"{base}/metrics") as r:
                        if r.status == 200:
                            metrics = await r.text()
                except (aiohttp.ClientError, TimeoutError, UnicodeDecodeError) as e:
                    healthz = f"no answer from {base} ({type(e).__name__})"
                event = daemon_health(status, healthz, metrics)
                if event != self.health:
                    self.health = event
                    self.broadcast(event)
                await asyncio.sleep(POLL_S)

    # ----------------------------------------------------------------------------- the web

    @web.middleware
    async def _guard(
        self, request: web.Request, handler: Callable[[web.Request], Awaitable[web.StreamResponse]]
    ) -> web.StreamResponse:
        if request.path == "/ws" or request.path.startswith("/api/"):
            bearer = request.headers.get("Authorization", "")
            token = bearer[7:] if bearer.startswith("Bearer ") else request.query.get("token")
            assert self.gate is not None  # made before the site takes requests
            refused = self.gate.refusal(request.headers.get("Host"), request.headers.get("Origin"), token)
            if refused is not None:
                status, why = refused
                self.callers_refused[why] += 1
                now = time.monotonic()
                if now - self._refusal_logged.get(why, -60.0) >= 1.0:  # a flood is counted, not logged
                    self._refusal_logged[why] = now
                    fields = {"path": request.path, "peer": request.remote, "why": why}
                    self.log.warning("caller refused", extra={"fields": fields})
                return web.Response(status=status, text=why + "\n")
        return await handler(request)

    def app(self) -> web.Application:
        app = web.Application(middlewares=[self._guard])
        app.router.add_get("/", self._page)
        app.router.add_get("/ws", self._socket)
        app.router.add_get("/api/status", self._status)
        app.router.add_static("/static/", STATIC, follow_symlinks=False)
        app.on_response_prepare.append(_secured)
        return app

    async def _page(self, request: web.Request) -> web.FileResponse:
        return web.FileResponse(STATIC / "index.html")

    async def _status(self, request: web.Request) -> web.Response:
        return web.json_response(self.status())

    async def _socket(self, request: web.Request) -> web.WebSocketResponse:
        ws = web.WebSocketResponse(heartbeat=HEARTBEAT_S, compress=False, max_msg_size=4096)
        await ws.prepare(request)
        sock = None if request.transport is None else request.transport.get_extra_info("socket")
        if sock is not None:
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, SEND_BUFFER)
        client = Client(ws, next(self._numbers), request.remote or "?")
        self.clients[client.number] = client
        self.log.info("client", extra={"fields": {"client": client.number, "peer": client.peer}})
        try:
            async with asyncio.TaskGroup() as group:
                writer = group.create_task(self._write(client), name=f"client {client.number} writer")
                group.create_task(self._read(client, writer), name=f"client {client.number} reader")
        except* (ConnectionError, aiohttp.ClientError):
            pass  # the tab went away while being written to
        finally:
            del self.clients[client.number]
            self.log.info("client gone", extra={"fields": {"client": client.number, "sent": client.sent}})
        return ws

    async def _read(self, client: Client, writer: asyncio.Task[None]) -> None:
        """Nothing the page says matters; its close ends the client."""
        async for _ in client.ws:
            pass
        writer.cancel()

    async def _write(self, client: Client) -> None:
        loop = asyncio.get_running_loop()
        ws, last = client.ws, 0.0
        while not ws.closed:
            await client.wake.wait()
            client.wake.clear()
            if client.resync:
                client.resync = False
                client.events.clear()
                client.poses.clear()
                await self._send(client, self.snapshot())
            while client.events:
                await self._send(client, client.events.popleft())
            wait = last + 1.0 / POSE_BATCHES_PER_S - loop.time()
            if wait > 0:
                await asyncio.sleep(wait)
            if client.poses:
                poses = list(client.poses.values())
                client.poses.clear()
                await self._send(client, {"type": "poses", "poses": poses})
                last = loop.time()

    @staticmethod
    async def _send(client: Client, event: Event) -> None:
        await client.ws.send_str(json.dumps(event, separators=(",", ":"), allow_nan=False))
        client.sent += 1

    # ------------------------------------------------------------------------------ running

    async def run(self, stop: asyncio.Event) -> None:
        """Serve until ``stop`` is set, then close the clients (at most :data:`GRACE_S`) and stop."""
        runner = web.AppRunner(self.app(), handle_signals=False, access_log=None)
        await runner.setup()
        try:
            site = web.TCPSite(runner, self.settings.host, self.settings.port, shutdown_timeout=GRACE_S)
            try:
                await site.start()
            except OSError as e:
                why = os.strerror(e.errno).lower() if e.errno else str(e)
                raise UsageError(
                    f"{self.settings.host}:{self.settings.port}: {why}", field="--port"
                ) from None
            host, port = runner.addresses[0][:2]
            self.url = f"http://{host}:{port}/"
            if not self.settings.loopback and self.settings.token is None:
                self.settings = dataclasses.replace(self.settings, token=secrets.token_urlsafe(24))
            self.gate = Gate(self.settings, port)
            self.log.info(
                "serving",
                extra={"fields": {"url": self.url, "bus": self.settings.bus, "version": self.version}},
            )
            if not self.settings.loopback:
                self.log.warning(
                    "served beyond loopback",
                    extra={
                        "fields": {
                            "host": self.settings.host,
                            "open": f"{self.url}?token={self.settings.token}",
                            "why": "anyone who reaches this address and has the token sees the bus",
                        }
                    },
                )
            try:
                async with asyncio.TaskGroup() as group:
                    group.create_task(self.watch.run(self.deliver), name="bus")
                    group.create_task(self._clock(), name="clock")
                    if self.settings.metrics is not None:
                        group.create_task(self._poll_health(self.settings.metrics), name="health")
                    group.create_task(self._shutdown(stop), name="shutdown")
            except* _Stop:
                pass
        finally:
            await runner.cleanup()
        self.log.info("stopped", extra={"fields": {"url": self.url}})

    async def _shutdown(self, stop: asyncio.Event) -> None:
        await stop.wait()
        with contextlib.suppress(TimeoutError):
            async with asyncio.timeout(GRACE_S):
                for client in list(self.clients.values()):
                    await client.ws.close(code=aiohttp.WSCloseCode.GOING_AWAY, message=b"mocapd view stopped")
        raise _Stop


async def _secured(request: web.Request, response: web.StreamResponse) -> None:
    response.headers.update(SECURITY)
    response.headers["Server"] = "mocapd"  # not aiohttp's and Python's versions


def serve_view(settings: ViewSettings, *, version: str, rigs: Sequence[RigMap] = BUILT_IN) -> int:
    """Run the view until SIGTERM/SIGINT; the exit status (0)."""
    from daemon.service.app import configure_logging

    logger = configure_logging("info")

    async def main() -> None:
        loop = asyncio.get_running_loop()
        stop = asyncio.Event()

        def on_signal(signum: int) -> None:
            logger.info("signal", extra={"fields": {"signal": signal.Signals(signum).name}})
            stop.set()

        for signum in (signal.SIGTERM, signal.SIGINT):
            loop.add_signal_handler(signum, on_signal, signum)
        await ViewServer(settings, version=version, logger=logger, rigs=rigs).run(stop)

    asyncio.run(main())
    return 0
