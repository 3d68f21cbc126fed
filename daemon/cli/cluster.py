"""``mocapd cluster status``: the live members of a cluster in etcd, the partitions the ring gives
each and those each reports it owns (disagreements flagged), streams per partition, lag and lease
left. ``mocapd cluster mappings``: the NATS server's subject mappings for ``cluster.partitions``."""

from __future__ import annotations

import argparse
import json
from typing import TYPE_CHECKING, Any

from daemon.config import ClusterConfig, Config
from daemon.errors import UsageError
from daemon.extras import require

if TYPE_CHECKING:  # the command imports etcd's client only when it runs
    from daemon.service.membership import ClusterStatus

DEFAULT_PARTITIONS = ClusterConfig().partitions
"""``--partitions`` when neither the option nor the configuration's ``cluster.partitions`` gives it."""


def _partition_count(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        value = 0
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be a whole number of partitions, 1 or more, got '{text}'")
    return value


def register(sub: Any) -> None:
    cluster = sub.add_parser("cluster", help="look at a cluster of workers (members in etcd)")
    cluster_sub = cluster.add_subparsers(required=True, metavar="{status,mappings}")
    status = cluster_sub.add_parser(
        "status",
        help="members, the partitions each owns by the ring and by its own report, streams, lag, lease left",
    )
    status.add_argument(
        "--coordinator",
        default=None,
        metavar="etcd://HOST:PORT",
        help="the cluster's etcd (default: the configuration's cluster.coordinator)",
    )
    _partitions_option(status)
    status.add_argument(
        "--prefix", default="/mocapd/", help="the cluster's key prefix in etcd (default /mocapd/)"
    )
    status.add_argument("--json", action="store_true", help="print one JSON object instead of text")
    status.set_defaults(func=_status)
    made = cluster_sub.add_parser(
        "mappings",
        help="print the NATS server's subject mappings for the partitions (deploy/nats/partitions.conf)",
    )
    _partitions_option(made)
    made.set_defaults(func=_mappings)


def _partitions_option(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--partitions",
        type=_partition_count,
        default=None,
        metavar="P",
        help=f"partitions of the streams (default: cluster.partitions, else {DEFAULT_PARTITIONS})",
    )


def _mappings(args: argparse.Namespace, config: Config) -> int:
    require("cluster", "mocapd cluster mappings")
    from protocols.nats import mappings

    print(mappings(args.partitions or _configured(config, "partitions") or DEFAULT_PARTITIONS), end="")
    return 0


def _configured(config: Config, name: str) -> Any:
    """``config.cluster.<name>`` where the configuration has a cluster section, else None."""
    return getattr(getattr(config, "cluster", None), name, None)


def _ints(value: Any) -> list[int] | None:
    if isinstance(value, list) and all(isinstance(v, int) and not isinstance(v, bool) for v in value):
        return sorted(value)
    return None


def _counts(value: Any) -> dict[int, int]:
    """The streams per partition of a report: ``{"3": 4}`` → ``{3: 4}``; what is not that, left out."""
    if not isinstance(value, dict):
        return {}
    return {
        int(k): c
        for k, c in value.items()
        if str(k).isdigit() and isinstance(c, int) and not isinstance(c, bool)
    }


def summary(status: ClusterStatus, partitions: int) -> dict[str, Any]:
    """The cluster as ``--json`` prints it: per member the ring's partitions and the reported ones,
    per partition its owner, who reports it and its streams, and the disagreements."""
    from daemon.cluster.ring import assignment

    ring = assignment(status.names, partitions, status.balance.weights)
    members: list[dict[str, Any]] = []
    reporters: dict[int, list[str]] = {p: [] for p in range(partitions)}
    streams: dict[int, int] = {}
    disagreements: list[str] = []
    for m in status.members:
        report = m.status or {}
        reported = _ints(report.get("partitions"))
        counts = _counts(report.get("streams"))
        for p, count in counts.items():
            streams[p] = streams.get(p, 0) + count
        expected = sorted(ring[m.name])
        if m.status is None:
            disagreements.append(f"{m.name} has not reported")
        elif reported is None:
            disagreements.append(f"{m.name} reports no list of partitions")
        elif reported != expected:
            disagreements.append(
                f"{m.name} reports owning {reported}, the ring over the live members "
                f"(with the balance) gives it {expected}"
            )
        for p in reported or ():
            if p in reporters:
                reporters[p].append(m.name)
            else:
                disagreements.append(f"{m.name} reports partition {p}, outside 0..{partitions - 1}")
        lag = report.get("lag_s")
        members.append(
            {
                "name": m.name,
                "lease_left_s": m.lease_left_s,
                "ring": expected,
                "reported": reported,
                "agrees": reported == expected,
                "streams": sum(counts.values()),
                "lag_s": lag if isinstance(lag, int | float) and not isinstance(lag, bool) else None,
                "status": m.status,
                "about": m.about,
            }
        )
    table = []
    for p in range(partitions):
        owner = next((name for name, ps in ring.items() if p in ps), None)
        if len(reporters[p]) > 1:
            disagreements.append(f"partition {p} is reported by {', '.join(reporters[p])}")
        table.append(
            {"partition": p, "owner": owner, "reported_by": reporters[p], "streams": streams.get(p, 0)}
        )
    return {
        "coordinator": status.coordinator,
        "prefix": status.prefix,
        "partitions": partitions,
        "balance": status.balance.generation,
        "members": members,
        "table": table,
        "disagreements": disagreements,
    }


def _numbers(ps: list[int] | None) -> str:
    return "-" if ps is None else " ".join(map(str, ps)) or "none"


def _status(args: argparse.Namespace, config: Config) -> int:
    require("cluster", "mocapd cluster status")
    from daemon.service.membership import read_cluster
    from protocols.transport import StartupError

    coordinator = args.coordinator or _configured(config, "coordinator")
    if not coordinator:
        raise UsageError("give --coordinator etcd://HOST:PORT (or cluster.coordinator in the configuration)")
    partitions = args.partitions or _configured(config, "partitions") or DEFAULT_PARTITIONS
    try:
        status = read_cluster(coordinator, args.prefix)
    except StartupError as exc:
        if args.coordinator:  # the option, not the configuration, named it
            raise UsageError(exc.reason, path="--coordinator") from None
        raise
    out = summary(status, partitions)
    if args.json:
        print(json.dumps(out))
        return 0
    print(f"cluster:    {coordinator} (prefix {args.prefix})")
    print(f"members:    {len(out['members'])}")
    print(f"partitions: {partitions}")
    print(f"balance:    generation {out['balance']}" + ("" if out["balance"] else " (the ring alone)"))
    if out["members"]:
        print()
        print(f"{'member':<16} {'lease left':>10} {'streams':>7} {'lag':>8}  partitions (ring / reported)")
        for m in out["members"]:
            lease = "-" if m["lease_left_s"] is None else f"{m['lease_left_s']} s"
            lag = "-" if m["lag_s"] is None else f"{m['lag_s']:.2f} s"
            mark = "" if m["agrees"] else "  DISAGREE"
            print(
                f"{m['name']:<16} {lease:>10} {m['streams']:>7} {lag:>8}  "
                f"{_numbers(m['ring'])} / {_numbers(m['reported'])}{mark}"
            )
        print()
        print(f"{'partition':>9} {'owner':<16} {'streams':>7}  reported by")
        for row in out["table"]:
            print(
                f"{row['partition']:>9} {row['owner'] or '-':<16} {row['streams']:>7}  "
                f"{', '.join(row['reported_by']) or '-'}"
            )
    if out["disagreements"]:
        print()
        for d in out["disagreements"]:
            print(f"disagreement: {d}")
    return 0
