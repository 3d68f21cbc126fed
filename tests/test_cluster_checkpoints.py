"""Checkpoints (``daemon/cluster/checkpoints.py``, docs/cluster.md "Checkpoints"): the choice of a
partition's checkpoint against its definition, and a takeover end to end that reads the buffer from
the checkpoint, not from its start, and still gives ``mocapd detect``'s detections, each once."""

from __future__ import annotations

import asyncio
import contextlib
import json
import signal
import time
from collections import Counter
from pathlib import Path

import nats
import pytest
from hypothesis import given
from hypothesis import strategies as st
from nats.js.errors import KeyNotFoundError

from bench.cluster_load import RECORDINGS, stream_id
from bench.processes import free_port, scrape
from daemon.cluster.checkpoints import Fed, Sample, far_enough, resume_after
from protocols.nats import CHECKPOINTS, partition_of
from tests.etcd_server import Etcd
from tests.helpers import (
    MqttCollector,
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

RUNS = [(0, None), (0, "a"), (1, "a")]
feds = st.builds(Fed, st.sampled_from(RUNS), st.integers(-1, 60))
progress = st.dictionaries(st.sampled_from("xyz"), feds, max_size=3)


@given(
    st.lists(st.tuples(st.integers(1, 5), progress), max_size=8),
    progress,
    st.integers(0, 30),
)
def test_the_checkpoint_is_the_newest_sample_every_stream_lies_far_enough_after(
    steps: list[tuple[int, dict[str, Fed]]], now: dict[str, Fed], need: int
) -> None:
    samples, position = [], 0
    for step, fed in steps:
        position += step
        samples.append(Sample(position, fed))
    needs = dict.fromkeys(now, need)

    def after(sample: Sample) -> bool:
        """Every stream of now: not in the sample's table or made anew since (a skeleton after
        it), or fed ``need`` frames of the same run since."""
        for s, f in now.items():
            then = sample.fed.get(s)
            if then is None or then.run[0] != f.run[0]:
                continue
            if then.run != f.run or f.seq - then.seq < need or then.seq > f.seq:
                return False
        return True

    found = [x for x in samples if after(x)]
    assert resume_after(samples, now, needs) == (found[-1] if found else None)


def test_a_stream_lies_after_a_sample_once_made_anew_or_fed_enough_of_the_same_run() -> None:
    then = Fed((3, "e1"), 500)
    assert not far_enough(then, Fed((3, "e1"), 600), 101)
    assert far_enough(then, Fed((3, "e1"), 601), 101)
    assert far_enough(then, Fed((4, "e1"), 10), 101)  # made anew by a skeleton after the sample
    assert far_enough(None, Fed((3, "e1"), 10), 101)  # not in the table then
    # a new run or numbering without a new skeleton: its skeleton lies before the sample
    assert not far_enough(then, Fed((3, "e2"), 5000), 101)
    assert not far_enough(then, Fed((3, "e1"), 10), 101)
    # in the table with nothing fed (its skeleton read before the sample), then fed enough
    assert not far_enough(Fed((3, "e1"), -1), Fed((3, "e1"), -1), 101)
    assert far_enough(Fed((3, "e1"), -1), Fed((3, "e1"), 100), 101)


STREAMS = 2
RATE = 360.0
"""Poses per second per stream: three times the recordings' 120 Hz, so that the streams are fed
the twice-a-warm-up a checkpoint needs (35 s of frames with the shipped library) in 12 s."""


def _fed_before(url: str, names: list[str]) -> set[str]:
    """Those of streams ``names`` whose partition's stored checkpoint lies after their run began."""

    async def read() -> set[str]:
        nc = await nats.connect(url)
        try:
            kv = await nc.jetstream().key_value(CHECKPOINTS)
            found = set()
            for name in names:
                with contextlib.suppress(KeyNotFoundError):
                    entry = await kv.get(str(partition_of(name, partitions())))
                    if name in json.loads(entry.value or b"{}")["runs"]:
                        found.add(name)
            return found
        finally:
            await nc.close()

    return asyncio.run(read())


@pytest.mark.slow
def test_a_new_owner_reads_the_buffer_from_the_checkpoint_and_misses_nothing(tmp_path: Path) -> None:
    """One worker with a 120 s buffer recognises two streams looping real recordings at three times
    their speed; once it has stored checkpoints it is killed (-9) and a second worker takes its
    partitions: it reads each from after its checkpoint (not the whole buffer), and the detections
    both published, as an MQTT client receives them, are ``mocapd detect``'s, each once."""
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
        wait_for(
            lambda: _fed_before(server.url, names) == set(names), 30, "checkpoints past the streams' starts"
        )
        first.send_signal(signal.SIGKILL)
        first.wait(10)
        killed = time.time()
        second = cluster_worker(tmp_path / "w2", server.url, etcd.url, ports[1], settings)
        out, err = load.communicate(timeout=60)
        assert load.returncode == 0, err
        sent = json.loads(out)
        want = {
            stream: detection_keys(looped_detections(s["asf"], s["amc"], s["last"]))
            for stream, s in sent.items()
        }
        total = sum(len(w) for w in want.values())
        wait_for(lambda: len(collector.detections()) >= total, 40, "the detections")
        time.sleep(1.0)
        got = collector.detections()
        assert not [i for i, n in Counter(d["id"] for d in got).items() if n > 1], "a detection twice"
        for stream in sent:
            assert sorted(detection_keys([d for d in got if d["stream"] == stream])) == sorted(want[stream])
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
