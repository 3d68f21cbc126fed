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

``--why`` lists, per method at its defaults, every false cut and every missed boundary: the AMC
frame and second, the behaviours on both sides (the labels of the truth files), the score that
decided the cut (Boundary.score) and the signed distance to the nearest true boundary or cut.

``--folds`` chooses each method's parameters by leaving one take out: for every take, the setting
of :data:`GRIDS` with the best pooled F1 on the other takes (ties: the earlier, the paper's first),
reported on the take left out; the held-out figures pooled over the takes, beside the defaults.
With ``--png DIR`` it also prints and draws each method's pooled precision-recall curve over its
threshold (PPCA's rise R, PCA's kσ, GMM's k), the other parameters at the grid's first (the paper's).

``--features`` runs PPCA the same way on four representations of the frames (:func:`representations`).
"""

from __future__ import annotations

import argparse
import csv
import time
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from bench.common import DATA
from bench.machine import describe
from daemon import behaviours as bh
from daemon.features.batch import features
from daemon.plots import precision_recall_png, segmentation_png
from daemon.recordings import native_rate, read_boundaries, read_recording
from daemon.tools.mocap6 import SEGMENTS, trial_recording
from daemon.types import Band, FloatArray
from replay import JOINT_NAMES
from replay.kinematics import joint_positions

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


def evaluate(data: Path, trial: str, png: Path | None, show_why: bool = False) -> list[Outcome]:
    """Every method on one file: an outcome per method; prints the cuts, draws the PNG."""
    take = load(data, trial)
    x, rate, bands = take.x, take.rate, take.bands
    print(
        f"{trial}: {len(x)} frames at {rate:g} Hz, {x.shape[1] // 4} bones (D = {x.shape[1]}); "
        f"true boundaries at AMC frames {[b.frame for b in bands]}"
    )
    results, outcomes = {}, []
    for name, method in METHODS.items():
        began = time.perf_counter()
        results[name] = method(x, rate)
        spent = time.perf_counter() - began
        cuts = [(take.frames[b.frame], b.score) for b in _cuts(results[name])]
        frames = [c for c, _ in cuts]
        outcomes.append(Outcome(name, trial, frames, len(bands), bh.match_boundaries(frames, bands), spent))
        print(f"  {name:9s} {spent:6.2f} s  cuts {frames}")
        if show_why and name in GRIDS:
            why(take, name, cuts)
    if png is not None:
        segmentation_png(
            png / f"segmentation_{trial}.png",
            f"{trial}: behaviour segmentation (Barbič et al. 2004), the paper's parameters",
            rate,
            (take.frames[0], take.frames[-1]),
            [results["pca"], results["ppca"], results["gmm"]],
            bands,
        )
    return outcomes


@dataclass(frozen=True)
class Take:
    """A labelled take: its frame vectors ``x`` ``(N, D)`` at ``rate`` Hz, the AMC frame number of
    each (``frames``), the true boundaries and the labelled behaviours (name, first, last AMC frame)."""

    trial: str
    x: FloatArray
    rate: float
    frames: list[int]
    bands: list[Band]
    behaviours: list[tuple[str, int, int]]

    def behaviour(self, frame: int) -> str:
        return next((name for name, a, b in self.behaviours if a <= frame <= b), "-")


def load_behaviours(data: Path, trial: str) -> list[tuple[str, int, int]]:
    """The labelled behaviours of ``trial`` in its truth file: (name, first, last AMC frame)."""
    path = data / (CMU86 if trial.startswith("86_") else SEGMENTS)
    with path.open(newline="", encoding="utf-8") as f:
        rows = [r for r in csv.DictReader(f) if r["trial"] == trial]
    return [
        (r.get("label") or r.get("label_name") or "?", int(r["start_frame"]), int(r["end_frame"]))
        for r in rows
    ]


def load(data: Path, trial: str) -> Take:
    asf, amc = trial_recording(data, trial)
    motion = read_recording(asf, amc)
    x = bh.JointRotations(motion.skeleton)(motion.channels)
    frames = [int(f) for f in motion.frames]
    return Take(trial, x, native_rate(motion), frames, truth(data, trial), load_behaviours(data, trial))


PPCA_GRID: list[bh.Params] = [
    bh.PpcaParams(rise=r, shortest=s)
    for s in (2.5, 0.0, 1.875, 3.75)
    for r in (15.0, 5.0, 7.5, 10.0, 20.0, 30.0, 45.0)
]
GRIDS: dict[str, list[bh.Params]] = {
    "ppca": PPCA_GRID,
    "ppca-fwd": PPCA_GRID,
    "pca": [bh.PcaParams(k_sigma=k) for k in (3.0, 1.5, 2.0, 2.5, 4.0, 5.0, 7.0)],
    "gmm": [bh.GmmParams(clusters=c, min_length=m) for m in (1.0, 0.5, 2.0) for c in (4, 3, 5, 6, 8)],
}
"""Each method's settings tried by ``--folds``, the paper's first: PPCA's rise R with the shortest
behaviour 2 T, none, 1.5 T and 3 T (T = 1.25 s), for all passes and for the forward pass alone (what
runs online); PCA's kσ; GMM's k and shortest segment in seconds."""

BATCH: dict[str, bh.Method] = {"ppca": "ppca", "pca": "pca", "gmm": "gmm"}
"""The methods of ``--folds`` that run through :func:`daemon.behaviours.segment`."""

THRESHOLD = {"ppca": "rise", "ppca-fwd": "rise", "pca": "k_sigma", "gmm": "clusters"}
"""The parameter each method's precision-recall curve runs over."""


def describe_params(p: bh.Params) -> str:
    if isinstance(p, bh.PpcaParams):
        shortest = "3 T" if p.shortest is None else f"{p.shortest / p.window:g} T"
        return f"R = {p.rise:g}, shortest {shortest}"
    if isinstance(p, bh.PcaParams):
        return f"kσ = {p.k_sigma:g}"
    return f"k = {p.clusters}, shortest {p.min_length:g} s"


def cut_frames(take: Take, method: str, params: bh.Params) -> list[tuple[int, float]]:
    """The AMC frame and score of each cut of ``method`` (batch, PPCA's all passes; ``ppca-fwd``
    its forward pass) on ``take``."""
    if method == "ppca-fwd":
        assert isinstance(params, bh.PpcaParams)
        cuts = bh.ppca_forward(take.x, take.rate, params=params)
    else:
        cuts = bh.segment(take.x, take.rate, BATCH[method], params=params)
    return [(take.frames[b.frame], b.score) for b in cuts]


def f1(hits: int, cuts: int, bounds: int) -> float:
    return 2 * hits / (cuts + bounds) if cuts + bounds else 0.0


Runs = dict[tuple[int, str], tuple[int, int]]
"""(a setting's index in its grid, trial) -> (cuts, boundaries found)."""


def pooled(runs: Runs, k: int, takes: list[Take]) -> tuple[int, int, int]:
    """Setting ``k``'s boundaries found, cuts and true boundaries over ``takes``."""
    return scored(runs, [k] * len(takes), takes)


def why(take: Take, method: str, cuts: list[tuple[int, float]]) -> None:
    """Every false cut and missed boundary of ``cuts`` on ``take``, with what decided it."""
    frames = [c for c, _ in cuts]
    pairs = bh.pair_boundaries(frames, take.bands)
    found = set(pairs.values())
    first = take.frames[0]
    for i, (c, score) in enumerate(cuts):
        if i in pairs:
            continue
        near = min(take.bands, key=lambda b: abs(b.frame - c), default=None)
        off = (
            ""
            if near is None
            else f", {(c - near.frame) / take.rate:+.2f} s from the boundary at {near.frame}"
        )
        print(
            f"    {method:8s} {take.trial} false cut at {c} ({(c - first) / take.rate:.1f} s), inside "
            f"{take.behaviour(c)}, score {score:.2f}{off}"
        )
    for j, band in enumerate(take.bands):
        if j in found:
            continue
        near_cut = min(cuts, key=lambda cs: abs(cs[0] - band.frame), default=None)
        what = (
            "no cut"
            if near_cut is None
            else f"nearest cut {(near_cut[0] - band.frame) / take.rate:+.2f} s away (score {near_cut[1]:.2f})"
        )
        print(
            f"    {method:8s} {take.trial} missed {take.behaviour(band.frame - 1)} -> "
            f"{take.behaviour(band.frame)} at {band.frame} ({(band.frame - first) / take.rate:.1f} s, "
            f"band {band.lo}..{band.hi}): {what}"
        )


def folds(takes: list[Take], png: Path | None, show_why: bool) -> None:
    """Leave one take out (see the module's docstring): per method, the setting chosen on the other
    takes and its figures on the one left out, pooled; the defaults beside them."""
    print(f"\nleave one take out: {len(takes)} folds; a setting's score is its pooled F1 on the other takes")
    for method, grid in GRIDS.items():
        runs = every_run(takes, method, grid)
        print(f"  {method}: {len(grid)} settings")
        picks = held_out(runs, len(grid), takes)
        for out, best in zip(takes, picks, strict=True):
            rest = [t for t in takes if t is not out]
            cuts, hits = runs[best, out.trial]
            print(
                f"    {out.trial}: chosen {describe_params(grid[best])} "
                f"(F1 {f1(*pooled(runs, best, rest)):.2f} on the others): {cuts} cuts, "
                f"{hits}/{len(out.bands)} boundaries, precision {_fraction(hits, cuts)}"
            )
            if show_why:
                why(out, method, cut_frames(out, method, grid[best]))
        hits, cuts, bounds = scored(runs, picks, takes)
        paper = scored(runs, [0] * len(takes), takes)
        print(
            f"  {method} held out, pooled: precision {_fraction(hits, cuts)}, recall "
            f"{_fraction(hits, bounds)} ({cuts} cuts); the paper's parameters: precision "
            f"{_fraction(paper[0], paper[1])}, recall {_fraction(paper[0], paper[2])} ({paper[1]} cuts)"
        )
        if png is not None:
            curve(takes, method, grid, runs, png)


def every_run(takes: list[Take], method: str, grid: list[bh.Params]) -> Runs:
    """Every setting of ``grid`` on every take (every fold reuses them)."""
    runs: Runs = {}
    for k, params in enumerate(grid):
        for take in takes:
            frames = [c for c, _ in cut_frames(take, method, params)]
            runs[k, take.trial] = (len(frames), bh.match_boundaries(frames, take.bands))
    return runs


def representations(data: Path, take: Take) -> dict[str, FloatArray]:
    """``take``'s frames in the representations ``--features`` compares, each ``(N, D)``: the
    paper's joint rotations (14 quaternions), those with their velocities (frame differences, x10
    so that both weigh alike), the 26 standard joints' positions relative to the root (metres),
    and the 39 relational features of the Bonn catalogue (0/1, a trace of noise so that no
    covariance is singular)."""
    motion = read_recording(*trial_recording(data, take.trial))
    positions = joint_positions(motion)
    velocity = np.vstack([np.zeros((1, take.x.shape[1])), np.diff(take.x, axis=0)]) * 10
    relational = features(positions, JOINT_NAMES, take.rate).astype(np.float64)
    noise = 1e-3 * np.random.default_rng(0).standard_normal(relational.shape)
    return {
        "joint rotations (the paper's)": take.x,
        "rotations and their velocities": np.hstack([take.x, velocity]),
        "joint positions, root-relative": (positions - positions[:, :1]).reshape(len(positions), -1) / 100,
        "relational features": relational + noise,
    }


def compare_features(data: Path, takes: list[Take]) -> None:
    """PPCA (all passes) on each representation of :func:`representations`, its parameters chosen
    by leaving one take out as ``--folds`` does: the held-out figures pooled."""
    print(f"\nPPCA on each representation, {len(takes)} folds")
    each = {t.trial: representations(data, t) for t in takes}
    for name in each[takes[0].trial]:
        seen = [replace(t, x=each[t.trial][name]) for t in takes]
        runs = every_run(seen, "ppca", PPCA_GRID)
        picks = held_out(runs, len(PPCA_GRID), seen)
        hits, cuts, bounds = scored(runs, picks, seen)
        print(
            f"  {name:32s} precision {_fraction(hits, cuts)}, recall {_fraction(hits, bounds)} "
            f"({cuts} cuts); chosen: {'; '.join(describe_params(PPCA_GRID[k]) for k in picks)}"
        )


def held_out(runs: Runs, settings: int, takes: list[Take]) -> list[int]:
    """For each take in turn, the setting :func:`choose` picks on the others."""
    return [choose(runs, settings, [t for t in takes if t is not out]) for out in takes]


def scored(runs: Runs, picks: list[int], takes: list[Take]) -> tuple[int, int, int]:
    """Boundaries found, cuts and true boundaries over ``takes``, each with its setting of ``picks``."""
    hits = sum(runs[k, t.trial][1] for k, t in zip(picks, takes, strict=True))
    cuts = sum(runs[k, t.trial][0] for k, t in zip(picks, takes, strict=True))
    return hits, cuts, sum(len(t.bands) for t in takes)


def choose(runs: Runs, settings: int, takes: list[Take]) -> int:
    """The index of the setting with the best pooled F1 over ``takes`` (and only those), the
    earliest of equals."""
    return max(range(settings), key=lambda k: (f1(*pooled(runs, k, takes)), -k))


def curve(takes: list[Take], method: str, grid: list[bh.Params], runs: Runs, png: Path) -> None:
    """The pooled precision-recall points of ``method`` over its threshold, the rest at grid[0]'s."""
    name = THRESHOLD[method]
    rest = {k: v for k, v in vars(grid[0]).items() if k != name}
    ks = sorted(
        (k for k, p in enumerate(grid) if {a: b for a, b in vars(p).items() if a != name} == rest),
        key=lambda k: getattr(grid[k], name),
    )
    points = []
    for k in ks:
        hits, cuts, bounds = pooled(runs, k, takes)
        points.append((hits / cuts if cuts else 0.0, hits / bounds))
    print(
        f"  {method} curve, pooled ({name}: precision / recall): "
        + ", ".join(
            f"{getattr(grid[k], name):g}: {p:.2f} / {r:.2f}" for k, (p, r) in zip(ks, points, strict=True)
        )
    )
    precision_recall_png(
        {f"{method}, pooled over {len(takes)} takes": points},
        [float(getattr(grid[k], name)) for k in ks],
        png / f"segmentation_pr_{method}.png",
        threshold=name,
    )


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--data", type=Path, default=DATA)
    parser.add_argument("--png", type=Path, default=None, help="directory for one PNG per file")
    parser.add_argument("--why", action="store_true", help="every false cut and missed boundary")
    parser.add_argument("--folds", action="store_true", help="parameters chosen leaving one take out")
    parser.add_argument(
        "--features", action="store_true", help="PPCA on four representations, each by the folds"
    )
    args = parser.parse_args()
    if args.png is not None:
        args.png.mkdir(parents=True, exist_ok=True)
    print(describe())
    if not (args.folds or args.features):
        report([o for trial in TRIALS for o in evaluate(args.data, trial, args.png, args.why)])
        return
    takes = [load(args.data, trial) for trial in TRIALS]
    if args.features:
        compare_features(args.data, takes)
        return
    folds(takes, args.png, args.why)


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
