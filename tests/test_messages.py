"""The wire (protocols/messages.py): every message type survives encode/decode exactly (hypothesis),
and every way a payload can be wrong is refused with its reason code and nothing else."""

from __future__ import annotations

import re
from typing import Any

import msgpack
import numpy as np
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st

from protocols.messages import (
    MAX_SEGMENT_DETECTIONS,
    MAX_SEQ,
    REASONS,
    BoundaryMessage,
    ClassProgress,
    DetectionMessage,
    EndMessage,
    FrameMessage,
    Message,
    PoseMessage,
    ProgressMessage,
    SegmentDetection,
    SkeletonMessage,
    StatusMessage,
    WireError,
    decode,
    encode,
    frame_of,
    parse_topic,
    topic,
)
from replay import JOINT_NAMES
from tests.helpers import DATA, REPO

ids = st.from_regex(r"[A-Za-z0-9_:@-]{1,20}", fullmatch=True)
epochs = st.none() | st.from_regex(r"[A-Za-z0-9_.:@-]{1,64}", fullmatch=True)
finite = st.floats(allow_nan=False, allow_infinity=False, width=64)
times = st.floats(0, 4e9)


@st.composite
def messages(draw: st.DrawFn) -> Message:
    kind = draw(
        st.sampled_from(
            [
                "skeleton-p",
                "skeleton-c",
                "skeleton-b",
                "pose-p",
                "pose-c",
                "end",
                "det",
                "bound",
                "prog",
                "status",
            ]
        )
    )
    stream = draw(ids)
    if kind == "end":
        return EndMessage(stream, draw(st.integers(0, 2**53 - 1)), draw(epochs))
    if kind == "skeleton-p":
        joints = tuple(draw(st.lists(ids, min_size=1, max_size=30, unique=True)))
        return SkeletonMessage(
            stream,
            draw(st.floats(1, 1000)),
            joints,
            draw(st.sampled_from(["y", "z"])),
            draw(st.sampled_from(["m", "cm", "asf"])),
            epoch=draw(epochs),
        )
    if kind == "skeleton-c":
        return SkeletonMessage(
            stream,
            draw(st.floats(1, 1000)),
            asf=draw(st.text(min_size=1).filter(str.strip)),
            angle_unit=draw(st.sampled_from(["deg", "rad"])),
            epoch=draw(epochs),
        )
    if kind == "skeleton-b":
        return SkeletonMessage(
            stream,
            draw(st.floats(1, 1000)),
            up=draw(st.sampled_from(["y", "z"])),
            units=draw(st.sampled_from(["m", "cm", "mm"])),
            bvh=draw(st.text(min_size=1).filter(str.strip)),
            epoch=draw(epochs),
        )
    if kind == "pose-p":
        n = draw(st.integers(1, 40))
        values = draw(st.lists(st.floats(-1e6, 1e6, width=32), min_size=3 * n, max_size=3 * n))
        return PoseMessage(
            stream,
            draw(st.integers(0, 2**53 - 1)),
            draw(times),
            positions=np.array(values, dtype=np.float32).reshape(n, 3),
            epoch=draw(epochs),
        )
    if kind == "pose-c":
        values = draw(st.lists(finite, min_size=1, max_size=70))
        return PoseMessage(
            stream,
            draw(st.integers(0, 2**53 - 1)),
            draw(times),
            channels=np.array(values),
            epoch=draw(epochs),
        )
    if kind == "det":
        return DetectionMessage(
            draw(st.uuids()).hex,
            stream,
            draw(st.text(min_size=1)),
            draw(st.integers(-(2**40), 2**40)),
            draw(st.integers(0, 2**40)),
            draw(finite),
            draw(finite),
            draw(st.integers(0, 2**40)),
            draw(times),
            draw(times),
        )
    if kind == "bound":
        frame = draw(st.integers(0, 2**40))
        summary = draw(st.booleans())
        inside = st.builds(
            SegmentDetection, st.text(min_size=1), st.integers(-(2**40), 2**40), st.integers(0, 2**40)
        )
        return BoundaryMessage(
            draw(st.uuids()).hex,
            stream,
            frame,
            draw(st.sampled_from(["pca", "ppca"])),
            draw(finite),
            draw(times),
            draw(st.integers(0, frame)) if summary else None,
            tuple(draw(st.lists(inside, max_size=MAX_SEGMENT_DETECTIONS))) if summary else (),
        )
    if kind == "prog":
        classes = []
        for _ in range(draw(st.integers(0, 4))):
            n = draw(st.integers(0, 8))
            matched = sorted(draw(st.lists(st.integers(0, 2**53 - 1), max_size=n)))
            classes.append(
                ClassProgress(
                    draw(st.text(min_size=1, max_size=128)),
                    n,
                    tuple(matched),
                    draw(st.floats(0, 1)),
                    draw(st.floats(0, 1e6)),
                    draw(st.floats(1e-6, 1e6)),
                )
            )
        return ProgressMessage(
            stream, draw(st.integers(0, 2**53 - 1)), tuple(classes), draw(times), draw(times)
        )
    return StatusMessage(
        stream,
        draw(st.sampled_from(["online", "offline"])),
        "0.1.0",
        draw(st.integers(0, 10**6)),
        draw(times),
    )


def same(a: Message, b: Message) -> bool:
    if type(a) is not type(b):
        return False
    for name in a.__dataclass_fields__:
        x, y = getattr(a, name), getattr(b, name)
        if isinstance(x, np.ndarray) or isinstance(y, np.ndarray):
            if not (
                isinstance(x, np.ndarray)
                and isinstance(y, np.ndarray)
                and x.shape == y.shape
                and np.array_equal(x, y)
            ):
                return False
        elif x != y:
            return False
    return True


# Huge finite values overflow the decoder's one-sum finiteness check before the exact check decides.
@pytest.mark.slow
@pytest.mark.filterwarnings("ignore:overflow encountered in reduce:RuntimeWarning")
@settings(max_examples=300, deadline=None)
@given(messages())
def test_round_trip(message: Message) -> None:
    payload = encode(message)
    back = decode(payload)
    assert same(message, back), (message, back)
    assert encode(back) == payload
    if not isinstance(message, StatusMessage | FrameMessage):
        assert parse_topic(topic(message)) == (message.stream, topic(message).rsplit("/", 1)[1])


def test_examples_of_the_schema_document_decode() -> None:
    """Every hex example of protocols/README.md decodes to a message of its type whose fields are
    the JSON-like line above it (bytes fields aside), and re-encodes to the same bytes."""
    text = (REPO / "protocols" / "README.md").read_text(encoding="utf-8")
    pairs = re.findall(r"^    (\{.*\})\n    ([0-9a-f]+)$", text, flags=re.M)
    assert len(pairs) == 10
    kinds = set()
    for shown, hexed in pairs:
        payload = bytes.fromhex(hexed)
        message = decode(payload)
        assert encode(message) == payload
        body = msgpack.unpackb(payload, raw=False)
        kinds.add(body["type"])
        for key, value in re.findall(r'"(\w+)": ("[^"]*"|[-\d.]+)', shown):
            if key in body and not isinstance(body[key], bytes):
                if value.startswith('"'):
                    assert str(body[key]) == value.strip('"').replace("\\n", "\n"), (key, body[key], value)
                else:
                    assert float(body[key]) == float(value), (key, body[key], value)
    assert kinds == {"skeleton", "pose", "frame", "end", "detection", "boundary", "progress", "status"}
    skeleton = decode(encode(SkeletonMessage("studio-a", 120.0, JOINT_NAMES)))
    assert (
        isinstance(skeleton, SkeletonMessage)
        and skeleton.kind == "positions"
        and skeleton.joints == JOINT_NAMES
    )
    asf = (DATA / "cmu" / "13" / "13.asf").read_text()
    channels = decode(encode(SkeletonMessage("s", 120.0, asf=asf, angle_unit="rad")))
    assert isinstance(channels, SkeletonMessage) and channels.kind == "channels" and channels.asf == asf
    hierarchy = "HIERARCHY\nROOT Hips\n{\n\tOFFSET 0 0 0\n\tCHANNELS 3 Xposition Yposition Zposition\n}\n"
    bvh = decode(encode(SkeletonMessage("s", 100.0, up="z", units="m", bvh=hierarchy)))
    assert (
        isinstance(bvh, SkeletonMessage)
        and bvh.kind == "bvh"
        and (bvh.bvh, bvh.up, bvh.units) == (hierarchy, "z", "m")
    )
    assert topic(skeleton) == "mocap/studio-a/skeleton"
    assert topic(StatusMessage("i1", "online", "0.1.0", 0, 0.0)) == "mocapd/i1/status"
    assert parse_topic("mocap/a/b/c") is None and parse_topic("other/a/pose") is None


def raw(body: dict[str, Any]) -> bytes:
    out: bytes = msgpack.packb(body, use_bin_type=True)
    return out


POSE = {
    "v": 1,
    "type": "pose",
    "stream": "s",
    "seq": 3,
    "time": 1.5,
    "positions": np.zeros(78, "<f4").tobytes(),
}
BOUNDARY = {
    "v": 1,
    "type": "boundary",
    "id": "b",
    "stream": "s",
    "frame": 2400,
    "method": "ppca",
    "score": 17.2,
    "emit_time": 1.5,
}
SEGMENT_DETECTION = {"class": "squat", "start_frame": 20, "end_frame": 30}


@pytest.mark.parametrize(
    ("payload", "reason", "words"),
    [
        (b"\xc1", "undecodable", "msgpack"),
        (b"", "undecodable", "msgpack"),
        (raw([1, 2]), "schema", "map"),  # type: ignore[arg-type]
        (raw({"type": "pose"}), "version", "'v'"),
        (raw({**POSE, "v": 2}), "version", "version 2"),
        (raw({**POSE, "v": True}), "version", "'v'"),
        (raw({**POSE, "type": "posture"}), "type", "unknown type"),
        (raw({**POSE, "type": 7}), "type", "unknown type"),
        (raw({k: v for k, v in POSE.items() if k != "seq"}), "schema", "pose.seq: missing"),
        (raw({**POSE, "seq": -1}), "schema", "pose.seq"),
        (raw({**POSE, "seq": 1.0}), "schema", "pose.seq: must be an integer"),
        (raw({**POSE, "seq": 2**53}), "schema", "pose.seq: must be at most 9007199254740991"),
        (raw({**POSE, "seq": 2**64 - 1}), "schema", "pose.seq: must be at most"),
        (raw({**POSE, "epoch": ""}), "schema", "pose.epoch"),
        (raw({**POSE, "epoch": "a/b"}), "schema", "pose.epoch"),
        (raw({**POSE, "epoch": 7}), "schema", "pose.epoch"),
        (raw({**POSE, "epoch": "x" * 65}), "schema", "pose.epoch"),
        (raw({**POSE, "stream": "a/b"}), "schema", "pose.stream"),
        (raw({**POSE, "stream": "a.b"}), "schema", "pose.stream"),  # it would split a NATS subject
        (
            raw({"v": 1, "type": "skeleton", "stream": "s.1", "rate": 120, "joints": ["a"]}),
            "schema",
            "stream",
        ),
        (raw({**POSE, "stream": ""}), "schema", "pose.stream"),
        (raw({**POSE, "time": float("nan")}), "non_finite", "pose.time"),
        (raw({**POSE, "positions": b"\0" * 10}), "shape", "pose.positions"),
        (raw({**POSE, "positions": b""}), "shape", "pose.positions"),
        (raw({**POSE, "positions": [1.0, 2.0, 3.0]}), "schema", "must be bytes"),
        (raw({**POSE, "positions": np.array([0, np.nan, 0], "<f4").tobytes()}), "non_finite", "value 1"),
        (raw({**POSE, "channels": b"\0" * 8}), "schema", "either"),
        (raw({**POSE, "extra": 1}), "schema", "unknown field(s) extra"),
        (raw({"v": 1, "type": "skeleton", "stream": "s", "rate": 120}), "schema", "either"),
        (
            raw({"v": 1, "type": "skeleton", "stream": "s", "rate": 120, "joints": ["a"], "bvh": "H"}),
            "schema",
            "either",
        ),
        (raw({"v": 1, "type": "skeleton", "stream": "s", "rate": 120, "bvh": " "}), "schema", "skeleton.bvh"),
        (raw({"v": 1, "type": "skeleton", "stream": "s", "rate": 120, "bvh": 3}), "schema", "skeleton.bvh"),
        (raw({"v": 1, "type": "skeleton", "stream": "s", "rate": 0, "joints": ["a"]}), "schema", "positive"),
        (
            raw({"v": 1, "type": "skeleton", "stream": "s", "rate": 120, "joints": ["a", "a"]}),
            "schema",
            "twice",
        ),
        (
            raw({"v": 1, "type": "skeleton", "stream": "s", "rate": 120, "joints": ["a"], "up": "w"}),
            "schema",
            "up",
        ),
        (
            raw({"v": 1, "type": "status", "instance": "i", "version": "1", "streams": 0, "started": 0.0}),
            "schema",
            "state",
        ),
        (
            raw({**BOUNDARY, "start": 2401, "detections": []}),
            "schema",
            "boundary.start: must be at most 2400",
        ),
        (raw({**BOUNDARY, "start": 10}), "schema", "boundary.detections: missing"),
        (raw({**BOUNDARY, "start": 10, "detections": {}}), "schema", "boundary.detections: must be a list"),
        (
            raw({**BOUNDARY, "start": 10, "detections": [[]]}),
            "schema",
            "boundary.detections[0]: must be a map",
        ),
        (
            raw({**BOUNDARY, "start": 10, "detections": [{**SEGMENT_DETECTION, "cost": 1.0}]}),
            "schema",
            "boundary.detections[0]: unknown field(s) cost",
        ),
        (
            raw({**BOUNDARY, "start": 10, "detections": [SEGMENT_DETECTION] * 65}),
            "schema",
            "at most 64",
        ),
    ],
)
def test_bad_payloads_are_refused_with_their_reason(payload: bytes, reason: str, words: str) -> None:
    with pytest.raises(WireError) as caught:
        decode(payload)
    assert caught.value.reason == reason and reason in REASONS
    assert words in str(caught.value), str(caught.value)


def test_oversize_before_parsing() -> None:
    payload = encode(PoseMessage("s", 0, 0.0, positions=np.zeros((26, 3), np.float32)))
    assert isinstance(decode(payload, max_bytes=len(payload)), PoseMessage)
    with pytest.raises(WireError, match=r"^oversize: ") as caught:
        decode(payload, max_bytes=len(payload) - 1)
    assert caught.value.reason == "oversize"


@settings(max_examples=400, deadline=None)
@given(st.binary(max_size=300))
def test_random_bytes_never_escape_as_another_error(payload: bytes) -> None:
    try:
        decode(payload)
    except WireError as e:
        assert e.reason in REASONS


def nested(depth: int, leaf: Any = 1, *, maps: bool = False) -> Any:
    """``leaf`` inside ``depth`` lists (or one-entry maps)."""
    for _ in range(depth):
        leaf = {"k": leaf} if maps else [leaf]
    return leaf


VALID_BODIES = {
    "pose": POSE,
    "skeleton": {"v": 1, "type": "skeleton", "stream": "s", "rate": 120.0, "joints": ["a"], "epoch": "e"},
    "status": {
        "v": 1,
        "type": "status",
        "instance": "i",
        "state": "online",
        "version": "1",
        "streams": 0,
        "started": 0.0,
    },
    "progress": msgpack.unpackb(
        encode(ProgressMessage("s", 4, (ClassProgress("c", 2, (1,), 0.5, 0.1, 0.2),), 1.0, 2.0)), raw=False
    ),
}
FIELDS = sorted({(kind, name) for kind, body in VALID_BODIES.items() for name in [*body, "epoch", "extra"]})


@pytest.mark.parametrize("maps", [False, True], ids=["lists", "maps"])
@pytest.mark.parametrize(("kind", "name"), FIELDS)
def test_a_value_nested_a_thousand_deep_is_refused_in_any_field(kind: str, name: str, maps: bool) -> None:
    """Issue 32: a pose whose ``v``, ``type`` or ``epoch`` was a list nested 1,000 deep (1 KB) raised
    RecursionError from a refusal's repr of the value, and the daemon died. Now the decoder refuses
    whatever nests more than 8 deep, and describes a bad value by its type and size."""
    payload = raw({**VALID_BODIES[kind], name: nested(1000, maps=maps)})
    assert len(payload) < 8200
    with pytest.raises(WireError) as caught:
        decode(payload)
    assert caught.value.reason in ("version", "schema"), str(caught.value)
    assert len(str(caught.value)) < 200, str(caught.value)


def test_nesting_is_bounded_at_eight() -> None:
    """Nine levels (the map, then a field nested eight deep) are refused, whatever the field; the
    deepest message of the wire (progress: map, list, map, list) is four."""
    with pytest.raises(WireError, match="nested deeper than 8"):
        decode(raw({**POSE, "extra": nested(8, maps=True)}))
    with pytest.raises(WireError, match=r"unknown field\(s\) extra"):
        decode(raw({**POSE, "extra": nested(7)}))


@st.composite
def hostile_values(draw: st.DrawFn) -> Any:
    """Any msgpack value, recursively: deep lists and maps, huge integers, NaN and infinities,
    long strings and bytes."""
    scalars = (
        st.none()
        | st.booleans()
        | st.integers(-(2**63), 2**64 - 1)
        | st.floats()
        | st.text(max_size=300)
        | st.binary(max_size=300)
    )
    tree = st.recursive(
        scalars,
        lambda inner: st.lists(inner, max_size=3) | st.dictionaries(st.text(max_size=5), inner, max_size=3),
    )
    value = draw(tree)
    return nested(draw(st.sampled_from([0, 0, 1, 7, 9, 200, 1000])), value, maps=draw(st.booleans()))


@settings(max_examples=500, deadline=None)
@given(st.sampled_from(FIELDS), hostile_values())
def test_any_value_in_any_field_decodes_or_is_refused_with_a_short_reason(
    field: tuple[str, str], value: Any
) -> None:
    kind, name = field
    try:
        decode(raw({**VALID_BODIES[kind], name: value}))
    except WireError as e:
        assert e.reason in REASONS
        assert len(str(e)) < 300, str(e)


# --------------------------------------------------------------------------- frame messages


@st.composite
def frames(draw: st.DrawFn) -> tuple[bytes, list[bytes], str]:
    """A frame message of 1-12 subjects, some of them faulty (a bad id, a seq beyond MAX_SEQ, a time
    or a value not finite, values not in threes or none), as its bytes, and each subject as the
    bytes of a pose message of its own; and the kind."""
    kind = draw(st.sampled_from(["positions", "channels"]))
    epoch = draw(epochs)
    width, dtype = (3, "<f4") if kind == "positions" else (1, "<f8")
    streams, seqs, stamps, counts, blobs, singles = [], [], [], [], [], []
    for _ in range(draw(st.integers(1, 12))):
        stream = draw(ids | st.sampled_from(["a.b", "", "x" * 129, "a/b"]))
        seq = draw(st.integers(0, MAX_SEQ) | st.sampled_from([MAX_SEQ + 1, 2**64 - 1]))
        stamp = draw(times | st.sampled_from([float("nan"), float("inf")]))
        count = draw(st.integers(0, 4)) * width + draw(st.sampled_from([0, 0, 0, 1]))
        value = st.floats(allow_nan=False, allow_infinity=False, width=32 if width == 3 else 64)
        value |= st.sampled_from([float("nan"), -float("inf")])
        values = np.array(draw(st.lists(value, min_size=count, max_size=count)), dtype=dtype)
        streams.append(stream)
        seqs.append(seq)
        stamps.append(stamp)
        counts.append(count)
        blobs.append(values.tobytes())
        body = {"v": 1, "type": "pose", "stream": stream, "seq": seq, "time": stamp, kind: values.tobytes()}
        if epoch is not None:
            body["epoch"] = epoch
        singles.append(msgpack.packb(body))
    frame = {
        "v": 1,
        "type": "frame",
        "source": "rig",
        "streams": streams,
        "seq": np.array(seqs, dtype="<u8").tobytes(),
        "time": np.array(stamps, dtype="<f8").tobytes(),
        "counts": np.array(counts, dtype="<u4").tobytes(),
        kind: b"".join(blobs),
    }
    if epoch is not None:
        frame["epoch"] = epoch
    return msgpack.packb(frame), singles, kind


NAN_BEFORE_AN_EMPTY_SUBJECT = (
    msgpack.packb(
        {
            "v": 1,
            "type": "frame",
            "source": "rig",
            "streams": ["0", "a.b"],
            "seq": bytes(16),
            "time": bytes(16),
            "counts": np.array([2, 0], dtype="<u4").tobytes(),
            "channels": np.array([0.0, np.nan]).tobytes(),
        }
    ),
    [
        msgpack.packb(
            {
                "v": 1,
                "type": "pose",
                "stream": "0",
                "seq": 0,
                "time": 0.0,
                "channels": np.array([0.0, np.nan]).tobytes(),
            }
        ),
        msgpack.packb({"v": 1, "type": "pose", "stream": "a.b", "seq": 0, "time": 0.0, "channels": b""}),
    ],
    "channels",
)
"""A rehearsal's find: a NaN in the last values, its subject followed by one with none (the
per-subject sums were cut at the empty subject's offset, clamped to the last value)."""


@settings(max_examples=300, deadline=None)
@given(frames())
@example(NAN_BEFORE_AN_EMPTY_SUBJECT)
def test_a_frames_subjects_are_taken_or_refused_as_their_own_pose_messages_would_be(
    case: tuple[bytes, list[bytes], str],
) -> None:
    """Each subject of a frame message, bad ones among good ones: its pose equals the one its own
    pose message decodes to, or it is refused with the reason that message is refused with; the
    others are untouched by it."""
    payload, singles, kind = case
    frame = decode(payload)
    assert isinstance(frame, FrameMessage) and frame.kind == kind
    assert topic(frame) == "mocap/rig/frame"
    got = frame.poses()
    assert len(got) == len(singles)
    for mine, single in zip(got, singles, strict=True):
        try:
            want: PoseMessage | WireError = decode(single)  # type: ignore[assignment]
        except WireError as e:
            want = e
        if isinstance(want, WireError):
            assert isinstance(mine, WireError) and mine.reason == want.reason, (mine, want)
        else:
            assert isinstance(mine, PoseMessage) and same(mine, want), (mine, want)
    back = decode(encode(frame))  # encode writes it back
    assert isinstance(back, FrameMessage) and len(back.poses()) == len(singles)


def test_a_frame_of_good_poses_round_trips_and_is_their_poses() -> None:
    poses = [
        PoseMessage("a", 7, 1.5, channels=np.arange(4.0), epoch="e1"),
        PoseMessage("b", 9, 1.5, channels=np.array([0.5]), epoch="e1"),
        PoseMessage("a", 8, 1.6, channels=np.arange(4.0) + 1, epoch="e1"),  # a second frame of a
    ]
    frame = decode(encode(frame_of(poses, "rig", epoch="e1")))
    assert isinstance(frame, FrameMessage)
    got = frame.poses()
    assert all(isinstance(a, PoseMessage) and same(a, b) for a, b in zip(got, poses, strict=True))
    with pytest.raises(ValueError, match="not both"):
        frame_of([poses[0], PoseMessage("c", 1, 1.0, positions=np.zeros((2, 3), np.float32))], "rig")


@pytest.mark.parametrize(
    ("change", "reason", "field"),
    [
        ({"counts": np.array([4], dtype="<u4").tobytes()}, "shape", "counts"),
        ({"seq": b"\x00" * 7}, "shape", "seq"),
        ({"time": b"\x00" * 24}, "shape", "time"),
        ({"channels": b"\x00" * 8}, "shape", "channels"),
        ({"streams": []}, "schema", "streams"),
        ({"streams": ["a", 3]}, "schema", "streams"),
        ({"source": "a.b"}, "schema", "source"),
        ({"positions": b""}, "schema", "positions"),
        ({"extra": 1}, "schema", "extra"),
    ],
)
def test_a_frame_message_wrong_as_a_whole_is_refused_whole(
    change: dict[str, Any], reason: str, field: str
) -> None:
    """Lengths that do not agree (the subjects cannot be told apart), a field missing or wrong."""
    body = msgpack.unpackb(
        encode(
            frame_of(
                [
                    PoseMessage("a", 1, 1.0, channels=np.ones(2)),
                    PoseMessage("b", 1, 1.0, channels=np.ones(3)),
                ],
                "rig",
            )
        )
    )
    body |= change
    with pytest.raises(WireError) as caught:
        decode(msgpack.packb(body))
    assert caught.value.reason == reason and field in caught.value.detail
