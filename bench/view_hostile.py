"""The live view's page under the worst the wire allows (issue 36): a real mosquitto, ``mocapd
view``, one headless Chromium tab; one live stream of 120 Hz throughout, and for each case
``--seconds`` of hostile traffic beside it, after a quiet baseline measured in the same run.

    python -m bench.view_hostile [--seconds 8]

Cases: ``keyframes`` — progress for one class with 64 keyframes (the wire's limit) at 10 messages
a second; ``classes`` — 256 classes of 64 keyframes a message at 10 a second; ``new names`` — 40
messages a second, each naming 16 classes never seen before; ``statuses`` — 64 retained fake
``online`` statuses of other instances, then 10 a second more. Printed per case: the page's frame
rate (requestAnimationFrame callbacks a second) and its ratio to the baseline's, the WebSocket's
reconnections (snapshots), and what the page holds: progress rows and keyframe ticks on the
card, daemon pills, the widest row against its card.
"""

from __future__ import annotations

import argparse
import shutil
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import paho.mqtt.client as paho
from paho.mqtt.enums import CallbackAPIVersion
from playwright.sync_api import Page, sync_playwright

from bench.bench_view import CHROMIUM, CHROMIUM_ARGS, until
from bench.machine import describe
from bench.processes import free_port, wait_port
from protocols.messages import (
    ClassProgress,
    Message,
    PoseMessage,
    ProgressMessage,
    SkeletonMessage,
    StatusMessage,
    encode,
    topic,
)
from replay import JOINT_NAMES

FACTS = """() => {
    const v = window.mocapdView;
    const card = document.querySelector('section.card[data-stream="live"]');
    const rows = card ? [...card.querySelectorAll('.class-progress')] : [];
    return {frames: v.frames, at: performance.now(), snapshots: v.snapshots, rows: rows.length,
            ticks: card ? card.querySelectorAll('.tick').length : 0,
            pills: document.querySelectorAll('#daemons .pill').length,
            overflow: card ? Math.max(0, ...rows.map((r) => r.scrollWidth)) - card.clientWidth : 0};
}"""


def keyframes_case(k: int) -> list[Message]:
    c = ClassProgress("Squat", 64, tuple(range(1, 41)), 0.5, 0.01, 0.1)
    return [ProgressMessage("live", 1000 + k, (c,), time.time(), time.time())]


def classes_case(k: int) -> list[Message]:
    many = tuple(ClassProgress(f"class-{i:03d}", 64, tuple(range(1, 33)), 0.5, 0.01, 0.1) for i in range(256))
    return [ProgressMessage("live", 1000 + k, many, time.time(), time.time())]


def new_names_case(k: int) -> list[Message]:
    fresh = tuple(ClassProgress(f"n{k:06d}-{i}", 4, (1, 2), 0.9, 0.01, 0.1) for i in range(16))
    return [ProgressMessage("live", 1000 + k, fresh, time.time(), time.time())]


def statuses_case(k: int) -> list[Message]:
    return [StatusMessage(f"fake-{k % 256:03d}", "online", "6.6.6", 0, time.time())]


CASES: dict[str, tuple[float, Callable[[int], list[Message]]]] = {
    "keyframes": (10.0, keyframes_case),
    "classes": (10.0, classes_case),
    "new names": (40.0, new_names_case),
    "statuses": (10.0, statuses_case),
}


class Publisher:
    def __init__(self, port: int) -> None:
        self.client = paho.Client(CallbackAPIVersion.VERSION2, client_id=f"hostile-{time.monotonic_ns()}")
        self.client.connect("127.0.0.1", port)
        self.client.loop_start()

    def send(self, m: Message, retain: bool = False) -> None:
        self.client.publish(topic(m), encode(m), qos=0, retain=retain)

    def close(self) -> None:
        self.client.loop_stop()
        self.client.disconnect()


def poses() -> Iterator[PoseMessage]:
    p = np.zeros((26, 3), np.float32)
    p[:, 1] = np.arange(26) * 6.0
    seq = 0
    while True:
        seq += 1
        p[:, 0] = np.sin(seq / 60) * 20
        yield PoseMessage("live", seq, time.time(), positions=p.copy())


def measure(page: Page, seconds: float, work: Callable[[], None] | None) -> dict[str, Any]:
    """The page's facts after ``work`` (or ``seconds`` of quiet), its frame rate and reconnections
    over that time."""
    start: dict[str, Any] = page.evaluate(FACTS)
    if work is not None:
        worker = threading.Thread(target=work)
        worker.start()
        worker.join()
    else:
        time.sleep(seconds)
    end: dict[str, Any] = page.evaluate(FACTS)
    fps = (end["frames"] - start["frames"]) / ((end["at"] - start["at"]) / 1000)
    return end | {"fps": fps, "reconnects": end["snapshots"] - start["snapshots"]}


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--seconds", type=float, default=8.0)
    args = parser.parse_args()
    print(describe())
    work = Path(tempfile.mkdtemp(prefix="bench-hostile-"))
    broker_port, view_port = free_port(), free_port()
    (work / "m.conf").write_text(f"listener {broker_port} 127.0.0.1\nallow_anonymous true\n")
    broker = subprocess.Popen(
        [shutil.which("mosquitto") or "/usr/sbin/mosquitto", "-c", str(work / "m.conf")],
        stderr=subprocess.DEVNULL,
    )
    wait_port(broker_port)
    mocapd = str(Path(sys.executable).parent / "mocapd")
    with open(work / "view.err", "wb") as err:
        view = subprocess.Popen(
            [mocapd, "view", "--bus", f"mqtt://127.0.0.1:{broker_port}", "--port", str(view_port)],
            stdout=subprocess.DEVNULL,
            stderr=err,
        )
    wait_port(view_port, 30)
    pub = Publisher(broker_port)
    stop = threading.Event()

    def stream() -> None:  # the live stream, 120 Hz, throughout
        pub.send(SkeletonMessage("live", 120.0, JOINT_NAMES))
        began = time.monotonic()
        for k, pose in enumerate(poses(), start=1):
            if stop.is_set():
                return
            pub.send(pose)
            time.sleep(max(0.0, began + k / 120 - time.monotonic()))

    streamer = threading.Thread(target=stream, daemon=True)
    streamer.start()
    try:
        with sync_playwright() as p:
            browser = p.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS)
            page = browser.new_page(viewport={"width": 1600, "height": 1000})
            page.goto(f"http://127.0.0.1:{view_port}/")
            until(page, "window.mocapdView && document.querySelector('section.card[data-stream=\"live\"]')")
            time.sleep(2.0)
            base = measure(page, args.seconds, None)
            print(f"one stream of 120 Hz; {args.seconds:g} s a case; baseline (quiet): {base['fps']:.1f} fps")
            head = ("case", "fps", "ratio", "reconnects", "rows", "ticks", "pills", "overflow px")
            print(" ".join(f"{h:>11}" for h in head))
            for name, (per_s, make) in CASES.items():

                def hostile(per_s: float = per_s, make: Callable[[int], list[Message]] = make) -> None:
                    began, k = time.monotonic(), 0
                    while time.monotonic() - began < args.seconds:
                        for m in make(k):
                            pub.send(m, retain=isinstance(m, StatusMessage))
                        k += 1
                        time.sleep(max(0.0, began + k / per_s - time.monotonic()))

                r = measure(page, args.seconds, hostile)
                ratio = r["fps"] / base["fps"]
                cells = (r["reconnects"], r["rows"], r["ticks"], r["pills"], r["overflow"])
                print(f"{name:>11} {r['fps']:11.1f} {ratio:11.2f} " + " ".join(f"{c:11d}" for c in cells))
            browser.close()
    finally:
        stop.set()
        pub.close()
        view.terminate()
        view.wait(10)
        broker.terminate()
        broker.wait(10)


if __name__ == "__main__":
    main()
