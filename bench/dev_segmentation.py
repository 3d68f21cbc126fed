"""A development set for behaviour segmentation, apart from the files ``eval_segmentation`` reports:
long takes joined from the HDM05 cut clips here, with known boundaries. Readings of the paper and
changes to the methods are tried here first, so that no choice is made on the reported files.

    python -m bench.dev_segmentation [--data DIR] [--seeds 2]

Takes: for each HDM05 actor here (bd, bk, dg) and seed, the actor's classes in a seeded random order;
each class is all of the actor's clips of it in file order (HDM05 cut them from one take, so most
meet frame to frame). Where two clips do not meet (a jump in the frame vectors), and between two
classes, 0.5 s of blend is put in: each joint's quaternion interpolated linearly and normalised.
A true boundary lies at the middle of each blend between classes, found by a cut within ± 60 frames
(as mocap6's in ``eval_segmentation``). The frames are the paper's representation (14 joints, D = 56)
of each clip, signs made consistent over the whole take.

Not natural transitions: a blend is smoother and shorter than most real ones, and a class's clips
meeting through a blend (a lie-down clip's end, lying, blended into the next one's start, standing)
are changes inside one "behaviour" that a method may rightly cut. The figures are for comparing
variants with each other, not with the paper's.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from bench.common import DATA
from bench.eval_segmentation import METHODS, Outcome, _cuts, report
from bench.machine import describe
from daemon import behaviours as bh
from daemon.recordings import read_recording
from daemon.types import Band, FloatArray

ACTORS = ("bd", "bk", "dg")
RATE = 120.0
BLEND = 60
"""Frames of blend (0.5 s at 120 Hz), between clips that do not meet and between classes."""
MEET = 0.05
"""Clips meet when their frame vectors differ by less than this (a frame's step is about 0.03)."""
TOLERANCE = 60


def clips(data: Path, actor: str) -> dict[str, list[FloatArray]]:
    """Each class's clips of ``actor``, as frame vectors ``(n, 56)``, in file order."""
    root = data / "hdm05"
    out: dict[str, list[FloatArray]] = {}
    for folder in sorted(p for p in (root / "cut").iterdir() if p.is_dir()):
        files = sorted(folder.glob(f"HDM_{actor}_*.amc*"))
        if files:
            motions = [read_recording(root / "asf" / f"HDM_{actor}.asf", f) for f in files]
            out[folder.name] = [bh.JointRotations(m.skeleton)(m.channels) for m in motions]
    return out


def blend(a: FloatArray, b: FloatArray, frames: int) -> FloatArray:
    """``frames`` vectors from ``a`` ``(D,)`` towards ``b``, both ends left out: each quaternion
    interpolated linearly (``b``'s taken on ``a``'s side) and normalised. Shape ``(frames, D)``."""
    q0, q1 = a.reshape(-1, 4), b.reshape(-1, 4).copy()
    q1[(q0 * q1).sum(axis=1) < 0] *= -1
    t = np.linspace(0.0, 1.0, frames + 2)[1:-1, None, None]
    q = (1 - t) * q0 + t * q1
    out: FloatArray = (q / np.linalg.norm(q, axis=2, keepdims=True)).reshape(frames, -1)
    return out


def take(classes: dict[str, list[FloatArray]], seed: int) -> tuple[FloatArray, list[Band], list[str]]:
    """One take: its frames ``(n, D)``, true boundaries and the classes' order."""
    order = [str(c) for c in np.random.default_rng(seed).permutation(sorted(classes))]
    parts: list[FloatArray] = []
    bands: list[Band] = []
    n = 0
    for name in order:
        for j, x in enumerate(classes[name]):
            if parts and (j == 0 or np.linalg.norm(parts[-1][-1] - x[0]) > MEET):
                parts.append(blend(parts[-1][-1], x[0], BLEND))
                n += BLEND
                if j == 0:
                    middle = n - BLEND // 2
                    bands.append(Band(middle, middle - TOLERANCE, middle + TOLERANCE))
            parts.append(x)
            n += x.shape[0]
    x = np.concatenate(parts)
    return bh.consistent_signs(x.reshape(x.shape[0], -1, 4)).reshape(x.shape), bands, order


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--data", type=Path, default=DATA)
    parser.add_argument("--seeds", type=int, default=2, help="takes per actor (default 2)")
    args = parser.parse_args()
    print(describe())
    outcomes: list[Outcome] = []
    for actor in ACTORS:
        classes = clips(args.data, actor)
        for seed in range(args.seeds):
            x, bands, order = take(classes, seed)
            name = f"{actor}/{seed}"
            print(f"{name}: {x.shape[0]} frames, {len(order)} classes: {', '.join(order)}")
            for method, run in METHODS.items():
                cuts = [b.frame for b in _cuts(run(x, RATE))]
                hits = bh.match_boundaries(cuts, bands)
                outcomes.append(Outcome(method, name, cuts, len(bands), hits, 0.0))
    report(outcomes)


if __name__ == "__main__":
    main()
