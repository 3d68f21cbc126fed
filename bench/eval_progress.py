"""How far along their templates the shipped library's classes get on real motion: the figures the
progress floor (:data:`daemon.progress.FLOOR`) is chosen from and checked on (issue 24).

    python -m bench.eval_progress [--data DIR]

Every clip is its own stream through the shipped library (the configuration's defaults), read after
every index frame with no floor (:func:`daemon.progress.read`). A class's position at a frame is
*unrelated* on an HDM05 cut clip of another class, *related* on a clip of its own class.

* **Choose** (HDM05 actors bd and bk): per candidate floor p (0.30 .. 0.95), the share of unrelated
  (clip, class, index frame) samples at position p or more (a bar shown for a motion that is not
  its class's) and the share of related clips whose class reaches p (a bar shown for the motion it
  is), how often unrelated bars appear, and how early related ones do. The floor is the lowest
  candidate at which unrelated bars appear at most a fifth as often as at the lowest
  (:data:`FEWER`), applied to these figures only.
* **Report** (HDM05 actor dg, and the CMU trials 13_29, 13_30, 14_14 whole): the same shares at the
  chosen floor, on clips the choice never saw; and, for every detection, the highest position its
  class showed from the detection's first frame to its emission.

Nothing here is tuned on the clips it reports.
"""

from __future__ import annotations

import argparse
from collections import defaultdict
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from bench.common import DATA
from bench.machine import describe
from daemon.frames import FrameClock
from daemon.library import Library, default_library_path, load_library
from daemon.progress import read
from daemon.recognizer import Detection, recording_stage
from daemon.recordings import read_recording
from daemon.tools.shipped import HDM05_CLASSES
from replay.kinematics import joint_positions

CANDIDATES = tuple(round(0.05 * k, 2) for k in range(1, 20))
"""The floors weighed, 0.05 .. 0.95."""
SIMILAR = {
    "Squat": "squat1Reps",
    "Jog": "jogLeftCircle4StepsRstart",
    "ArmCircle": "rotateArmsBothBackward1Reps",
    "KneeRaise": "elbowToKnee1RepsLelbowStart",
    "JumpJack": "hopBothLegs1hops",
    "ToeTouchOneHand": "depositFloorR",
}
"""The CMU exercise classes and the HDM05 class each resembles: not unrelated on its clips."""
FEWER = 5.0
"""The rule: the lowest candidate at which unrelated bars appear at most a fifth as often as at the
lowest (beyond it a higher floor removes few more, and costs lead)."""
TINY = 1e-9
"""A floor that lets every class with a path within τ through."""


def positions(asf: Path, amc: Path, library: Library) -> tuple[dict[str, list[float]], list[Detection], int]:
    """Per class the position at every index frame of the recording (0: no path within τ), the
    detections, and the recording's first frame number."""
    motion = read_recording(asf, amc)
    codes, stage = recording_stage(joint_positions(motion), library, 120.0)
    clock = stage.clock
    first, last = int(motion.frames[0]), int(motion.frames[-1])
    stage.start(first)
    names = [p.name for p in stage.codes.plans]
    out: dict[str, list[float]] = {n: [] for n in names}
    found: list[Detection] = []
    for j, code in enumerate(codes):
        found += stage.push(clock.known(first, j, last), code)
        seen = {c.class_name: c.position for c in read(stage, TINY)}
        for n in names:
            out[n].append(seen.get(n, 0.0))
    return out, found + stage.flush(last), first


def hdm05(data: Path, actors: tuple[str, ...]) -> list[tuple[str, Path, Path]]:
    clips = []
    for amc in sorted((data / "hdm05" / "cut").glob("*/*.amc.gz")):
        name, actor = amc.parent.name, amc.name.split("_")[1]
        if name in HDM05_CLASSES and actor in actors:
            clips.append((name, data / "hdm05" / "asf" / f"HDM_{actor}.asf", amc))
    return clips


@dataclass(frozen=True)
class Shares:
    """Per candidate floor: the share of unrelated samples at or above it, unrelated bars appearing
    (a class going from below to at or above it) per minute of a class's stream, the share of
    related clips whose class reaches it, and the median seconds from a related class first
    reaching it to its clip's end (how early its bar shows); the samples and clips counted."""

    unrelated: dict[float, float]
    appearing: dict[float, float]
    reached: dict[float, float]
    lead_s: dict[float, float]
    samples: int
    related: int


def shares(clips: list[tuple[str, Path, Path]], library: Library) -> Shares:
    unrelated: dict[float, int] = defaultdict(int)
    appearing: dict[float, int] = defaultdict(int)
    reached: dict[float, int] = defaultdict(int)
    leads: dict[float, list[float]] = defaultdict(list)
    samples = related = 0
    for name, asf, amc in clips:
        pos, _, _ = positions(asf, amc, library)
        for cls, values in pos.items():
            v = np.asarray(values)
            if cls == name:
                related += 1
                for p in CANDIDATES:
                    at = np.flatnonzero(v >= p)
                    reached[p] += len(at) > 0
                    if len(at):
                        leads[p].append((len(v) - at[0]) / library.rate)
            elif SIMILAR.get(cls) != name:
                samples += len(v)
                for p in CANDIDATES:
                    up = v >= p
                    unrelated[p] += int(np.count_nonzero(up))
                    appearing[p] += int(up[0]) + int(np.count_nonzero(up[1:] & ~up[:-1]))
    minutes = samples / library.rate / 60
    return Shares(
        {p: unrelated[p] / max(1, samples) for p in CANDIDATES},
        {p: appearing[p] / max(minutes, 1e-9) for p in CANDIDATES},
        {p: reached[p] / max(1, related) for p in CANDIDATES},
        {p: float(np.median(leads[p])) if leads[p] else 0.0 for p in CANDIDATES},
        samples,
        related,
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data", type=Path, default=DATA)
    args = parser.parse_args()
    library = load_library(default_library_path())
    print(describe())
    print("choose: HDM05 bd, bk")
    got = shares(hdm05(args.data, ("bd", "bk")), library)
    print(f"  {got.samples} unrelated samples, {got.related} related clips")
    print("  floor  unrelated>=floor  appearing/min  related reaching it  lead (s, median)")
    for p in CANDIDATES:
        print(
            f"  {p:5.2f}  {got.unrelated[p]:16.3f}  {got.appearing[p]:13.1f}  {got.reached[p]:19.3f}"
            f"  {got.lead_s[p]:.2f}"
        )
    a = got.appearing
    chosen = next((p for p in CANDIDATES if a[p] * FEWER <= a[CANDIDATES[0]]), CANDIDATES[-1])
    print(
        f"  chosen (the lowest with unrelated bars at most 1/{FEWER:g} as often as the lowest): {chosen:.2f}"
    )
    print("report: HDM05 dg")
    got = shares(hdm05(args.data, ("dg",)), library)
    print(
        f"  at {chosen:.2f}: unrelated samples {got.unrelated[chosen]:.3f} of {got.samples}, "
        f"appearing {got.appearing[chosen]:.1f}/min, related clips reaching it "
        f"{got.reached[chosen]:.3f} of {got.related}, lead {got.lead_s[chosen]:.2f} s"
    )
    print("report: CMU trials, the highest position of each detection's class before its emission")
    clock = FrameClock.of(120.0, library.rate)
    highest: list[float] = []
    for trial in ("13_29", "13_30", "14_14"):
        subject = trial.split("_")[0]
        asf = args.data / "cmu" / "13" / "13.asf"
        pos, found, first = positions(asf, args.data / "cmu" / subject / f"{trial}.amc.gz", library)
        for d in found:
            lo, hi = clock.index(first, d.start_frame), clock.index(first, d.emitted_at_frame - clock.delay)
            values = pos[d.class_name][lo : hi + 1]
            highest.append(max(values, default=0.0))
    h = np.asarray(highest)
    print(
        f"  {len(h)} detections: highest position min {h.min():.2f}, p5 {np.percentile(h, 5):.2f}, "
        f"median {np.median(h):.2f}"
    )


if __name__ == "__main__":
    main()
