"""A real nats-server for the tests, started from the shipped config (``deploy/nats/nats.conf``) with
only its ports, monitoring address and JetStream directory replaced, so the configuration that ships
(JetStream, the MQTT listener, the partitioning subject mappings) is the one tested.

nats-server is Debian's ``nats-server`` (2.9, ``/usr/sbin/nats-server``; ``.ci/run`` installs it)."""

from __future__ import annotations

import re
import shutil
import subprocess
from pathlib import Path

from bench.processes import free_port
from tests.helpers import ServerProcess

REPO = Path(__file__).resolve().parents[1]
CONFIG = REPO / "deploy" / "nats" / "nats.conf"
MAPPINGS = CONFIG.parent / "partitions.conf"
START_S = 15.0


def nats_binary() -> str:
    binary = shutil.which("nats-server") or "/usr/sbin/nats-server"
    if not Path(binary).exists():
        raise AssertionError(
            "nats-server is not installed (.ci/run installs it: apt-get install nats-server)"
        )
    return binary


def _replaced(text: str, pattern: str, value: str) -> str:
    out, n = re.subn(pattern, value, text, count=1, flags=re.M)
    if n != 1:
        raise AssertionError(f"the shipped {CONFIG.name} has no line matching {pattern!r}")
    return out


def partitions() -> int:
    """The P of the shipped mappings' ``partition(P, 1)``."""
    found = {int(n) for n in re.findall(r"partition\((\d+),", MAPPINGS.read_text(encoding="utf-8"))}
    assert len(found) == 1, f"{MAPPINGS.name}: the mappings disagree on the partitions: {found}"
    return found.pop()


class NatsServer(ServerProcess):
    """One nats-server on free loopback ports (client, MQTT, monitoring), its JetStream directory and
    log in ``where``."""

    def __init__(self, where: Path) -> None:
        self.where = where
        self.port = free_port()
        self.mqtt_port = free_port()
        self.http_port = free_port()
        self.config = where / "nats.conf"
        self.log = where / "nats.log"
        text = CONFIG.read_text(encoding="utf-8")
        text = _replaced(text, r"^port: \d+$", f"port: {self.port}")
        text = _replaced(text, r"^http: .*$", f"http: 127.0.0.1:{self.http_port}")
        text = _replaced(text, r"^  store_dir: .*$", f"  store_dir: {where / 'jetstream'}")
        text = _replaced(text, r"^  port: 1883$", f"  port: {self.mqtt_port}")
        self.config.write_text(text, encoding="utf-8")
        shutil.copyfile(MAPPINGS, where / MAPPINGS.name)
        self.process: subprocess.Popen[bytes] | None = None

    @property
    def url(self) -> str:
        return f"nats://127.0.0.1:{self.port}"

    @property
    def mqtt_url(self) -> str:
        return f"mqtt://127.0.0.1:{self.mqtt_port}"

    def start(self) -> NatsServer:
        from tests.helpers import wait_for

        with self.log.open("ab") as log:
            self.process = subprocess.Popen(
                [nats_binary(), "-c", str(self.config)], stdout=log, stderr=subprocess.STDOUT
            )

        def ready() -> bool:
            assert self.process is not None
            if self.process.poll() is not None:
                raise AssertionError(f"nats-server exited:\n{self.log.read_text()[-3000:]}")
            return "Server is ready" in self.log.read_text(encoding="utf-8", errors="replace")

        wait_for(ready, START_S, "nats-server")
        return self
