"""The service's parts without sockets: the stream table (sequence numbers, bridged and long gaps,
skeleton changes, eviction, the wire's units and axes) against plain recognisers, the service
configuration and its environment overrides, the replay's clock, and the behaviour boundaries of
segmented streams against the batch segmentation."""

from __future__ import annotations

import dataclasses
import math
import re
from functools import cache, partial
from itertools import pairwise
from pathlib import Path
from typing import Literal

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from daemon import behaviours as bh
from daemon.behaviours import JointRotations
from daemon.config import (
    Config,
    ConfigError,
    MqttConfig,
    SegmentationConfig,
    ServiceConfig,
    environment_overrides,
    load_config,
    parse_config,
)
from daemon.frames import bridge
from daemon.library import Library
from daemon.recognizer import Recognizer, detect_positions
from daemon.recordings import read_recording
from daemon.service.streams import Emitted, Refused, StreamTable
from protocols.messages import BoundaryMessage, DetectionMessage, EndMessage, PoseMessage, SkeletonMessage
from protocols.publish import due
from replay import JOINT_NAMES, Motion
from replay.amc import DEG
from replay.bvh import hierarchy_text, parse_bvh, write_bvh
from replay.convert import motion_to_bvh
from replay.kinematics import joint_positions
from replay.rigs import BUILT_IN, bvh_standard_joints, parse_rig_map, rig_plan, standard_joints
from tests.helpers import DATA, SegmentSummary, check_segment_summaries, hdm05_clip, small_library, takes

ASF, AMC = hdm05_clip("bd", "squat1Reps", takes("squat1Reps", "bd")[1])


@pytest.fixture(scope="module")
def library(tmp_path_factory: pytest.TempPathFactory) -> Library:
    return small_library(tmp_path_factory.mktemp("lib"))


@cache
def motion() -> Motion:
    return read_recording(ASF, AMC)


def table(library: Library, **kw: float) -> StreamTable:
    return StreamTable(library, session="t", service=ServiceConfig(queue_frames=100_000, **kw))  # type: ignore[arg-type]


def announce(t: StreamTable, stream: str = "s") -> None:
    t.skeleton(SkeletonMessage(stream, 120.0, asf=ASF.read_text(), angle_unit="rad"), 0.0)


def run(t: StreamTable, poses: list[PoseMessage]) -> list[tuple[str, int, int, float]]:
    """The detections of ``poses``, each taken at its own timestamp."""
    for p in poses:
        t.pose(p, p.time)
    out = []
    while t.queued:
        out += t.tick()[0]
    out += t.flush_all()
    return [
        (e.message.class_name, e.message.start_frame, e.message.end_frame, e.message.cost)
        for e in out
        if isinstance(e.message, DetectionMessage)
    ]


def filled(before: np.ndarray, after: np.ndarray, k: int, missing: int, angles: set[int]) -> np.ndarray:
    """Missing frame ``k`` (1-based) of ``missing`` between two channel frames, one channel at a
    time: a straight line, an angle's along the shorter way round."""
    out = before.copy()
    for c in range(len(before)):
        delta = after[c] - before[c]
        if c in angles:
            while delta > math.pi:
                delta -= 2 * math.pi
            while delta < -math.pi:
                delta += 2 * math.pi
        out[c] = before[c] + k / (missing + 1) * delta
    return out


def reference(
    library: Library, kept: list[int], seqs: list[int], max_gap: int
) -> list[tuple[str, int, int, float]]:
    """A plain reading: the recording's frames ``kept`` with sequence numbers ``seqs`` as frame
    numbers, each missing frame of a gap of at most ``max_gap`` filled in between its neighbours,
    a new recogniser after a longer gap."""
    m = motion()
    angles = set(m.skeleton.angle_channels)
    out = []
    pieces: list[list[int]] = [[]]
    for k, seq in enumerate(seqs):
        if k and seq - seqs[k - 1] - 1 > max_gap:
            pieces.append([])
        pieces[-1].append(k)
    for piece in pieces:
        r = Recognizer.for_skeleton(library, m.skeleton, 120.0, session="ref")
        found = []
        for j, k in enumerate(piece):
            if j:
                missing = seqs[k] - seqs[piece[j - 1]] - 1
                before, after = m.channels[kept[piece[j - 1]]], m.channels[kept[k]]
                for g in range(1, missing + 1):
                    found += r.push(seqs[piece[j - 1]] + g, filled(before, after, g, missing, angles))
            found += r.push(seqs[k], m.channels[kept[k]])
        found += r.flush()
        out += [(d.class_name, d.start_frame, d.end_frame, d.cost) for d in found]
    return out


@settings(max_examples=10, deadline=None)
@given(st.lists(st.tuples(st.integers(0, 400), st.integers(1, 60)), max_size=4), st.integers(0, 30))
def test_gaps_bridged_or_restarted_as_a_plain_reading_says(
    library: Library, gaps: list[tuple[int, int]], bridge: int
) -> None:
    n = len(motion())
    lost = {k for at, size in gaps for k in range(at, min(n, at + size))}
    kept = [k for k in range(n) if k not in lost]
    seqs = [1000 + k for k in kept]
    t = table(library, bridge_s=bridge / 120)
    announce(t)
    poses = [
        PoseMessage("s", s, k / 120, channels=motion().channels[k]) for s, k in zip(seqs, kept, strict=True)
    ]
    got = run(t, poses)  # stamped at 120 Hz, so no gap is too long for the time it took (implausible)
    want = reference(library, kept, seqs, bridge)
    assert [g[:3] for g in got] == [w[:3] for w in want]
    assert np.allclose([g[3] for g in got], [w[3] for w in want], rtol=0, atol=1e-9)
    gapped = sum(1 for a, b in pairwise(seqs) if b - a > 1)
    assert t.counts["gaps"] == gapped


def test_without_gaps_frames_are_sequence_numbers(library: Library) -> None:
    t = table(library)
    announce(t)
    m = motion()
    got = run(
        t, [PoseMessage("s", int(f), 0.0, channels=c) for f, c in zip(m.frames, m.channels, strict=True)]
    )
    r = Recognizer.for_skeleton(library, m.skeleton, 120.0, session="x")
    want = [d for f, c in zip(m.frames.tolist(), m.channels, strict=True) for d in r.push(f, c)] + r.flush()
    assert got == [(d.class_name, d.start_frame, d.end_frame, d.cost) for d in want]
    assert any(name.startswith("squat") for name, *_ in got)


def test_refusals(library: Library) -> None:
    t = table(library)
    m = motion()
    with pytest.raises(Refused) as caught:
        t.pose(PoseMessage("s", 1, 0.0, channels=m.channels[0]), 0.0)
    assert caught.value.reason == "no_skeleton"
    announce(t)
    t.pose(PoseMessage("s", 5, 0.0, channels=m.channels[0]), 0.0)
    for seq, reason in ((5, "duplicate"), (3, "out_of_order")):
        with pytest.raises(Refused) as caught:
            t.pose(PoseMessage("s", seq, 0.0, channels=m.channels[0]), 0.0)
        assert caught.value.reason == reason
    with pytest.raises(Refused) as caught:
        t.pose(PoseMessage("s", 6, 0.0, channels=m.channels[0][:-1]), 0.0)
    assert caught.value.reason == "shape"
    with pytest.raises(Refused) as caught:
        t.pose(PoseMessage("s", 6, 0.0, positions=np.zeros((26, 3), np.float32)), 0.0)
    assert caught.value.reason == "shape"
    with pytest.raises(Refused) as caught:
        t.skeleton(SkeletonMessage("x", 120.0, asf=":root\n  order TX\n:bonedata\n  begin\n"), 0.0)
    assert caught.value.reason == "skeleton"
    small = StreamTable(library, session="t", service=ServiceConfig(max_streams=1))
    announce(small, "a")
    with pytest.raises(Refused) as caught:
        announce(small, "b")
    assert caught.value.reason == "too_many_streams"


def detections(out: list[Emitted]) -> list[tuple[str, int, int, float]]:
    return [
        (e.message.class_name, e.message.start_frame, e.message.end_frame, e.message.cost)
        for e in out
        if isinstance(e.message, DetectionMessage)
    ]


def ids(emitted: list[Emitted]) -> list[str]:
    """The ids of the detections and boundaries among ``emitted``."""
    return [m.id for e in emitted if isinstance(m := e.message, DetectionMessage | BoundaryMessage)]


def drain(t: StreamTable) -> list[Emitted]:
    out = []
    while t.queued:
        out += t.tick()[0]
    return out


def alone(library: Library, frames: range) -> list[tuple[str, int, int, float]]:
    """The recording's ``frames`` (indices) through a recogniser of their own, numbered from 1."""
    m = motion()
    r = Recognizer.for_skeleton(library, m.skeleton, 120.0, session="x")
    found = [d for n, k in enumerate(frames, start=1) for d in r.push(n, m.channels[k])] + r.flush()
    return [(d.class_name, d.start_frame, d.end_frame, d.cost) for d in found]


@pytest.mark.parametrize("epochs", [("a1", "b2"), (None, None)], ids=["epochs", "no epochs"])
def test_a_restarted_source_is_a_new_run(library: Library, epochs: tuple[str | None, str | None]) -> None:
    """Two runs of one source back to back, each numbered from 1 (a replay started twice): each run
    gives what it gives alone (before, the second was refused out_of_order to the end). With epochs
    the second run's skeleton or first pose says so; without, the sequence number going back by more
    than a second of frames does. Poses of a replaced epoch are refused."""
    m = motion()
    frames = range(len(m))  # longer than a second: numbering from 1 again is no reordering
    t = table(library)
    out: list[Emitted] = []
    for epoch in epochs:
        t.skeleton(SkeletonMessage("s", 120.0, asf=ASF.read_text(), angle_unit="rad", epoch=epoch), 0.0)
        for n, k in enumerate(frames, start=1):
            t.pose(PoseMessage("s", n, 0.0, channels=m.channels[k], epoch=epoch), n / 120)
        out += drain(t)
    if epochs[0] is not None:
        with pytest.raises(Refused) as caught:
            t.pose(PoseMessage("s", 99, 0.0, channels=m.channels[0], epoch="a1"), 1.0)
        assert caught.value.reason == "stale_epoch"
        with pytest.raises(Refused) as caught:
            t.skeleton(SkeletonMessage("s", 120.0, asf=ASF.read_text(), angle_unit="rad", epoch="a1"), 1.0)
        assert caught.value.reason == "stale_epoch"
    out += t.flush_all()
    assert alone(library, frames) and detections(out) == alone(library, frames) * 2
    assert t.counts["restarts"] == 1 and t.counts["out_of_order"] == 0


def test_a_new_epoch_in_a_pose_begins_a_run_without_a_skeleton(library: Library) -> None:
    m = motion()
    t = table(library)
    t.skeleton(SkeletonMessage("s", 120.0, asf=ASF.read_text(), angle_unit="rad", epoch="a"), 0.0)
    for epoch in ("a", "b"):
        for n in range(1, 11):
            t.pose(PoseMessage("s", n, 0.0, channels=m.channels[n], epoch=epoch), n / 120)
        drain(t)
    assert t.counts["restarts"] == 1 and t.counts["out_of_order"] == 0


def test_sequence_numbers_a_source_cannot_have_sent_are_refused(library: Library) -> None:
    """One pose numbered 1,000,000 among poses numbered 1, 2, ... is refused (implausible) and the
    stream goes on as if it never came (before: 30 s of out_of_order, then evicted); a jump the
    time since the last pose allows is a gap; one beyond is refused; a little going back is
    out_of_order."""
    m = motion()
    t = table(library)
    announce(t)
    for n in range(1, 101):
        t.pose(PoseMessage("s", n, 0.0, channels=m.channels[n]), n / 120)
    with pytest.raises(Refused) as caught:
        t.pose(PoseMessage("s", 1_000_000, 0.0, channels=m.channels[0]), 101 / 120)
    assert caught.value.reason == "implausible"
    t.pose(PoseMessage("s", 101, 0.0, channels=m.channels[101]), 101 / 120)  # goes on
    later = 101 / 120 + 36  # a pause of 36 s: at most 2 x 36 s of frames + 1 s
    with pytest.raises(Refused) as caught:
        t.pose(PoseMessage("s", 101 + 73 * 120 + 200, 0.0, channels=m.channels[0]), later)
    assert caught.value.reason == "implausible"
    t.pose(PoseMessage("s", 101 + 36 * 120, 0.0, channels=m.channels[102]), later)
    with pytest.raises(Refused) as caught:
        t.pose(PoseMessage("s", 101 + 36 * 120 - 50, 0.0, channels=m.channels[0]), later)
    assert caught.value.reason == "out_of_order"
    drain(t)
    assert t.counts["gaps"] == 1 and t.counts["restarts"] == 0


def test_a_fast_source_after_a_gap_is_refused_once_then_followed(library: Library) -> None:
    """A replay at 4x its announced 120 Hz loses 1 s of poses (a broker restart): the first pose
    after the gap is further ahead than the time allows and is refused, the next follows it and
    confirms the jump, and every later one is taken (before: each was refused as implausible, the
    allowance growing at half the source's pace, for good). Corrupt numbers that do not follow each
    other confirm nothing."""
    m = motion()
    t = table(library)
    announce(t)
    for n in range(1, 101):
        t.pose(PoseMessage("s", n, 0.0, channels=m.channels[n]), n / 480)
    resumed = 100 / 480 + 1.0
    with pytest.raises(Refused) as caught:
        t.pose(PoseMessage("s", 100 + 480, 0.0, channels=m.channels[0]), resumed)
    assert caught.value.reason == "implausible"
    for k in range(1, 400):
        t.pose(PoseMessage("s", 100 + 480 + k, 0.0, channels=m.channels[k % 100]), resumed + k / 480)
    for seq, when in ((20_000_000, 3.0), (10_000_000, 3.01)):
        with pytest.raises(Refused) as caught:
            t.pose(PoseMessage("s", seq, 0.0, channels=m.channels[0]), when)
        assert caught.value.reason == "implausible"
    t.pose(PoseMessage("s", 100 + 480 + 400, 0.0, channels=m.channels[0]), 3.02)
    assert t.streams["s"].last_received == 980
    drain(t)
    assert t.counts["gaps"] == 1


def test_skeleton_change_repeat_and_eviction(library: Library) -> None:
    t = table(library)
    m = motion()
    announce(t)
    for f, c in zip(m.frames.tolist(), m.channels, strict=True):
        t.pose(PoseMessage("s", f, 0.0, channels=c), 1.0)
    while t.queued:
        t.tick()
    announce(t)  # the same skeleton again (a retained message): nothing happens
    assert t.counts["skeleton_changed"] == 0
    flushed = t.skeleton(SkeletonMessage("s", 120.0, JOINT_NAMES), 2.0)  # now positions
    assert t.counts["skeleton_changed"] == 1 and flushed  # the squat's last detections came out
    assert t.evict_idle(3.0, idle_s=5.0) == [] and "s" in t.streams
    assert t.evict_idle(8.0, idle_s=5.0, waiting={"s"}) == [] and "s" in t.streams  # its poses wait
    assert t.evict_idle(8.0, idle_s=5.0) == [] and "s" not in t.streams
    assert t.counts["idle"] == 1


def test_a_refused_skeleton_change_leaves_the_stream_be(library: Library) -> None:
    """A stream's skeleton replaced by one that cannot be recognised (two joints) is refused and the
    stream goes on as it was, its motion's detections all still to come (before: the old stream was
    taken out first, its last detections lost and its poses refused no_skeleton from then on)."""
    m = motion()
    t, whole = table(library), table(library)
    for x in (t, whole):
        announce(x)
    early = []
    for f, c in zip(m.frames.tolist(), m.channels, strict=True):
        for x in (t, whole):
            x.pose(PoseMessage("s", f, 0.0, channels=c), 1.0)
        if f == int(m.frames[len(m) // 2]):
            early = ids(drain(t))
            with pytest.raises(Refused) as caught:
                t.skeleton(SkeletonMessage("s", 120.0, ("a", "b")), 1.0)
            assert caught.value.reason == "skeleton"
    keys = [ids(drain(x) + x.flush_all()) for x in (t, whole)]
    assert early + keys[0] == keys[1] and keys[0]
    assert t.counts["skeleton_changed"] == 0


def test_wire_units_and_axes(library: Library) -> None:
    """Degrees on the wire are converted as the AMC reader converts them; z-up positions turned to
    y-up give the detections of y-up positions."""
    m = motion()
    angles = np.asarray(m.skeleton.angle_channels, dtype=np.intp)
    degrees = m.channels.copy()
    degrees[:, angles] /= DEG
    radians_table, degrees_table = table(library), table(library)
    announce(radians_table)
    degrees_table.skeleton(SkeletonMessage("s", 120.0, asf=ASF.read_text(), angle_unit="deg"), 0.0)
    a = run(radians_table, [PoseMessage("s", k, 0.0, channels=c) for k, c in enumerate(m.channels, 1)])
    b = run(degrees_table, [PoseMessage("s", k, 0.0, channels=c) for k, c in enumerate(degrees, 1)])
    assert [x[:3] for x in a] == [x[:3] for x in b] and a
    assert all(math.isclose(x[3], y[3], abs_tol=1e-6) for x, y in zip(a, b, strict=True))

    p = joint_positions(m).astype(np.float32)
    z_up = np.stack([p[..., 0], -p[..., 2], p[..., 1]], axis=-1)  # y-up turned a quarter about x
    y_table, z_table = table(library), table(library)
    y_table.skeleton(SkeletonMessage("s", 120.0, JOINT_NAMES, up="y"), 0.0)
    z_table.skeleton(SkeletonMessage("s", 120.0, JOINT_NAMES, up="z"), 0.0)
    y = run(y_table, [PoseMessage("s", k, 0.0, positions=q) for k, q in enumerate(p, 1)])
    z = run(z_table, [PoseMessage("s", k, 0.0, positions=q) for k, q in enumerate(z_up, 1)])
    assert y == z and y


# ------------------------------------------------------------------------------------- config


def test_service_sections_and_their_errors(tmp_path: Path) -> None:
    path = tmp_path / "c.yaml"
    path.write_text(
        "service:\n  sources: [mqtt]\n  sinks: [mqtt, stdout]\nmqtt:\n  url: mqtts://broker:8884\n"
    )
    config = load_config(path)
    assert config.service.sources == ("mqtt",) and config.mqtt.url == "mqtts://broker:8884"
    bad = {
        "service:\n  sources: [stdout]\n": "service.sources[0]: must be one of zmq, mqtt",
        "service:\n  sinks: [zmq, zmq]\n": "service.sinks: names a transport twice",
        "service:\n  queue_frames: 0\n": "service.queue_frames",
        "metrics:\n  stream_labels: true\n": "metrics.stream_labels: per-stream labels need service.max",
        "metrics:\n  stream_labels: 1\n": "metrics.stream_labels: must be true or false",
        "service:\n  sources: [mqtt]\nmqtt:\n  url: http://x\n": "mqtt.url: an MQTT broker is",
        "mqtt:\n  reconnect_min_s: 20\n": "mqtt.reconnect_min_s: must not exceed",
        "zmq:\n  hwm: -1\n": "zmq.hwm",
        "service:\n  max_gap_s: 0.5\n": "service.max_gap_s: renamed service.bridge_s",
        "logging:\n  level: loud\n": "logging.level: must be one of debug, info, warning, error",
    }
    for text, message in bad.items():
        path.write_text(text)
        with pytest.raises(ConfigError, match=rf"^{re.escape(str(path))}: {re.escape(message)}"):
            load_config(path)
    assert parse_config(
        {"metrics": {"stream_labels": True}, "service": {"max_streams": 50}}
    ).metrics.stream_labels


def test_environment_overrides() -> None:
    config = environment_overrides(
        Config(),
        {
            "MOCAPD_MQTT_URL": "mqtt://b:1",
            "MOCAPD_SERVICE_SOURCES": "mqtt,zmq",
            "MOCAPD_SERVICE_IDLE_S": "2.5",
            "HOME": "/x",
        },
    )
    assert config.mqtt == dataclasses.replace(MqttConfig(), url="mqtt://b:1")
    assert config.service == dataclasses.replace(ServiceConfig(), sources=("mqtt", "zmq"), idle_s=2.5)
    for env, message in (
        ({"MOCAPD_NOPE_X": "1"}, "MOCAPD_NOPE_X: no section 'nope'"),
        ({"MOCAPD_MQTT_PORT": "1"}, "MOCAPD_MQTT_PORT: mqtt has no field 'port'"),
        (
            {"MOCAPD_SERVICE_IDLE_S": "soon"},
            "MOCAPD_SERVICE_IDLE_S: service.idle_s: must be a positive number",
        ),
        ({"MOCAPD_SERVICE_MAX_STREAMS": "0"}, "MOCAPD_SERVICE_MAX_STREAMS: service.max_streams: must be"),
        ({"MOCAPD_SERVICE_SINKS": ""}, "environment: service.sinks: must name at least one transport"),
        ({"MOCAPD_SERVICE_MAX_GAP_S": "0.5"}, "MOCAPD_SERVICE_MAX_GAP_S: renamed service.bridge_s"),
    ):
        with pytest.raises(ConfigError, match=f"^{re.escape(message)}"):
            environment_overrides(Config(), env)


def test_replay_clock_does_not_drift() -> None:
    """Each frame's due time is computed from the start, never from the previous frame's."""
    assert due(10.0, 0, 120.0, 1.0) == 10.0
    assert due(10.0, 120 * 3600, 120.0, 1.0) == 10.0 + 3600.0
    assert due(10.0, 240, 120.0, 2.0) == 11.0
    assert due(10.0, 10**6, 120.0, None) == 10.0


# ---------------------------------------------------------------------------- behaviour boundaries

SEGMENTED = (DATA / "cmu" / "13" / "13.asf", DATA / "cmu" / "13" / "13_30.amc.gz")


@pytest.mark.slow
@pytest.mark.parametrize("method", ["pca", "ppca"])
def test_boundaries_are_the_online_methods_batch_cuts(
    library: Library, method: Literal["pca", "ppca"]
) -> None:
    """A segmented stream's boundaries are its recording's batch cuts (PCA; PPCA's forward pass) in
    sequence numbers, also across a long gap (each side segmented on its own); a stream its
    patterns do not name, and a stream of positions, get none."""
    m = read_recording(*SEGMENTED)
    x = JointRotations(m.skeleton)(m.channels)
    batch = partial(bh.pca_segment, params=bh.PCA_ONLINE) if method == "pca" else bh.ppca_forward
    t = StreamTable(
        library,
        session="t",
        service=ServiceConfig(queue_frames=100_000),
        segmentation=SegmentationConfig(method, ("seg*",)),
    )
    asf = SEGMENTED[0].read_text()
    for name in ("seg", "plain"):
        t.skeleton(SkeletonMessage(name, 120.0, asf=asf, angle_unit="rad"), 0.0)
    t.skeleton(SkeletonMessage("segpos", 120.0, joints=tuple(JOINT_NAMES)), 0.0)
    cut = 1500  # a gap of 10 s after frame cut: the motion ends, a new one begins
    seqs = [int(f) if k < cut else int(f) + 1200 for k, f in enumerate(m.frames)]
    positions = joint_positions(m)
    for k, (seq, c) in enumerate(zip(seqs, m.channels, strict=True)):
        now = seq / 120.0  # the poses arrive as they were taken (the gap is 10 s long)
        t.pose(PoseMessage("seg", seq, 0.0, channels=c), now)
        t.pose(PoseMessage("plain", seq, 0.0, channels=c), now)
        t.pose(PoseMessage("segpos", seq, 0.0, positions=positions[k].astype(np.float32)), now)
    out = []
    while t.queued:
        out += t.tick()[0]
    out += t.flush_all()
    got = [
        (e.message.stream, e.message.frame, e.message.method)
        for e in out
        if isinstance(e.message, BoundaryMessage)
    ]
    want = [("seg", seqs[b.frame], method) for b in batch(x[:cut], 120.0)]
    want += [("seg", seqs[cut + b.frame], method) for b in batch(x[cut:], 120.0)]
    assert got == want != []
    ids = [e.message.id for e in out if isinstance(e.message, BoundaryMessage)]
    assert len(set(ids)) == len(ids)
    # each boundary names the behaviour that ended (none of this library's detections lie in one:
    # test_segment_summaries.py has them); the motion begins anew after the gap
    events: list[DetectionMessage | SegmentSummary | int] = []
    for e in out:
        said = e.message
        if isinstance(said, BoundaryMessage) and said.frame >= seqs[cut] and seqs[cut] not in events:
            events.append(seqs[cut])
        if isinstance(said, DetectionMessage | BoundaryMessage) and said.stream == "seg":
            events.append(said)
    assert check_segment_summaries(events, seqs[0]) == len(want)


@pytest.mark.slow
def test_a_bvh_streams_boundaries_are_its_rigs_batch_cuts(library: Library) -> None:
    """A segmented BVH stream (13_30 written as BVH) is cut on its rig's joint rotations, as
    ``mocapd segment --bvh`` cuts the take: its boundaries are the batch cuts (PPCA's forward pass)
    in sequence numbers, across a gap of four lost poses (their channel rows bridged, angles the
    short way round in degrees) and a long gap (each side segmented on its own)."""
    m = read_recording(*SEGMENTED)
    take = motion_to_bvh(m, 120.0)
    rig = bh.RigRotations(take.hierarchy, bvh_standard_joints(take)[1])
    t = StreamTable(
        library,
        session="t",
        service=ServiceConfig(queue_frames=100_000),
        segmentation=SegmentationConfig("ppca", ("seg*",)),
    )
    t.skeleton(SkeletonMessage("segbvh", 120.0, bvh=hierarchy_text(take.hierarchy)), 0.0)
    channels = take.channels
    lost, cut = range(700, 704), 1500
    seqs = [k + 1 if k < cut else k + 1 + 1200 for k in range(len(channels))]
    for k, (seq, c) in enumerate(zip(seqs, channels, strict=True)):
        if k not in lost:
            t.pose(PoseMessage("segbvh", seq, 0.0, channels=c), seq / 120.0)
    out = []
    while t.queued:
        out += t.tick()[0]
    out += t.flush_all()
    got = [e.message.frame for e in out if isinstance(e.message, BoundaryMessage)]
    first = channels[:cut].copy()
    angles = np.array([k for k, n in enumerate(take.hierarchy.channel_names) if n.endswith("rotation")])
    first[lost.start : lost.stop] = bridge(
        channels[lost.start - 1], channels[lost.stop], len(lost), angles, 360.0
    )
    want = [seqs[b.frame] for b in bh.ppca_forward(rig(first), 120.0)]
    want += [seqs[cut + b.frame] for b in bh.ppca_forward(rig(channels[cut:]), 120.0)]
    assert got == want != []


def test_streams_of_one_skeleton_share_its_tables(library: Library) -> None:
    """Streams announcing the same ASF text are parsed once and share the forward kinematics, yet
    each stream's skeleton is named after it."""
    t = table(library)
    for stream in ("a", "b"):
        announce(t, stream)
    assert t.bank["a"].model is t.bank["b"].model is not None
    sources = [s.skeleton.source if s.skeleton else None for s in (t.streams["a"], t.streams["b"])]
    assert sources == ["<skeleton of a>", "<skeleton of b>"]


@pytest.mark.parametrize("ticked", [0, 200, 10**6], ids=["all queued", "some queued", "none queued"])
def test_an_end_gives_the_streams_last_detections_once_its_poses_are_recognised(
    library: Library, ticked: int
) -> None:
    """The end of a run, whenever it arrives among the ticks: exactly the detections of a
    recogniser flushed after the run's last pose (no more once the stream is gone), the stream
    forgotten as ``ended``; a second end, or one of a stream not held, changes nothing."""
    t = table(library)
    announce(t)
    m = motion()
    poses = [
        PoseMessage("s", int(f), 0.0, channels=c, epoch="e1")
        for f, c in zip(m.frames, m.channels, strict=True)
    ]
    for p in poses:
        t.pose(p, 0.0)
    out = []
    for _ in range(ticked):
        if not t.queued:
            break
        out += t.tick()[0]
    out += t.end(EndMessage("s", poses[-1].seq, "e1"))
    assert ("s" in t.streams) == bool(t.queued)
    out += drain(t)
    assert "s" not in t.streams and t.counts["ended"] == 1 and t.queued == 0
    assert t.end(EndMessage("s", poses[-1].seq, "e1")) == [] and t.flush_all() == []
    assert detections(out) == detections_of(library, poses) != []


def detections_of(library: Library, poses: list[PoseMessage]) -> list[tuple[str, int, int, float]]:
    """The poses' frames through a recogniser of their own, flushed after the last."""
    r = Recognizer.for_skeleton(library, motion().skeleton, 120.0, session="x")
    found = [d for p in poses if p.channels is not None for d in r.push(p.seq, p.channels)] + r.flush()
    return [(d.class_name, d.start_frame, d.end_frame, d.cost) for d in found]


def test_the_end_of_another_run(library: Library) -> None:
    """An end of a replaced run is refused; of a run not taken, ignored; a new run after an end
    that waits for its queue keeps the stream (the end was the old run's)."""
    t = table(library)
    announce(t)
    m = motion()
    t.pose(PoseMessage("s", 1, 0.0, channels=m.channels[0], epoch="e1"), 0.0)
    assert t.end(EndMessage("s", 1, "other")) == [] and "s" in t.streams
    t.end(EndMessage("s", 1, "e1"))  # one pose queued: it waits
    t.pose(PoseMessage("s", 1, 0.0, channels=m.channels[0], epoch="e2"), 0.0)  # a new run
    drain(t)
    assert "s" in t.streams and t.counts["ended"] == 0
    with pytest.raises(Refused) as caught:
        t.end(EndMessage("s", 1, "e1"))
    assert caught.value.reason == "stale_epoch"
    t.end(EndMessage("s", 1, "e2"))
    assert "s" not in t.streams and t.counts["ended"] == 1


MIXAMO_OF = {
    "root": "Hips", "lhip": "LeftUpLeg", "lknee": "LeftLeg", "lankle": "LeftFoot", "ltoes": "LeftToe_End",
    "rhip": "RightUpLeg", "rknee": "RightLeg", "rankle": "RightFoot", "rtoes": "RightToe_End",
    "belly": "Spine", "chest": "Spine2", "neck": "Neck", "head": "Head", "headtop": "HeadTop_End",
    "lshoulder": "LeftArm", "lelbow": "LeftForeArm", "lwrist": "LeftHand",
    "rshoulder": "RightArm", "relbow": "RightForeArm", "rwrist": "RightHand",
}  # fmt: skip
"""A Mixamo rig's names for the standard joints it has: no fingers, no thumbs, no clavicle joints."""


def test_a_positions_stream_of_a_rigs_names_without_fingers_is_mapped_and_recognised(
    library: Library,
) -> None:
    """A positions stream announced with Mixamo's names (``mixamorig:``, no fingers or thumbs) is
    taken through its rig map (:mod:`replay.rigs`: the fingers and thumbs derived): the table gives
    the batch twin's detections of the mapped joints, the squat among them. A rig no map fits is
    refused as a skeleton, naming what it lacks."""
    p = joint_positions(motion())
    names = tuple(f"mixamorig:{n}" for n in MIXAMO_OF.values())
    rig = p[:, [JOINT_NAMES.index(j) for j in MIXAMO_OF]].astype(np.float32)
    t = table(library)
    t.skeleton(SkeletonMessage("s", 120.0, names), 0.0)
    got = run(t, [PoseMessage("s", k, 0.0, positions=q) for k, q in enumerate(rig, 1)])
    plan = rig_plan(names, [True] * len(names), "x")
    mapped = standard_joints(rig.astype(np.float64), plan)
    want = detect_positions(mapped, np.arange(1, len(mapped) + 1), library, 120.0, session="t")
    assert [x[:3] for x in got] == [(d.class_name, d.start_frame, d.end_frame) for d in want]
    assert "squat1Reps" in {x[0] for x in got}
    with pytest.raises(Refused) as caught:
        table(library).skeleton(SkeletonMessage("s", 120.0, names[1:]), 0.0)
    assert caught.value.reason == "skeleton" and "finds no root" in str(caught.value)


def test_a_bvh_stream_is_taken_through_its_rig_as_the_take_is(library: Library) -> None:
    """A skeleton carrying a BVH hierarchy (here the squat clip written as BVH, ASF bone names) and
    poses carrying its channel rows: the table gives the batch twin's detections of the take's
    standard joints, costs and all (the channels are float64 on the wire). A pose of another width
    is refused as ``shape``; a hierarchy no rig map fits, as ``skeleton``."""
    take = parse_bvh(write_bvh(motion_to_bvh(motion(), 120.0)), "squat")
    joints, _ = bvh_standard_joints(take)
    t = table(library)
    t.skeleton(SkeletonMessage("s", 120.0, bvh=hierarchy_text(take.hierarchy)), 0.0)
    got = run(t, [PoseMessage("s", k, 0.0, channels=c) for k, c in enumerate(take.channels, 1)])
    want = detect_positions(joints, np.arange(1, len(joints) + 1), library, 120.0, session="t")
    assert got == [(d.class_name, d.start_frame, d.end_frame, d.cost) for d in want]
    assert "squat1Reps" in {x[0] for x in got}
    t.skeleton(SkeletonMessage("s", 120.0, bvh=hierarchy_text(take.hierarchy)), 0.0)
    with pytest.raises(Refused) as caught:
        t.pose(PoseMessage("s", 1, 0.0, channels=take.channels[0][:-1]), 0.0)
    assert caught.value.reason == "shape"
    lone = "HIERARCHY\nROOT Pelvis\n{\n\tOFFSET 0 0 0\n\tCHANNELS 3 Xposition Yposition Zposition\n}\n"
    with pytest.raises(Refused) as caught:
        t.skeleton(SkeletonMessage("s", 120.0, bvh=lone), 0.0)
    assert caught.value.reason == "skeleton" and "no rig map fits" in str(caught.value)


def test_a_positions_stream_of_names_only_a_users_rig_map_knows_is_mapped_by_it(library: Library) -> None:
    """``replay.rig_maps`` reach the table (``rigs``): a stream announcing names no built-in map
    fits is refused without the user's map and recognised with it, as the batch twin does."""
    p = joint_positions(motion())
    names = tuple(f"node{k}" for k in range(len(JOINT_NAMES)))
    user = parse_rig_map({"joints": dict(zip(JOINT_NAMES, names, strict=True))}, "studio.yaml")
    with pytest.raises(Refused) as caught:
        table(library).skeleton(SkeletonMessage("s", 120.0, names), 0.0)
    assert caught.value.reason == "skeleton"
    t = StreamTable(library, session="t", service=ServiceConfig(queue_frames=100_000), rigs=(user, *BUILT_IN))
    t.skeleton(SkeletonMessage("s", 120.0, names), 0.0)
    wire = p.astype(np.float32)
    got = run(t, [PoseMessage("s", k, 0.0, positions=q) for k, q in enumerate(wire, 1)])
    want = detect_positions(wire.astype(np.float64), np.arange(1, len(p) + 1), library, 120.0, session="t")
    assert got == [(d.class_name, d.start_frame, d.end_frame, d.cost) for d in want] and got
