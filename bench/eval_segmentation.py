"""Behaviour segmentation (Barbič et al. 2004; daemon.behaviours) against labelled boundaries, with
the paper's parameters (nothing here is tuned on these files).

    python -m bench.eval_segmentation [--data DIR] [--png DIR]

Files and truth: CMU 86_01 (``annotations/cmu86_aca_haca/cmu86_segments.csv``: a true boundary after
each segment but the last, found by a cut whose new behaviour starts at AMC frame ``end_lo + 1`` ..
``end_hi + 1``, i.e. the old one ends inside ``end_lo .. end_hi``) and the mocap6 trials 13_29, 13_30
and 14_14 (``annotations/mocap6/per_frame_120hz/segments_120hz.csv``: a true boundary at the first
frame of every labelled run but the first, found by a cut within ± 60 frames). A cut's frame is the
first frame of its new behaviour. Each cut counts for at most one boundary and each boundary for at
most one cut: the pairs (cut, boundary) in tolerance are matched greedily by increasing distance to
the boundary's frame. Precision = matched cuts / cuts, recall = matched boundaries / boundaries, per
method and file, then pooled per method (sums over files).

Methods: ``pca`` (§3.1, online, every frame), ``pca-grid`` (the same, the error evaluated every ℓ
frames: ``step = 0.5 s``), ``ppca-fwd`` (§3.2's forward pass alone: what runs online), ``ppca``
(§3.2, forward and backward passes until no new cut; behaviours of at least 2 T), ``ppca-pub`` (the
same as published: a segment as short as T), ``gmm`` (§3.3, k = 4, seed 0).

``--png DIR`` draws one picture per file: PCA's error derivative and its threshold, PPCA's ``H``
(first forward pass), GMM's labels, each with its cuts (red) and the true boundaries' tolerance bands
(green), against time.
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from bench.common import DATA
from bench.machine import describe
from daemon import behaviours as bh
from daemon.plots import segmentation_png
from daemon.recordings import native_rate, read_boundaries, read_recording
from daemon.tools.mocap6 import SEGMENTS, trial_recording
from daemon.types import Band, FloatArray

CMU86 = Path("annotations") / "cmu86_aca_haca" / "cmu86_segments.csv"
TRIALS = ("86_01", "13_29", "13_30", "14_14")


def truth(data: Path, trial: str) -> list[Band]:
    """The true boundaries of ``trial``: 86_* from ``cmu86_segments.csv`` (with its tolerance
    bands), the mocap6 trials from ``segments_120hz.csv`` (± 60 frames)."""
    return read_boundaries(data / (CMU86 if trial.startswith("86_") else SEGMENTS), trial)


@dataclass(frozen=True)
class Outcome:
    method: str
    trial: str
    cuts: list[int]
    boundaries: int
    hits: int
    seconds: float

    @property
    def precision(self) -> float:
        return self.hits / len(self.cuts) if self.cuts else 0.0

    @property
    def recall(self) -> float:
        return self.hits / self.boundaries if self.boundaries else 0.0


def _fraction(hits: int, total: int) -> str:
    return f"{hits / total:5.2f}" if total else "  -  "


METHODS: dict[str, Callable[[FloatArray, float], Any]] = {
    "pca": lambda x, rate: bh.pca_analysis(x, rate),
    "pca-grid": lambda x, rate: bh.pca_analysis(x, rate, params=bh.PCA_GRID),
    "ppca-fwd": lambda x, rate: bh.ppca_forward(x, rate),
    "ppca": lambda x, rate: bh.ppca_analysis(x, rate),
    "ppca-pub": lambda x, rate: bh.ppca_analysis(x, rate, params=bh.PPCA_PUBLISHED),
    "gmm": lambda x, rate: bh.gmm_analysis(x, rate),
}


def _cuts(result: Any) -> list[bh.Boundary]:
    return list(result) if isinstance(result, list) else list(result.boundaries)


def evaluate(data: Path, trial: str, png: Path | None) -> list[Outcome]:
    """Every method on one file: an outcome per method; prints the cuts, draws the PNG."""
    asf, amc = trial_recording(data, trial)
    motion = read_recording(asf, amc)
    rate = native_rate(motion)
    rotations = bh.JointRotations(motion.skeleton)
    x = rotations(motion.channels)
    bands = truth(data, trial)
    print(
        f"{trial}: {len(motion)} frames at {rate:g} Hz, {len(rotations.bones)} bones (D = {rotations.dims}); "
        f"true boundaries at AMC frames {[b.frame for b in bands]}"
    )
    results, outcomes = {}, []
    for name, method in METHODS.items():
        began = time.perf_counter()
        results[name] = method(x, rate)
        spent = time.perf_counter() - began
        frames = [int(motion.frames[b.frame]) for b in _cuts(results[name])]
        outcomes.append(Outcome(name, trial, frames, len(bands), bh.match_boundaries(frames, bands), spent))
        print(f"  {name:9s} {spent:6.2f} s  cuts {frames}")
    if png is not None:
        segmentation_png(
            png / f"segmentation_{trial}.png",
            f"{trial}: behaviour segmentation (Barbič et al. 2004), the paper's parameters",
            rate,
            (int(motion.frames[0]), int(motion.frames[-1])),
            [results["pca"], results["ppca"], results["gmm"]],
            bands,
        )
    return outcomes


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--data", type=Path, default=DATA)
    parser.add_argument("--png", type=Path, default=None, help="directory for one PNG per file")
    args = parser.parse_args()
    if args.png is not None:
        args.png.mkdir(parents=True, exist_ok=True)
    print(describe())
    report([o for trial in TRIALS for o in evaluate(args.data, trial, args.png)])


def report(outcomes: list[Outcome]) -> None:
    """The table: per method, each file's cuts, boundaries, hits, precision and recall, then pooled."""
    print(f"\n{'method':9s} {'file':6s} {'cuts':>5s} {'bounds':>6s} {'hits':>5s} {'prec':>5s} {'recall':>6s}")
    for method in METHODS:
        rows = [o for o in outcomes if o.method == method]
        for o in rows:
            print(
                f"{o.method:9s} {o.trial:6s} {len(o.cuts):5d} {o.boundaries:6d} {o.hits:5d} "
                f"{_fraction(o.hits, len(o.cuts))} {_fraction(o.hits, o.boundaries):>6s}"
            )
        cuts = sum(len(o.cuts) for o in rows)
        bounds = sum(o.boundaries for o in rows)
        hits = sum(o.hits for o in rows)
        print(
            f"{method:9s} {'pooled':6s} {cuts:5d} {bounds:6d} {hits:5d} {_fraction(hits, cuts)} "
            f"{_fraction(hits, bounds):>6s}"
        )


if __name__ == "__main__":
    main()
