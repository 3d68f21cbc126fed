"""The live view's state (daemon/service/view/state.py), pure: real recordings' messages in, the
browsers' updates out; decimation, the joints drawn, rate, lag, missing poses, refusals, bounds."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from daemon.recordings import read_recording
from daemon.service.metrics import Metrics
from daemon.service.view.state import (
    BONE_INDICES,
    DETECTIONS_KEPT,
    ENDED_KEPT,
    INSTANCES_KEPT,
    ViewState,
    closeness,
    daemon_health,
)
from protocols.messages import (
    STATUS_REMINDER_S,
    ClassProgress,
    DetectionMessage,
    EndMessage,
    Message,
    PoseMessage,
    ProgressMessage,
    SkeletonMessage,
    StatusMessage,
    encode,
    frame_of,
    topic,
)
from protocols.publish import messages
from protocols.transport import Incoming
from replay import JOINT_NAMES
from replay.bvh import BvhKinematics, hierarchy_text, read_bvh
from replay.rigs import bvh_standard_joints
from tests.helpers import DATA, joints_cm

ASF, AMC = DATA / "cmu" / "13" / "13.asf", DATA / "cmu" / "13" / "13_30.amc.gz"
BANDAI_TAKE = DATA / "bandai2" / "dataset-2_raise-up-left-hand_youthful_002.bvh.gz"
XSS = ("<script>window.__xss=1</script>", '<img src=x onerror="window.__xss=1">')


def wire(message: Message, at: float = 1000.0) -> Incoming:
    return Incoming(topic(message), encode(message), at)


def feed(state: ViewState, items: list[Message], rate: float = 120.0) -> list[dict[str, object]]:
    """Every message at its own time (pose k at k / rate seconds); the updates."""
    out = []
    for k, m in enumerate(items):
        out += state.take(wire(m, 1000.0 + k / rate), k / rate)
    return out


def recording(stream: str = "13_30", angle_unit: str = "rad") -> list[Message]:
    motion = read_recording(ASF, AMC)
    items: list[Message] = list(messages(motion, ASF.read_text(), stream, 120.0, 1, epoch="run1"))
    if angle_unit == "deg":
        skeleton = items[0]
        assert isinstance(skeleton, SkeletonMessage)
        angles = np.asarray(motion.skeleton.angle_channels)
        items[0] = SkeletonMessage(stream, 120.0, asf=skeleton.asf, angle_unit="deg", epoch="run1")
        for k, m in enumerate(items[1:-1], 1):  # the poses, before the run's end
            assert isinstance(m, PoseMessage) and m.channels is not None
            c = m.channels.copy()
            c[angles] = np.degrees(c[angles])
            items[k] = PoseMessage(stream, m.seq, 1000.0 + k / 120, channels=c, epoch="run1")
    return [
        PoseMessage(m.stream, m.seq, 1000.0 + k / 120, channels=m.channels, epoch=m.epoch)
        if isinstance(m, PoseMessage)
        else m
        for k, m in enumerate(items)
    ]


@pytest.mark.parametrize("angle_unit", ["rad", "deg"])
def test_a_channel_stream_is_drawn_by_forward_kinematics_decimated(angle_unit: str) -> None:
    state = ViewState(30.0)
    out = feed(state, recording(angle_unit=angle_unit))
    poses = [e for e in out if e["type"] == "pose"]
    assert [e["type"] for e in out[:1]] == ["stream"]
    assert len(poses) == pytest.approx(2465 / 4, abs=2)  # 120 Hz to at most 30 a second
    want = joints_cm(ASF, AMC)
    for e in poses:
        frame = int(e["seq"]) - 1  # type: ignore[call-overload]
        got = np.array(e["p"]).reshape(26, 3) / 10  # whole millimetres
        np.testing.assert_allclose(got, want[frame], atol=0.0501)
    s = state.streams["13_30"]
    assert (s.received, s.missing, s.drawn) == (2465, 0, len(poses))


def test_a_frame_messages_subjects_are_drawn_as_their_own_poses() -> None:
    """Two streams of a recording sent together in frame messages (as ``replay --with`` does), a
    bad subject among them: each stream drawn as its pose messages are, the bad one refused alone,
    the run's end on the frame topic shown as nothing."""
    items = recording()
    skeleton, poses, end = items[0], items[1:-1], items[-1]
    assert isinstance(skeleton, SkeletonMessage) and isinstance(end, EndMessage)
    alone, framed = ViewState(30.0), ViewState(30.0)
    other = dataclasses.replace(skeleton, stream="twin")
    for state in (alone, framed):
        state.take(wire(skeleton), 0.0)
        state.take(wire(other), 0.0)
    want, got = [], []
    for k, m in enumerate(poses):
        assert isinstance(m, PoseMessage)
        subjects = [m, dataclasses.replace(m, stream="twin")]
        for p in subjects:
            want += alone.take(wire(p, 1000.0 + k / 120), k / 120)
        if k == 7:
            subjects.append(PoseMessage("lost", 1, m.time, channels=np.full(3, np.nan)))
        got += framed.take(wire(frame_of(subjects, "rig"), 1000.0 + k / 120), k / 120)
    got += framed.take(Incoming("mocap/rig/frame", encode(end), 1000.0), len(poses) / 120)
    drawn = [e for e in got if e["type"] == "pose"]
    assert drawn and drawn == [e for e in want if e["type"] == "pose"]
    assert framed.refusals == {"non_finite": 1}
    assert framed.streams["twin"].received == alone.streams["twin"].received == len(poses)


def test_a_positions_stream_is_gathered_by_name_in_cm_y_up() -> None:
    rng = np.random.default_rng(1)
    names = ["extra", *reversed(JOINT_NAMES)]
    joints = rng.normal(size=(len(names), 3)).astype(np.float32)
    state = ViewState(30.0)
    state.take(wire(SkeletonMessage("s", 60.0, tuple(names), up="z", units="m")), 0.0)
    (made, pose) = state.take(wire(PoseMessage("s", 5, 999.0, positions=joints)), 0.0)
    assert made == {"type": "stream", "stream": "s", "kind": "positions", "rate": 60.0, "ended": False}
    by_name = {n: joints[i].astype(np.float64) * 100 for i, n in enumerate(names)}
    want = np.array([[by_name[j][0], by_name[j][2], -by_name[j][1]] for j in JOINT_NAMES])
    np.testing.assert_allclose(np.array(pose["p"]).reshape(26, 3) / 10, want, atol=0.0501)
    assert all(0 <= a < 26 and 0 <= b < 26 and a != b for a, b in BONE_INDICES)


def test_a_bvh_stream_and_a_rigs_positions_are_drawn_through_the_rig_map() -> None:
    """The view draws what the daemon recognises: a BVH stream's channel rows (a bandai2 take,
    CC BY-NC-ND 4.0, read unmodified) and a positions stream of the rig's own names, each through
    its rig map (:mod:`replay.rigs`), in whole millimetres."""
    take = read_bvh(BANDAI_TAKE)
    joints, _ = bvh_standard_joints(take)
    state = ViewState(30.0)
    state.take(wire(SkeletonMessage("b", 30.0, bvh=hierarchy_text(take.hierarchy))), 0.0)
    (made, pose) = state.take(wire(PoseMessage("b", 7, 0.0, channels=take.channels[6])), 0.0)
    assert made == {"type": "stream", "stream": "b", "kind": "bvh", "rate": 30.0, "ended": False}
    np.testing.assert_allclose(np.array(pose["p"]).reshape(26, 3) / 10, joints[6], atol=0.0501)
    points = [k for k, j in enumerate(take.hierarchy.joints) if not j.end_site or any(j.offset)]
    names = tuple(take.hierarchy.joints[k].name for k in points)  # its End Sites at their joints left out
    nodes = BvhKinematics(take.hierarchy).positions(take.channels[6:7])[0, points].astype(np.float32)
    state.take(wire(SkeletonMessage("r", 30.0, names)), 0.0)
    (made, pose) = state.take(wire(PoseMessage("r", 7, 0.0, positions=nodes)), 0.0)
    assert made["kind"] == "positions"
    np.testing.assert_allclose(np.array(pose["p"]).reshape(26, 3) / 10, joints[6], atol=0.06)


def test_rate_lag_and_missing_poses() -> None:
    state = ViewState(30.0)
    state.take(wire(SkeletonMessage("s", 120.0, JOINT_NAMES)), 0.0)
    p = np.zeros((26, 3), np.float32)
    state.tick(0.0)
    seqs = [*range(1, 61), *range(71, 131), 130, 129]  # 10 lost, a repeat, one overtaken
    for k, seq in enumerate(seqs):
        state.take(
            Incoming("mocap/s/pose", encode(PoseMessage("s", seq, 100.0 + k / 120, p)), 100.025 + k / 120),
            k / 120,
        )
    (stats,) = state.tick(1.0)
    (s,) = stats["streams"]
    assert s["missing"] == 10 and s["received"] == 120 and s["rate"] == 120.0
    assert s["lag"] == pytest.approx(0.025, abs=1e-6)
    # a new run of the source (another epoch) numbers afresh: nothing missing
    for seq in (1, 2, 4):
        state.take(wire(PoseMessage("s", seq, 101.0, p, epoch="b")), 1.1)
    assert state.streams["s"].missing == 11


@pytest.mark.parametrize("step", [1, 3, 4])
def test_the_relays_thinning_is_not_counted_missing(step: int) -> None:
    """Over ZeroMQ the daemon relays every ``step``-th pose it took in: gaps of ``step`` are its
    sampling (shown as such), and only what lies beyond them the publisher's loss. On MQTT every
    gap is a loss."""
    p = np.zeros((26, 3), np.float32)
    lost = {17, 18, 40}  # never sent by the publisher
    taken = [q for q in range(1, 121) if q not in lost]
    relayed = taken[::step]  # the daemon's relay: every step-th pose it took in
    for bus, want_sampled in ((True, step), (False, 1)):
        state = ViewState(30.0, relayed=bus)
        state.take(wire(SkeletonMessage("s", 120.0, JOINT_NAMES)), 0.0)
        for k, seq in enumerate(relayed):
            state.take(wire(PoseMessage("s", seq, 100.0, p)), k / 120)
        (s,) = state.tick(2.0)[-1]["streams"]
        gaps = np.diff(relayed)
        expected = int((gaps - (gaps.min() if bus else 1)).sum())
        assert s["sampled"] == want_sampled and s["missing"] == expected
        if bus:  # the relay's count is a lower bound of the publisher's loss, exact unthinned
            assert 0 < s["missing"] <= len(lost) and (step > 1 or s["missing"] == len(lost))
        else:
            assert s["missing"] == len(lost) + (step - 1) * (len(relayed) - 1)


def test_a_stream_goes_after_being_idle_and_its_state_is_bounded() -> None:
    state = ViewState(30.0, idle_s=10.0, max_streams=3)
    for k in range(200):
        d = DetectionMessage(f"id{k % 120}", "a", "Squat", k, k + 9, 0.01, 0.2, k + 12, 1.0, 2.0)
        state.take(wire(d), 0.0)
    a = state.streams["a"]
    assert len(a.detections) == DETECTIONS_KEPT and len(a.ids) <= 4 * DETECTIONS_KEPT
    progress = ProgressMessage("b", 40, (ClassProgress("Squat", 3, (10, 20), 0.5, 0.03, 0.2),), 1.0, 1.0)
    assert [e["type"] for e in state.take(wire(progress), 5.0)] == ["stream", "progress"]
    state.take(wire(progress), 5.0)  # the same stream: no new one
    state.take(wire(DetectionMessage("x", "c", "Jog", 1, 2, 0.0, 0.1, 3, 1.0, 2.0)), 5.0)
    (refused,) = state.take(wire(DetectionMessage("y", "d", "Jog", 1, 2, 0.0, 0.1, 3, 1.0, 2.0)), 5.0)
    assert refused["reason"] == "schema" and "more than 3 streams" in str(refused["detail"])
    events = state.tick(10.5)
    assert [e["stream"] for e in events if e["type"] == "ended"] == ["a"]  # kept, with its history
    assert [s["stream"] for s in events[-1]["streams"]] == ["b", "c"]
    assert state.streams["a"].ended and len(state.streams["a"].detections) == DETECTIONS_KEPT
    # an ended stream is no live one: another may come; its late detection joins it, ended
    assert [e["type"] for e in state.take(wire(dataclasses.replace(progress, stream="d")), 11.0)] == [
        "stream",
        "progress",
    ]
    late = DetectionMessage("late", "a", "Squat", 300, 309, 0.01, 0.2, 312, 1.0, 2.0)
    assert [e["type"] for e in state.take(wire(late), 12.0)] == ["detection"]
    assert state.streams["a"].ended and state.streams["a"].detections[-1]["id"] == "late"
    assert [e["id"] for e in state.snapshot()["log"]][-3:] == ["id119", "x", "late"]
    shown = {i["stream"]: i["ended"] for i in state.snapshot()["streams"]}
    assert shown == {"a": True, "b": False, "c": False, "d": False}
    # a pose makes it live again (once a live one has ended, under max_streams)
    state.tick(21.5)  # b, c, d end
    assert sorted(n for n, v in state.streams.items() if v.ended) == ["a", "b", "c", "d"]
    state.take(wire(SkeletonMessage("a", 120.0, JOINT_NAMES)), 22.0)
    (made, *_) = state.take(wire(PoseMessage("a", 1, 1.0, np.zeros((26, 3), np.float32))), 22.0)
    assert made == {"type": "stream", "stream": "a", "kind": "positions", "rate": 120.0, "ended": False}
    assert state.streams["a"].detections[-1]["id"] == "late"  # its history kept
    # the longest ended go once ENDED_KEPT have ended after them
    gone = []
    for k in range(ENDED_KEPT):
        state.take(wire(DetectionMessage(f"e{k}", f"e{k}", "Jog", 1, 2, 0.0, 0.1, 3, 1.0, 2.0)), 100.0 + k)
        gone += [e["stream"] for e in state.tick(111.0 + k) if e["type"] == "gone"]
    assert sum(v.ended for v in state.streams.values()) == ENDED_KEPT
    assert gone == ["b", "c", "d", "a"]  # in the order they ended (a at 32.0)
    json.dumps(state.snapshot(), allow_nan=False)


def test_what_cannot_be_used_is_refused_and_listed_as_text() -> None:
    state = ViewState(30.0)
    bad_topic = Incoming(
        f"mocap/{XSS[1]}/pose", encode(PoseMessage("s", 1, 1.0, np.zeros((26, 3), np.float32))), 5.0
    )
    (r,) = state.take(bad_topic, 0.0)
    assert r == {
        "type": "refused",
        "topic": f"mocap/{XSS[1]}/pose",
        "reason": "schema",
        "detail": "not a topic of mocapd's (mocap/<stream>/<kind>)",
        "time": 5.0,
    }
    assert state.take(bad_topic, 0.5) == []  # listed at most once a second per reason, all counted
    other = DetectionMessage("x", "s", XSS[0], 1, 2, 0.0, 0.1, 3, 1.0, 2.0)
    cases = [
        (Incoming("mocap/t/detections", encode(other), 0.0), "schema"),  # another stream's topic
        (Incoming("mocap/s/pose", encode(other), 0.0), "type"),
        (Incoming("mocap/s/pose", b"\xc1", 0.0), "undecodable"),
        (Incoming("mocap/s/pose", b"", 0.0), "undecodable"),
        (Incoming("mocap/s/pose", b"\x82\xa1v\x02\xa4type\xa4pose", 0.0), "version"),
    ]
    for k, (incoming, reason) in enumerate(cases):
        (r,) = state.take(incoming, 2.0 * (k + 1))
        assert r["reason"] == reason, (incoming, r)
    assert state.refusals["schema"] == 3 and sum(state.refusals.values()) == 7
    (d,) = state.take(wire(other), 20.0)[1:]
    assert d["class"] == XSS[0]  # kept as it came (the page shows it as text)
    # a pose of a skeleton it does not fit, and a skeleton neither of the standard joints nor of a rig
    state.take(wire(SkeletonMessage("p", 120.0, JOINT_NAMES)), 30.0)
    (s, r) = state.take(wire(PoseMessage("p", 1, 1.0, np.zeros((3, 3), np.float32))), 30.0)
    assert (s["type"], r["reason"]) == ("stream", "shape")
    (r,) = state.take(wire(SkeletonMessage("q", 120.0, ("root", "lhip"))), 30.0)
    assert r["reason"] == "schema" and "no rig map fits" in str(r["detail"])


def test_statuses_and_their_clearing() -> None:
    state = ViewState(30.0)
    online = StatusMessage("d-1", "online", "0.1.0", 2, 5.0)
    assert state.take(wire(online), 0.0) == [
        {
            "type": "status",
            "instance": "d-1",
            "state": "online",
            "version": "0.1.0",
            "streams": 2,
            "started": 5.0,
            "stale": False,
        }
    ]
    (r,) = state.take(Incoming("mocapd/d-2/status", encode(online), 0.0), 0.0)
    assert r["reason"] == "schema"  # another instance's status
    assert state.take(Incoming("mocapd/d-1/status", b"", 0.0), 0.0) == [
        {"type": "status_gone", "instance": "d-1"}
    ]
    assert state.snapshot()["statuses"] == []


@given(
    st.floats(0.0, 1.0),
    st.floats(0.0, 10.0, allow_subnormal=False),
    st.floats(1e-6, 10.0),
    st.floats(0.0, 1.0),
)
def test_closeness_is_position_times_the_share_of_tau_left(
    position: float, cost: float, tau: float, more: float
) -> None:
    """The bar: in [0, 1], 0 at position 0 or at τ and past it (the daemon's "none within τ" is
    position 0, cost τ), growing with the position and falling with the cost."""
    level = closeness(position, cost, tau)
    assert 0.0 <= level <= 1.0
    assert level == pytest.approx(position * max(0.0, 1 - cost / tau), abs=1e-4)
    assert closeness(0.0, tau, tau) == 0.0 and closeness(position, tau * (1 + more), tau) == 0.0
    assert closeness(min(1.0, position + more), cost, tau) >= level
    assert closeness(position, cost + more * tau, tau) <= level
    assert closeness(float("nan"), cost, tau) == 0.0 and closeness(position, cost, 0.0) == 0.0


def test_a_progress_update_carries_each_class_closeness() -> None:
    state = ViewState(30.0)
    c = ClassProgress("Squat", 3, (10, 20), 0.8, 0.05, 0.2)
    (_, event) = state.take(wire(ProgressMessage("s", 40, (c,), 1.0, 1.0)), 0.0)
    assert event["classes"][0]["level"] == closeness(0.8, 0.05, 0.2) == 0.6


def statuses_stale(state: ViewState) -> dict[str, bool]:
    return {e["instance"]: e["stale"] for e in state.snapshot()["statuses"]}


def test_a_status_not_reminded_for_two_periods_is_stale() -> None:
    """A daemon says ``online`` again every STATUS_REMINDER_S (ZeroMQ and MQTT): silent for two
    periods, it went without a word (kill -9), or it was a client's retained fake; heard again, it
    is live. An offline one never goes stale."""
    period = STATUS_REMINDER_S
    state = ViewState(30.0)
    state.take(wire(StatusMessage("d-1", "online", "1", 0, 5.0)), 0.0)
    state.take(wire(StatusMessage("d-2", "offline", "1", 0, 5.0)), 0.0)
    state.take(wire(StatusMessage("d-1", "online", "1", 0, 5.0)), period)  # reminded
    assert not [e for e in state.tick(3 * period) if e["type"] == "status"]
    stale = [e for e in state.tick(3 * period + 0.1) if e["type"] == "status"]
    assert [(e["instance"], e["stale"]) for e in stale] == [("d-1", True)]  # not the offline one
    assert not [e for e in state.tick(3 * period + 1.1) if e["type"] == "status"]  # said once
    assert statuses_stale(state) == {"d-1": True, "d-2": False}
    (back,) = state.take(wire(StatusMessage("d-1", "online", "1", 0, 5.0)), 4 * period)
    assert back["stale"] is False and statuses_stale(state)["d-1"] is False


def test_a_flood_of_statuses_evicts_stale_and_offline_ones_first() -> None:
    state = ViewState(30.0)
    state.take(wire(StatusMessage("real", "online", "1", 3, 5.0)), 0.0)
    state.take(wire(StatusMessage("gone", "online", "1", 0, 5.0)), 0.0)
    state.take(wire(StatusMessage("old", "offline", "1", 0, 5.0)), 0.0)
    for k in range(1, 8):  # the real one reminds; "gone" does not
        state.take(wire(StatusMessage("real", "online", "1", 3, 5.0)), k * STATUS_REMINDER_S)
        state.tick(k * STATUS_REMINDER_S + 0.5)
    for k in range(INSTANCES_KEPT - 1):
        state.take(wire(StatusMessage(f"fake-{k}", "online", "1", 0, 5.0)), 40.0)
    kept = statuses_stale(state)
    assert len(kept) == INSTANCES_KEPT and "real" in kept
    assert "gone" not in kept and "old" not in kept
    (_, gone) = state.take(wire(StatusMessage("fake-last", "online", "1", 0, 5.0)), 40.0)
    assert gone == {"type": "status_gone", "instance": "real"}  # the pages are told
    assert "real" not in statuses_stale(state)  # the longest unheard of the live ones, bounded ...
    state.take(wire(StatusMessage("real", "online", "1", 3, 5.0)), 40.0 + STATUS_REMINDER_S)
    kept = statuses_stale(state)  # ... until its next reminder
    assert len(kept) == INSTANCES_KEPT and kept["real"] is False


def test_the_daemons_health_from_its_own_metrics() -> None:
    metrics = Metrics(True, lambda: ({}, {"lagging": 3, "mqtt_incoming_full": 1}, {}), lambda: (1, 0, 0, {}))
    metrics.frame_in("a")
    metrics.frame_in("a")
    metrics.detection_out("a")
    h = daemon_health(200, "ok\n", metrics.exposition().decode())
    assert h["healthy"] is True and h["text"] == "ok"
    assert h["drops"] == 4 and h["drops_by_reason"] == {"lagging": 3, "mqtt_incoming_full": 1}
    assert h["streams"] == {"a": {"frames_in": 2, "detections_out": 1}}
    down = daemon_health(503, "mqtt: connection refused\n", "not {prometheus")
    assert (down["healthy"], down["text"], down["drops"]) == (False, "mqtt: connection refused", None)
    assert daemon_health(None, "no answer", None)["healthy"] is None


def test_the_page_is_shipped(tmp_path: Path) -> None:
    from daemon.service.view.server import STATIC

    assert {p.name for p in STATIC.iterdir()} >= {"index.html", "view.js", "view.css"}
    page = (STATIC / "view.js").read_text()
    assert "innerHTML" not in page and "insertAdjacentHTML" not in page and "document.write" not in page
