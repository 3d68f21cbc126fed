"""Cluster mode's startup errors, with real servers on loopback: a NATS server or an etcd that does
not answer stops ``mocapd run --cluster`` before anything is published, with one error line naming
the setting (``cluster.nats``, ``cluster.coordinator``, ``cluster.partitions``)."""

from __future__ import annotations

import subprocess
from pathlib import Path

import pytest
import yaml

from bench.processes import free_port
from daemon.config import ClusterConfig
from protocols.nats import mappings
from tests.helpers import REPO, mocapd
from tests.nats_server import MAPPINGS, NatsServer


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


def test_the_shipped_mappings_are_made_from_the_configured_partitions() -> None:
    """One place: ``cluster.partitions`` (its default, config.yaml's value); the server's mappings
    are what ``mocapd cluster mappings`` makes from it."""
    shipped = (MAPPINGS.read_text(encoding="utf-8"), ClusterConfig().partitions)
    assert (
        yaml.safe_load((REPO / "config.yaml").read_text(encoding="utf-8"))["cluster"]["partitions"]
        == shipped[1]
    )
    assert shipped[0] == mappings(shipped[1])
    result = mocapd("cluster", "mappings")
    assert (result.returncode, result.stdout) == (0, shipped[0])
    result = mocapd("cluster", "mappings", "--partitions", "64")
    assert "partition(64,1)" in result.stdout and "256" not in result.stdout


@pytest.mark.slow
def test_a_server_partitioning_by_another_count_is_refused(tmp_path: Path) -> None:
    """A worker whose ``cluster.partitions`` is not the server's, or a server without the mappings,
    is refused in one line naming ``cluster.partitions`` (before, the worker started and owned
    partitions nobody published into, or streams of no partition it read)."""
    server = NatsServer(tmp_path).start()
    try:
        config = tmp_path / "c.yaml"
        config.write_text("cluster:\n  partitions: 16\n", encoding="utf-8")
        args = ("--config", config, "run", "--cluster", server.url, "--coordinator", "etcd://127.0.0.1:1")
        assert last_line(mocapd(*args)) == (
            f"mocapd: cluster.partitions: 16 here, but the NATS server at {server.url} partitions by "
            f"{ClusterConfig().partitions}: make its mappings with `mocapd cluster mappings` from the "
            "same cluster.partitions"
        )
    finally:
        server.stop()
    bare = tmp_path / "bare"
    bare.mkdir()
    server = NatsServer(bare)
    (bare / MAPPINGS.name).write_text("# no mappings\n", encoding="utf-8")
    server.start()
    try:
        line = last_line(mocapd("run", "--cluster", server.url, "--coordinator", "etcd://127.0.0.1:1"))
        assert line.startswith(f"mocapd: cluster.partitions: the NATS server at {server.url} does not map")
    finally:
        server.stop()
