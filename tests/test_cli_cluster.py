"""``mocapd cluster status`` run for real against a real etcd holding live members (joined in this
test's event loop) and their reported statuses: the ring's partitions, the reported ones, the
disagreements flagged, streams per partition, lag and lease left, as text and as JSON."""

from __future__ import annotations

import asyncio
import json
import subprocess

from bench.processes import free_port
from daemon.cluster.ring import assignment
from daemon.config import ClusterConfig
from daemon.service.membership import Balance, Membership
from tests.etcd_server import Etcd
from tests.helpers import assert_ok, assert_one_error_line, mocapd

LEASE_S = 30.0
"""The members' leases: long enough that none expires while the test runs on a loaded machine (a
2 s lease did, between two ``cluster status`` calls: its member's report went with it). Expiry is
membership's to test, not the command's."""


async def status(*args: str) -> subprocess.CompletedProcess[str]:
    """The command in a subprocess, while this loop keeps the members' leases alive."""
    return await asyncio.to_thread(mocapd, "cluster", "status", *args)


async def test_status_shows_the_ring_and_the_reports_and_flags_disagreements(etcd: Etcd) -> None:
    """The ring as the members own it: evened out by the leader's balance, which every member's
    watch sees."""
    names = ["w1", "w2", "w3"]
    weights = {p: 3 for p in assignment(names, 8)["w1"]}  # all the streams on w1's partitions
    ring = assignment(names, 8, weights)
    assert ring != assignment(names, 8)
    async with (
        Membership(etcd.url, "w1", lease_s=LEASE_S) as w1,
        Membership(etcd.url, "w2", lease_s=LEASE_S) as w2,
        Membership(etcd.url, "w3", lease_s=LEASE_S) as w3,
    ):
        assert await w1.put_balance(Balance(1, weights))
        async with asyncio.timeout(5):
            while w3.balance != Balance(1, weights):
                await asyncio.sleep(0.01)
        one = sorted(ring["w1"])
        await w1.report({"partitions": one, "streams": {str(p): 2 for p in one}, "lag_s": 0.125})
        stolen = sorted(ring["w2"] | {one[0]})  # w2 still holds a partition the ring gave w1
        await w2.report({"partitions": stolen, "streams": {str(stolen[-1]): 5}, "lag_s": 1.5})
        result = await status("--coordinator", etcd.url, "--partitions", "8", "--json")
        assert_ok(result)
        out = json.loads(result.stdout)
        assert (out["coordinator"], out["prefix"], out["partitions"], out["balance"]) == (
            etcd.url,
            "/mocapd/",
            8,
            1,
        )
        members = {m["name"]: m for m in out["members"]}
        assert members.keys() == {"w1", "w2", "w3"}
        assert {name: m["ring"] for name, m in members.items()} == {n: sorted(ps) for n, ps in ring.items()}
        assert (members["w1"]["reported"], members["w1"]["agrees"]) == (one, True)
        assert (members["w2"]["reported"], members["w2"]["agrees"]) == (stolen, False)
        assert (members["w3"]["reported"], members["w3"]["agrees"]) == (None, False)
        assert (members["w1"]["streams"], members["w1"]["lag_s"]) == (2 * len(one), 0.125)
        assert (members["w2"]["streams"], members["w2"]["lag_s"]) == (5, 1.5)
        assert all(0 < m["lease_left_s"] <= LEASE_S for m in members.values())
        table = out["table"]
        assert [row["partition"] for row in table] == list(range(8))
        assert table[one[0]]["reported_by"] == ["w1", "w2"]
        assert table[one[0]]["owner"] == "w1"
        assert table[stolen[-1]]["streams"] == 5 + (2 if stolen[-1] in one else 0)
        assert sorted(out["disagreements"]) == sorted(
            [
                f"w2 reports owning {stolen}, the ring over the live members (with the balance) "
                f"gives it {sorted(ring['w2'])}",
                "w3 has not reported",
                f"partition {one[0]} is reported by w1, w2",
            ]
        )

        text = await status("--coordinator", etcd.url, "--partitions", "8")
        assert_ok(text)
        lines = text.stdout.splitlines()
        assert lines[:4] == [
            f"cluster:    {etcd.url} (prefix /mocapd/)",
            "members:    3",
            "partitions: 8",
            "balance:    generation 1",
        ]
        w1_line = next(line for line in lines if line.startswith("w1 "))
        assert w1_line.endswith(f"{' '.join(map(str, one))} / {' '.join(map(str, one))}")
        assert "0.12 s" in w1_line or "0.13 s" in w1_line
        assert next(line for line in lines if line.startswith("w2 ")).endswith("DISAGREE")
        assert sum(line.startswith("disagreement: ") for line in lines) == 3


async def test_status_of_an_empty_cluster(etcd: Etcd) -> None:
    result = await status("--coordinator", etcd.url, "--json")
    assert_ok(result)
    out = json.loads(result.stdout)
    assert (out["members"], out["partitions"], out["disagreements"]) == ([], ClusterConfig().partitions, [])
    assert all(row["owner"] is None for row in out["table"])


def test_status_names_the_coordinator_it_cannot_reach_or_parse() -> None:
    line = assert_one_error_line(
        mocapd("cluster", "status", "--coordinator", f"etcd://127.0.0.1:{free_port()}")
    )
    assert line.startswith("mocapd: --coordinator: cannot read the cluster from etcd at etcd://127.0.0.1:")
    line = assert_one_error_line(mocapd("cluster", "status", "--coordinator", "http://127.0.0.1:2379"))
    assert line.startswith("mocapd: --coordinator: an etcd coordinator is etcd://HOST[:PORT]")


def test_status_needs_a_coordinator_and_a_partition_count() -> None:
    line = assert_one_error_line(mocapd("cluster", "status"))
    assert "give --coordinator" in line
    line = assert_one_error_line(
        mocapd("cluster", "status", "--coordinator", "etcd://h", "--partitions", "0")
    )
    assert "--partitions" in line
