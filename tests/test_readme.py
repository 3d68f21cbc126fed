"""The README's commands, run as written (issue 22): its two first commands are what CI runs; every
``sh`` block of the tour runs, in order, in one shell in a scratch copy of the layout (the repository's
``.venv`` and ``../shared`` beside it), and must succeed and print what the tour says; the Python
subscriber receives a replay's detections."""

from __future__ import annotations

import contextlib
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from tests.helpers import REPO, SHARED

README = (REPO / "README.md").read_text(encoding="utf-8")


def blocks(language: str) -> list[str]:
    return re.findall(rf"^```{language}\n(.*?)^```", README, flags=re.M | re.S)


def workspace(tmp_path: Path) -> Path:
    """``tmp_path/main`` with the repository's virtual environment, ``tmp_path/shared`` the data."""
    main = tmp_path / "main"
    main.mkdir()
    (main / ".venv").symlink_to(Path(sys.executable).parents[1])
    (tmp_path / "shared").symlink_to(SHARED)
    return main


def test_the_first_two_commands_are_what_ci_runs() -> None:
    install, tests = blocks("sh")[:2]
    ci = (REPO / ".ci" / "run").read_text(encoding="utf-8")
    assert install.strip() in ci and tests.strip() in ci


@pytest.mark.slow
def test_the_tour_runs_as_written(tmp_path: Path) -> None:
    tour = blocks("sh")[2:]
    assert len(tour) >= 4
    main = workspace(tmp_path)
    script = "set -e\n" + "\n".join(tour) + "\nsleep 1\n"
    out_path, err_path = tmp_path / "out", tmp_path / "err"
    with out_path.open("w") as out_file, err_path.open("w") as err_file:
        process = subprocess.Popen(
            ["bash", "-c", script],
            cwd=main,
            stdout=out_file,  # files, not pipes: the daemons left in the background keep them open
            stderr=err_file,
            start_new_session=True,  # the daemons and the broker it leaves behind go with the group
        )
        try:
            process.wait(timeout=300)
        finally:
            for sig in (signal.SIGTERM, signal.SIGKILL):  # on SIGTERM mosquitto_sub writes what it holds
                with contextlib.suppress(ProcessLookupError):
                    os.killpg(process.pid, sig)
                time.sleep(2)
    out, err = out_path.read_text(), err_path.read_text()
    assert process.returncode == 0, err[-3000:]
    assert "mocapd_detections_out_total 13.0" in out  # the ZeroMQ replay's detections, on /metrics
    assert re.search(r"^mocap/13_30/detections [0-9a-f]+$", out, flags=re.M)  # mosquitto_sub
    assert re.search(r"^JumpJack\s", out, flags=re.M)  # detect with the shipped library
    assert re.search(r"^squat1Reps\s+[\d.]+-[\d.]+ s", out, flags=re.M)  # detect with the learned one
    assert re.search(r"ranked by cost: \d+ hits", out) and "HDM_dg_squat1Reps" in out  # search
    assert re.search(r"\d+ cuts by ppca", out)  # segment


@pytest.mark.slow
def test_the_python_subscriber_gets_the_detections(tmp_path: Path) -> None:
    (subscriber,) = blocks("python")
    main = workspace(tmp_path)
    data = "../shared/data/mocap/cmu/13"
    daemon = subprocess.Popen(
        [".venv/bin/mocapd", "run", "--metrics-port", "0"],
        cwd=main,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    client = subprocess.Popen(
        [sys.executable, "-c", subscriber],
        cwd=main,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        time.sleep(2)
        replay = [".venv/bin/mocapd", "replay", "--asf", f"{data}/13.asf", "--amc", f"{data}/13_30.amc.gz"]
        subprocess.run(
            [*replay, "--to", "zmq+tcp://127.0.0.1:5555", "--speed", "max"], cwd=main, check=True, timeout=60
        )
        time.sleep(2)
    finally:
        daemon.send_signal(signal.SIGTERM)
        daemon.wait(30)
        client.kill()
    out, err = client.communicate()
    lines = out.splitlines()
    assert len(lines) == 13, (out, err)
    assert lines[0].split()[:4] == ["13_30", "JumpJack", "85", "220"]
