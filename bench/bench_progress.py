"""What progress events cost the daemon (issue 24): the service's stream table with ``progress``
enabled against disabled, in the same run, on one core.

    python -m bench.bench_progress [--repeat 3] [--ticks 240] [--recordings 12] [--most 250]

For S streams of 120 Hz (stream k plays recording k mod R of ``--recordings`` spread over the
catalogue, channels, from a random frame, looping), two :class:`~daemon.service.streams.StreamTable`
of the shipped library, one with progress enabled (10 a second), are given the same poses; each tick
queues one pose of every stream and runs :meth:`StreamTable.tick` (the bank push and, enabled,
every stream's progress read and the events made into messages), then encodes every progress
message (what publishing it costs before a socket). 80 ticks of warm-up, then ``--ticks`` timed,
the two tables alternating which goes first tick by tick; median, p99 and mean ms per tick, the
ratio of the means enabled / disabled and the difference per stream and tick, each the median over
``--repeat`` runs; and the progress messages a second of the streams' time. Every stream starts at
sequence number 1, so all take their index frame (every 4th tick, when the DTW runs and progress
is read) on the same tick: the p99 is that tick's.
"""

from __future__ import annotations

import gc
import time

import numpy as np

from bench.common import arguments
from bench.machine import describe
from daemon.config import ProgressConfig, ServiceConfig
from daemon.library import Library, default_library_path, load_library
from daemon.recordings import read_recording
from daemon.service.streams import StreamTable
from protocols.messages import PoseMessage, ProgressMessage, SkeletonMessage, encode
from replay import Motion
from replay.catalog import CMU_SUBSTITUTES, recordings

SIZES = (1, 50, 100, 250)
WARM = 80


def run(
    library: Library, motions: list[tuple[str, Motion]], size: int, ticks: int, seed: int
) -> tuple[np.ndarray, np.ndarray, int]:
    """ms per tick (disabled, enabled) and the progress messages the enabled table gave."""
    rng = np.random.default_rng(seed)
    picks = [motions[k % len(motions)] for k in range(size)]
    starts = [int(rng.integers(len(m))) for _, m in picks]
    tables = [
        StreamTable(
            library,
            session="bench",
            service=ServiceConfig(queue_frames=1000, max_streams=10_000),
            progress=ProgressConfig(enabled=on),
        )
        for on in (False, True)
    ]
    for t in tables:
        for k, (asf, _) in enumerate(picks):
            t.skeleton(SkeletonMessage(f"s{k}", 120.0, asf=asf, angle_unit="rad"), 0.0)
    times = np.empty((2, ticks))
    messages = 0
    for tick in range(WARM + ticks):
        poses = [
            PoseMessage(f"s{k}", tick + 1, 1.0 + tick / 120, channels=m.channels[(starts[k] + tick) % len(m)])
            for k, (_, m) in enumerate(picks)
        ]
        for i in (0, 1) if tick % 2 else (1, 0):  # either goes first as often: no cache favours one
            table = tables[i]
            for p in poses:
                table.pose(p, 1.0 + tick / 120)
            began = time.perf_counter()
            emitted, _ = table.tick()
            for e in emitted:
                if isinstance(e.message, ProgressMessage):
                    encode(e.message)
                    messages += tick >= WARM
            if tick >= WARM:
                times[i, tick - WARM] = time.perf_counter() - began
        if tick == WARM - 1:
            gc.collect()
    return 1e3 * times[0], 1e3 * times[1], messages


def main() -> None:
    args = arguments(__doc__, ticks=240, recordings=12, most=250)
    print(describe())
    library = load_library(default_library_path())
    pairs = recordings(args.data, CMU_SUBSTITUTES)
    chosen = pairs[:: max(1, len(pairs) // args.recordings)][: args.recordings]
    motions = [(asf.read_text(), read_recording(asf, amc)) for asf, amc in chosen]
    print(
        f"pinned to one core; {len(library.classes)} classes, {len(motions)} recordings, {args.ticks} ticks "
        f"timed after {WARM}, medians of {args.repeat} runs; ms per tick (a tick is 8.33 ms)"
    )
    print(
        f"{'S':>5s} {'off med':>8s} {'off p99':>8s} {'off mean':>8s} {'on med':>8s} {'on p99':>8s}"
        f" {'on mean':>8s} {'mean ratio':>10s} {'us/stream/tick':>14s} {'events/s':>9s}"
    )
    for size in (s for s in SIZES if s <= args.most):
        rows = []
        for r in range(args.repeat):
            off, on, messages = run(library, motions, size, args.ticks, size + r)
            rows.append(
                (
                    float(np.median(off)),
                    float(np.percentile(off, 99)),
                    float(np.mean(off)),
                    float(np.median(on)),
                    float(np.percentile(on, 99)),
                    float(np.mean(on)),
                    messages / (args.ticks / 120),
                )
            )
        # the median over the repeats of each figure (neither side's best run picked)
        off_med, off_p99, off_mean, on_med, on_p99, on_mean, rate = (
            float(np.median([r[i] for r in rows])) for i in range(7)
        )
        print(
            f"{size:5d} {off_med:8.3f} {off_p99:8.3f} {off_mean:8.3f} {on_med:8.3f} {on_p99:8.3f} "
            f"{on_mean:8.3f} {on_mean / off_mean:9.2f}x {1e3 * (on_mean - off_mean) / size:14.2f} {rate:9.0f}"
        )


if __name__ == "__main__":
    main()
