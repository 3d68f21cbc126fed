"""The shipped library at other frame rates (issue 35, "Any frame rate"): CMU and HDM05 recordings
resampled from 120 Hz to 60 and 30 Hz (every 2nd or 4th frame), their detections against those at
120 Hz.

    python -m bench.eval_rates [--hdm05 20]

A detection at a lower rate matches one at 120 Hz of the same class whose start and end lie within
one index frame (1/30 s) of it. Printed per recording and in all: the 120 Hz detections, those
matched at 60 and at 30 Hz, and the detections at 60 and 30 Hz that match none (extra). Nothing is
tuned on them: the library and settings are the shipped defaults.
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


def matched(base: list[Detection], other: list[Detection], k: int) -> tuple[int, int]:
    """How many of ``base`` (120 Hz frames) one of ``other`` (frames every ``k``-th) matches, and how
    many of ``other`` match none."""
    tolerance = 4  # one index frame at 120 Hz
    used: set[int] = set()
    hits = 0
    for d in base:
        for j, o in enumerate(other):
            if j in used or o.class_name != d.class_name:
                continue
            if (
                abs(o.start_frame * k - d.start_frame) <= tolerance
                and abs((o.end_frame + 1) * k - 1 - d.end_frame) <= tolerance  # its frame's last at 120 Hz
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
    totals = np.zeros(5, dtype=int)
    print(f"{'recording':<44} {'120 Hz':>6} {'60 Hz':>6} {'30 Hz':>6} {'extra 60':>8} {'extra 30':>8}")
    for name, asf, amc in recordings(args.hdm05):
        p = joint_positions(read_recording(asf, amc))
        base = detect_positions(p, np.arange(len(p)), library, 120.0)
        row = [len(base)]
        extras = []
        for k in (2, 4):
            q = p[::k]
            hits, extra = matched(base, detect_positions(q, np.arange(len(q)), library, 120.0 / k), k)
            row.append(hits)
            extras.append(extra)
        row += extras
        totals += row
        print(f"{name:<44} {row[0]:>6} {row[1]:>6} {row[2]:>6} {row[3]:>8} {row[4]:>8}")
    print(f"{'all':<44} {totals[0]:>6} {totals[1]:>6} {totals[2]:>6} {totals[3]:>8} {totals[4]:>8}")
    print(f"took {time.perf_counter() - began:.0f} s")


if __name__ == "__main__":
    main()
