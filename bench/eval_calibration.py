"""Per-class calibration (issue 12) on the HDM05 clips in ../shared/data/mocap: the 11 classes of
actors bd, bk and dg (as bench.eval_templates chooses them), 30 Hz, toolbox steps.

    python -m bench.eval_calibration [--data DIR] [--workers N]

Held out: each actor in turn is the new person. The class is learned from the other two actors'
clips, and its τ and keyframe generalisation are calibrated on those two alone (leave one of them
out, then the other: daemon.calibration). On the held-out actor's clips, a clip is retrieved when
the template's best subsequence-DTW cost over it is at most τ: recall = retrieved clips of the
class / its clips, precision = retrieved clips of the class / all retrieved clips, pooled over the
three held-out actors, at the thesis' τ = 0.1 and at the calibrated τ. The learned keyframes keep a
clip when the keyframe search over it returns a component: the held-out actor's clips of the class
kept (and of other classes, the price) with the thesis' rule (ch. 6) and with the generalisation.

In-sample: calibration over all three actors (3 folds), as ``mocapd learn`` does it: the τ, its
pooled recall and precision, and the keyframes' retention fold by fold (the worst fold shown).
"""

from __future__ import annotations

import argparse
import os
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from bench.common import DATA
from bench.eval_templates import hdm05_clips
from bench.machine import describe
from daemon.calibration import Labelled, calibrate_class, clip_costs, clip_sets, keyframes_kept, retention
from daemon.templates import THESIS_KEYFRAMES, Generalisation, automatic_keyframes, learn

ACTORS = ("bd", "bk", "dg")
THESIS_TAU = 0.1


@dataclass(frozen=True)
class Result:
    name: str
    counts: dict[str, tuple[int, int, int]]  # "fixed" / "calibrated": TP, FP, FN over held-out clips
    taus: tuple[float, ...]  # calibrated τ per held-out actor
    kept: dict[str, tuple[int, int, int, int]]  # "thesis" / "generalised": kept, of, others kept, of
    generalisations: tuple[Generalisation, ...]
    inside: tuple[float, float | None, float | None, float, float, Generalisation]
    seconds: float


def evaluate(name: str, examples: Labelled) -> Result:
    began = time.perf_counter()
    counts = {"fixed": [0, 0, 0], "calibrated": [0, 0, 0]}
    kept = {"thesis": [0, 0, 0, 0], "generalised": [0, 0, 0, 0]}
    taus, chosen = [], []
    for actor in ACTORS:
        training = {n: [(a, m) for a, m in items if a != actor] for n, items in examples.items()}
        found = calibrate_class(training, name)
        taus.append(found.calibration.tau)
        chosen.append(found.keyframes)
        train = [m for _, m in training[name]]
        learned = learn(train, keyframes=0, name=name)
        positives = [m for a, m in examples[name] if a == actor]
        negatives = [m for n, items in examples.items() if n != name for a, m in items if a == actor]
        pos, neg = (
            clip_costs(learned.quantised, positives, "toolbox"),
            clip_costs(learned.quantised, negatives, "toolbox"),
        )
        for key, tau in (("fixed", THESIS_TAU), ("calibrated", found.calibration.tau)):
            tp, fp = int((pos <= tau).sum()), int((neg <= tau).sum())
            counts[key] = [counts[key][0] + tp, counts[key][1] + fp, counts[key][2] + len(pos) - tp]
        pos_sets, neg_sets = clip_sets(positives), clip_sets(negatives)
        for key, g in (("thesis", THESIS_KEYFRAMES), ("generalised", found.keyframes)):
            query = automatic_keyframes(learned.hard.template, train, 3, name, 30.0, g)
            k_pos, k_neg = keyframes_kept(query, pos_sets, 30.0), keyframes_kept(query, neg_sets, 30.0)
            old = kept[key]
            kept[key] = [
                old[0] + int(k_pos.sum()),
                old[1] + len(positives),
                old[2] + int(k_neg.sum()),
                old[3] + len(negatives),
            ]
    whole = calibrate_class(examples, name)
    c = whole.calibration
    inside = (
        c.tau,
        c.recall,
        c.precision,
        min(retention(whole.folds, THESIS_KEYFRAMES)),
        min(retention(whole.folds, whole.keyframes)),
        whole.keyframes,
    )
    return Result(
        name,
        {k: (v[0], v[1], v[2]) for k, v in counts.items()},
        tuple(taus),
        {k: (v[0], v[1], v[2], v[3]) for k, v in kept.items()},
        tuple(chosen),
        inside,
        time.perf_counter() - began,
    )


def _rates(tp: int, fp: int, fn: int) -> str:
    return f"{tp / max(tp + fn, 1):.2f} {tp / max(tp + fp, 1):.2f}"


def _g(g: Generalisation) -> str:
    return f"w{g.window} r{g.margin:g} g{g.min_gap} n{'-' if g.fixed is None else g.fixed}"


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--data", type=Path, default=DATA)
    parser.add_argument("--workers", type=int, default=os.cpu_count() or 1)
    args = parser.parse_args()
    print(describe())
    began = time.perf_counter()
    clips = hdm05_clips(args.data, ACTORS)
    examples: dict[str, list[tuple[str, np.ndarray]]] = {}
    for c in clips:
        examples.setdefault(c.name, []).append((c.actor, c.matrix))
    print(f"features of {len(clips)} clips of {', '.join(ACTORS)} in {time.perf_counter() - began:.1f} s")
    names = sorted(examples)
    with ProcessPoolExecutor(max_workers=args.workers) as pool:
        results = list(pool.map(evaluate, names, [examples] * len(names)))

    print("\nHeld out (each actor in turn; learned and calibrated on the other two), clips retrieved:")
    print(
        f"{'class':30s} {'τ=0.1 R  P':>11s} {'calibrated R  P':>16s}  {'τ per held-out bd/bk/dg':24s} "
        f"{'keyframes kept: thesis':>22s} {'generalised':>12s} {'others kept thesis/gen.':>24s}"
    )
    for r in results:
        t, g = r.kept["thesis"], r.kept["generalised"]
        print(
            f"{r.name:30s} {_rates(*r.counts['fixed']):>11s} {_rates(*r.counts['calibrated']):>16s}  "
            f"{' '.join(f'{x:.3f}' for x in r.taus):24s} {f'{t[0]}/{t[1]}':>22s} {f'{g[0]}/{g[1]}':>12s} "
            f"{f'{t[2]}/{t[3]}  {g[2]}/{g[3]}':>24s}"
        )
    total = {k: np.sum([r.counts[k] for r in results], axis=0) for k in ("fixed", "calibrated")}
    print(f"{'all classes':30s} {_rates(*total['fixed']):>11s} {_rates(*total['calibrated']):>16s}")

    print("\nIn-sample (calibrated over bd, bk, dg: 3 folds, as mocapd learn does):")
    print(
        f"{'class':30s} {'τ':>7s} {'recall':>6s} {'prec.':>6s} {'worst fold kept: thesis':>24s} "
        f"{'generalised':>11s}  generalisation (window, margin, min gap, fixed per keyframe)"
    )
    for r in results:
        tau, recall, precision, before, after, chosen = r.inside
        print(
            f"{r.name:30s} {tau:7.4f} {recall or 0:6.2f} {precision or 0:6.2f} {before:24.2f} "
            f"{after:11.2f}  {_g(chosen)}"
        )
    print(
        f"\ntotal {time.perf_counter() - began:.0f} s ({args.workers} workers; "
        f"{sum(r.seconds for r in results):.0f} s of work)"
    )


if __name__ == "__main__":
    main()
