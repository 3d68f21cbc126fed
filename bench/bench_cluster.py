"""Cluster mode on this machine (``docs/cluster.md``): how many 120 Hz streams 1, 2 and 3 workers
hold, how long takeovers take, and what that extrapolates to.

    python -m bench.bench_cluster [--workers 1,2,3] [--sizes 20,30,45,60,90] [--seconds 10]

A nats-server from ``deploy/nats/nats.conf`` and an etcd from ``deploy/etcd`` on loopback ports;
W workers (``mocapd run --cluster ... --coordinator ...``); one load process (this one) publishing
S streams of real recordings (:mod:`bench.cluster_load`'s) at 120 Hz over NATS, each tick's poses in
one write from a plain socket, and subscribing to ``mocap.*.detections``. A size holds when the
workers dropped nothing and saw no gap, were at most 0.5 s behind at the end, and the detections'
p99 end-to-end latency (received - the completing pose's source time) was at most 20 ms, as in
``bench/bench_service.py``. CPU per pose: the workers' and the nats-server's utime + stime over the
poses sent. Takeovers: with 3 workers and ``--takeover-streams`` streams, one worker killed (kill
-9), later another stopped (SIGTERM); per partition, the time to the first live pose its new owner
consumed, and the time until the survivors' recognition caught up (their queues back to at most a
pose per stream). Then the extrapolation, its assumptions stated.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import os
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import msgpack
import numpy as np

from bench.cluster_load import RATE, streams
from bench.machine import describe
from bench.processes import free_port, json_lines, scrape, wait_healthy
from protocols.messages import PoseMessage, encode
from tests.etcd_server import Etcd
from tests.nats_server import NatsServer, partitions

P99_MS = 20.0
REPO = Path(__file__).resolve().parents[1]


def cpu_s(pid: int) -> float:
    """utime + stime of a process, in seconds."""
    with open(f"/proc/{pid}/stat", encoding="utf-8") as f:
        fields = f.read().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


class Wire:
    """A NATS publisher on a plain socket (each tick's PUBs in one write) and a subscriber thread
    (nats-py) timing each detection."""

    def __init__(self, url: str) -> None:
        host, port = url.removeprefix("nats://").split(":")
        self.sock = socket.create_connection((host, int(port)))
        self.sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        self.sock.recv(4096)  # INFO
        self.sock.sendall(b'CONNECT {"verbose":false,"pedantic":false}\r\n')
        self.latencies: list[float] = []
        self.lock = threading.Lock()
        self._closing = threading.Event()
        ready = threading.Event()
        self._collector = threading.Thread(target=self._collect, args=(url, ready), daemon=True)
        self._collector.start()
        assert ready.wait(10)
        threading.Thread(target=self._drain, daemon=True).start()

    def _drain(self) -> None:
        while True:  # PINGs from the server
            data = self.sock.recv(65536)
            if not data:
                return
            if b"PING" in data:
                self.sock.sendall(b"PONG\r\n")

    def _collect(self, url: str, ready: threading.Event) -> None:
        import asyncio

        import nats

        async def main() -> None:
            nc = await nats.connect(url)

            async def got(msg: Any) -> None:
                body = msgpack.unpackb(msg.data, raw=False)
                if body.get("source_time", 0) > 0:
                    with self.lock:
                        self.latencies.append(time.time() - body["source_time"])

            await nc.subscribe("mocap.*.detections", cb=got)
            await nc.flush()
            ready.set()
            while not self._closing.is_set():
                await asyncio.sleep(0.1)
            await nc.close()

        asyncio.run(main())

    def close(self) -> None:
        """Disconnect both sides before the server stops (else the client logs its reconnects)."""
        self._closing.set()
        self._collector.join(10)
        self.sock.close()

    def send(self, messages: list[tuple[str, bytes]]) -> None:
        out = []
        for topic, payload in messages:
            out.append(f"PUB {topic.replace('/', '.')} {len(payload)}\r\n".encode() + payload + b"\r\n")
        self.sock.sendall(b"".join(out))

    def take(self) -> np.ndarray:
        with self.lock:
            out, self.latencies = self.latencies, []
        return np.array(out) * 1e3


class Load:
    """S looping streams (sequence numbers go on across runs), their skeletons every second; at
    ``rate`` Hz (the recordings' 120 Hz, or every k-th frame of them announced at 120 / k Hz)."""

    def __init__(self, wire: Wire, n: int, prefix: str, rate: float = RATE) -> None:
        self.wire = wire
        self.rate = rate
        self.items = streams(n)
        every = max(1, round(RATE / rate))
        for s in self.items:
            s.id = f"{prefix}{s.id}"
            m = s.motion
            s.motion = dataclasses.replace(m, frames=m.frames[::every], channels=m.channels[::every])
            skeleton = msgpack.unpackb(s.skeleton[1], raw=False)
            skeleton["stream"] = s.id
            skeleton["rate"] = rate
            s.skeleton = (f"mocap/{s.id}/skeleton", msgpack.packb(skeleton))

    def run(self, seconds: float, stop: threading.Event | None = None) -> int:
        self.wire.send([s.skeleton for s in self.items])
        time.sleep(0.3)
        start = announced = time.monotonic()
        sent = 0
        for tick in range(int(seconds * self.rate)):
            if stop is not None and stop.is_set():
                break
            wait = start + tick / self.rate - time.monotonic()
            if wait > 0:
                time.sleep(wait)
            now = time.time()
            batch = []
            if time.monotonic() - announced >= 1.0:
                batch += [s.skeleton for s in self.items]
                announced = time.monotonic()
            for s in self.items:
                row = s.motion.channels[s.next % len(s.motion.channels)]
                m = PoseMessage(s.id, s.next, now, channels=row, epoch=s.epoch)
                s.next += 1
                batch.append((f"mocap/{s.id}/pose", encode(m)))
            self.wire.send(batch)
            sent += len(self.items)
        return sent


class Worker:
    """``mocapd run --cluster`` as a process; ``settings``: more of its environment (``MOCAPD_...``)."""

    def __init__(
        self, where: Path, name: str, nats: str, etcd: str, settings: dict[str, str] | None = None
    ) -> None:
        self.name = name
        self.port = free_port()
        self.err = where / f"{name}.err"
        env = {
            **os.environ,
            "MOCAPD_CLUSTER_MEMBER": name,
            "MOCAPD_SERVICE_IDLE_S": "2",
            "MOCAPD_LOGGING_LEVEL": "info",
            "PYTHONPATH": str(REPO),
            **(settings or {}),
        }
        mocapd = str(Path(sys.executable).parent / "mocapd")
        with self.err.open("ab") as err:
            self.process = subprocess.Popen(
                [mocapd, "run", "--cluster", nats, "--coordinator", etcd, "--metrics-port", str(self.port)],
                stdout=subprocess.DEVNULL,
                stderr=err,
                env=env,
            )
        wait_healthy(self.port, 30)

    def events(self, name: str) -> list[dict[str, Any]]:
        return [e for e in json_lines(self.err) if e.get("event") == name]

    def owned(self) -> set[int]:
        last = self.events("partitions")
        return set(last[-1]["owned"]) if last else set()

    def sees(self, n: int) -> bool:
        last = self.events("partitions")
        return bool(last) and len(last[-1]["members"]) == n

    def metrics(self) -> dict[str, float]:
        try:
            return scrape(self.port, 2)
        except OSError:
            return {}

    def stop(self, sig: int = signal.SIGTERM) -> None:
        if self.process.poll() is None:
            self.process.send_signal(sig)
            self.process.wait(30)


def lost(m: dict[str, float]) -> float:
    return sum(v for k, v in m.items() if k.startswith("mocapd_drops_total")) + m.get(
        'mocapd_stream_events_total{event="gap_frames"}', 0.0
    )


def wait(condition: Any, timeout: float) -> None:
    deadline = time.monotonic() + timeout
    while not condition():
        if time.monotonic() > deadline:
            raise SystemExit("timed out waiting for the workers")
        time.sleep(0.05)


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--workers", default="1,2,3")
    parser.add_argument("--sizes", default="20,30,45,60,90")
    parser.add_argument("--seconds", type=float, default=10.0)
    parser.add_argument("--takeover-streams", type=int, default=60)
    args = parser.parse_args()
    print(describe())
    sample = streams(1)[0]
    pose_bytes = len(sample.pose()[1])
    print(f"a CMU pose (13.asf, {sample.motion.channels.shape[1]} channels) on the wire: {pose_bytes} bytes")
    work = Path(tempfile.mkdtemp(prefix="bench-cluster-"))
    (work / "nats").mkdir()
    (work / "etcd").mkdir()
    server = NatsServer(work / "nats").start()
    etcd = Etcd(work / "etcd").start()
    assert server.process is not None
    wire = Wire(server.url)
    results: dict[int, dict[str, Any]] = {}
    print(
        f"{partitions()} partitions; {args.seconds:g} s per size after a 2 s warm-up; "
        f"p99 aim <= {P99_MS:g} ms"
    )
    head = (
        "workers",
        "streams",
        "lost",
        "behind",
        "detections",
        "p50 ms",
        "p99 ms",
        "µs/pose w",
        "µs/pose bus",
    )
    print(" ".join(f"{h:>10s}" for h in head) + "  holds")
    try:
        for w in [int(x) for x in args.workers.split(",")]:
            purge(server.url)  # a new worker would replay the earlier sizes' streams
            workers = [Worker(work, f"b{w}-{i}", server.url, etcd.url) for i in range(w)]
            wait(lambda: all(x.sees(w) for x in workers), 30)  # noqa: B023  (called at once)
            held = 0
            for size in [int(x) for x in args.sizes.split(",")]:
                load = Load(wire, size, f"w{w}s{size}-")
                load.run(2.0)
                wire.take()
                before = [x.metrics() for x in workers]
                cpu0 = sum(cpu_s(x.process.pid) for x in workers), cpu_s(server.process.pid)
                sent = load.run(args.seconds)
                time.sleep(0.5)
                cpu1 = sum(cpu_s(x.process.pid) for x in workers), cpu_s(server.process.pid)
                after = [x.metrics() for x in workers]
                received = sum(
                    a.get("mocapd_frames_in_total", 0) - b.get("mocapd_frames_in_total", 0)
                    for a, b in zip(after, before, strict=True)
                )
                gone = sum(lost(a) - lost(b) for a, b in zip(after, before, strict=True)) + max(
                    0.0, sent - received
                )
                behind = sum(a.get("mocapd_queued_poses", 0) for a in after)
                lat = wire.take()
                p50, p99 = (
                    (np.percentile(lat, 50), np.percentile(lat, 99)) if lat.size else (float("nan"),) * 2
                )
                ok = gone == 0 and behind <= 0.5 * RATE * size and p99 <= P99_MS
                held = size if ok else held
                per_w, per_bus = (cpu1[0] - cpu0[0]) / sent * 1e6, (cpu1[1] - cpu0[1]) / sent * 1e6
                results.setdefault(w, {"sizes": {}})["sizes"][size] = (ok, per_w, per_bus)
                print(
                    f"{w:10d} {size:10d} {gone:10.0f} {behind / (RATE * size):9.2f}s {lat.size:10d} "
                    f"{p50:10.1f} {p99:10.1f} {per_w:10.1f} {per_bus:10.1f}  {'yes' if ok else 'no'}",
                    flush=True,
                )
                time.sleep(3)  # the streams go idle and are forgotten
            results[w]["held"] = held
            for x in workers:
                x.stop()
        takeover(work, server, etcd, wire, args.takeover_streams)
        extrapolate(results, pose_bytes)
    finally:
        wire.close()
        etcd.stop()
        server.stop()


def purge(url: str) -> None:
    """Empty the partitions' buffers (the earlier sizes' streams would be replayed too)."""
    import asyncio

    import nats
    from nats.js.errors import NotFoundError

    async def main() -> None:
        nc = await nats.connect(url)
        js = nc.jetstream()
        for p in range(partitions()):
            with contextlib.suppress(NotFoundError):  # not made yet
                await js.purge_stream(f"MOCAPD_BUF_{p}")
        await nc.close()

    asyncio.run(main())


def takeover(work: Path, server: NatsServer, etcd: Etcd, wire: Wire, size: int) -> None:
    time.sleep(3)  # the earlier streams idle, then their buffered poses gone
    purge(server.url)
    workers = [Worker(work, f"t-{i}", server.url, etcd.url) for i in range(3)]
    wait(lambda: all(x.sees(3) for x in workers), 30)
    load = Load(wire, size, "tk-")
    stop = threading.Event()
    thread = threading.Thread(target=load.run, args=(60.0, stop), daemon=True)
    thread.start()
    try:
        for (victim, sig, what), after_s in zip(
            ((workers[0], signal.SIGKILL, "kill -9"), (workers[1], signal.SIGTERM, "SIGTERM")),
            (8.0, 6.0),
            strict=True,
        ):
            time.sleep(after_s)
            owned, at = victim.owned(), time.time()
            victim.stop(sig)
            survivors = [x for x in workers if x.process.poll() is None]
            time.sleep(0.2)
            deadline = time.monotonic() + 15
            caught = None
            while time.monotonic() < deadline and caught is None:
                live = all(live_after(survivors, p, at) is not None for p in owned & used(workers))
                if live and sum(x.metrics().get("mocapd_queued_poses", 0) for x in survivors) <= size:
                    caught = time.time() - at
                time.sleep(0.05)
            lives = [t - at for p in owned & used(workers) if (t := live_after(survivors, p, at)) is not None]
            nan = float("nan")
            print(
                f"takeover after {what} of a worker owning {len(owned)} partitions ({size} streams, "
                f"3 workers): first live pose per partition {min(lives, default=nan):.2f}-"
                f"{max(lives, default=nan):.2f} s; recognition caught up after "
                f"{caught if caught is not None else nan:.2f} s",
                flush=True,
            )
    finally:
        stop.set()
        thread.join(10)
        for x in workers:
            x.stop(signal.SIGKILL)


def live_after(workers: list[Worker], partition: int, at: float) -> float | None:
    """When one of ``workers`` first consumed a live pose of ``partition`` after ``at``."""
    ts = [e["ts"] for x in workers for e in x.events("partition live") if e["partition"] == partition]
    return min((t for t in ts if t > at), default=None)


def used(workers: list[Worker]) -> set[int]:
    return {e["partition"] for x in workers for e in x.events("partition live")}


def extrapolate(results: dict[int, dict[str, Any]], pose_bytes: int) -> None:
    one = results.get(1)
    if not one or not one["held"]:
        print("extrapolation: no size held with one worker")
        return
    ok = [v for v in one["sizes"].values() if v[0]]
    per_w = float(np.median([v[1] for v in ok]))
    per_bus = float(np.median([v[2] for v in ok]))
    print("streams held: " + ", ".join(f"{w} worker(s) {r['held']}" for w, r in sorted(results.items())))
    stream_core = 1e6 / (RATE * per_w)
    print(
        f"measured here: a worker's CPU {per_w:.1f} µs per pose (a core holds {stream_core:.0f} "
        f"streams at 100 %), "
        f"the nats-server's {per_bus:.1f} µs per pose (mapping, the buffer's store, the delivery)"
    )
    # a 16-core machine: b cores of bus, the rest workers at 70 % (the tail stays inside 20 ms)
    util = 0.7
    streams_16 = 16 / (1 / (util * stream_core) + RATE * per_bus / 1e6)
    bus_cores = streams_16 * RATE * per_bus / 1e6
    print(
        f"16-core machine (one worker per core at {util:.0%}, the nats-server on the same machine, "
        f"its cost per pose as here): {streams_16:,.0f} streams, {bus_cores:.1f} cores of them the bus"
    )
    per_machine = 16 * util * stream_core
    total = 10 * per_machine
    bytes_s = total * RATE * pose_bytes
    print(
        f"10 machines of 16 worker cores (the bus on machines of its own: a NATS cluster with the "
        f"partitions' buffers spread over its servers): {total:,.0f} streams, "
        f"{total * RATE / 1e6:.2f} M poses/s into the bus ({bytes_s * 8 / 1e9:.2f} Gbit/s of "
        f"{pose_bytes}-byte poses; "
        f"each goes in once and out once to its owner, so about twice that crosses the network), "
        f"which at this machine's {per_bus:.1f} µs of server CPU per pose needs "
        f"{total * RATE * per_bus / 1e6:.0f} server cores; NATS publishes its throughput per server "
        f"with `nats bench` (docs.nats.io/using-nats/nats-tools/nats_cli/natsbench): check that figure "
        f"for JetStream memory streams of this message size on the target hardware before sizing the bus"
    )


if __name__ == "__main__":
    main()
