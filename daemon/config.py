"""``config.yaml``, parsed once at the edge into frozen dataclasses; errors name the file and field.

Each section is a frozen dataclass whose fields carry their defaults (here only: the transports and
the stream table take their sections, not values of their own) and their checks (``metadata``: a
range, or the names a value must be one of); :func:`parse_config` reads them generically, so a field
is declared once. A transport is a section too: its field in :class:`Config` names the module that
makes it (:func:`transport_section`), which is all the registry there is, so adding a transport is
adding its module and its section. Environment variables ``MOCAPD_<SECTION>_<FIELD>`` (e.g.
``MOCAPD_MQTT_URL``) override the file (:func:`environment_overrides`): the value is read as a YAML
scalar, lists as comma-separated words, and errors name the variable."""

from __future__ import annotations

import os
import re
import types
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any, Literal, NamedTuple, Union, get_args, get_origin, get_type_hints

import yaml

from daemon.checks import Checker, read_structured
from daemon.errors import InputError, MocapdError
from daemon.types import (
    DEFAULT_HOLD_S,
    DEFAULT_MAX_GAP_S,
    DEFAULT_NATIVE_RATE,
    MAX_NATIVE_RATE,
    RecognitionMode,
    RecognitionSettings,
)
from protocols.urls import check_zmq_endpoint, parse_etcd_urls, parse_mqtt_url, parse_nats_urls

Units = Literal["asf", "cm"]
LogLevel = Literal["debug", "info", "warning", "error"]
StdoutFormat = Literal["json", "text"]
SegmentationMethod = Literal["none", "pca", "ppca"]


class ConfigError(MocapdError, ValueError):
    """A configuration value that cannot be used; the message names the file and the field."""


def _range(low: float | None = None, high: float | None = None, *, open_low: bool = False) -> dict[str, Any]:
    return {"low": low, "high": high, "low_open": open_low}


def _positive(high: float | None = None) -> dict[str, Any]:
    return _range(0, high, open_low=True)


def transport_section(module: str, *, source: bool) -> dict[str, Any]:
    """The metadata of a transport's section in :class:`Config`: ``module`` makes the transport of
    the section (its ``transport`` function, :class:`protocols.transport.Factory`; imported only
    when the transport is named), which can take poses in if ``source``."""
    return {"transport": module, "source": source}


@dataclass(frozen=True)
class ReplayConfig:
    """How recordings are read: the frame rate assumed when an AMC file does not state one, the
    units of joint positions, and the users' rig maps (YAML files, docs/recordings-and-features.md,
    "BVH"), tried before the built-in ones for BVH recordings and for positions and BVH streams."""

    frame_rate_hz: float = field(default=DEFAULT_NATIVE_RATE, metadata=_positive(MAX_NATIVE_RATE))
    units: Units = "asf"
    rig_maps: tuple[str, ...] = ()


@dataclass(frozen=True)
class RecognizerConfig:
    """The live recogniser (:mod:`daemon.recognizer`): how far an unbounded keyframe gap (stiffness
    0) may reach, in seconds; whether classes compete for a motion (the cheaper template wins); the
    longest a detection is held while another template could still explain its motion more
    cheaply, in seconds; how the classes are found (``mode``, :class:`~daemon.types.RecognitionSettings`)."""

    max_gap_s: float = field(default=DEFAULT_MAX_GAP_S, metadata=_positive(3600))
    compete: bool = True
    hold_s: float = field(default=DEFAULT_HOLD_S, metadata=_range(0, 60))
    mode: RecognitionMode = "library"

    def settings(self, classes: Sequence[str] | None = None) -> RecognitionSettings:
        """These settings for the library's ``classes`` (None: all); ValueError for a class named twice."""
        return RecognitionSettings(
            None if classes is None else tuple(classes), self.max_gap_s, self.compete, self.hold_s, self.mode
        )


@dataclass(frozen=True)
class SegmentationConfig:
    """Behaviour boundaries in the daemon (:mod:`daemon.behaviours`, the online methods): ``method``
    (``none``: off) and the ``streams`` it runs on (shell-style patterns of stream ids)."""

    method: SegmentationMethod = "none"
    streams: tuple[str, ...] = ("*",)


@dataclass(frozen=True)
class ProgressConfig:
    """Progress events (:mod:`daemon.progress`) on ``mocap/<stream>/progress``: whether the daemon
    publishes them (``enabled``), and at most how many a second of a stream's frames (``per_s``;
    a change of the keyframes matched goes out at once)."""

    enabled: bool = False
    per_s: float = field(default=10.0, metadata=_positive(1000))


@dataclass(frozen=True)
class ServiceConfig:
    """``mocapd run``: this instance's name (empty: the host name), the transports poses come in on
    and detections go out on, the limits of the stream table, and the recognition processes
    (``workers``, 0: one per core available; :func:`workers_of`; at most :func:`max_workers`) (see
    config.yaml)."""

    instance: str = ""
    sources: tuple[str, ...] = field(default=("zmq",), metadata={"choices": lambda: SOURCES})
    sinks: tuple[str, ...] = field(default=("zmq", "stdout"), metadata={"choices": lambda: TRANSPORTS})
    idle_s: float = field(default=30.0, metadata=_positive())
    queue_frames: int = field(default=240, metadata=_range(1, 1_000_000))
    max_streams: int = field(default=1000, metadata=_range(1, 1_000_000))
    max_message_bytes: int = field(default=1 << 20, metadata=_range(1024, 1 << 30))
    bridge_s: float = field(default=0.25, metadata=_range(0, 60))
    grace_s: float = field(default=5.0, metadata=_positive(3600))
    tick_budget_ms: float = field(default=2.0, metadata=_positive(1000))
    workers: int = field(default=0, metadata=_range(0, 1024))


@dataclass(frozen=True)
class ZmqConfig:
    """ZeroMQ endpoints (``bind``/``connect`` prefix optional; bare: bind), queue size, linger, CURVE."""

    poses: str = "tcp://127.0.0.1:5555"
    detections: str = "tcp://127.0.0.1:5556"
    hwm: int = field(default=100_000, metadata=_range(1, 1 << 30))
    linger_ms: int = field(default=1000, metadata=_range(0, 600_000))
    curve_secret_key_file: str | None = None
    curve_clients_dir: str | None = None
    relay_per_s: float = field(default=0.0, metadata=_range(0, 1000))
    """Pass each stream's skeleton (at most once a second) and up to this many of its poses a
    second on the detections socket, unchanged, for ``mocapd view`` (0: none)."""


@dataclass(frozen=True)
class MqttConfig:
    """The MQTT broker, the client's identity and credentials, TLS files, the queue bounds, the
    reconnect back-off, and ``startup_s``: how long a starting daemon waits for the broker before
    it gives up (status 2, before "online"; once connected it reconnects for ever)."""

    url: str = "mqtt://127.0.0.1:1883"
    client_id: str = ""
    username: str | None = None
    password: str | None = None
    ca_file: str | None = None
    cert_file: str | None = None
    key_file: str | None = None
    queue: int = field(default=10_000, metadata=_range(1, 10_000_000))
    outbox: int = field(default=100_000, metadata=_range(1, 10_000_000))
    keepalive_s: int = field(default=30, metadata=_range(5, 3600))
    reconnect_min_s: float = field(default=0.25, metadata=_positive(60))
    reconnect_max_s: float = field(default=10.0, metadata=_positive(3600))
    startup_s: float = field(default=10.0, metadata=_positive(3600))


@dataclass(frozen=True)
class StdoutConfig:
    """The stdout sink: JSON lines or readable lines."""

    format: StdoutFormat = "json"


@dataclass(frozen=True)
class ClusterConfig:
    """Cluster mode (``docs/cluster.md``): the NATS server carrying poses and detections, the etcd
    holding the membership, the number of partitions (the NATS server's mappings,
    ``deploy/nats/partitions.conf``, are made from it by ``mocapd cluster mappings``; a worker
    refuses a server that partitions otherwise), this member's lease, the seconds each partition's
    JetStream buffer keeps (0: computed from the lease and the library's reach,
    :func:`daemon.service.cluster.buffer_seconds`), how often at most a partition's checkpoint is
    stored (0: never; a new owner then rebuilds the streams from the whole buffer,
    :meth:`daemon.service.cluster.Cluster.checkpoint`), how often the leader looks at the streams
    per member to even them out (0: never, the ring alone; :meth:`daemon.service.cluster.Cluster.lead`),
    and this member's name (empty: host name and process id). The coordinator has no default: a
    worker must be told where the others are."""

    nats: str = "nats://127.0.0.1:4222"
    coordinator: str = ""
    partitions: int = field(default=256, metadata=_range(1, 1024))
    lease_s: float = field(default=2.0, metadata=_range(0.5, 60))
    replicas: int = field(default=1, metadata=_range(1, 5))
    buffer_s: float = field(default=0.0, metadata=_range(0, 3600))
    checkpoint_s: float = field(default=2.0, metadata=_range(0, 600))
    balance_s: float = field(default=5.0, metadata=_range(0, 600))
    member: str = ""


@dataclass(frozen=True)
class MetricsConfig:
    """``/healthz`` and ``/metrics`` (port 0: off); per-stream labels only with a bounded stream table."""

    host: str = "127.0.0.1"
    port: int = field(default=9464, metadata=_range(0, 65535))
    stream_labels: bool = False


@dataclass(frozen=True)
class LoggingConfig:
    """Structured logs (one JSON object per line on stderr) at ``level``."""

    level: LogLevel = "info"


@dataclass(frozen=True)
class Config:
    replay: ReplayConfig = field(default_factory=ReplayConfig)
    recognizer: RecognizerConfig = field(default_factory=RecognizerConfig)
    segmentation: SegmentationConfig = field(default_factory=SegmentationConfig)
    progress: ProgressConfig = field(default_factory=ProgressConfig)
    service: ServiceConfig = field(default_factory=ServiceConfig)
    zmq: ZmqConfig = field(
        default_factory=ZmqConfig, metadata=transport_section("protocols.zeromq", source=True)
    )
    mqtt: MqttConfig = field(
        default_factory=MqttConfig, metadata=transport_section("protocols.mqtt", source=True)
    )
    stdout: StdoutConfig = field(
        default_factory=StdoutConfig, metadata=transport_section("protocols.stdout", source=False)
    )
    cluster: ClusterConfig = field(
        default_factory=ClusterConfig, metadata=transport_section("protocols.nats", source=True)
    )
    metrics: MetricsConfig = field(default_factory=MetricsConfig)
    logging: LoggingConfig = field(default_factory=LoggingConfig)


TRANSPORTS: tuple[str, ...] = tuple(f.name for f in fields(Config) if "transport" in f.metadata)
"""The transports, by the names of their sections."""
SOURCES: tuple[str, ...] = tuple(f.name for f in fields(Config) if f.metadata.get("source"))
"""The transports that can take poses in."""


class TransportUse(NamedTuple):
    """A transport a configuration names: its name, the module that makes it, its section, and
    whether it is a source and a sink of the service."""

    name: str
    module: str
    settings: Any
    source: bool
    sink: bool


def transports_named(config: Config) -> list[TransportUse]:
    """The transports ``config`` names as sources and sinks, each once, sources first."""
    service = config.service
    kinds = {f.name: f for f in fields(Config)}
    return [
        TransportUse(
            name,
            kinds[name].metadata["transport"],
            getattr(config, name),
            name in service.sources,
            name in service.sinks,
        )
        for name in dict.fromkeys(service.sources + service.sinks)
    ]


def cores() -> int:
    """The cores this process may run on."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1


WORKERS_PER_CORE = 4
"""``service.workers`` may ask for at most this many recognition processes per core: more gain
nothing (recognition is CPU-bound), and each costs its memory, its start and its share of a
shutdown (500 workers on 2 cores took 54 s to stop)."""


def max_workers() -> int:
    """The most recognition processes ``service.workers`` may ask for on this machine."""
    return WORKERS_PER_CORE * cores()


def workers_reason(workers: int) -> str | None:
    """Why ``workers`` is not a number of recognition processes for this machine, or None."""
    if 0 <= workers <= max_workers():
        return None
    return (
        f"must be 0 (one per core) to {max_workers()} ({WORKERS_PER_CORE} per core, {cores()} "
        f"available), got {workers}"
    )


def workers_of(service: ServiceConfig) -> int:
    """The recognition processes ``service`` asks for: ``workers``, or with 0 the cores this
    process may run on."""
    return service.workers or cores()


RENAMED = {
    "service.max_gap_s": "renamed service.bridge_s (the longest run of lost poses bridged); "
    "recognizer.max_gap_s is another setting, the longest keyframe gap of a match",
}
"""Fields that have another name now: what an old file or variable is told."""


MAX_LABELLED_STREAMS = 100
"""``metrics.stream_labels`` needs ``service.max_streams`` at most this (a label per stream)."""


def load_config(path: str | Path | None, environ: Mapping[str, str] | None = None) -> Config:
    """Read ``path`` (``None``: the built-in defaults), then the ``MOCAPD_...`` variables of
    ``environ`` (None: none)."""
    data: Any = {}
    if path is not None:
        data = read_structured(path, "yaml", ConfigError)
        data = {} if data is None else data
    config = parse_config(data, str(path) if path is not None else "<defaults>")
    return config if environ is None else environment_overrides(config, environ)


def parse_config(data: object, source: str = "<config>") -> Config:
    """Build a :class:`Config` from parsed YAML; unknown or ill-typed fields are errors."""
    check = Checker(source, ConfigError)
    sections = {f.name: f for f in fields(Config)}
    root = check.mapping(data, "", optional=list(sections))
    out = {}
    for name, f in sections.items():
        value = root.get(name)
        cls = _section_type(f)
        out[name] = _section(check, name, cls, {} if value is None else value)
    config = Config(**out)
    _cross_checks(check, config)
    return config


def environment_overrides(config: Config, environ: Mapping[str, str]) -> Config:
    """``config`` with every ``MOCAPD_<SECTION>_<FIELD>`` of ``environ`` applied."""
    changes: dict[str, dict[str, Any]] = {}
    known = {f.name: _section_type(f) for f in fields(Config)}
    for key, text in sorted(environ.items()):
        if not key.startswith("MOCAPD_"):
            continue
        rest = key[len("MOCAPD_") :].lower()
        section = next((s for s in known if rest.startswith(s + "_")), None)
        if section is None:
            raise ConfigError(f"no section {rest.split('_')[0]!r} (known: {', '.join(known)})", path=key)
        name = rest[len(section) + 1 :]
        names = {f.name for f in fields(known[section])}
        if f"{section}.{name}" in RENAMED:
            raise ConfigError(RENAMED[f"{section}.{name}"], path=key)
        if name not in names:
            raise ConfigError(
                f"{section} has no field {name!r} (fields: {', '.join(sorted(names))})", path=key
            )
        try:
            value = yaml.safe_load(text) if text.strip() else None
        except yaml.YAMLError:
            value = text
        if _is_tuple(get_type_hints(known[section])[name]):
            value = [w for w in str(text).replace(",", " ").split()]
        f = next(g for g in fields(known[section]) if g.name == name)
        # checked alone first, so that an error names the variable
        _field(
            Checker(key, ConfigError),
            f"{section}.{name}",
            get_type_hints(known[section])[name],
            f.metadata,
            value,
        )
        changes.setdefault(section, {})[name] = value
    if not changes:
        return config
    check = Checker("environment", ConfigError)
    out = {}
    for f in fields(Config):
        current = getattr(config, f.name)
        mine = {g.name: getattr(current, g.name) for g in fields(current)}
        mine = {k: list(v) if isinstance(v, tuple) else v for k, v in mine.items()}
        mine.update(changes.get(f.name, {}))
        out[f.name] = _section(check, f.name, _section_type(f), mine)
    result = Config(**out)
    _cross_checks(check, result)
    return result


def _section_type(f: Any) -> type[Any]:
    cls: type[Any] = f.default_factory
    return cls


def _is_tuple(kind: Any) -> bool:
    return get_origin(kind) is tuple


def _section(check: Checker, name: str, cls: type[Any], value: object) -> Any:
    hints = get_type_hints(cls)
    if isinstance(value, dict):
        for key in value:
            if f"{name}.{key}" in RENAMED:
                check.fail(f"{name}.{key}", RENAMED[f"{name}.{key}"])
    own = check.mapping(value, name, optional=[f.name for f in fields(cls)])
    kwargs = {}
    for f in fields(cls):
        if f.name not in own:
            continue
        kwargs[f.name] = _field(check, f"{name}.{f.name}", hints[f.name], f.metadata, own[f.name])
    return cls(**kwargs)


def _field(check: Checker, where: str, kind: Any, meta: Mapping[str, Any], value: Any) -> Any:
    origin, args = get_origin(kind), get_args(kind)
    if origin in (Union, types.UnionType) and type(None) in args:
        if value is None:
            return None
        (kind,) = [a for a in args if a is not type(None)]
        origin, args = get_origin(kind), get_args(kind)
    if origin is Literal:
        return check.choice(value, where, args)
    if origin is tuple:
        items = check.listing(value, where)
        choices = meta.get("choices")
        choices = choices() if callable(choices) else choices
        out = []
        for i, item in enumerate(items):
            word = check.string(item, f"{where}[{i}]")
            if choices is not None and word not in choices:
                check.fail(f"{where}[{i}]", f"must be one of {', '.join(choices)}, got {word!r:.60}")
            out.append(word)
        if len(set(out)) != len(out):
            check.fail(where, "names a transport twice")
        return tuple(out)
    if kind is bool:
        if not isinstance(value, bool):
            check.fail(where, f"must be true or false, got {value!r:.60}")
        return value
    if kind is int:
        return check.integer(value, where, minimum=meta.get("low"), maximum=meta.get("high"))
    if kind is float:
        return check.number(
            value, where, low=meta.get("low"), high=meta.get("high"), low_open=meta.get("low_open", False)
        )
    if kind is str:
        if not isinstance(value, str):
            check.fail(where, f"must be a string, got {value!r:.60}")
        return value
    raise TypeError(f"{where}: no check for {kind}")


INSTANCE = re.compile(r"[A-Za-z0-9][A-Za-z0-9_.-]{0,63}")
"""An instance name: one MQTT topic level and client id (no ``/``, ``+``, ``#``, spaces)."""


def _cross_checks(check: Checker, config: Config) -> None:
    if config.service.instance and not INSTANCE.fullmatch(config.service.instance):
        check.fail(
            "service.instance",
            "letters, digits, '_', '.', '-' (at most 64, one topic level), "
            f"got {config.service.instance!r:.70}",
        )
    for name in ("sources", "sinks"):
        if not getattr(config.service, name):
            check.fail(
                f"service.{name}", "must name at least one transport (a daemon without one does nothing)"
            )
    if (why := workers_reason(config.service.workers)) is not None:
        check.fail("service.workers", why)
    if config.metrics.stream_labels and config.service.max_streams > MAX_LABELLED_STREAMS:
        check.fail(
            "metrics.stream_labels",
            f"per-stream labels need service.max_streams <= {MAX_LABELLED_STREAMS}, "
            f"it is {config.service.max_streams}",
        )
    if config.mqtt.reconnect_min_s > config.mqtt.reconnect_max_s:
        check.fail("mqtt.reconnect_min_s", "must not exceed mqtt.reconnect_max_s")
    cluster = config.cluster
    try:
        parse_nats_urls(cluster.nats)
    except InputError as e:
        check.fail("cluster.nats", str(e))
    clustered = "cluster" in config.service.sources + config.service.sinks
    if (cluster.coordinator or clustered) and not re.fullmatch(r"etcd://[^/\s]+", cluster.coordinator):
        check.fail(
            "cluster.coordinator",
            f"must be etcd://HOST[:PORT][,HOST[:PORT]...], got {cluster.coordinator!r:.70}",
        )
    if cluster.coordinator:
        try:
            parse_etcd_urls(cluster.coordinator)
        except InputError as e:
            check.fail("cluster.coordinator", str(e))
    if cluster.member and not INSTANCE.fullmatch(cluster.member):
        check.fail(
            "cluster.member", f"letters, digits, '_', '.', '-' (at most 64), got {cluster.member!r:.70}"
        )
    used = config.service.sources + config.service.sinks
    if "zmq" in used:
        # checked here, not at bind: libzmq takes a port modulo 65536 (":99999" binds 34463)
        for name, wanted in (
            ("poses", "zmq" in config.service.sources),
            ("detections", "zmq" in config.service.sinks),
        ):
            if wanted:
                try:
                    check_zmq_endpoint(getattr(config.zmq, name))
                except InputError as e:
                    check.fail(f"zmq.{name}", str(e))
    if "mqtt" not in used:
        return
    try:
        parse_mqtt_url(config.mqtt.url)
    except InputError as e:
        check.fail("mqtt.url", str(e))
