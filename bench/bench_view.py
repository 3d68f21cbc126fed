"""The live view under load: S streams of 120 Hz published on a real broker into ``mocapd view``, one
headless Chromium tab open on its page; what the view's server costs per stream and how the page
keeps up.

    python -m bench.bench_view [--sizes 1,50] [--seconds 10] [--poses-per-s 30]

A mosquitto on a free loopback port; ``mocapd view --bus mqtt://...`` as a process; the load of
``bench/bench_service.py`` (real recordings looped from different starts, channels on the wire, each
tick's poses in one write from a plain socket) in a thread of this process; Chromium (Debian's,
through Playwright) on the page. No daemon: the view subscribes to the broker directly. Each size
runs ``--seconds`` after a 2 s warm-up, 1 stream first as the baseline. Figures per size: the
view's CPU (user + system) in µs per pose received and in % of one core, and per stream; the
browser's frame rate (requestAnimationFrame callbacks a second) and CPU (its processes, % of one
core); poses drawn a second per stream; the pose→drawing latency, p50 and p99 over every pose
drawn (the pose's ``time``, stamped by the load, against ``Date.now()`` when the page drew it:
one machine, one clock).
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import threading
import time
import urllib.request
from pathlib import Path
from typing import Any

import numpy as np
from playwright.sync_api import Page, sync_playwright

from bench.bench_service import Load, MqttLoad
from bench.common import DATA
from bench.machine import describe
from bench.processes import cpu_seconds, free_port, wait_port
from daemon.recordings import read_recording
from replay.catalog import CMU_SUBSTITUTES, recordings

CHROMIUM = "/usr/bin/chromium"
CHROMIUM_ARGS = [
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-quic",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
]
"""Debian's Chromium, headless, as root, talking to nothing but the page (Playwright gives each
launch a fresh profile directory)."""


def until(page: Page, expression: str, timeout: float = 30.0) -> None:
    """Wait until ``expression`` (JavaScript) is true in ``page``, asked through the DevTools protocol:
    Playwright's ``wait_for_function`` evaluates it with ``eval`` in the page, which the view's
    Content-Security-Policy refuses."""
    deadline = time.monotonic() + timeout
    while not page.evaluate(expression):
        if time.monotonic() > deadline:
            raise TimeoutError(f"{expression} did not hold within {timeout:g} s")
        time.sleep(0.05)


def sources(count: int = 12) -> list[tuple[bytes, list[bytes]]]:
    """(ASF text, channel rows packed) of ``count`` recordings spread over the shared data."""
    pairs = recordings(DATA, CMU_SUBSTITUTES)
    out = []
    for asf, amc in pairs[:: max(1, len(pairs) // count)][:count]:
        m = read_recording(asf, amc)
        out.append((Path(asf).read_bytes(), [np.ascontiguousarray(row).tobytes() for row in m.channels]))
    return out


def status(port: int) -> dict[str, Any]:
    with urllib.request.urlopen(f"http://127.0.0.1:{port}/api/status", timeout=5) as r:
        out: dict[str, Any] = json.loads(r.read())
        return out


def children(pid: int) -> list[int]:
    out = []
    for task in Path(f"/proc/{pid}/task").iterdir():
        out += [int(c) for c in (task / "children").read_text().split()]
    return out


def browser_cpu(exclude: set[int]) -> float:
    """CPU seconds of this process's children but ``exclude`` (the Playwright driver and Chromium)."""
    return sum(cpu_seconds(c) for c in children(os.getpid()) if c not in exclude)


PAGE_START = """() => {
    const v = window.mocapdView;
    for (const s of Object.values(v.streams)) s.latencies.length = 0;
    return {frames: v.frames, at: performance.now(),
            drawn: Object.fromEntries(Object.entries(v.streams).map(([k, s]) => [k, s.posesDrawn]))};
}"""
PAGE_END = """() => {
    const v = window.mocapdView;
    return {frames: v.frames, at: performance.now(), latencies: v.latencies(),
            drawn: Object.fromEntries(Object.entries(v.streams).map(([k, s]) => [k, s.posesDrawn]))};
}"""


def measure(
    page: Page,
    load: Load,
    size: int,
    seconds: float,
    view: subprocess.Popen[bytes],
    port: int,
    others: set[int],
) -> dict[str, float]:
    """One size: a warm-up, then ``seconds`` measured."""
    prefix = "v"
    load.run(size, 2.0, prefix)
    until(page, f"Object.keys(window.mocapdView.streams).length >= {size}")
    before_status, before_cpu, before_browser = status(port), cpu_seconds(view.pid), browser_cpu(others)
    start = page.evaluate(PAGE_START)
    sender = threading.Thread(target=load.run, args=(size, seconds, prefix))
    began = time.monotonic()
    sender.start()
    sender.join()
    elapsed = time.monotonic() - began
    end = page.evaluate(PAGE_END)
    cpu, browser = cpu_seconds(view.pid) - before_cpu, browser_cpu(others) - before_browser
    after_status = status(port)
    poses = after_status["bus"]["received"] - before_status["bus"]["received"]
    names = [f"{prefix}{k}" for k in range(size)]
    drawn = [end["drawn"].get(n, 0) - start["drawn"].get(n, 0) for n in names]
    lat = np.array(end["latencies"], dtype=float)
    page_s = (end["at"] - start["at"]) / 1000
    return {
        "streams": size,
        "poses_per_s": poses / elapsed,
        "view_us_per_pose": cpu / max(1, poses) * 1e6,
        "view_core_pct": cpu / elapsed * 100,
        "view_core_pct_per_stream": cpu / elapsed * 100 / size,
        "fps": (end["frames"] - start["frames"]) / page_s,
        "browser_core_pct": browser / elapsed * 100,
        "drawn_per_stream_s": float(np.mean(drawn)) / page_s,
        "latency_p50_ms": float(np.percentile(lat, 50)) if lat.size else float("nan"),
        "latency_p99_ms": float(np.percentile(lat, 99)) if lat.size else float("nan"),
        "bus_dropped": after_status["bus"]["dropped"] - before_status["bus"]["dropped"],
        "coalesced": sum(c["coalesced"] for c in after_status["client_details"])
        - sum(c["coalesced"] for c in before_status["client_details"]),
    }


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--sizes", default="1,50")
    parser.add_argument("--seconds", type=float, default=10.0)
    parser.add_argument("--poses-per-s", type=float, default=30.0)
    args = parser.parse_args()
    print(describe())
    work = Path(tempfile.mkdtemp(prefix="bench-view-"))
    broker_port, view_port = free_port(), free_port()
    (work / "m.conf").write_text(
        f"listener {broker_port} 127.0.0.1\nallow_anonymous true\nset_tcp_nodelay true\n"
        "max_queued_messages 100000\n"
    )
    mosquitto = shutil.which("mosquitto") or "/usr/sbin/mosquitto"
    broker = subprocess.Popen([mosquitto, "-c", str(work / "m.conf")], stderr=subprocess.DEVNULL)
    wait_port(broker_port)
    command = [
        str(Path(sys.executable).parent / "mocapd"),
        *("view", "--bus", f"mqtt://127.0.0.1:{broker_port}", "--port", str(view_port)),
        *("--poses-per-s", str(args.poses_per_s)),
    ]
    with open(work / "view.err", "wb") as err:
        view = subprocess.Popen(command, stdout=subprocess.DEVNULL, stderr=err)
    wait_port(view_port, 30)
    load = Load(sources())
    load.wire = MqttLoad(broker_port, load.on_detection)
    results = []
    try:
        others = set(children(os.getpid()))  # mosquitto and the view: not the browser
        with sync_playwright() as p:
            browser = p.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS)
            page = browser.new_page(viewport={"width": 1600, "height": 1000})
            page.goto(f"http://127.0.0.1:{view_port}/")
            until(page, "window.mocapdView && window.mocapdView.connected")
            print(
                f"mosquitto on loopback; mocapd view --poses-per-s {args.poses_per_s:g}; one headless "
                f"Chromium tab (1600x1000); {args.seconds:g} s per size after a 2 s warm-up"
            )
            head = (
                "streams",
                "poses/s",
                "view µs/pose",
                "view %core",
                "%/stream",
                "fps",
                "browser %",
                "drawn/s",
                "p50 ms",
                "p99 ms",
            )
            print(" ".join(f"{h:>12s}" for h in head))
            for size in [int(x) for x in args.sizes.split(",")]:
                r = measure(page, load, size, args.seconds, view, view_port, others)
                results.append(r)
                print(
                    f"{size:12d} {r['poses_per_s']:12,.0f} {r['view_us_per_pose']:12.1f} "
                    f"{r['view_core_pct']:12.1f} "
                    f"{r['view_core_pct_per_stream']:12.2f} {r['fps']:12.1f} {r['browser_core_pct']:12.1f} "
                    f"{r['drawn_per_stream_s']:12.1f} {r['latency_p50_ms']:12.1f} {r['latency_p99_ms']:12.1f}"
                )
            browser.close()
    finally:
        load.close()
        view.terminate()
        view.wait(10)
        broker.terminate()
        broker.wait(10)
    print(json.dumps(results))


if __name__ == "__main__":
    main()
