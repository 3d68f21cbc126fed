"""The README's picture of the live view (``docs/view.png``): four real recordings replayed in a loop
through a real mosquitto and a real daemon with its progress events on (``mocapd run --progress``),
``mocapd view`` on them, a headless Chromium tab's screenshot.

    python -m bench.view_figure [--out docs/view.png]
"""

from __future__ import annotations

import argparse
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from playwright.sync_api import sync_playwright

from bench.bench_view import CHROMIUM, CHROMIUM_ARGS, until
from bench.common import DATA
from bench.processes import free_port, wait_healthy, wait_port

CLIPS = [
    ("cmu/13/13.asf", "cmu/13/13_30.amc.gz", "studio-a"),
    ("cmu/13/13.asf", "cmu/13/13_29.amc.gz", "studio-b"),
    ("cmu/02/02.asf", "cmu/02/02_05.amc.gz", "stage-left"),
    ("cmu/86/86.asf", "cmu/86/86_01.amc.gz", "stage-right"),
]


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
                    "--progress",
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
        for process in reversed(processes):
            process.terminate()
            process.wait(30)
    print(f"{args.out}: {args.out.stat().st_size // 1024} KiB")


if __name__ == "__main__":
    main()
