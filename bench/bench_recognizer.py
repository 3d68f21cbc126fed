"""The live recogniser on one core: one stream through :class:`Recognizer`, and many streams of 120 Hz
through :class:`RecognizerBank` against one :class:`Recognizer` per stream in the same run.

    python -m bench.bench_recognizer [--repeat 3] [--ticks 240] [--recordings 24] [--most 400]

Library: the shipped one (``load_library(default_library_path())``). Data: ``--recordings`` AMC
files of ../shared/data/mocap evenly spaced in the catalogue (CMU and HDM05; joint positions for the
positions-in figure computed beforehand, not timed).

One stream: every frame of those recordings pushed one by one (channels in, then positions in),
frames/s, best of ``--repeat``; and what a stream joining costs (a recogniser made for a new
skeleton, or from one made before: :meth:`Recognizer.fresh`), in ms and in frames of one stream.

Bank: for S streams (1, 10, 50, 100, 200, 250, 300, 400 up to ``--most``), stream k plays
recording k mod R (channels) from a random frame (looping, renumbered) and joins at a random tick of
the first 40 (so the streams' decimation phases differ, as they do live); 80 ticks of warm-up, then
``--ticks`` ticks timed, each tick one frame of every stream in one push (one compiled call,
:func:`daemon._live.push_many`). Time per tick: median and p99 in ms; the same S as one recogniser
per stream on the same frames (each pushed alone, the same compiled step over one frame) is the
baseline. A tick is 8.33 ms at 120 Hz; the aim is p99 <= 2 ms at 250 streams.

The floor: the arithmetic operations one 120 Hz pose needs at the least (:func:`floor_ops`: forward
kinematics of the recordings' skeletons, the cosines and sines of the half angles at an assumed
:data:`SINCOS_OPS` each, the feature program's instructions, its velocity points and comparisons,
every template's DTW cells at the library's rate shared among the ``step`` poses per index frame
at :data:`CELL_OPS` each; the keyframe automata's few bit tests are left out) at two per cycle (this
core's two scalar floating-point pipes, no FMA) at the clock /proc/cpuinfo reports; each bank row
prints its median per pose and its ratio to that.
"""

from __future__ import annotations

import gc
import sys
import time
from collections.abc import Callable

import numpy as np

from bench.common import arguments, best_of, shipped_library
from bench.machine import describe
from daemon.bank import RecognizerBank
from daemon.features.compiler import compiled
from daemon.library import Library
from daemon.recognizer import Recognizer, plans
from daemon.recordings import read_recording
from replay import JOINT_NAMES, Motion
from replay.catalog import CMU_SUBSTITUTES, recordings
from replay.kinematics import joint_positions

SIZES = (1, 10, 50, 100, 200, 250, 300, 400)
WARM = 80
JOIN = 40
BUDGET_MS = 2.0
SINCOS_OPS = 20
"""Operations counted for one cosine or sine (range reduction and a polynomial)."""
CELL_OPS = 8
"""Operations of one DTW cell: its cost (xor, and, popcount, table index and read), the three
predecessors' minimum (two comparisons), the add and the threshold test."""


def floor_ops(library: Library, motions: list[Motion]) -> tuple[float, dict[str, float]]:
    """The arithmetic operations of one 120 Hz pose at the least, in total and by part (the mean over
    ``motions``' skeletons for forward kinematics)."""
    fk, trig = [], []
    for m in motions:
        s = m.skeleton
        rotations = [c for c in s.channel_names if ".r" in c]
        rotated = len({c.split(".")[0] for c in rotations})
        nodes, channels = len(s.node_names), len(s.channel_names)
        # half angles; a node's first dof 3 products, each further one 3 + a quaternion product (28);
        # the root's orientation (28); per child node its global rotation (28), the rotated offset
        # (12 + 21) ; the root's translation; the scale to centimetres
        fk.append(
            channels
            + 3 * rotated
            + 31 * (len(rotations) - rotated)
            + 28
            + 61 * (nodes - 1)
            + (channels - len(rotations))
            + 3 * nodes
        )
        trig.append(2 * channels * SINCOS_OPS)
    program = compiled(JOINT_NAMES, 120.0).bytecode
    # the program's instructions, each velocity point's difference, window sum and scale, and a
    # comparison per feature and track
    features = (program.registers - program.n_rows - program.n_points) + 3 * program.n_points + 2 * 39
    cells = sum(m.length for p in plans(library) for m in p.members)
    step = round(120.0 / library.rate)
    parts = {
        "kinematics": float(np.mean(fk)),
        "cos/sin": float(np.mean(trig)),
        "features": float(features),
        "DTW": CELL_OPS * cells / step,
    }
    return sum(parts.values()), parts


def clock_ghz() -> float:
    """The core's clock from /proc/cpuinfo (0: unknown)."""
    try:
        with open("/proc/cpuinfo", encoding="utf-8") as f:
            for line in f:
                if line.startswith("cpu MHz"):
                    return float(line.split(":", 1)[1]) / 1e3
    except (OSError, ValueError):
        pass
    return 0.0


def one_stream(library: Library, motions: list[Motion], positions: list[np.ndarray], repeat: int) -> None:
    frames = sum(len(m) for m in motions)

    def channels_in() -> None:
        for m in motions:
            r = Recognizer.for_skeleton(library, m.skeleton, 120.0, session="bench")
            for number, row in zip(m.frames.tolist(), m.channels, strict=True):
                r.push(number, row)
            r.flush()

    def positions_in() -> None:
        for m, p in zip(motions, positions, strict=True):
            r = Recognizer.for_positions(library, JOINT_NAMES, 120.0, session="bench")
            for number, pose in zip(m.frames.tolist(), p, strict=True):
                r.push(number, pose)
            r.flush()

    print(f"one stream, {len(library.classes)} classes, {frames} frames:")
    rates = {}
    for name, run in (("channels in", channels_in), ("positions in", positions_in)):
        rate = rates[name] = frames / best_of(repeat, run)
        print(f"  {name:14s} {rate:10,.0f} frames/s  ({1e6 / rate:.0f} us/frame)")
    joins = 200
    skeleton = motions[0].skeleton
    made = Recognizer.for_skeleton(library, skeleton, 120.0, session="bench")

    def new_skeleton() -> None:
        for _ in range(joins):
            Recognizer.for_skeleton(library, skeleton, 120.0, session="bench")

    def known_skeleton() -> None:  # a stream joining with a skeleton seen before
        for _ in range(joins):
            made.fresh()

    for name, run in (("a new skeleton", new_skeleton), ("a known one", known_skeleton)):
        seconds = best_of(repeat, run) / joins
        print(
            f"  a stream joining, {name + ':':15s} {seconds * 1e3:.2f} ms "
            f"(= {seconds * rates['channels in']:.0f} frames of one stream)"
        )


def tick_times(step: Callable[[int], object], ticks: int) -> np.ndarray:
    """ms per call of ``step(tick)`` over the timed ticks (after the warm-up)."""
    for t in range(WARM):
        step(t)
    gc.collect()
    out = np.empty(ticks)
    for t in range(ticks):
        start = time.perf_counter()
        step(WARM + t)
        out[t] = time.perf_counter() - start
    return 1e3 * out


def one_size(
    library: Library, motions: list[Motion], size: int, ticks: int, seed: int
) -> tuple[np.ndarray, np.ndarray]:
    """ms per tick of ``size`` streams: through one bank, and through one recogniser per stream."""
    rng = np.random.default_rng(seed)
    picks = [motions[k % len(motions)] for k in range(size)]
    starts = [int(rng.integers(len(m))) for m in picks]
    joins = [int(rng.integers(JOIN)) for _ in range(size)]
    names = [f"s{k}" for k in range(size)]

    rows = [m.channels for m in picks]
    lengths = [len(m) for m in picks]
    bank = RecognizerBank(library)
    added: list[int] = []

    def bank_step(t: int) -> None:
        for k in range(size):
            if joins[k] == t:
                bank.add(names[k], 120.0, skeleton=picks[k].skeleton, session="bench")
                added.append(k)
        bank.push(
            [(names[k], t - joins[k] + 1, rows[k][(starts[k] + t - joins[k]) % lengths[k]]) for k in added]
        )

    recognizers: dict[int, Recognizer] = {}

    def baseline_step(t: int) -> None:
        for k in range(size):
            if joins[k] == t:
                recognizers[k] = Recognizer.for_skeleton(library, picks[k].skeleton, 120.0, session="bench")
        for k, r in recognizers.items():
            r.push(t - joins[k] + 1, rows[k][(starts[k] + t - joins[k]) % lengths[k]])

    return tick_times(bank_step, ticks), tick_times(baseline_step, ticks)


def many_streams(library: Library, motions: list[Motion], sizes: list[int], ticks: int) -> None:
    ops, parts = floor_ops(library, motions)
    ghz = clock_ghz()
    floor_us = ops / (2 * ghz * 1e3) if ghz else 0.0
    print(
        f"floor per pose: {ops:,.0f} operations ("
        + ", ".join(f"{k} {v:,.0f}" for k, v in parts.items())
        + f"), {floor_us:.2f} us at 2 per cycle at {ghz:.2f} GHz"
    )
    print(
        f"many streams of 120 Hz, {len(library.classes)} classes, {len(motions)} recordings, "
        f"{ticks} ticks timed after {WARM} (ms per tick; a tick is 8.33 ms):"
    )
    print(
        f"{'S':>5s} {'bank med':>9s} {'bank p99':>9s} {'per-stream med':>15s} {'p99':>8s} "
        f"{'med ratio':>10s} {'bank frames/s':>14s} {'us/pose':>8s} {'x floor':>8s}"
    )
    best, best_pose = 0, 0.0
    for size in sizes:
        banked, alone = one_size(library, motions, size, ticks, size)
        b_med, b_p99 = float(np.median(banked)), float(np.percentile(banked, 99))
        a_med, a_p99 = float(np.median(alone)), float(np.percentile(alone, 99))
        pose_us = 1e3 * b_med / size
        print(
            f"{size:5d} {b_med:9.2f} {b_p99:9.2f} {a_med:15.2f} {a_p99:8.2f} {a_med / b_med:9.1f}x "
            f"{size / (b_med / 1e3):14,.0f} {pose_us:8.2f} "
            + (f"{pose_us / floor_us:7.1f}x" if floor_us else "       -")
        )
        if b_p99 <= BUDGET_MS and size > best:
            best, best_pose = size, pose_us
        sys.stdout.flush()
    print(f"largest S with bank p99 <= {BUDGET_MS:g} ms: {best if best else 'none'} (of {sizes})")
    if best and floor_us:
        ratio = best_pose / floor_us
        print(f"there, per pose {best_pose:.2f} us = {ratio:.1f} x the floor ({floor_us:.2f} us)")


def main() -> None:
    args = arguments(__doc__, ticks=240, recordings=24, most=400)
    print(describe())
    library = shipped_library()
    pairs = recordings(args.data, CMU_SUBSTITUTES)
    chosen = pairs[:: max(1, len(pairs) // args.recordings)][: args.recordings]
    motions = [read_recording(asf, amc) for asf, amc in chosen]
    positions = [joint_positions(m) for m in motions]
    print(
        f"pinned to one core; recordings: {len(motions)} of {len(pairs)}, every {len(pairs) // len(chosen)}th"
    )
    one_stream(library, motions, positions, args.repeat)
    many_streams(library, motions, [s for s in SIZES if s <= args.most], args.ticks)


if __name__ == "__main__":
    main()
