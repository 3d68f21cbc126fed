"""Who is in the cluster, kept in etcd: each worker holds a lease and a key under it; everyone
watches the keys.

A :class:`Membership` joins by granting a lease, putting ``{prefix}members/{member}`` under it (only
if no live worker has that name: a transaction on the key's creation revision) and keeping the
lease alive every third of its TTL; it watches ``{prefix}members/`` from the revision it listed, so
it misses no join or leave. Leaving revokes the lease: etcd deletes the member's keys at once and
every watcher sees the delete within milliseconds. A worker that dies without leaving (SIGKILL, a
power cut) stops keeping its lease alive; etcd deletes its keys when the lease expires, between TTL
and TTL + 0.5 s after the last keep-alive (etcd's lessor looks for expired leases every 500 ms).

Leases are whole seconds, and etcd grants no TTL below ``ceil(1.5 * election-timeout)`` seconds: 2 s
with its default Raft timing (heartbeat 100 ms, election timeout 1000 ms; ``deploy/etcd``'s config).
A ``lease_s`` of 2.0 asks for 2 s and gets 2 s; 0.5 or 1.0 is rounded up to 1 s, which etcd raises
to 2 s; 2.5 asks for 3 s. :attr:`Membership.lease_ttl` is what etcd granted.

Fencing (how a worker never publishes for a partition that another worker owns): etcd may give
away a member's partitions (delete its key) no earlier than TTL after the member *sent* its last
answered keep-alive. :attr:`Membership.problem` becomes non-None two thirds of a TTL after that
moment when no newer keep-alive has been answered (at once when etcd says the lease is gone, or the
watch of the others breaks): the member is **paused** (:attr:`Membership.paused`). A paused worker
publishes nothing and recognises nothing, but keeps its partitions and every stream's state: no
other worker can own them yet. When a keep-alive is answered again before the lease could have
expired, it goes on where it stopped, having moved nothing (before issue 34 a worker fenced itself
by dropping every partition and re-reading every buffer, even when the answer came a millisecond
later). Only when the lease may have expired (TTL after the last answered keep-alive, etcd said it
did, or the member's own key was deleted) is the member **out**
(:attr:`Membership.out`): :attr:`Membership.members` then leaves it out, so ``ring.owned(member,
members, P)`` is empty and the worker drops its partitions and their state; the others may own them
now. Keep-alives go on being tried; when the lease did expire the member joins again with a new
lease (unless another worker took its name meanwhile: ``problem`` says so until it leaves).
A broken watch pauses the member until it has listed the members and watched again, however long
that takes, but never makes it out while its lease is kept alive: nobody else can own its
partitions then, so dropping them would only throw their state away (before, a watch broken for a
TTL did, and an etcd election under load, each endpoint tried in turn, took that long: a healthy
worker gave up its partitions and re-read their buffers).

Consistency over availability: while etcd cannot be reached nobody can know who owns what, so
every worker pauses two thirds of a TTL after its last answered keep-alive and is out a third of a
TTL later; no detection is published until etcd answers again. The workers then join again and take
the partitions the ring gives them, replaying each one's buffer (detections of motions that ended
during the outage arrive late, recomputed from the buffer; motions that began before the buffer's
start are lost: ``docs/cluster.md``, "When etcd is lost").

The membership runs on an event loop of its own, in a thread of its own: the keep-alives and the
watch must not wait for whatever the worker's loop is doing (recognition, reading a buffer), or a
worker busy with its work would miss keep-alives and fence itself, throwing its partitions away.
Python switches threads at least every 5 ms, so a keep-alive is late by that at most while the
worker computes. The worker's loop is told of changes (:meth:`Membership.changes`) thread-safely.

etcd's client is ``aetcd`` (asyncio, gRPC; its public API: ``Client``, ``leases.Lease``,
``get_prefix``, ``transaction``, ``watch_prefix``). It talks to one endpoint; ``cluster.coordinator``
may name several members of an etcd cluster (``etcd://h1:2379,h2:2379,h3:2379``): the membership
starts with the first that answers and moves to the next when a keep-alive or the watch fails,
carrying the lease over (a lease is the etcd cluster's, not a member's), so a killed etcd member
costs a worker the time to find the next one (the failed call's timeout, then :data:`RETRY_S`: up
to 1.6 s measured under load, a pause when it outlasts two thirds of the lease), not its lease.
:func:`cluster_status` reads the members, their reported statuses and their leases' TTLs left, for
``mocapd cluster status``.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import math
import os
import socket
import threading
import time
from collections.abc import AsyncIterator, Coroutine, Mapping
from dataclasses import dataclass, field
from types import TracebackType
from typing import Any

import aetcd

from daemon.errors import InputError
from protocols.endpoints import each_in_turn
from protocols.transport import StartupError
from protocols.urls import parse_etcd_urls

FIELD = "cluster.coordinator"
"""The configuration field every failure to reach or join etcd names."""
STARTUP_S = 3.0
"""Entering (and :func:`cluster_status`) fails when etcd has not answered within this many seconds."""
LEAVE_S = 1.0
"""Leaving waits at most this long for etcd to revoke the lease."""
RETRY_S = 0.2
"""How soon a failed keep-alive or a broken watch is tried again (at most a third of a TTL)."""


@dataclass(frozen=True)
class Balance:
    """The streams per partition the cluster's leader last measured (``{prefix}balance``), by which
    every worker evens the ring's loads out (:func:`daemon.cluster.ring.assignment`);
    ``generation`` counts the leader's writes (0: none yet, the ring alone)."""

    generation: int = 0
    weights: Mapping[int, int] = field(default_factory=dict)

    def encode(self) -> bytes:
        weights = {str(p): n for p, n in sorted(self.weights.items()) if n}
        return json.dumps({"generation": self.generation, "weights": weights}, separators=(",", ":")).encode()


def parse_balance(raw: bytes) -> Balance | None:
    """The :class:`Balance` that ``raw`` holds (None: not one; a worker then keeps to the ring)."""
    value = _json_object(raw)
    if value is None:
        return None
    generation, weights = value.get("generation"), value.get("weights")
    if not isinstance(generation, int) or isinstance(generation, bool) or not isinstance(weights, dict):
        return None
    parsed: dict[int, int] = {}
    for k, n in weights.items():
        if not (k.isdigit() and isinstance(n, int) and not isinstance(n, bool) and n >= 0):
            return None
        parsed[int(k)] = n
    return Balance(generation, parsed)


def _addresses(coordinator: str) -> list[tuple[str, int]]:
    """(host, port) of each member of ``etcd://HOST:PORT[,HOST:PORT...]``, the host bracketed for
    gRPC if it is IPv6."""
    try:
        members = parse_etcd_urls(coordinator)
    except InputError as exc:
        raise StartupError(FIELD, exc.reason) from None
    return [((f"[{host}]" if ":" in host else host), port) for host, port in members]


async def _finish_tasks() -> None:
    """Cancel and await every other task of the running loop (the client's, gRPC's), as
    ``asyncio.run`` does before it closes its loop: none is destroyed pending."""
    rest = [t for t in asyncio.all_tasks() if t is not asyncio.current_task()]
    for t in rest:
        t.cancel()
    await asyncio.gather(*rest, return_exceptions=True)
    await asyncio.get_running_loop().shutdown_asyncgens()


def _reraise_if_cancelled(exc: BaseException) -> None:
    """Re-raise ``exc`` if it is the running task's own cancellation. gRPC raises CancelledError in
    a call whose channel was closed under it (the other task moved to another endpoint): that is a
    failed call, and let through it would end the keep-alive or the watch for good, silently (a
    TaskGroup does not count a cancelled child as failed)."""
    task = asyncio.current_task()
    if isinstance(exc, asyncio.CancelledError) and (task is None or task.cancelling()):
        raise exc


def _why(exc: BaseException) -> str:
    if isinstance(exc, TimeoutError):
        return "no answer in time"
    if isinstance(exc, asyncio.CancelledError):
        return "its connection was closed"
    return str(exc) or type(exc).__name__


class Membership:
    """This worker's place in the cluster at ``coordinator`` (``etcd://HOST:PORT``) as ``member``:
    ``async with Membership(...) as m:`` joins, leaving the block leaves. Construction checks the
    values only (StartupError naming ``cluster.coordinator`` for a bad address; InputError for an
    empty name or a ``lease_s`` that is not a positive number); entering talks to etcd."""

    def __init__(
        self, coordinator: str, member: str, *, lease_s: float = 2.0, prefix: str = "/mocapd/"
    ) -> None:
        self.coordinator = coordinator
        self.endpoints = _addresses(coordinator)
        self._at = 0  # the endpoint the client talks to
        if not member:
            raise InputError("a member name must not be empty")
        if not (math.isfinite(lease_s) and lease_s > 0):
            raise InputError(f"lease_s must be a positive number of seconds, got {lease_s!r}")
        self.member = member
        self.prefix = prefix
        self.requested_ttl = max(1, math.ceil(lease_s))
        self.lease_ttl = 0
        """The TTL etcd granted, in whole seconds (0 before entering)."""
        self._members_prefix = f"{prefix}members/".encode()
        self._balance_key = f"{prefix}balance".encode()
        self._balance = Balance()
        self._key = self._members_prefix + member.encode()
        self._status_key = f"{prefix}status/{member}".encode()
        self._client: Any = None
        self._lease: Any = None
        self._lease_dead = False  # etcd said the lease expired
        self._seen: dict[str, int] = {}  # member -> its lease id, as the watch last said
        self._fence_at = 0.0  # monotonic: the member owns nothing from then on, unless kept alive
        self._expires_at = 0.0  # monotonic: the earliest the lease may expire at etcd
        self._next_keep = 0.0
        self._lease_problem: str | None = None
        self._watch_problem: str | None = None
        self._report_problem: str | None = None
        self._watch: Any = None
        self._changed = asyncio.Event()  # of the worker's loop
        self._closed = False
        self._runner: asyncio.Task[None] | None = None  # of the membership's loop
        self._home: asyncio.AbstractEventLoop | None = None  # the worker's loop
        self._loop: asyncio.AbstractEventLoop | None = None  # the membership's, in its thread
        self._thread: threading.Thread | None = None

    # ------------------------------------------------------------------------------- what it tells

    @property
    def interval(self) -> float:
        """Seconds between keep-alives: a third of the granted TTL."""
        return self.lease_ttl / 3

    @property
    def problem(self) -> str | None:
        """None while this member surely holds its lease and sees the others; else why not.

        While it is set the worker publishes nothing (see the module's "Fencing"): it is
        :attr:`paused` (its lease may still hold: it keeps its partitions and their state) or
        :attr:`out` (its lease may have expired: :attr:`members` leaves it out, so it owns nothing)::

            async for members in membership.changes():
                mine = ring.owned(membership.member, members, partitions)  # empty while out

        and, for work already under way, checking ``problem is None`` before each batch."""
        if self._closed:
            return "left the cluster"
        if self._runner is None:
            return "not joined"
        if self._runner is not None and self._runner.done():
            failed = None if self._runner.cancelled() else self._runner.exception()
            return f"the membership's tasks ended: {failed!r}"
        if self._watch_problem is not None:
            return self._watch_problem
        now = time.monotonic()
        if now >= self._fence_at:
            if self._lease_problem is not None:
                return self._lease_problem
            return f"no keep-alive answered for {now - self._fence_at + 2 * self.interval:.1f} s"
        if self.member not in self._seen:
            return f"etcd deleted the key of {self.member!r}"
        return None

    @property
    def out(self) -> bool:
        """True when this member may no longer own anything: left, its tasks ended, its lease may
        have expired, or its key is gone (a broken watch only pauses it: see the module's "Fencing")."""
        if self._closed or self._runner is None or self._runner.done():
            return True
        return self.member not in self._seen or time.monotonic() >= self._expires_at

    @property
    def paused(self) -> bool:
        """True while :attr:`problem` is set but the lease may still hold: publish nothing, keep
        everything."""
        return self.problem is not None and not self.out

    @property
    def members(self) -> frozenset[str]:
        """The live members as last seen, this one included unless it is :attr:`out`."""
        seen = frozenset(self._seen)
        return seen - {self.member} if self.out else seen | {self.member}

    @property
    def balance(self) -> Balance:
        """The leader's last :class:`Balance` as the watch last said."""
        return self._balance

    async def changes(self) -> AsyncIterator[frozenset[str]]:
        """The current :attr:`members` first, then each new set whenever it changes: joins, leaves,
        expiries, and this member going out or coming back (a pause changes nothing; a consumer
        slower than the changes gets the latest set, not every one between); the set again when
        the :attr:`balance` changes. Ends when the membership is left."""
        last: tuple[frozenset[str], Balance] | None = None
        while not self._closed:
            current = (self.members, self._balance)
            if current != last:
                last = current
                yield current[0]
                continue
            changed = self._changed
            wait = self._expires_at - time.monotonic() if self.member in current[0] else None
            with contextlib.suppress(TimeoutError):
                async with asyncio.timeout(None if wait is None else max(wait, 0.001)):
                    await changed.wait()

    @property
    def report_problem(self) -> str | None:
        """Why the last :meth:`report` was not written (None if it was)."""
        return self._report_problem

    def _notify(self) -> None:
        """Wake :meth:`changes` on the worker's loop (from either thread)."""
        if self._home is not None and not self._home.is_closed():
            self._home.call_soon_threadsafe(self._wake)

    def _wake(self) -> None:
        self._changed.set()
        self._changed = asyncio.Event()

    async def _call(self, work: Coroutine[Any, Any, Any]) -> Any:
        """``work`` run on the membership's loop, awaited from the worker's."""
        assert self._loop is not None
        return await asyncio.wrap_future(asyncio.run_coroutine_threadsafe(work, self._loop))

    def _start_loop(self) -> None:
        self._home = asyncio.get_running_loop()
        loop = self._loop = asyncio.new_event_loop()
        self._thread = threading.Thread(
            target=loop.run_forever, name=f"membership {self.member}", daemon=True
        )
        self._thread.start()

    async def _stop_loop(self) -> None:
        loop, thread = self._loop, self._thread
        if loop is None or thread is None:
            return
        with contextlib.suppress(TimeoutError):
            async with asyncio.timeout(LEAVE_S):
                await self._call(_finish_tasks())
        loop.call_soon_threadsafe(loop.stop)
        await asyncio.to_thread(thread.join, LEAVE_S)
        if not thread.is_alive():
            loop.close()

    # ---------------------------------------------------------------------------- joining, leaving

    async def __aenter__(self) -> Membership:
        """Join: StartupError naming ``cluster.coordinator`` within :data:`STARTUP_S` seconds if
        etcd does not answer or the member's name is already live."""
        self._start_loop()
        try:
            await self._call(self._enter())
        except BaseException:
            await self._stop_loop()
            raise
        return self

    async def _enter(self) -> None:
        """:meth:`__aenter__` on the membership's loop: each endpoint in turn, for its share of
        :data:`STARTUP_S`."""

        async def attempt(k: int, endpoint: tuple[str, int]) -> None:
            self._at = k
            self._client = aetcd.Client(*endpoint)
            try:
                if not await self._join():
                    raise StartupError(
                        FIELD,
                        f"a member named {self.member!r} is already live at {self.coordinator} "
                        f"(its key {self._key.decode()} is held by another worker's lease)",
                    )
                await self._list_and_watch()
            except BaseException:
                await self._close()
                raise

        try:
            await each_in_turn(self.endpoints, attempt, STARTUP_S, (aetcd.ClientError, OSError))
        except (aetcd.ClientError, TimeoutError, OSError) as exc:
            raise StartupError(
                FIELD, f"cannot join through etcd at {self.coordinator}: {_why(exc)}"
            ) from None
        self._runner = asyncio.create_task(self._run(), name=f"membership {self.member}")

    async def _switch(self, failed: Any) -> None:
        """The client ``failed`` (a keep-alive or the watch did not get through): talk to the next
        endpoint, the lease and the watch carried over (once, whichever task noticed first)."""
        if failed is not self._client or len(self.endpoints) == 1:
            return
        self._at = (self._at + 1) % len(self.endpoints)
        self._client = aetcd.Client(*self.endpoints[self._at])
        if self._lease is not None:
            self._lease = aetcd.leases.Lease(self._lease.id, self._lease.ttl, self._client)
        self._watch = None
        try:
            async with asyncio.timeout(LEAVE_S):
                await failed.close()
        except (aetcd.ClientError, TimeoutError, OSError, asyncio.CancelledError) as exc:
            _reraise_if_cancelled(exc)

    async def __aexit__(
        self, kind: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        """Leave at once: revoke the lease (the others see this member go within milliseconds)."""
        self._closed = True
        self._notify()
        if self._loop is None:
            return
        try:
            await self._call(self._leave())
        finally:
            await self._stop_loop()

    async def _leave(self) -> None:
        """:meth:`__aexit__` on the membership's loop."""
        if self._runner is not None:
            self._runner.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._runner
        if self._lease is not None:
            with contextlib.suppress(aetcd.ClientError, TimeoutError, OSError):
                async with asyncio.timeout(LEAVE_S):
                    await self._lease.revoke()
        await self._close()

    async def _close(self) -> None:
        if self._client is not None:
            with contextlib.suppress(aetcd.ClientError, TimeoutError, OSError):
                async with asyncio.timeout(LEAVE_S):
                    await self._client.close()
        self._client = None

    async def _join(self) -> bool:
        """Grant a lease and put the member's key under it if no one holds that key; False if
        someone does (the new lease revoked again)."""
        client = self._client
        sent = time.monotonic()  # the lease lasts at least TTL from here
        lease = await client.lease(self.requested_ttl)
        about = {"host": socket.gethostname(), "pid": os.getpid(), "joined": time.time()}
        taken, _ = await client.transaction(
            compare=[client.transactions.create(self._key) == 0],
            success=[client.transactions.put(self._key, json.dumps(about).encode(), lease=lease)],
            failure=[],
        )
        if not taken:
            with contextlib.suppress(aetcd.ClientError):
                await lease.revoke()
            return False
        self._lease = lease
        self._lease_dead = False
        self.lease_ttl = int(lease.ttl)
        self._kept(sent)
        self._seen[self.member] = lease.id
        return True

    def _kept(self, sent: float) -> None:
        """A keep-alive (or the grant) sent at ``sent`` was answered."""
        self._expires_at = sent + self.lease_ttl
        self._fence_at = sent + 2 * self.interval
        self._next_keep = sent + self.interval
        self._lease_problem = None

    async def _list_and_watch(self) -> None:
        """List the members and the balance, and watch the whole prefix from there (the members'
        statuses come along, passed over)."""
        listing = await self._client.get_prefix(self.prefix.encode())
        seen, balance = {}, Balance()
        for kv in listing:
            key = bytes(kv.key)
            if key.startswith(self._members_prefix):
                seen[key[len(self._members_prefix) :].decode(errors="replace")] = kv.lease
            elif key == self._balance_key:
                balance = parse_balance(kv.value) or Balance()
        # each replaced whole: the worker's loop, in another thread, must never see a partial list
        self._seen = seen
        self._balance = balance
        self._watch = await self._client.watch_prefix(
            self.prefix.encode(), start_revision=listing.header.revision + 1
        )
        self._watch_problem = None
        self._notify()

    async def _run(self) -> None:
        async with asyncio.TaskGroup() as tasks:
            tasks.create_task(self._keep_alive(), name=f"etcd keep-alive {self.member}")
            tasks.create_task(self._follow(), name=f"etcd watch {self.member}")

    async def _keep_alive(self) -> None:
        while True:
            await asyncio.sleep(max(0.0, self._next_keep - time.monotonic()))
            sent = time.monotonic()
            answered = False
            client = self._client
            try:
                async with asyncio.timeout(self.interval):
                    gone = self._watch_problem is None and self.member not in self._seen
                    # past the TTL the lease is asked about, not given up: an election (a killed
                    # etcd leader) delays answers, and etcd extends every lease when it has a leader
                    # again, so the old lease may well be alive (joining again would find the
                    # member's key held by it)
                    if self._lease is None or self._lease_dead or gone:
                        answered = await self._rejoin()
                    else:
                        reply = await self._lease.refresh()
                        if reply is None:  # the keep-alive stream closed without an answer
                            raise aetcd.ClientError("the keep-alive stream closed without an answer")
                        answered = reply.TTL > 0
                        if not answered:
                            self._lease_problem = f"etcd says the lease of {self.member!r} expired"
                            self._fence_at = self._expires_at = 0.0
                            self._lease_dead = True
                if answered:
                    self._kept(sent)
            except (aetcd.ClientError, TimeoutError, OSError, asyncio.CancelledError) as exc:
                _reraise_if_cancelled(exc)
                self._lease_problem = f"keep-alive to etcd at {self.coordinator} failed: {_why(exc)}"
                await self._switch(client)
            if not answered:
                self._next_keep = time.monotonic() + min(RETRY_S, self.interval)
            # changes() looks again after every keep-alive, answered or not: the problem may have
            # changed while it was on its way by the clock alone (the fence passed, and the answer
            # then came: the member fenced and live again with nothing said had it notified only
            # when the problem differed from what it was when the keep-alive was sent)
            self._notify()

    def _saw(self, key: bytes, value: bytes | None, lease: int) -> bool:
        """A key of the prefix listed, put or (``value`` None) deleted: whether it was a member's
        or the balance."""
        if key.startswith(self._members_prefix):
            name = key[len(self._members_prefix) :].decode(errors="replace")
            if value is None:
                self._seen.pop(name, None)
            else:
                self._seen[name] = lease
            return True
        if key == self._balance_key:
            self._balance = (None if value is None else parse_balance(value)) or Balance()
            return True
        return False

    async def _rejoin(self) -> bool:
        """The lease may have expired at etcd: join again with a new one."""
        if self._lease is not None:
            with contextlib.suppress(aetcd.ClientError):
                await self._lease.revoke()
            self._lease = None
        if await self._join():
            return True
        self._lease_problem = f"a member named {self.member!r} is live again, under another worker's lease"
        return False

    async def _follow(self) -> None:
        """Apply the watch's events to the members seen; list and watch again when it breaks."""
        while True:
            client = self._client
            try:
                if self._watch is None:
                    async with asyncio.timeout(max(self.interval, RETRY_S)):
                        await self._list_and_watch()
                async for event in self._watch:
                    deleted = event.kind == aetcd.EventKind.DELETE
                    if self._saw(bytes(event.kv.key), None if deleted else event.kv.value, event.kv.lease):
                        self._notify()
                self._watch_problem = "the watch of etcd's members ended (watching again)"
            except (aetcd.ClientError, TimeoutError, OSError, asyncio.CancelledError) as exc:
                _reraise_if_cancelled(exc)
                self._watch_problem = (
                    f"watching the members in etcd at {self.coordinator} failed: {_why(exc)}"
                )
                await self._switch(client)
            self._watch = None
            self._notify()
            await asyncio.sleep(RETRY_S)

    # ---------------------------------------------------------------------------------- reporting

    async def report(self, status: Mapping[str, Any]) -> None:
        """Put ``{prefix}status/{member}`` = ``status`` as JSON under the member's lease (it goes when
        the member goes). Best effort: while :attr:`problem` is set, or when etcd does not answer
        within a keep-alive interval, nothing is written and :attr:`report_problem` says why.
        ValueError for a status JSON cannot hold (NaN, infinities, objects).

        ``mocapd cluster status`` reads these keys of it (others are shown as they are):
        ``partitions`` (the partitions the worker owns now, a list of ints), ``streams`` (streams
        per partition: an object from the partition's number as a string to a count) and ``lag_s``
        (how far behind the worker is, in seconds)."""
        payload = json.dumps(dict(status), allow_nan=False, separators=(",", ":")).encode()
        if self.problem is not None or self._lease is None:
            self._report_problem = f"not reported: {self.problem or 'no lease'}"
            return
        await self._call(self._put_status(payload))

    async def put_balance(self, balance: Balance) -> bool:
        """Write ``balance`` (the leader's; under no lease: it outlives any one worker): whether
        etcd took it within a keep-alive interval."""
        return bool(await self._call(self._put_balance(balance.encode())))

    async def _put_balance(self, payload: bytes) -> bool:
        try:
            async with asyncio.timeout(self.interval):
                await self._client.put(self._balance_key, payload)
        except (aetcd.ClientError, TimeoutError, OSError):
            return False
        return True

    async def statuses(self) -> dict[str, dict[str, Any]] | None:
        """The statuses the members reported (:meth:`report`), by name (those not JSON objects
        left out); None when etcd did not answer within a keep-alive interval."""
        return await self._call(self._statuses())  # type: ignore[no-any-return]

    async def _statuses(self) -> dict[str, dict[str, Any]] | None:
        prefix = f"{self.prefix}status/".encode()
        try:
            async with asyncio.timeout(self.interval):
                listing = await self._client.get_prefix(prefix)
        except (aetcd.ClientError, TimeoutError, OSError):
            return None
        out = {}
        for kv in listing:
            value = _json_object(kv.value)
            if value is not None:
                out[bytes(kv.key)[len(prefix) :].decode(errors="replace")] = value
        return out

    async def _put_status(self, payload: bytes) -> None:
        try:
            async with asyncio.timeout(self.interval):
                await self._client.put(self._status_key, payload, lease=self._lease)
            self._report_problem = None
        except (aetcd.ClientError, TimeoutError, OSError) as exc:
            self._report_problem = f"not reported: {_why(exc)}"


# -------------------------------------------------------------------------------- cluster status


@dataclass(frozen=True)
class MemberStatus:
    """One live member: ``status`` as it last reported it (None if it has not, or not as a JSON
    object), ``lease_left_s`` the whole seconds its lease has left (etcd's count; None if the lease
    ended while being read), ``about`` what it wrote when it joined (host, pid, joined)."""

    name: str
    status: dict[str, Any] | None
    lease_left_s: int | None
    about: dict[str, Any]


@dataclass(frozen=True)
class ClusterStatus:
    """The members live at ``coordinator`` under ``prefix``, by name."""

    coordinator: str
    prefix: str
    members: tuple[MemberStatus, ...]
    balance: Balance = Balance()
    """The leader's balance (the members own their partitions by it)."""

    @property
    def names(self) -> frozenset[str]:
        return frozenset(m.name for m in self.members)


def _json_object(raw: bytes) -> dict[str, Any] | None:
    try:
        value = json.loads(raw)
    except ValueError:
        return None
    return value if isinstance(value, dict) else None


def read_cluster(coordinator: str, prefix: str = "/mocapd/") -> ClusterStatus:
    """:func:`cluster_status` for a caller without an event loop (the command line)."""
    return asyncio.run(cluster_status(coordinator, prefix))


async def cluster_status(coordinator: str, prefix: str = "/mocapd/") -> ClusterStatus:
    """The live members at ``coordinator``, their reported statuses and their leases' TTLs left;
    StartupError naming ``cluster.coordinator`` if etcd does not answer within :data:`STARTUP_S`."""
    members_prefix, status_prefix = f"{prefix}members/".encode(), f"{prefix}status/".encode()

    async def read(_: int, endpoint: tuple[str, int]) -> tuple[list[MemberStatus], Balance]:
        client = aetcd.Client(*endpoint)
        try:
            written = await client.get(f"{prefix}balance".encode())
            balance = (None if written is None else parse_balance(written.value)) or Balance()
            listing = await client.get_prefix(members_prefix)
            statuses = {
                bytes(kv.key)[len(status_prefix) :].decode(errors="replace"): _json_object(kv.value)
                for kv in await client.get_prefix(status_prefix)
            }
            members = []
            for kv in listing:
                name = bytes(kv.key)[len(members_prefix) :].decode(errors="replace")
                left = (await client.get_lease_info(kv.lease, keys=False)).TTL if kv.lease else -1
                members.append(
                    MemberStatus(
                        name, statuses.get(name), left if left >= 0 else None, _json_object(kv.value) or {}
                    )
                )
            return members, balance
        finally:
            with contextlib.suppress(aetcd.ClientError, TimeoutError, OSError):
                async with asyncio.timeout(LEAVE_S):
                    await client.close()

    try:
        members, balance = await each_in_turn(
            _addresses(coordinator), read, STARTUP_S, (aetcd.ClientError, OSError)
        )
    except (aetcd.ClientError, TimeoutError, OSError) as exc:
        raise StartupError(
            FIELD, f"cannot read the cluster from etcd at {coordinator}: {_why(exc)}"
        ) from None
    return ClusterStatus(coordinator, prefix, tuple(sorted(members, key=lambda m: m.name)), balance)
