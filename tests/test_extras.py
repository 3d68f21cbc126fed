"""The install without extras (issue 36): with aiohttp, aetcd and nats-py absent (a finder that
refuses them, in the real process), the daemon replays a real recording over ZeroMQ and over a real
mosquitto and finds what ``detect`` finds; every module but the four that need an extra imports;
``mocapd view`` and cluster mode end with one line naming the extra to install."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from bench.processes import free_port
from daemon.extras import EXTRAS
from daemon.library import default_library_path, load_library
from daemon.recognizer import detect
from daemon.recordings import read_recording
from tests.helpers import DATA, REPO, Broker, MqttCollector, assert_one_error_line, wait_for

ABSENT = sorted({m for modules in EXTRAS.values() for m in modules} | {"grpc"})
WITHOUT = f"""
import sys
from importlib.abc import MetaPathFinder

class Absent(MetaPathFinder):
    def find_spec(self, name, path=None, target=None):
        if name.partition(".")[0] in {ABSENT!r}:
            raise ModuleNotFoundError(f"No module named {{name!r}}", name=name)
        return None

sys.meta_path.insert(0, Absent())
"""
NEED_EXTRAS = {
    "daemon.service.view.server",
    "daemon.service.membership",
    "daemon.service.cluster",
    "protocols.nats",
}
ASF, AMC = DATA / "cmu" / "13" / "13.asf", DATA / "cmu" / "13" / "13_30.amc.gz"


def without_extras(code: str, *args: str | Path, timeout: float = 120) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-c", WITHOUT + code, *map(str, args)],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=timeout,
        check=False,
    )


def mocapd_without_extras(*args: str | Path) -> subprocess.CompletedProcess[str]:
    return without_extras("from daemon.cli import main\nsys.exit(main())", *args)


def test_the_finder_refuses_what_the_extras_hold() -> None:
    result = without_extras("import aiohttp")
    assert result.returncode == 1 and "No module named 'aiohttp'" in result.stderr


def test_every_module_but_the_extras_own_imports_without_them() -> None:
    names = sorted(
        ".".join(p.relative_to(REPO).with_suffix("").parts).removesuffix(".__init__")
        for top in ("daemon", "protocols", "replay")
        for p in (REPO / top).rglob("*.py")
        if p.name != "__main__.py"
    )
    code = "import importlib\nfor name in sys.argv[1:]:\n    importlib.import_module(name)\n"
    result = without_extras(code, *[n for n in names if n not in NEED_EXTRAS])
    assert result.returncode == 0, result.stderr
    for name in sorted(NEED_EXTRAS):  # and these four do need them (else the list above is stale)
        assert without_extras(f"import {name}").returncode == 1, name


def replay_config(tmp_path: Path) -> Path:
    """A configuration whose ZeroMQ sockets take free ports (run --replay needs a known poses port)."""
    config = tmp_path / "daemon.yaml"
    zmq = {"poses": f"tcp://127.0.0.1:{free_port()}", "detections": f"tcp://127.0.0.1:{free_port()}"}
    config.write_text(json.dumps({"zmq": zmq, "metrics": {"port": 0}}), encoding="utf-8")
    return config


def detections(stdout: str) -> list[tuple[str, int, int]]:
    found = [json.loads(line) for line in stdout.splitlines() if line.startswith("{")]
    return [(d["class"], d["start_frame"], d["end_frame"]) for d in found if d.get("type") == "detection"]


@pytest.mark.slow
def test_the_daemon_runs_on_zeromq_and_mqtt_without_the_extras(tmp_path: Path) -> None:
    over_zmq = mocapd_without_extras(
        "--config", replay_config(tmp_path), "run", "--speed", "4", "--replay", ASF, AMC
    )
    assert over_zmq.returncode == 0, over_zmq.stderr
    found = detections(over_zmq.stdout)
    expected = detect(read_recording(ASF, AMC), load_library(default_library_path()), 120.0)
    assert found and found == [(d.class_name, d.start_frame, d.end_frame) for d in expected]
    broker = Broker(tmp_path).start()
    collector = MqttCollector(broker.url, ["mocap/+/detections"], client_id="extras")
    try:
        config = replay_config(tmp_path)
        over_mqtt = mocapd_without_extras(
            "--config", config, "run", "--mqtt", broker.url, "--speed", "4", "--replay", ASF, AMC
        )
        assert over_mqtt.returncode == 0, over_mqtt.stderr
        wait_for(lambda: len(collector.detections()) >= len(found), 10, "the detections over MQTT")
        got = [(d["class"], d["start_frame"], d["end_frame"]) for d in collector.detections()]
    finally:
        collector.close()
        broker.stop()
    assert got == found


@pytest.mark.parametrize(
    ("args", "error"),
    [
        (
            ["view", "--bus", "mqtt://127.0.0.1:1"],
            "mocapd: mocapd view needs mocapd's view extra (aiohttp not installed): "
            "pip install 'mocapd[view]'",
        ),
        (
            ["run", "--cluster", "nats://127.0.0.1:1", "--coordinator", "etcd://127.0.0.1:1"],
            "mocapd: --cluster: cluster mode needs mocapd's cluster extra (aetcd, nats not installed): "
            "pip install 'mocapd[cluster]'",
        ),
        (
            ["cluster", "status", "--coordinator", "etcd://127.0.0.1:1"],
            "mocapd: mocapd cluster status needs mocapd's cluster extra (aetcd, nats not installed): "
            "pip install 'mocapd[cluster]'",
        ),
    ],
)
def test_a_command_whose_extra_is_missing_names_it(args: list[str], error: str) -> None:
    assert assert_one_error_line(mocapd_without_extras(*args)) == error
