"""The deploy/ folder: every file listed in its README, the etcd config the tests start from, and the
systemd units well formed."""

from __future__ import annotations

import configparser
import shutil
import subprocess
from pathlib import Path

import pytest
import yaml

from tests.etcd_server import CLUSTER, CONFIG, Etcd, EtcdCluster
from tests.helpers import REPO

DEPLOY = REPO / "deploy"
MOCAPD = "/opt/mocapd/.venv/bin/mocapd"


def test_the_readme_lists_every_file() -> None:
    readme = (DEPLOY / "README.md").read_text(encoding="utf-8")
    files = sorted(
        str(p.relative_to(DEPLOY)) for p in DEPLOY.rglob("*") if p.is_file() and p.name != "README.md"
    )
    assert files and [f for f in files if f"`{f}`" not in readme] == []


def test_the_tests_run_the_shipped_etcd_config_changing_only_addresses_and_paths(tmp_path: Path) -> None:
    shipped = yaml.safe_load(CONFIG.read_text(encoding="utf-8"))
    server = Etcd(tmp_path)
    server.client_port, server.peer_port = 12379, 12380
    tested = server.settings()
    changed = {k for k in shipped.keys() | tested.keys() if shipped.get(k) != tested.get(k)}
    assert changed == {
        "data-dir",
        "listen-client-urls",
        "advertise-client-urls",
        "listen-peer-urls",
        "initial-advertise-peer-urls",
        "initial-cluster",
        "log-outputs",
    }
    assert shipped["listen-client-urls"] == "http://127.0.0.1:2379"  # what README and the unit say


ADDRESSES = {
    "data-dir",
    "listen-client-urls",
    "advertise-client-urls",
    "listen-peer-urls",
    "initial-advertise-peer-urls",
    "log-outputs",
}


def test_the_three_member_etcd_is_the_one_member_config_but_for_names_and_addresses(tmp_path: Path) -> None:
    """The cluster's members are the single config's settings (timing, compaction, quota) with only
    the name, the addresses and the initial cluster differing; the tests change only addresses and
    paths of them."""
    single = yaml.safe_load(CONFIG.read_text(encoding="utf-8"))
    members = [yaml.safe_load(c.read_text(encoding="utf-8")) for c in CLUSTER]
    peers = ",".join(f"{m['name']}={m['initial-advertise-peer-urls']}" for m in members)
    for m in members:
        assert m["initial-cluster"] == peers
        differ = {k for k in single.keys() | m.keys() if single.get(k) != m.get(k)}
        assert (
            {"name", "initial-cluster"}
            <= differ
            <= (ADDRESSES - {"log-outputs"}) | {"name", "initial-cluster"}
        )
    cluster = EtcdCluster(tmp_path)
    for k, member in enumerate(cluster.members):
        member.client_port, member.peer_port = 30000 + k, 31000 + k
    for member, shipped in zip(cluster.members, members, strict=True):
        tested = member.settings()
        assert {k for k in shipped.keys() | tested.keys() if shipped.get(k) != tested.get(k)} == ADDRESSES | {
            "initial-cluster"
        }
    assert cluster.url == "etcd://127.0.0.1:30000,127.0.0.1:30001,127.0.0.1:30002"


def test_the_etcd_unit_runs_the_config_it_is_installed_with() -> None:
    unit = configparser.ConfigParser(strict=False, interpolation=None)
    unit.read(DEPLOY / "systemd" / "mocapd-etcd.service", encoding="utf-8")
    assert unit["Service"]["ExecStart"] == "/usr/bin/etcd --config-file /etc/mocapd/etcd.conf.yml"
    assert unit["Service"]["StateDirectory"] == "mocapd-etcd"
    shipped = yaml.safe_load(CONFIG.read_text(encoding="utf-8"))
    assert shipped["data-dir"] == "/var/lib/mocapd-etcd"
    readme = (DEPLOY / "README.md").read_text(encoding="utf-8")
    assert "`/etc/mocapd/etcd.conf.yml`" in readme


@pytest.mark.parametrize("unit", sorted(p.name for p in (DEPLOY / "systemd").glob("*.service")))
def test_systemd_accepts_the_units(unit: str, tmp_path: Path) -> None:
    analyze = shutil.which("systemd-analyze")
    if analyze is None:
        pytest.skip("systemd-analyze is not installed")
    copy = tmp_path / unit
    shutil.copy(DEPLOY / "systemd" / unit, copy)
    result = subprocess.run([analyze, "verify", str(copy)], capture_output=True, text=True, timeout=60)
    # mocapd itself is installed where the units say (/opt/mocapd, docs/daemon.md) only on a host
    absent = f"Command {MOCAPD} is not executable: No such file or directory"
    complaints = [line for line in result.stderr.splitlines() if not line.endswith(absent)]
    assert complaints == [], result.stderr
    assert result.returncode == 0 or absent in result.stderr


def test_the_tests_run_the_shipped_nats_config_changing_only_ports_and_paths(tmp_path: Path) -> None:
    from daemon.config import ClusterConfig, load_config
    from tests.nats_server import CONFIG as NATS_CONFIG
    from tests.nats_server import NatsServer, partitions

    server = NatsServer(tmp_path)
    shipped = NATS_CONFIG.read_text(encoding="utf-8").splitlines()
    tested = server.config.read_text(encoding="utf-8").splitlines()
    changed = [(a.strip(), b.strip()) for a, b in zip(shipped, tested, strict=True) if a != b]
    assert [a.split(":")[0] for a, _ in changed] == ["port", "http", "store_dir", "port"]
    # the mappings' partitions are the workers' (config.yaml and the default)
    assert partitions() == ClusterConfig().partitions == load_config(REPO / "config.yaml").cluster.partitions
    unit = configparser.ConfigParser(strict=False, interpolation=None)
    unit.read(DEPLOY / "systemd" / "mocapd-nats.service", encoding="utf-8")
    assert unit["Service"]["ExecStart"] == "/usr/sbin/nats-server -c /etc/mocapd/nats.conf"
    assert "store_dir: /var/lib/mocapd-nats" in NATS_CONFIG.read_text(encoding="utf-8")
    assert unit["Service"]["StateDirectory"] == "mocapd-nats"
