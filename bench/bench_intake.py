"""The daemon's own Python per pose, in process, without a transport: a message's decoding
(:func:`protocols.messages.decode`), the stream table's intake (:meth:`StreamTable.pose` or
:meth:`StreamTable.frame`) and its tick (:meth:`StreamTable.tick`) beside the bank's push within it,
for S streams of real recordings (channels, as ``bench_service`` sends them), one pose message each
or frame messages of K subjects, a tick after each capture frame's messages.

    python -m bench.bench_intake [--streams 400] [--subjects-per-message 1,50] [--ticks 300]

Two tables run in turns on the same messages, block by block, each first in turn (this VM's
neighbours come and go, and whichever runs first after the messages are made pays for it):
the table as shipped, and one that queues every pose (the definition the direct intake is tested
against, ``tests/test_table_direct.py``); each figure the best of five blocks. CPU time
(``time.process_time``), µs per pose.
"""

from __future__ import annotations

import argparse
import gc
import time
from collections.abc import Sequence
from pathlib import Path

import msgpack
import numpy as np

from bench.bench_service import RATE
from bench.common import DATA, shipped_library
from bench.machine import describe
from daemon.bank import BankResult, Frame
from daemon.recordings import read_recording
from daemon.service.streams import StreamTable
from protocols.messages import VERSION, PoseMessage, SkeletonMessage, decode, encode
from replay.catalog import CMU_SUBSTITUTES, recordings

BLOCKS = 5


class Queueing(StreamTable):
    """Every pose through the queue (no direct intake)."""

    def _direct(self, name: str, s: object, epoch: str | None) -> bool:
        return False


def sources(count: int = 12) -> list[tuple[str, np.ndarray]]:
    """ASF text and channels ``(N, C)`` of ``count`` recordings, CMU 13_30 first (as bench_service)."""
    pairs = recordings(DATA, CMU_SUBSTITUTES)
    first = [p for p in pairs if Path(p[1]).name.startswith("13_30.")]
    chosen = first + [p for p in pairs[:: max(1, len(pairs) // count)] if p not in first][: count - 1]
    return [
        (Path(asf).read_text(), np.ascontiguousarray(read_recording(asf, amc).channels))
        for asf, amc in chosen
    ]


def messages(src: list[tuple[str, np.ndarray]], streams: int, per_message: int, tick: int) -> list[bytes]:
    """Capture frame ``tick`` of every stream, as pose messages or frame messages of ``per_message``."""
    names = [f"s{k}" for k in range(streams)]
    rows = [src[k % len(src)][1][(97 * k + tick) % len(src[k % len(src)][1])] for k in range(streams)]
    if per_message == 1:
        stamp = 1.0 + tick / RATE
        return [encode(PoseMessage(n, tick + 1, stamp, channels=r)) for n, r in zip(names, rows, strict=True)]
    out = []
    for g in range(0, streams, per_message):
        members = range(g, min(g + per_message, streams))
        body = {
            "v": VERSION,
            "type": "frame",
            "source": f"g{g}",
            "streams": [names[k] for k in members],
            "seq": np.full(len(members), tick + 1, "<u8").tobytes(),
            "time": np.full(len(members), 1.0 + tick / RATE, "<f8").tobytes(),
            "counts": np.array([len(rows[k]) for k in members], "<u4").tobytes(),
            "channels": np.concatenate([rows[k] for k in members]).tobytes(),
        }
        out.append(msgpack.packb(body))
    return out


class Run:
    """One table fed tick by tick, its CPU split by stage."""

    def __init__(self, kind: type[StreamTable], src: list[tuple[str, np.ndarray]], streams: int) -> None:
        self.table = kind(shipped_library(), session="bench")
        for k in range(streams):
            message = SkeletonMessage(f"s{k}", RATE, asf=src[k % len(src)][0], angle_unit="rad")
            self.table.skeleton(message, 0.0)
        self.bank_s = 0.0
        push = self.table.bank.push

        def timed(frames: Sequence[Frame]) -> BankResult:
            started = time.process_time()
            try:
                return push(frames)
            finally:
                self.bank_s += time.process_time() - started

        self.table.bank.push = timed  # type: ignore[method-assign]

    def step(self, payloads: list[bytes], now: float) -> tuple[float, float, float]:
        """Decode, intake, tick (bank included) of one capture frame's messages: CPU seconds each."""
        a = time.process_time()
        decoded = [decode(p) for p in payloads]
        b = time.process_time()
        t = self.table
        for m in decoded:
            if isinstance(m, PoseMessage):
                t.pose(m, now)
            else:
                t.frame(m, now)  # type: ignore[arg-type]
        c = time.process_time()
        while t.queued:
            t.tick()
        return b - a, c - b, time.process_time() - c


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--streams", type=int, default=400)
    parser.add_argument("--subjects-per-message", default="1,50")
    parser.add_argument("--ticks", type=int, default=300, help="capture frames a block")
    args = parser.parse_args()
    print(describe())
    src = sources()
    print(
        f"{args.streams} streams of 12 recordings (channels); "
        f"{BLOCKS} blocks of {args.ticks} capture frames a table"
    )
    print(
        f"{'K':>3s} {'table':>9s} {'decode':>7s} {'intake':>7s} {'tick':>7s} {'bank':>7s} {'all':>7s}"
        "  µs/pose"
    )
    for k in [int(x) for x in args.subjects_per_message.split(",")]:
        runs = {"shipped": Run(StreamTable, src, args.streams), "queueing": Run(Queueing, src, args.streams)}
        best: dict[str, list[float]] = {}
        for block in range(BLOCKS + 1):  # the first a warm-up
            payloads = [messages(src, args.streams, k, block * args.ticks + t) for t in range(args.ticks)]
            order = list(runs.items())
            for name, run in order if block % 2 else order[::-1]:  # each first in turn
                gc.collect()
                run.bank_s = 0.0
                spent = np.zeros(3)
                for t, tick in enumerate(payloads):
                    spent += run.step(tick, (block * args.ticks + t) / RATE)
                figures = [*spent, run.bank_s]
                per = [1e6 * x / (args.streams * args.ticks) for x in figures]
                per[2] -= per[3]  # the tick less the bank's push
                if block and (name not in best or sum(per) < sum(best[name])):
                    best[name] = per
        for name, per in best.items():
            decode_us, intake_us, tick_us, bank_us = per
            print(
                f"{k:3d} {name:>9s} {decode_us:7.2f} {intake_us:7.2f} {tick_us:7.2f} {bank_us:7.2f} "
                f"{sum(per):7.2f}"
            )
        shipped, queueing = best["shipped"], best["queueing"]
        around = sum(shipped) - shipped[3], sum(queueing) - queueing[3]
        print(
            f"    the Python around the bank: {around[0]:.2f} against {around[1]:.2f} µs "
            f"({around[0] / around[1]:.2f}x)"
        )


if __name__ == "__main__":
    main()
