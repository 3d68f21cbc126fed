"""Cluster mode's worker side (``docs/cluster.md``): membership in etcd, the partitions this worker
owns, status reports, and leaving.

:class:`Cluster` is entered with the service's transports (joining fails fast, naming
``cluster.coordinator``, when etcd does not answer). Its :meth:`Cluster.follow` task takes each
change of the live members from :class:`~daemon.service.membership.Membership` and has the
transport consume exactly the partitions :func:`~daemon.cluster.ring.owned` gives this member;
streams of a partition given up are dropped from the stream table without publishing anything (the
new owner publishes their detections). :meth:`Cluster.report` writes this worker's status about once
a second. :meth:`Cluster.leave` (SIGTERM) revokes the lease first, so the others take over within
milliseconds, and flushes nothing.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import os
import socket
import time
from collections.abc import Callable, Iterable, Mapping
from types import TracebackType
from typing import TYPE_CHECKING, Any

from daemon.cluster.ring import assignment, loads, orphaned, owned, spread
from daemon.config import ClusterConfig
from daemon.library import Library
from daemon.recognizer import Recognizer
from daemon.service.membership import Balance, Membership
from replay import JOINT_NAMES

if TYPE_CHECKING:
    from daemon.service.streams import StreamTable
    from protocols.nats import NatsTransport

REPORT_S = 1.0
SKELETON_PERIOD_S = 1.0
"""How often publishers announce their skeletons at least (``protocols/README.md``)."""
MARGIN_S = 1.0
SETTLE_S = 0.25
"""Partitions gained are taken once the live members have held still this long."""
SAMPLE_S = 0.5
"""How often the owned partitions are looked at for a checkpoint."""
HAND_OVER_S = 1.0
"""The longest a worker told to stop waits for its last checkpoints (:meth:`Cluster.hand_over`)."""
TOLERANCE = 0.2
"""The leader evens the loads out when the fullest or emptiest member is further than this share
of the mean from it (and evening out brings them closer)."""


def measured(
    statuses: Mapping[str, Mapping[str, Any]], members: Iterable[str], generation: int
) -> dict[int, int] | None:
    """The streams per partition the live ``members`` report (a partition reported by two, handed
    over between reports: the larger count); None unless every one of them reported owning its
    partitions by the balance of ``generation`` (its losses given up: what it reports is what it
    holds by that balance)."""
    counts: dict[int, int] = {}
    for name in members:
        status = statuses.get(name)
        if status is None or status.get("generation") != generation:
            return None
        streams = status.get("streams")
        for k, n in streams.items() if isinstance(streams, dict) else ():
            if isinstance(k, str) and k.isdigit() and isinstance(n, int) and n > 0:
                counts[int(k)] = max(counts.get(int(k), 0), n)
    return counts


def rebalance(
    members: frozenset[str], partitions: int, now: Balance, counts: Mapping[int, int]
) -> Balance | None:
    """The balance the leader writes when the members' loads of ``counts`` under ``now`` spread
    further than :data:`TOLERANCE` from their mean and evening them out by ``counts`` brings them
    closer (None: keep ``now``)."""
    spread_now = spread(loads(assignment(members, partitions, now.weights), counts))
    if spread_now <= TOLERANCE:
        return None
    if spread(loads(assignment(members, partitions, counts), counts)) >= spread_now:
        return None
    return Balance(now.generation + 1, dict(counts))


def reach_seconds(library: Library, config: Any) -> float:
    """Seconds before the pose that emits it that a detection may start at, at most, with the
    library and the ``recognizer`` settings of ``config`` (:attr:`Recognizer.reach`)."""
    r = Recognizer(library, library.rate * 4, settings=config.recognizer.settings(), joint_names=JOINT_NAMES)
    return r.reach / library.rate


def needed_seconds(cluster: ClusterConfig, library: Library, config: Any) -> float:
    """The buffer a takeover needs: the lease (the old owner's last pose to the new owner's start),
    a skeleton announcement (its first usable pose), twice the library's reach (the warm-up whose
    detections are suppressed, then the reach of the old owner's last unpublished detection) and a
    margin."""
    return round(cluster.lease_s + SKELETON_PERIOD_S + 2 * reach_seconds(library, config) + MARGIN_S, 1)


def buffer_seconds(cluster: ClusterConfig, library: Library, config: Any) -> float:
    """``cluster.buffer_s``, or when 0 :func:`needed_seconds`."""
    return cluster.buffer_s or needed_seconds(cluster, library, config)


def member_name(cluster: ClusterConfig) -> str:
    return cluster.member or f"{socket.gethostname().split('.')[0] or 'mocapd'}-{os.getpid()}"


class Cluster:
    """This worker in the cluster of ``settings`` as ``member``, reading through ``transport``."""

    def __init__(
        self, settings: ClusterConfig, member: str, transport: NatsTransport, log: logging.Logger
    ) -> None:
        self.settings = settings
        self.member = member
        self.transport = transport
        self.log = log
        self.members: frozenset[str] = frozenset()
        self.balance = Balance()
        """The leader's balance this worker owns its partitions by (given up what it loses)."""
        self.takeovers = 0
        """Partitions taken after this worker's first assignment (from a member that left or died,
        or given up to one that joined: counted by the taker)."""
        self.changes = 0
        self._membership: Membership | None = None
        self._assigned = False
        self._left = False
        self._handing_over = False

    async def __aenter__(self) -> Cluster:
        s = self.settings
        self._membership = await Membership(s.coordinator, self.member, lease_s=s.lease_s).__aenter__()
        self.log.info("joined", extra={"fields": {"member": self.member, "coordinator": s.coordinator}})
        return self

    async def __aexit__(
        self, kind: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        await self.leave()

    async def leave(self) -> None:
        """Leave the cluster (revoke the lease) and stop consuming; idempotent."""
        if self._left or self._membership is None:
            return
        self._left = True
        started = time.monotonic()
        await self._membership.__aexit__(None, None, None)
        await self.transport.own(frozenset())
        self.log.info(
            "left", extra={"fields": {"member": self.member, "took_s": round(time.monotonic() - started, 4)}}
        )

    @property
    def problem(self) -> str | None:
        m = self._membership
        if self._left:
            return "left the cluster"
        return None if m is None else m.problem

    @property
    def holding(self) -> bool:
        """True while this worker must publish nothing: its membership has a problem (paused: its
        partitions and their state are kept; or out: it owns nothing)."""
        return self.problem is not None

    async def follow(self, table: StreamTable, settled: Callable[[], bool]) -> None:
        """Own what the ring gives this member among the live members, at every change: partitions
        lost are given up at once (each, when ``settled()`` and its streams have no pose waiting,
        with a last checkpoint, as :meth:`hand_over` stores, for the member that takes it), and so
        are partitions gained from a member that is gone (or from nobody: the first member of a new
        cluster); partitions gained from a live member (this one joining, another joining, or the
        loads evened out) are taken once the members have held still for :data:`SETTLE_S`, after
        their old owner has seen the change and given them up."""
        m = self._membership
        assert m is not None
        async for members in m.changes():
            if self._left:
                return
            count, balance = self.settings.partitions, m.balance
            mine = owned(self.member, members, count, balance.weights)
            held = self.transport.owned
            before, then = (
                (self.members, self.balance) if self._assigned else (members - {self.member}, balance)
            )
            if waiting := mine - held - orphaned(mine - held, before, members, count, then.weights):
                # losses and the gone's first
                await self._own(mine - waiting, members, balance, table, settled, final=False)
                await asyncio.sleep(SETTLE_S)
                if self._left:
                    return
                members, balance = m.members, m.balance
                mine = owned(self.member, members, count, balance.weights)
            await self._own(mine, members, balance, table, settled)

    async def _own(
        self,
        mine: frozenset[int],
        members: frozenset[str],
        balance: Balance,
        table: StreamTable,
        settled: Callable[[], bool],
        *,
        final: bool = True,
    ) -> None:
        """Consume ``mine``; ``final``: the whole of what the ring gives this member among
        ``members`` with ``balance`` (not the part taken before settling), after which gains count
        as takeovers."""
        before = self.transport.owned
        if mine == before and members == self.members and balance == self.balance:
            return
        gained = mine - before
        if self._assigned:
            self.takeovers += len(gained)
        self._assigned = self._assigned or final
        self.members = members
        self.balance = balance
        self.changes += 1
        lost = sorted(before - mine)
        handed = 0
        if lost and self.settings.checkpoint_s > 0 and not self.holding and settled():
            handed = await self._last_checkpoints(lost, table, SETTLE_S / 2)  # before the taker reads
        for stream in await self.transport.own(mine):
            table.forget(stream)
        self.log.info(
            "partitions",
            extra={
                "fields": {
                    "members": sorted(members),
                    "generation": balance.generation,
                    "owned": sorted(mine),
                    "gained": sorted(gained),
                    "lost": lost,
                    "checkpoints": handed,
                    "problem": self.problem,
                }
            },
        )

    async def checkpoint(self, table: StreamTable, settled: Callable[[], bool]) -> None:
        """Store each owned partition's checkpoint (``docs/cluster.md``, "Checkpoints") at most
        every ``cluster.checkpoint_s``, looked at every :data:`SAMPLE_S`: while this worker holds its
        partitions and ``settled()`` (nothing emitted waits to be published), a partition none of
        whose streams has a pose waiting, and that took something in since its last one."""
        stored: dict[int, tuple[int, float]] = {}  # partition -> (position, when stored)
        while not self._left and not self._handing_over:
            await asyncio.sleep(SAMPLE_S)
            for p in stored.keys() - self.transport.owned:
                del stored[p]
            now = time.monotonic()
            for p in sorted(self.transport.owned):
                last = stored.get(p)
                if last is not None and now - last[1] < self.settings.checkpoint_s:
                    continue
                if self._left or self._handing_over or self.holding or not settled():
                    break
                taken = self.states(p, table)
                if taken is None or (last is not None and taken[0] == last[0]):
                    continue
                if await self.transport.checkpoint(p, *taken):
                    stored[p] = (taken[0], now)

    def states(self, p: int, table: StreamTable) -> tuple[int, dict[str, bytes]] | None:
        """Partition ``p``'s checkpoint now: the buffer sequence of the last message taken in, and
        the state of each of its streams in the table (:meth:`StreamTable.state`); None if nothing
        was taken in yet or a pose of one of its streams waits."""
        position = self.transport.taken_up_to(p)
        if position is None:
            return None
        held = [name for name in self.transport.streams_of(p) if name in table.streams]
        if any(table.waiting(name) for name in held):
            return None
        now = time.monotonic()
        return position, {name: table.state(name, now) for name in held}

    async def hand_over(self, table: StreamTable, settled: Callable[[], bool]) -> None:
        """SIGTERM, before :meth:`leave`: take nothing more in, wait (at most :data:`HAND_OVER_S`)
        until every pose taken in is recognised and published, and store every owned partition's
        checkpoint then, so that the new owners resume its streams where this worker left them
        and read only what it did not take in. A partition still busy when the time is up keeps
        its last periodic checkpoint."""
        if self._left or self._membership is None or self.settings.checkpoint_s <= 0:
            return
        self._handing_over = True
        started = time.monotonic()
        self.transport.stop_taking()
        with contextlib.suppress(TimeoutError):
            async with asyncio.timeout(HAND_OVER_S):
                while not (settled() and not table.queued):
                    await asyncio.sleep(0.005)
        owned = sorted(self.transport.owned)
        left = max(0.1, HAND_OVER_S - (time.monotonic() - started))
        stored = await self._last_checkpoints(owned, table, left)
        self.log.info(
            "handed over",
            extra={
                "fields": {
                    "partitions": len(owned),
                    "checkpoints": stored,
                    "took_s": round(time.monotonic() - started, 4),
                }
            },
        )

    async def _last_checkpoints(self, partitions: list[int], table: StreamTable, seconds: float) -> int:
        """The checkpoints of ``partitions`` now (:meth:`states`; those with a pose waiting
        passed over), stored at once within ``seconds``: how many were stored."""
        due = [(p, taken) for p in partitions if (taken := self.states(p, table)) is not None]
        stored: list[bool] = []
        with contextlib.suppress(TimeoutError):
            async with asyncio.timeout(seconds):
                stored = await asyncio.gather(*(self.transport.checkpoint(p, *t) for p, t in due))
        return sum(stored)

    async def lead(self) -> None:
        """While this worker is the cluster's leader (the live member with the smallest name), every
        ``cluster.balance_s`` (0: never): once every member owns its partitions by the current
        balance, read the streams per partition they report and write a new balance when
        :func:`rebalance` says so at two looks in a row (``docs/cluster.md``, "Balance": streams
        that start or end for a moment move nothing). Every worker then owns by it, as by a change
        of members."""
        m = self._membership
        assert m is not None
        every = self.settings.balance_s
        wanted = False  # whether the last look wanted a new balance
        while not self._left and every > 0:
            await asyncio.sleep(every)
            looked = await self._look(m)
            if looked is None:
                wanted = False
                continue
            if not wanted:
                wanted = True
                continue
            members, now, counts, new = looked
            if self._left or self.holding or not await m.put_balance(new):
                continue
            wanted = False
            p = self.settings.partitions
            fields = {
                "generation": new.generation,
                "streams": sum(counts.values()),
                "before": loads(assignment(members, p, now.weights), counts),
                "after": loads(assignment(members, p, counts), counts),
            }
            self.log.info("balanced", extra={"fields": fields})

    async def _look(self, m: Membership) -> tuple[frozenset[str], Balance, dict[int, int], Balance] | None:
        """One look of :meth:`lead`: (the members, the current balance, the streams per partition,
        the new balance) when this worker leads, every member owns by the current balance and
        :func:`rebalance` wants a new one; else None."""
        members, now = m.members, m.balance
        if not members or self.member != min(members) or self.holding or self._handing_over:
            return None
        if now != self.balance:
            return None  # not owned by yet here
        statuses = await m.statuses()
        counts = None if statuses is None else measured(statuses, members, now.generation)
        new = None if counts is None else rebalance(members, self.settings.partitions, now, counts)
        return None if counts is None or new is None else (members, now, counts, new)

    async def report(self, table: StreamTable, lag: Any) -> None:
        """This worker's status in etcd about once a second: partitions, streams per partition,
        queued poses."""
        m = self._membership
        assert m is not None
        while not self._left:
            await asyncio.sleep(REPORT_S)
            self.transport.forget(set(table.streams))
            per: dict[str, int] = {}
            for stream in table.streams:
                p = self.transport.partition(stream)
                if p is not None:
                    per[str(p)] = per.get(str(p), 0) + 1
            with contextlib.suppress(ValueError):
                await m.report(
                    {
                        "partitions": sorted(self.transport.owned),
                        "generation": self.balance.generation,
                        "streams": per,
                        "queued": table.queued,
                        "lag_s": lag(),
                        "takeovers": self.takeovers,
                        "replayed": self.transport.replayed,
                        "duplicates": self.transport.duplicates,
                        "time": time.time(),
                    }
                )
