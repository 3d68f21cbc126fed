"""What lost poses do to the detections (issue 32): random runs of lost frames in real recordings,
each recording's detections with them against its detections without them.

    python -m bench.lost_poses [--trials 200] [--seed 32]

Per trial: one CMU recording of ``bench.lost_poses.RECORDINGS``, one to three runs of 1-30 lost
frames at random places (each bridged: at most ``service.bridge_s`` = 0.25 s at 120 Hz). Two ways
of taking them, both measured here on the same frames:

* **bridged** (mocapd now): the missing frames interpolated, index frames sampled by frame number
  (:func:`daemon.recognizer.detect` on the recording less those frames, which the stream table
  equals: ``tests/test_lost_poses.py``);
* **closed up** (mocapd before): the frames after a gap numbered on from the one before it, as if
  nothing was lost, every 4th pose counted from the motion's first, the detections' frames mapped
  back to the source's numbers.

Prints the share of trials whose detections (class, first and last frame) are exactly those of the
whole recording, and the detections that differ (in one but not the other), per way.
"""

from __future__ import annotations

import random
import sys
import time

import numpy as np

from bench.common import arguments
from bench.machine import describe
from daemon.library import default_library_path, load_library
from daemon.recognizer import detect, detect_positions
from daemon.recordings import read_recording
from replay import Motion
from replay.kinematics import joint_positions
from tests.helpers import DATA

RECORDINGS = [
    (DATA / "cmu" / "13" / "13.asf", DATA / "cmu" / "13" / f"13_{n}.amc.gz") for n in (17, 29, 30, 34)
]
Key = tuple[str, int, int]


def closed_up(motion: Motion, library: object) -> list[Key]:
    """The detections of ``motion`` (frames missing) as the live path took it before: consecutive
    frame numbers from its first, mapped back to the frames' own numbers."""
    numbers = np.arange(int(motion.frames[0]), int(motion.frames[0]) + len(motion), dtype=np.int64)
    back = dict(zip(numbers.tolist(), motion.frames.tolist(), strict=True))
    found = detect_positions(joint_positions(motion), numbers, library, 120.0)  # type: ignore[arg-type]
    return [(d.class_name, back[d.start_frame], back[d.end_frame]) for d in found]


def main() -> int:
    args = arguments(__doc__, trials=200, seed=32)
    print(describe())
    library = load_library(default_library_path())
    motions = [read_recording(asf, amc) for asf, amc in RECORDINGS]
    whole = [[(d.class_name, d.start_frame, d.end_frame) for d in detect(m, library, 120.0)] for m in motions]
    rng = random.Random(args.seed)
    same = {"bridged": 0, "closed up": 0}
    differ = {"bridged": 0, "closed up": 0}
    began = time.perf_counter()
    for trial in range(args.trials):
        k = trial % len(motions)
        motion = motions[k]
        lost: set[int] = set()
        for _ in range(rng.randint(1, 3)):
            at = rng.randrange(1, len(motion) - 32)
            lost.update(range(at, at + rng.randint(1, 30)))
        keep = np.array([i for i in range(len(motion)) if i not in lost])
        gappy = Motion(
            motion.source, motion.skeleton, motion.header, motion.frames[keep], motion.channels[keep]
        )
        ways = {
            "bridged": [(d.class_name, d.start_frame, d.end_frame) for d in detect(gappy, library, 120.0)],
            "closed up": closed_up(gappy, library),
        }
        for way, got in ways.items():
            same[way] += got == whole[k]
            differ[way] += len(set(got) ^ set(whole[k]))
        if (trial + 1) % 50 == 0:
            print(f"  {trial + 1} of {args.trials} trials", file=sys.stderr, flush=True)
    n = args.trials
    print(
        f"{n} trials, 1-3 runs of 1-30 lost frames each, CMU 13_17/29/30/34 "
        f"({time.perf_counter() - began:.0f} s)"
    )
    print(f"{'way':<10} {'trials exactly as whole':>24} {'detections differing per trial':>32}")
    for way in same:
        print(f"{way:<10} {same[way] / n:>24.2f} {differ[way] / n:>32.2f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
