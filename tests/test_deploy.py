"""The deploy/ folder: every file listed in its README, the etcd config the tests start from, and the
systemd units well formed."""

from __future__ import annotations

import configparser
import shutil
import subprocess
from pathlib import Path

import pytest
import yaml

from tests.etcd_server import CONFIG, Etcd
from tests.helpers import REPO

DEPLOY = REPO / "deploy"


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
    assert (result.returncode, result.stderr) == (0, ""), result.stderr
