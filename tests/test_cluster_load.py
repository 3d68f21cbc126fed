"""A cluster worker under load keeps what it owns (issue 34's acceptance): with two CPU-bound
processes beside it on the two cores, a worker recognising 12 looping streams never gives a
partition up while it lives and its lease is valid, and its detections are ``mocapd detect``'s."""

from __future__ import annotations

import json
import subprocess
from pathlib import Path

import pytest

from bench.processes import free_port, scrape
from tests.etcd_server import Etcd
from tests.helpers import (
    NatsCollector,
    burner,
    cluster_load,
    cluster_worker,
    detection_keys,
    log_events,
    looped_detections,
    stop_all,
    wait_for,
)
from tests.nats_server import NatsServer, partitions

REPO = Path(__file__).resolve().parents[1]
STREAMS = 12
SECONDS = 25.0
RATE = 60.0


@pytest.mark.slow
@pytest.mark.exclusive  # a bound in real time: no other test beside it under xdist
def test_a_worker_beside_two_cpu_bound_processes_keeps_its_partitions(tmp_path: Path) -> None:
    (tmp_path / "nats").mkdir()
    (tmp_path / "etcd").mkdir()
    server = NatsServer(tmp_path / "nats").start()
    etcd = Etcd(tmp_path / "etcd").start()
    port = free_port()
    worker = cluster_worker(tmp_path, server.url, etcd.url, port, {"partitions": partitions()})
    log = tmp_path / "worker.err"
    burners: list[subprocess.Popen[bytes]] = []
    load = collector = None
    try:
        wait_for(lambda: len(log_events(log, "partition taken")) == partitions(), 30, "the partitions")
        collector = NatsCollector(server.url)
        burners = [burner(), burner()]
        load = cluster_load(server.url, STREAMS, SECONDS, RATE)
        out, err = load.communicate(timeout=SECONDS + 60)
        assert load.returncode == 0, err
        sent = json.loads(out)
        want = {s: detection_keys(looped_detections(x["asf"], x["amc"], x["last"])) for s, x in sent.items()}
        total = sum(len(w) for w in want.values())
        wait_for(lambda: len(collector.messages) >= total, 60, "the detections")  # idle streams flushed
        stop_all(*burners)
        changes = log_events(log, "partitions")
        assert len(changes) == 1 and changes[0]["lost"] == [], changes  # the first assignment only
        m = scrape(port)
        assert m.get('mocapd_stream_events_total{event="handed_over"}', 0) == 0
        assert m["mocapd_cluster_partitions"] == partitions()
        got = collector.messages
        assert len({d["id"] for d in got}) == len(got)
        for stream, keys in want.items():
            assert sorted(detection_keys([d for d in got if d["stream"] == stream])) == sorted(keys), stream
        assert total > STREAMS
    finally:
        stop_all(load, *burners, worker, collector, etcd, server)
