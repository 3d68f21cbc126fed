"""The README's picture of the live view (``docs/view.png``): four real recordings replayed in a loop
through a real mosquitto and a real daemon, ``mocapd view`` on them, a headless Chromium tab's
screenshot.

    python -m bench.view_figure [--out docs/view.png]

The daemon on this branch does not publish progress yet (``mocapd run --progress``, issue 24 part
1), so this script publishes the progress messages itself: for each stream, each detection that
``mocapd detect`` gives on its recording and whose frames the stream's latest pose is inside, the
share of its frames gone by as the position, its keyframes spread evenly over that share, its cost
against its τ. Once the daemon publishes progress, drop that and run it with ``--progress``.
"""

from __future__ import annotations

import argparse
import shutil
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import paho.mqtt.client as paho
from paho.mqtt.enums import CallbackAPIVersion
from playwright.sync_api import sync_playwright

from bench.bench_view import CHROMIUM, CHROMIUM_ARGS, until
from bench.common import DATA
from bench.processes import free_port, wait_healthy, wait_port
from daemon.library import default_library_path, load_library
from daemon.recognizer import Detection, detect
from daemon.recordings import read_recording
from protocols.messages import ClassProgress, PoseMessage, ProgressMessage, decode, encode

CLIPS = [
    ("cmu/13/13.asf", "cmu/13/13_30.amc.gz", "studio-a"),
    ("cmu/13/13.asf", "cmu/13/13_29.amc.gz", "studio-b"),
    ("cmu/02/02.asf", "cmu/02/02_05.amc.gz", "stage-left"),
    ("cmu/86/86.asf", "cmu/86/86_01.amc.gz", "stage-right"),
]


class Progress:
    """The progress messages of :mod:`protocols.messages` for the replayed streams (module docstring)."""

    def __init__(
        self, port: int, clips: dict[str, tuple[int, int, list[Detection]]], keyframes: dict[str, int]
    ):
        self.clips = clips
        self.keyframes = keyframes
        self.latest: dict[str, int] = {}
        self.client = paho.Client(CallbackAPIVersion.VERSION2, client_id="view-figure-progress")
        self.client.on_message = self.pose
        self.client.connect("127.0.0.1", port)
        self.client.subscribe("mocap/+/pose", 0)
        self.client.loop_start()
        self.running = True
        self.thread = threading.Thread(target=self.publish, daemon=True)
        self.thread.start()

    def pose(self, client: paho.Client, userdata: object, message: paho.MQTTMessage) -> None:
        pose = decode(bytes(message.payload))
        if isinstance(pose, PoseMessage):
            self.latest[pose.stream] = pose.seq

    def publish(self) -> None:
        while self.running:
            for stream, seq in list(self.latest.items()):
                first, length, found = self.clips[stream]
                frame = first + (seq - first) % length
                classes = []
                for d in found:
                    if d.start_frame <= frame <= d.end_frame:
                        share = (frame - d.start_frame) / max(1, d.end_frame - d.start_frame)
                        n = self.keyframes.get(d.class_name, 0)
                        k = min(n, int(share * n + 0.5))
                        span = d.end_frame - d.start_frame
                        matched = tuple(d.start_frame + round(span * (i + 0.5) / max(1, n)) for i in range(k))
                        classes.append(ClassProgress(d.class_name, n, matched, share, d.cost * share, d.tau))
                m = ProgressMessage(stream, seq, tuple(classes), time.time(), time.time())
                self.client.publish(f"mocap/{stream}/progress", encode(m), qos=0)
            time.sleep(0.1)

    def close(self) -> None:
        self.running = False
        self.thread.join(2)
        self.client.loop_stop()
        self.client.disconnect()


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--out", type=Path, default=Path(__file__).resolve().parents[1] / "docs" / "view.png")
    parser.add_argument(
        "--seconds", type=float, default=14.0, help="how long the replays run before the picture"
    )
    args = parser.parse_args()
    work = Path(tempfile.mkdtemp(prefix="view-figure-"))
    broker_port, metrics_port, view_port = free_port(), free_port(), free_port()
    (work / "m.conf").write_text(f"listener {broker_port} 127.0.0.1\nallow_anonymous true\n")
    mosquitto = shutil.which("mosquitto") or "/usr/sbin/mosquitto"
    mocapd = str(Path(sys.executable).parent / "mocapd")
    url = f"mqtt://127.0.0.1:{broker_port}"
    processes = [subprocess.Popen([mosquitto, "-c", str(work / "m.conf")], stderr=subprocess.DEVNULL)]
    wait_port(broker_port)
    library = load_library(default_library_path())
    keyframes = {n: len(c.keyframes.keyframes) if c.keyframes else 0 for n, c in library.classes.items()}
    clips = {}
    for asf, amc, stream in CLIPS:
        motion = read_recording(DATA / asf, DATA / amc)
        clips[stream] = (int(motion.frames[0]), len(motion), detect(motion, library, 120.0))
    progress = None
    try:
        env_config = work / "daemon.yaml"
        env_config.write_text('{"service": {"instance": "studio-pc"}}')
        processes.append(
            subprocess.Popen(
                [
                    mocapd,
                    "--config",
                    str(env_config),
                    "run",
                    "--mqtt",
                    url,
                    "--metrics-port",
                    str(metrics_port),
                ],
                stderr=subprocess.DEVNULL,
            )
        )
        wait_healthy(metrics_port)
        view = [
            mocapd,
            "view",
            "--bus",
            url,
            "--port",
            str(view_port),
            "--metrics",
            f"http://127.0.0.1:{metrics_port}",
        ]
        processes.append(subprocess.Popen(view, stderr=subprocess.DEVNULL))
        wait_port(view_port, 30)
        progress = Progress(broker_port, clips, keyframes)
        for asf, amc, stream in CLIPS:
            replay = [mocapd, "replay", "--asf", str(DATA / asf), "--amc", str(DATA / amc), "--to", url]
            processes.append(
                subprocess.Popen([*replay, "--stream", stream, "--loop"], stdout=subprocess.DEVNULL)
            )
        with sync_playwright() as p:
            browser = p.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS)
            page = browser.new_page(viewport={"width": 1440, "height": 700})
            page.goto(f"http://127.0.0.1:{view_port}/")
            until(page, "Object.keys(window.mocapdView.streams).length === 4")
            time.sleep(args.seconds)
            until(
                page,
                "Object.values(window.mocapdView.streams).some((s) => Object.keys(s.progress).length)",
                60,
            )
            page.screenshot(path=str(args.out))
            browser.close()
    finally:
        if progress is not None:
            progress.close()
        for process in reversed(processes):
            process.terminate()
            process.wait(30)
    print(f"{args.out}: {args.out.stat().st_size // 1024} KiB")


if __name__ == "__main__":
    main()
