"""Thesis Tables 3.1 and 5.2 on the HDM05 clips in ../shared/data/mocap: every class learned from the
cut clips of actors bd and bk, searched in a database of all actor-dg clips (30 Hz).

    python -m bench.eval_templates [--data DIR] [--steps toolbox|thesis] [--png FILE]

Table 3.1: per class, for each τ, the hits with cost <= τ and the relevant ones among them (hits in
a dg clip of the class), ranking the whole database with the quantised soft MT (δ = 0.1, at most
500 hits as the thesis). Table 5.2: the same ranking at τ = 0.1 only inside the ranges a keyframe
search kept, with the learned (automatic, thesis ch. 6) and the published (manual) keyframes: false
negatives (relevant clips without a hit), false positives (hits outside the class's clips) and the
share of the database kept. The thesis' own figures (D57 database, 36,551 frames) are printed beside.
"""

from __future__ import annotations

import argparse
import json
import time
from collections.abc import Collection, Iterable
from dataclasses import dataclass
from pathlib import Path

from bench.common import DATA
from bench.eval_keyframes import KEYFRAMES, hdm05_rows
from bench.machine import describe
from daemon.dtw import Steps
from daemon.keyframes import KeyframeQuery, parse_keyframe_queries
from daemon.learn.library import learn_class
from daemon.library import ClassTemplate
from daemon.search.retrieval import TemplateHits, frame_codes, template_search
from daemon.search.store import Document, index_from_matrices, read_document
from daemon.types import BoolArray, TrainingClip

TAUS = (0.02, 0.04, 0.06, 0.08, 0.1)
LIMIT = 500
# Thesis Table 3.1 (γ; |H_τ| at τ = 0.02 .. 0.1) and Table 5.2 (FN, FP, %(D)) for the classes here.
THESIS = {
    "depositFloorR": (16, (8, 12, 14, 24, 37), (1, 12, 10.00)),
    "elbowToKnee1RepsLelbowStart": (13, (7, 13, 13, 15, 22), (0, 0, 1.27)),
    "grabHighR": (14, (18, 25, 29, 57, 117), (2, 10, 3.61)),
    "hopBothLegs1hops": (18, (17, 22, 28, 81, 273), (1, 4, 1.72)),
    "jogLeftCircle4StepsRstart": (8, (15, 31, 35, 59, 81), (0, 1, 1.48)),
    "kickLFront1Reps": (16, (12, 15, 16, 16, 16), (0, 16, 4.35)),
    "lieDownFloor": (10, (5, 8, 11, 15, 23), (0, 0, 4.33)),
    "rotateArmsBothBackward1Reps": (8, (7, 8, 8, 11, 30), (0, 0, 0.61)),
    "sneak2StepsLStart": (8, (7, 35, 68, 146, 220), (0, 1, 1.31)),
    "squat1Reps": (26, (24, 26, 26, 26, 27), (0, 0, 3.48)),
    "throwBasketball": (7, (5, 6, 7, 7, 7), (0, 0, 2.41)),
}


@dataclass(frozen=True)
class Clip:
    """An HDM05 cut clip: its class, actor, provenance, document and 30 Hz features ``(frames, 39)``."""

    name: str
    actor: str
    clip: TrainingClip
    document: Document
    matrix: BoolArray


def hdm05_clips(data: Path, actors: Collection[str]) -> list[Clip]:
    """Every HDM05 cut clip of ``actors``, features at 30 Hz."""
    out = []
    for row in hdm05_rows(data):
        actor = row.amc.name.split("_")[1]
        if actor in actors:
            d, matrix = read_document(row)
            clip = TrainingClip(row.asf_text, row.amc_text, d.first_amc_frame, d.last_amc_frame, d.frames)
            out.append(Clip(row.amc.parent.name, actor, clip, d, matrix))
    return out


def training_sets(clips: Iterable[Clip]) -> dict[str, list[tuple[TrainingClip, BoolArray]]]:
    """The clips' (provenance, features) by class, as learn_class takes them."""
    out: dict[str, list[tuple[TrainingClip, BoolArray]]] = {}
    for c in clips:
        out.setdefault(c.name, []).append((c.clip, c.matrix))
    return out


def counts(hits: TemplateHits, relevant: set[int], tau: float) -> tuple[int, int, int]:
    """Hits with cost <= tau, those in relevant documents, and the relevant documents found."""
    inside = hits.cost <= tau
    docs = hits.doc[inside].tolist()
    good = [d for d in docs if d in relevant]
    return len(docs), len(good), len(set(good))


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--data", type=Path, default=DATA)
    parser.add_argument("--steps", choices=("thesis", "toolbox"), default="toolbox")
    parser.add_argument("--png", type=Path, default=None, help="precision/recall over τ per class")
    args = parser.parse_args()
    steps: Steps = args.steps
    print(describe())
    began = time.perf_counter()
    clips = hdm05_clips(args.data, ("bd", "bk", "dg"))
    training = training_sets(c for c in clips if c.actor in ("bd", "bk"))
    test = [c for c in clips if c.actor == "dg"]
    database, documents = [c.matrix for c in test], [c.document for c in test]
    classes = [c.name for c in test]
    index = index_from_matrices(database, documents, 30.0)
    codes = frame_codes(index)
    print(
        f"features of {len(clips)} clips in {time.perf_counter() - began:.1f} s; training: "
        f"{sum(map(len, training.values()))} bd/bk clips; database: {len(documents)} dg clips, "
        f"{index.n_frames} frames at 30 Hz; DTW steps: {steps}"
    )
    published = parse_keyframe_queries(json.loads(KEYFRAMES.read_text()), str(KEYFRAMES))
    learned: dict[str, ClassTemplate] = {}
    print(
        f"\n{'class':30s} {'train':>5s} {'K':>4s} {'iter':>4s} {'hard K':>6s} "
        f"{'keyframes (set@column)':24s} {'s':>6s}"
    )
    for name in sorted(training):
        t0 = time.perf_counter()
        cls = learn_class(name, training[name], steps=steps)
        learned[name] = cls
        assert cls.keyframes is not None
        kf = " ".join(f"{k.feature_set}@{k.position}" for k in cls.keyframes.keyframes)
        print(
            f"{name:30s} {len(training[name]):5d} {cls.quantised.length:4d} {cls.iterations:4d} "
            f"{cls.hard.length:6d} {kf:24s} {time.perf_counter() - t0:6.1f}"
        )

    print(
        "\nTable 3.1: hits / relevant hits for τ = " + ", ".join(f"{t:g}" for t in TAUS) + " (thesis: hits)"
    )
    curves = {}
    for name, cls in learned.items():
        relevant = {d for d, c in enumerate(classes) if c == name}
        t0 = time.perf_counter()
        hits = template_search(index, cls.quantised, tau=max(TAUS), steps=steps, limit=LIMIT, codes=codes)
        ms = 1e3 * (time.perf_counter() - t0)
        table = [counts(hits, relevant, t) for t in TAUS]
        curves[name] = [(good / max(n, 1), found / len(relevant)) for n, good, found in table]
        ours = "  ".join(f"{n:3d}/{good:<3d}" for n, good, _ in table)
        gamma, thesis_hits, _ = THESIS.get(name, (0, (), ()))
        theirs = " ".join(f"{h:3d}" for h in thesis_hits)
        n, good, found = table[-1]
        print(
            f"{name:30s} γ={len(relevant):2d}  {ours}  recall {found / len(relevant):.2f} "
            f"precision {good / max(n, 1):.2f} ({ms:.0f} ms)   thesis γ={gamma}: {theirs}"
            + (f" precision <= {min(gamma, thesis_hits[-1]) / thesis_hits[-1]:.2f}" if thesis_hits else "")
        )

    print("\nTable 5.2: keyframe pre-selection, then ranking at τ = 0.1: FN / FP / %(D) kept / ms")
    print(
        f"{'class':30s} {'learned keyframes':>24s} {'published keyframes':>24s} {'thesis (published)':>20s}"
    )
    for name, cls in learned.items():
        relevant = {d for d, c in enumerate(classes) if c == name}
        cells = []
        queries: list[KeyframeQuery | None] = [cls.keyframes, published.get(name)]
        for query in queries:
            if query is None:
                cells.append(f"{'-':>24s}")
                continue
            t0 = time.perf_counter()
            hits = template_search(
                index, cls.quantised, tau=0.1, steps=steps, keyframes=query, limit=LIMIT, codes=codes
            )
            ms = 1e3 * (time.perf_counter() - t0)
            n, good, found = counts(hits, relevant, 0.1)
            share = 100 * hits.searched / index.n_frames
            cells.append(f"{f'{len(relevant) - found:3d} {n - good:3d} {share:6.2f} {ms:6.1f}':>24s}")
        fn, fp, kept = THESIS.get(name, (0, (), (0, 0, 0.0)))[2]
        print(f"{name:30s} {cells[0]} {cells[1]} {fn:6d} {fp:3d} {kept:6.2f}")
    if args.png is not None:
        from daemon.plots import precision_recall_png

        precision_recall_png(curves, TAUS, args.png)
        print(f"\nprecision/recall: {args.png}")


if __name__ == "__main__":
    main()
