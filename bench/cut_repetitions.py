"""Single repetitions of the mocap6 exercise classes in CMU 13_29, 13_30 and 14_14 (14_14 read with
13.asf: there is no 14.asf), cut by :mod:`daemon.tools.repetitions`.

    python -m bench.cut_repetitions OUT_DIR [--data DIR] [--rate 30]

Prints one line per trial and class (runs, repetitions found, period in seconds, confidence, the
repetitions' lengths, or why a run gave none) and writes, into OUT_DIR, ``<trial>.repetitions.png``
(features, joint heights and the shoulders' heading over time, labelled runs shaded, cuts as red lines) and
``mocap6_repetitions.csv``, a ``mocapd learn`` manifest of the repetitions (``class, asf, amc,
start_frame, end_frame, actor``; paths relative to OUT_DIR).
"""

from __future__ import annotations

import argparse
import os
import time
from collections import defaultdict
from pathlib import Path

import numpy as np

from bench.common import DATA
from daemon.plots import repetitions_png
from daemon.tools.mocap6 import (
    SEGMENTS,
    TRIALS,
    RepetitionRow,
    cut_trials,
    read_segments,
    repetition_rows,
    rows_csv,
    trial_recording,
)
from replay import JOINT_NAMES
from replay.kinematics import joint_positions

CURVES = ("lwrist", "rwrist", "lknee", "rknee", "headtop")


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("out", type=Path, help="directory for the PNGs and the manifest (created)")
    parser.add_argument("--data", type=Path, default=DATA)
    parser.add_argument("--rate", type=float, default=30.0, help="Hz to cut at (divides 120)")
    args = parser.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    segments = read_segments(args.data / SEGMENTS)
    rows: list[RepetitionRow] = []
    print(
        f"{'trial':6} {'class':16} {'runs':>4} {'reps':>4} {'period s':>8} {'conf':>5}"
        "  repetition lengths in s"
    )
    start = time.perf_counter()
    for motion, cuts in cut_trials(args.data, segments, TRIALS, rate=args.rate):
        trial = cuts.trial
        asf, amc = trial_recording(args.data, trial)
        by_class = defaultdict(list)
        for run in cuts.runs:
            by_class[run.segment.label].append(run)
        for label, runs in by_class.items():
            for run in runs:
                c = run.cutting
                lengths = " ".join(f"{r.length / c.rate:.2f}" for r in c.repetitions)
                period = f"{c.period_seconds:8.2f}" if c.period.samples else f"{'-':>8}"
                print(
                    f"{trial:6} {label:16} {len(runs):4d} {len(c.repetitions):4d} {period} "
                    f"{c.period.confidence:5.2f}  {lengths or c.reason}"
                )
        elapsed = time.perf_counter() - start
        rel = [os.path.relpath(p, args.out) for p in (asf, amc)]
        rows += repetition_rows(cuts, rel[0], rel[1])
        joints = joint_positions(motion)[:: cuts.features.step]
        heights = {
            f"{name} height - root (cm)": joints[:, JOINT_NAMES.index(name), 1] - joints[:, 0, 1]
            for name in CURVES
        }
        shoulders = joints[:, JOINT_NAMES.index("lshoulder")] - joints[:, JOINT_NAMES.index("rshoulder")]
        heading = np.degrees(np.unwrap(np.arctan2(shoulders[:, 2], shoulders[:, 0])))
        heights["shoulder-line heading (deg, minus its median)"] = heading - np.median(heading)
        png = args.out / f"{trial}.repetitions.png"
        skeleton = " (skeleton 13.asf: there is no 14.asf)" if trial.startswith("14_") else ""
        repetitions_png(
            cuts.features.matrix,
            cuts.features.frames,
            cuts.features.rate,
            heights,
            [(r.segment.start_frame, r.segment.end_frame, r.segment.label) for r in cuts.runs],
            [f for r in cuts.runs for f in r.cut_frames(cuts.features)],
            png,
            f"CMU {trial}{skeleton}: mocap6 runs and repetition cuts at {cuts.features.rate:g} Hz",
        )
        print(f"{trial}: {len(cuts.runs)} runs read and cut in {elapsed:.2f} s; {png}")
        start = time.perf_counter()
    manifest = args.out / "mocap6_repetitions.csv"
    manifest.write_text(rows_csv(rows), encoding="utf-8")
    print(f"{len(rows)} repetitions in {manifest}")


if __name__ == "__main__":
    main()
