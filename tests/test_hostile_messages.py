"""Issue 32: one message must never stop the daemon. A 1 KB pose or skeleton whose ``v``, ``type`` or
``epoch`` is a list nested 1,000 deep made the refusal's repr raise RecursionError, which the intake
did not catch: the single process exited 70, a worker died and was restarted (losing its streams'
poses), and the same message retained on a skeleton topic put an MQTT daemon in a restart loop. Every
part real: the daemon, its workers and the replay are processes, the broker a mosquitto on loopback.
And any other exception one message sets off costs that message only (``rejects{reason="internal"}``)."""

from __future__ import annotations

import logging
import time
from functools import cache
from pathlib import Path
from typing import Any

import msgpack
import numpy as np
import paho.mqtt.client as paho
import pytest
from paho.mqtt.enums import CallbackAPIVersion

from daemon.config import Config
from daemon.library import default_library_path, load_library
from daemon.recognizer import detect
from daemon.recordings import read_recording
from daemon.service.app import Service
from daemon.service.streams import Pose
from protocols.messages import PoseMessage, SkeletonMessage, encode
from protocols.transport import Incoming
from replay import JOINT_NAMES
from tests.helpers import DATA, Broker, Daemon, detection_keys, finished, raw_publisher, replay, wait_for

TRIAL = (DATA / "cmu" / "13" / "13.asf", DATA / "cmu" / "13" / "13_30.amc.gz")
BIG_QUEUE: dict[str, dict[str, object]] = {"service": {"queue_frames": 100_000}}


def nested(depth: int) -> Any:
    value: Any = []
    for _ in range(depth - 1):
        value = [value]
    return value


def hostile(stream: str) -> list[tuple[bytes, bytes]]:
    """(topic, payload) of the messages that killed the daemon, on ``stream``'s topics: about 1 KB each."""
    pose: dict[str, Any] = msgpack.unpackb(
        encode(PoseMessage(stream, 1, 0.0, positions=np.zeros((len(JOINT_NAMES), 3), np.float32))), raw=False
    )
    skeleton: dict[str, Any] = msgpack.unpackb(encode(SkeletonMessage(stream, 120.0, JOINT_NAMES)), raw=False)
    deep = nested(1000)
    bodies = [
        (f"mocap/{stream}/pose", {**pose, "v": deep}),
        (f"mocap/{stream}/pose", {**pose, "type": deep}),
        (f"mocap/{stream}/pose", {**pose, "epoch": deep}),
        (f"mocap/{stream}/skeleton", {**skeleton, "epoch": deep}),
        (f"mocap/{stream}/skeleton", {**skeleton, "type": deep}),
    ]
    return [(t.encode(), msgpack.packb(b, use_bin_type=True)) for t, b in bodies]


@cache
def expected() -> list[tuple[Any, ...]]:
    motion = read_recording(*TRIAL)
    return detection_keys([d.as_json() for d in detect(motion, load_library(default_library_path()), 120.0)])


def rejected(m: dict[str, float]) -> float:
    return sum(v for k, v in m.items() if k.startswith("mocapd_rejects_total{"))


@pytest.mark.slow
@pytest.mark.parametrize("workers", [1, 2])
def test_nested_values_beside_a_good_stream_stop_nothing(tmp_path: Path, workers: int) -> None:
    """The messages that killed the daemon, before and throughout a replay on the replayed stream's
    own topics: the daemon (and every worker) lives, each is refused and counted, none is an
    internal error, and the stream's detections are exactly ``mocapd detect``'s."""
    daemon = Daemon(tmp_path, config=BIG_QUEUE, workers=workers).start()
    try:
        with raw_publisher(daemon.poses) as sock:
            bad = hostile("good")
            for frames in bad:
                sock.send_multipart(frames)
            sent = len(bad)
            running = replay(*TRIAL, "zmq+" + daemon.poses, stream="good", speed="4")
            while running.poll() is None:
                for frames in bad:
                    sock.send_multipart(frames)
                sent += len(bad)
                time.sleep(0.25)
            finished(running)
            wait_for(
                lambda: daemon.metrics().get("mocapd_frames_in_total") == 2465, 60, "every pose received"
            )
            wait_for(lambda: rejected(daemon.metrics()) >= sent, 10, "every hostile message refused")
            m = daemon.metrics()
            assert daemon.alive
            assert rejected(m) == sent and m.get('mocapd_rejects_total{reason="internal"}', 0) == 0
            if workers > 1:
                assert sum(v for k, v in m.items() if k.startswith("mocapd_worker_restarts_total")) == 0
                assert m.get('mocapd_drops_total{reason="worker_down"}', 0) == 0
            assert daemon.stop() == 0
            assert detection_keys(daemon.detections_printed()) == expected()
            assert not [e for e in daemon.logs() if e["level"] == "error"]
    finally:
        daemon.stop()


@pytest.mark.slow
def test_a_retained_nested_skeleton_does_not_stop_an_mqtt_daemon(tmp_path: Path) -> None:
    """The message retained on a skeleton topic reaches every daemon that starts: it is refused,
    and the daemon serves on (it exited 70 2.8 s after every start)."""
    broker = Broker(tmp_path).start()
    client = paho.Client(CallbackAPIVersion.VERSION2, client_id="hostile")
    client.connect("127.0.0.1", broker.port)
    client.loop_start()
    try:
        skeletons = [p for n, p in hostile("evil") if n.endswith(b"/skeleton")]
        for k, payload in enumerate(skeletons * 2):  # a topic retains one message: a stream each
            client.publish(f"mocap/evil{k}/skeleton", payload, qos=1, retain=True).wait_for_publish(10)
        daemon = Daemon(tmp_path, sources=["mqtt"], sinks=["stdout"], mqtt=broker.url).start()
        try:
            wait_for(lambda: rejected(daemon.metrics()) >= 4, 10, "the retained skeletons refused")
            time.sleep(3.0)
            assert daemon.alive and daemon.health()[0] == 200
            assert daemon.metrics()['mocapd_rejects_total{reason="schema"}'] == 4
            assert daemon.stop() == 0
        finally:
            daemon.stop()
    finally:
        client.loop_stop()
        client.disconnect()
        broker.stop()


class _Broken(Exception):
    """What the stream table below raises: a defect no real message can set off any more."""


def test_an_exception_one_message_sets_off_costs_that_message_only(caplog: pytest.LogCaptureFixture) -> None:
    """Whatever one message sets off is counted as ``internal`` and logged, and the next message
    is taken in as before: the intake's loop never sees it. The table is made to fail on one
    stream's poses (fault injection: the decoder's recursion was the last real case)."""
    library = load_library(default_library_path())
    logger = logging.getLogger("mocapd.test")
    service = Service(Config(), library, [], instance="t", version="0", logger=logger)
    take_pose = service.table.pose

    def pose(message: Pose, now: float) -> None:
        if message.stream == "cursed":
            raise _Broken("a defect")
        take_pose(message, now)

    service.table.pose = pose  # type: ignore[method-assign]
    frame = np.zeros((len(JOINT_NAMES), 3), np.float32)
    for stream in ("cursed", "fine"):
        service.receive(
            Incoming(f"mocap/{stream}/skeleton", encode(SkeletonMessage(stream, 120.0, JOINT_NAMES)), 0.0)
        )
    with caplog.at_level(logging.WARNING, logger="mocapd.test"):
        for seq in range(3):
            for stream in ("cursed", "fine"):
                payload = encode(PoseMessage(stream, seq, 0.0, positions=frame))
                assert service.receive(Incoming(f"mocap/{stream}/pose", payload, 0.0)) == []
    assert service.rejects == {"internal": 3}
    assert service.table.streams["fine"].received == 3 and service.table.streams["cursed"].received == 0
    warned = [r for r in caplog.records if getattr(r, "fields", {}).get("reason") == "internal"]
    assert warned and warned[0].fields["detail"] == "_Broken: a defect"  # type: ignore[attr-defined]
