"""Cluster membership against a real etcd (started from deploy/etcd/etcd.conf.yml on free loopback
ports): joins and leaves seen by the others, a killed worker's lease expiring, a duplicate name
refused, an unreachable etcd failing fast, reported statuses read back, and the fence while etcd
does not answer.

The deadlines asserted are the issue's protocol: a member that leaves (SIGTERM) hands its
partitions over within 1 s, so the others must see it go (and come) in well under that; a member
killed is gone within its lease's TTL + 1 s, and not before the TTL less a keep-alive interval."""

from __future__ import annotations

import asyncio
import os
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

import aetcd
import pytest
import yaml

from bench.processes import free_port
from daemon.errors import InputError
from daemon.service.membership import STARTUP_S, Membership, cluster_status
from protocols.transport import StartupError
from tests.etcd_server import CONFIG, Etcd, EtcdCluster
from tests.helpers import REPO, freeze

SEEN_S = 0.5
"""A join or leave must reach the others within this (the handover's whole budget is 1 s)."""


async def until(condition: Callable[[], bool], timeout: float, what: str) -> float:
    """Seconds until ``condition`` held; AssertionError after ``timeout``."""
    start = time.monotonic()
    while not condition():
        if time.monotonic() - start > timeout:
            raise AssertionError(f"timed out after {timeout:g} s waiting for {what}")
        await asyncio.sleep(0.005)
    return time.monotonic() - start


async def test_joins_and_leaves_are_seen_by_the_others_at_once(etcd: Etcd) -> None:
    async with Membership(etcd.url, "a") as a:
        assert a.members == {"a"} and a.problem is None
        assert a.lease_ttl == 2 and a.interval == pytest.approx(2 / 3)
        seen: list[frozenset[str]] = []

        async def follow() -> None:
            async for members in a.changes():
                seen.append(members)

        follower = asyncio.create_task(follow(), name="follow a's changes")
        await until(lambda: seen == [frozenset({"a"})], 1, "the current set first")
        b = Membership(etcd.url, "b")
        await b.__aenter__()
        assert b.members == {"a", "b"}  # entering lists the others
        joined = await until(lambda: a.members == {"a", "b"}, 5, "a to see b join")
        await until(lambda: seen[-1] == {"a", "b"}, 1, "changes() to yield the join")
        started = time.monotonic()
        await b.__aexit__(None, None, None)
        await until(lambda: a.members == {"a"}, 5, "a to see b leave")
        left = time.monotonic() - started
        await until(lambda: seen[-1] == {"a"}, 1, "changes() to yield the leave")
        assert joined < SEEN_S and left < SEEN_S, (joined, left)
        assert b.problem == "left the cluster" and b.members == {"a"}
    await asyncio.wait_for(follower, 1)  # changes() ends when the membership is left
    assert seen == [{"a"}, {"a", "b"}, {"a"}]


async def test_a_duplicate_member_name_is_refused(etcd: Etcd) -> None:
    async with Membership(etcd.url, "w1") as first:
        with pytest.raises(StartupError, match="'w1' is already live") as refused:
            async with Membership(etcd.url, "w1"):
                pass
        assert refused.value.field == "cluster.coordinator"
        assert first.members == {"w1"} and first.problem is None  # the first keeps its place
    async with Membership(etcd.url, "w1") as again:  # once it left, the name is free
        assert again.members == {"w1"}


async def test_an_unreachable_etcd_fails_fast_naming_the_coordinator() -> None:
    started = time.monotonic()
    with pytest.raises(StartupError, match="cannot join through etcd") as refused:
        async with Membership(f"etcd://127.0.0.1:{free_port()}", "w"):
            pass
    assert refused.value.field == "cluster.coordinator"
    assert time.monotonic() - started < STARTUP_S + 1  # "fail fast"
    with pytest.raises(StartupError, match="cannot read the cluster"):
        await cluster_status(f"etcd://127.0.0.1:{free_port()}")


def test_bad_settings_are_refused_before_anything_is_contacted() -> None:
    for coordinator in ("http://127.0.0.1:2379", "etcd://h:port", "127.0.0.1:2379"):
        with pytest.raises(StartupError, match=r"etcd://HOST\[:PORT\]") as refused:
            Membership(coordinator, "w")
        assert str(refused.value).startswith("cluster.coordinator: ")
    with pytest.raises(InputError, match="empty"):
        Membership("etcd://127.0.0.1:2379", "")
    with pytest.raises(InputError, match="lease_s"):
        Membership("etcd://127.0.0.1:2379", "w", lease_s=float("nan"))


async def test_etcd_grants_no_lease_shorter_than_its_minimum(etcd: Etcd) -> None:
    """TTLs are whole seconds; with the shipped Raft timing (election timeout 1 s) etcd's minimum is
    ceil(1.5 * 1 s) = 2 s."""
    for lease_s, granted in ((0.5, 2), (1.0, 2), (2.0, 2), (2.5, 3)):
        async with Membership(etcd.url, f"w{lease_s}", lease_s=lease_s) as m:
            assert (m.requested_ttl, m.lease_ttl) == (max(1, int(-(-lease_s // 1))), granted)


async def test_reported_statuses_and_leases_are_read_back(etcd: Etcd) -> None:
    async with Membership(etcd.url, "w1") as w1, Membership(etcd.url, "w2") as w2:
        await w1.report({"partitions": [0, 3], "streams": {"0": 4, "3": 1}, "lag_s": 0.25})
        assert w1.report_problem is None
        status = await cluster_status(etcd.url)
        assert status.names == {"w1", "w2"}
        one, two = status.members
        assert one.name == "w1" and one.status == {
            "partitions": [0, 3],
            "streams": {"0": 4, "3": 1},
            "lag_s": 0.25,
        }
        assert two.name == "w2" and two.status is None  # it has not reported
        for m in status.members:
            assert m.lease_left_s is not None and 0 <= m.lease_left_s <= 2
            assert m.about["pid"] == os.getpid()
        with pytest.raises(ValueError, match="Out of range float"):
            await w2.report({"lag_s": float("nan")})
    assert (await cluster_status(etcd.url)).members == ()  # leaving took the statuses with it


VICTIM = """
import asyncio, sys
from daemon.service.membership import Membership

async def main() -> None:
    async with Membership(sys.argv[1], "victim") as m:
        await m.report({"partitions": [1]})
        print("joined", flush=True)
        await asyncio.sleep(3600)

asyncio.run(main())
"""


@pytest.mark.slow
async def test_a_killed_member_is_gone_when_its_lease_expires_and_not_before(etcd: Etcd) -> None:
    victim = subprocess.Popen(
        [sys.executable, "-c", VICTIM, etcd.url],
        cwd=REPO,
        env={**os.environ, "PYTHONPATH": str(REPO)},
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        assert victim.stdout is not None
        line = await asyncio.wait_for(asyncio.to_thread(victim.stdout.readline), 30)
        assert line == "joined\n"
        async with Membership(etcd.url, "observer") as observer:
            assert observer.members == {"observer", "victim"}
            await asyncio.sleep(1.0)  # a few keep-alives of the victim's
            victim.send_signal(signal.SIGKILL)
            victim.wait(5)
            killed = time.monotonic()
            ttl, interval = observer.lease_ttl, observer.interval  # the victim's are the same
            # the victim's last keep-alive was sent at most an interval before it died
            still = ttl - interval - 0.3
            await asyncio.sleep(still)
            present = "victim" in observer.members and time.monotonic() - killed < ttl - interval
            gone = await until(
                lambda: "victim" not in observer.members, ttl + 1, "the victim's lease to expire"
            )
            assert present, f"the victim was gone {still:.2f} s after SIGKILL"
            assert still + gone < ttl + 1
            assert (await cluster_status(etcd.url)).names == {"observer"}
    finally:
        victim.kill()
        victim.wait(5)


async def _follow_states(w: Membership, seen: list[frozenset[str]], states: list[str]) -> None:
    """Record ``w``'s changes() into ``seen`` and, every millisecond, whether it is live, paused or
    out into ``states`` (each state once per run of it)."""

    async def changes() -> None:
        async for members in w.changes():
            seen.append(members)

    async def poll() -> None:
        while True:
            state = "out" if w.out else "paused" if w.paused else "live"
            if not states or states[-1] != state:
                states.append(state)
            await asyncio.sleep(0.001)

    async with asyncio.TaskGroup() as tasks:
        tasks.create_task(changes(), name="follow w's changes")
        tasks.create_task(poll(), name="poll w's state")


async def _followed(w: Membership) -> tuple[list[frozenset[str]], list[str], asyncio.Task[None]]:
    """:func:`_follow_states` of ``w`` started, once it said the current set (``w`` alone, live)."""
    seen: list[frozenset[str]] = []
    states: list[str] = []
    follower = asyncio.create_task(_follow_states(w, seen, states), name=f"follow {w.member}")
    await until(lambda: seen == [{w.member}] and states == ["live"], 1, "the current set")
    return seen, states, follower


async def _went_on_with_nothing_moved(
    w: Membership, seen: list[frozenset[str]], states: list[str], lease: int, what: str
) -> None:
    """``w`` live again after one pause, its members never changed, on the same lease."""
    await until(lambda: w.problem is None, w.lease_ttl, what)
    await asyncio.sleep(0.05)
    assert states == ["live", "paused", "live"], states
    assert seen == [{w.member}]  # nothing moved
    assert w._lease.id == lease


@pytest.mark.slow
async def test_a_member_whose_keep_alives_go_unanswered_pauses_and_goes_on_with_nothing_moved(
    etcd: Etcd,
) -> None:
    """etcd frozen (SIGSTOP) until the member pauses, two thirds of a TTL after its last answered
    keep-alive, then thawed before its lease could expire: the member was paused (it would publish
    nothing) but never out, its members never changed (a worker keeps its partitions and their
    state), and it is live again on the same lease."""
    assert etcd.process is not None
    async with Membership(etcd.url, "w") as w:
        seen, states, follower = await _followed(w)
        lease = w._lease.id
        freeze(etcd.process)
        frozen = time.monotonic()
        try:
            await until(lambda: w.problem is not None, w.lease_ttl, "the pause")
            paused = time.monotonic() - frozen
            assert w.paused and not w.out and "keep-alive" in (w.problem or "")
            assert w.members == {"w"}
            assert paused < 2 * w.interval + 0.05  # from the last answer (before frozen): ≤ 2/3 TTL
        finally:
            etcd.process.send_signal(signal.SIGCONT)
        await _went_on_with_nothing_moved(w, seen, states, lease, "w to go on")
    follower.cancel()


async def test_a_watch_broken_for_longer_than_the_lease_only_pauses_while_keep_alives_hold(
    tmp_path: Path,
) -> None:
    """The watch of the others broken for 1.5 TTL while every keep-alive is answered: the member is
    paused (publishes nothing) but never out, keeps its lease and its place, and goes on when it
    has listed the members again. The fault is real: an etcd that takes requests of up to 6 MiB,
    and a 5 MB value put under the prefix, which the client's gRPC (4 MiB a message) can neither
    receive as a watch event nor in a listing, while the keep-alives get through; then the value
    deleted. Before, a watch broken for a TTL made the member out: it dropped its partitions though
    nobody else could own them."""
    config = tmp_path / "etcd.conf.yml"
    shipped = yaml.safe_load(CONFIG.read_text(encoding="utf-8"))
    config.write_text(yaml.safe_dump(shipped | {"max-request-bytes": 6 << 20}), encoding="utf-8")
    (tmp_path / "etcd").mkdir()
    etcd = Etcd(tmp_path / "etcd", config).start()
    try:
        async with Membership(etcd.url, "w") as w:
            seen, states, follower = await _followed(w)
            lease = w._lease.id
            host, port = etcd.url.removeprefix("etcd://").split(":")
            other = aetcd.Client(host, int(port))
            try:
                big = f"{w.prefix}status/big".encode()
                await other.put(big, b"x" * 5_000_000)
                await until(lambda: w.problem is not None, 2, "the watch to break")
                end = time.monotonic() + 1.5 * w.lease_ttl
                while time.monotonic() < end:
                    assert w.paused and not w.out and w.members == {"w"}, w.problem
                    await asyncio.sleep(0.05)
                assert "watch" in (w.problem or ""), w.problem
                await other.delete(big)
            finally:
                await other.close()
            await _went_on_with_nothing_moved(w, seen, states, lease, "w to list and watch again")
        follower.cancel()
    finally:
        etcd.stop()


@pytest.mark.slow
async def test_a_member_unanswered_for_its_whole_lease_is_out_and_joins_again(etcd: Etcd) -> None:
    """etcd frozen for longer than a TTL: the member pauses, then is out (it owns nothing: another
    worker may own its partitions now) from a TTL after its last answered keep-alive, and when etcd
    answers again it owns again: with a new lease, or with its old one when etcd (frozen too) never
    expired it (a keep-alive sent before the TTL ran out answered alive: nobody saw it go)."""
    assert etcd.process is not None
    async with Membership(etcd.url, "w") as w:
        seen: list[frozenset[str]] = []
        states: list[str] = []
        follower = asyncio.create_task(_follow_states(w, seen, states), name="follow w")
        await until(lambda: seen == [{"w"}], 1, "the current set")
        freeze(etcd.process)
        frozen = time.monotonic()
        try:
            await until(lambda: w.out, w.lease_ttl + 0.5, "w to be out")
            out = time.monotonic() - frozen
            assert w.members == frozenset() and w.problem is not None
            await until(lambda: seen[-1] == frozenset(), 1, "changes() to yield w out")
            assert 2 * w.interval <= out < w.lease_ttl + 0.05, out
        finally:
            etcd.process.send_signal(signal.SIGCONT)
        await until(lambda: w.problem is None, 3 * w.lease_ttl, "w to join again")
        await until(lambda: seen[-1] == {"w"}, 1, "changes() to yield w back")
        await asyncio.sleep(0.05)
        assert states[:3] == ["live", "paused", "out"] and states[-1] == "live", states
    follower.cancel()


@pytest.mark.slow
async def test_the_watch_comes_back_after_etcd_restarts(etcd: Etcd) -> None:
    """etcd killed and started again on its ports and data: the members keep their leases (etcd
    restores them and extends them when it leads again), their problem clears, and a join after the
    restart is seen."""
    async with Membership(etcd.url, "a") as a, Membership(etcd.url, "b") as b:
        etcd.kill()
        await until(lambda: a.problem is not None and b.problem is not None, 5, "both to notice")
        assert "watching the members" in (a.problem or "") or "keep-alive" in (a.problem or "")
        await asyncio.to_thread(etcd.start, True)
        await until(lambda: a.problem is None and b.problem is None, 15, "both to be back")
        assert a.members == b.members == {"a", "b"}
        async with Membership(etcd.url, "c"):
            await until(lambda: a.members == {"a", "b", "c"}, 5, "a to see c join after the restart")
        await until(lambda: a.members == {"a", "b"}, 5, "a to see c leave")


async def test_a_worker_busy_computing_keeps_its_lease_and_its_place(etcd: Etcd) -> None:
    """The worker's event loop held by computation (recognition, a buffer read) for longer than a
    TTL: the keep-alives go on from the membership's own thread, so the member is never fenced and
    the others never see it go."""
    async with Membership(etcd.url, "busy") as busy:
        seen: list[frozenset[str]] = []

        async def follow() -> None:
            async for members in busy.changes():
                seen.append(members)

        follower = asyncio.create_task(follow(), name="follow busy's changes")
        await until(lambda: seen == [{"busy"}], 1, "the current set first")
        problems = []
        end = time.monotonic() + 1.5 * busy.lease_ttl
        n = 0
        while time.monotonic() < end:  # pure Python holding the loop (and the GIL, but for switches)
            n += sum(i * i for i in range(1000)) % 7
            problems.append(busy.problem)
        assert problems and set(problems) == {None}, set(problems)
        assert (await cluster_status(etcd.url)).names == {"busy"}
        await asyncio.sleep(0.05)
        assert seen == [{"busy"}]  # no flap: never fenced, never dropped its partitions
    follower.cancel()


@pytest.mark.slow
async def test_a_killed_etcd_member_costs_no_worker_its_lease(tmp_path: Path) -> None:
    """The shipped three-member etcd cluster (``deploy/etcd/cluster``), a member given all three and
    talking to the first: the first killed (kill -9), the member moves to another endpoint with its
    lease, so it is never out and the others never see it go; what happens after (a join) it sees.
    With the 2 s lease and the CI rehearsal beside it, the election after a killed leader outlasted
    the lease once in five runs (the member was out, and back on its lease)."""
    cluster = await asyncio.to_thread(EtcdCluster(tmp_path).start)
    try:
        _, *rest = cluster.url.removeprefix("etcd://").split(",")
        # a lease longer than an election under load (docs/cluster.md): 4 s
        w = Membership(cluster.url, "w", lease_s=4.0)
        async with w, Membership(f"etcd://{','.join(rest)}", "o", lease_s=4.0) as o:
            seen: list[frozenset[str]] = []
            states: list[str] = []
            follower = asyncio.create_task(_follow_states(w, seen, states), name="follow w")
            await until(lambda: o.members == {"w", "o"} and seen == [{"w", "o"}], 5, "both")
            watched: list[frozenset[str]] = []

            async def watch_o() -> None:
                while True:
                    watched.append(o.members)
                    await asyncio.sleep(0.005)

            watcher = asyncio.create_task(watch_o(), name="watch o")
            lease = w._lease.id
            await asyncio.to_thread(cluster.members[0].kill)
            await asyncio.sleep(w.lease_ttl + 1.0)
            assert "out" not in states, states
            assert w._lease.id == lease and w.problem is None
            assert all("w" in m for m in watched)
            async with Membership(f"etcd://{rest[0]}", "late"):
                await until(lambda: w.members == {"w", "o", "late"}, 5, "w to see a join after the kill")
            watcher.cancel()
            follower.cancel()
    finally:
        await asyncio.to_thread(cluster.stop)
