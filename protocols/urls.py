"""The addresses transports are configured with, understood in one place and without a transport's
library: the configuration checks them (:mod:`daemon.config`), the transports use them."""

from __future__ import annotations

import re
from urllib.parse import SplitResult, urlsplit

from daemon.errors import InputError

PORTS = "1..65535"
"""The ports a TCP address may name (0 is no port: binding to it takes any free one)."""


def _split(url: str, what: str) -> SplitResult:
    """``url``'s parts; InputError (saying ``what`` a good one is) for one that cannot be split."""
    try:
        return urlsplit(url)
    except ValueError:  # an IPv6 host without its closing bracket
        raise InputError(f"{what}, got {url!r}") from None


def _port(parts: SplitResult, what: str, url: str) -> int | None:
    """The port of ``parts`` (None if the URL names none); InputError for one outside 1..65535."""
    try:
        port = parts.port
    except ValueError:  # not a number, or past 65535
        port = -1
    if port is not None and not 1 <= port <= 65535:
        raise InputError(f"{what}, the port in {PORTS}, got {url!r}")
    return port


def parse_mqtt_url(url: str) -> tuple[str, int, bool]:
    """(host, port, tls) of ``mqtt://host:port`` or ``mqtts://host:port`` (ports 1883 / 8883 by
    default); InputError otherwise (a port outside 1..65535 too)."""
    what = "an MQTT broker is mqtt://HOST[:PORT] or mqtts://HOST[:PORT]"
    parts = _split(url, what)
    if parts.scheme not in ("mqtt", "mqtts") or not parts.hostname:
        raise InputError(f"{what}, got {url!r}")
    port = _port(parts, what, url)
    tls = parts.scheme == "mqtts"
    return parts.hostname, port or (8883 if tls else 1883), tls


def parse_etcd_url(url: str) -> tuple[str, int]:
    """(host, port) of the cluster's coordinator ``etcd://host[:port]`` (port 2379 by default);
    InputError otherwise (a port outside 1..65535 too)."""
    what = "an etcd coordinator is etcd://HOST[:PORT]"
    parts = _split(url, what)
    if parts.scheme != "etcd" or not parts.hostname or parts.path not in ("", "/") or parts.query:
        raise InputError(f"{what}, got {url!r}")
    return parts.hostname, _port(parts, what, url) or 2379


def parse_nats_urls(text: str) -> list[str]:
    """The servers of ``cluster.nats``: ``nats://HOST:PORT`` or several of one NATS cluster,
    ``nats://HOST:PORT,nats://HOST:PORT`` (or ``nats://HOST:PORT,HOST:PORT``), each as
    ``nats://HOST:PORT``, in the order given, duplicates once; InputError naming the one that is not
    such an address."""
    what = "must be nats://HOST:PORT[,nats://HOST:PORT...] (a port in 1..65535)"
    out: list[str] = []
    for piece in text.split(","):
        one = piece if piece.startswith("nats://") else f"nats://{piece}"
        match = re.fullmatch(r"nats://[^/\s,]+:(\d+)", one)
        if match is None or not 1 <= int(match[1]) <= 65535 or not text.startswith("nats://"):
            raise InputError(
                f"{what}, got {text!r:.70}" + (f" (its server {piece!r})" if "," in text else "")
            )
        if one not in out:
            out.append(one)
    return out


def parse_etcd_urls(text: str) -> list[tuple[str, int]]:
    """The (host, port) of each member of the coordinator ``etcd://host[:port][,host[:port]...]``
    (each may also be written ``etcd://host:port``), in the order given, duplicates once;
    InputError naming the one that is not an etcd address."""
    what = "an etcd coordinator is etcd://HOST[:PORT][,HOST[:PORT]...]"
    if not text.startswith("etcd://"):
        raise InputError(f"{what}, got {text!r}")
    out: list[tuple[str, int]] = []
    for piece in text.removeprefix("etcd://").split(","):
        one = piece if piece.startswith("etcd://") else f"etcd://{piece}"
        try:
            address = parse_etcd_url(one)
        except InputError:
            raise InputError(f"{what}, got {text!r} (its member {piece!r})") from None
        if address not in out:
            out.append(address)
    return out


def split_endpoint(endpoint: str) -> tuple[str, bool]:
    """A ZeroMQ endpoint setting: ``"connect tcp://h:p"`` → (``"tcp://h:p"``, False); a bare endpoint
    binds."""
    words = endpoint.split()
    if len(words) == 2 and words[0] in ("bind", "connect"):
        return words[1], words[0] == "bind"
    return endpoint, True


FREE_PORTS = ("0", "*")
"""What a bound TCP endpoint may name in place of its port: any free port (ZeroMQ's ``*``)."""


def tcp_address(endpoint: str) -> tuple[str, str] | None:
    """(host, port) as written of a ZeroMQ ``tcp://`` endpoint (of a connect's ``source;host:port``,
    the host connected to; an IPv6 host without its brackets); None for another transport or an
    endpoint without a port, which ZeroMQ itself refuses."""
    if not endpoint.startswith("tcp://"):
        return None
    host, colon, port = endpoint[len("tcp://") :].rsplit(";", 1)[-1].rpartition(":")
    if not colon or not host:
        return None
    return host.removeprefix("[").removesuffix("]"), port


def check_zmq_endpoint(setting: str) -> tuple[str, bool]:
    """(endpoint, bind) of a ZeroMQ endpoint setting (:func:`split_endpoint`); InputError for a TCP
    port outside 1..65535, which libzmq would take modulo 65536 (``:99999`` binds 34463), or for a
    free port (``0``, ``*``) to connect to. Anything else ZeroMQ checks when it binds or connects."""
    endpoint, bind = split_endpoint(setting)
    address = tcp_address(endpoint)
    if address is None:
        return endpoint, bind
    port = address[1]
    if bind and port in FREE_PORTS:
        return endpoint, bind
    if not re.fullmatch(r"[0-9]+", port) or not 1 <= int(port) <= 65535:
        free = " (or 0 or * to bind any free port)" if bind else ""
        raise InputError(f"{setting}: the port must be in {PORTS}{free}, got {port!r}")
    return endpoint, bind


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
