"""What the benchmarks that run real processes share: free loopback ports, waiting for one to
listen and for a daemon to be healthy, a daemon's /metrics samples and JSON log lines, and a
process's resident memory and CPU time."""

from __future__ import annotations

import contextlib
import json
import os
import random
import socket
import time
import urllib.error
import urllib.request
from pathlib import Path
from typing import Any

_HANDED_OUT: set[int] = set()


def _port_range() -> tuple[int, int]:
    """The ports :func:`free_port` draws from: the 12,000 below the kernel's ephemeral range, or,
    in a pytest-xdist worker (and the processes it starts, which inherit its environment), that
    worker's own share of them, so that two workers never draw the same port (each remembers only
    its own draws; and Hypothesis seeds ``random`` alike in every worker, so their draws would
    repeat each other's)."""
    try:
        low = int(Path("/proc/sys/net/ipv4/ip_local_port_range").read_text().split()[0])
    except (OSError, ValueError, IndexError):
        low = 32768
    start, stop = max(1024, low - 12000), low
    worker = os.environ.get("PYTEST_XDIST_WORKER", "")
    try:
        count = int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1"))
        index = int(worker.removeprefix("gw")) if worker.startswith("gw") else 0
    except ValueError:
        return start, stop
    if count > 1 and 0 <= index < count:
        share = (stop - start) // count
        start, stop = start + index * share, start + (index + 1) * share
    return start, stop


def json_lines(path: Path) -> list[dict[str, Any]]:
    """The JSON objects that a running process has written whole to ``path`` so far (a log or a
    sink's file): a line still being written, with no newline yet, is left for the next read."""
    lines = path.read_text(encoding="utf-8", errors="replace").splitlines(keepends=True)
    return [json.loads(x) for x in lines if x.startswith("{") and x.endswith("\n")]


def free_port() -> int:
    """A TCP port on loopback nobody listens on now, below the kernel's ephemeral range: a port the
    kernel hands out (bind to 0) can be taken by any process's outgoing connection before the
    daemon binds it (seen in CI: "address already in use" for a port just found free). Never the
    same port twice in a process: ports drawn for servers not yet started are free too (CI: a fresh
    three-server NATS cluster's MQTT listener found its port "already in use", most likely drawn
    for another of its twelve ports; 12 draws of 12,000 collide once in about 180)."""
    start, stop = _port_range()
    for _ in range(100):
        port = random.randrange(start, stop)
        if port in _HANDED_OUT:
            continue
        with socket.socket() as s:
            try:
                s.bind(("127.0.0.1", port))
            except OSError:
                continue
            _HANDED_OUT.add(port)
            return port
    raise RuntimeError("no free loopback port below the ephemeral range")


def listening(port: int) -> bool:
    with socket.socket() as s:
        s.settimeout(0.2)
        return s.connect_ex(("127.0.0.1", port)) == 0


def wait_port(port: int, timeout: float = 10) -> None:
    """Return once something listens on ``port``; SystemExit after ``timeout`` seconds."""
    deadline = time.monotonic() + timeout
    while not listening(port):
        if time.monotonic() > deadline:
            raise SystemExit(f"nothing listens on port {port}")
        time.sleep(0.05)


def wait_healthy(port: int, timeout: float = 30) -> None:
    """Return once the daemon whose /healthz is on ``port`` answers 200 (its transports connected
    and subscribed); SystemExit after ``timeout`` seconds."""
    deadline = time.monotonic() + timeout
    while True:
        try:
            with urllib.request.urlopen(f"http://127.0.0.1:{port}/healthz", timeout=2) as response:
                if response.status == 200:
                    return
        except (urllib.error.URLError, OSError):
            pass  # 503 (an HTTPError) while starting, or not listening yet
        if time.monotonic() > deadline:
            raise SystemExit(f"the daemon on port {port} did not become healthy")
        time.sleep(0.05)


def samples(text: str) -> dict[str, float]:
    """A Prometheus exposition's samples by name with labels (``mocapd_rejects_total{reason="shape"}``)."""
    out = {}
    for line in text.splitlines():
        if line and not line.startswith("#"):
            name, value = line.rsplit(" ", 1)
            out[name] = float(value)
    return out


def scrape(port: int, timeout: float = 10) -> dict[str, float]:
    """The /metrics :func:`samples` on ``port``."""
    with urllib.request.urlopen(f"http://127.0.0.1:{port}/metrics", timeout=timeout) as response:
        return samples(response.read().decode())


def rss_kib(pid: int) -> int:
    """Resident memory of process ``pid`` in KiB (0 if it is gone)."""
    try:
        lines = Path(f"/proc/{pid}/status").read_text().splitlines()
    except OSError:
        return 0
    return next((int(line.split()[1]) for line in lines if line.startswith("VmRSS:")), 0)


def _tree(pid: int) -> list[int]:
    """``pid`` and its descendants alive now."""
    out, todo = [], [pid]
    while todo:
        p = todo.pop()
        out.append(p)
        try:
            tasks = list(Path(f"/proc/{p}/task").iterdir())
        except OSError:
            continue
        for task in tasks:
            with contextlib.suppress(OSError):
                todo += [int(c) for c in (task / "children").read_text().split()]
    return out


def cpu_seconds(pid: int) -> float:
    """User plus system CPU seconds used so far by process ``pid`` and its descendants alive now
    (``mocapd run --workers``: the front and its workers)."""
    tick = os.sysconf("SC_CLK_TCK")
    total = 0
    for p in _tree(pid):
        try:
            fields = Path(f"/proc/{p}/stat").read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        total += int(fields[11]) + int(fields[12])  # utime, stime (fields 14 and 15 of proc(5))
    return total / tick
