"""What reading a partition on both paths costs a worker per message (``protocols/merge.py``).

    python -m bench.bench_merge [--messages 200000] [--streams 100]

Real poses (a CMU recording, as :mod:`bench.cluster_load` publishes them, 581 bytes each) of
``--streams`` streams, each message delivered twice as on a NATS cluster (the live copy first, then
the buffered one), through :class:`protocols.merge.Merge` with the keys the transport computes; and
three times, as a worker of a NATS cluster gets it (two live copies through
:class:`protocols.merge.Twice`, then the buffered one). Printed per message, beside a baseline
measured in the same run: decoding the pose's msgpack, which the service does once per pose
whatever the path. Not measured here: what the extra deliveries cost the servers and the worker's
readers (``protocols/deliveries.py``).
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Callable

import msgpack

from bench.cluster_load import streams
from bench.machine import describe
from protocols.deliveries import Delivery
from protocols.merge import Merge, Twice
from protocols.nats import HELD_MOST, HOLD_S, REMEMBER_S, TWIN_S, merge_key


def deliveries(n: int, k: int) -> list[Delivery]:
    """``n`` poses of ``k`` streams, round robin, as their partition's subscription delivers them."""
    sources = streams(min(k, 8))
    out = []
    for i in range(n):
        s = sources[i % len(sources)]
        _, payload = s.pose()
        stream = f"x{i % k}"
        out.append(Delivery(f"mocap.p.0.{stream}.pose".encode(), b"", None, payload))
    return out


def per_message(f: Callable[[], None], n: int, repeat: int = 3) -> float:
    """The best of ``repeat`` runs of ``f()`` in µs per message."""
    best = float("inf")
    for _ in range(repeat):
        started = time.perf_counter()
        f()
        best = min(best, time.perf_counter() - started)
    return best / n * 1e6


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--messages", type=int, default=200_000)
    parser.add_argument("--streams", type=int, default=100)
    args = parser.parse_args()
    ds = deliveries(args.messages, args.streams)
    print(describe())
    print(f"{len(ds)} poses of {args.streams} streams, {len(ds[0].data)} bytes each")

    def merged() -> None:
        merge: Merge[Delivery] = Merge(HOLD_S, REMEMBER_S, HELD_MOST)
        now = time.monotonic()
        merge.went_live(now)
        for seq, d in enumerate(ds, 1):
            key = merge_key(Delivery(d.subject, d.reply, d.headers, bytes(d.data)))  # a fresh copy's hash
            merge.push(key, d, now)
            merge.push(merge_key(Delivery(d.subject, d.reply, d.headers, bytes(d.data))), d, now, seq)
            if seq % 10_000 == 0:
                merge.release(now)

    def twinned() -> None:  # both live paths, then the merge (protocols.merge.Twice)
        twice = Twice(TWIN_S)
        merge: Merge[Delivery] = Merge(HOLD_S, REMEMBER_S, HELD_MOST)
        now = time.monotonic()
        merge.went_live(now)
        for seq, d in enumerate(ds, 1):
            for path in (0, 1):
                key = merge_key(Delivery(d.subject, d.reply, d.headers, bytes(d.data)))
                if twice.first(key, path, now):
                    merge.push(key, d, now)
            merge.push(merge_key(Delivery(d.subject, d.reply, d.headers, bytes(d.data))), d, now, seq)
            if seq % 10_000 == 0:
                merge.release(now)

    def copies() -> None:  # the two fresh copies alone, subtracted from the merge's figure
        for d in ds:
            Delivery(d.subject, d.reply, d.headers, bytes(d.data))
            Delivery(d.subject, d.reply, d.headers, bytes(d.data))

    def decoded() -> None:
        for d in ds:
            msgpack.unpackb(d.data)

    copies_us = per_message(copies, len(ds))  # two fresh copies a message
    merge_us = per_message(merged, len(ds)) - copies_us
    decode_us = per_message(decoded, len(ds))
    print(f"merge, both copies of a message: {merge_us:.2f} µs")
    twice_us = per_message(twinned, len(ds)) - 1.5 * copies_us
    print(f"with the second live path, all three copies: {twice_us:.2f} µs ({twice_us / decode_us:.2f}x)")
    ratio = merge_us / decode_us
    print(f"baseline, msgpack decode of the pose: {decode_us:.2f} µs (the merge {ratio:.2f} times that)")


if __name__ == "__main__":
    main()
