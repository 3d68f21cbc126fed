"""What a takeover costs against the streams a worker owned and the buffers' length, without and
with checkpoints (``docs/cluster.md``, "Checkpoints"; issue 34).

    python -m bench.bench_takeover [--per-worker 10,30,100] [--buffers 10,60] [--rate 30]
    python -m bench.bench_takeover --handovers 20 [--streams 60]

A nats-server from ``deploy/nats/nats.conf`` and an etcd from ``deploy/etcd`` on loopback ports. For
each buffer length, checkpoints off and on (``cluster.checkpoint_s`` 0 and 2) and streams per worker
S: the buffers and checkpoints of the run before deleted, two workers, 2 S looping streams of real
recordings (:class:`bench.bench_cluster.Load`, every 120 / ``rate``-th frame announced at ``rate``
Hz, so that a hundred streams per worker fit this machine) published over NATS for the buffer's
length and 40 s more (the buffers full, the last checkpoint at most ``checkpoint_s`` behind), then
one worker killed (kill -9). Per partition of the killed worker that carries
streams: from the kill to the first live pose its new owner consumed (the lease's expiry, the
buffer read from its start or from its checkpoint, the catching up); the time until the survivor's
queue was back to a pose per stream; the buffered messages it read again.

``--handovers N``: instead, three workers (default settings) and ``--streams`` streams at 120 Hz;
N times a worker stopped with SIGTERM and, in turn, N times one killed with -9, a new worker started
after each; per partition of the stopped or killed worker that carries streams, the time from the
signal to its first live pose at its new owner: their p50, p99 and maximum per kind (issue 34's
aims: SIGTERM within 1 s, kill -9 within the lease and a second).
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import signal
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

from bench.bench_cluster import Load, Wire, Worker, live_after, used, wait
from bench.machine import describe
from tests.etcd_server import Etcd
from tests.nats_server import NatsServer, partitions

AFTER_S = 40.0
"""Seconds published beyond the buffer's length before the kill (``--after``)."""


def reset(url: str) -> None:
    """Delete the partitions' buffers and the checkpoints (the next workers make them anew)."""
    import nats
    from nats.js.errors import NotFoundError

    async def main() -> None:
        nc = await nats.connect(url)
        js = nc.jetstream()
        for name in [f"MOCAPD_BUF_{p}" for p in range(partitions())] + ["KV_MOCAPD_CHECKPOINTS"]:
            with contextlib.suppress(NotFoundError):
                await js.delete_stream(name)
        await nc.close()

    asyncio.run(main())


def one(
    work: Path,
    server: NatsServer,
    etcd: Etcd,
    wire: Wire,
    per: int,
    buffer_s: float,
    every_s: float,
    rate: float,
    after_s: float,
) -> str:
    reset(server.url)
    name = f"b{buffer_s:g}c{every_s:g}s{per}"
    settings = {"MOCAPD_CLUSTER_BUFFER_S": str(buffer_s), "MOCAPD_CLUSTER_CHECKPOINT_S": str(every_s)}
    workers = [Worker(work, f"{name}-{i}", server.url, etcd.url, settings) for i in range(2)]
    try:
        wait(lambda: all(x.sees(2) for x in workers), 30)
        load = Load(wire, 2 * per, f"{name}-", rate)
        stop = threading.Event()
        thread = threading.Thread(target=load.run, args=(buffer_s + after_s + 30, stop), daemon=True)
        thread.start()
        try:
            time.sleep(buffer_s + after_s)
            victim, survivor = workers
            owned, at = victim.owned(), time.time()
            before = survivor.metrics()
            victim.stop(signal.SIGKILL)
            deadline = time.monotonic() + 25
            caught = None
            while time.monotonic() < deadline and caught is None:
                live = all(live_after([survivor], p, at) is not None for p in owned & used(workers))
                if live and survivor.metrics().get("mocapd_queued_poses", 0) <= 2 * per:
                    caught = time.time() - at
                time.sleep(0.05)
            after = survivor.metrics()
        finally:
            stop.set()
            thread.join(10)
        lives = [t - at for p in owned & used(workers) if (t := live_after([survivor], p, at)) is not None]
        replayed = after.get("mocapd_cluster_replayed_poses_total", 0) - before.get(
            "mocapd_cluster_replayed_poses_total", 0
        )
        resumed = after.get("mocapd_cluster_resumed_partitions_total", 0) - before.get(
            "mocapd_cluster_resumed_partitions_total", 0
        )
        nan = float("nan")
        p50, top = (np.percentile(lives, 50), max(lives)) if lives else (nan, nan)
        return (
            f"{per:>9d} {buffer_s:>8g}s {'on' if every_s else 'off':>11s} {len(lives):>10d} {resumed:>8.0f} "
            f"{p50:>11.2f} {top:>10.2f} {caught if caught is not None else nan:>11.2f} {replayed:>10.0f}"
        )
    finally:
        for x in workers:
            x.stop(signal.SIGKILL)


def handovers(work: Path, server: NatsServer, etcd: Etcd, wire: Wire, n: int, size: int) -> None:
    reset(server.url)
    workers = [Worker(work, f"h-{i}", server.url, etcd.url) for i in range(3)]
    load = Load(wire, size, "h-")
    stop = threading.Event()
    thread = threading.Thread(target=load.run, args=(3600.0, stop), daemon=True)
    thread.start()
    times: dict[str, list[float]] = {"SIGTERM": [], "kill -9": []}
    started = 3
    try:
        wait(lambda: all(x.sees(3) for x in workers), 30)
        time.sleep(3)
        for k in range(2 * n):
            what, sig = ("SIGTERM", signal.SIGTERM) if k < n else ("kill -9", signal.SIGKILL)
            victim = workers[k % 3]
            owned, at = victim.owned(), time.time()
            victim.stop(sig)
            survivors = [x for x in workers if x is not victim]
            carrying = owned & used(workers)
            wait(lambda: all(live_after(survivors, p, at) is not None for p in carrying), 30)  # noqa: B023
            lives = [t - at for p in carrying if (t := live_after(survivors, p, at)) is not None]
            times[what] += lives
            most = max(lives, default=0.0)
            print(
                f"{what} {k % n + 1}: {len(lives)} partitions live again, the last {most:.2f} s after",
                flush=True,
            )
            workers[k % 3] = Worker(work, f"h-{started}", server.url, etcd.url)
            started += 1
            wait(lambda: all(x.sees(3) for x in workers) and all(x.owned() for x in workers), 30)
            time.sleep(2)  # the joiner's partitions taken and live
    finally:
        stop.set()
        thread.join(10)
        for x in workers:
            x.stop(signal.SIGKILL)
    for what, got in times.items():
        if got:
            a = np.array(got)
            print(
                f"{what}: {a.size} partition handovers in {n} events; first live pose p50 "
                f"{np.percentile(a, 50):.2f} s, p99 {np.percentile(a, 99):.2f} s, max {a.max():.2f} s",
                flush=True,
            )


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--per-worker", default="10,30,100", help="streams per worker")
    parser.add_argument("--buffers", default="10,60", help="cluster.buffer_s values")
    parser.add_argument("--rate", type=float, default=30.0, help="poses per second per stream")
    parser.add_argument("--after", type=float, default=AFTER_S, help="seconds published beyond the buffer")
    parser.add_argument("--handovers", type=int, default=0, help="SIGTERM and kill -9 handovers instead")
    parser.add_argument("--streams", type=int, default=60, help="streams for --handovers")
    args = parser.parse_args()
    print(describe())
    work = Path(tempfile.mkdtemp(prefix="bench-takeover-"))
    (work / "nats").mkdir()
    (work / "etcd").mkdir()
    server = NatsServer(work / "nats").start()
    etcd = Etcd(work / "etcd").start()
    wire = Wire(server.url)
    try:
        if args.handovers:
            print(f"{partitions()} partitions, 3 workers, lease 2 s, {args.streams} streams at 120 Hz")
            handovers(work, server, etcd, wire, args.handovers, args.streams)
        else:
            matrix(work, server, etcd, wire, args)
    finally:
        wire.close()
        etcd.stop()
        server.stop()


def matrix(work: Path, server: NatsServer, etcd: Etcd, wire: Wire, args: argparse.Namespace) -> None:
    print(
        f"{partitions()} partitions, 2 workers, lease 2 s, {args.rate:g} poses/s per stream; kill -9 of one "
        f"after buffer + {args.after:g} s; times from the kill"
    )
    head = (
        "per worker",
        "buffer",
        "checkpoints",
        "partitions",
        "resumed",
        "live p50 s",
        "live max s",
        "caught up s",
        "replayed",
    )
    print(" ".join(f"{h:>10s}" for h in head), flush=True)
    for buffer_s in [float(x) for x in args.buffers.split(",")]:
        for every_s in (0.0, 2.0):
            for per in [int(x) for x in args.per_worker.split(",")]:
                print(
                    one(work, server, etcd, wire, per, buffer_s, every_s, args.rate, args.after), flush=True
                )


if __name__ == "__main__":
    main()
