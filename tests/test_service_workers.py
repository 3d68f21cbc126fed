"""``mocapd run --workers 2`` end to end, every part real (the daemon, its workers and the replays are
processes; the sockets are ZeroMQ's): each stream's detections are exactly ``mocapd detect``'s, each
stream on the worker :func:`protocols.routing.worker_of` names; a worker killed with SIGKILL is
started again and learns its streams from publishers that announce only when asked; SIGTERM stops
the front and every worker cleanly; workers whose front is gone stop by themselves; whatever escapes
a worker is one JSON line on stderr, never a traceback."""

from __future__ import annotations

import dataclasses
import json
import os
import signal
import socket
import threading
import time
from functools import cache
from pathlib import Path
from typing import Any

import msgpack
import pytest
import zmq

from daemon.library import default_library_path, load_library
from daemon.recognizer import detect
from daemon.recordings import read_recording
from protocols.messages import PoseMessage, encode, topic
from protocols.publish import messages
from protocols.routing import worker_of
from tests.helpers import (
    DATA,
    Broker,
    Daemon,
    MqttCollector,
    ZmqCollector,
    detection_keys,
    finished,
    hdm05_clip,
    mocapd,
    raw_publisher,
    replay,
    takes,
    wait_for,
)

CMU_13 = DATA / "cmu" / "13" / "13.asf"
TRIAL = (CMU_13, DATA / "cmu" / "13" / "13_30.amc.gz")
BIG_QUEUE: dict[str, dict[str, object]] = {"service": {"queue_frames": 100_000}}


@cache
def expected(asf: Path, amc: Path) -> list[dict[str, Any]]:
    """``mocapd detect``'s detections (the batch twin) on the recording."""
    return [
        d.as_json() for d in detect(read_recording(asf, amc), load_library(default_library_path()), 120.0)
    ]


def unique(items: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """First arrivals only (QoS 1 may deliver a detection twice; the id says which)."""
    seen: set[str] = set()
    out = []
    for d in items:
        if d["id"] not in seen:
            seen.add(d["id"])
            out.append(d)
    return out


def gone(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return True
    return False


def worker_pids(daemon: Daemon) -> dict[int, int]:
    """The pid of each worker, the last it said it was ready with."""
    return {e["worker"]: e["pid"] for e in daemon.logs() if e["event"] == "worker ready"}


@pytest.mark.slow
def test_two_workers_give_each_stream_the_detections_of_detect(tmp_path: Path) -> None:
    sources = [
        TRIAL,
        (DATA / "cmu" / "02" / "02.asf", DATA / "cmu" / "02" / "02_05.amc.gz"),
        (DATA / "cmu" / "86" / "86.asf", DATA / "cmu" / "86" / "86_01.amc.gz"),
        hdm05_clip("bd", "squat1Reps", takes("squat1Reps", "bd")[0]),
        hdm05_clip("bk", "hopBothLegs1hops", takes("hopBothLegs1hops", "bk")[1]),
        TRIAL,  # the same recording as another stream
    ]
    names = [f"s{k}" for k in range(len(sources))]
    assert {worker_of(n, 2) for n in names} == {0, 1}  # both workers have streams
    daemon = Daemon(tmp_path, config=BIG_QUEUE, workers=2).start()
    collector = ZmqCollector(daemon.detections)
    try:
        pids = worker_pids(daemon)
        assert sorted(pids) == [0, 1] and daemon.metrics()["mocapd_workers"] == 2
        running = [
            replay(asf, amc, "zmq+" + daemon.poses, stream=n, speed="4")
            for n, (asf, amc) in zip(names, sources, strict=True)
        ]
        for p in running:
            finished(p)
        total = sum(len(read_recording(asf, amc)) for asf, amc in sources)
        wait_for(lambda: daemon.metrics().get("mocapd_frames_in_total") == total, 60, "every pose received")
        assert daemon.stop() == 0
        got = daemon.detections_printed()
        for name, (asf, amc) in zip(names, sources, strict=True):
            mine = [d for d in got if d["stream"] == name]
            assert detection_keys(mine) == detection_keys(expected(asf, amc)), name
        assert sum(len(expected(a, m)) for a, m in sources) > 20  # not a vacuous comparison
        taken = {e["stream"]: e["worker"] for e in daemon.logs() if e["event"] == "skeleton"}
        assert taken == {n: worker_of(n, 2) for n in names}
        wait_for(lambda: len(collector.detections()) == len(got), 10, "the published detections")
        statuses = [m for m in collector.messages if m.get("type") == "status"]
        assert statuses[-1]["state"] == "offline" and statuses[-1]["streams"] == 0  # every replay ended
        assert all(gone(pid) for pid in pids.values())  # SIGTERM stopped every worker
        assert [e["clean"] for e in daemon.logs() if e["event"] == "offline"] == [True] * 3
    finally:
        collector.close()
        daemon.stop()


@pytest.mark.slow
def test_two_workers_behind_mqtt(tmp_path: Path) -> None:
    """Over MQTT the front is the one client: both streams, on both workers, get detect's
    detections, published on the broker."""
    names = ["m0", "m1"]
    assert sorted(worker_of(n, 2) for n in names) == [0, 1]
    broker = Broker(tmp_path).start()
    daemon = Daemon(
        tmp_path, sources=["mqtt"], sinks=["mqtt"], mqtt=broker.url, config=BIG_QUEUE, workers=2
    ).start()
    collector = MqttCollector(broker.url, ["mocap/+/detections", "mocapd/+/status"])
    try:
        wait_for(lambda: any(s["state"] == "online" for s in collector.statuses()), 10, "the retained online")
        for p in [replay(*TRIAL, broker.url, stream=n, speed="8") for n in names]:
            finished(p)
        wait_for(
            lambda: daemon.metrics().get("mocapd_frames_in_total") == 2 * 2465, 60, "every pose received"
        )
        assert daemon.stop() == 0
        want = detection_keys(expected(*TRIAL))
        for name in names:

            def arrived(n: str = name) -> bool:
                return len({d["id"] for d in collector.detections() if d["stream"] == n}) >= len(want)

            wait_for(arrived, 10, f"the detections of {name}")
            mine = unique([d for d in collector.detections() if d["stream"] == name])
            assert detection_keys(mine) == want, name
        wait_for(lambda: collector.statuses()[-1]["state"] == "offline", 10, "offline")
    finally:
        collector.close()
        daemon.stop()
        broker.stop()


class AskedPublisher:
    """A stream looped at ``speed`` times 120 Hz from an XPUB socket that announces the skeleton
    only when a subscription reaches it (never by itself), so a restarted worker learns the stream
    only if the front's renewed subscription gets through."""

    def __init__(self, endpoint: str, asf: Path, amc: Path, stream: str, speed: float) -> None:
        self.ctx = zmq.Context()
        self.sock = self.ctx.socket(zmq.XPUB)
        self.sock.setsockopt(zmq.SNDHWM, 1_000_000)
        self.sock.setsockopt(zmq.LINGER, 0)
        self.sock.connect(endpoint)
        motion = read_recording(asf, amc)
        self.items = messages(motion, asf.read_text(), stream, 120.0, None, epoch="e1")
        self.skeleton = next(self.items)
        self.interval = 1 / (120.0 * speed)
        self.announced = 0
        self.running = True
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    def _announce(self) -> None:
        self.sock.send_multipart([topic(self.skeleton).encode(), encode(self.skeleton)])
        self.announced += 1

    def _run(self) -> None:
        start, i = time.monotonic(), 0
        while self.running:
            while self.sock.poll(0):
                if self.sock.recv()[:1] == b"\x01":
                    self._announce()
            if not self.announced:
                time.sleep(0.01)
                continue
            pose = next(self.items)
            assert isinstance(pose, PoseMessage)
            pose = dataclasses.replace(pose, time=time.time())
            self.sock.send_multipart([topic(pose).encode(), encode(pose)])
            i += 1
            time.sleep(max(0.0, start + i * self.interval - time.monotonic()))

    def close(self) -> None:
        self.running = False
        self.thread.join(5)
        self.sock.close()
        self.ctx.term()


@pytest.mark.slow
def test_a_killed_worker_is_restarted_and_its_stream_resumes(tmp_path: Path) -> None:
    daemon = Daemon(tmp_path, workers=2).start()
    stream = "studio-a"
    victim = worker_of(stream, 2)
    publisher = AskedPublisher(daemon.poses, *TRIAL, stream=stream, speed=4)
    try:
        wait_for(lambda: len(daemon.detections_printed()) >= 2, 60, "the first detections")
        pid = worker_pids(daemon)[victim]
        asked = publisher.announced
        os.kill(pid, signal.SIGKILL)
        killed = time.time()
        wait_for(lambda: worker_pids(daemon).get(victim, pid) != pid, 30, "the worker started again")
        wait_for(lambda: daemon.health()[0] == 200, 10, "healthy again")
        m = daemon.metrics()
        assert m[f'mocapd_worker_restarts_total{{worker="{victim}"}}'] == 1
        assert m[f'mocapd_worker_up{{worker="{victim}"}}'] == 1
        exited = [e for e in daemon.logs() if e["event"] == "worker exited"]
        assert [(e["worker"], e["status"]) for e in exited] == [(victim, -signal.SIGKILL)]
        wait_for(
            lambda: any(d["emit_time"] > killed for d in daemon.detections_printed()),
            60,
            "a detection of the stream after the restart",
        )
        assert publisher.announced > asked  # the front asked: the restarted worker learned the stream
        assert {d["stream"] for d in daemon.detections_printed()} == {stream}
        pids = worker_pids(daemon)
        assert daemon.stop() == 0
        assert all(gone(p) for p in pids.values())
    finally:
        publisher.close()
        daemon.stop()


@pytest.mark.slow
def test_workers_stop_when_their_front_is_killed(tmp_path: Path) -> None:
    daemon = Daemon(tmp_path, workers=2).start()
    pids = worker_pids(daemon)
    assert len(pids) == 2
    daemon.signal(signal.SIGKILL)
    daemon.wait(10)
    wait_for(lambda: all(gone(p) for p in pids.values()), 15, "the orphaned workers to stop")


def test_a_front_that_cannot_bind_fails_at_once(tmp_path: Path) -> None:
    """An address in use ends ``run --workers 2`` as it ends one process: status 2, one line naming
    the setting, no worker started."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen()
        endpoint = f"tcp://127.0.0.1:{s.getsockname()[1]}"
        config = tmp_path / "daemon.yaml"
        config.write_text(json.dumps({"zmq": {"poses": endpoint}, "metrics": {"port": 0}}), encoding="utf-8")
        result = mocapd("--config", config, "run", "--workers", "2", timeout=30)
    assert result.returncode == 2, result.stderr
    assert result.stderr.splitlines()[-1] == f"mocapd: zmq.poses: {endpoint}: address already in use"
    assert '"worker ready"' not in result.stderr


def test_workers_must_be_a_count() -> None:
    """From none (0: one per core) to 4 per core: 500 workers on 2 cores once started, took 54 s to
    stop and exited 1 (issue 32)."""
    cores = len(os.sched_getaffinity(0))
    bound = f"must be 0 (one per core) to {4 * cores} (4 per core, {cores} available)"
    for workers in (-1, 4 * cores + 1, 500):
        result = mocapd("run", "--workers", str(workers))
        assert result.returncode == 2
        assert result.stderr == f"mocapd: --workers: {bound}, got {workers}\n"


@pytest.mark.slow
def test_what_the_front_cannot_route_whole_is_refused_and_counted_once(tmp_path: Path) -> None:
    """A message that is not ``[topic, payload]`` and one whose payload is not msgpack pass the front
    undecoded and are refused by a worker as the single process refuses them; ``/metrics`` sums
    the workers' counts."""
    daemon = Daemon(tmp_path, workers=2).start()
    try:
        with raw_publisher(daemon.poses, linger_ms=1000) as sock:
            sock.send_multipart([b"mocap/x/pose", b"a", b"b"])
            sock.send_multipart([b"mocap/y/pose", b"\xc1 not msgpack"])
            sock.send_multipart([b"mocap/z/pose"])
            wait_for(
                lambda: daemon.metrics().get('mocapd_rejects_total{reason="undecodable"}') == 3,
                10,
                "three undecodable messages counted",
            )
            assert daemon.stop() == 0
    finally:
        daemon.stop()


@pytest.mark.slow
def test_a_second_signal_ends_the_front_and_its_workers_at_once(tmp_path: Path) -> None:
    """The first SIGTERM has a worker recognising a long backlog (recognition in slices of one tick
    falls behind intake on any machine); the second ends every process there."""
    service = {"queue_frames": 1_000_000, "grace_s": 120, "tick_budget_ms": 0.001}
    daemon = Daemon(tmp_path, config={"service": service}, workers=2).start()
    pids = worker_pids(daemon)
    sender = replay(
        CMU_13, DATA / "cmu" / "13" / "13_29.amc.gz", "zmq+" + daemon.poses, "--loop", speed="max"
    )
    try:
        wait_for(lambda: daemon.metrics().get("mocapd_queued_poses", 0) > 20_000, 60, "a backlog")
        daemon.signal(signal.SIGTERM)
        wait_for(lambda: any(e["event"] == "stopping" for e in daemon.logs()), 10, "the shutdown begun")
        assert daemon.alive and not all(gone(p) for p in pids.values())  # still recognising the backlog
        daemon.signal(signal.SIGTERM)
        assert daemon.wait(timeout=5) == 128 + signal.SIGTERM
        wait_for(lambda: all(gone(p) for p in pids.values()), 5, "every worker gone")
    finally:
        sender.kill()
        sender.communicate()
        daemon.stop()


def nested(depth: int) -> list[Any]:
    """A list ``depth`` lists deep."""
    out: list[Any] = []
    for _ in range(depth):
        out = [out]
    return out


def stderr_lines(daemon: Daemon) -> list[dict[str, Any]]:
    """Every line on the daemon's stderr (its workers' too), each of which must be a JSON object:
    while it runs, a last line not yet written whole is left; once it has ended, none may be."""
    text = daemon.stderr_path.read_text()
    assert daemon.alive or not text or text.endswith("\n"), text[-200:]
    return [json.loads(line) for line in text.splitlines(keepends=True) if line.endswith("\n")]


@pytest.mark.slow
def test_a_worker_that_cannot_read_its_setup_says_so_in_one_json_line(tmp_path: Path) -> None:
    """A worker started again after its setup file was removed (a temporary-file cleaner at work
    under a long-running daemon) fails at once: one JSON line says why, with the traceback in a field,
    it exits 70 and the front tries again. Before: a multi-line Python traceback on the daemon's
    stderr each time."""
    temporary = tmp_path / "tmp"
    temporary.mkdir()
    daemon = Daemon(tmp_path, workers=2, env={"TMPDIR": str(temporary)}).start()
    try:
        (setup,) = temporary.glob("mocapd-workers-*/setup.pickle")
        setup.unlink()
        os.kill(worker_pids(daemon)[1], signal.SIGKILL)

        def exits() -> set[tuple[int, int]]:
            return {(e["worker"], e["status"]) for e in daemon.logs() if e["event"] == "worker exited"}

        wait_for(lambda: (1, 70) in exits(), 30, "the restarted worker's failure")
        assert daemon.alive
        lines = stderr_lines(daemon)
        failed = [e for e in lines if e["event"] == "internal error"]
        assert failed and all(e["worker"] == 1 and e["level"] == "critical" for e in failed)
        assert failed[0]["exception"].startswith("FileNotFoundError: ")
        assert failed[0]["error"].startswith("Traceback (most recent call last):")
        assert "setup.pickle" in failed[0]["error"]
        daemon.stop()
        stderr_lines(daemon)  # to the end
    finally:
        daemon.stop()


@pytest.mark.slow
def test_a_message_that_breaks_a_worker_leaves_only_json_on_stderr(tmp_path: Path) -> None:
    """A pose whose ``v`` is a list 1000 deep (issue 32: it made the decoder raise RecursionError)
    sent to ``run --workers 2``: whatever the worker makes of it, every line on stderr is one JSON
    object, and the daemon serves on. Before: the worker's traceback, dozens of lines."""
    daemon = Daemon(tmp_path, workers=2).start()
    try:
        with raw_publisher(daemon.poses, linger_ms=1000) as sock:
            body = {"v": nested(1000), "type": "pose", "stream": "deep", "seq": 1, "time": 1.0}
            sock.send_multipart([b"mocap/deep/pose", msgpack.packb(body)])

            def handled() -> bool:  # the worker failed and was started again, or refused the message
                logs = daemon.logs()
                return any(e["event"] == "worker exited" for e in logs) or any(
                    e["event"] == "refused" and e["stream"] == "deep" for e in logs
                )

            wait_for(handled, 30, "the nested message handled")
            wait_for(lambda: daemon.health()[0] == 200, 30, "serving again")
            lines = stderr_lines(daemon)
            failed = [e for e in lines if e["event"] == "internal error"]
            assert all(e["worker"] == worker_of("deep", 2) for e in failed)
            assert daemon.stop() == 0
            stderr_lines(daemon)  # to the end
    finally:
        daemon.stop()
