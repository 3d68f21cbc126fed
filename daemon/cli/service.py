"""``mocapd run`` (the daemon) and ``mocapd replay`` (a recording onto the bus as a live stream)."""

from __future__ import annotations

import argparse
import dataclasses
import re
import signal
from pathlib import Path
from typing import TYPE_CHECKING, Any

from daemon.cli import _terminate, common
from daemon.cli.detect import speed
from daemon.config import Config, workers_of, workers_reason
from daemon.errors import InputError, UsageError
from daemon.extras import require
from daemon.library import default_library_path, load_library
from daemon.recordings import native_rate, read_recording
from protocols.messages import Up
from protocols.publish import BvhChannels, Positions, Recording
from protocols.urls import parse_nats_urls
from replay.bvh import hierarchy_text
from replay.joints import JOINT_NAMES
from replay.rigs import read_bvh_take

if TYPE_CHECKING:
    from daemon.service.replay import Tasks


def register(sub: Any) -> None:
    run = sub.add_parser("run", help="the daemon: recognise motions on every stream of the bus")
    run.add_argument(
        "--config",
        type=Path,
        default=argparse.SUPPRESS,  # ``mocapd --config C run`` sets it too
        help="config.yaml to read (as mocapd --config C run)",
    )
    run.add_argument(
        "--mqtt",
        default=None,
        metavar="mqtt://HOST:PORT",
        help="use this MQTT broker as the only source and sink (overrides service.sources/sinks, mqtt.url)",
    )
    run.add_argument(
        "--cluster",
        default=None,
        metavar="nats://HOST:PORT",
        help="cluster mode: a worker on this NATS server, the only source and sink (docs/cluster.md)",
    )
    run.add_argument(
        "--coordinator",
        default=None,
        metavar="etcd://HOST:PORT",
        help="cluster mode: the etcd holding the membership (cluster.coordinator)",
    )
    run.add_argument(
        "--metrics-port", type=int, default=None, metavar="N", help="port of /healthz and /metrics (0: off)"
    )
    run.add_argument(
        "--library", type=Path, default=None, help="template library directory (default: the shipped one)"
    )
    run.add_argument(
        "--replay",
        nargs=2,
        type=Path,
        default=None,
        metavar=("ASF", "AMC"),
        help="also replay this recording into the daemon over its first source, and stop when it ends",
    )
    run.add_argument(
        "--speed", type=speed, default=1.0, metavar="1|X|max", help="--replay's pace (default 1)"
    )
    run.add_argument("--stream", default=None, help="--replay's stream id (default: the AMC file's name)")
    run.add_argument(
        "--workers",
        type=int,
        default=None,
        metavar="N",
        help="recognition processes, a stream always on the same one (default: service.workers, "
        "whose 0 is one per core); 1: one process (as --replay always is)",
    )
    run.add_argument(
        "--progress",
        action="store_true",
        default=None,
        help="publish progress events on mocap/<stream>/progress (progress.enabled)",
    )
    run.set_defaults(func=_run)

    rep = sub.add_parser(
        "replay", help="publish a recording onto the bus as a live stream, paced by the clock"
    )
    common.recording_options(rep, bvh=True)
    rep.add_argument(
        "--to",
        required=True,
        metavar="URL",
        help="zmq+tcp://HOST:PORT (the daemon's poses socket) or mqtt://HOST:PORT (a broker)",
    )
    rep.add_argument("--stream", default=None, help="stream id (default: the AMC file's name)")
    rep.add_argument(
        "--speed", type=speed, default=1.0, metavar="1|X|max", help="1 = real time (default), X times, max"
    )
    rep.add_argument(
        "--with",
        dest="others",
        nargs=2,
        action="append",
        default=[],
        type=Path,
        metavar=("ASF", "AMC"),
        help="another recording, sent with the first as one source: each step's poses in one frame "
        "message (protocols/README.md, frame); its stream is the AMC file's name; repeatable",
    )
    rep.add_argument(
        "--source",
        default="replay",
        help="with --with: the source id of the frame messages (mocap/<source>/frame; default replay)",
    )
    rep.add_argument("--loop", action="store_true", help="start over at the end, until interrupted")
    rep.add_argument(
        "--no-retain",
        dest="retain",
        action="store_false",
        help="MQTT: the skeleton and the end at QoS 0, not retained (for a NATS cluster's MQTT port)",
    )
    rep.set_defaults(func=_replay)


def _replay(args: argparse.Namespace, config: Config) -> int:
    from daemon.service.app import configure_logging
    from protocols.messages import ID_RULE, is_id
    from protocols.replay import TargetError, replay

    configure_logging(config.logging.level)  # the MQTT client's log lines as JSON, like the daemon's
    bvh = common.bvh_or_asf(args)
    motion: Recording
    if bvh is not None:  # frames from 1
        take = read_bvh_take(bvh, common.rig_maps(args, config))
        rate, asf_text = take.rate, ""
        if args.rig is None:  # as it is: the daemon maps the rig as detect does
            up: Up = "z" if take.up == "z" else "y"
            motion = BvhChannels(hierarchy_text(take.motion.hierarchy), take.frames, take.motion.channels, up)
        else:  # a user's rig map, which the daemon does not know: its standard joints
            motion = Positions(take.frames, take.joints, JOINT_NAMES)
    else:
        motion = read_recording(args.asf, args.amc)
        rate = native_rate(motion, common.default_native_rate(args, config))
        asf_text = Path(args.asf).read_text(encoding="utf-8", errors="replace")
    source = bvh or args.amc
    stream = common.stream_name(source) if args.stream is None else args.stream
    if not is_id(stream):  # the recording's name, unless given
        raise UsageError(f"{stream!r} is not a stream id ({ID_RULE})", field="--stream")
    others = _others(args, config, rate, stream)
    try:
        sent = replay(
            args.to,
            motion,
            asf_text,
            stream=stream,
            rate=rate,
            speed=args.speed,
            loop=args.loop,
            retain=args.retain,
            others=others,
            source=args.source,
        )
    except TargetError as e:
        raise UsageError(e.reason, field="--to") from None
    except InputError as e:  # an MQTT URL protocols.urls.parse_mqtt_url refuses
        raise UsageError(str(e), field="--to") from None
    except TimeoutError:
        raise UsageError(
            f"nothing answered at {args.to} (is the daemon or broker running?)", field="--to"
        ) from None
    names = "".join(f", {name!r}" for _, _, name in others)
    print(f"replayed {sent} frames of {source.name} as stream {stream!r}{names} to {args.to}")
    return 0


def _others(
    args: argparse.Namespace, config: Config, rate: float, stream: str
) -> list[tuple[Recording, str, str]]:
    """``replay --with``'s recordings as (recording, ASF text, stream), each at ``rate`` and named
    apart from ``stream`` and each other; UsageError naming ``--with`` or ``--source`` otherwise."""
    from protocols.messages import ID_RULE, is_id

    if not args.others:
        return []
    if not is_id(args.source):
        raise UsageError(f"{args.source!r} is not a source id ({ID_RULE})", field="--source")
    out: list[tuple[Recording, str, str]] = []
    names = {stream}
    for asf, amc in args.others:
        motion = read_recording(asf, amc)
        other = native_rate(motion, common.default_native_rate(args, config))
        name = common.stream_name(amc)
        if other != rate:
            raise UsageError(
                f"{amc.name} is at {other:g} Hz, the first recording at {rate:g}", field="--with"
            )
        if name in names or not is_id(name):
            raise UsageError(f"{amc.name}: stream {name!r} is taken or not an id ({ID_RULE})", field="--with")
        names.add(name)
        out.append((motion, Path(asf).read_text(encoding="utf-8", errors="replace"), name))
    return out


def _run(args: argparse.Namespace, config: Config) -> int:
    """The daemon. SIGHUP is taken as SIGTERM from here on (unless it is ignored, as under
    ``nohup``): before the daemon serves it stops the command ("terminated", 143), then the
    daemon drains and exits 0 (``daemon.service.app.STOP_SIGNALS``)."""
    hangup = signal.getsignal(signal.SIGHUP)
    if hangup != signal.SIG_IGN:
        signal.signal(signal.SIGHUP, _terminate)
    try:
        return _serve(args, config)
    finally:
        signal.signal(signal.SIGHUP, signal.SIG_DFL if hangup is None else hangup)


def _serve(args: argparse.Namespace, config: Config) -> int:
    from daemon.cli import package_version
    from daemon.service.app import serve

    config = _overridden(args, config)
    library = load_library(default_library_path() if args.library is None else args.library)
    clustered = "cluster" in config.service.sources + config.service.sinks
    if clustered:
        require("cluster", "cluster mode", "--cluster" if args.cluster is not None else "service.sources")
    if clustered and config.service.workers > 1:
        raise UsageError(
            "a cluster worker is one recognition process: start one worker per core "
            "(deploy/systemd/mocapd-worker@.service) instead",
            field="--workers" if args.workers is not None else "service.workers",
        )
    # a cluster worker is one process (the cluster shares the streams between workers)
    workers = 1 if args.replay is not None or clustered else workers_of(config.service)
    if workers > 1:
        from daemon.service.workers import serve_workers

        return serve_workers(config, library, workers, version=package_version())
    extra = None if args.replay is None else _replay_into(args, config)
    return serve(config, library, version=package_version(), extra=extra)


def _replay_into(args: argparse.Namespace, config: Config) -> Tasks:
    """``run --replay``'s task: once the daemon serves, the recording into its first source; when
    every pose sent has been received and recognised, the stop."""
    from daemon.service.replay import replay_then_stop

    asf, amc = args.replay
    motion = read_recording(asf, amc)
    rate = native_rate(motion, config.replay.frame_rate_hz)
    asf_text = asf.read_text(encoding="utf-8", errors="replace")
    stream = common.stream_name(amc) if args.stream is None else args.stream
    return replay_then_stop(_own_source(config), motion, asf_text, stream=stream, rate=rate, speed=args.speed)


def _overridden(args: argparse.Namespace, config: Config) -> Config:
    service, metrics, mqtt, cluster = config.service, config.metrics, config.mqtt, config.cluster
    progress = config.progress
    if args.progress:
        progress = dataclasses.replace(progress, enabled=True)
    if args.cluster is not None or args.coordinator is not None:
        if args.mqtt is not None:
            raise UsageError("--mqtt and --cluster exclude each other", field="--cluster")
        if args.cluster is not None:
            try:
                parse_nats_urls(args.cluster)
            except InputError as e:
                raise UsageError(e.reason, field="--cluster") from None
            cluster = dataclasses.replace(cluster, nats=args.cluster)
        if args.coordinator is not None:
            if not re.fullmatch(r"etcd://[^/\s]+", args.coordinator):
                raise UsageError(
                    f"must be etcd://HOST[:PORT], got {args.coordinator!r}", field="--coordinator"
                )
            cluster = dataclasses.replace(cluster, coordinator=args.coordinator)
        if not cluster.coordinator:
            raise UsageError(
                "give --coordinator etcd://HOST[:PORT] (or cluster.coordinator in the configuration)",
                field="--coordinator",
            )
        service = dataclasses.replace(service, sources=("cluster",), sinks=("cluster",))
    if args.mqtt is not None:
        from protocols.urls import parse_mqtt_url

        try:
            parse_mqtt_url(args.mqtt)
        except InputError as e:
            raise UsageError(str(e), field="--mqtt") from None
        service = dataclasses.replace(service, sources=("mqtt",), sinks=("mqtt",))
        mqtt = dataclasses.replace(mqtt, url=args.mqtt)
    if args.metrics_port is not None:
        if not 0 <= args.metrics_port <= 65535:
            raise UsageError(f"must be a port in 0..65535, got {args.metrics_port}", field="--metrics-port")
        metrics = dataclasses.replace(metrics, port=args.metrics_port)
    if args.workers is not None:
        if (why := workers_reason(args.workers)) is not None:
            raise UsageError(why, field="--workers")
        service = dataclasses.replace(service, workers=args.workers)
    return dataclasses.replace(
        config, service=service, metrics=metrics, mqtt=mqtt, cluster=cluster, progress=progress
    )


def _own_source(config: Config) -> str:
    """Where ``run --replay`` sends: the daemon's first source, as a replay URL."""
    first = config.service.sources[0]
    if first == "mqtt":
        return config.mqtt.url
    if first != "zmq":  # a transport mocapd replay does not speak
        raise UsageError(f"replays over zmq or mqtt, and the first source is {first}", field="--replay")
    from protocols.urls import FREE_PORTS, split_endpoint, tcp_address

    endpoint, _ = split_endpoint(config.zmq.poses)
    address = tcp_address(endpoint)
    if address is not None and address[1] in FREE_PORTS:
        raise UsageError(f"replays into zmq.poses, which binds any free port ({endpoint})", field="--replay")
    return "zmq+" + endpoint.replace("://*:", "://127.0.0.1:").replace("://0.0.0.0:", "://127.0.0.1:")
