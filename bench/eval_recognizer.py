"""The user's path on people the templates never saw: ``mocapd learn`` with its defaults, then the
live recogniser over the left-out people's motions (issue 20).

    python -m bench.eval_recognizer [--data DIR] [--seed 0] [--blend-s 0.25] [--workers 2]
                                    [--only hdm05,cmu,one] [--keep DIR] [--keyframes FILE]

Every fold writes a training manifest (class, asf, amc, start_frame, end_frame, actor) and runs
``mocapd learn --manifest M --out LIB`` in a process of its own, with no other option: no published
keyframes anywhere, τ, templates and keyframe gates as ``learn`` chooses them. The left-out people's
motions then go frame by frame through the :class:`~daemon.recognizer.Recognizer` that ``mocapd
detect`` runs (the configuration's defaults). With ``--keyframes FILE`` (e.g. the thesis' hand-made
ones, ``../shared/reference/manual-keyframes.json``) ``mocapd learn`` gets ``--keyframes`` with the
file's keyframes of the fold's classes instead of learning them: what the same engine does with
keyframes known to hold, to hold a default run's learned ones against.

* **HDM05**, for each of bd, bk, dg: learned from the other two actors' cut clips of the 11 classes;
  the left-out actor's clips joined into one stream in random order (each clip moved on the floor
  to start where the previous one ended, ``--blend-s`` of linear blending of all channels between
  clips). A detection is right when at least half of it lies inside a clip of its class; a clip is
  found when it holds a right detection.
* **CMU mocap6**, for each of 13_29, 13_30, 14_14: learned from the single repetitions (cut as the
  shipped library cuts them, from the training trials alone) of the other two trials; detected on
  the whole left-out trial; a labelled run is found when it holds a right detection (a class the
  training trials lack is not counted).
* **One actor** (``one``), the case users meet first: HDM05 learned from one actor and detected on
  each of the two others; CMU learned from subject 13 (13_29, 13_30) and detected on 14_14, and
  from subject 14 and detected on 13_29 and 13_30.

Printed: per class precision and recall (detections), pooled; every missed motion explained (no
match within τ, with the best cost; no keyframe window around it; beaten by another class's cheaper match;
the motion already taken by a detection); how each class is recognised in each fold's library and,
for gated classes, the share of the left-out motions a keyframe match overlapped, the share of other
classes' motion frames inside one of its windows and the keyframe matches completed inside other
classes' motions per minute of them; the latency from
a motion's last frame to its first right detection and from a detection's last frame to its
emission (median and p95, at 120 Hz). Nothing here tunes anything on the motions it reports.
"""

from __future__ import annotations

import argparse
import csv
import dataclasses
import json
import math
import os
import random
import subprocess
import sys
import tempfile
import time
from collections import Counter, defaultdict
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from bench.common import DATA
from bench.machine import describe
from daemon.dtw import local_minima, pack, retrieval_tables, subsequence_codes, to_cost
from daemon.features import sampled_features
from daemon.frames import FrameClock
from daemon.library import DTW, GATED, ClassTemplate, Library, load_library
from daemon.recognizer import (
    Detection,
    Recognizer,
    completions,
    keyframe_windows,
    same_motion,
    window_extent,
)
from daemon.recordings import native_rate, read_recording
from daemon.templates import expand
from daemon.tools import mocap6
from daemon.tools.shipped import COLUMNS, HDM05_ACTORS, HDM05_CLASSES, Row, cmu_rows, hdm05_rows
from daemon.types import FloatArray, RecognitionSettings
from replay import JOINT_NAMES, Motion
from replay.kinematics import joint_positions

REPO = Path(__file__).resolve().parents[1]


@dataclass(frozen=True)
class Segment:
    """A labelled motion in a stream: class ``name`` over frames ``start`` .. ``end``."""

    name: str
    start: int
    end: int


@dataclass(frozen=True)
class Stream:
    """One left-out stream: its motion, rate and labelled motions."""

    name: str
    motion: Motion
    rate: float
    truth: tuple[Segment, ...]


@dataclass(frozen=True)
class Fold:
    """What one ``mocapd learn`` learns from (``rows``) and the streams it is measured on."""

    kind: str
    name: str
    rows: tuple[Row, ...]
    streams: tuple[Stream, ...]


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


def inside(start: int, end: int, name: str, s: Segment) -> bool:
    """At least half of ``start .. end`` lies inside ``s``, and they are of one class."""
    shared = min(end, s.end) - max(start, s.start) + 1
    return name == s.name and 2 * shared >= end - start + 1


# ------------------------------------------------------------------------------------ the folds


def hdm05_folds(data: Path, rng: random.Random, blend_s: float, one: bool) -> list[Fold]:
    rows = hdm05_rows(data, REPO)
    motions = {r.amc: read_recording(REPO / r.asf, REPO / r.amc) for r in rows}
    streams = {}
    for actor in HDM05_ACTORS:
        clips = [(r.name, motions[r.amc]) for r in rows if r.actor == actor]
        rng.shuffle(clips)
        rate = native_rate(clips[0][1])
        motion, truth = join(clips, round(blend_s * rate))
        streams[actor] = Stream(f"HDM05 {actor}", motion, rate, tuple(truth))
    if one:
        return [
            Fold("HDM05 one actor", f"learned from {a}", tuple(r for r in rows if r.actor == a),
                 tuple(streams[b] for b in HDM05_ACTORS if b != a))
            for a in HDM05_ACTORS
        ]  # fmt: skip
    return [
        Fold("HDM05", f"without {a}", tuple(r for r in rows if r.actor != a), (streams[a],))
        for a in HDM05_ACTORS
    ]


def cmu_stream(data: Path, trial: str) -> Stream:
    segments = mocap6.read_segments(data / mocap6.SEGMENTS)
    asf, amc = mocap6.trial_recording(data, trial)
    motion = read_recording(asf, amc)
    truth = tuple(Segment(s.label, s.start_frame, s.end_frame) for s in segments if s.trial == trial)
    return Stream(f"CMU {trial}", motion, native_rate(motion), truth)


def cmu_folds(data: Path, one: bool) -> list[Fold]:
    if one:
        subjects = {"13": ("13_29", "13_30"), "14": ("14_14",)}
        return [
            Fold("CMU one actor", f"learned from subject {s}", tuple(cmu_rows(data, REPO, trials=trials)),
                 tuple(cmu_stream(data, t) for t in mocap6.TRIALS if t not in trials))
            for s, trials in subjects.items()
        ]  # fmt: skip
    out = []
    for trial in mocap6.TRIALS:
        training = [t for t in mocap6.TRIALS if t != trial]
        rows = tuple(cmu_rows(data, REPO, trials=training))  # cut from the training trials alone
        out.append(Fold("CMU", f"without {trial}", rows, (cmu_stream(data, trial),)))
    return out


def learn(fold: Fold, where: Path, keyframes: Path | None = None) -> tuple[Library, float]:
    """``mocapd learn`` with its defaults on the fold's rows, in a process of its own; with
    ``keyframes`` (a file as manual-keyframes.json), those of the fold's classes given to it."""
    where.mkdir(parents=True, exist_ok=True)
    given: list[str] = []
    if keyframes is not None:
        published = json.loads(keyframes.read_text(encoding="utf-8"))
        names = {r.name for r in fold.rows}
        published["classes"] = {n: k for n, k in published["classes"].items() if n in names}
        lengths = published.get("template_length", {})
        published["template_length"] = {n: v for n, v in lengths.items() if n in names}
        if published["classes"]:
            (where / "keyframes.json").write_text(json.dumps(published), encoding="utf-8")
            given = ["--keyframes", str(where / "keyframes.json")]
    manifest = where / "training.csv"
    with manifest.open("w", newline="", encoding="utf-8") as out:
        w = csv.writer(out)
        w.writerow(COLUMNS)
        for r in fold.rows:
            cells = list(r.cells())
            cells[1], cells[2] = str((REPO / r.asf).resolve()), str((REPO / r.amc).resolve())
            w.writerow(cells)
    library = where / "library"
    began = time.perf_counter()
    done = subprocess.run(
        [sys.executable, "-m", "daemon", "learn", "--manifest", str(manifest), "--out", str(library), *given],
        capture_output=True,
        text=True,
        check=False,
    )
    if done.returncode != 0:
        raise RuntimeError(f"mocapd learn failed for {fold.kind} {fold.name}:\n{done.stderr[-2000:]}")
    (where / "learn.log").write_text(done.stdout + done.stderr, encoding="utf-8")
    return load_library(library), time.perf_counter() - began


def recognise(library: Library, s: Stream) -> list[Detection]:
    """What ``mocapd detect`` prints for the stream, with the configuration's defaults."""
    r = Recognizer.for_skeleton(library, s.motion.skeleton, s.rate, stream=s.name, session="eval")
    out = [d for n, c in zip(s.motion.frames.tolist(), s.motion.channels, strict=True) for d in r.push(n, c)]
    return out + r.flush()


# ------------------------------------------------------------------------------------ the scores


@dataclass
class Tally:
    detections: int = 0
    right: int = 0
    motions: int = 0
    found: int = 0
    gate_opened: int = 0
    gated: int = 0
    other_frames: int = 0
    other_covered: int = 0
    other_matches: int = 0
    other_s: float = 0.0
    misses: Counter[str] = field(default_factory=Counter)


@dataclass
class Results:
    tallies: dict[str, dict[str, Tally]] = field(default_factory=dict)
    latency: dict[str, list[int]] = field(default_factory=lambda: defaultdict(list))
    modes: dict[str, dict[str, list[str]]] = field(default_factory=dict)
    learn_s: list[float] = field(default_factory=list)

    def tally(self, kind: str, name: str) -> Tally:
        return self.tallies.setdefault(kind, {}).setdefault(name, Tally())


def why_missed(library: Library, s: Stream, seg: Segment, detections: Sequence[Detection]) -> str:
    """Why a motion of a class holds no right detection, read from the class's stream-wide DTW (the
    batch twin's features)."""
    clock = FrameClock.of(s.rate, library.rate)
    first = int(s.motion.frames[0])
    codes = pack(sampled_features(joint_positions(s.motion), JOINT_NAMES, s.rate, clock.step))
    lo, hi = clock.index(first, seg.start), clock.index(first, seg.end)
    cls = library.classes[seg.name]
    best = math.inf
    mine = []
    for template, tau in cls.members:
        t = expand(template)
        delta, start = subsequence_codes(retrieval_tables(t.values, t.weights), codes, None, cls.steps)
        cost = to_cost(delta)
        for e in range(lo, min(hi + 1, len(cost))):
            if 2 * (min(e, hi) - max(int(start[e]), lo) + 1) >= e - int(start[e]) + 1:
                best = min(best, float(cost[e]))
        mine += [
            (m, tau)
            for m in local_minima(cost, start, tau)
            if 2 * (min(m.end, hi) - max(m.start, lo) + 1) >= m.end - m.start + 1
        ]
    if not mine:
        return f"no match within tau (best {best:.3f} vs {cls.tau:.3f})"
    if cls.mode == GATED:
        assert cls.keyframes is not None
        spans, _ = class_windows(cls, library.rate, codes.tolist())
        if not any(a <= m.start and m.end <= b for m, _ in mine for a, b in spans):
            return "no keyframe window around it"
    for d in detections:
        a, b = clock.index(first, d.start_frame), clock.index(first, d.end_frame)
        if any(same_motion((m.start, m.end), (a, b)) and d.cost < m.cost for m, _ in mine):
            return (
                f"beaten by {d.class_name}" if d.class_name != seg.name else "taken by a detection across it"
            )
    return "beaten by a match that was not published"


def class_windows(
    cls: ClassTemplate, rate: float, codes: list[int]
) -> tuple[list[tuple[int, int]], list[tuple[int, int]]]:
    """The windows keyframe-first class ``cls`` opens over index-rate ``codes`` (first, last frame),
    and its keyframe matches there (:func:`completions`)."""
    assert cls.keyframes is not None
    max_gap = RecognitionSettings().max_gap(rate)
    found = completions(cls.keyframes, rate, max_gap, codes)
    extent = window_extent(cls.keyframes, cls.hard.length, cls.slack, cls.extent)
    made = keyframe_windows(cls.keyframes, extent, rate, max_gap, found)
    return [(a, b) for a, b, _, _ in made], found


def stream_wide(library: Library) -> Library:
    """The same library with every class recognised by the stream-wide DTW alone."""
    return Library(library.rate, {n: dataclasses.replace(c, mode=DTW) for n, c in library.classes.items()})


def measure(library: Library, fold: Fold, results: Results, kind: str) -> None:
    for s in fold.streams:
        detections = recognise(library, s)
        for d in detections:
            t = results.tally(kind, d.class_name)
            t.detections += 1
            t.right += any(inside(d.start_frame, d.end_frame, d.class_name, seg) for seg in s.truth)
        clock = FrameClock.of(s.rate, library.rate)
        first = int(s.motion.frames[0])
        codes = pack(sampled_features(joint_positions(s.motion), JOINT_NAMES, s.rate, clock.step)).tolist()
        segments = [(seg, clock.index(first, seg.start), clock.index(first, seg.end)) for seg in s.truth]
        for seg in s.truth:
            if seg.name not in library.classes:
                continue
            t = results.tally(kind, seg.name)
            t.motions += 1
            hits = [d for d in detections if inside(d.start_frame, d.end_frame, d.class_name, seg)]
            if hits:
                t.found += 1
                if kind.startswith("HDM05"):  # a run of repetitions is found long before its end
                    results.latency[f"{kind} motion"].append(min(d.emitted_at_frame for d in hits) - seg.end)
            else:
                t.misses[why_missed(library, s, seg, detections)] += 1
        for name, cls in library.classes.items():
            if cls.mode != GATED:
                continue
            assert cls.keyframes is not None
            spans, found = class_windows(cls, library.rate, codes)
            completed = [j for _, j in found]
            inside_gate = np.zeros(len(codes), dtype=bool)
            for a, b in spans:
                inside_gate[a : b + 1] = True
            t = results.tally(kind, name)
            for seg, lo, hi in segments:
                if seg.name == name:
                    t.gated += 1
                    t.gate_opened += any(a <= hi and lo <= b for a, b in spans)
                else:
                    t.other_frames += hi - lo + 1
                    t.other_covered += int(inside_gate[lo : hi + 1].sum())
                    t.other_matches += sum(lo <= j <= hi for j in completed)
                    t.other_s += (hi - lo + 1) / library.rate
        results.latency[f"{kind} detection"] += [d.emitted_at_frame - d.end_frame for d in detections]
    for name, cls in library.classes.items():
        results.modes.setdefault(kind, {}).setdefault(name, []).append(
            f"{cls.mode}{'' if len(cls.members) == 1 else f' x{len(cls.members)}'}"
        )


def table(kind: str, results: Results, classes: Sequence[str]) -> None:
    tallies = results.tallies.get(kind, {})
    print(f"\n{kind}: precision / recall (detections), how each class is recognised in each fold")
    print(f"{'class':30s} {'P':>5s} {'R':>5s} {'right/dets':>11s} {'found/motions':>14s}  modes")
    total = Tally()
    for name in classes:
        t = tallies.get(name)
        if t is None or (t.motions == 0 and t.detections == 0):
            continue
        p = t.right / t.detections if t.detections else math.nan
        r = t.found / t.motions if t.motions else math.nan
        modes = ", ".join(results.modes.get(kind, {}).get(name, []))
        print(
            f"{name:30s} {p:5.2f} {r:5.2f} {t.right:5d}/{t.detections:<5d} "
            f"{t.found:6d}/{t.motions:<7d}  {modes}"
        )
        total.detections += t.detections
        total.right += t.right
        total.motions += t.motions
        total.found += t.found
    p = total.right / total.detections if total.detections else math.nan
    r = total.found / total.motions if total.motions else math.nan
    print(
        f"{'pooled':30s} {p:5.2f} {r:5.2f} {total.right:5d}/{total.detections:<5d} "
        f"{total.found:6d}/{total.motions:<7d}"
    )
    gated = [(n, t) for n, t in tallies.items() if t.gated]
    if gated:
        print("  keyframes first, left-out motions a window overlapped: " + ", ".join(
            f"{n} {t.gate_opened}/{t.gated}" for n, t in gated))  # fmt: skip
        print("  keyframes first, share of other classes' motion frames inside a window: " + ", ".join(
            f"{n} {t.other_covered / t.other_frames:.1%}" for n, t in gated if t.other_frames))  # fmt: skip
        print("  keyframes first, matches completed in other classes' motions a minute of them: " + ", ".join(
            f"{n} {t.other_matches / (t.other_s / 60):.1f}" for n, t in gated if t.other_s))  # fmt: skip
    misses = [(n, t.misses) for n, t in tallies.items() if t.misses]
    for n, m in misses:
        print(f"  missed {n}: " + "; ".join(f"{c} x {why}" for why, c in m.most_common()))


def percentiles(frames: Sequence[int], rate: float) -> str:
    if not frames:
        return "none"
    ms = np.asarray(frames, dtype=np.float64) / rate * 1000
    return f"median {np.median(ms):.0f} ms, p95 {np.percentile(ms, 95):.0f} ms (n = {len(ms)})"


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--data", type=Path, default=DATA)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--blend-s", type=float, default=0.25)
    parser.add_argument(
        "--workers", type=int, default=os.cpu_count() or 1, help="learn this many folds at once"
    )
    parser.add_argument("--only", default="hdm05,cmu,one", help="which of hdm05, cmu, one to run")
    parser.add_argument(
        "--keep", type=Path, default=None, help="keep each fold's manifest, library and log here"
    )
    parser.add_argument(
        "--keyframes",
        type=Path,
        default=None,
        help="give mocapd learn these keyframes (a file as manual-keyframes.json) for the classes it names",
    )
    args = parser.parse_args()
    print(describe())
    if args.keyframes is not None:
        print(f"keyframes given to mocapd learn: {args.keyframes} (for the classes it names)")
    began = time.perf_counter()
    only = set(args.only.split(","))
    rng = random.Random(args.seed)
    folds: list[Fold] = []
    if "hdm05" in only:
        folds += hdm05_folds(args.data, rng, args.blend_s, one=False)
    if "cmu" in only:
        folds += cmu_folds(args.data, one=False)
    if "one" in only:
        folds += hdm05_folds(args.data, random.Random(args.seed), args.blend_s, one=True)
        folds += cmu_folds(args.data, one=True)
    results = Results()
    with tempfile.TemporaryDirectory() as tmp:
        root = args.keep or Path(tmp)

        def run(i: int) -> tuple[Library, float]:
            f = folds[i]
            return learn(f, root / f"{i:02d} {f.kind} {f.name}".replace(" ", "_"), args.keyframes)

        with ThreadPoolExecutor(max(1, args.workers)) as pool:
            for f, (library, seconds) in zip(folds, pool.map(run, range(len(folds))), strict=True):
                print(f"{f.kind} {f.name}: learned in {seconds:.0f} s", file=sys.stderr, flush=True)
                results.learn_s.append(seconds)
                measure(library, f, results, f.kind)
                measure(stream_wide(library), f, results, f"{f.kind} stream-wide")
    classes = [*HDM05_CLASSES, *mocap6.CLASSES]
    for kind in ("HDM05", "CMU", "HDM05 one actor", "CMU one actor"):
        for mode in ("", " stream-wide"):
            if kind + mode in results.tallies:
                table(kind + mode, results, classes)
    print("\nlatency at 120 Hz:")
    for key, frames in results.latency.items():
        print(f"  {key + ':':<32} {percentiles(frames, 120.0)}")
    print(
        f"\nmocapd learn: {len(results.learn_s)} runs, "
        f"{min(results.learn_s):.0f}-{max(results.learn_s):.0f} s each"
    )
    print(f"total {time.perf_counter() - began:.0f} s")


if __name__ == "__main__":
    main()
