"""The leader's balance (docs/cluster.md, "Balance") with real workers, etcd and nats-server: streams
the ring alone spreads unevenly over three workers are evened out to within a fifth of the mean
(here exactly) while they play, with a CPU-bound process beside them, and the partitions moved on
the way lose and repeat no detection."""

from __future__ import annotations

import json
import time
from collections import Counter
from pathlib import Path

import pytest

from bench.cluster_load import RECORDINGS, stream_id
from bench.processes import free_port
from daemon.cluster.ring import assignment, loads, spread
from daemon.service.cluster import measured, rebalance
from daemon.service.membership import Balance, read_cluster
from protocols.nats import partition_of
from tests.etcd_server import Etcd
from tests.helpers import (
    MqttCollector,
    burner,
    cluster_load,
    cluster_worker,
    each_once_as_detect,
    log_events,
    stop_all,
    wait_for,
)
from tests.nats_server import NatsServer, partitions

STREAMS = 12
SECONDS = 25.0
RATE = 60.0


def _reported(coordinator: str) -> dict[str, int]:
    """The streams each live member reports holding."""
    status = read_cluster(coordinator)
    return {
        m.name: sum((m.status or {}).get("streams", {}).values())
        for m in status.members
        if m.status is not None
    }


@pytest.mark.slow
def test_the_leader_evens_the_streams_out_and_every_detection_comes_once(tmp_path: Path) -> None:
    count = partitions()
    weights = Counter(
        partition_of(stream_id(i, RECORDINGS[i % len(RECORDINGS)][1]), count) for i in range(STREAMS)
    )
    # three member names that the ring alone gives streams further than a fifth from the mean
    trio = next(
        names
        for names in (tuple(f"{c}{k}" for c in "abc") for k in range(1000))
        if spread(loads(assignment(names, count), weights)) > 0.2
    )
    assert spread(loads(assignment(trio, count, weights), weights)) == 0
    for d in ("nats", "etcd"):
        (tmp_path / d).mkdir()
    server = NatsServer(tmp_path / "nats").start()
    etcd = Etcd(tmp_path / "etcd").start()
    settings = {"partitions": count, "buffer_s": 60, "checkpoint_s": 1, "balance_s": 1}
    workers = []
    collector = load = heat = None
    try:
        for name in trio:
            (tmp_path / name).mkdir()
            workers.append(
                cluster_worker(
                    tmp_path / name, server.url, etcd.url, free_port(), settings | {"member": name}
                )
            )
        logs = [tmp_path / name / "worker.err" for name in trio]
        wait_for(
            lambda: sum(len(log_events(log, "partition taken")) for log in logs) >= count,
            30,
            "the three workers to own every partition",
        )
        collector = MqttCollector(server.mqtt_url, ["mocap/+/detections"], client_id="balance-collector")
        load = cluster_load(server.mqtt_url, STREAMS, SECONDS, RATE)
        heat = burner()
        started = time.monotonic()
        leader = logs[0]  # the smallest name
        wait_for(lambda: bool(log_events(leader, "balanced")), SECONDS, "the leader to even the streams out")
        wait_for(
            lambda: sorted(_reported(etcd.url).values()) == [STREAMS // 3] * 3,
            SECONDS - (time.monotonic() - started),
            "every worker to report a third of the streams",
        )
        (first, *_) = log_events(leader, "balanced")
        assert spread(first["before"]) > 0.2 and spread(first["after"]) < spread(first["before"]), first
        assert read_cluster(etcd.url).balance.generation >= 1
        out, err = load.communicate(timeout=SECONDS + 30)
        assert load.returncode == 0, err
        each_once_as_detect(json.loads(out), collector.detections, 30)
    finally:
        stop_all(heat, load, *workers, collector, etcd, server)


def test_the_leader_measures_only_once_every_member_owns_by_the_current_balance() -> None:
    members = frozenset({"a", "b"})
    statuses = {
        "a": {"generation": 3, "streams": {"1": 2, "4": 1, "x": 5}},
        "b": {"generation": 3, "streams": {"4": 2, "7": 0}},  # 4 handed over between two reports
        "gone": {"generation": 2, "streams": {"9": 9}},
    }
    assert measured(statuses, members, 3) == {1: 2, 4: 2}
    assert measured(statuses, members, 4) is None  # not owned by yet
    assert measured(statuses, members | {"c"}, 3) is None  # c has not reported


def test_the_leader_writes_a_new_balance_only_past_a_fifth_and_when_it_helps() -> None:
    members = frozenset({"a", "b", "c"})
    ring = assignment(members, 64)
    # all the streams on a's partitions: far past a fifth, and evening out helps
    skewed = {p: 1 for p in sorted(ring["a"])[:9]}
    new = rebalance(members, 64, Balance(2, {}), skewed)
    assert new == Balance(3, skewed)
    assert rebalance(members, 64, new, skewed) is None  # even by it already
    # one stream in one partition: no assignment can do better than the ring
    assert rebalance(members, 64, Balance(), {0: 1}) is None
