"""Bad input on both transports, sent by a real process's socket beside a good stream: every kind of
bad message is counted on /metrics under its reason and logged once, the daemon neither crashes nor
grows, and the good stream keeps exactly its detections."""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Any

import msgpack
import numpy as np
import pytest
import zmq

from daemon.library import default_library_path, load_library
from daemon.recognizer import detect
from daemon.recordings import read_recording
from protocols.messages import PoseMessage, SkeletonMessage, encode
from replay import JOINT_NAMES
from tests.helpers import DATA, Broker, Daemon, detection_keys, finished, replay, wait_for

GOOD = (DATA / "cmu" / "13" / "13.asf", DATA / "cmu" / "13" / "13_30.amc.gz")
POSE = np.zeros((len(JOINT_NAMES), 3), dtype=np.float32)


def raw(body: dict[str, Any]) -> bytes:
    out: bytes = msgpack.packb(body, use_bin_type=True)
    return out


def pose(stream: str, seq: int, positions: np.ndarray = POSE) -> bytes:
    return encode(PoseMessage(stream, seq, time.time(), positions=positions))


def bad_messages() -> list[tuple[str, bytes, str]]:
    """(topic, payload, the reason it is counted under)."""
    skeleton = encode(SkeletonMessage("bad-a", 120.0, JOINT_NAMES))
    body = {"v": 1, "type": "pose", "stream": "bad-a", "seq": 1, "time": 0.0, "positions": POSE.tobytes()}
    return [
        ("mocap/bad-a/skeleton", skeleton, ""),  # fine: the bad stream exists
        ("mocap/bad-a/pose", b"\x00\xff garbage", "undecodable"),
        ("mocap/bad-a/pose", raw({**body, "v": 9}), "version"),
        ("mocap/bad-a/pose", raw({**body, "type": "posture"}), "type"),
        ("mocap/bad-a/pose", raw({**body, "positions": np.full(78, np.nan, "<f4").tobytes()}), "non_finite"),
        ("mocap/bad-a/pose", raw({**body, "pad": b"x" * 70_000}), "oversize"),
        ("mocap/bad-a/pose", raw({k: v for k, v in body.items() if k != "seq"}), "schema"),
        ("mocap/bad-a/pose", pose("bad-a", 10), ""),
        ("mocap/bad-a/pose", pose("bad-a", 10), "duplicate"),
        ("mocap/bad-a/pose", pose("bad-a", 4), "out_of_order"),
        ("mocap/bad-a/pose", pose("bad-a", 11, POSE[:10]), "shape"),  # 10 joints, 26 announced
        ("mocap/bad-b/pose", pose("bad-b", 1), "no_skeleton"),
        ("mocap/bad-a/detections", pose("bad-a", 12), "topic"),  # MQTT: not subscribed, never arrives
        ("mocap/bad-a/skeleton", encode(SkeletonMessage("bad-a", 120.0, tuple(reversed(JOINT_NAMES)))), ""),
        ("mocap/bad-a/pose", pose("bad-a", 100), ""),  # after the change: a new stream, any start
        ("mocap/bad-a/pose", pose("bad-a", 200), ""),  # a gap
        ("mocap/bad-c/skeleton", encode(SkeletonMessage("bad-c", 120.0, ("a", "b"))), "skeleton"),
        ("mocap/bad-d/skeleton", b"", ""),  # MQTT's way to clear a retained skeleton: nothing refused
    ]


class ZmqSender:
    def __init__(self, endpoint: str) -> None:
        self.ctx = zmq.Context()
        self.sock = self.ctx.socket(zmq.XPUB)
        self.sock.setsockopt(zmq.SNDHWM, 1_000_000)
        self.sock.setsockopt(zmq.LINGER, 5000)
        self.sock.connect(endpoint)
        assert self.sock.poll(10_000), "the daemon did not subscribe"
        self.sock.recv()

    def send(self, topic: str, payload: bytes) -> None:
        self.sock.send_multipart([topic.encode(), payload])

    def close(self) -> None:
        self.sock.close()
        self.ctx.term()


class MqttSender:
    def __init__(self, url: str) -> None:
        import paho.mqtt.client as paho
        from paho.mqtt.enums import CallbackAPIVersion

        host, port = url.removeprefix("mqtt://").split(":")
        self.client = paho.Client(CallbackAPIVersion.VERSION2, client_id="bad-sender")
        self.client.max_queued_messages_set(0)
        self.client.connect(host, int(port))
        self.client.loop_start()
        self.last: Any = None

    def send(self, topic: str, payload: bytes) -> None:
        self.last = self.client.publish(topic, payload, qos=1)

    def close(self) -> None:
        if self.last is not None:
            self.last.wait_for_publish(30)
        self.client.loop_stop()
        self.client.disconnect()


def rss_kib(pid: int) -> int:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1])
    raise AssertionError("no VmRSS")


@pytest.mark.slow
@pytest.mark.parametrize("transport", ["zmq", "mqtt"])
def test_bad_input_is_counted_and_spoils_nothing(tmp_path: Path, transport: str) -> None:
    broker = Broker(tmp_path).start() if transport == "mqtt" else None
    daemon = Daemon(
        tmp_path,
        sources=[transport],
        sinks=["stdout"],
        mqtt=broker.url if broker else None,
        config={"service": {"queue_frames": 100_000, "max_message_bytes": 65536}, "mqtt": {"queue": 100_000}},
    ).start()
    assert daemon.process is not None
    sender: ZmqSender | MqttSender = ZmqSender(daemon.poses) if transport == "zmq" else MqttSender(broker.url)  # type: ignore[union-attr]
    to = "zmq+" + daemon.poses if transport == "zmq" else broker.url  # type: ignore[union-attr]
    try:
        good = replay(*GOOD, to, stream="good", speed="8")
        for topic, payload, _ in bad_messages():
            sender.send(topic, payload)
        reasons = [r for _, _, r in bad_messages() if r and not (r == "topic" and transport == "mqtt")]
        if isinstance(sender, ZmqSender):  # not [topic, payload]: undecodable, as the wire says
            sender.sock.send_multipart([b"mocap/bad-a/pose"])
            sender.sock.send_multipart([b"mocap/bad-a/pose", pose("bad-a", 300), b"more"])
            reasons += ["undecodable", "undecodable"]

        def counted() -> dict[str, float]:
            m = daemon.metrics()
            return {r: m.get(f'mocapd_rejects_total{{reason="{r}"}}', 0) for r in set(reasons)}

        wait_for(
            lambda: all(counted()[r] >= reasons.count(r) for r in reasons), 20, "every bad message counted"
        )
        assert counted() == {r: reasons.count(r) for r in set(reasons)}
        m = daemon.metrics()
        assert m['mocapd_stream_events_total{event="skeleton_changed"}'] == 1
        wait_for(lambda: daemon.metrics()['mocapd_stream_events_total{event="gaps"}'] == 1, 10, "the gap")
        assert daemon.metrics()['mocapd_stream_events_total{event="gap_frames"}'] == 99

        # a flood of 10,000 bad messages: counted, memory flat
        before = rss_kib(daemon.process.pid)
        for k in range(10_000):
            sender.send("mocap/bad-a/pose", b"\xc1" * (1 + k % 50))
        wait_for(
            lambda: daemon.metrics().get('mocapd_rejects_total{reason="undecodable"}', 0) >= 10_001,
            60,
            "the flood counted",
        )
        assert rss_kib(daemon.process.pid) - before < 20_000  # KiB
        assert daemon.alive

        finished(good, timeout=120)
        wait_for(
            lambda: daemon.metrics().get("mocapd_queued_poses", 1) == 0, 30, "the good stream recognised"
        )
        assert daemon.stop() == 0
        motion = read_recording(*GOOD)
        want = detection_keys(
            [d.as_json() for d in detect(motion, load_library(default_library_path()), 120.0)]
        )
        assert detection_keys([d for d in daemon.detections_printed() if d["stream"] == "good"]) == want
        assert not any(e.get("reason") == "undecodable" and e.get("stream") == "bad-d" for e in daemon.logs())
        refused = [e for e in daemon.logs() if e["event"] == "refused"]
        per = [(e["stream"], e["reason"]) for e in refused]
        assert per.count(("bad-a", "undecodable")) == 1  # logged once, then rate-limited
        assert {r for _, r in per} >= set(reasons)
    finally:
        sender.close()
        daemon.stop()
        if broker is not None:
            broker.stop()


@pytest.mark.slow
def test_a_lagging_stream_drops_its_oldest_poses_and_says_so(tmp_path: Path) -> None:
    """A replay as fast as possible into a daemon with a short queue: poses are dropped (counted),
    detections never are, and the stream's frames still arrive in order."""
    daemon = Daemon(tmp_path, config={"service": {"queue_frames": 8}}).start()
    try:
        finished(replay(*GOOD, "zmq+" + daemon.poses, speed="max"))
        wait_for(lambda: daemon.metrics().get("mocapd_frames_in_total") == 2465, 30, "every pose received")
        wait_for(lambda: daemon.metrics().get("mocapd_queued_poses", 1) == 0, 30, "the queue emptied")
        m = daemon.metrics()
        assert m['mocapd_drops_total{reason="lagging"}'] > 0
        assert m['mocapd_stream_events_total{event="gaps"}'] > 0
        published = m.get("mocapd_detections_out_total", 0)
        assert daemon.stop() == 0
        printed = daemon.detections_printed()
        assert all(d["start_frame"] <= d["end_frame"] <= d["emitted_at_frame"] for d in printed)
        assert len(printed) >= published
    finally:
        daemon.stop()


def test_a_refused_skeleton_is_not_logged_as_taken(tmp_path: Path) -> None:
    """With room for one stream, a second stream's skeleton is refused (too_many_streams) and
    logged only as refused (before: first logged as a skeleton taken)."""
    daemon = Daemon(tmp_path, sinks=["stdout"], config={"service": {"max_streams": 1}}).start()
    sender = ZmqSender(daemon.poses)
    try:
        for stream in ("one", "two"):
            sender.send(f"mocap/{stream}/skeleton", encode(SkeletonMessage(stream, 120.0, JOINT_NAMES)))
        wait_for(
            lambda: daemon.metrics().get('mocapd_rejects_total{reason="too_many_streams"}', 0) == 1,
            10,
            "the refusal",
        )
        taken = [e["stream"] for e in daemon.logs() if e["event"] == "skeleton"]
        assert taken == ["one"]
    finally:
        sender.close()
        daemon.stop()


@pytest.mark.slow
def test_every_log_line_is_one_json_object(tmp_path: Path) -> None:
    """The daemon's and a replay's stderr hold one JSON object per line: a pose of values near the
    float32 maximum (numpy's overflow warning in the decoder's finiteness check) and a replay as
    fast as possible over MQTT (aiomqtt's "There are N pending publish calls", thousands of times)
    used to put bare lines in between."""
    broker = Broker(tmp_path).start()
    big: dict[str, dict[str, object]] = {"service": {"queue_frames": 100_000}, "mqtt": {"queue": 100_000}}
    daemon = Daemon(tmp_path, sources=["mqtt"], sinks=["stdout"], mqtt=broker.url, config=big).start()
    sender = MqttSender(broker.url)
    try:
        sender.send("mocap/huge/skeleton", encode(SkeletonMessage("huge", 120.0, JOINT_NAMES)))
        sender.send("mocap/huge/pose", pose("huge", 1, np.full((26, 3), 3e38, np.float32)))
        fast = replay(*GOOD, broker.url, stream="fast", speed="max")
        out, err = fast.communicate(timeout=120)
        assert fast.returncode == 0 and out.startswith("replayed "), err
        wait_for(lambda: daemon.metrics().get("mocapd_queued_poses", 1) == 0, 30, "the poses recognised")
        assert daemon.metrics().get('mocapd_rejects_total{reason="non_finite"}', 0) == 0  # huge, finite
        assert daemon.stop() == 0
        for name, text in (("daemon", daemon.stderr_path.read_text()), ("replay", err)):
            for line in text.splitlines():
                assert isinstance(json.loads(line), dict), (name, line)
    finally:
        sender.close()
        daemon.stop()
        broker.stop()


@pytest.mark.slow
def test_state_and_logs_are_bounded_by_what_is_live(tmp_path: Path) -> None:
    """50,000 poses of 50,000 stream ids that never announced a skeleton: a handful of log lines
    (per reason, not per id) and memory flat (before: 50,000 warning lines, RSS +124 MB for good);
    rounds of 600 streams that are then forgotten as idle: the memory they held is given back, so
    a third round ends where the first did."""
    # idle_s: a round's 600 streams must all be live at once, and taking one in costs 1.5-4 ms
    daemon = Daemon(tmp_path, sinks=["stdout"], config={"service": {"idle_s": 5, "queue_frames": 4}}).start()
    assert daemon.process is not None
    sender = ZmqSender(daemon.poses)
    try:
        before = rss_kib(daemon.process.pid)
        for k in range(50_000):
            sender.send(f"mocap/ghost-{k}/pose", pose(f"ghost-{k}", 1))
        wait_for(
            lambda: daemon.metrics().get('mocapd_rejects_total{reason="no_skeleton"}', 0) == 50_000,
            60,
            "every ghost counted",
        )
        time.sleep(1.5)  # the housekeeping gives the memory back
        assert rss_kib(daemon.process.pid) - before < 15_000  # KiB
        ghosts = [e for e in daemon.logs() if e.get("reason") == "no_skeleton"]
        assert 1 <= len(ghosts) <= 10

        asf = GOOD[0].read_text()
        after: list[int] = []
        for r in range(3):
            for k in range(600):
                name = f"round{r}-{k}"
                message = (
                    SkeletonMessage(name, 120.0, asf=asf, angle_unit="rad")
                    if k % 2
                    else SkeletonMessage(name, 120.0, JOINT_NAMES)
                )
                sender.send(f"mocap/{name}/skeleton", encode(message))
            wait_for(lambda: daemon.metrics().get("mocapd_streams", 0) == 600, 60, "the round's streams")
            wait_for(lambda: daemon.metrics().get("mocapd_streams", 1) == 0, 60, "the round forgotten")
            time.sleep(1.5)  # the housekeeping gives the memory back
            after.append(rss_kib(daemon.process.pid))
        assert after[2] < 1.1 * after[0], after
        taken = [e for e in daemon.logs() if e["event"] == "skeleton"]
        assert 20 <= len(taken) < 200  # not 1,800: 20 per 10 s, then one saying how many were not
        assert daemon.alive
    finally:
        sender.close()
        daemon.stop()


@pytest.mark.slow
def test_a_flood_on_mqtt_does_not_crowd_out_a_good_stream(tmp_path: Path) -> None:
    """50,000 garbage messages on one stream's topic while a good stream replays, with an incoming
    queue of 2,000: the drops are the flood's, the good stream's detections are ``mocapd detect``'s
    (before: the good stream's poses were dropped, mqtt_incoming_full)."""
    broker = Broker(tmp_path).start()
    config: dict[str, dict[str, object]] = {"service": {"queue_frames": 100_000}, "mqtt": {"queue": 2000}}
    daemon = Daemon(tmp_path, sources=["mqtt"], sinks=["stdout"], mqtt=broker.url, config=config).start()
    sender = MqttSender(broker.url)
    try:
        good = replay(*GOOD, broker.url, stream="good", speed="4")
        for _ in range(50_000):  # QoS 0: as fast as the sender can, no acknowledgement to wait for
            sender.client.publish("mocap/flood/pose", b"\xc1 garbage", qos=0)
        finished(good, timeout=120)
        assert daemon.metrics().get('mocapd_drops_total{reason="mqtt_incoming_full"}', 0) > 0
        wait_for(
            lambda: daemon.metrics().get("mocapd_queued_poses", 1) == 0, 30, "the good stream recognised"
        )
        assert daemon.stop() == 0
        want = detection_keys(
            [d.as_json() for d in detect(read_recording(*GOOD), load_library(default_library_path()), 120.0)]
        )
        assert detection_keys([d for d in daemon.detections_printed() if d["stream"] == "good"]) == want
    finally:
        sender.close()
        daemon.stop()
        broker.stop()


def test_a_forgotten_stream_is_logged(tmp_path: Path) -> None:
    """Streams silent for ``idle_s`` are forgotten with a line each ("stream forgotten", the stream,
    why, how long it was silent, its poses), throttled like the other per-stream lines: 25 streams
    forgotten at once give the first 20 (before: no line at all)."""
    daemon = Daemon(tmp_path, sinks=["stdout"], config={"service": {"idle_s": 1}}).start()
    sender = ZmqSender(daemon.poses)
    names = [f"quiet-{k}" for k in range(25)]
    try:
        for name in names:
            sender.send(f"mocap/{name}/skeleton", encode(SkeletonMessage(name, 120.0, JOINT_NAMES)))
            sender.send(f"mocap/{name}/pose", pose(name, 1))
        wait_for(lambda: daemon.metrics().get("mocapd_frames_in_total", 0) == 25, 10, "a pose of each")
        wait_for(lambda: daemon.metrics().get("mocapd_streams", 1) == 0, 10, "the streams forgotten")
        assert daemon.metrics()['mocapd_stream_events_total{event="idle"}'] == 25
        forgotten = [e for e in daemon.logs() if e["event"] == "stream forgotten"]
        assert len(forgotten) == 20
        assert len({e["stream"] for e in forgotten}) == 20 and {e["stream"] for e in forgotten} <= set(names)
        assert all(e["level"] == "info" and e["reason"] == "idle" and e["poses"] == 1 for e in forgotten)
        assert all(e["silent_s"] >= 1 for e in forgotten)
    finally:
        sender.close()
        daemon.stop()


def test_a_message_that_breaks_the_daemon_leaves_only_json_on_stderr(tmp_path: Path) -> None:
    """A pose whose ``v`` is a list 1000 deep (issue 32: it made the decoder raise RecursionError):
    the daemon refuses it, or, if it is a bug that ends the daemon, it says so in one JSON line
    (``internal error``, the exception and its traceback in fields) and exits 70; every line on
    stderr is one JSON object. Before: a plain line "mocapd: internal error: ExceptionGroup ..."."""
    daemon = Daemon(tmp_path, sinks=["stdout"]).start()
    sender = ZmqSender(daemon.poses)
    try:
        v: list[Any] = []
        for _ in range(1000):
            v = [v]
        sender.send("mocap/deep/pose", raw({"v": v, "type": "pose", "stream": "deep", "seq": 1, "time": 1.0}))
        wait_for(
            lambda: not daemon.alive or any(e.get("stream") == "deep" for e in daemon.logs()),
            10,
            "the message refused, or the daemon ended",
        )
        code = daemon.stop()
        lines = [json.loads(line) for line in daemon.stderr_path.read_text().splitlines()]
        if code != 0:
            assert code == 70
            assert lines[-1]["event"] == "internal error" and lines[-1]["level"] == "critical"
            assert lines[-1]["exception"].startswith("RecursionError: ")
            assert "Traceback (most recent call last)" in lines[-1]["error"]
    finally:
        sender.close()
        daemon.stop()
