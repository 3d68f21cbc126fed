"""The package daemon.features itself: each module imports only the modules below it, and the
package's ``__all__`` names exactly what it re-exports."""

from __future__ import annotations

import ast
from pathlib import Path

import daemon.features
from tests.helpers import REPO

PACKAGE = REPO / "daemon" / "features"
LAYERS = ("language", "catalog", "velocity", "assembler", "compiler", "batch", "stream")
"""The package's modules from the bottom up: each may import only those before it."""


def package_imports(path: Path) -> set[str]:
    """The daemon.features modules that the module at ``path`` imports by name, ``""`` for the package
    itself (which imports every module)."""
    out: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom):
            assert node.level == 0, f"{path.name}: a relative import"
            modules = [node.module or ""]
        elif isinstance(node, ast.Import):
            modules = [alias.name for alias in node.names]
        else:
            continue
        for module in modules:
            if module == "daemon.features" or module.startswith("daemon.features."):
                out.add(module.removeprefix("daemon.features").removeprefix("."))
    return out


def test_the_modules_import_only_downward() -> None:
    assert sorted(p.stem for p in PACKAGE.glob("*.py") if p.stem != "__init__") == sorted(LAYERS)
    for k, name in enumerate(LAYERS):
        assert package_imports(PACKAGE / f"{name}.py") <= set(LAYERS[:k]), name


def test_all_names_what_the_package_re_exports() -> None:
    public = {name for name in vars(daemon.features) if not name.startswith("_")} - set(LAYERS)
    assert sorted(daemon.features.__all__) == sorted(public)
