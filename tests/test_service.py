"""``mocapd run`` end to end, every part real: the daemon and the replays are processes, the broker is
a mosquitto on a loopback port, the sockets are ZeroMQ's. A replayed recording gives exactly the
detections ``mocapd detect`` gives (every field but the id), over ZeroMQ and over MQTT, for one
stream and for eight at once; SIGTERM mid-stream publishes everything received and "offline"; a
broker restart loses no detection; kill -9 leaves the will; the latency metric does not trust a
source's clock."""

from __future__ import annotations

import dataclasses
import signal
import subprocess
import time
from functools import cache
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import zmq

from daemon.behaviours import JointRotations, ppca_forward
from daemon.frames import FrameClock
from daemon.library import default_library_path, load_library
from daemon.recognizer import Recognizer, detect, detect_positions, same_motion
from daemon.recordings import read_recording
from daemon.types import RecognitionSettings
from protocols.messages import PoseMessage, encode, topic
from protocols.publish import messages
from replay import JOINT_NAMES, Motion
from replay.bvh import read_bvh, write_bvh
from replay.convert import motion_to_bvh
from replay.rigs import BUILT_IN, bvh_standard_joints
from tests.helpers import (
    DATA,
    MOCAPD_SCRIPT,
    Broker,
    Daemon,
    MqttCollector,
    ZmqCollector,
    detection_keys,
    finished,
    hdm05_clip,
    replay,
    resampled_motion,
    takes,
    wait_for,
)

CMU_13 = DATA / "cmu" / "13" / "13.asf"
TRIAL = (CMU_13, DATA / "cmu" / "13" / "13_30.amc.gz")
LONG = (CMU_13, DATA / "cmu" / "13" / "13_29.amc.gz")


@cache
def expected(asf: Path, amc: Path, frames: int | None = None) -> list[dict[str, Any]]:
    """``mocapd detect``'s detections (its batch twin) on the recording, or its first ``frames``."""
    motion = read_recording(asf, amc)
    if frames is not None:
        motion = Motion(
            motion.source, motion.skeleton, motion.header, motion.frames[:frames], motion.channels[:frames]
        )
    return [d.as_json() for d in detect(motion, load_library(default_library_path()), 120.0)]


def unique(items: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """First arrivals only (QoS 1 may deliver a detection twice; the id says which)."""
    seen: set[str] = set()
    out = []
    for d in items:
        if d["id"] not in seen:
            seen.add(d["id"])
            out.append(d)
    return out


BIG_QUEUE: dict[str, dict[str, object]] = {"service": {"queue_frames": 100_000}}
"""A replay as fast as possible outruns recognition; with a queue this long nothing is dropped."""


@pytest.mark.slow
def test_zeromq_replay_gives_the_detections_of_detect(tmp_path: Path) -> None:
    daemon = Daemon(tmp_path, config=BIG_QUEUE).start()
    collector = ZmqCollector(daemon.detections)
    try:
        finished(replay(*TRIAL, "zmq+" + daemon.poses, speed="max"))
        want = detection_keys(expected(*TRIAL))
        wait_for(lambda: daemon.metrics().get("mocapd_frames_in_total") == 2465, 30, "every pose received")
        # the replay's end: the stream's last detections at once, not after service.idle_s (30 s)
        wait_for(lambda: len(collector.detections()) >= len(want), 20, "the last detections")
        metrics = daemon.metrics()
        assert metrics['mocapd_stream_events_total{event="ended"}'] == 1 and metrics["mocapd_streams"] == 0
        assert daemon.stop() == 0
        assert detection_keys(collector.detections()) == want
        assert detection_keys(daemon.detections_printed()) == want
        statuses = [m for m in collector.messages if m.get("type") == "status"]
        assert [m["state"] for m in statuses[-1:]] == ["offline"]
        assert statuses[-1]["streams"] == 0  # the stream ended before the daemon stopped
    finally:
        collector.close()
        daemon.stop()


def held(where: Path, hold: float) -> list[dict[str, Any]]:
    """What a daemon with ``recognizer.hold_s`` = ``hold`` publishes over ZeroMQ for CMU 13_30,
    checked against ``mocapd detect``'s with the same hold."""
    where.mkdir()
    config: dict[str, dict[str, object]] = {**BIG_QUEUE, "recognizer": {"hold_s": hold}}
    daemon = Daemon(where, config=config).start()
    collector = ZmqCollector(daemon.detections)
    try:
        finished(replay(*TRIAL, "zmq+" + daemon.poses, speed="max"))
        want = [
            d.as_json()
            for d in detect(
                read_recording(*TRIAL),
                load_library(default_library_path()),
                120.0,
                settings=RecognitionSettings(hold_s=hold),
            )
        ]
        wait_for(lambda: daemon.metrics().get("mocapd_frames_in_total") == 2465, 30, "every pose received")
        assert daemon.stop() == 0
        wait_for(lambda: len(collector.detections()) >= len(want), 10, "the last detections")
        assert detection_keys(collector.detections()) == detection_keys(want)
        return collector.detections()
    finally:
        collector.close()
        daemon.stop()


@pytest.mark.slow
def test_the_hold_end_to_end(tmp_path: Path) -> None:
    """Through two real daemons over ZeroMQ, ``recognizer.hold_s`` 0 and 2: each publishes what
    ``mocapd detect`` gives with the same hold; without a hold every detection of a stream-wide
    class comes out one index frame after its last frame is seen (the features' delay, then the
    frame that shows Δ's minimum; a keyframes-first class's when its keyframes have matched,
    within the recogniser's reach), with one a detection is held while another template could
    still explain its motion more cheaply, at most 2 s; in both, no two detections are the same
    motion. On CMU 13_30 the hold changes what comes out: a cheaper match of a motion that comes
    later wins."""
    got = {hold: held(tmp_path / f"hold{hold:g}", hold) for hold in (0.0, 2.0)}
    clock = FrameClock.of(120.0, 30.0)
    delay = clock.delay  # the features' (20 native frames)
    library = load_library(default_library_path())
    for hold, detections in got.items():
        bound = delay + (round(hold * 30) + 2) * 4  # native frames: features, the minimum's frame, the hold
        # a keyframes-first class's detection waits for its keyframes, at most the recogniser's reach
        reach = Recognizer(
            library, 120.0, joint_names=JOINT_NAMES, settings=RecognitionSettings(hold_s=hold)
        ).reach
        for d in detections:
            gated = library.classes[d["class"]].mode == "keyframes"
            assert 0 <= d["emitted_at_frame"] - d["end_frame"] <= (clock.lag(reach) if gated else bound), d
        ranges = [(d["start_frame"], d["end_frame"]) for d in detections]
        assert not any(same_motion(a, b) for i, a in enumerate(ranges) for b in ranges[i + 1 :])
    assert (
        max(
            d["emitted_at_frame"] - d["end_frame"]
            for d in got[0.0]
            if library.classes[d["class"]].mode == "dtw"
        )
        <= delay + 4
    )
    assert max(d["emitted_at_frame"] - d["end_frame"] for d in got[2.0]) > delay + 4
    assert detection_keys(got[0.0]) != detection_keys(got[2.0])


@pytest.mark.slow
def test_mqtt_replay_gives_the_detections_of_detect(tmp_path: Path) -> None:
    broker = Broker(tmp_path).start()
    daemon = Daemon(
        tmp_path, sources=["mqtt"], sinks=["mqtt", "stdout"], mqtt=broker.url, config=BIG_QUEUE
    ).start()
    collector = MqttCollector(broker.url, ["mocap/+/detections", "mocapd/+/status"])
    try:
        assert daemon.health() == (200, "ok\n")
        wait_for(lambda: any(s["state"] == "online" for s in collector.statuses()), 10, "the retained online")
        finished(replay(*TRIAL, broker.url, speed="8"))
        wait_for(lambda: daemon.metrics().get("mocapd_frames_in_total") == 2465, 30, "every pose received")
        assert daemon.stop() == 0
        want = detection_keys(expected(*TRIAL))
        wait_for(lambda: len(unique(collector.detections())) >= len(want), 10, "the last detections")
        assert detection_keys(unique(collector.detections())) == want
        wait_for(lambda: collector.statuses()[-1]["state"] == "offline", 10, "offline")
    finally:
        collector.close()
        daemon.stop()
        broker.stop()


def test_a_replay_with_no_retain_leaves_no_skeleton_retained(tmp_path: Path) -> None:
    """``mocapd replay --no-retain`` (for a NATS cluster's MQTT port, docs/cluster.md) announces
    the skeleton at QoS 0 and leaves nothing retained; without it, a subscriber that comes later
    still gets the skeleton."""
    broker = Broker(tmp_path).start()
    live = MqttCollector(broker.url, ["mocap/+/skeleton"], client_id="live")
    late = None
    try:
        finished(replay(*TRIAL, broker.url, "--no-retain", stream="plain"))
        finished(replay(*TRIAL, broker.url, stream="kept"))
        late = MqttCollector(broker.url, ["mocap/+/skeleton"], client_id="late")
        wait_for(lambda: late is not None and bool(late.messages), 10, "the retained skeleton")
        time.sleep(0.5)
        assert {t for t, _ in late.messages} == {"mocap/kept/skeleton"}
        plain = [q for (t, _), q in zip(live.messages, live.qos, strict=True) if t == "mocap/plain/skeleton"]
        assert plain and set(plain) == {(0, False)}
    finally:
        for collector in (live, late):
            if collector is not None:
                collector.close()
        broker.stop()


@pytest.mark.slow
def test_mqtt_boundaries_of_a_segmented_stream(tmp_path: Path) -> None:
    """With segmentation on, the daemon publishes a replayed stream's behaviour boundaries on
    ``mocap/<stream>/boundaries``: the online method's cuts (PPCA's forward pass) of the recording,
    at its AMC frame numbers, beside its detections."""
    broker = Broker(tmp_path).start()
    config: dict[str, dict[str, object]] = {**BIG_QUEUE, "segmentation": {"method": "ppca"}}
    daemon = Daemon(tmp_path, sources=["mqtt"], sinks=["mqtt"], mqtt=broker.url, config=config).start()
    collector = MqttCollector(broker.url, ["mocap/+/boundaries", "mocap/+/detections"])
    try:
        finished(replay(*TRIAL, broker.url, "--stream", "take7", speed="8"))
        wait_for(lambda: daemon.metrics().get("mocapd_frames_in_total") == 2465, 30, "every pose received")
        wait_for(lambda: daemon.metrics().get("mocapd_boundaries_out_total", 0) > 0, 30, "a boundary counted")
        assert daemon.stop() == 0
        motion = read_recording(*TRIAL)
        x = JointRotations(motion.skeleton)(motion.channels)
        want = [int(motion.frames[b.frame]) for b in ppca_forward(x, 120.0)]
        wait_for(lambda: len(collector.boundaries()) >= len(want), 10, "the boundaries")
        got = {m["id"]: (t, m["frame"], m["method"]) for t, m in collector.boundaries()}  # QoS 1 repeats
        assert sorted(got.values(), key=lambda g: g[1]) == [
            ("mocap/take7/boundaries", f, "ppca") for f in want
        ]
        assert len(want) >= 3 and collector.detections()
    finally:
        collector.close()
        daemon.stop()
        broker.stop()


@pytest.mark.slow
def test_eight_replays_at_once_are_eight_streams(tmp_path: Path) -> None:
    sources = [
        TRIAL,
        (DATA / "cmu" / "02" / "02.asf", DATA / "cmu" / "02" / "02_05.amc.gz"),
        (DATA / "cmu" / "86" / "86.asf", DATA / "cmu" / "86" / "86_01.amc.gz"),
        hdm05_clip("bd", "squat1Reps", takes("squat1Reps", "bd")[0]),
        hdm05_clip("bk", "hopBothLegs1hops", takes("hopBothLegs1hops", "bk")[1]),
        hdm05_clip("dg", "kickLFront1Reps", takes("kickLFront1Reps", "dg")[0]),
        hdm05_clip("bd", "elbowToKnee1RepsLelbowStart", takes("elbowToKnee1RepsLelbowStart", "bd")[0]),
        TRIAL,  # the same recording as another stream
    ]
    daemon = Daemon(tmp_path, config=BIG_QUEUE).start()
    collector = ZmqCollector(daemon.detections)
    try:
        names = [f"s{k}" for k in range(len(sources))]
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
        wait_for(lambda: len(collector.detections()) == len(got), 10, "the published detections")
    finally:
        collector.close()
        daemon.stop()


@pytest.mark.slow
def test_sigterm_mid_stream_publishes_what_was_received_then_offline(tmp_path: Path) -> None:
    daemon = Daemon(tmp_path, config={"service": {"grace_s": 5}}).start()
    collector = ZmqCollector(daemon.detections)
    sender = replay(*LONG, "zmq+" + daemon.poses, speed="2")
    try:
        wait_for(lambda: daemon.metrics().get("mocapd_frames_in_total", 0) > 1500, 60, "poses flowing")
        daemon.signal(signal.SIGTERM)
        began = time.monotonic()
        assert daemon.wait(timeout=5 + 5) == 0
        stopping = next(e for e in daemon.logs() if e["event"] == "stopping")
        received = stopping["received"][Path(LONG[1]).name.removesuffix(".amc.gz")]
        assert received > 1500
        want = detection_keys(expected(*LONG, received))
        assert detection_keys(daemon.detections_printed()) == want
        wait_for(lambda: len(collector.detections()) == len(want), 10, "the published detections")
        assert detection_keys(collector.detections()) == want
        statuses = [m["state"] for m in collector.messages if m.get("type") == "status"]
        assert statuses[-1:] == ["offline"]
        assert time.monotonic() - began < 10
    finally:
        sender.kill()
        sender.communicate()
        collector.close()
        daemon.stop()


@pytest.mark.slow
def test_broker_restart_mid_stream_loses_no_detection(tmp_path: Path) -> None:
    broker = Broker(tmp_path).start()
    daemon = Daemon(tmp_path, sources=["mqtt"], sinks=["mqtt", "stdout"], mqtt=broker.url).start()
    collector = MqttCollector(broker.url, ["mocap/+/detections"], client_id="restart-collector")
    sender = replay(*LONG, broker.url, speed="2")
    try:
        wait_for(lambda: len(daemon.detections_printed()) >= 5, 60, "detections flowing")
        broker.stop()
        wait_for(lambda: daemon.health()[0] == 503, 10, "the daemon noticing")
        assert "mqtt" in daemon.health()[1]
        time.sleep(0.5)
        broker.start()
        wait_for(lambda: daemon.health()[0] == 200, 20, "the daemon reconnecting by itself")
        finished(sender, timeout=120)
        wait_for(lambda: daemon.metrics().get("mocapd_queued_poses", 1) == 0, 30, "the last poses recognised")
        assert daemon.stop() == 0
        emitted = {d["id"] for d in daemon.detections_printed()}
        assert len(emitted) > 10
        wait_for(lambda: emitted <= {d["id"] for d in collector.detections()}, 20, "every emitted detection")
        connects = [e for e in daemon.logs() if e["event"] == "mqtt connected"]
        assert len(connects) >= 2
        # the reading connection (gmqtt's) came back once, made by the transport: gmqtt's own
        # reconnect, seconds later, would take its client id from the one the transport made
        log = (tmp_path / "mosquitto.log").read_text(encoding="utf-8", errors="replace")
        assert log.count(f"as mocapd-test-{daemon.metrics_port}-in ") == len(connects)
        assert "already connected" not in log
    finally:
        sender.kill()
        sender.communicate()
        collector.close()
        daemon.stop()
        broker.stop()


@pytest.mark.slow
def test_kill_9_leaves_the_will(tmp_path: Path) -> None:
    broker = Broker(tmp_path).start()
    daemon = Daemon(tmp_path, sources=["mqtt"], sinks=["mqtt"], mqtt=broker.url).start()
    collector = MqttCollector(broker.url, ["mocapd/+/status"], client_id="will-collector")
    try:
        wait_for(lambda: [s["state"] for s in collector.statuses()][-1:] == ["online"], 10, "online")
        daemon.signal(signal.SIGKILL)
        daemon.wait(10)
        wait_for(lambda: [s["state"] for s in collector.statuses()][-1:] == ["offline"], 10, "the will")
        assert collector.statuses()[-1]["instance"] == daemon.instance
    finally:
        collector.close()
        broker.stop()


def test_a_channel_frame_roundtrip_is_exact() -> None:
    """What makes the equality above possible: a channel frame crosses the wire as float64, bit for bit."""
    from protocols.messages import PoseMessage, decode, encode

    motion = read_recording(*TRIAL)
    for row in motion.channels[::97]:
        back = decode(encode(PoseMessage("s", 1, 0.0, channels=row)))
        assert isinstance(back, PoseMessage) and back.channels is not None
        assert np.array_equal(back.channels, row)


def test_a_second_signal_exits_at_once(tmp_path: Path) -> None:
    """The first SIGTERM starts recognising a long backlog; the second ends the process there.
    Recognition in slices of one tick (a tiny budget) falls behind intake on any machine."""
    service = {"queue_frames": 1_000_000, "grace_s": 120, "tick_budget_ms": 0.001}
    daemon = Daemon(tmp_path, config={"service": service}).start()
    sender = replay(*LONG, "zmq+" + daemon.poses, "--loop", speed="max")
    try:
        wait_for(lambda: daemon.metrics().get("mocapd_queued_poses", 0) > 20_000, 60, "a backlog")
        daemon.signal(signal.SIGTERM)
        wait_for(lambda: any(e["event"] == "stopping" for e in daemon.logs()), 10, "the shutdown begun")
        assert daemon.alive  # still recognising the backlog
        daemon.signal(signal.SIGTERM)
        assert daemon.wait(timeout=5) == 128 + signal.SIGTERM
    finally:
        sender.kill()
        sender.communicate()
        daemon.stop()


@pytest.mark.slow
def test_the_latency_metric_does_not_trust_the_source_clock(tmp_path: Path) -> None:
    """A source whose clock jumps back an hour halfway through a recording (issue 32: the end-to-end
    sum was 1.08e10 s for 13 detections): ``mocapd_end_to_end_seconds`` counts from each pose's
    arrival on the daemon's own clock, so an hour of skew is not in it, while the detections still
    carry the source's timestamps."""
    daemon = Daemon(tmp_path, config=BIG_QUEUE).start()
    motion = read_recording(*TRIAL)
    ctx = zmq.Context()
    sock = ctx.socket(zmq.XPUB)
    sock.setsockopt(zmq.SNDHWM, 1_000_000)
    sock.setsockopt(zmq.LINGER, 5000)
    try:
        sock.connect(daemon.poses)
        assert sock.poll(10_000) and sock.recv()[:1] == b"\x01"  # the daemon's subscription
        began = time.monotonic()
        for i, m in enumerate(messages(motion, TRIAL[0].read_text(), "skewed", 120.0, 1, epoch="e1")):
            if isinstance(m, PoseMessage):  # at 4 times real time, the second half an hour behind
                behind = 3600.0 if m.seq > len(motion) // 2 else 0.0
                m = dataclasses.replace(m, time=time.time() - behind)
                time.sleep(max(0.0, began + i / (4 * 120.0) - time.monotonic()))
            sock.send_multipart([topic(m).encode(), encode(m)])
        wait_for(lambda: daemon.metrics().get("mocapd_frames_in_total") == len(motion), 30, "every pose")
        wait_for(lambda: daemon.metrics().get("mocapd_queued_poses", 1) == 0, 30, "every pose recognised")
        metrics = daemon.metrics()
        count, total = metrics["mocapd_end_to_end_seconds_count"], metrics["mocapd_end_to_end_seconds_sum"]
        assert count >= 10
        assert total < 60 * count  # an hour's skew puts 3600 s in each of the later ones
        assert daemon.stop() == 0
        printed = daemon.detections_printed()
        assert detection_keys(printed) == detection_keys(expected(*TRIAL))
        assert sum(d["source_time"] < time.time() - 3000 for d in printed) >= 3  # the source's clock
    finally:
        sock.close()
        ctx.term()
        daemon.stop()


BVH_TAKE = DATA / "bandai2" / "dataset-2_wave-right-hand_normal_001.bvh.gz"
"""A bandai2 take (CC BY-NC-ND 4.0, read unmodified)."""
UPPERARM = next(m for m in BUILT_IN if m.name == "upperarm")


@pytest.mark.slow
@pytest.mark.parametrize(
    ("transport", "as_positions", "at_100_hz"),
    [("zmq", False, False), ("mqtt", False, False), ("zmq", True, False), ("zmq", False, True)],
    ids=["zmq", "mqtt", "rig", "100 Hz"],
)
def test_a_bvh_replay_gives_the_detections_of_detect_bvh(
    tmp_path: Path, transport: str, as_positions: bool, at_100_hz: bool
) -> None:
    """``mocapd replay --bvh`` sends the take as it is, its hierarchy in the skeleton and its
    channel rows in the poses (float64 on the wire): a daemon maps the rig as ``mocapd detect
    --bvh`` does and publishes its detections, costs and all. With ``--rig`` (a user's map, which
    the daemon does not know) it sends the mapped standard joints as a positions stream (float32):
    the batch twin's detections of those, ``detect --bvh``'s but for the costs' last digits. At
    100 Hz (CMU 13_29 resampled, written as BVH), a rate the library's 30 Hz does not divide."""
    take_path = BVH_TAKE
    if at_100_hz:
        take_path = tmp_path / "13_29_100hz.bvh"
        lower = resampled_motion(read_recording(*LONG), 120.0, 100.0)
        take_path.write_bytes(write_bvh(motion_to_bvh(lower, 100.0)))
    broker = Broker(tmp_path).start() if transport == "mqtt" else None
    daemon = (
        Daemon(tmp_path, config=BIG_QUEUE)
        if broker is None
        else Daemon(tmp_path, sources=["mqtt"], sinks=["mqtt", "stdout"], mqtt=broker.url, config=BIG_QUEUE)
    ).start()
    rig = tmp_path / "rig.yaml"  # the built-in map of bandai2's scheme, given as a user's
    rig.write_text(
        "joints:\n" + "".join(f"  {j}: [{', '.join(n)}]\n" for j, n in UPPERARM.points.items() if n),
        encoding="utf-8",
    )
    try:
        to = "zmq+" + daemon.poses if broker is None else broker.url
        command = [str(MOCAPD_SCRIPT), "replay", "--bvh", str(take_path), "--to", to, "--speed", "max"]
        out = finished(
            subprocess.Popen(
                command + (["--rig", str(rig)] if as_positions else []),
                stdout=subprocess.PIPE,
                stderr=subprocess.PIPE,
                text=True,
            )
        )
        take = read_bvh(take_path)
        joints, _ = bvh_standard_joints(take)
        assert out.startswith(f"replayed {len(joints)} frames of {take_path.name}")
        stream = take_path.name.removesuffix(".gz").removesuffix(".bvh")
        library = load_library(default_library_path())
        numbers = np.arange(1, len(joints) + 1)
        cli = [d.as_json() for d in detect_positions(joints, numbers, library, take.rate, stream=stream)]
        wire = joints.astype(np.float32).astype(np.float64) if as_positions else joints
        want = [d.as_json() for d in detect_positions(wire, numbers, library, take.rate, stream=stream)]
        wait_for(lambda: len(daemon.detections_printed()) >= len(want), 60, "the take's detections")
        assert daemon.stop() == 0
        assert want and detection_keys(daemon.detections_printed()) == detection_keys(want)
        assert [k[:3] + k[4:] for k in detection_keys(cli)] == [k[:3] + k[4:] for k in detection_keys(want)]
        assert np.allclose([d["cost"] for d in cli], [d["cost"] for d in want], atol=1e-5)
    finally:
        daemon.stop()
        if broker is not None:
            broker.stop()
