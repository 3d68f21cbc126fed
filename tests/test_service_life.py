"""A stream's life through a real daemon (issue 21): a replay run twice back to back is two runs of
its stream, each giving ``mocapd detect``'s detections; a daemon restarted under a running replay,
and a stream silent longer than ``service.idle_s``, are recognised again within seconds (the replay
re-announces its skeleton when the daemon's subscription reaches it and every second). Real daemon
and replay processes, real ZeroMQ sockets."""

from __future__ import annotations

import signal
import time
from pathlib import Path

import pytest

from daemon.library import default_library_path, load_library
from daemon.recognizer import detect
from daemon.recordings import read_recording
from tests.helpers import (
    DATA,
    Daemon,
    ZmqCollector,
    detection_keys,
    finished,
    hdm05_clip,
    replay,
    takes,
    wait_for,
)

TRIAL = (DATA / "cmu" / "13" / "13.asf", DATA / "cmu" / "13" / "13_30.amc.gz")
BIG_QUEUE: dict[str, dict[str, object]] = {"service": {"queue_frames": 100_000}}
SQUAT = hdm05_clip("bd", "squat1Reps", takes("squat1Reps", "bd")[0])


@pytest.mark.slow
def test_a_replay_run_twice_is_two_runs_of_its_stream(tmp_path: Path) -> None:
    """Before: the second run was refused out_of_order to the end ("seq 1 after 2465")."""
    daemon = Daemon(tmp_path, config=BIG_QUEUE).start()
    collector = ZmqCollector(daemon.detections)
    try:
        for n in (2465, 2 * 2465):
            finished(replay(*TRIAL, "zmq+" + daemon.poses, stream="again"))
            wait_for(lambda: daemon.metrics().get("mocapd_frames_in_total") == n, 30, "every pose")  # noqa: B023
        assert daemon.stop() == 0
        once = [
            d.as_json() for d in detect(read_recording(*TRIAL), load_library(default_library_path()), 120.0)
        ]
        want = detection_keys([{**d, "stream": "again"} for d in once]) * 2
        wait_for(lambda: len(collector.detections()) >= len(want), 10, "the last detections")
        assert detection_keys(collector.detections()) == want
        ids = [d["id"] for d in collector.detections()]
        assert len(set(ids)) == len(ids)
        logs = daemon.logs()
        assert not any(e.get("reason") == "out_of_order" for e in logs)
    finally:
        collector.close()
        daemon.stop()


def first_detection_after(collector: ZmqCollector, since: float, timeout: float) -> float:
    """Seconds from ``since`` (time.time()) to the first detection emitted after it."""

    def found() -> bool:
        return any(d["emit_time"] > since for d in collector.detections())

    wait_for(found, timeout, "a detection after the disruption")
    first: float = min(d["emit_time"] for d in collector.detections() if d["emit_time"] > since)
    return first - since


@pytest.mark.slow
def test_a_restarted_daemon_learns_a_running_replay_again(tmp_path: Path) -> None:
    """Restart the daemon under ``mocapd replay --loop`` (squats, in real time): the new daemon's
    subscription reaches the replay, which announces its skeleton again; squats are detected again
    within a squat or two. Before: every later pose was refused no_skeleton, for ever."""
    daemon = Daemon(tmp_path).start()
    collector = ZmqCollector(daemon.detections)
    source = replay(*SQUAT, "zmq+" + daemon.poses, "--loop", stream="loop", speed="1")
    try:
        first_detection_after(collector, time.time(), 20)
        assert daemon.stop() == 0
        daemon.start()
        back = time.time()
        delay = first_detection_after(collector, back, 20)
        assert delay < 6.0, delay  # a squat is 1.2 s long; the skeleton comes back at once
        assert daemon.metrics().get('mocapd_rejects_total{reason="no_skeleton"}', 0) <= 120
    finally:
        source.terminate()
        source.wait(10)
        collector.close()
        daemon.stop()


@pytest.mark.slow
def test_a_stream_silent_longer_than_idle_comes_back(tmp_path: Path) -> None:
    """The replay stopped for 3 s with ``service.idle_s`` 1: the daemon forgets the stream, and when
    the replay goes on, its next announcement brings the stream back. Before: no_skeleton for ever.
    The stream's per-stream series go with it and come back with it (before: kept for ever)."""
    config: dict[str, dict[str, object]] = {
        "service": {"idle_s": 1, "max_streams": 10},
        "metrics": {"stream_labels": True},
    }
    daemon = Daemon(tmp_path, config=config).start()
    series = 'mocapd_frames_in_total{stream="pause"}'
    collector = ZmqCollector(daemon.detections)
    source = replay(*SQUAT, "zmq+" + daemon.poses, "--loop", stream="pause", speed="1")
    try:
        first_detection_after(collector, time.time(), 20)
        source.send_signal(signal.SIGSTOP)
        wait_for(
            lambda: daemon.metrics().get('mocapd_stream_events_total{event="idle"}', 0) >= 1, 10, "evicted"
        )
        wait_for(lambda: series not in daemon.metrics(), 5, "the stream's series gone")
        source.send_signal(signal.SIGCONT)
        resumed = time.time()
        delay = first_detection_after(collector, resumed, 20)
        assert delay < 6.0, delay
        assert daemon.metrics()[series] > 0
    finally:
        source.send_signal(signal.SIGCONT)
        source.terminate()
        source.wait(10)
        collector.close()
        daemon.stop()
