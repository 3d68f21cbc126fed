"""A real nats-server for the tests, started from the shipped config (``deploy/nats/nats.conf``) with
only its ports, monitoring address and JetStream directory replaced, so the configuration that ships
(JetStream, the MQTT listener, the partitioning subject mappings) is the one tested.

nats-server is Debian's ``nats-server`` (2.9, ``/usr/sbin/nats-server``; ``.ci/run`` installs it)."""

from __future__ import annotations

import json
import re
import shutil
import subprocess
import urllib.request
from pathlib import Path
from typing import Any

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
    log in ``where``; from ``config`` (the shipped single server's by default, or a member of the
    shipped cluster with ``routes``: the cluster ports of all members, this one's first)."""

    def __init__(self, where: Path, config: Path = CONFIG, routes: list[int] | None = None) -> None:
        self.where = where
        self.port = free_port()
        self.mqtt_port = free_port()
        self.http_port = free_port()
        self.config = where / "nats.conf"
        self.log = where / "nats.log"
        text = config.read_text(encoding="utf-8")
        text = _replaced(text, r"^port: \d+$", f"port: {self.port}")
        text = _replaced(text, r"^http: .*$", f"http: 127.0.0.1:{self.http_port}")
        text = _replaced(text, r"^  store_dir: .*$", f"  store_dir: {where / 'jetstream'}")
        text = _replaced(text, r"^  port: 18\d\d$", f"  port: {self.mqtt_port}")
        if routes is not None:
            text = _replaced(text, r"^  port: 62\d\d$", f"  port: {routes[0]}")
            for k, route in enumerate(sorted(routes)):  # the shipped routes: 6222, 6223, 6224
                text = _replaced(
                    text, rf"^    nats-route://127.0.0.1:{6222 + k}$", f"    nats-route://127.0.0.1:{route}"
                )
        self.config.write_text(text, encoding="utf-8")
        include = re.search(r"^include (\S+)$", text, flags=re.M)
        assert include is not None, f"{config.name} includes no mappings"
        shutil.copyfile(MAPPINGS, (where / include[1]).resolve())
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

    def subscribed(self, subject: str) -> bool:
        """Whether a client subscribed ``subject`` (exactly) on this server (its monitoring's
        ``/subsz``): a publisher may rely on its interest from then on."""
        with urllib.request.urlopen(f"http://127.0.0.1:{self.http_port}/subsz?subs=1", timeout=5) as r:
            listed = json.loads(r.read()).get("subscriptions_list") or []
        return any(sub.get("subject") == subject for sub in listed)


CLUSTER = tuple(CONFIG.parent / "cluster" / f"nats-{i}.conf" for i in (1, 2, 3))
"""The shipped three-server cluster's configs."""


class NatsCluster:
    """The shipped three-server NATS cluster (``deploy/nats/cluster``) on free loopback ports, each
    server in ``where/nats-<i>``; :attr:`url` names all three as ``cluster.nats`` takes them."""

    def __init__(self, where: Path, partitions: int | None = None) -> None:
        routes = [free_port() for _ in CLUSTER]
        self.servers = []
        for k, config in enumerate(CLUSTER):
            home = where / config.stem
            home.mkdir(parents=True, exist_ok=True)
            self.servers.append(NatsServer(home, config, routes[k:] + routes[:k]))
        if partitions is not None:  # the mappings `mocapd cluster mappings --partitions N` makes
            from protocols.nats import mappings

            (where / MAPPINGS.name).write_text(mappings(partitions), encoding="utf-8")

    @property
    def url(self) -> str:
        return ",".join(s.url for s in self.servers)

    async def leader_of(self, stream: str, js: Any) -> int | None:
        """The index in :attr:`servers` of the server leading JetStream stream ``stream`` (None:
        none now), asked through the JetStream context ``js`` (each server is named
        ``mocapd-nats-<i>`` by its shipped config)."""
        info = await js.stream_info(stream)
        leader = info.cluster.leader if info.cluster is not None else None
        return next((k for k in range(len(self.servers)) if leader == f"mocapd-nats-{k + 1}"), None)

    def start(self) -> NatsCluster:
        """All three started, each ready and JetStream's cluster led."""
        from tests.helpers import wait_for

        for server in self.servers:
            server.start()

        def led() -> bool:
            logs = [s.log.read_text(encoding="utf-8", errors="replace") for s in self.servers]
            return all(
                "JetStream cluster new metadata leader" in log
                or "Self is new JetStream cluster metadata leader" in log
                for log in logs
            )

        wait_for(led, START_S, "JetStream's cluster to elect its leader")
        return self

    def stop(self) -> None:
        for server in self.servers:
            server.stop()
