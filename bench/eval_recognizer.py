"""The live recogniser on people its templates never saw (leave one actor out).

    python -m bench.eval_recognizer [--data DIR] [--seed 0] [--blend-s 0.25] [--png DIR]

HDM05: for each of bd, bk, dg, the 11 classes are learned from the other two actors' clips as the
shipped library is learned (``mocapd learn``'s way, τ calibrated by leave-one-actor-out over those
two actors, published keyframes where they do better on those two actors' folds); the left-out
actor's clips are joined into one stream in random order, each clip moved on the floor to start where
the previous one ended, with ``--blend-s`` of linear blending of the joint angles between them, and
the stream is pushed frame by frame through a :class:`~daemon.recognizer.Recognizer`. A detection is
right when at least half of it lies inside a clip of its class; a clip is found when it holds a right
detection. CMU mocap6: the 7 exercise classes are learned from the single repetitions (cut as the
shipped library cuts them, the phase of each class taken from those two trials) of two of 13_29,
13_30, 14_14 and detected on the whole third trial; a labelled run is found when it holds a right
detection.

Each fold runs twice: with the calibrated τ per class and with the thesis' fixed τ = 0.1 (the same
templates and keyframes). Prints per-class precision and recall for both, and the latency from a
motion's labelled last frame to its first right detection (median and p95, ms), and from a
detection's own last frame to its emission. Nothing here tunes anything on the clips it reports.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import random
import sys
import time
from collections import defaultdict
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from bench.common import DATA
from bench.machine import describe
from bench.shipped_library import TAU, keyframe_choice, learn_all, with_keyframes
from daemon import mocap6
from daemon.keyframes import KeyframeQuery, parse_keyframe_queries
from daemon.library import Library
from daemon.recognizer import Detection, Recognizer
from daemon.recordings import Examples, TrainingClip, native_rate, read_example, read_recording
from daemon.shipped import CMU_CLASSES, HDM05_ACTORS, HDM05_CLASSES, Row, cmu_rows, hdm05_rows, training_items
from daemon.types import BoolArray, FloatArray
from replay import Motion

REPO = Path(__file__).resolve().parents[1]


@dataclass(frozen=True)
class Segment:
    """A labelled motion in a stream: class ``name`` over frames ``start`` .. ``end``."""

    name: str
    start: int
    end: int


def join(motions: Sequence[tuple[str, Motion]], blend: int) -> tuple[Motion, list[Segment]]:
    """One stream of ``motions`` (class, motion; one skeleton) in the given order, frames numbered
    from 1: each clip's root moved on the floor (x, z) to start where the previous one ended, and
    ``blend`` frames between two clips interpolating every channel linearly (angles the short way
    round). Returns the stream and each clip's segment in it."""
    skeleton = motions[0][1].skeleton
    names = skeleton.channel_names
    floor = [names.index("root.tx"), names.index("root.tz")]
    angles = np.array([n.split(".")[1].startswith("r") for n in names])
    parts: list[FloatArray] = []
    segments = []
    at = 1
    previous: FloatArray | None = None
    for name, m in motions:
        channels = np.array(m.channels, dtype=np.float64)
        if previous is not None:
            channels[:, floor] += previous[floor] - channels[0, floor]
            step = channels[0] - previous
            step[angles] = (step[angles] + math.pi) % (2 * math.pi) - math.pi
            k = np.arange(1, blend + 1)[:, None] / (blend + 1)
            parts.append(previous + k * step)
            at += blend
        parts.append(channels)
        segments.append(Segment(name, at, at + len(channels) - 1))
        at += len(channels)
        previous = channels[-1]
    stacked = np.concatenate(parts)
    first = motions[0][1]
    return Motion("joined", skeleton, first.header, np.arange(1, len(stacked) + 1), stacked), segments


def inside(d: Detection, s: Segment) -> bool:
    """At least half of ``d`` lies inside ``s``, and they are of one class."""
    shared = min(d.end_frame, s.end) - max(d.start_frame, s.start) + 1
    return d.class_name == s.name and 2 * shared >= d.end_frame - d.start_frame + 1


@dataclass
class Tally:
    """Per class: detections, right ones, motions, found ones; latencies in frames."""

    detections: int = 0
    right: int = 0
    motions: int = 0
    found: int = 0


def score(
    detections: Sequence[Detection], truth: Sequence[Segment], classes: Sequence[str]
) -> tuple[dict[str, Tally], list[int], list[int]]:
    """Per class tallies; the latencies (frames) from each found motion's last frame to its first
    right detection's emission, and from every detection's last frame to its emission."""
    tally = {c: Tally() for c in classes}
    for d in detections:
        tally[d.class_name].detections += 1
        tally[d.class_name].right += any(inside(d, s) for s in truth)
    to_motion = []
    for s in truth:
        if s.name not in tally:
            continue
        tally[s.name].motions += 1
        hits = [d for d in detections if inside(d, s)]
        if hits:
            tally[s.name].found += 1
            to_motion.append(min(d.emitted_at_frame for d in hits) - s.end)
    return tally, to_motion, [d.emitted_at_frame - d.end_frame for d in detections]


def run(library: Library, motion: Motion, rate: float) -> list[Detection]:
    recognizer = Recognizer.for_skeleton(library, motion.skeleton, rate, session="eval")
    out = [
        d for n, c in zip(motion.frames.tolist(), motion.channels, strict=True) for d in recognizer.push(n, c)
    ]
    return out + recognizer.flush()


def fixed_tau(library: Library, tau: float) -> Library:
    return Library(library.rate, {n: dataclasses.replace(c, tau=tau) for n, c in library.classes.items()})


def learn(examples: Examples, published: dict[str, KeyframeQuery]) -> Library:
    """The classes of ``examples`` learned as the shipped library is (:mod:`bench.shipped_library`):
    calibrated, with the published keyframes where they do better on the training folds."""
    learned = learn_all(examples, TAU, workers=2)
    return Library(30.0, with_keyframes(learned, published, keyframe_choice(examples, learned, published)))


def read_all(rows: Sequence[Row]) -> list[tuple[Row, TrainingClip, BoolArray]]:
    items = training_items(rows, REPO)
    out = []
    for i, (row, item) in enumerate(zip(rows, items, strict=True), start=1):
        clip, matrix = read_example(item, "eval", rate=30.0)
        out.append((row, clip, matrix))
        if i % 50 == 0 or i == len(rows):
            print(f"  [{i}/{len(rows)}] examples read", file=sys.stderr, flush=True)
    return out


def examples_of(
    read: Sequence[tuple[Row, TrainingClip, BoolArray]], group: Callable[[Row], str], left_out: str
) -> Examples:
    """The examples of every row whose ``group`` (its actor, its trial) is not ``left_out``."""
    out: Examples = defaultdict(list)
    for row, clip, matrix in read:
        if group(row) != left_out:
            out[row.name].append((clip, matrix))
    return dict(out)


def actor_of(row: Row) -> str:
    return row.actor


def trial_of(row: Row) -> str:
    return Path(row.amc).name.split(".")[0]


Totals = dict[str, dict[str, Tally]]


def add(totals: Totals, kind: str, tally: dict[str, Tally]) -> None:
    for name, t in tally.items():
        total = totals.setdefault(kind, {}).setdefault(name, Tally())
        total.detections += t.detections
        total.right += t.right
        total.motions += t.motions
        total.found += t.found


def table(title: str, totals: Totals, classes: Sequence[str]) -> None:
    print(f"\n{title}")
    print(f"{'class':<30} {'calibrated P':>12} {'R':>6} {'dets':>5}   {'tau 0.1 P':>9} {'R':>6} {'dets':>5}")
    for name in classes:
        cells = []
        for kind in ("calibrated", "tau 0.1"):
            t = totals[kind][name]
            p = t.right / t.detections if t.detections else float("nan")
            r = t.found / t.motions if t.motions else float("nan")
            cells.append(f"{p:>9.2f} {r:>6.2f} {t.detections:>5}")
        print(f"{name:<30} {cells[0]:>22}   {cells[1]}")


def percentiles(frames: Sequence[int], rate: float) -> str:
    if not frames:
        return "none"
    ms = np.asarray(frames, dtype=np.float64) / rate * 1000
    return f"median {np.median(ms):.0f} ms, p95 {np.percentile(ms, 95):.0f} ms (n = {len(ms)})"


def measure(
    library: Library,
    motion: Motion,
    rate: float,
    truth: Sequence[Segment],
    data: str,
    totals: dict[str, Totals],
    latency: dict[str, list[int]],
    to_motion: bool = True,
) -> None:
    """Run ``motion`` through ``library`` with its calibrated τ and with τ = 0.1; add the tallies to
    ``totals[data]`` and the latencies (frames; from a motion's end only with ``to_motion``)."""
    for kind, lib in (("calibrated", library), ("tau 0.1", fixed_tau(library, 0.1))):
        tally, motion_frames, detection_frames = score(run(lib, motion, rate), truth, list(lib.classes))
        add(totals[data], kind, tally)
        if to_motion:
            latency[f"{data} {kind} motion"] += motion_frames
        latency[f"{data} {kind} detection"] += detection_frames


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--data", type=Path, default=DATA)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--blend-s", type=float, default=0.25)
    args = parser.parse_args()
    print(describe())
    began = time.perf_counter()
    rng = random.Random(args.seed)
    totals: dict[str, Totals] = {"HDM05": {}, "CMU": {}}
    latency: dict[str, list[int]] = defaultdict(list)

    keyframes = args.data.parent.parent / "reference" / "manual-keyframes.json"
    published = parse_keyframe_queries(json.loads(keyframes.read_text(encoding="utf-8")), keyframes)
    print("HDM05 clips:", file=sys.stderr)
    hdm05 = read_all(hdm05_rows(args.data, REPO))
    for left_out in HDM05_ACTORS:
        started = time.perf_counter()
        library = learn(examples_of(hdm05, actor_of, left_out), published)
        clips = [
            (row.name, read_recording(REPO / row.asf, REPO / row.amc))
            for row, _, _ in hdm05
            if row.actor == left_out
        ]
        rng.shuffle(clips)
        rate = native_rate(clips[0][1])
        stream, truth = join(clips, round(args.blend_s * rate))
        measure(library, stream, rate, truth, "HDM05", totals, latency)
        print(
            f"HDM05 left out {left_out}: {len(clips)} clips, {len(stream)} frames, learned in "
            f"{time.perf_counter() - started:.0f} s",
            file=sys.stderr,
            flush=True,
        )

    segments = mocap6.read_segments(args.data / mocap6.SEGMENTS)
    for left_out in mocap6.TRIALS:
        started = time.perf_counter()
        # the training trials' repetitions, cut at phases found in those trials only
        print(f"CMU repetitions without {left_out}:", file=sys.stderr)
        training = [t for t in mocap6.TRIALS if t != left_out]
        cmu = read_all(cmu_rows(args.data, REPO, trials=training))
        library = learn(examples_of(cmu, trial_of, left_out), {})
        asf, amc = mocap6.trial_recording(args.data, left_out)
        motion = read_recording(asf, amc)
        rate = native_rate(motion)
        truth = [Segment(s.label, s.start_frame, s.end_frame) for s in segments if s.trial == left_out]
        # a labelled run holds many repetitions: its first detection comes long before its end
        measure(library, motion, rate, truth, "CMU", totals, latency, to_motion=False)
        print(
            f"CMU left out {left_out}: {len(library.classes)} classes learned in "
            f"{time.perf_counter() - started:.0f} s",
            file=sys.stderr,
            flush=True,
        )

    table(
        "HDM05, left-out actor's clips joined into one stream (precision, recall, detections)",
        totals["HDM05"],
        HDM05_CLASSES,
    )
    table(
        "CMU mocap6, left-out trial (precision, recall of labelled runs, detections)",
        totals["CMU"],
        CMU_CLASSES,
    )
    print("\nlatency at 120 Hz:")
    for key, frames in latency.items():
        print(f"  {key + ':':<32} {percentiles(frames, 120.0)}")
    print(f"\ntotal {time.perf_counter() - began:.0f} s")


if __name__ == "__main__":
    main()
