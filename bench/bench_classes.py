"""What a pose costs the live recogniser with 18, 180 and 1,000 classes, stream-wide against keyframes
first, in one run (issue 33: the yardstick for an engine whose cost follows candidates, not classes).

    python -m bench.bench_classes [--repeat 3] [--streams 100] [--ticks 600] [--big-frames 2000]
                                  [--big-ticks 300] [--most 1000]

Data: CMU 13_29 (``cmu/13/13.asf``, ``13_29.amc.gz`` under ``--data``; 4,592 frames of 120 Hz, the
mocap6 exercises), channels in. Libraries: the shipped one (``load_library(default_library_path())``,
18 classes) and its classes replicated under new names (``name#i``, :func:`replicated`) up to 180 and
1,000 classes (cycling through the 18: 1,000 is 55 copies and the first 10 classes once more), each
in two modes:

* *stream-wide*: every class with ``mode=dtw``;
* *keyframes first*: every class that has keyframes with ``mode=keyframes``, the others as they are
  (the output names the classes without keyframes, which stay stream-wide).

Per (mode, classes), pinned to one core; every library's plans are made first, untimed, then
``--repeat`` rounds in which every (mode, classes) takes its turn, so that a change in a shared
machine's load falls on all of them alike (on the 2-core development machine a run of the same
frames takes 9 or 16 µs a pose by the second, whatever else runs in the container):

* **One stream**: a :class:`Recognizer` (``for_skeleton``) and ``push(number, frame)`` of every frame
  of the recording, the pushes timed (not making the recogniser), µs per pose; per round as many runs
  as make :data:`ROUND_S` (at most :data:`MOST_RUNS`), after an untimed run over the first 240
  frames before the first round; the median of all runs. And the detections (the same with every
  class count: a copy's candidates tie with its original's, which wins).
* **Bank**: per round a fresh :class:`RecognizerBank` of ``--streams`` streams of the recording,
  stream k starting at frame k·N/S (so no two are in lock-step; looping, renumbered), 40 ticks of
  warm-up, then ``--ticks`` ticks timed, each one push of one frame of every stream (the frame lists
  made beforehand); µs per pose (the median of the rounds) and poses/s. Memory: the growth of the
  resident set from before the first round's bank is made (free heap handed back first) to after
  its warm-up, per stream.

With 1,000 classes a pose costs ~25x more, so one stream pushes only the first ``--big-frames``
frames and the bank times ``--big-ticks`` ticks; every ratio is against 18 classes of the same mode
measured on the same frames (so 18 classes are also measured on those: the pruned DTW's cost depends
on the motion), and keyframes first against stream-wide with the same classes on the same frames.

Candidates: the keyframe matches the keyframes-first classes' automata complete on the recording
(its index-rate codes as the live path makes them, :func:`daemon.recognizer.recording_stage`) per
minute of motion, and the frames inside their windows (:func:`daemon.recognizer.keyframe_windows`);
per library the DTW columns a minute stream-wide (one per template per index-rate frame) against
those keyframes first runs (a keyframes-first class's templates over its windows only).
"""

from __future__ import annotations

import gc
import os
import statistics
import sys
import time
from dataclasses import dataclass, field, replace

import numpy as np

from bench.common import arguments, shipped_library
from bench.machine import describe
from bench.processes import rss_kib
from daemon.bank import RecognizerBank
from daemon.library import DTW, GATED, ClassTemplate, Library
from daemon.recognizer import (
    Recognizer,
    completions,
    keyframe_windows,
    plans,
    recording_stage,
    window_extent,
)
from daemon.recordings import read_recording
from daemon.service.app import release_memory
from daemon.types import RecognitionSettings
from replay import Motion
from replay.kinematics import joint_positions

COUNTS = (18, 180, 1000)
BIG = 1000
"""From this many classes on, the shorter runs (``--big-frames``, ``--big-ticks``)."""
RATE = 120.0
WARM_FRAMES = 240
WARM_TICKS = 40
STREAM_WIDE = "stream-wide"
KEYFRAMES_FIRST = "keyframes first"
MODES = (STREAM_WIDE, KEYFRAMES_FIRST)
RECORDING = ("cmu/13/13.asf", "cmu/13/13_29.amc.gz")
ROUND_S = 0.2
"""Seconds of one stream's timed pushes a configuration takes at least in each round (more runs of
the cheap ones, so that a burst of another job on a shared core falls on fewer of them)."""
MOST_RUNS = 10


def replicated(library: Library, count: int) -> Library:
    """``count`` classes: the library's, then copies of them named ``name#1``, ``name#2``, ...
    (cycling through them in order, so the last copy may be partial)."""
    originals = list(library.classes.values())
    classes: dict[str, ClassTemplate] = {}
    for k in range(count):
        copy, cls = divmod(k, len(originals))
        c = originals[cls]
        name = c.name if copy == 0 else f"{c.name}#{copy}"
        classes[name] = replace(c, name=name)
    return Library(library.rate, classes)


def in_mode(library: Library, mode: str) -> Library:
    """``library`` with every class stream-wide, or every class that has keyframes gated by them."""
    if mode == STREAM_WIDE:
        return Library(library.rate, {n: replace(c, mode=DTW) for n, c in library.classes.items()})
    return Library(
        library.rate,
        {n: c if c.keyframes is None else replace(c, mode=GATED) for n, c in library.classes.items()},
    )


def gated(library: Library) -> int:
    return sum(c.mode == GATED for c in library.classes.values())


def templates(library: Library) -> int:
    return sum(len(c.members) for c in library.classes.values())


def one_stream(library: Library, motion: Motion, frames: int) -> tuple[float, int]:
    """Seconds pushing the first ``frames`` frames into a fresh recogniser, and its detections (the
    pushes' and the flush's)."""
    r = Recognizer.for_skeleton(library, motion.skeleton, RATE, session="bench")
    numbers, rows = motion.frames[:frames].tolist(), list(motion.channels[:frames])
    gc.collect()
    found = 0
    start = time.perf_counter()
    for number, row in zip(numbers, rows, strict=True):
        found += len(r.push(number, row))
    elapsed = time.perf_counter() - start
    return elapsed, found + len(r.flush())


Tick = list[tuple[str, int, np.ndarray]]


def bank_ticks(motion: Motion, streams: int, ticks: int) -> list[Tick]:
    """Every tick's frames: stream k plays the recording from frame k·N/S, looping, numbered from 1."""
    n = len(motion)
    offsets = [k * n // streams for k in range(streams)]
    names = [f"s{k}" for k in range(streams)]
    rows = motion.channels
    return [
        [(names[k], t + 1, rows[(offsets[k] + t) % n]) for k in range(streams)]
        for t in range(WARM_TICKS + ticks)
    ]


def bank(library: Library, motion: Motion, frames: list[Tick]) -> tuple[float, float]:
    """Seconds per pose of a fresh bank over the timed ticks of ``frames`` (after the warm-up), and
    the growth of the resident memory per stream in KiB from before the bank was made to after its
    warm-up."""
    streams = len(frames[0])
    gc.collect()
    release_memory()
    before = rss_kib(os.getpid())
    b = RecognizerBank(library)
    for name, _, _ in frames[0]:
        b.add(name, RATE, skeleton=motion.skeleton, session="bench")
    for tick in frames[:WARM_TICKS]:
        b.push(tick)
    kib = (rss_kib(os.getpid()) - before) / streams
    gc.collect()
    timed = frames[WARM_TICKS:]
    start = time.perf_counter()
    for tick in timed:
        b.push(tick)
    return (time.perf_counter() - start) / (len(timed) * streams), kib


@dataclass
class Config:
    """One measurement: a library in one mode, the frames one stream pushes and the bank's ticks, and
    what its runs measured."""

    mode: str
    classes: int
    library: Library
    frames: int
    ticks: list[Tick]
    stream_us: list[float] = field(default_factory=list)
    bank_us: list[float] = field(default_factory=list)
    detections: int = 0
    kib: float = 0.0


def measure(configs: list[Config], motion: Motion, rounds: int) -> None:
    """``rounds`` rounds in which every configuration takes its turn (so a change in a shared
    machine's load falls on all of them alike): each one's single stream, run as often as makes
    :data:`ROUND_S` (at most :data:`MOST_RUNS`), then each one's bank once."""
    for c in configs:
        one_stream(c.library, motion, min(WARM_FRAMES, c.frames))
    for r in range(rounds):
        for c in configs:
            spent, runs = 0.0, 0
            while runs < 1 or (spent < ROUND_S and runs < MOST_RUNS):
                elapsed, c.detections = one_stream(c.library, motion, c.frames)
                c.stream_us.append(1e6 * elapsed / c.frames)
                spent, runs = spent + elapsed, runs + 1
        for c in configs:
            seconds, grown = bank(c.library, motion, c.ticks)
            c.bank_us.append(1e6 * seconds)
            if r == 0:
                c.kib = grown
        print(f"  round {r + 1} of {rounds} done")
        sys.stdout.flush()


@dataclass(frozen=True)
class Row:
    mode: str
    classes: int
    gated: int
    frames: int
    stream_us: float
    detections: int
    ticks: int
    bank_us: float
    kib: float
    runs: int


def candidates(library: Library, motion: Motion, counts: list[int]) -> None:
    """The keyframe matches of the library's keyframes-first classes on ``motion`` per minute of
    motion and the frames inside their windows, and the DTW columns a minute of the replicated
    libraries: every template over every index-rate frame (stream-wide) and each keyframes-first
    class's templates over its windows only (what runs, replays of frames before a window opened
    included)."""
    codes, _ = recording_stage(joint_positions(motion), library, RATE)
    minutes = len(motion) / RATE / 60
    max_gap = RecognitionSettings().max_gap(library.rate)
    print(
        f"candidates, keyframes first, on 13_29 ({len(codes)} index-rate frames at {library.rate:g} Hz, "
        f"{minutes:.2f} min of motion):"
    )
    found: dict[str, tuple[int, int]] = {}
    for cls in library.classes.values():
        if cls.mode != GATED or cls.keyframes is None:
            continue
        matches = completions(cls.keyframes, library.rate, max_gap, codes)
        extent = window_extent(cls.keyframes, cls.hard.length, cls.slack, cls.extent)
        made = keyframe_windows(cls.keyframes, extent, library.rate, max_gap, matches)
        covered = np.zeros(len(codes), dtype=bool)
        for a, b, _, _ in made:
            covered[a : b + 1] = True
        inside = int(covered.sum())
        # the columns computed: a window that opens over frames the last one covered computes them again
        found[cls.name] = (len(matches), sum(min(b, len(codes) - 1) - a + 1 for a, b, _, _ in made))
        print(
            f"  {cls.name}: {len(matches)} keyframe matches ({len(matches) / minutes:.1f} a minute), "
            f"{inside} of {len(codes)} index-rate frames ({inside / len(codes):.0%}) inside a window"
        )
    print(
        f"  {'classes':>7s} {'gated':>5s} {'matches/min':>11s} {'DTW columns/min today':>22s} "
        f"{'keyframes first: DTW in windows':>32s}"
    )
    for count in counts:
        big = in_mode(replicated(library, count), KEYFRAMES_FIRST)
        raised, today, windowed = 0, 0, 0
        for name, cls in big.classes.items():
            width = len(cls.members)
            today += width * len(codes)
            if cls.mode == GATED:
                n, columns = found[name.split("#")[0]]
                raised += n
                windowed += width * columns
            else:
                windowed += width * len(codes)
        print(
            f"  {count:7,d} {gated(big):5d} {raised / minutes:11,.0f} {today / minutes:22,.0f} "
            f"{windowed / minutes:21,.0f} ({windowed / today:.2f})"
        )


def table(rows: list[Row]) -> None:
    base = {(r.mode, r.frames, r.ticks): r for r in rows if r.classes == COUNTS[0]}

    def first(mode: str, frames: int, ticks: int) -> Row:
        return base[(mode, frames, ticks)]

    print()
    print(
        f"{'mode':16s} {'classes':>7s} {'gated':>5s} {'frames':>6s} {'runs':>4s} {'1 stream':>9s} "
        f"{'x18':>6s} {'det':>4s} {'ticks':>5s} {'bank':>8s} {'x18':>6s} {'poses/s':>9s} {'KiB/stream':>10s}"
    )
    print(
        f"{'':16s} {'':>7s} {'':>5s} {'':>6s} {'':>4s} {'us/pose':>9s} {'':>6s} {'':>4s} {'':>5s} "
        f"{'us/pose':>8s}"
    )
    for r in rows:
        b = first(r.mode, r.frames, r.ticks)
        print(
            f"{r.mode:16s} {r.classes:7,d} {r.gated:5d} {r.frames:6d} {r.runs:4d} {r.stream_us:9.2f} "
            f"{r.stream_us / b.stream_us:5.1f}x {r.detections:4d} {r.ticks:5d} {r.bank_us:8.2f} "
            f"{r.bank_us / b.bank_us:5.1f}x {1e6 / r.bank_us:9,.0f} {r.kib:10,.0f}"
        )
    print()
    print("keyframes first / stream-wide, same classes and frames:")
    wide = {(r.classes, r.frames, r.ticks): r for r in rows if r.mode == STREAM_WIDE}
    for r in rows:
        if r.mode != KEYFRAMES_FIRST:
            continue
        w = wide[(r.classes, r.frames, r.ticks)]
        print(
            f"  {r.classes:5,d} classes ({r.frames} frames, {r.ticks} ticks): one stream "
            f"{r.stream_us / w.stream_us:.2f}, bank {r.bank_us / w.bank_us:.2f}"
        )


def main() -> None:
    args = arguments(__doc__, streams=100, ticks=600, most=1000, **{"big-frames": 2000, "big-ticks": 300})
    print(describe())
    shipped = shipped_library()
    asf, amc = (args.data / p for p in RECORDING)
    motion = read_recording(asf, amc)
    bare = [c.name for c in shipped.classes.values() if c.keyframes is None]
    print(
        f"pinned to one core; {amc.name}: {len(motion)} frames at {RATE:g} Hz; the shipped library: "
        f"{len(shipped.classes)} classes at {shipped.rate:g} Hz, {templates(shipped)} templates"
    )
    print(
        f"keyframes first: {len(shipped.classes) - len(bare)} of {len(shipped.classes)} classes, as the "
        f"library says; stream-wide there: {', '.join(bare)}"
    )
    counts = [c for c in COUNTS if c <= args.most]
    small = [c for c in counts if c < BIG]
    big = [c for c in counts if c >= BIG]
    print(
        f"one stream: every frame ({len(motion)}) with {'/'.join(map(str, small))} classes, "
        f"the first {args.big_frames} with {'/'.join(map(str, big)) or '-'} (and {counts[0]} on those); "
        f"bank: {args.streams} streams, {args.ticks} ticks timed ({args.big_ticks} with "
        f"{'/'.join(map(str, big)) or '-'}); {args.repeat} rounds"
    )
    sys.stdout.flush()
    ticks_of: dict[int, list[Tick]] = {}
    spans = [(c, len(motion), args.ticks) for c in small]
    if big:
        spans += [(c, min(args.big_frames, len(motion)), args.big_ticks) for c in [counts[0], *big]]
    configs: list[Config] = []
    start = time.perf_counter()
    for count, frames, ticks in spans:
        if ticks not in ticks_of:
            ticks_of[ticks] = bank_ticks(motion, args.streams, ticks)
        for mode in MODES:
            library = in_mode(replicated(shipped, count), mode)
            plans(library)
            configs.append(Config(mode, count, library, frames, ticks_of[ticks]))
    print(f"plans of the {len(configs)} libraries made in {time.perf_counter() - start:.1f} s")
    sys.stdout.flush()
    measure(configs, motion, args.repeat)
    rows = [
        Row(
            c.mode,
            c.classes,
            gated(c.library),
            c.frames,
            statistics.median(c.stream_us),
            c.detections,
            len(c.ticks) - WARM_TICKS,
            statistics.median(c.bank_us),
            c.kib,
            len(c.stream_us),
        )
        for c in configs
    ]
    table(rows)
    print()
    candidates(in_mode(shipped, KEYFRAMES_FIRST), motion, counts)


if __name__ == "__main__":
    main()
