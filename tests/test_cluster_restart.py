"""A cluster worker outlives what its servers do (real processes on loopback): a restart of its NATS
server (the server's memory streams and consumers are gone with it; the worker reconnects, makes them
again and goes on consuming its partitions), and an etcd that stops answering for less than a lease
(the worker pauses, keeps its partitions and every stream's state, and goes on). Either way a
recording replayed through it gives ``mocapd detect``'s detections."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import time
from collections.abc import Callable
from pathlib import Path

import pytest

from bench.processes import free_port, scrape
from daemon.library import default_library_path, load_library
from daemon.recognizer import detect
from daemon.recordings import read_recording
from replay import Motion
from tests.etcd_server import Etcd
from tests.helpers import (
    DATA,
    MOCAPD_SCRIPT,
    MqttCollector,
    cluster_worker,
    detection_keys,
    freeze,
    http_get,
    mocapd,
    stop_all,
    wait_for,
)
from tests.nats_server import NatsServer, partitions

REPO = Path(__file__).resolve().parents[1]
TRIAL = (DATA / "cmu" / "13" / "13.asf", DATA / "cmu" / "13" / "13_30.amc.gz")


def _expected() -> list[dict[str, object]]:
    """``mocapd detect``'s detections of :data:`TRIAL` as a cluster worker sees it replayed: the
    replay numbers its poses from the AMC's first frame, 1; cluster mode begins the motion at the
    first multiple of the decimation step, 4 (docs/cluster.md, rule 2)."""
    m = read_recording(*TRIAL)
    aligned = Motion(m.source, m.skeleton, m.header, m.frames[3:], m.channels[3:])
    assert aligned.frames[0] == 4
    return [d.as_json() for d in detect(aligned, load_library(default_library_path()), 120.0)]


@pytest.mark.slow
def test_a_worker_goes_on_after_the_nats_server_restarts(tmp_path: Path) -> None:
    (tmp_path / "nats").mkdir()
    (tmp_path / "etcd").mkdir()
    server = NatsServer(tmp_path / "nats").start()
    etcd = Etcd(tmp_path / "etcd").start()
    worker = cluster_worker(tmp_path, server.url, etcd.url, free_port())
    err = tmp_path / "worker.err"
    collector = None
    try:
        wait_for(lambda: '"partition taken"' in err.read_text(), 30, "the worker's partitions")
        server.stop()
        server.start()  # the same ports, its streams gone
        wait_for(
            lambda: err.read_text().count('"partition taken"') > partitions(), 30, "the partitions read again"
        )
        collector = MqttCollector(server.mqtt_url, ["mocap/+/detections"], client_id="restart-collector")
        result = mocapd(
            "replay", "--asf", TRIAL[0], "--amc", TRIAL[1], "--to", server.mqtt_url, "--speed", "4"
        )
        assert result.returncode == 0, result.stderr
        want = _expected()
        # the stream goes idle (2 s) and is flushed, as detect ends the recording
        wait_for(lambda: len(collector.detections()) >= len(want), 20, "the detections")
        assert detection_keys(collector.detections()) == detection_keys(want)
    finally:
        stop_all(collector, worker, etcd, server)


Disturb = Callable[[Etcd, int], None]
"""What happens to etcd while a recording plays through the worker (given its metrics port)."""


def _through_a_worker(tmp_path: Path, disturb: Disturb) -> tuple[dict[str, float], dict[str, float], str]:
    """:data:`TRIAL` replayed at twice its speed through one cluster worker, ``disturb`` called once
    600 of its poses are in: the worker's /metrics before and after it, and the worker's log. Its
    detections, as an MQTT client receives them, must be ``mocapd detect``'s, each once."""
    (tmp_path / "nats").mkdir()
    (tmp_path / "etcd").mkdir()
    server = NatsServer(tmp_path / "nats").start()
    etcd = Etcd(tmp_path / "etcd").start()
    port = free_port()
    worker = cluster_worker(tmp_path, server.url, etcd.url, port)
    err = tmp_path / "worker.err"
    collector = None
    replay = None
    try:
        wait_for(
            lambda: err.read_text().count('"partition taken"') == partitions(), 30, "the worker's partitions"
        )
        collector = MqttCollector(server.mqtt_url, ["mocap/+/detections"], client_id="etcd-collector")
        source = ["--asf", str(TRIAL[0]), "--amc", str(TRIAL[1])]
        replay = subprocess.Popen(
            [str(MOCAPD_SCRIPT), "replay", *source, "--to", server.mqtt_url, "--speed", "2"],
            stdout=subprocess.DEVNULL,
            stderr=subprocess.PIPE,
            env={**os.environ, "PYTHONPATH": str(REPO)},
        )
        wait_for(lambda: scrape(port).get("mocapd_frames_in_total", 0) > 600, 30, "the recording under way")
        before = scrape(port)
        disturb(etcd, port)
        _, stderr = replay.communicate(timeout=60)
        assert replay.returncode == 0, stderr
        want = _expected()
        wait_for(lambda: len(collector.detections()) >= len(want), 30, "the detections")
        time.sleep(0.5)
        got = collector.detections()
        assert len({d["id"] for d in got}) == len(got), "a detection delivered twice"
        assert detection_keys(got) == detection_keys(want)
        return before, scrape(port), err.read_text()
    finally:
        stop_all(replay, worker, collector, etcd, server)


@pytest.mark.slow
def test_a_worker_paused_by_an_etcd_that_does_not_answer_keeps_its_streams(tmp_path: Path) -> None:
    """etcd frozen (SIGSTOP) mid-recording until the worker says it has a problem (two thirds of its
    lease after its last answered keep-alive), then thawed: the worker paused (published nothing)
    but gave up no partition and no stream, re-read no buffer, and its detections are ``mocapd
    detect``'s. Before issue 34 it fenced itself by dropping every partition and re-reading every
    buffer, and the stream's history read again began mid-motion."""

    def pause_etcd(etcd: Etcd, port: int) -> None:
        assert etcd.process is not None
        freeze(etcd.process)
        try:
            wait_for(lambda: http_get(port, "/healthz")[0] == 503, 5, "the worker to pause")
            paused = time.monotonic()
        finally:
            etcd.process.send_signal(signal.SIGCONT)
        wait_for(lambda: http_get(port, "/healthz")[0] == 200, 5, "the worker to go on")
        assert time.monotonic() - paused < 2.0

    before, after, log = _through_a_worker(tmp_path, pause_etcd)
    for series in (
        'mocapd_stream_events_total{event="handed_over"}',
        "mocapd_cluster_replayed_poses_total",
        "mocapd_cluster_takeovers_total",
    ):
        assert after.get(series, 0) == before.get(series, 0), series
    assert log.count('"partition taken"') == partitions()


@pytest.mark.slow
def test_while_etcd_is_lost_nothing_is_published_and_afterwards_nothing_is_missing(tmp_path: Path) -> None:
    """Consistency over availability (docs/cluster.md, "When etcd is lost"): etcd killed mid-recording
    for 4 s, then started again on its data. The worker pauses, is out once its lease may have
    expired (it gives its partitions up: another worker could own them), publishes nothing from then
    until etcd answers, then owns its partitions again, reads their buffers and publishes what it
    recomputes: ``mocapd detect``'s detections, each once (those it had published are suppressed as
    duplicates by the store)."""
    window: list[float] = []

    def lose(etcd: Etcd, port: int) -> None:
        etcd.kill()
        killed = time.time()
        wait_for(lambda: http_get(port, "/healthz")[0] == 503, 5, "the worker to see etcd gone")
        time.sleep(4.0)
        window.extend((killed + 2.0 + 0.1, time.time()))  # out from a lease after the last answer
        etcd.start(True)
        wait_for(lambda: http_get(port, "/healthz")[0] == 200, 20, "the worker to be back")

    before, after, log = _through_a_worker(tmp_path, lose)
    out, back = window
    published = [json.loads(line) for line in log.splitlines() if '"event": "detection"' in line]
    assert not [d for d in published if out < d["ts"] < back], "published while etcd was lost"
    assert after['mocapd_stream_events_total{event="handed_over"}'] > before.get(
        'mocapd_stream_events_total{event="handed_over"}', 0
    )
    assert log.count('"partition taken"') == 2 * partitions()  # every partition given up and taken again
