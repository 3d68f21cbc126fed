"""How evenly the ring spreads partitions and streams over workers, and what a join or leave moves.

    python -m bench.bench_ring [--partitions 256] [--sets 30]

For 3 to 10 members, over ``--sets`` random sets of member names (a fixed seed):

- the partitions per member, least and most against the mean, with the ring
  (``daemon/cluster/ring.py``, bounded loads) and with plain rendezvous hashing for comparison;
- the partitions that move on a leave or a join besides the leaver's or joiner's own, as a share of
  those (mean and worst);
- the streams per member, for 10, 30, 100 and 300 streams per member (random stream ids hashed to
  partitions as nats-server does, ``protocols.nats.partition_of``): the busiest member's streams
  against the mean, median and worst over the sets, with the ring alone and evened out by the
  streams per partition (the leader's balance), and what evening out costs against the ring.
"""

from __future__ import annotations

import argparse
import random
import statistics
import time
from collections import Counter

from bench.machine import describe
from daemon.cluster.ring import assignment, score
from daemon.cluster.ring import loads as loads_of
from protocols.nats import partition_of

MEMBERS = range(3, 11)
STREAMS_PER_MEMBER = (10, 30, 100, 300)


def rendezvous(members: list[str], partitions: int) -> dict[str, set[int]]:
    """Plain rendezvous hashing: each partition to its highest-ranked member, no bound on loads."""
    out: dict[str, set[int]] = {m: set() for m in members}
    for p in range(partitions):
        out[max(members, key=lambda m: (score(m, p), m))].add(p)
    return out


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--partitions", type=int, default=256)
    parser.add_argument("--sets", type=int, default=30)
    args = parser.parse_args()
    print(describe())
    rng = random.Random(34)
    p = args.partitions
    print(f"partitions: {p}, sets of names: {args.sets}")
    print(
        f"{'members':>7} {'mean':>6} {'ring least-most':>16} {'rendezvous least-most':>22} "
        f"{'extra moves mean':>17} {'worst':>6}  busiest member's streams / mean, median (worst) "
        + " ".join(f"{s}/member" for s in STREAMS_PER_MEMBER)
        + "   evened out, worst: "
        + " ".join(f"{s}/member" for s in STREAMS_PER_MEMBER)
    )
    started = time.perf_counter()
    timing = [0.0, 0.0]  # evening out, the ring alone
    for n in MEMBERS:
        least = most = plain_least = plain_most = None
        extra: list[float] = []
        busiest: dict[int, list[float]] = {s: [] for s in STREAMS_PER_MEMBER}
        even: dict[int, list[float]] = {s: [] for s in STREAMS_PER_MEMBER}
        for _ in range(args.sets):
            names = [f"worker-{rng.getrandbits(40):010x}" for _ in range(n)]
            ring = assignment(names, p)
            loads = [len(v) for v in ring.values()]
            plain = [len(v) for v in rendezvous(names, p).values()]
            least = min(loads) if least is None else min(least, *loads)
            most = max(loads) if most is None else max(most, *loads)
            plain_least = min(plain) if plain_least is None else min(plain_least, *plain)
            plain_most = max(plain) if plain_most is None else max(plain_most, *plain)
            after = assignment(names[1:], p)
            extra.append(sum(len(ring[m] - after[m]) for m in names[1:]) / max(1, len(ring[names[0]])))
            joiner = f"worker-{rng.getrandbits(40):010x}"
            joined = assignment([*names, joiner], p)
            moved = sum(len(ring[m] - joined[m]) for m in names) - len(joined[joiner])
            extra.append(moved / max(1, len(joined[joiner])))
            for per in STREAMS_PER_MEMBER:
                weights = Counter(partition_of(f"s{rng.getrandbits(48):012x}", p) for _ in range(per * n))
                busiest[per].append(max(loads_of(ring, weights).values()) / per)
                t = time.perf_counter()
                evened = assignment(names, p, weights)
                timing[0] += time.perf_counter() - t
                t = time.perf_counter()
                assignment(names, p)
                timing[1] += time.perf_counter() - t
                even[per].append(max(loads_of(evened, weights).values()) / per)
        balance = " ".join(
            f"{statistics.median(b):.2f} ({max(b):.2f})".rjust(len(f"{s}/member")) for s, b in busiest.items()
        )
        evened_out = " ".join(f"{max(b):.2f}".rjust(len(f"{s}/member")) for s, b in even.items())
        print(
            f"{n:>7} {p / n:>6.1f} {f'{least}-{most}':>16} {f'{plain_least}-{plain_most}':>22} "
            f"{statistics.mean(extra):>17.0%} {max(extra):>6.0%}  {balance}   {evened_out}"
        )
    each = timing[0] * 1000 / (len(MEMBERS) * args.sets * len(STREAMS_PER_MEMBER))
    print(f"evening out: {timing[0] / timing[1]:.2f}x the ring's time ({each:.1f} ms an assignment)")
    print(f"took {time.perf_counter() - started:.1f} s")


if __name__ == "__main__":
    main()
