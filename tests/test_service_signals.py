"""How ``mocapd run`` takes SIGHUP, every part real (the daemon, its workers and the replays are
processes; the sockets are ZeroMQ's). SIGHUP, which a closed terminal or an operator expecting a
reload sends, is a graceful stop as SIGTERM is: intake stops, every pose received is recognised and
its detections published, "offline" goes out, a line is logged, exit 0; for one process, and for a
front whose whole process group is hung up (its workers leave the stop to it). A SIGHUP ignored
when the daemon starts (``nohup``) stays ignored, and one during start-up stops the command as
SIGTERM does. Before: SIGHUP killed the daemon at once, with no drain, no "offline" and no log line."""

from __future__ import annotations

import json
import os
import signal
from functools import cache
from pathlib import Path
from typing import Any

import pytest

from daemon.library import default_library_path, load_library
from daemon.recognizer import detect
from daemon.recordings import read_recording
from protocols.routing import worker_of
from replay import Motion
from tests.helpers import DATA, Daemon, ZmqCollector, detection_keys, replay, wait_for

CMU_13 = DATA / "cmu" / "13" / "13.asf"
LONG = (CMU_13, DATA / "cmu" / "13" / "13_29.amc.gz")
BIG_QUEUE: dict[str, dict[str, object]] = {"service": {"queue_frames": 100_000, "grace_s": 5}}


@cache
def expected(asf: Path, amc: Path, frames: int) -> list[dict[str, Any]]:
    """``mocapd detect``'s detections on the recording's first ``frames``."""
    motion = read_recording(asf, amc)
    motion = Motion(
        motion.source, motion.skeleton, motion.header, motion.frames[:frames], motion.channels[:frames]
    )
    return [d.as_json() for d in detect(motion, load_library(default_library_path()), 120.0)]


def json_lines(daemon: Daemon) -> list[dict[str, Any]]:
    """Every line the daemon wrote on stderr, each of which must be one JSON object."""
    lines = daemon.stderr_path.read_text().splitlines()
    return [json.loads(line) for line in lines]


def signals(logs: list[dict[str, Any]]) -> list[str]:
    return [e["signal"] for e in logs if e["event"] == "signal"]


def sighup_caught(pid: int) -> bool:
    """Whether the process has a handler for SIGHUP (its ``SigCgt`` in ``/proc``)."""
    status = Path(f"/proc/{pid}/status").read_text(encoding="ascii")
    caught = next(line.split()[1] for line in status.splitlines() if line.startswith("SigCgt:"))
    return bool(int(caught, 16) >> (signal.SIGHUP - 1) & 1)


@pytest.mark.slow
def test_sighup_drains_says_offline_and_logs_it(tmp_path: Path) -> None:
    daemon = Daemon(tmp_path, config=BIG_QUEUE).start()
    collector = ZmqCollector(daemon.detections)
    sender = replay(*LONG, "zmq+" + daemon.poses, speed="4")
    try:
        wait_for(lambda: daemon.metrics().get("mocapd_frames_in_total", 0) > 1500, 60, "poses flowing")
        daemon.signal(signal.SIGHUP)
        assert daemon.wait(timeout=30) == 0
        logs = json_lines(daemon)
        assert signals(logs) == ["SIGHUP"]
        received = next(e for e in logs if e["event"] == "stopping")["received"]["13_29"]
        want = detection_keys(expected(*LONG, received))
        assert len(want) >= 3
        assert detection_keys(daemon.detections_printed()) == want  # everything received, published
        wait_for(lambda: len(collector.detections()) == len(want), 10, "the published detections")
        statuses = [m["state"] for m in collector.messages if m.get("type") == "status"]
        assert statuses[-1:] == ["offline"]
        assert [e["clean"] for e in logs if e["event"] == "offline"] == [True]
    finally:
        sender.kill()
        sender.communicate()
        collector.close()
        daemon.stop()


@pytest.mark.slow
def test_a_hangup_of_its_process_group_stops_the_front_and_its_workers_gracefully(tmp_path: Path) -> None:
    """A closed terminal hangs up its whole job: the front and both workers get SIGHUP at once. The
    workers ignore it and the front stops them as on SIGTERM: every pose received is recognised and
    published, one "signal" line (the front's), every process "offline" and clean, exit 0."""
    names = ["h0", "h1", "h2", "h3"]
    assert {worker_of(n, 2) for n in names} == {0, 1}
    daemon = Daemon(tmp_path, config=BIG_QUEUE, workers=2).start(group=True)
    assert daemon.process is not None
    collector = ZmqCollector(daemon.detections)
    senders = [replay(*LONG, "zmq+" + daemon.poses, stream=n, speed="4") for n in names]
    try:
        pids = {e["worker"]: e["pid"] for e in json_lines(daemon) if e["event"] == "worker ready"}
        assert sorted(pids) == [0, 1]
        wait_for(lambda: daemon.metrics().get("mocapd_frames_in_total", 0) > 4 * 1000, 60, "poses flowing")
        os.killpg(daemon.process.pid, signal.SIGHUP)
        assert daemon.wait(timeout=30) == 0
        logs = json_lines(daemon)
        assert signals(logs) == ["SIGHUP"]
        assert not [e for e in logs if e["event"] == "worker exited"]
        assert [e["clean"] for e in logs if e["event"] == "offline"] == [True] * 3
        for name in names:
            received = next(
                e["received"][name]
                for e in logs
                if e["event"] == "stopping" and name in e.get("received", {})
            )
            mine = [d for d in daemon.detections_printed() if d["stream"] == name]
            assert detection_keys(mine) == detection_keys(expected(*LONG, received)), name
        wait_for(lambda: any(m.get("state") == "offline" for m in collector.messages), 10, "offline")
        for pid in pids.values():
            with pytest.raises(ProcessLookupError):
                os.kill(pid, 0)
    finally:
        for sender in senders:
            sender.kill()
            sender.communicate()
        collector.close()
        daemon.stop()


def test_a_sighup_ignored_when_it_starts_stays_ignored(tmp_path: Path) -> None:
    """``nohup mocapd run``: the SIGHUP it was started to survive changes nothing; SIGTERM then stops
    it, and only that is logged."""
    daemon = Daemon(tmp_path).start(command=["nohup"])
    try:
        daemon.signal(signal.SIGHUP)
        assert daemon.stop() == 0
        assert signals(json_lines(daemon)) == ["SIGTERM"]
    finally:
        daemon.stop()


def test_a_sighup_during_start_up_stops_it_as_sigterm_does(tmp_path: Path) -> None:
    """SIGHUP sent as soon as the command catches it (before the daemon serves, or just after): the
    command stops as SIGTERM would stop it then, with "mocapd: terminated" and 143 before it serves,
    drained with "offline" and 0 after; never killed by the signal."""
    daemon = Daemon(tmp_path).start(wait=False)
    assert daemon.process is not None
    pid = daemon.process.pid
    wait_for(lambda: not daemon.alive or sighup_caught(pid), 30, "SIGHUP caught", step=0.001)
    daemon.signal(signal.SIGHUP)
    status = daemon.wait(timeout=30)
    err = daemon.stderr_path.read_text()
    if status == 128 + signal.SIGTERM:
        assert err.splitlines()[-1] == "mocapd: terminated", err
        assert '"online"' not in err
    else:
        assert status == 0, err
        logs = json_lines(daemon)
        assert signals(logs) == ["SIGHUP"] and logs[-1]["event"] == "offline"
