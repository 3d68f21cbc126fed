"""Cluster mode end to end, every part real (``docs/cluster.md``): the shipped three-server NATS
cluster (JetStream with three replicas of every buffer, the MQTT listener, the partitioning
mappings), the shipped three-member etcd, ``mocapd run --cluster ... --coordinator ...`` workers as
processes, and a publisher of 30 looping streams of real recordings over MQTT into the first NATS
server's MQTT port, with a CPU-bound process beside them on the 2 cores. Three workers start; the
etcd member they talk to is killed (kill -9: no partition moves), then one worker is killed
(kill -9), one stopped (SIGTERM), a new one started, and the NATS server leading the most
partitions' buffers killed (kill -9; the clients talk to another), all while the streams go on.
Every stream's detections, as an MQTT client and a NATS client receive them, are ``mocapd
detect``'s on the frames sent, each delivered once; the killed worker is seen gone within the lease
and a second, its partitions are consumed live again within a second after that, those of the
stopped one within a second."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import time
from collections import Counter
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest

from bench.processes import free_port, json_lines, scrape
from tests.etcd_server import EtcdCluster
from tests.helpers import (
    MOCAPD_SCRIPT,
    MqttCollector,
    NatsCollector,
    cluster_load,
    each_once_as_detect,
    wait_for,
)
from tests.helpers import (
    burner as burner_process,
)
from tests.nats_server import NatsCluster

LEASE_S = 4.0
"""Longer than an etcd election under load (1-2 s after its leader is killed), as docs/cluster.md
asks of a worker of a three-member etcd: with 2 s every worker was out for a moment."""
STREAMS = 30
RATE = 60.0
"""Poses per second per stream (the recordings are 120 Hz: half speed, so the 2 cores keep up)."""
SECONDS = 30.0
PARTITIONS = 16
"""Fewer than the default 256: a clustered JetStream makes a replicated stream in 0.2-0.5 s here."""
REPO = Path(__file__).resolve().parents[1]


class Worker:
    """``mocapd run --cluster ... --coordinator ...`` as a process named ``name``; its logs in
    ``where/<name>.err``."""

    def __init__(self, where: Path, name: str, nats: str, etcd: str) -> None:
        self.name = name
        self.err = where / f"{name}.err"
        self.metrics_port = free_port()
        config = where / f"{name}.yaml"
        config.write_text(
            json.dumps(
                {
                    "service": {"idle_s": 3},
                    "cluster": {"partitions": PARTITIONS, "lease_s": LEASE_S, "replicas": 3},
                    "metrics": {"port": self.metrics_port},
                    "logging": {"level": "debug"},
                }
            ),
            encoding="utf-8",
        )
        env = {**os.environ, "MOCAPD_CLUSTER_MEMBER": name, "PYTHONPATH": str(REPO)}
        with self.err.open("ab") as err:
            self.process = subprocess.Popen(
                [
                    str(MOCAPD_SCRIPT),
                    "--config",
                    str(config),
                    "run",
                    "--cluster",
                    nats,
                    "--coordinator",
                    etcd,
                ],
                stdout=subprocess.DEVNULL,
                stderr=err,
                env=env,
            )

    def logs(self) -> list[dict[str, Any]]:
        return json_lines(self.err)

    def events(self, name: str) -> list[dict[str, Any]]:
        return [e for e in self.logs() if e.get("event") == name]

    def owned(self) -> set[int]:
        last = self.events("partitions")
        return set(last[-1]["owned"]) if last else set()

    def sees(self, members: int) -> bool:
        last = self.events("partitions")
        return bool(last) and len(last[-1]["members"]) == members

    def metrics(self) -> dict[str, float]:
        return scrape(self.metrics_port)

    def stop(self, sig: int = signal.SIGTERM) -> None:
        if self.process.poll() is None:
            self.process.send_signal(sig)
            self.process.wait(15)


def most_buffers_led(cluster: NatsCluster) -> int:
    """The index of the server, not the first (which every client talks to), that leads the most
    partitions' buffers."""
    import asyncio

    import nats

    async def leaders() -> Counter[int | None]:
        nc = await nats.connect(cluster.servers[0].url)
        try:
            js = nc.jetstream(timeout=5.0)
            return Counter([await cluster.leader_of(f"MOCAPD_BUF_{p}", js) for p in range(PARTITIONS)])
        finally:
            await nc.close()

    led = asyncio.run(leaders())
    return max((1, 2), key=lambda k: led[k])


KILL_WINDOW_S = 5.0
"""How long before its kill -9 a worker's detection may have been logged (when it is queued for
the store, one store at a time) and not yet published."""


def lost_to_the_kill(
    killed: Worker, at: float, workers: list[Worker]
) -> Callable[[list[dict[str, Any]]], Counter[tuple[str, str]]]:
    """The loss ``protocols/nats.py`` documents: a worker killed between storing a detection in
    ``MOCAPD_OUT`` and publishing it loses it (its taker's copy is acknowledged as a duplicate and
    not published). Per (stream, class), the detections that never came, the ``killed`` worker
    logged in the :data:`KILL_WINDOW_S` before its kill at ``at``, and another worker's store found
    stored already; on a loaded machine the worker's event loop may take that long from the store's
    answer to the publish (2 runs in 5 lost one with a CPU-bound process more than this test's)."""

    def excused(got: list[dict[str, Any]]) -> Counter[tuple[str, str]]:
        came = {d["id"] for d in got}
        stored = {e["id"] for w in workers if w is not killed for e in w.events("duplicate")}
        return Counter(
            (e["stream"], e["class"])
            for e in killed.events("detection")
            if at - KILL_WINDOW_S <= e["ts"] <= at and e["id"] in stored and e["id"] not in came
        )

    return excused


def first_live_after(workers: list[Worker], partition: int, after: float) -> float | None:
    """When a worker first consumed a live pose of ``partition`` after ``after`` (wall clock)."""
    times = [
        e["ts"]
        for w in workers
        for e in w.events("partition live")
        if e["partition"] == partition and e["ts"] > after
    ]
    return min(times, default=None)


@pytest.mark.slow
@pytest.mark.exclusive  # leases and elections in real time beside its own load, and no other test's
def test_takeovers_lose_and_repeat_no_detection(tmp_path: Path) -> None:
    cluster = NatsCluster(tmp_path / "nats", PARTITIONS).start()
    server = cluster.servers[0]  # every client's
    etcd = EtcdCluster(tmp_path / "etcd").start()
    workers: list[Worker] = []
    mqtt = nats = None
    load = burner = None
    try:
        workers = [Worker(tmp_path, f"w{i}", cluster.url, etcd.url) for i in (1, 2, 3)]
        wait_for(
            lambda: (
                all(w.sees(3) for w in workers)
                and set().union(*(w.owned() for w in workers)) == set(range(PARTITIONS))
            ),
            60,
            "three workers, each seeing three, owning every partition between them",
        )
        mqtt = MqttCollector(server.mqtt_url, ["mocap/+/detections"], client_id="e2e-collector")
        nats = NatsCollector(server.url)
        load = cluster_load(server.mqtt_url, STREAMS, SECONDS, RATE)
        burner = burner_process()  # the load beside it
        w1, w2, _ = workers
        time.sleep(3)
        etcd.members[0].kill()  # the member every worker talks to first
        etcd_killed = time.time()
        # etcd's new leader extends every lease when it is elected (1-3 s here under this load): a
        # worker killed before that is seen gone a lease after the election, not after the kill
        time.sleep(5)
        killed_owned, killed_at = w1.owned(), time.time()
        w1.stop(signal.SIGKILL)
        time.sleep(7)
        stopped_owned, stopped_at = w2.owned(), time.time()
        w2.stop(signal.SIGTERM)
        time.sleep(4)
        w4 = Worker(tmp_path, "w4", cluster.url, etcd.url)
        workers.append(w4)
        # the NATS server killed once the new worker owns its partitions: a worker starting takes
        # 4-8 s under this load, and killed before it joined, the server's buffers lost their poses
        # of the election while the joiner then took its partitions from checkpoints older than
        # that gap, which no path brings again (docs/cluster.md, "A known gap")
        w3 = workers[2]
        wait_for(
            lambda: (
                bool(w4.owned())
                and w3.owned() | w4.owned() == set(range(PARTITIONS))
                and not w3.owned() & w4.owned()
            ),
            30,
            "the new worker to own its partitions and the other to have given them up",
        )
        time.sleep(2)
        cluster.servers[most_buffers_led(cluster)].kill()
        out, err = load.communicate(timeout=SECONDS + 30)
        burner.kill()
        assert load.returncode == 0, err
        sent = json.loads(out)
        assert len(sent) == STREAMS
        # each stream's last detection comes once it is idle (3 s), its owner flushing it as detect
        # ends a recording; later where its poses came late
        assert (
            each_once_as_detect(sent, lambda: nats.messages, 30, lost_to_the_kill(w1, killed_at, workers))
            > 3 * STREAMS
        )

        # takeovers: the first live pose of every partition of the killed and the stopped worker
        # that streams hash to (a partition with none has no pose to consume). The killed one's
        # lease runs out a TTL after its last keep-alive and etcd revokes it at its next check
        # (every 500 ms), on a loaded machine later still: measured from when the survivors saw it
        # gone, as the stopped one's from the signal
        used = {e["partition"] for w in workers for e in w.events("partition live")}
        gone = min(
            e["ts"]
            for w in workers
            for e in w.events("partitions")
            if e["ts"] > killed_at and "w1" not in e["members"]
        )
        assert gone - killed_at <= LEASE_S + 1.0, f"w1 seen gone {gone - killed_at:.2f} s after the kill"
        for owned, at in ((killed_owned, gone), (stopped_owned, stopped_at)):
            assert owned & used
            for p in owned & used:
                live = first_live_after(workers, p, at)
                assert live is not None, f"partition {p} was never consumed again"
                assert live - at <= 1.0, f"partition {p} taken {live - at:.2f} s after, more than 1 s"

        # the etcd member killed moved no partition: the workers paused at most, kept their leases,
        # and saw all three throughout (the leader evening the streams out may move some meanwhile)
        moved = [
            e
            for w in workers
            for e in w.events("partitions")
            if etcd_killed <= e["ts"] < killed_at and (e["members"] != ["w1", "w2", "w3"] or e["problem"])
        ]
        assert not moved, f"partitions moved when an etcd member was killed: {moved}"

        assert {d["id"] for d in mqtt.detections()} == {d["id"] for d in nats.messages}
        # the killed and the stopped worker's streams were resumed from checkpoints and recognised
        # on from their buffers: what the killed one had published since its last checkpoint was
        # computed again, with the same ids, and not published twice (each id once, above)
        survivors = (workers[2], workers[3])
        # every partition owned (read twice, one metrics page after the other, they may straddle a
        # move of the leader's balance, which gives up before it takes)
        wait_for(
            lambda: sum(w.metrics()["mocapd_cluster_partitions"] for w in survivors) == PARTITIONS,
            10,
            "the two workers to own every partition between them",
        )
        m = [w.metrics() for w in survivors]
        assert sum(x["mocapd_cluster_resumed_partitions_total"] for x in m) > 0
        assert [x["mocapd_cluster_members"] for x in m] == [2, 2]
        assert sum(x["mocapd_cluster_takeovers_total"] for x in m) > 0
        assert sum(x["mocapd_cluster_replayed_poses_total"] for x in m) > 0
        assert sum(x["mocapd_cluster_duplicates_suppressed_total"] for x in m) == sum(
            len(w.events("duplicate")) for w in workers[2:]
        )
        # the poses the killed server's buffers lost while they elected new leaders came through
        # the partitions' plain subscriptions
        assert sum(x["mocapd_cluster_unbuffered_total"] for x in m) > 0
    finally:
        for process in (load, burner):
            if process is not None and process.poll() is None:
                process.kill()
        for w in workers:
            w.stop(signal.SIGKILL)
        if mqtt is not None:
            mqtt.close()
        if nats is not None:
            nats.close()
        etcd.stop()
        cluster.stop()
