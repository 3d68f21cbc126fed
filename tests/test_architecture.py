"""The packages show the architecture: the runtime (readers, features, automaton, DTW, the live
recogniser, loading a library) loads nothing of search, segmentation, learning or dataset
preparation, and every module imports only from its own layer or those below it."""

from __future__ import annotations

import ast
import importlib
import json
import re
import subprocess
import sys
from pathlib import Path

import pytest

from tests.helpers import REPO

PACKAGES = ("daemon", "protocols", "replay")

LAYERS: tuple[tuple[str, tuple[str, ...]], ...] = (
    ("base", ("daemon", "daemon.types", "daemon.errors", "daemon.checks", "daemon.storage", "daemon.stages")),
    ("readers", ("replay",)),
    (
        "runtime",
        (
            "daemon._automaton",
            "daemon._dtw",
            "daemon._features",
            "daemon._live",
            "daemon.features",
            "daemon.frames",
            "daemon.dtw",
            "daemon.keyframes",
            "daemon.templates",
            "daemon.automaton",
            "daemon.library",
            "daemon.recognizer",
            "daemon.bank",
            "daemon.progress",
        ),
    ),
    ("search", ("daemon.recordings", "daemon.search")),
    ("segmentation", ("daemon.behaviours",)),
    ("learning", ("daemon.learn",)),
    ("tools", ("daemon.tools", "daemon.plots")),
    ("config", ("daemon.config", "protocols.urls")),
    ("wire", ("protocols",)),
    ("cluster", ("daemon.cluster",)),
    ("service", ("daemon.service",)),
    ("cli", ("daemon.cli", "daemon.__main__")),
)
"""Lowest first; a module is in the layer of its longest listed prefix."""

RUNTIME = {
    "daemon",
    "daemon._automaton",
    "daemon._dtw",
    "daemon._features",
    "daemon._live",
    "daemon.automaton",
    "daemon.checks",
    "daemon.dtw",
    "daemon.errors",
    "daemon.features",
    "daemon.frames",
    "daemon.keyframes",
    "daemon.library",
    "daemon.recognizer",
    "daemon.storage",
    "daemon.templates",
    "daemon.types",
    "replay",
    "replay._kinematics",
    "replay.amc",
    "replay.asf",
    "replay.errors",
    "replay.joints",
    "replay.kinematics",
    "replay.textio",
}
"""What ``import daemon.recognizer`` loads (a package's own modules counted as the package)."""

PACKAGE_ORDER = {
    "daemon.features": ("language", "catalog", "velocity", "assembler", "compiler", "batch", "stream"),
    "daemon.behaviours": (
        "common",
        "quaternions",
        "moments",
        "online",
        "pca",
        "ppca",
        "gmm",
        "scoring",
        "methods",
    ),
}
"""The modules of the packages that re-export one subsystem a module, bottom up: each imports only
those before it."""


def layer(module: str) -> int:
    best, at = "", -1
    for i, (_, prefixes) in enumerate(LAYERS):
        for p in prefixes:
            if (module == p or module.startswith(p + ".")) and len(p) > len(best):
                best, at = p, i
    assert at >= 0, f"{module} is in no layer: add it to LAYERS"
    return at


def loaded(statement: str) -> set[str]:
    """The project's modules a fresh interpreter has loaded after ``statement``, the submodules of
    a subpackage of daemon counted as it (daemon.features.x -> daemon.features)."""
    code = (
        f"import json, sys\n{statement}\n"
        f"print(json.dumps(sorted(m for m in sys.modules if m.split('.')[0] in {PACKAGES!r})))"
    )
    out = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, check=True)
    names = json.loads(out.stdout)
    subpackages = {n for n in names if (REPO / Path(*n.split(".")) / "__init__.py").is_file()}
    return {next((p for p in subpackages if n.startswith(p + ".") and p.count(".") == 1), n) for n in names}


def test_the_live_recogniser_loads_only_the_runtime() -> None:
    assert loaded("import daemon.recognizer") == RUNTIME
    assert loaded("import daemon.bank") == RUNTIME | {"daemon.bank"}


WIRE = sorted(
    f"protocols.{p.stem}"
    for p in (REPO / "protocols").glob("*.py")
    if p.stem not in ("__init__", "replay", "publish")
)


@pytest.mark.parametrize("module", ["protocols", *WIRE])
def test_the_wire_loads_nothing_of_the_engine(module: str) -> None:
    """Of daemon, the wire loads only the error root (a refused message is a client's error)."""
    engine = {m for m in loaded(f"import {module}") if not m.startswith("protocols")}
    assert engine <= {"daemon", "daemon.errors"}


@pytest.mark.parametrize("module", ["protocols.publish", "protocols.replay"])
def test_replaying_loads_the_readers_not_the_engine(module: str) -> None:
    got = loaded(f"import {module}")
    assert {m for m in got if m.startswith("daemon")} <= {"daemon", "daemon.errors", "daemon.types"}


def sources() -> list[Path]:
    return sorted(p for pkg in PACKAGES for p in (REPO / pkg).rglob("*.py*") if p.suffix in (".py", ".pyx"))


def imports(path: Path) -> list[tuple[int, str]]:
    """The project modules ``path`` imports (at any depth of its code), with their lines."""
    text = path.read_text(encoding="utf-8")
    if path.suffix == ".pyx":
        return [
            (i, m.group(1))
            for i, line in enumerate(text.splitlines(), 1)
            if (m := re.match(r"\s*(?:from|import)\s+((?:daemon|protocols|replay)[\w.]*)", line))
        ]
    out = []
    for node in ast.walk(ast.parse(text)):
        if isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            base = node.module
            for a in node.names:  # `from daemon.tools import mocap6` imports daemon.tools.mocap6
                sub = f"{base}.{a.name}"
                here = REPO / Path(*sub.split("."))
                out.append((node.lineno, sub if here.with_suffix(".py").is_file() or here.is_dir() else base))
        elif isinstance(node, ast.Import):
            out += [(node.lineno, a.name) for a in node.names]
    return [(n, m) for n, m in out if m.split(".")[0] in PACKAGES]


def module_name(path: Path) -> str:
    parts = path.relative_to(REPO).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def test_imports_go_only_downward() -> None:
    wrong = []
    for path in sources():
        me = module_name(path)
        for line, other in imports(path):
            if layer(other) > layer(me):
                wrong.append(
                    f"{path.relative_to(REPO)}:{line}: {me} ({LAYERS[layer(me)][0]}) imports "
                    f"{other} ({LAYERS[layer(other)][0]})"
                )
    assert wrong == []


ASYNC = ("daemon.service", "protocols")
"""Where asyncio may be imported: the service (with its adapters to etcd) and the transports."""


def test_asyncio_only_in_the_service_and_the_transports() -> None:
    """DESIGN: daemon/service/ is the only place besides the transports that imports asyncio; the
    cluster's ring is pure."""
    wrong = [
        str(path.relative_to(REPO))
        for path in sources()
        if not module_name(path).startswith(ASYNC)
        and re.search(r"^\s*(import asyncio|from asyncio)", path.read_text(encoding="utf-8"), re.M)
    ]
    assert wrong == []


def test_the_ring_is_pure() -> None:
    """Which member owns which partition loads nothing but the error root: no asyncio, no etcd
    client, no engine."""
    code = (
        "import sys, daemon.cluster.ring\n"
        "print(sorted(m for m in ('asyncio', 'aetcd', 'grpc', 'numpy') if m in sys.modules))"
    )
    out = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"
    assert loaded("import daemon.cluster.ring") == {"daemon", "daemon.errors", "daemon.cluster"}


@pytest.mark.parametrize("package", sorted(PACKAGE_ORDER))
def test_a_packages_modules_import_only_those_below(package: str) -> None:
    order = PACKAGE_ORDER[package]
    directory = REPO / Path(*package.split("."))
    assert sorted(p.stem for p in directory.glob("*.py") if p.stem != "__init__") == sorted(order)
    for k, name in enumerate(order):
        inside = {
            m.removeprefix(package + ".")
            for _, m in imports(directory / f"{name}.py")
            if m.startswith(package + ".")
        }
        assert inside <= set(order[:k]), f"{package}.{name} imports {sorted(inside - set(order[:k]))}"


@pytest.mark.parametrize("package", sorted(PACKAGE_ORDER))
def test_all_names_what_a_package_re_exports(package: str) -> None:
    module = importlib.import_module(package)
    public = {name for name in vars(module) if not name.startswith("_")} - set(PACKAGE_ORDER[package])
    assert sorted(module.__all__) == sorted(public)
