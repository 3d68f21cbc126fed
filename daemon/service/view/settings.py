"""``mocapd view``'s settings, parsed once from its options into a frozen dataclass; a bad one is a
:class:`~daemon.errors.UsageError` naming its option."""

from __future__ import annotations

import ipaddress
import math
import re
from dataclasses import dataclass
from urllib.parse import urlsplit

from daemon.errors import InputError, UsageError
from protocols.urls import parse_bus_url

MAX_POSES_PER_S = 240.0
TOKEN = re.compile(r"[A-Za-z0-9._~-]{16,256}")
"""A token as it may stand in a URL's query unescaped: 16 to 256 characters."""


@dataclass(frozen=True)
class ViewSettings:
    """The bus to watch (``mqtt://HOST:PORT``, ``mqtts://``, ``zmq+tcp://HOST:PORT``), where to serve
    the page (``host``, ``port``; 0: any free port), the daemon's metrics base URL (``http://HOST:PORT``,
    None: no health shown), the most poses a second per stream sent to the browsers, and the token
    ``/ws`` and ``/api/`` ask for (None: none on loopback; beyond it the server makes one)."""

    bus: str
    host: str = "127.0.0.1"
    port: int = 8080
    metrics: str | None = None
    poses_per_s: float = 30.0
    token: str | None = None

    @property
    def loopback(self) -> bool:
        """Whether the page is served on the loopback interface alone."""
        return is_loopback(self.host)


def is_loopback(host: str) -> bool:
    """``host`` (a name or an address) is this machine's loopback: ``localhost``, 127.0.0.0/8, ::1."""
    if host.lower() == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def view_settings(
    bus: str, host: str, port: int, metrics: str | None, poses_per_s: float, token: str | None = None
) -> ViewSettings:
    """The settings of these option values, checked (``token`` from ``--token`` or the environment's
    ``MOCAPD_VIEW_TOKEN``)."""
    try:
        parse_bus_url(bus)
    except InputError as e:
        raise UsageError(e.reason, field="--bus") from None
    if not host or any(c.isspace() or c in "/[]" for c in host):
        raise UsageError(f"must be a host name or address, got {host!r}", field="--host")
    if not 0 <= port <= 65535:
        raise UsageError(f"must be a port in 0..65535, got {port}", field="--port")
    if metrics is not None:
        try:
            parts = urlsplit(metrics)
            given = parts.port
        except ValueError as e:
            raise UsageError(f"must be http://HOST:PORT, got {metrics!r}: {e}", field="--metrics") from None
        if parts.scheme not in ("http", "https") or not parts.hostname or given is None or parts.query:
            raise UsageError(f"must be http://HOST:PORT, got {metrics!r}", field="--metrics")
        metrics = metrics.rstrip("/")
    if not math.isfinite(poses_per_s) or not 0 < poses_per_s <= MAX_POSES_PER_S:
        raise UsageError(
            f"must be a number of poses a second in (0, {MAX_POSES_PER_S:g}], got {poses_per_s:g}",
            field="--poses-per-s",
        )
    if token is not None and not TOKEN.fullmatch(token):
        raise UsageError(
            "must be 16 to 256 characters of A-Z, a-z, 0-9 and . _ ~ - (e.g. python -c "
            "'import secrets; print(secrets.token_urlsafe(24))')",
            field="--token",
        )
    return ViewSettings(bus, host, port, metrics, poses_per_s, token)
