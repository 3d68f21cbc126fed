"""``zmq.relay_per_s``: the daemon passes each stream's skeleton and every (rate / relay_per_s)-th
pose on, unchanged, on its ZeroMQ detections socket, for viewers that cannot hear ZeroMQ publishers
(``mocapd view``); one process and ``--workers 2`` alike, never onto MQTT or stdout, and nothing
when it is 0 (the default). Every part real: the daemon, the replays, mosquitto, the sockets."""

from __future__ import annotations

from collections import defaultdict
from pathlib import Path
from typing import Any

import pytest

from daemon.recordings import read_recording
from protocols.routing import worker_of
from tests.helpers import (
    DATA,
    Broker,
    Daemon,
    MqttCollector,
    ZmqCollector,
    detection_keys,
    finished,
    replay,
    wait_for,
)

CMU_13 = DATA / "cmu" / "13" / "13.asf"
TRIAL = (CMU_13, DATA / "cmu" / "13" / "13_30.amc.gz")
OTHER = (DATA / "cmu" / "02" / "02.asf", DATA / "cmu" / "02" / "02_05.amc.gz")
BIG_QUEUE = {"queue_frames": 100_000}


def relayed(collector: ZmqCollector, kind: str) -> dict[str, list[dict[str, Any]]]:
    """The relayed messages of ``kind`` (``pose`` or ``skeleton``) by stream, in arrival order."""
    out: dict[str, list[dict[str, Any]]] = defaultdict(list)
    for m in list(collector.messages):
        if m.get("type") == kind:
            out[m["stream"]].append(m)
    return out


def run(tmp_path: Path, workers: int, relay: float, streams: dict[str, tuple[Path, Path]]) -> tuple[Any, ...]:
    broker = Broker(tmp_path).start()
    daemon = Daemon(
        tmp_path,
        sinks=("zmq", "mqtt", "stdout"),
        mqtt=broker.url,
        config={"service": BIG_QUEUE, "zmq": {"relay_per_s": relay}},
        workers=workers,
    ).start()
    collector = ZmqCollector(daemon.detections)
    on_broker = MqttCollector(broker.url, ["mocap/+/pose", "mocap/+/skeleton"], client_id="relay-watch")
    try:
        for p in [replay(asf, amc, "zmq+" + daemon.poses, stream=n) for n, (asf, amc) in streams.items()]:
            finished(p)
        total = sum(len(read_recording(asf, amc)) for asf, amc in streams.values())
        wait_for(lambda: daemon.metrics().get("mocapd_frames_in_total") == total, 60, "every pose taken in")
        assert daemon.stop() == 0
        wait_for(
            lambda: any(m.get("type") == "status" and m["state"] == "offline" for m in collector.messages),
            10,
            "the daemon's last message",
        )
        return collector, on_broker, daemon
    finally:
        collector.close()
        on_broker.close()
        daemon.stop()
        broker.stop()


@pytest.mark.parametrize("workers", [1, pytest.param(2, marks=pytest.mark.slow)])
def test_skeletons_and_every_fourth_pose_are_relayed_unchanged(tmp_path: Path, workers: int) -> None:
    streams = {"s0": TRIAL, "s2": OTHER}
    if workers == 2:
        assert {worker_of(n, 2) for n in streams} == {0, 1}
    collector, on_broker, daemon = run(tmp_path, workers, 30.0, streams)
    poses, skeletons = relayed(collector, "pose"), relayed(collector, "skeleton")
    assert sorted(poses) == sorted(skeletons) == sorted(streams)
    for name, (asf, amc) in streams.items():
        motion = read_recording(asf, amc)
        assert skeletons[name][0]["asf"] == asf.read_text() and skeletons[name][0]["rate"] == 120.0
        seqs = [p["seq"] for p in poses[name]]
        assert seqs == list(range(seqs[0], seqs[0] + 4 * len(seqs), 4))  # 30 of 120 a second
        assert abs(len(seqs) - len(motion) / 4) <= 1
    assert [m for m in on_broker.messages if m[0].endswith(("/pose", "/skeleton"))] == []
    assert not [m for m in daemon.printed() if m.get("type") in ("pose", "skeleton")]
    assert detection_keys(daemon.detections_printed())  # recognition went on as ever


@pytest.mark.slow
def test_nothing_is_relayed_by_default(tmp_path: Path) -> None:
    collector, _, daemon = run(tmp_path, 1, 0.0, {"s0": TRIAL})
    assert relayed(collector, "pose") == relayed(collector, "skeleton") == {}
    assert len(daemon.detections_printed()) == len(collector.detections()) > 0
