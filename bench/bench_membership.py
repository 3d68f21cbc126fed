"""Cluster membership in etcd (``daemon/service/membership.py``): how soon the others see a worker
join, leave, or die.

    python -m bench.bench_membership [--repeat 3] [--joins 50] [--kills 3]

Starts etcd from ``deploy/etcd/etcd.conf.yml`` on free loopback ports (as the tests do) ``--repeat``
times and prints how long it took to be healthy; then, with one member watching, ``--joins`` times
another joins and leaves (revoking its lease): the time from entering (or from leaving) until the
watcher's members show it; then ``--kills`` times a worker process joins and is killed with SIGKILL:
the time until the watcher sees it gone, against the lease's TTL (etcd deletes it between TTL and
TTL + 0.5 s after its last keep-alive, which came up to a third of a TTL before the kill).
"""

from __future__ import annotations

import argparse
import asyncio
import os
import signal
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

from bench.machine import describe
from daemon.service.membership import Membership
from tests.etcd_server import Etcd, running

REPO = Path(__file__).resolve().parents[1]
WORKER = """
import asyncio, sys
from daemon.service.membership import Membership

async def main() -> None:
    async with Membership(sys.argv[1], sys.argv[2]):
        print("joined", flush=True)
        await asyncio.sleep(3600)

asyncio.run(main())
"""


async def until(condition: Callable[[], bool]) -> float:
    start = time.monotonic()
    while not condition():
        await asyncio.sleep(0.0005)
    return time.monotonic() - start


def has(watcher: Membership, name: str, present: bool = True) -> Callable[[], bool]:
    return lambda: (name in watcher.members) == present


def figures(name: str, seconds: list[float]) -> None:
    ms = sorted(s * 1000 for s in seconds)
    print(
        f"{name:34s} median {statistics.median(ms):8.1f} ms   max {ms[-1]:8.1f} ms   "
        f"min {ms[0]:8.1f} ms   (n={len(ms)})"
    )


async def joins_and_leaves(url: str, n: int) -> None:
    joined, left = [], []
    async with Membership(url, "watcher") as watcher:
        for k in range(n):
            name = f"w{k}"
            other = Membership(url, name)
            start = time.monotonic()
            await other.__aenter__()
            await until(has(watcher, name))
            joined.append(time.monotonic() - start)
            start = time.monotonic()
            await other.__aexit__(None, None, None)
            await until(has(watcher, name, False))
            left.append(time.monotonic() - start)
    figures("join seen (from entering)", joined)
    figures("leave seen (from leaving)", left)


async def kills(url: str, n: int) -> None:
    gone: list[float] = []
    async with Membership(url, "watcher") as watcher:
        for k in range(n):
            name = f"victim{k}"
            process = subprocess.Popen(
                [sys.executable, "-c", WORKER, url, name],
                cwd=REPO,
                env={**os.environ, "PYTHONPATH": str(REPO)},
                stdout=subprocess.PIPE,
                text=True,
            )
            assert process.stdout is not None
            assert await asyncio.to_thread(process.stdout.readline) == "joined\n"
            await until(has(watcher, name))
            await asyncio.sleep(1.0)
            process.send_signal(signal.SIGKILL)
            process.wait()
            gone.append(await until(has(watcher, name, False)))
        ttl = watcher.lease_ttl
    figures(f"killed: gone after (TTL {ttl} s)", gone)


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    for name, default in (("repeat", 3), ("joins", 50), ("kills", 3)):
        parser.add_argument(f"--{name}", type=int, default=default)
    args = parser.parse_args()  # not pinned to one core: etcd and the workers are processes of their own
    print(describe())
    with tempfile.TemporaryDirectory() as where:
        starts = []
        for k in range(args.repeat):
            server = Etcd(Path(where) / f"start{k}")
            server.where.mkdir()
            start = time.monotonic()
            server.start()
            starts.append(time.monotonic() - start)
            server.stop()
        figures("etcd started to healthy", starts)
        home = Path(where) / "etcd"
        home.mkdir()
        with running(home) as etcd:
            asyncio.run(joins_and_leaves(etcd.url, args.joins))
            asyncio.run(kills(etcd.url, args.kills))


if __name__ == "__main__":
    main()
