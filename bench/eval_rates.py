"""The shipped library at other frame rates (issue 35, "Any frame rate"): CMU and HDM05 recordings
resampled from 120 Hz to 60 and 30 Hz (every 2nd or 4th frame) and to 100 and 50 Hz (joint
positions interpolated linearly), their detections against those at 120 Hz.

    python -m bench.eval_rates [--hdm05 20]

A detection at another rate matches one at 120 Hz of the same class whose start and end (in
seconds from the first frame) lie within one index frame (1/30 s) of it, and a native frame more
at 100 and 50 Hz (an index frame is the first frame at or after its instant). Printed per
recording and in all: the 120 Hz detections, and for each rate those matched as ``A/B``, A with
start and end, B with the start alone (a match's end moves along a flat valley of the DTW cost
when a few bits change, as blended poses change them), and the detections at each rate that
match none by their start (extra). Nothing is tuned on them: the library and settings are the
shipped defaults.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from bench.common import DATA
from bench.machine import describe
from daemon.library import default_library_path, load_library
from daemon.recognizer import Detection, detect_positions
from daemon.recordings import read_recording
from daemon.types import FloatArray
from replay.kinematics import joint_positions

CMU = ("13_29", "13_30", "13_17", "13_34", "14_14", "86_01")


def recordings(hdm05: int) -> list[tuple[str, Path, Path]]:
    out: list[tuple[str, Path, Path]] = []
    for trial in CMU:
        subject = trial.split("_")[0]
        asf = DATA / "cmu" / subject / f"{'13' if subject == '14' else subject}.asf"
        amc = DATA / "cmu" / subject / f"{trial}.amc.gz"
        if asf.exists() and amc.exists():
            out.append((trial, asf, amc))
    for amc in sorted((DATA / "hdm05" / "cut").glob("*/*.amc.gz"))[:: max(1, 330 // max(hdm05, 1))][:hdm05]:
        actor = amc.name.split("_")[1]
        out.append((amc.name.removesuffix(".amc.gz"), DATA / "hdm05" / "asf" / f"HDM_{actor}.asf", amc))
    return out


RATES = (60.0, 30.0, 100.0, 50.0)


def resampled(positions: FloatArray, rate: float) -> FloatArray:
    """``positions`` (N, J, 3) at 120 Hz at ``rate`` Hz: every k-th frame if ``rate`` divides 120,
    else interpolated linearly."""
    k = 120.0 / rate
    if k == int(k):
        out: FloatArray = positions[:: int(k)]
        return out
    t = np.arange(int((len(positions) - 1) / k) + 1) * k
    i = np.minimum(t.astype(int), len(positions) - 2)
    w = (t - i)[:, None, None]
    out = (1 - w) * positions[i] + w * positions[i + 1]
    return out


def matched(base: list[Detection], other: list[Detection], rate: float, ends: bool = True) -> tuple[int, int]:
    """How many of ``base`` (120 Hz frames) one of ``other`` (frames at ``rate``) matches (by start
    and end, or by start alone without ``ends``), and how many of ``other`` match none."""
    tolerance = 1 / 30 + (0.0 if 120.0 / rate == int(120.0 / rate) else 1 / rate) + 1e-9
    used: set[int] = set()
    hits = 0
    for d in base:
        for j, o in enumerate(other):
            if j in used or o.class_name != d.class_name:
                continue
            if abs(o.start_frame / rate - d.start_frame / 120.0) <= tolerance and (
                not ends or abs((o.end_frame + 1) / rate - (d.end_frame + 1) / 120.0) <= tolerance
            ):
                used.add(j)
                hits += 1
                break
    return hits, len(other) - len(used)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--hdm05", type=int, default=20, help="HDM05 cut clips, spread over the classes")
    args = parser.parse_args()
    print(describe())
    library = load_library(default_library_path())
    began = time.perf_counter()
    totals = np.zeros(1 + 3 * len(RATES), dtype=int)
    heads = [f"{r:g} Hz" for r in RATES] + [f"extra {r:g}" for r in RATES]
    print(f"{'recording':<44} {'120 Hz':>6} " + " ".join(f"{h:>9}" for h in heads))

    def line(name: str, row: list[int] | np.ndarray) -> None:
        n = len(RATES)
        pairs = [f"{row[1 + i]}/{row[1 + n + i]}" for i in range(n)]
        print(f"{name:<44} {row[0]:>6} " + " ".join(f"{v:>9}" for v in [*pairs, *row[1 + 2 * n :]]))

    for name, asf, amc in recordings(args.hdm05):
        p = joint_positions(read_recording(asf, amc))
        base = detect_positions(p, np.arange(len(p)), library, 120.0)
        full, starts, extras = [], [], []
        for rate in RATES:
            q = resampled(p, rate)
            found = detect_positions(q, np.arange(len(q)), library, rate)
            full.append(matched(base, found, rate)[0])
            hits, extra = matched(base, found, rate, ends=False)
            starts.append(hits)
            extras.append(extra)
        row = [len(base), *full, *starts, *extras]
        totals += row
        line(name, row)
    line("all", totals)
    print(f"took {time.perf_counter() - began:.0f} s")


if __name__ == "__main__":
    main()
