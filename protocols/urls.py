"""The addresses transports are configured with, understood in one place and without a transport's
library: the configuration checks them (:mod:`daemon.config`), the transports use them."""

from __future__ import annotations

from urllib.parse import urlsplit

from daemon.errors import InputError


def parse_mqtt_url(url: str) -> tuple[str, int, bool]:
    """(host, port, tls) of ``mqtt://host:port`` or ``mqtts://host:port`` (ports 1883 / 8883 by
    default); ValueError otherwise."""
    parts = urlsplit(url)
    if parts.scheme not in ("mqtt", "mqtts") or not parts.hostname:
        raise InputError(f"an MQTT broker is mqtt://HOST[:PORT] or mqtts://HOST[:PORT], got {url!r}")
    tls = parts.scheme == "mqtts"
    return parts.hostname, parts.port or (8883 if tls else 1883), tls


def parse_etcd_url(url: str) -> tuple[str, int]:
    """(host, port) of the cluster's coordinator ``etcd://host[:port]`` (port 2379 by default);
    InputError otherwise."""
    try:
        parts = urlsplit(url)
        port = parts.port
    except ValueError as exc:  # a port that is not a number, or out of range
        raise InputError(f"an etcd coordinator is etcd://HOST[:PORT], got {url!r}: {exc}") from None
    if parts.scheme != "etcd" or not parts.hostname or parts.path not in ("", "/") or parts.query:
        raise InputError(f"an etcd coordinator is etcd://HOST[:PORT], got {url!r}")
    return parts.hostname, port or 2379


def split_endpoint(endpoint: str) -> tuple[str, bool]:
    """A ZeroMQ endpoint setting: ``"connect tcp://h:p"`` → (``"tcp://h:p"``, False); a bare endpoint
    binds."""
    words = endpoint.split()
    if len(words) == 2 and words[0] in ("bind", "connect"):
        return words[1], words[0] == "bind"
    return endpoint, True


def parse_bus_url(url: str) -> tuple[str, str]:
    """(kind, address) of a bus an observer subscribes to: ``mqtt://HOST[:PORT]`` or ``mqtts://`` (a
    broker; kind ``mqtt``, the URL itself) or ``zmq+tcp://HOST:PORT`` (the daemon's detections PUB
    socket; kind ``zmq``, the ZeroMQ endpoint ``tcp://HOST:PORT``); InputError otherwise."""
    if url.startswith(("mqtt://", "mqtts://")):
        parse_mqtt_url(url)
        return "mqtt", url
    try:
        parts = urlsplit(url)
        port = parts.port
    except ValueError as exc:
        raise InputError(f"a ZeroMQ bus is zmq+tcp://HOST:PORT, got {url!r}: {exc}") from None
    if parts.scheme != "zmq+tcp" or not parts.hostname or port is None or parts.path not in ("", "/"):
        raise InputError(f"a bus is mqtt://HOST[:PORT] or zmq+tcp://HOST:PORT, got {url!r}")
    return "zmq", f"tcp://{parts.netloc}"
