"""A fuzz run of the daemon over its transports (issues 21 and 32): a real ``mocapd run`` takes a
stream of N fuzzed messages beside one good stream, and must not crash, must count every message it
gets under exactly one reason, and must give the good stream exactly ``mocapd detect``'s detections.

    python -m bench.fuzz [--messages 1000000] [--transport zmq|mqtt|nats|both|all] [--seed N]
                         [--speed X|auto] [--members 2]

Per transport: the daemon (``mocapd --config C run``, its config in a temporary directory: sink
stdout, ``service.max_streams`` 200, ``service.max_message_bytes`` 16 KiB, ``service.idle_s`` 10,
logging at debug; one worker per core); over MQTT a mosquitto on a free loopback port that never
drops (``max_queued_messages 0``; its ``$SYS`` count of dropped messages is checked). Over NATS the
cluster (:class:`Cluster`): a nats-server from the shipped nats.conf, an etcd, and ``--members``
workers ``mocapd run --cluster ... --coordinator ...`` with the same service settings, the
partitions split between them. ``mocapd replay`` sends CMU 13_30 (exercises) as stream ``good``
(over NATS to the server's MQTT port), paced (``--speed auto``) to last about as long as the
fuzzing; meanwhile this process sends the fuzzed messages, a seeded mix of

* random bytes of random length (0 to 2 KiB, a few beyond ``max_message_bytes``);
* structure-aware mutations of valid skeletons and poses (and the daemon's own message types:
  detection, boundary, progress, status): fields removed, added, retyped; ``positions``/``channels``
  of wrong lengths, NaN, infinity, huge values; sequence numbers negative, huge, 2**64-1; wrong
  ``v`` and ``type``; odd stream ids (with ``/``, ``+``, ``#``, unicode, 129+ characters); epochs of
  the wrong type; ASF texts cut, shuffled or with garbage; truncated or bit-flipped msgpack, extra
  bytes, deep nesting, non-string keys;
* field values mutated recursively (issue 32): any field of any of those messages, or a value
  inside one (an element of ``joints`` or ``matched``, an entry of a progress message's
  ``classes``, recursively), replaced by lists and maps nested to random depths (often 7-10, around
  the decoder's bound of 8; sometimes about 1,000 and 3,000, beyond what ``msgpack.packb`` packs:
  :func:`pack_value`), deep maps with odd keys, huge integers (±2**63, 2**64-1), NaN and ±infinity,
  the wrong type (bytes for a string, a string for bytes, a bool for an int, None), long strings;
* valid messages on other streams: skeletons (positions and ASF, repeated, changed, new runs),
  poses in order, repeated, out of order, after gaps, implausibly far ahead, of streams that
  announced no skeleton; new streams beyond ``max_streams``;
* messages on wrong topics: another stream's, the other message word, ``detections``, too many or
  too few levels, odd stream ids, topics outside ``mocap/`` (ZeroMQ also: one or three frames);
* over NATS (from a raw client connection: any subject bytes and header block), all of the above
  on their subjects (``mocap/<s>/pose`` as ``mocap.<s>.pose``, mapped to a partition), one in ten
  with a header block (status lines, bytes that are not UTF-8, ``Nats-Msg-Id`` once and repeated,
  failed ``Nats-Expected-*``, ``Nats-Rollup``), some with a reply subject; and subjects only NATS
  carries: straight into a partition's buffer (``mocap.p.<p>.<stream>.<word>``, of the wrong
  partition, too few tokens, not UTF-8, control characters, ``*`` and ``>`` tokens), the
  detections' de-duplication store ``mocap.d.<s>.detections``, subjects the server drops (empty
  tokens); and messages on the workers' delivery subjects themselves (found through JetStream's
  API): published there directly, with forged acknowledgement subjects (refused by the server) and
  forged flow control and heartbeats (``Nats-Consumer-Stalled`` naming ``$JS.API.STREAM.DELETE``).

Nothing fuzzed is sent on the good stream's topics (a fuzzed body may claim to be ``good``, on
another stream's topic). Over ZeroMQ the fuzz goes from an XPUB socket that never drops
(``XPUB_NODROP``: a full queue waits) and the replay's messages pass through it, counted; over MQTT
the replay publishes to the broker itself and a subscriber of its topics counts them. The sender
keeps at most 20,000 messages ahead of what the daemon has counted.

Checks (exit status 1 if one fails):

* no crash: the daemon is alive throughout and exits 0 on SIGTERM, no worker of it was started
  again (``mocapd_worker_restarts_total``), no message set off a defect
  (``rejects{reason="internal"}``); every line of its stderr is one JSON object, none an error, a
  traceback or a Python warning;
* every message counted once: the messages that reached the daemon (the fuzzed ones a ZeroMQ
  subscription or an MQTT subscription lets through, over NATS those a partition's buffer stored,
  the four-token pose and skeleton subjects no buffer stores (:func:`nats_stray`) and those
  published on a delivery subject but forged flow control; and the good stream's) equal
  ``mocapd_messages_in_total{type}`` (taken in) + ``mocapd_rejects_total{reason}`` (refused) +
  the drops before a message is looked at (:data:`INTAKE_DROPS`: ``mqtt_incoming_full``,
  ``nats_foreign``, ``nats_internal``); the other drops (``lagging``, ``recognizer_<problem>``:
  taken-in poses not recognised; ``zmq_send_full``, ``mqtt_outbox_full``: going out) count no
  incoming message;
* over NATS also: the buffers stored exactly what the fuzzer predicts (:func:`nats_stored`, the
  header blocks' effects; each buffer's last sequence number), the server refused exactly the
  forged acknowledgement subjects, every worker was healthy whenever looked at (no fence) and the
  partitions never moved, no buffer gap, no lost connection, no detection suppressed as a duplicate;
* the good stream's detections are ``mocapd detect``'s on the clip, exactly (all but the ids; over
  NATS on the frames from the first whose number is a multiple of the decimation step, where a
  cluster worker begins).

Prints the machine, then per transport the table of reasons, messages a second, the wall time and
the daemon's resident memory at the start and the end, and a summary.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import getpass
import json
import math
import os
import random
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
import urllib.request
from collections import Counter
from collections.abc import Callable, Coroutine, Iterator
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, TypeVar

import msgpack
import numpy as np
import paho.mqtt.client as paho
import zmq
from paho.mqtt.enums import CallbackAPIVersion

from bench.common import DATA
from bench.machine import describe
from bench.processes import free_port, json_lines, rss_kib, scrape, wait_port
from daemon.config import ClusterConfig
from daemon.frames import FrameClock
from daemon.library import default_library_path, load_library
from daemon.recognizer import detect
from daemon.recordings import read_recording
from protocols.deliveries import Delivery, Reader
from protocols.messages import (
    BoundaryMessage,
    ClassProgress,
    DetectionMessage,
    Message,
    PoseMessage,
    ProgressMessage,
    SkeletonMessage,
    StatusMessage,
    encode,
)
from replay import JOINT_NAMES, Motion, parse_asf

T = TypeVar("T")

MOCAPD = Path(sys.executable).parent / "mocapd"
GOOD_STREAM = "good"
GOOD_CLIP = ("cmu/13/13.asf", "cmu/13/13_30.amc.gz")
RATE = 120.0
MAX_MESSAGE_BYTES = 16384
MAX_STREAMS = 200
AHEAD = 20_000
"""The most messages the sender is ahead of what the daemon counted."""
ESTIMATED_RATE = {"zmq": 10000.0, "mqtt": 5500.0, "nats": 8500.0}
"""Fuzzed messages a second on 2 cores (measured 2026-12-06 with the recursive field values, the
machine shared with other work), for ``--speed auto``."""
INTAKE_DROPS = ("mqtt_incoming_full", "nats_foreign", "nats_internal")
"""Drops of a message before the daemon looked at it (the others are of taken-in poses or going out):
the MQTT intake's queue full; over NATS, a message published on a worker's delivery subject that no
buffer delivered, and one whose handling raised (a defect)."""
DETECTION_KEY = ("class", "start_frame", "end_frame", "cost", "tau", "emitted_at_frame")
POOL = 40
"""Streams with valid traffic (``fz-00`` ...), 12 of them channel streams."""
GHOSTS = 200
"""Streams whose poses come without a skeleton (``ghost-000`` ...)."""


# ------------------------------------------------------------------------------------ the fuzzer


@dataclass(frozen=True)
class Fuzzed:
    """One message: its kind (random, mutated, valid, topic; over NATS also subject and inbox), the
    topic's bytes (over NATS the subject), the frames after the topic (one normally; ZeroMQ framing
    faults have none or two) and the MQTT QoS; over NATS its header block and reply subject, and
    whether a worker counts it (:func:`nats_stored`, or for a message on a delivery subject whether
    it is anything but the server's flow control), and whether it reaches a worker as a ``stray``
    (:func:`nats_stray`: on a plain subscription, not from a buffer)."""

    kind: str
    topic: bytes
    payloads: tuple[bytes, ...]
    qos: int = 0
    headers: bytes | None = None
    reply: bytes = b""
    reaches: bool = True
    stray: bool = False


@dataclass
class _Pooled:
    """A pool stream as its source sees it: its announcement, width, last sequence number, epoch."""

    name: str
    skeleton: dict[str, Any]
    width: int
    channels: bool
    seq: int = 0
    epoch: str | None = None


EDGE_INTS = (0, 1, -1, 2, 255, 2**31, 2**53 - 1, 2**53, 2**63 - 1, 2**64 - 1, -(2**63), -(2**31))
EDGE_FLOATS = (
    float("nan"),
    float("inf"),
    float("-inf"),
    0.0,
    -0.0,
    1e308,
    -1e308,
    5e-324,
    3.4e38,
    1e-300,
    1e300,
    120.0,
)
ODD_IDS = (
    "",
    "a" * 129,
    "a" * 128,
    "b" * 10_000,
    "with space",
    "slash/inside",
    "a/b/c",
    "plus+",
    "hash#",
    "+",
    "#",
    "ünïcödé",
    "流れ",
    "😀",
    "nul\x00inside",
    "tab\tinside",
    "a.b:c@d-e_f",
    "..",
    "-",
    "$SYS",
    "good",
    "ghost-000",
    "fz-00",
    "é" * 200,
)
"""Stream ids for bodies and topics: invalid ones, and valid ones of the wrong stream."""
MQTT_UNSAFE = set("+#") | {chr(c) for c in (*range(0x20), *range(0x7F, 0xA0))}
"""Characters a publisher may not put in an MQTT topic (wildcards; mosquitto refuses control
characters, and disconnects the client)."""


NAN, INF = float("nan"), float("inf")
BAD: dict[str, tuple[Any, ...]] = {
    "v": (0, 2, -1, "1", 1.0, None, True, 2**64 - 1, [1]),
    "type": ("posture", "", "POSE", 1, None, "detection", "boundary", "status", "skeleton", "pose"),
    "seq": (-1, -(2**63), 2**53, 2**53 - 1, 2**64 - 1, 1.5, "1", None, True, 0, 10**15),
    "time": (NAN, INF, -INF, "now", None, 2**64 - 1, -1e308, True, [], 0),
    "epoch": (1, "", "x" * 65, "x" * 64, "bad epoch", None, ["a"], "é", b"bytes", 1.5),
    "rate": (0, -1, NAN, INF, 1e-300, 1e300, 1e6, 10_000.0, 10_000.5, 9990.0, 30.0, 0.001, "120", True),
    "up": ("x", "Y", 1, "", "z", None),
    "units": ("furlong", "", "m", 2, "asf"),
    "angle_unit": ("grad", "rad", "", 0, "deg"),
    "joints": (
        [],
        [1, 2],
        list(JOINT_NAMES[:10]),
        list(JOINT_NAMES) * 2,
        list(reversed(JOINT_NAMES)),
        [""],
        [f"j{k}" for k in range(3000)],
        [*JOINT_NAMES, None],
        "root",
        [*JOINT_NAMES, "é" * 100],
    ),
    "asf": ("", " ", ":bonedata", "\n" * 1000, ":root\n order", ":version 1.10\n:units\n  mass"),
    "asf word": ("nan", "inf", "-1", "1e400", "0", "x", "", "begin", "end", ":root", "99999999999", "ry"),
    "huge": (3.4e38, -3.4e38, 1e308, 1e-45, 5e-324),
}
"""Values of each field at or past its edges (``asf word``: put in place of a word of an ASF line)."""
RATES = (RATE, 60.0, 100.0, 240.0, 30.0, 90.0, 9990.0)
"""A pool stream's rate when its skeleton changes (100 Hz cannot be recognised: refused)."""
EXTRA_FIELDS = ("extra", "pad", "positions", "channels", "asf", "joints", "epoch", "seq", "")
BAD_TIMESTAMPS = (b"\xd4\xff\x00", b"\xc7\x03\xff\x00\x00\x00", b"\x81\xa1v\xd4\xff\x01")
DEPTHS = (1, 2, 3, 4, 6, 7, 7, 8, 8, 8, 9, 9, 10, 16, 64, 500, 999, 1000, 1000, 1001, 3000)
"""How deep a generated value nests: often around the decoder's bound (``MAX_DEPTH`` 8: a field's
value at depth 7 makes the message 8 deep, taken; 8 or 9 makes it 9 or 10, refused), sometimes about
1,000 deep (issue 32's attack: the refusal's repr raised RecursionError) and beyond what
``msgpack.packb`` itself packs (:func:`pack_value` writes any depth)."""
HUGE_INTS = (
    2**63 - 1,
    2**63,
    2**64 - 1,
    -(2**63),
    -(2**63) + 1,
    2**53 + 1,
    -(2**53) - 1,
    2**32,
    -(2**31) - 1,
)
"""Integers at the edges of msgpack's int64 and uint64 and of a double's exact integers."""
ODD_FLOATS = (float("nan"), float("inf"), float("-inf"), -0.0, 5e-324, 1.7976931348623157e308, -1e308)
ODD_KEYS: tuple[str | bytes, ...] = (
    "",
    " ",
    "v",
    "type",
    "stream",
    "class",
    "classes",
    "é" * 50,
    "k" * 1000,
    "\x00",
    "😀",
    "a.b",
    "$",
    "__proto__",
    "\ud7ff\ue000",
    b"bytes-key",
    b"",
    b"\xff\xfe",
)
"""Map keys for generated maps: empty, long, control and astral characters, field names, and bytes
(msgpack allows str and bytes keys; the decoder takes neither as a field)."""
SHORT_KEYS: tuple[str | bytes, ...] = tuple(k for k in ODD_KEYS if len(k) <= 4)
LONG_TEXTS = (129, 300, 1000, 5000, 15000)


PARTITIONS = ClusterConfig().partitions
"""``cluster.partitions``'s default, of the shipped mappings (the cluster run reads them)."""
SUBJECT_SAFE = bytes.maketrans(b" \t\n\r\x0b\x0c.", b"_______")
"""Bytes a NATS subject token cannot hold (the protocol's separators, and the token separator) as
``_``: a subject is any other bytes, which the server passes on (not UTF-8 included)."""
HEADER_BLOCKS: tuple[tuple[bytes, bool], ...] = (
    (b"NATS/1.0\r\nX-Fuzz: 1\r\n\r\n", True),
    (b"NATS/1.0\r\nX-Fuzz: " + b"y" * 3000 + b"\r\n\r\n", True),
    (b"NATS/1.0\r\nX: \xff\xfe\r\n\r\n", True),
    (b"NATS/1.0\r\n\xff\xfe: v\r\n\r\n", True),
    (b"NATS/1.0\r\nStatus: 100\r\n\r\n", True),
    (b"NATS/1.0 100 FlowControl Request\r\n\r\n", True),
    (b"NATS/1.0 100 Idle Heartbeat\r\nNats-Consumer-Stalled: fuzz.stalled\r\n\r\n", True),
    (b"NATS/1.0 \xff\xfe\r\n\r\n", True),
    (b"NATS/1.0 100 \xff\xfe\r\n\r\n", True),
    (b"NATS/1.0", True),
    (b"NATS/1.0 503\r\n\r\n", True),
    (b"NATS/1.0 404 No Messages\r\n\r\n", True),
    (b"garbage\r\n\r\n", True),
    (b"NATS/1.0\nA: b\n\n", True),
    (b"NATS/1.0\r\nNats-Msg-Id: \r\n\r\n", True),
    (b"NATS/1.0\r\nNats-Expected-Stream: NOPE\r\n\r\n", False),
    (b"NATS/1.0\r\nNats-Expected-Last-Sequence: 9223372036854775807\r\n\r\n", False),
    (b"NATS/1.0\r\nNats-Expected-Last-Subject-Sequence: 9223372036854775807\r\n\r\n", False),
    (b"NATS/1.0\r\nNats-Expected-Last-Msg-Id: fuzz-never\r\n\r\n", False),
    (b"NATS/1.0\r\nNats-Rollup: all\r\n\r\n", False),
    (b"NATS/1.0\r\nNats-Rollup: sub\r\n\r\n", False),
)
"""Header blocks a NATS publisher may put on a message, and whether JetStream still stores it (a
failed expectation and a rollup the buffers do not allow are refused; measured on nats-server
2.9.10): headers of odd bytes, status lines (the server's flow control and heartbeats as a
publisher's header, not UTF-8, none at all: ``NATS/1.0`` alone), not a header block."""


STALLED = b"NATS/1.0 100 Idle Heartbeat\r\nNats-Consumer-Stalled: %s\r\n\r\n"
"""A heartbeat's header block whose consumer asks for flow control on the subject given."""


def subject_of(topic: bytes) -> bytes:
    """An MQTT-style topic as a NATS subject: ``/`` as ``.``, the protocol's separators as ``_``,
    at most 3,000 bytes (the server's protocol line is 4 KiB)."""
    subject = topic.translate(bytes.maketrans(b" \t\n\r\x0b\x0c/", b"______."))
    if len(subject) > 3000:
        subject = subject[:1500] + subject[-1500:]
    return subject or b"mocap"


def nats_stored(subject: bytes, partitions: int = PARTITIONS) -> bool:
    """Whether nats-server (the shipped nats.conf, the workers' buffers) stores a message published
    on ``subject`` in a partition's buffer, from which a worker reads it: ``mocap.<s>.pose`` and
    ``.skeleton`` mapped to a partition (``s`` any token but ``>``), ``mocap.p.<p>.`` and more
    tokens straight in; none with an empty token (the server drops those). Measured on 2.9.10."""
    tokens = subject.split(b".")
    if not all(tokens):
        return False
    if len(tokens) == 3 and tokens[0] == b"mocap" and tokens[2] in (b"pose", b"skeleton"):
        return tokens[1] != b">"
    return (
        len(tokens) >= 4
        and tokens[:2] == [b"mocap", b"p"]
        and tokens[2] in {str(p).encode() for p in range(partitions)}
    )


def nats_stray(subject: bytes, partitions: int = PARTITIONS) -> bool:
    """Whether a worker reads a message on ``subject`` that no buffer stores: a pose or skeleton
    subject of four tokens (``mocap.<a>.<b>.pose``), which the owner of partition 0 subscribes to
    (``protocols.nats.STRAYS``; core NATS delivers it whatever its headers, and any token bytes),
    unless a buffer stores it."""
    tokens = subject.split(b".")
    return (
        len(tokens) == 4
        and all(tokens)
        and tokens[0] == b"mocap"
        and tokens[3] in (b"pose", b"skeleton")
        and not nats_stored(subject, partitions)
    )


def pack(body: Any) -> bytes:
    """``body`` as msgpack: by ``msgpack.packb``, or by :func:`pack_value` for a value nested deeper
    than msgpack packs (about 1,000 levels)."""
    try:
        out: bytes = msgpack.packb(body, use_bin_type=True)
    except ValueError:  # "recursion limit exceeded"
        return pack_value(body)
    return out


def _container_head(kind: str, n: int) -> bytes:
    small, word, long = (0x90, b"\xdc", b"\xdd") if kind == "list" else (0x80, b"\xde", b"\xdf")
    if n < 16:
        return bytes([small | n])
    if n < 1 << 16:
        return word + n.to_bytes(2, "big")
    return long + n.to_bytes(4, "big")


def pack_value(value: Any) -> bytes:
    """``value`` as msgpack at any depth, without recursion (an explicit stack): lists and maps
    written here, every other value by ``msgpack.packb``."""
    out = bytearray()
    stack: list[Any] = [value]
    while stack:
        item = stack.pop()
        if isinstance(item, list):
            out += _container_head("list", len(item))
            stack.extend(reversed(item))
        elif isinstance(item, dict):
            out += _container_head("map", len(item))
            for k, v in reversed(list(item.items())):
                stack += [v, k]
        else:
            out += msgpack.packb(item, use_bin_type=True)
    return bytes(out)


def shape(value: Any) -> str:
    """A value by its type, size and depth, never its repr (unbounded, and for a deep value a
    RecursionError)."""
    depth, level = 0, [value]
    while level and depth < 10_000:
        level = [
            inner
            for outer in level
            if isinstance(outer, dict | list)
            for inner in (outer.values() if isinstance(outer, dict) else outer)
        ]
        depth += 1
    size = len(value) if isinstance(value, str | bytes | list | dict) else 0
    return f"{type(value).__name__} of {size}, {depth} deep"


def _mqtt_safe(text: str) -> bool:
    return bool(text) and not (set(text) & MQTT_UNSAFE) and "\ufffe" not in text and "\uffff" not in text


class Fuzzer:
    """Fuzzed messages for the daemon from a seed (:meth:`messages`); ``mqtt``: only topics an MQTT
    publisher may use, and only one payload per message."""

    def __init__(self, seed: int, *, mqtt: bool = False, nats: bool = False) -> None:
        self.rng = random.Random(seed)
        self.np = np.random.default_rng(seed)
        self.mqtt = mqtt
        self.nats = nats
        self.frames = not (mqtt or nats)  # ZeroMQ: messages of other than two frames
        self.inboxes: list[bytes] = []
        """The workers' delivery subjects (NATS: set before the messages are drawn)."""
        self.partitions = PARTITIONS
        self.ids = 0
        self.headed = 0
        """Messages with a header block (NATS)."""
        self.refused = 0
        """Messages the NATS server refuses: a reply subject of JetStream's acknowledgements."""
        asf_path = DATA / GOOD_CLIP[0]
        self.asf = asf_path.read_text(encoding="utf-8")
        self.asf_lines = self.asf.splitlines()
        self.channels = len(parse_asf(self.asf_lines, str(asf_path)).channel_names)
        base = self.np.normal(0, 30, (len(JOINT_NAMES), 3))
        self.position_blobs = [
            (base + self.np.normal(0, 2, base.shape)).astype("<f4").tobytes() for _ in range(64)
        ]
        self.channel_blobs = [self.np.normal(0, 20, self.channels).astype("<f8").tobytes() for _ in range(64)]
        self.positions = base.astype(np.float32)
        self.good_channels = self.np.normal(0, 20, self.channels)
        self.extra_blobs = {
            n: [(self.np.normal(0, 30, (n, 3))).astype("<f4").tobytes() for _ in range(8)] for n in (27, 29)
        }
        self.new_streams = 0
        self.runs = 0
        self.pool = [self._pooled(k) for k in range(POOL)]
        self.kinds: Counter[str] = Counter()

    # --- the pool of streams with valid traffic

    def _pooled(self, k: int) -> _Pooled:
        name = f"fz-{k:02d}"
        if k < 12:
            skeleton: dict[str, Any] = {
                "v": 1,
                "type": "skeleton",
                "stream": name,
                "rate": RATE,
                "asf": self.asf,
                "angle_unit": "deg" if k % 2 else "rad",
            }
            width, channels = self.channels, True
        else:
            joints = list(JOINT_NAMES) + [f"extra{j}" for j in range(k % 3 if k % 3 != 2 else 3)]
            self.rng.shuffle(joints)
            skeleton = {
                "v": 1,
                "type": "skeleton",
                "stream": name,
                "rate": RATE if k % 5 else 60.0,
                "joints": joints,
                "up": "z" if k % 4 == 0 else "y",
                "units": "cm",
            }
            width, channels = len(joints), False
        stream = _Pooled(name, skeleton, width, channels, seq=self.rng.randrange(0, 10**6))
        if k % 2:
            self._new_epoch(stream)
        return stream

    def _new_epoch(self, s: _Pooled) -> None:
        self.runs += 1
        s.epoch = f"run{self.runs:x}-{self.rng.getrandbits(32):08x}"
        s.skeleton["epoch"] = s.epoch

    def _values(self, s: _Pooled) -> bytes:
        if s.channels:
            return self.rng.choice(self.channel_blobs)
        if s.width == len(JOINT_NAMES):
            return self.rng.choice(self.position_blobs)
        blobs = self.extra_blobs.get(s.width)
        if blobs is None:
            blobs = self.extra_blobs[s.width] = [
                self.np.normal(0, 30, (s.width, 3)).astype("<f4").tobytes() for _ in range(8)
            ]
        return self.rng.choice(blobs)

    def _pose_body(self, s: _Pooled, seq: int) -> dict[str, Any]:
        body: dict[str, Any] = {"v": 1, "type": "pose", "stream": s.name, "seq": seq, "time": time.time()}
        body["channels" if s.channels else "positions"] = self._values(s)
        if s.epoch is not None:
            body["epoch"] = s.epoch
        return body

    # --- values

    def _text(self) -> str:
        r = self.rng.random()
        if r < 0.3:
            return self.rng.choice(ODD_IDS)
        n = self.rng.choice((0, 1, 5, 40, 300))
        return "".join(
            chr(self.rng.choice((self.rng.randrange(32, 127), self.rng.randrange(0x80, 0x3000))))
            for _ in range(n)
        )

    def junk(self, depth: int = 0) -> Any:
        """A random msgpack value: scalars at their edges, strings, bytes, containers, ext types."""
        r = self.rng.randrange(12 if depth < 3 else 8)
        if r == 0:
            return None
        if r == 1:
            return self.rng.random() < 0.5
        if r == 2:
            return (
                self.rng.choice(EDGE_INTS) if self.rng.random() < 0.6 else self.rng.randrange(-(10**9), 10**9)
            )
        if r == 3:
            return self.rng.choice(EDGE_FLOATS) if self.rng.random() < 0.6 else self.rng.uniform(-1e6, 1e6)
        if r in (4, 5):
            return self._text()
        if r == 6:
            return self.rng.randbytes(self.rng.choice((0, 1, 12, 78 * 4, 100)))
        if r == 7:
            if self.rng.random() < 0.5:
                return msgpack.Timestamp(self.rng.randrange(-(2**33), 2**33), self.rng.randrange(10**9))
            return msgpack.ExtType(
                self.rng.randrange(128), self.rng.randbytes(self.rng.choice((0, 4, 8, 12, 3)))
            )
        if r in (8, 9):
            return [self.junk(depth + 1) for _ in range(self.rng.randrange(4))]
        return {self._text(): self.junk(depth + 1) for _ in range(self.rng.randrange(4))}

    # --- the four kinds

    def messages(self, n: int) -> Iterator[Fuzzed]:
        """``n`` fuzzed messages (over NATS a repeated ``Nats-Msg-Id`` is a second message)."""
        sent = 0
        while sent < n:
            r = self.rng.random()
            if self.nats and r < 0.08:
                batch = self.nats_only()
            else:
                r = self.rng.random()
                if r < 0.20:
                    m = self.random_bytes()
                elif r < 0.65:
                    m = self.mutated()
                elif r < 0.90:
                    m = self.valid()
                else:
                    m = self.wrong_topic()
                assert _not_good(m.topic), m.topic
                batch = self.over_nats(m) if self.nats else [m]
            for m in batch[: n - sent]:
                assert not self.nats or _not_good_subject(m.topic), m.topic
                self.kinds[m.kind] += 1
                self.headed += m.headers is not None
                self.refused += m.reply.startswith(b"$JS.ACK.")
                sent += 1
                yield m

    # --- NATS: subjects, header blocks, reply subjects, the workers' delivery subjects

    def over_nats(self, m: Fuzzed) -> list[Fuzzed]:
        """``m`` published on NATS: its topic as a subject (:func:`subject_of`), one in ten with a
        header block (:data:`HEADER_BLOCKS`; a ``Nats-Msg-Id`` of its own, or the same message
        twice with one, the second not stored), one in thirty with a reply subject."""
        rng = self.rng
        subject = subject_of(m.topic)
        reply = b"fuzz.reply." + str(rng.randrange(100)).encode() if rng.random() < 0.03 else b""
        stored = nats_stored(subject, self.partitions)
        stray = nats_stray(subject, self.partitions)  # read on a plain subscription: every copy
        m = replace(m, topic=subject, reply=reply, reaches=stored or stray, stray=stray)
        if rng.random() >= 0.1:
            return [m]
        r = rng.random()
        if r < 0.15:  # twice with one id: JetStream stores the first copy only
            self.ids += 1
            block = b"NATS/1.0\r\nNats-Msg-Id: fuzz-%d-%d\r\n\r\n" % (self.ids, rng.getrandbits(32))
            first = replace(m, headers=block)
            return [first, replace(first, reaches=stray)]
        if r < 0.25:
            self.ids += 1
            block = b"NATS/1.0\r\nNats-Msg-Id: fuzz-%d-%d\r\n\r\n" % (self.ids, rng.getrandbits(32))
            return [replace(m, headers=block)]
        block, kept = rng.choice(HEADER_BLOCKS)
        return [replace(m, headers=block, reaches=(stored and kept) or stray)]

    def nats_only(self) -> list[Fuzzed]:
        """A message only NATS can carry: on a subject straight into a partition's buffer (of a
        pool stream, the wrong partition or none, a subject of the wrong shape, bytes that are not
        UTF-8, control characters, wildcard tokens), one the server drops or stores elsewhere
        (empty tokens, ``mocap.d.<s>.detections``, a status subject), or one published on a
        worker's delivery subject (:meth:`inbox`)."""
        rng = self.rng
        if self.inboxes and rng.random() < 0.25:
            return [self.inbox()]
        s = rng.choice(self.pool)
        name = s.name.encode()
        n = rng.randrange(self.partitions)
        part = b"mocap.p.%d." % n
        r = rng.random()
        if r < 0.3:  # a pool stream's valid message, straight into some partition
            word = b"pose" if rng.random() < 0.8 else b"skeleton"
            body = pack(self._pose_body(s, s.seq + 1)) if word == b"pose" else pack(s.skeleton)
            return [Fuzzed("subject", part + name + b"." + word, (body,))]
        payload = self.rng.choice(
            (pack(self._pose_body(s, s.seq + 1)), self.rng.randbytes(self.rng.randrange(64)), b"")
        )
        subjects = (
            part + b"x",
            part + rng.randbytes(rng.randrange(1, 9)).translate(SUBJECT_SAFE) + b".pose",
            b"mocap." + b"\xff\xfe" + rng.randbytes(3).translate(SUBJECT_SAFE) + b".pose",
            part + b"a\x00b.pose",
            b"mocap.a\x01\x7f.skeleton",
            part + b"*.pose",
            b"mocap.*.pose",
            part + b">",
            part + name + b".pose.extra",
            part + b"a.b.pose",
            part + b"\xc3\xa9" * 700 + b".pose",
            b"mocap.p.%02d.x.pose" % n,
            b"mocap.p.%d.x.pose" % self.partitions,  # no such partition: no buffer stores it
            b"mocap..pose",
            b".mocap.x.pose",
            b"mocap.x.pose.",
            b"mocap.>.pose",
            b"mocap.>",
            b"mocap.d." + name + b".detections",
            b"mocap." + name + b".detections",
            b"mocapd." + name + b".status",
            b"MOCAP." + name + b".pose",
        )
        subject = rng.choice(subjects)
        stray = nats_stray(subject, self.partitions)
        headers = None
        if subject.startswith(b"mocap.d."):
            self.ids += 1
            headers = b"NATS/1.0\r\nNats-Msg-Id: fuzz-d-%d\r\n\r\n" % self.ids
        return [
            Fuzzed(
                "subject",
                subject,
                (payload,),
                headers=headers,
                reaches=nats_stored(subject, self.partitions) or stray,
                stray=stray,
            )
        ]

    def inbox(self) -> Fuzzed:
        """A message published on a worker's delivery subject: a pose or junk with no reply,
        another reply, a forged acknowledgement subject (the server refuses a reply of ``$JS.ACK.``
        from any client: measured), odd header blocks; or the server's flow control and heartbeats
        forged (status 100: answered only on a ``$JS.FC.`` subject, never on the one a
        ``Nats-Consumer-Stalled`` header names otherwise; not counted)."""
        rng = self.rng
        subject = rng.choice(self.inboxes)
        s = rng.choice(self.pool)
        payload = rng.choice((pack(self._pose_body(s, s.seq + 1)), pack(s.skeleton), rng.randbytes(40), b""))
        p = rng.randrange(self.partitions)
        replies = (
            b"",
            b"fuzz.reply",
            b"$JS.ACK.MOCAPD_BUF_%d.forged.1.%d.%d.0.0" % (p, rng.randrange(1, 10**6), rng.randrange(10**6)),
            b"$JS.ACK.MOCAPD_BUF_%d.forged.1.x.y.0.0" % p,
            b"$JS.ACK.x",
            b"$JS.ACK.MOCAPD_BUF_%d.\xff\xfe.1.2.3.0.0" % p,
        )
        r = rng.random()
        if r < 0.25:
            block = rng.choice(
                (
                    b"NATS/1.0 100 FlowControl Request\r\n\r\n",
                    STALLED % b"$JS.API.STREAM.DELETE.MOCAPD_BUF_%d" % p,
                    STALLED % b"fuzz.stalled",
                    STALLED % b"$JS.FC.fuzz.%d" % p,
                )
            )
            reply = rng.choice((b"", b"$JS.FC.MOCAPD_BUF_%d.fuzz.%d" % (p, rng.randrange(100))))
            return Fuzzed("inbox", subject, (b"",), headers=block, reply=reply, reaches=False)
        other: bytes | None = rng.choice(
            (None, None, *(b for b, _ in HEADER_BLOCKS if not b.startswith(b"NATS/1.0 100")))
        )
        reply = rng.choice(replies)  # the server refuses a reply of $JS.ACK.: no client forges one
        forged = reply.startswith(b"$JS.ACK.")
        return Fuzzed("inbox", subject, (payload,), headers=other, reply=reply, reaches=not forged)

    def _topic(self, stream: str, word: str) -> bytes:
        return f"mocap/{stream}/{word}".encode()

    def _some_topic(self) -> bytes:
        """Mostly a pool or ghost stream's pose or skeleton topic."""
        r = self.rng.random()
        word = "pose" if self.rng.random() < 0.7 else "skeleton"
        if r < 0.8:
            return self._topic(self.rng.choice(self.pool).name, word)
        if r < 0.9:
            return self._topic(f"ghost-{self.rng.randrange(GHOSTS):03d}", word)
        return self.odd_topic()

    def random_bytes(self) -> Fuzzed:
        r = self.rng.random()
        if r < 0.0005:
            size = self.rng.randrange(MAX_MESSAGE_BYTES + 1, MAX_MESSAGE_BYTES + 4000)
        elif r < 0.4:
            size = self.rng.randrange(33)
        elif r < 0.8:
            size = self.rng.randrange(33, 513)
        else:
            size = self.rng.randrange(513, 2049)
        payload = self.rng.randbytes(size)
        if size and self.rng.random() < 0.2:  # a map's first byte: parsed a little further
            payload = bytes([0x80 | self.rng.randrange(16)]) + payload[1:]
        return Fuzzed("random", self._some_topic(), (payload,), self._qos())

    def _qos(self) -> int:
        return 1 if self.rng.random() < 0.2 else 0

    def mutated(self) -> Fuzzed:
        """A valid skeleton, pose or other message with one to three things wrong with it."""
        s = self.rng.choice(self.pool)
        r = self.rng.random()
        word = "pose"
        if r < 0.6:
            body = self._pose_body(s, s.seq + 1)
        elif r < 0.9:
            body = dict(s.skeleton)
            word = "skeleton"
        else:
            body = self._other_message(s.name)
        for _ in range(self.rng.choice((1, 1, 1, 2, 3))):
            self._mutate(body)
        try:
            payload = pack(body)
        except (OverflowError, ValueError, TypeError):  # nothing generated should get here
            payload = pack({"v": 1, "type": word, "stream": s.name, "x": shape(body)})
        r = self.rng.random()
        if r < 0.08 and payload:
            payload = payload[: self.rng.randrange(len(payload))]  # truncated
        elif r < 0.14 and payload:
            flipped = bytearray(payload)
            for _ in range(self.rng.randrange(1, 4)):
                flipped[self.rng.randrange(len(flipped))] ^= 1 << self.rng.randrange(8)
            payload = bytes(flipped)
        elif r < 0.17:
            payload += self.rng.randbytes(self.rng.randrange(1, 9))  # extra bytes after the map
        elif r < 0.19:
            payload = self._nested()
        elif r < 0.195:
            payload = self.rng.choice(BAD_TIMESTAMPS)
        elif r < 0.21:
            payload = msgpack.packb({1: 2, "v": 1}, strict_types=False)  # a key that is no string
        elif r < 0.22:
            payload = pack([body.get("v"), body.get("type")])  # not a map
        topic = (
            self._topic(s.name, word)
            if self.rng.random() < 0.9
            else self._topic(s.name, "skeleton" if word == "pose" else "pose")
        )
        return Fuzzed("mutated", topic, (payload,), 1 if word == "skeleton" else self._qos())

    def _nested(self) -> bytes:
        depth = self.rng.choice((10, 500, 1000, 2000, 5000))
        opener = b"\x91" if self.rng.random() < 0.5 else b"\x81\xa1k"
        return opener * depth + b"\xc0"

    def _other_message(self, stream: str) -> dict[str, Any]:
        """A valid message of a type the daemon publishes (detection, boundary, progress, status), as
        a map."""
        kind = self.rng.randrange(4)
        if kind == 0:
            message: Message = DetectionMessage("x", stream, "squat", 1, 2, 0.1, 0.2, 3, 1.0, 2.0)
        elif kind == 1:
            message = BoundaryMessage("x", stream, 4, "pca", 1.0, 1.0)
        elif kind == 2:
            classes = tuple(
                ClassProgress(f"class{k}", 3, (10 + k, 20 + k), 0.25 * k, 0.01, 0.1)
                for k in range(self.rng.randrange(1, 4))
            )
            message = ProgressMessage(stream, 30, classes, 1.0, 2.0)
        else:
            message = StatusMessage("fuzz", "online", "0", 1, 1.0)
        body: dict[str, Any] = msgpack.unpackb(encode(message))
        return body

    def _mutate(self, body: dict[str, Any]) -> None:
        rng = self.rng
        keys = list(body)
        op = rng.randrange(20)
        if op >= 14 and keys:  # a field's value, recursively (into lists and maps such as classes)
            key = rng.choice(keys)
            body[key] = self.mutate_value(body[key])
        elif op == 0 and keys:
            del body[rng.choice(keys)]
        elif op == 1:
            body[rng.choice(EXTRA_FIELDS)] = self.junk()
        elif op == 2 and keys:
            body[rng.choice(keys)] = self.junk()
        elif op in (3, 4, 6, 7, 8, 10, 11, 12):
            name = {3: "v", 4: "type", 6: "seq", 7: "time", 8: "epoch", 10: "rate", 11: "joints"}.get(op)
            name = name or rng.choice(("up", "units", "angle_unit"))
            body[name] = rng.choice(BAD[name])
        elif op == 5:
            body["stream"] = rng.choice(ODD_IDS) if rng.random() < 0.8 else self.junk()
        elif op == 9:
            self._mutate_array(body)
        else:
            body["asf"] = self._mutated_asf()

    # --- field values, recursively

    def mutate_value(self, value: Any, depth: int = 0) -> Any:
        """``value`` mutated: a list's or a map's contents mutated in turn (an element or an entry,
        recursively, or one added or removed), or the value replaced by :meth:`hostile`."""
        rng = self.rng
        if isinstance(value, list | dict) and value and depth < 6 and rng.random() < 0.6:
            value = list(value) if isinstance(value, list) else dict(value)
            r = rng.random()
            if isinstance(value, list):
                k = rng.randrange(len(value))
                if r < 0.7:
                    value[k] = self.mutate_value(value[k], depth + 1)
                elif r < 0.85:
                    value.insert(k, self.hostile(value[k]))
                else:
                    del value[k]
            else:
                key = rng.choice(list(value))
                if r < 0.7:
                    value[key] = self.mutate_value(value[key], depth + 1)
                elif r < 0.85:
                    value[rng.choice(ODD_KEYS)] = self.hostile(None)
                else:
                    del value[key]
            return value
        return self.hostile(value)

    def hostile(self, original: Any) -> Any:
        """A value to put in place of ``original``: nested lists and maps (often around the
        decoder's depth bound, sometimes ~1,000 deep), deep maps with odd keys, huge integers, NaN
        and infinities, the wrong type for ``original`` (bytes for a string, a string for bytes, a
        bool for an int, None), long strings, ext types, or any :meth:`junk`."""
        rng = self.rng
        r = rng.randrange(10)
        if r in (0, 1):
            return self.nested(rng.choice(DEPTHS))
        if r == 2:
            return self.nested(rng.choice(DEPTHS), maps=True)
        if r == 3:
            return rng.choice(HUGE_INTS)
        if r == 4:
            return rng.choice(ODD_FLOATS)
        if r in (5, 6):
            return self.retyped(original)
        if r == 7:
            n = rng.choice(LONG_TEXTS)
            return rng.choice(("x", "é", "流", "😀", "\x00", "a.b")) * (n // 2) + "y" * (n - n // 2)
        if r == 8:
            return rng.choice((None, [], {}, "", b"", 0, False))
        return self.junk()

    def retyped(self, original: Any) -> Any:
        """``original`` as the wrong type: a string as bytes, bytes as a string, a number as a bool,
        a string or a float, a list as a map, a map as a list, anything as None."""
        rng = self.rng
        if rng.random() < 0.15:
            return None
        if isinstance(original, str):
            return original.encode("utf-8", "surrogatepass") if rng.random() < 0.7 else [original]
        if isinstance(original, bytes):
            return original.decode("latin-1") if rng.random() < 0.7 else list(original[:64])
        if isinstance(original, bool):
            return int(original)
        if isinstance(original, int):
            return rng.choice((True, False, float(original), str(original), [original]))
        if isinstance(original, float):
            return rng.choice((True, int(original) if math.isfinite(original) else 0, str(original)))
        if isinstance(original, list):
            return {str(k): v for k, v in enumerate(original)}
        if isinstance(original, dict):
            return list(original.values())
        return rng.choice((True, b"bytes", "text", 1))

    def nested(self, depth: int, *, maps: bool = False) -> Any:
        """A value ``depth`` lists or maps deep (maps: keys from :data:`ODD_KEYS`, and now and then
        a sibling entry; only maps with ``maps``) around a scalar: as a field's value, it makes the
        message ``depth`` + 1 deep."""
        rng = self.rng
        keys = ODD_KEYS if depth <= 16 else SHORT_KEYS  # 1,000 levels of long keys: past any size limit
        value: Any = rng.choice((None, 1, "x", b"\x00", 2**64 - 1, float("nan"), True))
        for level in range(depth):
            if maps or (depth < 100 and rng.random() < 0.3):
                inner: dict[Any, Any] = {rng.choice(keys): value}
                if level < 10 and rng.random() < 0.2:
                    inner[rng.choice(keys)] = rng.choice(HUGE_INTS)
                value = inner
            else:
                value = [value]
        return value

    def _mutate_array(self, body: dict[str, Any]) -> None:
        rng = self.rng
        name = "channels" if "channels" in body else "positions"
        dtype = "<f8" if name == "channels" else "<f4"
        width = self.channels if name == "channels" else len(JOINT_NAMES) * 3
        r = rng.randrange(9)
        if r == 0:
            body[name] = rng.randbytes(rng.choice((0, 1, 7, 11, 13, 77)))  # no whole number of values
        elif r == 1:
            count = rng.choice((1, 3, 10, 25, 27, 100, 1000)) * (1 if name == "channels" else 3)
            body[name] = self.np.normal(0, 30, count).astype(dtype).tobytes()  # another width
        elif r in (2, 3):
            a = self.np.normal(0, 30, width).astype(dtype)
            a[rng.randrange(width)] = rng.choice((NAN, INF, -INF))
            body[name] = a.tobytes()
        elif r == 4:
            with np.errstate(over="ignore", under="ignore"):  # 1e308 as float32: infinity
                body[name] = np.full(width, rng.choice(BAD["huge"]), dtype).tobytes()
        elif r == 5:
            body[name] = self.np.normal(0, 30, width).astype(dtype).tolist()  # a list, not bytes
        elif r == 6:
            body[name] = "not bytes"
        elif r == 7:
            body["positions" if name == "channels" else "channels"] = body.pop(name, b"")  # the other kind
        else:
            body["positions"] = self.np.normal(0, 30, len(JOINT_NAMES) * 3).astype("<f4").tobytes()
            body["channels"] = self.np.normal(0, 30, self.channels).astype("<f8").tobytes()  # both

    def _mutated_asf(self) -> Any:
        rng = self.rng
        lines = list(self.asf_lines)
        r = rng.randrange(9)
        if r == 0:
            return self.asf[: rng.randrange(len(self.asf))]
        if r == 1:
            for _ in range(rng.randrange(1, 20)):
                del lines[rng.randrange(len(lines))]
        elif r == 2:
            k = rng.randrange(len(lines))
            words = lines[k].split()
            if words:
                words[rng.randrange(len(words))] = rng.choice(BAD["asf word"])
                lines[k] = " ".join(words)
        elif r == 3:
            rng.shuffle(lines)
        elif r == 4:
            k = rng.randrange(len(lines))
            lines[k : k + 1] = [lines[k]] * rng.randrange(2, 50)
        elif r == 5:
            lines.insert(rng.randrange(len(lines)), self.rng.randbytes(40).decode("latin-1"))
        elif r == 6:
            return rng.choice((*BAD["asf"], self.asf.replace("dof", "dof rx ry rz tx ty tz l")))
        elif r == 7:
            start = rng.randrange(len(lines))
            del lines[start : start + rng.randrange(1, 60)]
        else:
            return self.junk()
        return "\n".join(lines)

    def valid(self) -> Fuzzed:
        """A valid message of another stream: announcements, poses in order and not."""
        rng = self.rng
        r = rng.random()
        s = rng.choice(self.pool)
        if r < 0.12:
            q = rng.random()
            if q < 0.3:
                self._new_epoch(s)  # a new run of the source
            elif q < 0.35:
                s.skeleton["rate"] = rng.choice(RATES)  # a changed skeleton
            return self._skeleton_of(s)
        if r < 0.70:
            s.seq += 1
            return self._pose_of(s, s.seq)
        if r < 0.74:
            return self._pose_of(s, s.seq)  # the same again
        if r < 0.78:
            return self._pose_of(s, max(0, s.seq - rng.randrange(1, 100)))  # out of order
        if r < 0.81:
            s.seq += rng.randrange(2, 40)  # a gap
            return self._pose_of(s, s.seq)
        if r < 0.83:
            return self._pose_of(s, min(s.seq + 10**7, 2**53 - 1))  # implausibly far ahead
        if r < 0.84:
            s.seq = rng.randrange(0, 100)  # numbered from its start again
            return self._pose_of(s, s.seq)
        if r < 0.93:
            ghost = f"ghost-{rng.randrange(GHOSTS):03d}"
            message = PoseMessage(ghost, rng.randrange(10**6), time.time(), positions=self.positions)
            return Fuzzed("valid", self._topic(ghost, "pose"), (encode(message),), self._qos())
        if r < 0.935:
            self.new_streams += 1
            name = f"new-{self.new_streams}"
            skeleton = encode(SkeletonMessage(name, RATE, JOINT_NAMES))
            return Fuzzed("valid", self._topic(name, "skeleton"), (skeleton,), 1)
        if r < 0.96:
            other = pack(self._other_message(s.name))
            return Fuzzed("valid", self._topic(s.name, "pose"), (other,), self._qos())
        s.seq += 1
        return self._pose_of(s, s.seq)

    def _skeleton_of(self, s: _Pooled) -> Fuzzed:
        return Fuzzed("valid", self._topic(s.name, "skeleton"), (pack(s.skeleton),), 1)

    def _pose_of(self, s: _Pooled, seq: int) -> Fuzzed:
        payload = pack(self._pose_body(s, seq))
        return Fuzzed("valid", self._topic(s.name, "pose"), (payload,), self._qos())

    def odd_topic(self) -> bytes:
        """A topic mocapd does not take, or one of a stream id that is no id."""
        rng = self.rng
        s = rng.choice(self.pool).name
        options = [
            f"mocap/{s}/detections",
            f"mocap/{s}/boundaries",
            f"mocap/{s}/Pose",
            f"mocap/{s}/",
            f"mocap/{s}",
            f"mocap/{s}/pose/extra",
            "mocap//pose",
            "mocap//skeleton",
            "mocap/" + "a" * 129 + "/pose",
            "mocap/with space/pose",
            "mocap/ünïcödé/skeleton",
            "mocap/😀/pose",
            "mocap/$x/pose",
            f"mocapd/{s}/status",
            "foo/bar",
            "mocap",
            f"MOCAP/{s}/pose",
            f"/mocap/{s}/pose",
            "mocap/" + rng.choice(ODD_IDS) + "/" + rng.choice(("pose", "skeleton")),
        ]
        if not self.mqtt:
            options += [
                "mocap/+/pose",
                "mocap/#",
                "mocap/a\x00b/pose",
                f"mocap/{s}/pose\x00",
                "",
            ]
        while True:
            topic = rng.choice(options)
            if self.mqtt and not _mqtt_safe(topic):
                continue
            encoded = topic.encode("utf-8", "surrogatepass")
            if not self.mqtt and rng.random() < 0.1:
                encoded = b"mocap/" + rng.randbytes(rng.randrange(1, 12)) + b"/pose"  # not UTF-8
            if self.nats and not _not_good_subject(subject_of(encoded)):
                continue
            if _not_good(encoded):
                return encoded

    def wrong_topic(self) -> Fuzzed:
        """A valid message on a topic that does not fit it, or on a topic mocapd does not take."""
        rng = self.rng
        s, other = rng.sample(self.pool, 2)
        pose = pack(self._pose_body(s, s.seq + 1))
        r = rng.random()
        if r < 0.25:
            return Fuzzed("topic", self._topic(other.name, "pose"), (pose,), self._qos())  # another stream's
        if r < 0.35:
            good = PoseMessage(GOOD_STREAM, s.seq + 1, time.time(), channels=self.good_channels)
            return Fuzzed("topic", self._topic(s.name, "pose"), (encode(good),), self._qos())
        if r < 0.45:
            return Fuzzed("topic", self._topic(s.name, "skeleton"), (pose,), 1)  # a pose as a skeleton
        if r < 0.52:
            skeleton = pack(s.skeleton)
            return Fuzzed("topic", self._topic(s.name, "pose"), (skeleton,), 0)  # a skeleton as a pose
        if r < 0.57:
            return Fuzzed("topic", self._topic(other.name, "skeleton"), (pack(s.skeleton),), 1)
        if r < 0.62:  # an empty skeleton: MQTT's way to clear a retained one
            return Fuzzed("topic", self._topic(s.name, "skeleton"), (b"",), 1)
        if self.frames and r < 0.72:
            frames = rng.choice(((), (pose, b"more"), (b"", b""), (pose, pose, pose)))
            return Fuzzed("topic", self._topic(s.name, "pose"), frames)  # not [topic, payload]
        return Fuzzed("topic", self.odd_topic(), (pose,), self._qos())


def _not_good(topic: bytes) -> bool:
    """Whether a topic stays off the good stream (its second level is not the good stream's id)."""
    return topic.split(b"/")[1:2] != [GOOD_STREAM.encode()]


def _not_good_subject(subject: bytes) -> bool:
    """Whether a NATS subject stays off the good stream: neither ``mocap.good.*`` nor
    ``mocap.p.<p>.good.*``."""
    tokens = subject.split(b".")
    good = GOOD_STREAM.encode()
    return tokens[1:2] != [good] and not (tokens[:2] == [b"mocap", b"p"] and tokens[3:4] == [good])


def routed(m: Fuzzed, transport: str) -> bool:
    """Whether a message reaches the daemon: over ZeroMQ what its subscription (``mocap/``) lets
    through; over MQTT what its subscriptions (``mocap/+/skeleton``, ``mocap/+/pose``) match; over
    NATS what a partition's buffer stores (:func:`nats_stored`) and what is published on a worker's
    delivery subject, but the server's flow control (:attr:`Fuzzed.reaches`)."""
    if transport == "nats":
        return m.reaches
    if transport == "zmq":
        return m.topic.startswith(b"mocap/")
    levels = m.topic.decode().split("/")
    return len(levels) == 3 and levels[0] == "mocap" and levels[2] in ("skeleton", "pose")


# ---------------------------------------------------------------------------------- the senders


class DaemonDied(Exception):
    """The daemon died while a message waited to be sent to it."""


class ZmqWire:
    """The fuzz sender over ZeroMQ: an XPUB socket connected to the daemon that never drops (a full
    queue waits), and a SUB socket the good replay sends to, whose messages it passes on (counted)
    between the fuzzed ones."""

    def __init__(self, poses: str, alive: Callable[[], bool] = lambda: True) -> None:
        self.alive = alive
        self.ctx = zmq.Context()
        self.pub = self.ctx.socket(zmq.XPUB)
        self.pub.setsockopt(zmq.SNDHWM, 100_000)
        self.pub.setsockopt(zmq.XPUB_NODROP, 1)
        self.pub.setsockopt(zmq.LINGER, 10_000)
        self.pub.connect(poses)
        if not self.pub.poll(10_000):
            raise RuntimeError("the daemon did not subscribe")
        self.pub.recv()
        self.relay = self.ctx.socket(zmq.SUB)
        self.relay.setsockopt(zmq.RCVHWM, 0)
        self.relay.setsockopt(zmq.LINGER, 0)
        self.relay.setsockopt(zmq.SUBSCRIBE, b"")
        port = free_port()
        self.relay.bind(f"tcp://127.0.0.1:{port}")
        self.good_url = f"zmq+tcp://127.0.0.1:{port}"
        self.good = 0
        self.problem: str | None = None

    def _send(self, frames: list[bytes]) -> None:
        waited = 0
        while True:
            try:
                self.pub.send_multipart(frames, zmq.NOBLOCK)
                return
            except zmq.Again:
                time.sleep(0.0005)  # the daemon's queue is full: wait, never drop
                waited += 1
                if waited % 200 == 0 and not self.alive():
                    raise DaemonDied from None  # a dead daemon never takes it: do not wait for ever

    def send(self, m: Fuzzed) -> None:
        self._send([m.topic, *m.payloads])

    def pump(self) -> None:
        """Pass on what the good replay sent."""
        while True:
            try:
                frames = self.relay.recv_multipart(zmq.NOBLOCK)
            except zmq.Again:
                return
            self._send(frames)
            self.good += 1

    def close(self) -> None:
        self.relay.close()
        self.pub.close()
        self.ctx.term()


class MqttWire:
    """The fuzz sender over MQTT (paho, QoS 0 and 1 as :class:`Fuzzed` says), and a subscriber of
    the good stream's topics that counts its messages and reads the broker's count of dropped
    messages (``$SYS``)."""

    def __init__(self, port: int, good_url: str) -> None:
        self.good_url = good_url
        self.good = 0
        self.dropped: int | None = None
        self.problem: str | None = None
        self.client = paho.Client(CallbackAPIVersion.VERSION2, client_id=f"fuzz-{os.getpid()}")
        self.client.max_queued_messages_set(0)
        self.client.max_inflight_messages_set(1000)
        self.client.on_disconnect = self._lost
        self.client.connect("127.0.0.1", port)
        self.client.loop_start()
        self.counter = paho.Client(CallbackAPIVersion.VERSION2, client_id=f"fuzz-count-{os.getpid()}")
        self.subscribed = threading.Event()
        self.counter.on_message = self._counted
        self.counter.on_subscribe = lambda *_: self.subscribed.set()
        self.counter.connect("127.0.0.1", port)
        self.counter.subscribe(
            [
                (f"mocap/{GOOD_STREAM}/skeleton", 1),
                (f"mocap/{GOOD_STREAM}/pose", 1),
                ("$SYS/broker/publish/messages/dropped", 0),
            ]
        )
        self.counter.loop_start()
        if not self.subscribed.wait(10):
            raise RuntimeError("the counting subscriber did not subscribe")
        self.last: paho.MQTTMessageInfo | None = None

    def _lost(self, *args: Any) -> None:
        self.problem = f"the fuzz sender was disconnected: {args[3]}"

    def _counted(self, client: Any, userdata: Any, message: Any) -> None:
        if message.topic.startswith("$SYS/"):
            self.dropped = int(message.payload)
        else:
            self.good += 1

    def send(self, m: Fuzzed) -> None:
        info = self.client.publish(m.topic.decode(), m.payloads[0], qos=m.qos)
        if info.rc != paho.MQTT_ERR_SUCCESS:
            self.problem = f"publish failed: {paho.error_string(info.rc)}"
        if m.qos:
            self.last = info

    def pump(self) -> None:
        """Nothing: the good replay publishes to the broker itself."""

    def close(self) -> None:
        if self.last is not None:
            self.last.wait_for_publish(30)
        self.client.disconnect()
        self.client.loop_stop()
        self.counter.disconnect()
        self.counter.loop_stop()


class NatsWire:
    """The fuzz sender over NATS: a raw client connection of its own (``PUB`` and ``HPUB`` of any
    subject, reply and header block, which nats-py would refuse to send), a thread answering the
    server's PINGs on it; and in a thread with an event loop, a subscriber
    (:class:`protocols.deliveries.Reader`: a nats-py subscriber stops at the first message it cannot
    decode) counting the good stream's messages on ``mocap.p.*.good.*`` and collecting its
    detections from ``mocap.good.detections``, and a nats-py client for JetStream's API (the
    buffers' counts, the workers' delivery subjects). The good replay publishes over the server's
    MQTT listener itself."""

    def __init__(self, port: int, mqtt_port: int, partitions: int) -> None:
        self.url = f"nats://127.0.0.1:{port}"
        self.partitions = partitions
        self.good_url = f"mqtt://127.0.0.1:{mqtt_port}"
        self.good = 0
        self.detections: list[dict[str, Any]] = []
        self.problem: str | None = None
        self.refused = 0
        """Fuzzed messages the server refused (a reply subject of ``$JS.ACK.``)."""
        self._buffer = bytearray()
        self._lock = threading.Lock()
        self._pongs = threading.Semaphore(0)
        self.sock = socket.create_connection(("127.0.0.1", port))
        self.sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        hello = b""
        while b"\r\n" not in hello:
            hello += self.sock.recv(4096)
        connect = {"verbose": False, "pedantic": False, "headers": True, "echo": False, "name": "fuzz"}
        self.sock.sendall(b"CONNECT %s\r\n" % json.dumps(connect).encode())
        self._watcher = threading.Thread(target=self._watch, name="fuzz nats", daemon=True)
        self._watcher.start()
        self.loop = asyncio.new_event_loop()
        self._thread = threading.Thread(target=self.loop.run_forever, name="fuzz nats api", daemon=True)
        self._thread.start()
        self.call(self._connect())
        self.sync()

    def call(self, coroutine: Coroutine[Any, Any, T], timeout: float = 30) -> T:
        return asyncio.run_coroutine_threadsafe(coroutine, self.loop).result(timeout)

    async def _connect(self) -> None:
        import nats

        self.nc = await nats.connect(self.url)
        self.js = self.nc.jetstream()
        self.reader = await Reader(self.url, "fuzz counter").start()
        await self.reader.subscribe(f"mocap.p.*.{GOOD_STREAM}.*", self._good)
        await self.reader.subscribe(f"mocap.{GOOD_STREAM}.detections", self._detection)

    async def _good(self, delivery: Delivery) -> None:
        self.good += 1

    async def _detection(self, delivery: Delivery) -> None:
        self.detections.append(msgpack.unpackb(delivery.data, raw=False))

    def _watch(self) -> None:
        """The server's lines: PING answered, PONG counted (:meth:`sync`), -ERR kept as a problem."""
        pending = b""
        while True:
            try:
                data = self.sock.recv(65536)
            except OSError:
                return
            if not data:
                self.problem = self.problem or "the fuzz sender's NATS connection was closed"
                return
            pending += data
            while b"\r\n" in pending:
                line, pending = pending.split(b"\r\n", 1)
                if line.startswith(b"PING"):
                    with self._lock:
                        self.sock.sendall(b"PONG\r\n")
                elif line.startswith(b"PONG"):
                    self._pongs.release()
                elif line.startswith(b"-ERR 'Permissions Violation for Publish with Reply of \"$JS.ACK."):
                    self.refused += 1  # a forged acknowledgement subject: refused, as it should be
                elif line.startswith(b"-ERR"):
                    self.problem = f"the server refused a fuzzed message: {line[:200]!r}"

    def send(self, m: Fuzzed) -> None:
        payload = m.payloads[0] if m.payloads else b""
        reply = b" " + m.reply if m.reply else b""
        if m.headers is None:
            self._buffer += b"PUB %s%s %d\r\n%s\r\n" % (m.topic, reply, len(payload), payload)
        else:
            total = len(m.headers) + len(payload)
            self._buffer += b"HPUB %s%s %d %d\r\n%s%s\r\n" % (
                m.topic,
                reply,
                len(m.headers),
                total,
                m.headers,
                payload,
            )
        if len(self._buffer) > 1 << 16:
            self.pump()

    def pump(self) -> None:
        """Send what is buffered."""
        if self._buffer:
            with self._lock:
                self.sock.sendall(self._buffer)
            self._buffer.clear()

    def sync(self, timeout: float = 30) -> None:
        """Return once the server has read everything sent (a PING answered)."""
        self.pump()
        with self._lock:
            self.sock.sendall(b"PING\r\n")
        if not self._pongs.acquire(timeout=timeout):
            raise RuntimeError("the NATS server did not answer the fuzz sender's PING")

    def stored(self) -> int:
        """Messages the partitions' buffers ever stored (each buffer's last sequence number)."""

        async def count() -> int:  # one by one: the server lists streams a page (256) at a time
            total = 0
            for p in range(self.partitions):
                total += (await self.js.stream_info(f"MOCAPD_BUF_{p}")).state.last_seq
            return total

        return self.call(count())

    def inboxes(self) -> list[bytes]:
        """The subjects the workers' consumers deliver the partitions' buffers on, once every
        buffer has one consumer: while the workers share the partitions out at startup, a worker
        deletes the consumers of those it gave up, and a message sent to one of those would
        reach no worker (it would be counted as reaching the daemon, and never be)."""

        async def find() -> list[bytes]:
            deadline = time.monotonic() + 15
            while True:
                found: list[list[bytes]] = []
                for info in await self.js.streams_info():
                    name = info.config.name or ""
                    if name.startswith("MOCAPD_BUF_"):
                        found.append(
                            [
                                c.config.deliver_subject.encode()
                                for c in await self.js.consumers_info(name)
                                if c.config.deliver_subject
                            ]
                        )
                if all(len(f) == 1 for f in found) or time.monotonic() > deadline:
                    return sorted(s for f in found for s in f)
                await asyncio.sleep(0.05)

        return self.call(find())

    def close(self) -> None:
        async def shut() -> None:
            await self.reader.close()
            await self.nc.close()

        with contextlib.suppress(Exception):
            self.call(shut(), 10)
        self.loop.call_soon_threadsafe(self.loop.stop)
        self._thread.join(10)
        self.loop.close()
        with contextlib.suppress(OSError):
            self.sock.close()


# ------------------------------------------------------------------------------ the processes


def start_broker(where: Path) -> tuple[subprocess.Popen[bytes], int]:
    """A mosquitto on a free loopback port that queues without limit (it never drops a message to a
    slow subscriber), no persistence, ``$SYS`` every second."""
    port = free_port()
    config = where / "mosquitto.conf"
    config.write_text(
        f"listener {port} 127.0.0.1\nallow_anonymous true\nset_tcp_nodelay true\nmax_queued_messages 0\n"
        f"sys_interval 1\nlog_dest file {where}/mosquitto.log\nuser {getpass.getuser()}\n",
        encoding="utf-8",
    )
    binary = shutil.which("mosquitto") or "/usr/sbin/mosquitto"
    process = subprocess.Popen(
        [binary, "-c", str(config)], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL
    )
    wait_port(port)
    return process, port


class Daemon:
    """``mocapd --config C run`` on free ports, its stdout (the detections) and stderr (the logs) in
    files in ``where``."""

    def __init__(self, where: Path, transport: str, broker_port: int | None) -> None:
        self.where = where
        self.metrics_port = free_port()
        self.poses = f"tcp://127.0.0.1:{free_port()}"
        config: dict[str, dict[str, Any]] = {
            "service": {
                "instance": f"fuzz-{self.metrics_port}",
                "sources": [transport],
                "sinks": ["stdout"],
                "queue_frames": 100_000,
                "max_streams": MAX_STREAMS,
                "max_message_bytes": MAX_MESSAGE_BYTES,
                "idle_s": 10,
            },
            "zmq": {"poses": self.poses, "detections": f"tcp://127.0.0.1:{free_port()}"},
            "mqtt": {"url": f"mqtt://127.0.0.1:{broker_port}", "queue": 200_000, "reconnect_max_s": 0.5},
            "metrics": {"port": self.metrics_port},
            "logging": {"level": "debug"},
        }
        self.config = where / "daemon.yaml"
        self.config.write_text(json.dumps(config, indent=1), encoding="utf-8")  # JSON is YAML
        self.out, self.err = where / "daemon.out", where / "daemon.err"
        with self.out.open("wb") as out, self.err.open("wb") as err:
            self.process = subprocess.Popen(
                [str(MOCAPD), "--config", str(self.config), "run"], stdout=out, stderr=err
            )
        deadline = time.monotonic() + 60
        while not self._healthy():
            if not self.alive or time.monotonic() > deadline:
                raise RuntimeError(f"the daemon did not start: {self.err.read_text()[-2000:]}")
            time.sleep(0.05)

    def _healthy(self) -> bool:
        try:
            with urllib.request.urlopen(f"http://127.0.0.1:{self.metrics_port}/healthz", timeout=2) as r:
                return bool(r.status == 200)
        except OSError:
            return False

    @property
    def alive(self) -> bool:
        return self.process.poll() is None

    def metrics(self) -> dict[str, float]:
        """The /metrics samples (none if the daemon does not answer)."""
        try:
            return scrape(self.metrics_port)
        except OSError:
            return {}

    def rss_kib(self) -> int:
        return rss_kib(self.process.pid)

    def watch(self) -> None:
        """Nothing: a lone daemon's health is its being alive."""

    def logs(self) -> list[Path]:
        return [self.err]

    def stop(self) -> int:
        if self.alive:
            self.process.send_signal(signal.SIGTERM)
        return self.process.wait(60)

    def close(self) -> None:
        if self.alive:
            self.process.kill()
            self.process.wait()


class Member:
    """One cluster worker, ``mocapd --config C run --cluster NATS --coordinator ETCD`` as member
    ``fuzz-<k>``, its stderr in ``worker-<k>.err``."""

    def __init__(self, where: Path, k: int, nats: str, etcd: str, partitions: int, lease_s: float) -> None:
        self.name = f"fuzz-{k}"
        self.metrics_port = free_port()
        config = {
            "service": {
                "queue_frames": 100_000,
                "max_streams": MAX_STREAMS,
                "max_message_bytes": MAX_MESSAGE_BYTES,
                "idle_s": 10,
            },
            "cluster": {"partitions": partitions, "lease_s": lease_s, "member": self.name},
            "metrics": {"port": self.metrics_port},
            "logging": {"level": "debug"},
        }
        path = where / f"worker-{k}.yaml"
        path.write_text(json.dumps(config, indent=1), encoding="utf-8")
        self.err = where / f"worker-{k}.err"
        command = [str(MOCAPD), "--config", str(path), "run", "--cluster", nats, "--coordinator", etcd]
        with self.err.open("wb") as err:
            self.process = subprocess.Popen(command, stdout=subprocess.DEVNULL, stderr=err)

    def healthy(self) -> bool:
        try:
            with urllib.request.urlopen(f"http://127.0.0.1:{self.metrics_port}/healthz", timeout=2) as r:
                return bool(r.status == 200)
        except OSError:
            return False

    def events(self, name: str) -> list[dict[str, Any]]:
        return [e for e in json_lines(self.err) if e.get("event") == name]


class Cluster:
    """Cluster mode (``docs/cluster.md``): a nats-server from the shipped nats.conf (JetStream, the
    MQTT listener, the partitioning mappings; ``tests/nats_server.py``), an etcd from the shipped
    config, and ``members`` workers (``lease_s``: the shipped 2 s); once every worker sees them
    all, the partitions are split between them. Watched as one daemon (:class:`Daemon`'s
    interface: metrics summed)."""

    def __init__(self, where: Path, members: int, lease_s: float = 2.0) -> None:
        from tests.etcd_server import Etcd
        from tests.nats_server import NatsServer, partitions

        (where / "nats").mkdir(exist_ok=True)
        (where / "etcd").mkdir(exist_ok=True)
        self.partitions = partitions()
        self.server = NatsServer(where / "nats").start()
        self.etcd: Etcd | None = None
        self.members: list[Member] = []
        self.unhealthy: list[str] = []
        try:
            self.etcd = Etcd(where / "etcd").start()
            for k in range(members):
                member = Member(where, k, self.server.url, self.etcd.url, self.partitions, lease_s)
                self.members.append(member)
            deadline = time.monotonic() + 60
            while not self._settled(members):
                if not self.alive or time.monotonic() > deadline:
                    logs = "\n".join(m.err.read_text()[-1500:] for m in self.members)
                    raise RuntimeError(f"the cluster did not form: {logs}")
                time.sleep(0.1)
        except BaseException:
            self.close()
            raise
        quiet = time.monotonic()  # and then no worker told a new assignment for 2 s
        told = [len(m.events("partitions")) for m in self.members]
        while time.monotonic() - quiet < 2.0 and time.monotonic() < deadline:
            time.sleep(0.1)
            now = [len(m.events("partitions")) for m in self.members]
            if now != told:
                told, quiet = now, time.monotonic()
        self.assignments = [len(m.events("partitions")) for m in self.members]
        self.owned = [sorted(m.events("partitions")[-1]["owned"]) for m in self.members]
        self.generations = [m.events("partitions")[-1]["generation"] for m in self.members]

    def _settled(self, members: int) -> bool:
        owned: list[int] = []
        for m in self.members:
            last = m.events("partitions")
            if not m.healthy() or not last or len(last[-1]["members"]) != members:
                return False
            owned += last[-1]["owned"]
        return sorted(owned) == list(range(self.partitions))

    @property
    def alive(self) -> bool:
        return all(m.process.poll() is None for m in self.members)

    def metrics(self) -> dict[str, float]:
        """Every worker's /metrics samples, summed (none if one does not answer)."""
        total: Counter[str] = Counter()
        for m in self.members:
            try:
                total.update(scrape(m.metrics_port))
            except OSError:
                return {}
        return dict(total)

    def watch(self) -> None:
        """Note a worker that is not healthy now (a lease lost: fenced; a connection down)."""
        for m in self.members:
            if m.process.poll() is None and not m.healthy():
                self.unhealthy.append(f"{m.name} unhealthy at {time.strftime('%H:%M:%S')}")

    def rss_kib(self) -> int:
        return sum(rss_kib(m.process.pid) for m in self.members)

    def logs(self) -> list[Path]:
        return [m.err for m in self.members]

    def stop(self) -> int:
        """SIGTERM to every worker; the worst exit status."""
        for m in self.members:
            if m.process.poll() is None:
                m.process.send_signal(signal.SIGTERM)
        return max(m.process.wait(60) for m in self.members)

    def close(self) -> None:
        for m in self.members:
            if m.process.poll() is None:
                m.process.kill()
                m.process.wait()
        if self.etcd is not None:
            self.etcd.stop()
        self.server.stop()


def counted(m: dict[str, float]) -> int:
    """The incoming messages the daemon counted: taken in, refused, or dropped before being looked at."""
    total = sum(
        v for k, v in m.items() if k.startswith(("mocapd_messages_in_total{", "mocapd_rejects_total{"))
    )
    total += sum(m.get(f'mocapd_drops_total{{reason="{r}"}}', 0.0) for r in INTAKE_DROPS)
    return round(total)


def detection_keys(items: list[dict[str, Any]]) -> list[tuple[Any, ...]]:
    """What must agree between a detection on the wire and ``mocapd detect``'s: all but the id."""
    return [tuple(d[k] for k in DETECTION_KEY) for d in items]


def good_detections(cluster: bool = False) -> list[tuple[Any, ...]]:
    """``mocapd detect``'s detections of the good clip (the shipped library), as :func:`detection_keys`;
    ``cluster``: of the frames from the first whose number is a multiple of the decimation step on,
    where a cluster worker begins a stream's motion (``docs/cluster.md``, rule 2)."""
    motion = read_recording(DATA / GOOD_CLIP[0], DATA / GOOD_CLIP[1])
    library = load_library(default_library_path())
    if cluster:
        step = FrameClock.of(RATE, library.rate).step
        k = int(np.flatnonzero(motion.frames % step == 0)[0])
        motion = Motion(motion.source, motion.skeleton, motion.header, motion.frames[k:], motion.channels[k:])
    return detection_keys([d.as_json() for d in detect(motion, library, RATE)])


# ------------------------------------------------------------------------------------- the run


@dataclass
class Result:
    """What one transport's run gave; :attr:`failures` is empty when every check held."""

    transport: str
    messages: int
    seed: int
    speed: str
    fuzz_routed: int = 0
    fuzz_unrouted: int = 0
    good: int = 0
    kinds: Counter[str] = field(default_factory=Counter)
    counted: int = 0
    series: dict[str, float] = field(default_factory=dict)
    send_s: float = 0.0
    wall_s: float = 0.0
    rss_start_kib: int = 0
    rss_end_kib: int = 0
    exit_code: int | None = None
    crashed: bool = False
    log_lines: int = 0
    workers: int = 0
    restarts: int = 0
    detections: int = 0
    expected_detections: int = 0
    broker_dropped: int | None = None
    members: int = 0
    rebalances: int = 0
    fuzz_stored: int = 0
    fuzz_inbox: int = 0
    headed: int = 0
    refused: int = 0
    refused_predicted: int = 0
    stored: int | None = None
    failures: list[str] = field(default_factory=list)

    @property
    def expected(self) -> int:
        return self.fuzz_routed + self.good

    @property
    def rate(self) -> float:
        return self.messages / self.send_s if self.send_s else 0.0


def auto_speed(transport: str, messages: int, clip_s: float) -> float:
    """A replay speed that makes the good clip last about 80 % of the fuzzing."""
    fuzz_s = messages / ESTIMATED_RATE[transport]
    return max(0.05, min(50.0, clip_s / (0.8 * fuzz_s)))


def run(
    transport: str,
    messages: int,
    seed: int,
    speed: str = "auto",
    where: Path | None = None,
    expected_detections: list[tuple[Any, ...]] | None = None,
    say: Callable[[str], None] = lambda line: None,
    members: int = 2,
    lease_s: float = 2.0,
) -> Result:
    """One transport's fuzz run (see the module docstring); the working files in ``where`` (default:
    a temporary directory, removed). ``expected_detections``: ``mocapd detect``'s on the clip, as
    :func:`detection_keys` (computed if not given; over NATS on the frames a cluster worker
    recognises). ``members`` and ``lease_s``: the cluster's workers and their leases (NATS)."""
    asf, amc = DATA / GOOD_CLIP[0], DATA / GOOD_CLIP[1]
    nats = transport == "nats"
    want = good_detections(nats) if expected_detections is None else expected_detections
    clip_s = len(read_recording(asf, amc)) / RATE
    pace = speed if speed != "auto" else f"{auto_speed(transport, messages, clip_s):.3g}"
    result = Result(transport, messages, seed, pace, expected_detections=len(want))
    work = Path(tempfile.mkdtemp(prefix=f"fuzz-{transport}-")) if where is None else where
    broker: subprocess.Popen[bytes] | None = None
    daemon: Daemon | Cluster | None = None
    wire: ZmqWire | MqttWire | NatsWire | None = None
    replay: subprocess.Popen[str] | None = None
    started = time.monotonic()
    try:
        fuzzer = Fuzzer(seed, mqtt=transport == "mqtt", nats=nats)
        if nats:
            daemon = Cluster(work, members, lease_s)
            result.members = members
            wire = NatsWire(daemon.server.port, daemon.server.mqtt_port, daemon.partitions)
            fuzzer.partitions = daemon.partitions
            fuzzer.inboxes = wire.inboxes()
        else:
            broker_port = None
            if transport == "mqtt":
                broker, broker_port = start_broker(work)
            daemon = Daemon(work, transport, broker_port)
            if transport == "zmq":
                wire = ZmqWire(daemon.poses, lambda: daemon is not None and daemon.alive)
            else:
                wire = MqttWire(broker_port or 0, f"mqtt://127.0.0.1:{broker_port}")
        result.rss_start_kib = daemon.rss_kib()
        command = [str(MOCAPD), "replay", "--asf", str(asf), "--amc", str(amc), "--to", wire.good_url]
        command += ["--stream", GOOD_STREAM, "--speed", pace]
        replay = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        # the good stream is in the daemon's table before anything could fill it
        deadline = time.monotonic() + 30
        while daemon.metrics().get("mocapd_streams", 0) < 1:
            wire.pump()
            if time.monotonic() > deadline or not daemon.alive:
                raise RuntimeError("the good stream did not reach the daemon")
            time.sleep(0.01)
        say(f"{transport}: sending {messages:,} fuzzed messages (the good replay at speed {pace})")
        try:
            _fuzz(fuzzer, wire, daemon, result, say)
            while replay.poll() is None:  # the rest of the good stream
                wire.pump()
                time.sleep(0.002)
            for _ in range(50):
                wire.pump()
                time.sleep(0.01)
        except DaemonDied:
            replay.kill()  # _settle says the daemon died
        _, err = replay.communicate()
        if replay.returncode != 0:
            result.failures.append(f"the good replay failed ({replay.returncode}): {err[-500:]}")
        _settle(wire, daemon, result)
        result.wall_s = time.monotonic() - started
        printed = wire.detections if isinstance(wire, NatsWire) else _printed(work / "daemon.out")
        _check(result, daemon, printed, want)
    finally:
        if replay is not None and replay.poll() is None:
            replay.kill()
            replay.wait()
        if wire is not None:
            wire.close()
        if daemon is not None:
            daemon.close()
        if broker is not None:
            broker.terminate()
            broker.wait(10)
        if where is None:
            shutil.rmtree(work, ignore_errors=True)
    return result


def _fuzz(
    fuzzer: Fuzzer,
    wire: ZmqWire | MqttWire | NatsWire,
    daemon: Daemon | Cluster,
    result: Result,
    say: Callable[[str], None],
) -> None:
    """Send the fuzzed messages, passing the good stream's on between them, at most :data:`AHEAD`
    ahead of what the daemon counted."""
    start = checked = time.monotonic()
    progress = 100_000
    try:
        for i, message in enumerate(fuzzer.messages(result.messages)):
            wire.send(message)
            if not routed(message, result.transport):
                result.fuzz_unrouted += 1
            elif message.kind == "inbox":
                result.fuzz_inbox += 1
            else:
                result.fuzz_stored += result.transport == "nats" and not message.stray
                result.fuzz_routed += 1
            if i % 16 == 0:
                wire.pump()
            if i % 1000 == 0 and time.monotonic() - checked > 0.5:
                checked = time.monotonic()
                daemon.watch()
                ahead = result.fuzz_routed + result.fuzz_inbox + wire.good
                while ahead - counted(daemon.metrics()) > AHEAD and daemon.alive:
                    wire.pump()
                    time.sleep(0.005)
                if not daemon.alive:
                    break
            if i + 1 == progress:
                say(f"  {progress:,} sent in {time.monotonic() - start:.0f} s")
                progress += 100_000
    finally:  # also when the daemon died (DaemonDied)
        result.send_s = time.monotonic() - start
        result.kinds = fuzzer.kinds
        result.headed = fuzzer.headed
        result.refused_predicted = fuzzer.refused
    result.fuzz_routed += result.fuzz_inbox


def _settle(wire: ZmqWire | MqttWire | NatsWire, daemon: Daemon | Cluster, result: Result) -> None:
    """Wait for every message to be counted and every pose recognised (over NATS also for every
    stream to be flushed as idle: a cluster worker flushes nothing when it stops); read the counts,
    stop the daemon."""
    if isinstance(wire, NatsWire):
        wire.sync()
    expected = result.fuzz_routed + wire.good
    deadline = time.monotonic() + 120
    while daemon.alive and time.monotonic() < deadline:
        m = daemon.metrics()
        if counted(m) >= expected and m.get("mocapd_queued_poses", 1) == 0:
            break
        time.sleep(0.1)
    if isinstance(wire, NatsWire):
        deadline = time.monotonic() + 60
        while daemon.alive and time.monotonic() < deadline and daemon.metrics().get("mocapd_streams", 1):
            time.sleep(0.2)  # idle_s 10
        deadline = time.monotonic() + 10  # the flushed streams' detections: stored, then published
        while len(wire.detections) < result.expected_detections and time.monotonic() < deadline:
            time.sleep(0.1)
        daemon.watch()
        result.stored = wire.stored()
        result.refused = wire.refused
    time.sleep(1.2 if isinstance(wire, MqttWire) else 0.3)  # the broker's $SYS count: every second
    m = daemon.metrics()
    result.good = wire.good
    kinds = ("mocapd_messages_in_total{", "mocapd_rejects_total{", "mocapd_drops_total{", "mocapd_cluster_")
    result.series = {k: v for k, v in m.items() if k.startswith(kinds)}
    result.counted = counted(m)
    result.workers = round(m.get("mocapd_workers", 1)) if isinstance(daemon, Daemon) else len(daemon.members)
    result.restarts = round(sum(v for k, v in m.items() if k.startswith("mocapd_worker_restarts_total")))
    if result.restarts:
        result.failures.append(f"workers were started again {result.restarts} times")
    result.rss_end_kib = daemon.rss_kib() if daemon.alive else 0
    if isinstance(wire, MqttWire):
        result.broker_dropped = wire.dropped
    if wire.problem is not None:
        result.failures.append(wire.problem)
    if not daemon.alive:
        result.crashed = True
        result.failures.append(
            "the daemon died (a worker of the cluster)" if result.members else "the daemon died"
        )
    result.exit_code = daemon.stop()
    if result.exit_code != 0 and not result.crashed:
        result.crashed = True
        result.failures.append(f"the daemon exited {result.exit_code} on SIGTERM")


def _printed(out: Path) -> list[dict[str, Any]]:
    """The detections a daemon printed on stdout (JSON lines)."""
    return [json.loads(line) for line in out.read_text(encoding="utf-8").splitlines() if line.strip()]


def _strict(constant: str) -> Any:
    raise ValueError(f"{constant} is not JSON")


def _check(
    result: Result, daemon: Daemon | Cluster, printed: list[dict[str, Any]], want: list[tuple[Any, ...]]
) -> None:
    """The accounting, the logs and the good stream's detections (the crash checks are made as the
    run goes)."""
    if result.counted != result.expected:
        result.failures.append(
            f"counted {result.counted:,} messages, {result.expected:,} reached the daemon "
            f"({result.fuzz_routed:,} fuzzed + {result.good:,} good)"
        )
    internal = result.series.get('mocapd_rejects_total{reason="internal"}', 0.0)
    if internal:
        result.failures.append(f'{internal:,.0f} messages set off a defect (rejects{{reason="internal"}})')
    if result.broker_dropped is None and result.transport == "mqtt":
        result.failures.append("the broker's count of dropped messages never came")
    elif result.broker_dropped:
        result.failures.append(f"the broker dropped {result.broker_dropped} messages")
    if isinstance(daemon, Cluster):
        _check_cluster(result, daemon)
    bad = []
    result.log_lines = 0
    for log in daemon.logs():
        text = log.read_text(encoding="utf-8", errors="replace")
        lines = text.splitlines()
        result.log_lines += len(lines)
        for line in lines:
            try:
                entry = json.loads(line, parse_constant=_strict)
            except ValueError:
                bad.append(line)
                continue
            if (
                not isinstance(entry, dict)
                or entry.get("level") in ("error", "critical")
                or "error" in entry
                or "Warning: " in str(entry.get("event"))  # a Python warning, routed through the log
            ):
                bad.append(line)
        if "Traceback" in text or "internal error" in text:
            bad.append("a traceback or an internal error")
    if bad:
        result.failures.append(f"{len(bad)} bad log lines, the first: {bad[0][:300]}")
    good = [b for b in printed if b.get("type") == "detection" and b.get("stream") == GOOD_STREAM]
    got = detection_keys(good)
    result.detections = len(got)
    if got != want:
        result.failures.append(
            f"the good stream's detections differ: {len(got)} published, {len(want)} expected"
        )


def _check_cluster(result: Result, cluster: Cluster) -> None:
    """What only a cluster can get wrong: the buffers stored other than what the fuzzer predicts
    (:func:`nats_stored`, the header blocks' effects); a worker unhealthy at any look (its lease
    lost: fenced), the partitions moved after the cluster formed, a buffer gap, a delivery
    connection lost, a detection suppressed as a duplicate (fuzzed ``mocap.d.>``), a delivery whose
    handling raised."""
    if result.stored != result.fuzz_stored + result.good:
        result.failures.append(
            f"the buffers stored {result.stored:,} messages, {result.fuzz_stored + result.good:,} "
            f"expected ({result.fuzz_stored:,} fuzzed + {result.good:,} good)"
        )
    if result.refused != result.refused_predicted:
        result.failures.append(
            f"the server refused {result.refused:,} fuzzed messages, {result.refused_predicted:,} expected"
        )
    if cluster.unhealthy:
        result.failures.append(f"unhealthy {len(cluster.unhealthy)} times, first: {cluster.unhealthy[0]}")
    # an event after the cluster formed that says the same partitions again is no move (a worker
    # may tell its assignment once more as the membership's last step lands); nor is one under a
    # new balance generation (the leader evening out the streams the fuzzed names made: a promise
    # kept, docs/cluster.md "Balance"; the detections are checked whole)
    moved = [
        sum(sorted(e["owned"]) != owned and e["generation"] == generation for e in m.events("partitions")[n:])
        for m, n, owned, generation in zip(
            cluster.members, cluster.assignments, cluster.owned, cluster.generations, strict=True
        )
    ]
    if any(moved):
        result.failures.append(
            f"the partitions moved during the run with no new balance ({moved} new assignments per worker)"
        )
    result.rebalances = max(
        (e["generation"] for m in cluster.members for e in m.events("partitions")), default=0
    ) - max(cluster.generations)
    for event in ("buffer gap", "deliveries disconnected", "partition not read", "nats error"):
        seen = sum(len(m.events(event)) for m in cluster.members)
        if seen:
            result.failures.append(f"{seen} '{event}' events")
    series = result.series
    for key in ("mocapd_cluster_takeovers_total", "mocapd_cluster_duplicates_suppressed_total"):
        if series.get(key, 0.0):
            result.failures.append(f"{key} is {series[key]:,.0f}")
    failures = series.get('mocapd_drops_total{reason="nats_internal"}', 0.0)
    if failures:
        result.failures.append(f"{failures:,.0f} deliveries whose handling raised (nats_internal)")


# ------------------------------------------------------------------------------------ reporting


def report(r: Result) -> str:
    """The table of one transport's run."""
    out = [
        f"\n== {r.transport}: {r.messages:,} fuzzed messages (seed {r.seed}), "
        f"good stream: mocapd replay of CMU 13_30 at speed {r.speed}",
        "kinds sent: " + ", ".join(f"{k} {n:,}" for k, n in sorted(r.kinds.items())),
        f"reached the daemon: {r.fuzz_routed:,} fuzzed + {r.good:,} good = {r.expected:,}; "
        f"not routed to it (no subscription matches the topic): {r.fuzz_unrouted:,}",
    ]
    if r.transport == "nats":
        out += [
            f"cluster: {r.members} workers (mocapd run --cluster); {r.headed:,} fuzzed messages with a "
            f"header block; stored in the partitions' buffers: {r.stored if r.stored is not None else '?':,} "
            f"({r.fuzz_stored:,} fuzzed + {r.good:,} good expected); published on the workers' delivery "
            f"subjects: {r.fuzz_inbox:,} (and {r.kinds.get('inbox', 0) - r.fuzz_inbox - r.refused:,} forged "
            f"flow control, not counted; {r.refused:,} with a forged acknowledgement subject, refused by "
            f"the server); not stored (the subject or a header): {r.fuzz_unrouted - r.refused:,}; "
            f"the leader's new balances after the cluster formed: {r.rebalances}",
        ]
    out += [
        f"{'counted under':<52s} {'messages':>10s}",
    ]
    for key in sorted(r.series):
        name = key.removeprefix("mocapd_").replace("_total{", "{")
        intake = key.startswith(("mocapd_messages_in", "mocapd_rejects")) or any(
            f'"{d}"' in key for d in INTAKE_DROPS
        )
        note = "" if intake else "  (not an intake outcome)"
        out.append(f"  {name:<50s} {r.series[key]:>10,.0f}{note}")
    out.append(f"  {'total (taken in + refused + dropped at intake)':<50s} {r.counted:>10,}")
    if r.broker_dropped is not None:
        out.append(f"broker: {r.broker_dropped} messages dropped ($SYS/broker/publish/messages/dropped)")
    out += [
        f"sending: {r.rate:,.0f} fuzzed messages/s ({r.send_s:.1f} s); wall time {r.wall_s:.1f} s",
        f"daemon RSS: {r.rss_start_kib / 1024:.1f} MiB at the start, "
        f"{r.rss_end_kib / 1024:.1f} MiB at the end",
        f"daemon log: {r.log_lines:,} lines, each one JSON object; exit status {r.exit_code} on SIGTERM",
        f"workers: {r.workers}, started again {r.restarts} times",
        f"good stream: {r.detections} detections, mocapd detect: {r.expected_detections}",
        "checks: " + ("all hold" if not r.failures else "FAILED: " + "; ".join(r.failures)),
    ]
    return "\n".join(out)


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--messages", type=int, default=1_000_000)
    parser.add_argument(
        "--transport",
        choices=("zmq", "mqtt", "nats", "both", "all"),
        default="all",
        help="both: ZeroMQ and MQTT; all: and NATS (cluster mode)",
    )
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument(
        "--speed",
        default="auto",
        help="the good replay's speed (auto: it lasts about as long as the fuzzing)",
    )
    parser.add_argument("--members", type=int, default=2, help="cluster workers (NATS)")
    args = parser.parse_args()
    print(describe(), flush=True)
    transports = {"both": ("zmq", "mqtt"), "all": ("zmq", "mqtt", "nats")}.get(
        args.transport, (args.transport,)
    )
    results = []
    started = time.monotonic()
    for t in transports:
        r = run(
            t,
            args.messages,
            args.seed,
            args.speed,
            expected_detections=good_detections(cluster=t == "nats"),
            say=lambda s: print(s, flush=True),
            members=args.members,
        )
        print(report(r), flush=True)
        results.append(r)
    print("\n== summary")
    head = (
        "transport",
        "fuzzed",
        "reached",
        "counted",
        "msg/s",
        "wall s",
        "RSS MiB",
        "crashes",
        "restarts",
        "good",
    )
    widths = (9, 10, 10, 10, 7, 7, 11, 7, 8, 6)
    print(
        f"{head[0]:<9s} "
        + " ".join(f"{h:>{w}s}" for h, w in zip(head[1:], widths[1:], strict=True))
        + "  checks"
    )
    for r in results:
        row = (
            r.transport,
            f"{r.messages:,}",
            f"{r.expected:,}",
            f"{r.counted:,}",
            f"{r.rate:,.0f}",
            f"{r.wall_s:.1f}",
            f"{r.rss_start_kib / 1024:.0f} -> {r.rss_end_kib / 1024:.0f}",
            str(int(r.crashed)),
            str(r.restarts),
            f"{r.detections}/{r.expected_detections}",
        )
        ok = "all hold" if not r.failures else "FAILED"
        cells = " ".join(f"{v:>{w}s}" for v, w in zip(row[1:], widths[1:], strict=True))
        print(f"{row[0]:<9s} {cells}  {ok}")
    print(f"total wall time {time.monotonic() - started:.1f} s")
    sys.exit(1 if any(r.failures for r in results) else 0)


if __name__ == "__main__":
    main()
