"""Progress events end to end, every part real: a ``mocapd run`` process with progress enabled, fed
a real replay over ZeroMQ, publishes exactly the progress events ``mocapd detect --progress`` prints
for the same frames (every field but the times), each tick's before its detections, and the
detections stay ``detect``'s; the same through ``--workers 2``; over MQTT they are QoS 0 and not
retained; disabled, none is published and the table follows nothing."""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Any

import pytest

from daemon.config import ProgressConfig, ServiceConfig
from daemon.library import default_library_path, load_library
from daemon.recordings import read_recording
from daemon.service.streams import StreamTable
from protocols.messages import PoseMessage, ProgressMessage, SkeletonMessage
from tests.helpers import (
    DATA,
    Broker,
    Daemon,
    MqttCollector,
    ZmqCollector,
    finished,
    mocapd,
    replay,
    wait_for,
)

TRIAL = (DATA / "cmu" / "13" / "13.asf", DATA / "cmu" / "13" / "13_30.amc.gz")
FRAMES = 2465
ENABLED: dict[str, dict[str, object]] = {"service": {"queue_frames": 100_000}, "progress": {"enabled": True}}
"""Progress on; a queue long enough that a replay as fast as possible drops nothing."""


def key(m: dict[str, Any]) -> tuple[Any, ...]:
    """What must agree between the wire and ``detect --progress``: a progress event's every field
    but the times (the replay stamps its poses with the wall clock), a detection's all but the id."""
    if m["type"] == "progress":
        return ("progress", m["stream"], m["frame"], json.dumps(m["classes"], sort_keys=True))
    return (
        "detection",
        m["class"],
        m["start_frame"],
        m["end_frame"],
        m["cost"],
        m["tau"],
        m["emitted_at_frame"],
    )


def expected(asf: Path, amc: Path, stream: str) -> list[tuple[Any, ...]]:
    """``mocapd detect --progress --json`` run as a process: its lines, in its order."""
    result = mocapd("detect", "--asf", asf, "--amc", amc, "--progress", "--json", "--stream", stream)
    assert result.returncode == 0, result.stderr
    lines = [json.loads(line) for line in result.stdout.splitlines()]
    for m in lines:
        m.setdefault("type", "detection")
    return [key(m) for m in lines]


def published(messages: list[dict[str, Any]]) -> list[tuple[Any, ...]]:
    return [key(m) for m in messages if m.get("type") in ("progress", "detection")]


def run_replay(tmp_path: Path, workers: int) -> None:
    daemon = Daemon(tmp_path, config=ENABLED, workers=workers).start()
    collector = ZmqCollector(daemon.detections)
    try:
        want = expected(*TRIAL, "13_30")
        assert sum(k[0] == "progress" for k in want) > 100 and sum(k[0] == "detection" for k in want) > 5
        finished(replay(*TRIAL, "zmq+" + daemon.poses, speed="max"))
        wait_for(lambda: daemon.metrics().get("mocapd_frames_in_total") == FRAMES, 60, "every pose received")
        assert daemon.stop() == 0
        wait_for(lambda: len(published(collector.messages)) >= len(want), 10, "the last messages")
        assert published(collector.messages) == want
        assert published(daemon.printed()) == want  # the stdout sink prints them in the same order
        progress = [m for m in collector.messages if m.get("type") == "progress"]
        assert all(m["source_time"] > 0 and m["emit_time"] >= m["source_time"] for m in progress)
        assert progress[-1]["classes"] == []  # the end of the stream: nothing under way
    finally:
        collector.close()
        daemon.stop()


def test_zeromq_replay_gives_the_progress_of_detect(tmp_path: Path) -> None:
    run_replay(tmp_path, 1)


def test_two_workers_give_the_progress_of_detect(tmp_path: Path) -> None:
    """Through the front: the workers tell it each message's kind of delivery."""
    run_replay(tmp_path, 2)


@pytest.mark.slow
def test_over_mqtt_progress_is_qos_0_and_not_retained(tmp_path: Path) -> None:
    broker = Broker(tmp_path).start()
    daemon = Daemon(tmp_path, sources=("mqtt",), sinks=("mqtt",), mqtt=broker.url, config=ENABLED).start()
    collector = MqttCollector(broker.url, ["mocap/+/progress", "mocap/+/detections"], client_id="progress")
    try:
        finished(replay(*TRIAL, broker.url, speed="4"))
        wait_for(lambda: daemon.metrics().get("mocapd_frames_in_total") == FRAMES, 60, "every pose received")
        assert daemon.stop() == 0
        wait_for(lambda: any(m.get("type") == "detection" for m in collector.detections()), 10, "detections")
        with collector.lock:
            how = list(zip(collector.messages, collector.qos, strict=True))
        progress = [(t, m) for (t, m), _ in how if m.get("type") == "progress"]
        assert progress and all(t == "mocap/13_30/progress" for t, _ in progress)
        # delivered as published (the subscription asks QoS 1): progress QoS 0, detections QoS 1
        assert {q for (_, m), q in how if m.get("type") == "progress"} == {(0, False)}
        assert {q for (_, m), q in how if m.get("type") == "detection"} == {(1, False)}
        assert [m["frame"] for _, m in progress] == sorted(m["frame"] for _, m in progress)
        late = MqttCollector(broker.url, ["mocap/+/progress"], client_id="late")
        try:
            time.sleep(0.5)
            assert late.messages == []  # nothing retained
        finally:
            late.close()
    finally:
        collector.close()
        daemon.stop()
        broker.stop()


def test_disabled_publishes_nothing_and_follows_nothing() -> None:
    """Progress off (the default): no stream is followed, no class stage is watched, and a whole
    recording through the table gives detections and nothing else."""
    motion = read_recording(*TRIAL)
    library = load_library(default_library_path())
    got = {}
    for enabled in (False, True):
        table = StreamTable(
            library,
            session="t",
            service=ServiceConfig(queue_frames=100_000),
            progress=ProgressConfig(enabled=enabled),
        )
        table.skeleton(SkeletonMessage("s", 120.0, asf=TRIAL[0].read_text(), angle_unit="rad"), 0.0)
        assert (table.streams["s"].progress is None) == (not enabled)
        assert (table.bank["s"].stage.watch is None) == (not enabled)
        out = []
        for number, channels in zip(motion.frames.tolist(), motion.channels, strict=True):
            table.pose(PoseMessage("s", number, 1.0 + number / 120, channels=channels), 1.0 + number / 120)
            out += table.tick()[0]
        out += table.flush_all()
        got[enabled] = out
    assert not any(isinstance(e.message, ProgressMessage) for e in got[False])
    assert sum(isinstance(e.message, ProgressMessage) for e in got[True]) > 100
    # the detections are the same either way
    assert [e.message for e in got[False]] == [
        e.message for e in got[True] if not isinstance(e.message, ProgressMessage)
    ]
