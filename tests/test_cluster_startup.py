"""Cluster mode's startup errors, with real servers on loopback: a NATS server or an etcd that does
not answer stops ``mocapd run --cluster`` before anything is published, with one error line naming
the setting (``cluster.nats``, ``cluster.coordinator``)."""

from __future__ import annotations

import subprocess
from pathlib import Path

import pytest

from bench.processes import free_port
from tests.helpers import mocapd
from tests.nats_server import NatsServer


def last_line(result: subprocess.CompletedProcess[str]) -> str:
    """Status 2, no traceback, "online" never said; the last stderr line (the error)."""
    assert result.returncode == 2, result.stderr
    assert "Traceback" not in result.stderr and '"online"' not in result.stderr
    return result.stderr.splitlines()[-1]


@pytest.mark.slow
def test_an_unreachable_bus_or_coordinator_is_named(tmp_path: Path) -> None:
    nowhere = f"127.0.0.1:{free_port()}"
    result = mocapd(
        "run", "--cluster", f"nats://{nowhere}", "--coordinator", f"etcd://{nowhere}", "--metrics-port", "0"
    )
    assert last_line(result).startswith(f"mocapd: cluster.nats: cannot connect to NATS at nats://{nowhere}")
    assert "ConnectionRefusedError" in last_line(result)  # why, in that one line
    assert '"nats error"' not in result.stderr  # not a dozen retries' warnings before it
    server = NatsServer(tmp_path).start()
    try:
        result = mocapd(
            "run", "--cluster", server.url, "--coordinator", f"etcd://{nowhere}", "--metrics-port", "0"
        )
        assert last_line(result).startswith(
            f"mocapd: cluster.coordinator: cannot join through etcd at etcd://{nowhere}"
        )
    finally:
        server.stop()


@pytest.mark.slow
def test_bad_cluster_settings_are_named(tmp_path: Path) -> None:
    result = mocapd("run", "--cluster", "http://127.0.0.1:4222", "--coordinator", "etcd://127.0.0.1:2379")
    assert result.returncode == 2
    assert "--cluster: must be nats://HOST:PORT" in result.stderr.splitlines()[-1]
    result = mocapd(
        "run", "--cluster", "nats://127.0.0.1:4222", "--coordinator", "etcd://h", "--workers", "2"
    )
    assert result.returncode == 2
    assert "--workers: a cluster worker is one recognition process" in result.stderr.splitlines()[-1]
    result = mocapd("run", "--cluster", "nats://127.0.0.1:4222")
    assert result.returncode == 2
    assert "--coordinator: give --coordinator etcd://HOST[:PORT]" in result.stderr.splitlines()[-1]
    config = tmp_path / "c.yaml"
    config.write_text("cluster:\n  coordinator: zk://127.0.0.1:2181\n", encoding="utf-8")
    result = mocapd("--config", config, "run")
    assert result.returncode == 2
    assert "cluster.coordinator: must be etcd://HOST[:PORT]" in result.stderr.splitlines()[-1]
