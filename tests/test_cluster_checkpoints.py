"""Checkpoints (docs/cluster.md "Checkpoints"): a partition's new owner resumes its streams from
the states its checkpoint holds and reads only the buffer after it, after a kill -9 (the last
periodic checkpoint) and after a SIGTERM (the checkpoint the leaving worker stores last), and the
detections are still ``mocapd detect``'s, each once."""

from __future__ import annotations

import asyncio
import contextlib
import json
import signal
import subprocess
import time
from pathlib import Path
from typing import Any

import msgpack
import nats
import pytest
from nats.js.errors import KeyNotFoundError

from bench.cluster_load import RECORDINGS, stream_id
from bench.processes import free_port, scrape
from daemon.cluster.ring import owned
from protocols.nats import CHECKPOINTS, partition_of
from tests.etcd_server import Etcd
from tests.helpers import (
    MqttCollector,
    cluster_load,
    cluster_worker,
    each_once_as_detect,
    log_events,
    stop_all,
    wait_for,
)
from tests.nats_server import NatsServer, partitions

REPO = Path(__file__).resolve().parents[1]

STREAMS = 2
RATE = 120.0


def _checkpointed(url: str, names: list[str]) -> set[str]:
    """Those of streams ``names`` whose partition's stored checkpoint holds their state."""

    async def read() -> set[str]:
        nc = await nats.connect(url)
        try:
            kv = await nc.jetstream().key_value(CHECKPOINTS)
            found = set()
            for name in names:
                with contextlib.suppress(KeyNotFoundError):
                    entry = await kv.get(str(partition_of(name, partitions())))
                    if name in msgpack.unpackb(entry.value or b"\x80").get("streams", {}):
                        found.add(name)
            return found
        finally:
            await nc.close()

    return asyncio.run(read())


def _each_once_as_detect(load: subprocess.Popen[str], collector: MqttCollector) -> tuple[dict[str, Any], int]:
    """Once ``load`` has ended: the detections ``collector`` received are ``mocapd detect``'s on
    what it sent, each once (:func:`tests.helpers.each_once_as_detect`). What it sent, and how many
    detections that is."""
    out, err = load.communicate(timeout=60)
    assert load.returncode == 0, err
    sent: dict[str, Any] = json.loads(out)
    return sent, each_once_as_detect(sent, collector.detections, 40)


@pytest.mark.slow
def test_a_new_owner_reads_the_buffer_from_the_checkpoint_and_misses_nothing(tmp_path: Path) -> None:
    """One worker with a 120 s buffer recognises two streams looping real recordings; once it has
    stored checkpoints it is killed (-9) and a second worker takes its partitions: it resumes their
    streams from the checkpoints and reads each buffer from after its checkpoint (not the whole
    buffer), and the detections both published, as an MQTT client receives them, are ``mocapd
    detect``'s, each once."""
    for d in ("nats", "etcd", "w1", "w2"):
        (tmp_path / d).mkdir()
    server = NatsServer(tmp_path / "nats").start()
    etcd = Etcd(tmp_path / "etcd").start()
    settings = {"partitions": partitions(), "buffer_s": 120, "checkpoint_s": 1}
    ports = [free_port(), free_port()]
    first = cluster_worker(tmp_path / "w1", server.url, etcd.url, ports[0], settings)
    second = load = collector = None
    try:
        wait_for(
            lambda: len(log_events(tmp_path / "w1" / "worker.err", "partition taken")) == partitions(),
            30,
            "w1",
        )
        collector = MqttCollector(server.mqtt_url, ["mocap/+/detections"], client_id="checkpoint-collector")
        load = cluster_load(server.mqtt_url, STREAMS, 30, RATE)
        names = [stream_id(i, RECORDINGS[i][1]) for i in range(STREAMS)]
        wait_for(lambda: _checkpointed(server.url, names) == set(names), 30, "checkpoints of the streams")
        first.send_signal(signal.SIGKILL)
        first.wait(10)
        killed = time.time()
        second = cluster_worker(tmp_path / "w2", server.url, etcd.url, ports[1], settings)
        sent, total = _each_once_as_detect(load, collector)
        assert total > 2 * STREAMS

        used = {partition_of(stream, partitions()) for stream in sent}
        taken = [
            e for e in log_events(tmp_path / "w2" / "worker.err", "partition taken") if e["partition"] in used
        ]
        assert taken and all(e["from"] > 1 and e["ts"] > killed for e in taken), taken
        m = scrape(ports[1])
        assert m["mocapd_cluster_resumed_partitions_total"] == len(used)
        # what it read of the buffers is what followed the checkpoints, not all they held
        assert 0 < m["mocapd_cluster_replayed_poses_total"] < sum(e["buffered"] for e in taken)
    finally:
        stop_all(load, first, second, collector, etcd, server)


@pytest.mark.slow
@pytest.mark.exclusive  # a handover raced against SIGTERM: once 0 checkpoints of 2 beside another test
def test_a_worker_hands_its_streams_over_in_their_state_to_a_joiner_and_when_told_to_stop(
    tmp_path: Path,
) -> None:
    """Four streams looping real recordings on one worker, a; a second worker, b, joins: a stores
    the last checkpoint of each partition it gives b, and b resumes those streams from it; then
    SIGTERM to a: it takes nothing more in, stores the last checkpoint of each partition it
    recognised, and b resumes those streams too. Each time b reads less than a second of the taken
    streams' poses from the buffers, and the detections are ``mocapd detect``'s, each once."""
    for d in ("nats", "etcd", "a", "b"):
        (tmp_path / d).mkdir()
    server = NatsServer(tmp_path / "nats").start()
    etcd = Etcd(tmp_path / "etcd").start()
    streams = 4
    names = [stream_id(i, RECORDINGS[i][1]) for i in range(streams)]
    mine = owned("a", {"a", "b"}, partitions())
    leaving = [n for n in names if partition_of(n, partitions()) in mine]
    joined = [n for n in names if n not in leaving]
    assert leaving and joined  # both workers recognise some
    ports = [free_port(), free_port()]
    # the ring alone (no balance): a and b own what owned() says
    settings = {"partitions": partitions(), "buffer_s": 60, "checkpoint_s": 1, "balance_s": 0}
    a = cluster_worker(tmp_path / "a", server.url, etcd.url, ports[0], settings | {"member": "a"})
    b = load = collector = None
    a_log, b_log = tmp_path / "a" / "worker.err", tmp_path / "b" / "worker.err"
    try:
        everything = partitions()
        wait_for(lambda: len(log_events(a_log, "partition taken")) == everything, 30, "a")
        collector = MqttCollector(server.mqtt_url, ["mocap/+/detections"], client_id="handover-collector")
        load = cluster_load(server.mqtt_url, streams, 30, RATE)
        wait_for(lambda: _checkpointed(server.url, names) == set(names), 30, "a's checkpoints")
        time.sleep(3.0)  # poses past the periodic checkpoints: the joiner's is the hand-over's
        b = cluster_worker(tmp_path / "b", server.url, etcd.url, ports[1], settings | {"member": "b"})
        share = partitions() - len(mine)
        wait_for(lambda: len(log_events(b_log, "partition taken")) == share, 30, "b")
        time.sleep(4.0)
        at_join = scrape(ports[1])
        a.send_signal(signal.SIGTERM)
        assert a.wait(10) == 0
        termed = time.time()
        _, total = _each_once_as_detect(load, collector)
        assert total > len(names)

        given = {partition_of(n, partitions()) for n in joined}
        (gave,) = [e for e in log_events(a_log, "partitions") if e["lost"]]
        assert gave["checkpoints"] == len(given)
        (handed,) = log_events(a_log, "handed over")
        used = {partition_of(n, partitions()) for n in leaving}
        assert handed["checkpoints"] == len(used)
        taken = log_events(b_log, "partition taken")
        for partitions_, after in ((given, 0.0), (used, termed - 1)):
            these = [e for e in taken if e["partition"] in partitions_ and e["ts"] > after]
            assert len(these) == len(partitions_) and all(e["from"] > 1 for e in these), these
        m = scrape(ports[1])
        assert m["mocapd_cluster_resumed_partitions_total"] == len(given) + len(used)
        assert at_join["mocapd_cluster_replayed_poses_total"] < RATE * len(joined)
        replayed = m["mocapd_cluster_replayed_poses_total"] - at_join["mocapd_cluster_replayed_poses_total"]
        assert replayed < RATE * len(leaving)
        assert m.get('mocapd_rejects_total{reason="state"}', 0) == 0
    finally:
        stop_all(load, a, b, collector, etcd, server)
