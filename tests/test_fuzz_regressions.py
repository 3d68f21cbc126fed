"""What the fuzz run (``python -m bench.fuzz``) found, each kept from coming back: a message refused
after it was decoded counted twice (in ``messages_in`` and in ``rejects``) and an empty skeleton not
at all, so the counts could not be reconciled with what was sent; one pose the recogniser refuses
(channels finite on the wire, beyond floating point after forward kinematics) black-holed its stream
(every later pose refused as a ``jump``); a pose of infinities of both signs put a numpy warning in
the log."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import msgpack
import numpy as np
import pytest
import zmq

from daemon.library import default_library_path, load_library
from daemon.recordings import read_recording
from daemon.service.streams import StreamTable
from protocols.messages import DetectionMessage, PoseMessage, SkeletonMessage, encode
from replay import JOINT_NAMES
from tests.helpers import DATA, Daemon, wait_for

CLIP = (DATA / "cmu" / "13" / "13.asf", DATA / "cmu" / "13" / "13_30.amc.gz")
POSE = np.zeros((len(JOINT_NAMES), 3), dtype=np.float32)


def pose(stream: str, seq: int, positions: np.ndarray = POSE) -> bytes:
    return encode(PoseMessage(stream, seq, time.time(), positions=positions))


def counted(m: dict[str, float]) -> float:
    return sum(
        v for k, v in m.items() if k.startswith(("mocapd_messages_in_total{", "mocapd_rejects_total{"))
    )


@pytest.mark.slow
def test_every_message_is_counted_once_and_the_log_has_no_numpy_warning(tmp_path: Path) -> None:
    """Taken in (a pose, a skeleton, a clear) or refused (before or after decoding), each message
    once: messages_in + rejects = messages sent; no numpy warning for infinities of both signs."""
    daemon = Daemon(tmp_path, sinks=["stdout"]).start()
    ctx = zmq.Context()
    sock = ctx.socket(zmq.XPUB)
    sock.setsockopt(zmq.LINGER, 5000)
    sock.connect(daemon.poses)
    assert sock.poll(10_000), "the daemon did not subscribe"
    sock.recv()
    body: dict[str, Any] = {"v": 1, "type": "pose", "stream": "a", "seq": 3, "time": 0.0}
    both = np.full(POSE.size, np.inf, "<f4")
    both[1::2] = -np.inf
    detection = DetectionMessage("i", "a", "squat", 1, 2, 0.1, 0.2, 3, 1.0, 2.0)
    messages = [
        ("mocap/a/skeleton", encode(SkeletonMessage("a", 120.0, JOINT_NAMES))),  # taken in
        ("mocap/a/pose", pose("a", 1)),  # taken in
        ("mocap/a/pose", pose("a", 1)),  # decoded, refused: duplicate
        ("mocap/ghost/pose", pose("ghost", 1)),  # decoded, refused: no_skeleton
        ("mocap/b/pose", pose("a", 2)),  # decoded, refused: schema (another stream's)
        ("mocap/a/pose", encode(detection)),  # decoded, refused: type
        ("mocap/a/pose", msgpack.packb({**body, "positions": both.tobytes()})),  # refused: non_finite
        ("mocap/a/pose", b"\xc1"),  # refused: undecodable
        ("mocap/a/skeleton", b""),  # taken in: a clear
    ]
    try:
        for topic, payload in messages:
            sock.send_multipart([topic.encode(), payload])
        wait_for(lambda: counted(daemon.metrics()) >= len(messages), 10, "every message counted")
        time.sleep(0.3)
        m = daemon.metrics()
        assert counted(m) == len(messages)
        assert m['mocapd_messages_in_total{type="pose"}'] == m["mocapd_frames_in_total"] == 1
        assert m['mocapd_messages_in_total{type="skeleton"}'] == 1
        assert m['mocapd_messages_in_total{type="clear"}'] == 1
        assert m['mocapd_rejects_total{reason="non_finite"}'] == 1
        assert daemon.stop() == 0
        assert not [e for e in daemon.logs() if "Warning" in e["event"]]
    finally:
        sock.close()
        ctx.term()
        daemon.stop()


def test_a_pose_the_recogniser_refuses_does_not_black_hole_its_stream() -> None:
    """A channel pose of huge finite values (valid on the wire; not finite after forward
    kinematics) is refused by the recogniser and counted as a drop of a taken-in pose; the stream's
    next poses follow on (before: every one refused as a jump), so the clip's detections still come."""
    motion = read_recording(*CLIP)
    asf = CLIP[0].read_text(encoding="utf-8")
    table = StreamTable(load_library(default_library_path()), session="s")
    table.skeleton(SkeletonMessage("c", 120.0, asf=asf, angle_unit="rad"), 0.0)
    refused: list[tuple[str, str, str]] = []
    detections = []
    for k, row in enumerate(motion.channels):
        channels = np.full_like(row, 1e308) if k in (100, 101, 500) else np.ascontiguousarray(row)
        table.pose(PoseMessage("c", k + 1, float(k), channels=channels), k / 120)
        with np.errstate(over="ignore"):  # as the daemon runs (configure_logging)
            out, problems = table.tick()
        refused += problems
        detections += [e.message for e in out]
    detections += [e.message for e in table.flush_all()]
    assert [(p, why.split(":")[1].strip()) for _, p, why in refused] == [
        ("non_finite", "frame 101"),
        ("non_finite", "frame 101"),  # bridging 100 to the bad 102: 102 is dropped
        ("non_finite", "frame 501"),
    ]
    assert "bridging the gap before pose 102, dropped" in refused[1][2]
    # the poses after each refused one bridge a gap: 102 (1 missing), 103 (2), 502 (1)
    assert dict(table.counts) == {"recognizer_non_finite": 3, "gaps": 3, "gap_frames": 4}
    assert len(detections) >= 10, detections  # the clip's exercises (13 with no pose refused)
    frames = [(d.start_frame, d.end_frame) for d in detections if isinstance(d, DetectionMessage)]
    assert all(1 <= a <= b <= len(motion) for a, b in frames)
