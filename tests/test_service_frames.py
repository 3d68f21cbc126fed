"""Frame messages (several streams' poses in one message, issue 37) end to end: a real daemon (one
process, and a front with two workers, which every frame message reaches) over real ZeroMQ sockets,
poses sent as single pose messages and as frame messages mixed, bad subjects among good ones and a
frame message wrong as a whole: every stream's detections are ``mocapd detect``'s, and what is bad
is refused alone, counted by reason (once, whatever the workers)."""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from functools import cache
from pathlib import Path
from typing import Any

import msgpack
import numpy as np
import pytest

from daemon.library import default_library_path, load_library
from daemon.recognizer import detect
from daemon.recordings import read_recording
from protocols.messages import EndMessage, PoseMessage, SkeletonMessage, encode, frame_of, topic
from protocols.publish import messages
from tests.helpers import (
    DATA,
    Broker,
    Daemon,
    detection_keys,
    finished,
    hdm05_clip,
    raw_publisher,
    replay,
    takes,
    wait_for,
)

SOURCES = {
    "s0": (DATA / "cmu" / "13" / "13.asf", DATA / "cmu" / "13" / "13_30.amc.gz"),
    "s1": hdm05_clip("bd", "squat1Reps", takes("squat1Reps", "bd")[0]),
    "s2": (DATA / "cmu" / "02" / "02.asf", DATA / "cmu" / "02" / "02_05.amc.gz"),
    "s3": hdm05_clip("bk", "hopBothLegs1hops", takes("hopBothLegs1hops", "bk")[1]),
}
FRAMED = (("s0", "s1"), ("s3",))
"""The streams sent together in frame messages (s2 goes as pose messages of its own)."""
BAD_EVERY = 97
"""Every so many frames, bad subjects ride along in the first frame message."""


@cache
def expected(name: str) -> list[dict[str, Any]]:
    asf, amc = SOURCES[name]
    return [
        d.as_json()
        for d in detect(read_recording(asf, amc), load_library(default_library_path()), 120.0, stream=name)
    ]


def sent(name: str) -> tuple[SkeletonMessage, list[PoseMessage], EndMessage]:
    asf, amc = SOURCES[name]
    items = list(messages(read_recording(asf, amc), asf.read_text(), name, 120.0, 1))
    skeleton, end = items[0], items[-1]
    assert isinstance(skeleton, SkeletonMessage) and isinstance(end, EndMessage)
    return skeleton, [p for p in items[1:-1] if isinstance(p, PoseMessage)], end


@contextmanager
def publisher(daemon: Daemon, broker: Broker | None) -> Iterator[Callable[[str, bytes], None]]:
    """Send (topic, payload) to ``daemon``: over its ZeroMQ poses socket, or through ``broker``
    (QoS 1, so that the comparison is not at the mercy of a dropped pose)."""
    if broker is None:
        with raw_publisher(daemon.poses) as sock:
            yield lambda name, payload: sock.send_multipart([name.encode(), payload])
        return
    import paho.mqtt.client as paho
    from paho.mqtt.enums import CallbackAPIVersion

    client = paho.Client(CallbackAPIVersion.VERSION2, client_id="frames-publisher")
    client.max_queued_messages_set(0)
    client.connect("127.0.0.1", broker.port)
    client.loop_start()
    try:

        def publish(name: str, payload: bytes) -> None:
            client.publish(name, payload, qos=1)

        yield publish
        wait_for(lambda: not client.want_write(), 30, "everything published")
    finally:
        client.loop_stop()
        client.disconnect()


@pytest.mark.slow  # 5-10 s: four recordings at 8x
@pytest.mark.parametrize(("transport", "workers"), [("zmq", 1), ("zmq", 2), ("mqtt", 1)])
def test_single_and_frame_messages_mixed_give_the_detections_of_detect(
    transport: str, workers: int, tmp_path: Path
) -> None:
    broker = Broker(tmp_path).start() if transport == "mqtt" else None
    daemon = Daemon(
        tmp_path,
        sources=(transport,),
        mqtt=None if broker is None else broker.url,
        config={"service": {"queue_frames": 100_000}},
        workers=workers,
    ).start()
    streams = {name: sent(name) for name in SOURCES}
    bad = 0
    try:
        with publisher(daemon, broker) as publish:

            def send(message: Any) -> None:
                publish(topic(message), encode(message))

            for skeleton, _, _ in streams.values():
                send(skeleton)
            time.sleep(0.5)
            whole = msgpack.unpackb(encode(frame_of([streams["s0"][1][0]], "rig")))
            whole["counts"] = np.array([7], dtype="<u4").tobytes()  # the subjects cannot be told apart
            publish("mocap/rig/frame", msgpack.packb(whole))
            longest = max(len(poses) for _, poses, _ in streams.values())
            for i in range(longest):
                now = time.time()
                at = {n: p[i] for n, (_, p, _) in streams.items() if i < len(p)}
                for k, group in enumerate(FRAMED):
                    here = [n for n in group if n in at]
                    poses = [PoseMessage(n, at[n].seq, now, channels=at[n].channels) for n in here]
                    if k == 0 and i % BAD_EVERY == 0 and poses:
                        nan = PoseMessage("lost", 1, now, channels=np.full(3, np.nan))
                        dotted = PoseMessage("a.b", 1, now, channels=np.ones(3))
                        again = PoseMessage(poses[0].stream, poses[0].seq, now, channels=poses[0].channels)
                        poses += [nan, dotted, again]  # again: a pose of its seq came before it
                        bad += 1
                    if poses:
                        send(frame_of(poses, f"rig{k}"))
                if "s2" in at:
                    send(PoseMessage("s2", at["s2"].seq, now, channels=at["s2"].channels))
                if i % 8 == 7:
                    time.sleep(0.001)  # 8x a 120 Hz stream
            total = sum(len(p) for _, p, _ in streams.values())
            # the ends at once: a framed stream's on its source's frame topic, after its frames
            # (on the stream's own pose topic it could overtake them over MQTT)
            for k, group in enumerate(FRAMED):
                for name in group:
                    publish(f"mocap/rig{k}/frame", encode(streams[name][2]))
            send(streams["s2"][2])
            deadline = time.monotonic() + 60
            ended = 'mocapd_stream_events_total{event="ended"}'
            while daemon.metrics().get(ended, 0) < len(SOURCES) and time.monotonic() < deadline:
                time.sleep(0.05)
        m = daemon.metrics()
        assert daemon.stop() == 0
        got = daemon.detections_printed()
        for name in SOURCES:
            mine = [d for d in got if d["stream"] == name]
            assert detection_keys(mine) == detection_keys(expected(name)), name
        assert sum(len(expected(n)) for n in SOURCES) > 20
        assert bad > 10
        assert m["mocapd_frames_in_total"] == total
        assert m['mocapd_messages_in_total{type="end"}'] == len(SOURCES)
        assert m[ended] == len(SOURCES)  # every stream ended, none left to go idle
        for reason, count in (("non_finite", bad), ("schema", bad), ("duplicate", bad), ("shape", 1)):
            assert m.get(f'mocapd_rejects_total{{reason="{reason}"}}') == count, (reason, m)
    finally:
        daemon.stop()
        if broker is not None:
            broker.stop()


@pytest.mark.slow  # 5-10 s: three recordings at 8x
def test_a_replay_with_other_recordings_sends_frames_that_give_the_detections_of_detect(
    tmp_path: Path,
) -> None:
    """``mocapd replay --with`` sends the recordings as one source (a frame message a step): each
    stream gets ``mocapd detect``'s detections."""
    daemon = Daemon(tmp_path, config={"service": {"queue_frames": 100_000}}).start()
    try:
        (asf, amc), others = SOURCES["s0"], [SOURCES["s2"], SOURCES["s1"]]
        extra = [str(x) for pair in others for x in ("--with", *pair)]
        out = finished(
            replay(asf, amc, "zmq+" + daemon.poses, *extra, "--source", "rig", stream="s0", speed="8")
        )
        names = ["s0", *(p[1].name.removesuffix(".gz").removesuffix(".amc") for p in others)]
        assert out.startswith("replayed ") and all(repr(n) in out for n in names)
        total = sum(len(read_recording(*SOURCES[k])) for k in ("s0", "s1", "s2"))
        wait_for(lambda: daemon.metrics().get("mocapd_frames_in_total") == total, 60, "every pose received")
        assert daemon.stop() == 0
        got = daemon.detections_printed()
        for name, key in zip(names, ("s0", "s2", "s1"), strict=True):
            mine = [dict(d, stream=key) for d in got if d["stream"] == name]
            want = [dict(d, stream=key) for d in expected(key)]
            assert detection_keys(mine) == detection_keys(want), name
    finally:
        daemon.stop()


def test_a_replay_with_a_recording_named_as_another_is_refused_in_one_line() -> None:
    asf, amc = SOURCES["s0"]
    done = replay(asf, amc, "zmq+tcp://127.0.0.1:9", "--with", str(asf), str(amc))
    _, err = done.communicate(timeout=60)
    assert done.returncode == 2
    assert err.splitlines() == [
        "mocapd: --with: 13_30.amc.gz: stream '13_30' is taken or not an id "
        "(letters, digits, _:@-, at most 128)"
    ]
