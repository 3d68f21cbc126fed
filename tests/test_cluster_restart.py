"""A cluster worker outlives a restart of its NATS server (real processes on loopback): the server's
memory streams and consumers are gone with it; the worker reconnects, makes them again and goes on
consuming its partitions, so a recording replayed after the restart gives ``mocapd detect``'s
detections."""

from __future__ import annotations

import json
import os
import subprocess
from pathlib import Path

import pytest

from bench.processes import free_port
from daemon.library import default_library_path, load_library
from daemon.recognizer import detect
from daemon.recordings import read_recording
from replay import Motion
from tests.etcd_server import Etcd
from tests.helpers import DATA, MOCAPD_SCRIPT, MqttCollector, detection_keys, mocapd, wait_for
from tests.nats_server import NatsServer

REPO = Path(__file__).resolve().parents[1]
TRIAL = (DATA / "cmu" / "13" / "13.asf", DATA / "cmu" / "13" / "13_30.amc.gz")


@pytest.mark.slow
def test_a_worker_goes_on_after_the_nats_server_restarts(tmp_path: Path) -> None:
    (tmp_path / "nats").mkdir()
    (tmp_path / "etcd").mkdir()
    server = NatsServer(tmp_path / "nats").start()
    etcd = Etcd(tmp_path / "etcd").start()
    config = tmp_path / "worker.yaml"
    config.write_text(
        json.dumps({"service": {"idle_s": 2}, "metrics": {"port": free_port()}}), encoding="utf-8"
    )
    err = tmp_path / "worker.err"
    with err.open("wb") as log:
        worker = subprocess.Popen(
            [
                str(MOCAPD_SCRIPT),
                "--config",
                str(config),
                "run",
                "--cluster",
                server.url,
                "--coordinator",
                etcd.url,
            ],
            stdout=subprocess.DEVNULL,
            stderr=log,
            env={**os.environ, "PYTHONPATH": str(REPO)},
        )
    collector = None
    try:
        wait_for(lambda: '"partition taken"' in err.read_text(), 30, "the worker's partitions")
        server.stop()
        server.start()  # the same ports, its streams gone
        wait_for(lambda: err.read_text().count('"partition taken"') > 16, 30, "the partitions read again")
        collector = MqttCollector(server.mqtt_url, ["mocap/+/detections"], client_id="restart-collector")
        result = mocapd(
            "replay", "--asf", TRIAL[0], "--amc", TRIAL[1], "--to", server.mqtt_url, "--speed", "4"
        )
        assert result.returncode == 0, result.stderr
        # the replay numbers its poses from the AMC's first frame, 1; cluster mode begins the motion
        # at the first multiple of the decimation step, 4 (docs/cluster.md, rule 2)
        m = read_recording(*TRIAL)
        aligned = Motion(m.source, m.skeleton, m.header, m.frames[3:], m.channels[3:])
        assert aligned.frames[0] == 4
        want = [d.as_json() for d in detect(aligned, load_library(default_library_path()), 120.0)]
        # the stream goes idle (2 s) and is flushed, as detect ends the recording
        wait_for(lambda: len(collector.detections()) >= len(want), 20, "the detections")
        assert detection_keys(collector.detections()) == detection_keys(want)
    finally:
        if collector is not None:
            collector.close()
        worker.kill()
        worker.wait(10)
        etcd.stop()
        server.stop()
