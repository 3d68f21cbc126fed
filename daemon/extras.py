"""The optional parts of the install: ``mocapd[view]`` (``mocapd view``'s web server) and
``mocapd[cluster]`` (cluster mode's bus and membership client). The core install runs the daemon
on ZeroMQ and MQTT without them; a command that needs one it lacks ends with one line naming it."""

from __future__ import annotations

import importlib

from daemon.errors import UsageError

EXTRAS: dict[str, tuple[str, ...]] = {
    "view": ("aiohttp",),
    "cluster": ("aetcd", "nats"),
}
"""Each extra's top-level modules (pyproject.toml's ``[project.optional-dependencies]``)."""


def require(extra: str, what: str, field: str = "") -> None:
    """Nothing if the modules of ``extra`` import, else a :class:`UsageError` (exit 2) saying that
    ``what`` needs it and how to install it, naming ``field`` (an option) if given."""
    missing = []
    for module in EXTRAS[extra]:
        try:
            importlib.import_module(module)
        except ImportError:
            missing.append(module)
    if missing:
        raise UsageError(
            f"{what} needs mocapd's {extra} extra ({', '.join(missing)} not installed): "
            f"pip install 'mocapd[{extra}]'",
            field=field,
        )
