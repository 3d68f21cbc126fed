"""A real etcd for the tests, started from the shipped config (``deploy/etcd/etcd.conf.yml``) with
only its data directory, ports and log file replaced, so the configuration that ships is the one
tested.

:class:`Etcd` is one server on free loopback ports (:meth:`Etcd.start`, :meth:`Etcd.stop`,
:meth:`Etcd.kill`); :func:`running` is it as a context manager and :func:`etcd` as a pytest fixture
(``tests/conftest.py`` makes it available to every test module). etcd is Debian's ``etcd-server``
(3.4, ``/usr/bin/etcd``; ``.ci/run`` installs it)."""

from __future__ import annotations

import contextlib
import shutil
import subprocess
import time
import urllib.error
import urllib.request
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
import yaml

from bench.processes import free_port
from tests.helpers import ServerProcess

REPO = Path(__file__).resolve().parents[1]
CONFIG = REPO / "deploy" / "etcd" / "etcd.conf.yml"
CLUSTER = tuple(REPO / "deploy" / "etcd" / "cluster" / f"etcd-{i}.conf.yml" for i in (1, 2, 3))
"""The shipped three-member cluster's configs."""
START_S = 15.0
"""How long etcd may take to be healthy: about 0.7 s here (one election), more on a loaded CI."""


def etcd_binary() -> str:
    binary = shutil.which("etcd") or "/usr/bin/etcd"
    if not Path(binary).exists():
        raise AssertionError("etcd is not installed (.ci/run installs it: apt-get install etcd-server)")
    return binary


class Etcd(ServerProcess):
    """One etcd on free loopback ports, its data and ``etcd.log`` in ``where``."""

    def __init__(self, where: Path, config: Path = CONFIG) -> None:
        self.where = where
        self.shipped = config
        self.config = where / "etcd.conf.yml"
        self.log = where / "etcd.log"
        self.client_port = 0
        self.peer_port = 0
        self.process: subprocess.Popen[bytes] | None = None

    @property
    def url(self) -> str:
        """The coordinator's address as mocapd takes it (``cluster.coordinator``)."""
        return f"etcd://127.0.0.1:{self.client_port}"

    def settings(self) -> dict[str, Any]:
        """The shipped config with this server's data directory, ports and log file."""
        settings: dict[str, Any] = yaml.safe_load(self.shipped.read_text(encoding="utf-8"))
        client = f"http://127.0.0.1:{self.client_port}"
        peer = f"http://127.0.0.1:{self.peer_port}"
        settings |= {
            "data-dir": str(self.where / "data"),
            "listen-client-urls": client,
            "advertise-client-urls": client,
            "listen-peer-urls": peer,
            "initial-advertise-peer-urls": peer,
            "initial-cluster": f"{settings['name']}={peer}",
            "log-outputs": [str(self.log)],
        }
        return settings

    def healthy(self) -> bool:
        try:
            with urllib.request.urlopen(f"http://127.0.0.1:{self.client_port}/health", timeout=1) as r:
                return b'"true"' in r.read()
        except (OSError, urllib.error.URLError):
            return False

    def launch(self) -> None:
        """Start the process on the current ports (not waiting)."""
        self.config.write_text(yaml.safe_dump(self.settings()), encoding="utf-8")
        self.process = subprocess.Popen(
            [etcd_binary(), "--config-file", str(self.config)],
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
            cwd=self.where,
        )

    def wait_healthy(self, deadline: float) -> bool:
        """Whether it said it is healthy before ``deadline`` (monotonic); stopped if not."""
        assert self.process is not None
        while self.process.poll() is None and time.monotonic() < deadline:
            if self.healthy():
                return True
            time.sleep(0.02)
        self.kill()
        return False

    def why(self) -> str:
        log = self.log.read_text(encoding="utf-8", errors="replace") if self.log.exists() else ""
        return log[-3000:]

    def start(self, same_ports: bool = False) -> Etcd:
        """Start on free ports (``same_ports``: those of the last start, for a restart) and wait
        until healthy; new ports again if one was taken meanwhile."""
        for _ in range(1 if same_ports else 3):
            if not same_ports:
                self.client_port, self.peer_port = free_port(), free_port()
            self.launch()
            if self.wait_healthy(time.monotonic() + START_S):
                return self
            if "address already in use" not in self.why():
                raise AssertionError(f"etcd did not become healthy within {START_S:g} s:\n{self.why()}")
        raise AssertionError("etcd could not listen on its ports")


class EtcdCluster:
    """The shipped three-member etcd cluster (``deploy/etcd/cluster``) on free loopback ports, each
    member's data and log in ``where/etcd-<i>``; :attr:`url` names all three as a coordinator."""

    def __init__(self, where: Path) -> None:
        self.members = []
        for config in CLUSTER:
            home = where / config.name.removesuffix(".conf.yml")
            home.mkdir(parents=True, exist_ok=True)
            self.members.append(_Member(home, config, self))

    @property
    def url(self) -> str:
        return "etcd://" + ",".join(f"127.0.0.1:{m.client_port}" for m in self.members)

    def peers(self) -> str:
        return ",".join(f"{m.settings_name}=http://127.0.0.1:{m.peer_port}" for m in self.members)

    def start(self) -> EtcdCluster:
        """All three started together (each waits for a quorum) and healthy."""
        for m in self.members:
            m.client_port, m.peer_port = free_port(), free_port()
        for m in self.members:
            m.launch()
        deadline = time.monotonic() + START_S
        if not all([m.wait_healthy(deadline) for m in self.members]):
            self.stop()
            raise AssertionError(
                "the etcd cluster did not become healthy:\n" + "\n".join(m.why() for m in self.members)
            )
        return self

    def stop(self) -> None:
        for m in self.members:
            m.stop()


class _Member(Etcd):
    def __init__(self, where: Path, config: Path, cluster: EtcdCluster) -> None:
        super().__init__(where, config)
        self.cluster = cluster
        self.settings_name = str(yaml.safe_load(config.read_text(encoding="utf-8"))["name"])

    def settings(self) -> dict[str, Any]:
        return super().settings() | {"initial-cluster": self.cluster.peers()}


@contextlib.contextmanager
def running(where: Path) -> Iterator[Etcd]:
    """An etcd started in ``where`` for the ``with`` block, stopped after it."""
    server = Etcd(where)
    try:
        yield server.start()
    finally:
        server.stop()


@pytest.fixture
def etcd(tmp_path: Path) -> Iterator[Etcd]:
    """A fresh etcd for one test."""
    where = tmp_path / "etcd"
    where.mkdir()
    with running(where) as server:
        yield server
