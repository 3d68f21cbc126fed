"""The daemon on a real broker: how many concurrent 120 Hz streams one ``mocapd run`` process holds
with no drops, and the end-to-end latency from a pose leaving its source (its timestamp; the broker
is on loopback) to the detection it completed arriving at a subscriber.

    python -m bench.bench_service [--sizes 1,10,50,100,150,200] [--seconds 15] [--workers 1,2]
                                  [--transport mqtt|zmq] [--subjects-per-message K]

A mosquitto broker on a free loopback port; the daemon (``mocapd run --mqtt``) pinned to core 0;
one load process on the other core publishes S streams at 120 Hz each (from a plain socket, MQTT
QoS 0 or ZMTP 3.0, each tick's poses in one write, paced by the clock; each pose from bytes packed
beforehand, stamped as it is joined),
every stream a real recording looped from a different start (CMU and HDM05 of
``../shared/data/mocap``, channels on the wire; stream 0 the exercises of CMU 13_30), and subscribes
to the detections (QoS 1). Each size
runs ``--seconds`` after a 2 s warm-up; a size holds when the daemon dropped nothing (no lagging
pose, no full queue), saw no gap, was at most 0.5 s behind at the end, and its latency's p99 was at
most ``--p99-ms`` (20). Latency: p50 and p99 of
(detection received) - (``source_time``, the completing pose's timestamp), in ms. CPU: the
daemon's (front and workers) and the load's, in µs per pose sent. Baseline in the
same run: one stream, the floor the broker and the wire add.

``--subjects-per-message K`` (K > 1) sends each tick's poses in frame messages of K subjects
(``protocols/README.md``, ``frame``) instead of a message per pose. Each row also prints the
recogniser bank's own CPU per pose for that many streams, measured in this process on the daemon's
core before the daemon starts (:func:`bank_us`), a tick every 1/120 s as the daemon runs it, the
daemon's as a ratio of it, and the bank's back to back ("b2b", as ``bench_recognizer`` measures
it), which a live daemon cannot reach.

``--workers 1,2`` sweeps a daemon of each worker count in turn (``mocapd run --workers N``; N on the
first N cores, the load then on the last core, shared with a worker) and prints each count's largest
size held as a ratio of the first's (a count named more than once, e.g. ``1,2,1,2``, is swept each
time and its median taken): the issue's aim on 2 cores is 1.7x or more. A sweep stops after two
sizes in a row that do not hold.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import shutil
import socket
import statistics
import struct
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable
from pathlib import Path

import msgpack
import numpy as np
import numpy.typing as npt
import paho.mqtt.client as paho
import zmq
from paho.mqtt.enums import CallbackAPIVersion

from bench.common import DATA, shipped_library
from bench.machine import describe
from bench.processes import cpu_seconds, free_port, rss_kib, scrape, wait_healthy, wait_port
from daemon.bank import RecognizerBank
from daemon.recordings import read_recording
from protocols.messages import VERSION, SkeletonMessage, encode
from replay import parse_asf
from replay.catalog import CMU_SUBSTITUTES, recordings

RATE = 120.0
P99_MS = 20.0
"""The issue's bound on the end-to-end p99 of a size that holds."""


def lost(m: dict[str, float]) -> float:
    """Poses the daemon dropped or never saw (gaps), by its own counters."""
    keys = [k for k in m if k.startswith("mocapd_drops_total")]
    return sum(m[k] for k in keys) + m.get('mocapd_stream_events_total{event="gap_frames"}', 0.0)


def nodelay(client: paho.Client) -> None:
    """No Nagle delay on the client's small packets (paho leaves it on)."""
    sock = client.socket()
    if isinstance(sock, socket.socket):
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)


def _varint(n: int) -> bytes:
    out = bytearray()
    while True:
        n, b = divmod(n, 128)
        out.append(b | (0x80 if n else 0))
        if not n:
            return bytes(out)


def _utf8(text: str) -> bytes:
    b = text.encode()
    return len(b).to_bytes(2, "big") + b


class RawPublisher:
    """An MQTT 3.1.1 publisher on a plain socket: QoS 0 PUBLISH packets, a tick's packets in one
    ``sendall``. A Python client library would queue them through threads and add latency of its
    own to what is measured."""

    def __init__(self, port: int, client_id: str) -> None:
        self.sock = socket.create_connection(("127.0.0.1", port))
        self.sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        body = _utf8("MQTT") + bytes([4, 0x02]) + (60).to_bytes(2, "big") + _utf8(client_id)
        self.sock.sendall(b"\x10" + _varint(len(body)) + body)
        if self.sock.recv(4)[:1] != b"\x20":
            raise SystemExit("the broker refused the load's connection")

    @staticmethod
    def packet(topic: str, payload: bytes, retain: bool = False) -> bytes:
        body = _utf8(topic) + payload
        return bytes([0x31 if retain else 0x30]) + _varint(len(body)) + body

    def send(self, packets: list[bytes]) -> None:
        self.sock.sendall(b"".join(packets))


ZMTP_GREETING = b"\xff" + bytes(8) + b"\x7f" + bytes([3, 0]) + b"NULL".ljust(20, b"\x00") + bytes(32)
"""A ZMTP 3.0 greeting (RFC 23): signature, version 3.0, the NULL mechanism, not a server."""
ZMTP_READY = b"\x04\x19\x05READY\x0bSocket-Type" + (3).to_bytes(4, "big") + b"PUB"
"""The NULL handshake's READY command of a PUB peer."""


def zmtp_frame(body: bytes, more: bool) -> bytes:
    """One ZMTP 3.0 message frame (short below 256 bytes, else long)."""
    if len(body) < 256:
        return bytes([1 if more else 0, len(body)]) + body
    return bytes([3 if more else 2]) + len(body).to_bytes(8, "big") + body


class ZmqLoad:
    """The same load over ZeroMQ: a ZMTP 3.0 PUB peer on a plain TCP socket connected to the daemon's
    poses socket (RFC 23: the greeting, the NULL handshake, then each tick's ``[topic, payload]``
    messages in one ``sendall``; what the daemon's SUB socket sends, its subscription, read and
    dropped), and a pyzmq SUB socket on its detections. On 2 cores the load shares a core with a
    worker of ``--workers 2``: publishers on other machines cost this one nothing, and libzmq's two
    sends a message and its I/O thread cost a worker about 5 µs a pose of its core (a worker's
    p99 a third above the other's)."""

    def __init__(self, poses: str, detections: str, on_detection: Callable[[bytes], None]) -> None:
        host, port = poses.removeprefix("tcp://").rsplit(":", 1)
        self.pub = socket.create_connection((host, int(port)))
        self.pub.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        self.pub.sendall(ZMTP_GREETING + ZMTP_READY)
        self.pub.settimeout(10.0)
        peer = b""
        while len(peer) < 64:  # the daemon's greeting; its READY and subscription follow
            chunk = self.pub.recv(64 - len(peer))
            if not chunk:
                raise SystemExit("the daemon closed the load's connection")
            peer += chunk
        if peer[:1] != b"\xff" or peer[10] < 3:
            raise SystemExit("the daemon's poses socket did not answer in ZMTP 3")
        self.pub.settimeout(None)
        threading.Thread(target=self._discard, daemon=True).start()
        self.ctx = zmq.Context()
        self.sub = self.ctx.socket(zmq.SUB)
        self.sub.setsockopt(zmq.LINGER, 0)
        self.sub.setsockopt(zmq.SUBSCRIBE, b"mocap/")
        self.sub.connect(detections)
        self.on_detection = on_detection
        self._topics: dict[str, bytes] = {}
        self._heads: dict[int, bytes] = {}
        threading.Thread(target=self._collect, daemon=True).start()
        time.sleep(0.3)

    def _discard(self) -> None:
        with contextlib.suppress(OSError):
            while self.pub.recv(65536):
                pass

    def _collect(self) -> None:
        while True:
            try:
                _, payload = self.sub.recv_multipart()
            except zmq.ContextTerminated:
                self.sub.close()
                return
            self.on_detection(payload)

    def close(self) -> None:
        self.pub.close()
        self.ctx.term()  # the collecting thread closes its socket when told

    def send(self, messages: list[tuple[str, bytes]]) -> None:
        out: list[bytes] = []
        topics, heads = self._topics, self._heads
        for topic, payload in messages:
            framed = topics.get(topic)
            if framed is None:
                framed = topics[topic] = zmtp_frame(topic.encode(), True)
            head = heads.get(len(payload))
            if head is None:
                head = heads[len(payload)] = zmtp_frame(payload, False)[: -len(payload) or None]
            out += (framed, head, payload)
        self.pub.sendall(b"".join(out))


class MqttLoad:
    """The load over MQTT: :class:`RawPublisher` out, a paho subscriber (QoS 1) on the detections."""

    def __init__(self, port: int, on_detection: Callable[[bytes], None]) -> None:
        self.pub = RawPublisher(port, f"bench-load-{os.getpid()}")
        self.sub = paho.Client(CallbackAPIVersion.VERSION2, client_id=f"bench-sub-{os.getpid()}")
        self.sub.on_message = lambda client, userdata, message: on_detection(bytes(message.payload))
        self.sub.connect("127.0.0.1", port)
        nodelay(self.sub)
        self.sub.subscribe("mocap/+/detections", qos=1)
        self.sub.loop_start()

    def send(self, messages: list[tuple[str, bytes]]) -> None:
        self.pub.send([RawPublisher.packet(topic, payload) for topic, payload in messages])

    def close(self) -> None:
        self.sub.loop_stop()
        self.sub.disconnect()
        self.pub.sock.close()


SEQ_TIME = struct.Struct(">Q6sd")
"""A pose's sequence number (msgpack uint64), the key "time" and the time (float64): fixed widths,
so that a pose is one join of bytes packed beforehand."""
TIME_KEY = msgpack.packb("time") + b"\xcb"


def pose_head(stream: str) -> bytes:
    """A pose map of protocols/README.md up to its sequence number's value."""
    head = [b"\x86"]
    for key, value in (("v", VERSION), ("type", "pose"), ("stream", stream), ("seq", None)):
        head.append(msgpack.packb(key))
        if value is not None:
            head.append(msgpack.packb(value))
    return b"".join(head) + b"\xcf"


class Load:
    """S streams published at 120 Hz from this process through ``wire`` (ZmqLoad or MqttLoad),
    detections collected with their latency."""

    def __init__(self, sources: list[tuple[bytes, list[bytes]]]) -> None:
        self.sources = sources
        self.latencies: list[float] = []
        self.lock = threading.Lock()
        self.seq: dict[str, int] = {}
        self.wire: ZmqLoad | MqttLoad | None = None
        self._tails: dict[int, list[bytes]] = {}
        self._rows: dict[int, npt.NDArray[np.float64]] = {}

    def on_detection(self, payload: bytes) -> None:
        now = time.time()
        body = msgpack.unpackb(payload, raw=False)
        if body.get("type") == "detection" and body.get("source_time", 0) > 0:
            with self.lock:
                self.latencies.append(now - body["source_time"])

    def run(self, streams: int, seconds: float, prefix: str, per_message: int = 1) -> int:
        """Publish ``streams`` streams for ``seconds``; the poses sent. ``per_message`` > 1: each
        tick's poses in frame messages of that many subjects (``mocap/<prefix>g<k>/frame``)."""
        assert self.wire is not None
        if per_message > 1:
            return self.run_frames(streams, seconds, prefix, per_message)
        rng = np.random.default_rng(streams)
        picks = [self.sources[k % len(self.sources)] for k in range(streams)]
        names = [f"{prefix}{k}" for k in range(streams)]
        topics = [f"mocap/{name}/pose" for name in names]
        at = [int(rng.integers(len(frames))) for _, frames in picks]
        for name, (asf, _) in zip(names, picks, strict=True):
            if name not in self.seq:
                message = SkeletonMessage(name, RATE, asf=asf.decode(), angle_unit="rad")
                self.wire.send([(f"mocap/{name}/skeleton", encode(message))])
                self.seq[name] = 0
        time.sleep(0.5)
        start = time.monotonic()
        ticks = int(seconds * RATE)
        sent = 0
        tails = [self.tails(k) for k in range(len(self.sources))]
        heads = [pose_head(name) for name in names]
        mids = [tails[self.sources.index(pick)] for pick in picks]
        stamp, now = SEQ_TIME.pack, time.time
        for tick in range(ticks):
            wait = start + tick / RATE - time.monotonic()
            if wait > 0:
                time.sleep(wait)
            messages = []
            for k, name in enumerate(names):
                rows = mids[k]
                self.seq[name] += 1
                # each pose stamped as it is packed (the load's own time is not the daemon's
                # latency) from bytes packed beforehand: it costs little of the core it shares
                body = heads[k] + stamp(self.seq[name], TIME_KEY, now()) + rows[(at[k] + tick) % len(rows)]
                messages.append((topics[k], body))
            self.wire.send(messages)
            sent += len(messages)
        return sent

    def run_frames(self, streams: int, seconds: float, prefix: str, per_message: int) -> int:
        """:meth:`run` with each tick's poses in frame messages of ``per_message`` subjects, each
        message's fields but its channels and times packed beforehand."""
        assert self.wire is not None
        rng = np.random.default_rng(streams)
        picks = [k % len(self.sources) for k in range(streams)]
        names = [f"{prefix}{k}" for k in range(streams)]
        at = [int(rng.integers(len(self.sources[p][1]))) for p in picks]
        for name, p in zip(names, picks, strict=True):
            if name not in self.seq:
                message = SkeletonMessage(name, RATE, asf=self.sources[p][0].decode(), angle_unit="rad")
                self.wire.send([(f"mocap/{name}/skeleton", encode(message))])
                self.seq[name] = 0
        time.sleep(0.5)
        rows = [self.rows(p) for p in range(len(self.sources))]
        groups = [list(range(g, min(g + per_message, streams))) for g in range(0, streams, per_message)]
        packed = []
        for g, members in enumerate(groups):
            counts = np.array([rows[picks[k]].shape[1] for k in members], dtype="<u4").tobytes()
            packed.append((f"mocap/{prefix}g{g}/frame", f"{prefix}g{g}", [names[k] for k in members], counts))
        start = time.monotonic()
        sent = 0
        for tick in range(int(seconds * RATE)):
            wait = start + tick / RATE - time.monotonic()
            if wait > 0:
                time.sleep(wait)
            messages = []
            for (topic, source, members_names, counts), members in zip(packed, groups, strict=True):
                seqs = np.array([self.seq[n] + 1 for n in members_names], dtype="<u8")
                for n in members_names:
                    self.seq[n] += 1
                values = np.concatenate(
                    [rows[picks[k]][(at[k] + tick) % len(rows[picks[k]])] for k in members]
                )
                body = {
                    "v": VERSION,
                    "type": "frame",
                    "source": source,
                    "streams": members_names,
                    "seq": seqs.tobytes(),
                    "time": np.full(len(members), time.time(), dtype="<f8").tobytes(),
                    "counts": counts,
                    "channels": values.tobytes(),
                }
                messages.append((topic, msgpack.packb(body)))
            self.wire.send(messages)
            sent += streams
        return sent

    def rows(self, k: int) -> npt.NDArray[np.float64]:
        """Source ``k``'s channels, frame by frame ``(N, C)``."""
        if k not in self._rows:
            self._rows[k] = np.array([np.frombuffer(r, dtype="<f8") for r in self.sources[k][1]])
        return self._rows[k]

    def tails(self, k: int) -> list[bytes]:
        """What follows the time in a pose of source ``k``, frame by frame (packed once)."""
        if k not in self._tails:
            self._tails[k] = [msgpack.packb("channels") + msgpack.packb(row) for row in self.sources[k][1]]
        return self._tails[k]

    def close(self) -> None:
        if self.wire is not None:
            self.wire.close()

    def take_latencies(self) -> list[float]:
        with self.lock:
            out, self.latencies = self.latencies, []
        return out


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--sizes", default="1,10,50,100,150,200")
    parser.add_argument("--seconds", type=float, default=15.0)
    parser.add_argument("--transport", choices=("mqtt", "zmq"), default="mqtt")
    parser.add_argument("--data", type=Path, default=DATA)
    parser.add_argument(
        "--workers",
        default="1",
        help="comma-separated worker counts (mocapd run --workers N), each swept in turn, e.g. 1,2",
    )
    parser.add_argument("--p99-ms", type=float, default=P99_MS, help="a size holds only at this p99 or less")
    parser.add_argument(
        "--subjects-per-message",
        type=int,
        default=1,
        metavar="K",
        help="K > 1: each tick's poses in frame messages of K subjects (protocols/README.md, frame)",
    )
    args = parser.parse_args()
    sizes = [int(x) for x in args.sizes.split(",")]
    counts = [int(x) for x in args.workers.split(",")]
    print(describe())
    pairs = recordings(args.data, CMU_SUBSTITUTES)
    # stream 0 (the one-stream baseline) an exercise trial, so that it has detections to time
    first = [p for p in pairs if Path(p[1]).name.startswith("13_30.")]
    chosen = first + [p for p in pairs[:: max(1, len(pairs) // 12)] if p not in first][:11]
    sources = []
    for asf, amc in chosen:
        m = read_recording(asf, amc)
        sources.append((Path(asf).read_bytes(), [np.ascontiguousarray(row).tobytes() for row in m.channels]))
    cores = sorted(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else [0]
    held: dict[int, list[int]] = {}
    for n in counts:  # a count named twice is swept twice (interleaved: 1,2,1,2), its median taken
        held.setdefault(n, []).append(sweep(args, sizes, sources, n, cores))
    if len(held) > 1:
        one, *others = held
        base = statistics.median(held[one])
        for n in others:
            ratio = statistics.median(held[n]) / base if base else float("nan")
            print(f"--workers {n}: {held[n]} streams held, {ratio:.2f}x --workers {one} ({held[one]})")
    print(json.dumps({"held": held}))


def bank_us(
    sources: list[tuple[bytes, list[bytes]]], streams: int, cores: list[int], paced: bool, ticks: int = 240
) -> float:
    """The recogniser bank's CPU per pose (µs) in this process on the daemon's first core, for
    ``streams`` streams of ``sources`` as the load sends them (stream k plays source k mod R), after
    80 ticks of warm-up, the best of three thirds of ``ticks``; ``paced``: a tick every 1/120 s, as
    a daemon runs it (its caches cold again after each wait: 1.4-1.6x the cost back to back here),
    else back to back. The baseline the daemon's cost per pose is a ratio of."""
    library = shipped_library()
    bank = RecognizerBank(library)
    rows = [np.array([np.frombuffer(r, dtype="<f8") for r in frames]) for _, frames in sources]
    for k in range(streams):
        asf = sources[k % len(sources)][0].decode()
        bank.add(f"b{k}", RATE, skeleton=parse_asf(asf.splitlines(), "<bench>"))
    mine = os.sched_getaffinity(0) if hasattr(os, "sched_getaffinity") else None
    if mine is not None:
        os.sched_setaffinity(0, {cores[0]})
    blocks = [0.0, 0.0, 0.0]  # the best third: this VM's neighbours come and go
    start = time.monotonic()
    try:
        for tick in range(80 + ticks):
            frames = [
                (f"b{k}", tick + 1, rows[k % len(rows)][tick % len(rows[k % len(rows)])])
                for k in range(streams)
            ]
            if paced and (wait := start + tick / RATE - time.monotonic()) > 0:
                time.sleep(wait)
            started = time.process_time()
            bank.push(frames)
            if tick >= 80:
                blocks[3 * (tick - 80) // ticks] += time.process_time() - started
    finally:
        if mine is not None:
            os.sched_setaffinity(0, mine)
    return min(blocks) / (streams * ticks / 3) * 1e6


def sweep(
    args: argparse.Namespace,
    sizes: list[int],
    sources: list[tuple[bytes, list[bytes]]],
    workers: int,
    cores: list[int],
) -> int:
    """A daemon of ``workers`` processes on ``cores`` through ``sizes``; the largest size held."""
    work = Path(tempfile.mkdtemp(prefix="bench-service-"))
    metrics_port = free_port()
    # the streams of every size stay in the table (none evicted mid-sweep): room for all of them
    env = {
        **os.environ,
        "MOCAPD_LOGGING_LEVEL": "warning",
        "MOCAPD_SERVICE_IDLE_S": "3600",
        "MOCAPD_SERVICE_MAX_STREAMS": str(10 * sum(sizes)),
    }
    broker = None
    broker_port = free_port()
    poses, detections = f"tcp://127.0.0.1:{free_port()}", f"tcp://127.0.0.1:{free_port()}"
    if args.transport == "mqtt":
        (work / "m.conf").write_text(
            f"listener {broker_port} 127.0.0.1\nallow_anonymous true\nset_tcp_nodelay true\n"
            "max_queued_messages 1000000\n"
        )
        mosquitto = shutil.which("mosquitto") or "/usr/sbin/mosquitto"
        broker = subprocess.Popen([mosquitto, "-c", str(work / "m.conf")], stderr=subprocess.DEVNULL)
        wait_port(broker_port)
        where = ["--mqtt", f"mqtt://127.0.0.1:{broker_port}"]
    else:
        env |= {"MOCAPD_ZMQ_POSES": poses, "MOCAPD_ZMQ_DETECTIONS": detections, "MOCAPD_SERVICE_SINKS": "zmq"}
        where = []
    # one worker on the first core, N on the first N (the front shares them); the load on the last
    daemon_cores = cores[: max(1, min(workers, len(cores)))]
    # before the daemon runs: the bank paced as the daemon runs it, and back to back
    banks = {
        size: (bank_us(sources, size, daemon_cores, True), bank_us(sources, size, daemon_cores, False))
        for size in sizes
    }
    load_cores = set(cores[1:] or cores) if workers == 1 else {cores[-1]}
    mocapd = str(Path(sys.executable).parent / "mocapd")
    pin = ["taskset", "-c", ",".join(map(str, daemon_cores))]
    command = [*pin, mocapd, "run", *where, "--metrics-port", str(metrics_port), "--workers", str(workers)]
    with open(work / "daemon.err", "wb") as err:
        daemon = subprocess.Popen(command, stdout=subprocess.DEVNULL, stderr=err, env=env)
    wait_port(metrics_port, 30)
    wait_healthy(metrics_port)  # subscribed: a skeleton published before that would be lost
    if hasattr(os, "sched_setaffinity"):
        os.sched_setaffinity(0, load_cores)
    load = Load(sources)
    if args.transport == "mqtt":
        load.wire = MqttLoad(broker_port, load.on_detection)
    else:
        load.wire = ZmqLoad(poses, detections, load.on_detection)
    print(
        f"{args.transport}{' (mosquitto on loopback)' if broker else ' on loopback'}; --workers {workers}: "
        f"daemon on cores {daemon_cores}, load on {sorted(load_cores)}; {args.seconds:g} s per size"
    )
    head = (
        "streams",
        "poses/s",
        "lost",
        "behind",
        "detections",
        "p50 ms",
        "p99 ms",
        "daemon µs",
        "load µs",
        "bank µs",
        "ratio",
        "b2b µs",
    )
    widths = (8, 9, 6, 8, 11, 8, 8, 10, 8, 8, 6, 7)
    print(" ".join(f"{h:>{w}s}" for h, w in zip(head, widths, strict=True)) + "  holds")
    held, failed = 0, 0
    try:
        for size in sizes:
            before = scrape(metrics_port)
            k = args.subjects_per_message
            load.run(size, 2.0, f"w{size}-", k)  # warm-up: the recognisers made, the phases spread
            load.take_latencies()
            warm = scrape(metrics_port)
            cpu, own = cpu_seconds(daemon.pid), time.process_time()
            sent = load.run(size, args.seconds, f"w{size}-", k)
            cpu, own = cpu_seconds(daemon.pid) - cpu, time.process_time() - own
            time.sleep(0.5)
            after = scrape(metrics_port)
            received = after.get("mocapd_frames_in_total", 0) - warm.get("mocapd_frames_in_total", 0)
            behind = after.get("mocapd_queued_poses", 0)
            gone = lost(after) - lost(before) + max(0.0, sent - received)
            lat = np.array(load.take_latencies()) * 1e3
            p50, p99 = (np.percentile(lat, 50), np.percentile(lat, 99)) if lat.size else (float("nan"),) * 2
            ok = gone == 0 and behind <= 0.5 * RATE * size and (not lat.size or p99 <= args.p99_ms)
            held = max(held, size) if ok else held
            failed = 0 if ok else failed + 1
            bank, back_to_back = banks[size]
            print(
                f"{size:8d} {sent / args.seconds:9,.0f} {gone:6.0f} {behind / (RATE * size):7.2f}s "
                f"{lat.size:11d} {p50:8.1f} {p99:8.1f} {cpu / sent * 1e6:10.1f} {own / sent * 1e6:8.1f}"
                f" {bank:8.1f} {cpu / sent * 1e6 / bank:6.2f} {back_to_back:7.1f}  {'yes' if ok else 'no'}",
                flush=True,
            )
            if failed == 2:  # two sizes in a row not held: the larger ones will not be
                break
            time.sleep(1.0)
        print(
            f"largest size held with no drops and p99 <= {args.p99_ms:g} ms: {held} streams of "
            f"{RATE:g} Hz (aim: >= 100)"
        )
        print(json.dumps({"workers": workers, "front_or_daemon_rss_kib": rss_kib(daemon.pid)}))
    finally:
        load.close()
        daemon.terminate()
        daemon.wait(30)
        if broker is not None:
            broker.terminate()
            broker.wait(10)
        shutil.rmtree(work, ignore_errors=True)
        if hasattr(os, "sched_setaffinity"):
            os.sched_setaffinity(0, set(cores))
    return held


if __name__ == "__main__":
    main()
