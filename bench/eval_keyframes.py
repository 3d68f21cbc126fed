"""Thesis Table 5.2 on the HDM05 clips in ../shared/data/mocap: all cut clips indexed as one database
(30 Hz), each class's published manual keyframes run as they are.

    python -m bench.eval_keyframes [--data DIR]

Per class: relevant clips (gamma), hits (Ω^Z components), true positives (hits inside a clip of the
class), false negatives (clips of the class without a hit), false positives (hits in clips of other
classes), the share of the database kept (%(D)) and the search time.
"""

from __future__ import annotations

import argparse
import json
import time
from dataclasses import dataclass
from pathlib import Path

from bench.common import DATA
from bench.machine import describe
from daemon.keyframes import parse_keyframe_queries
from daemon.recordings import ManifestRow
from daemon.search.keyframes import keyframe_search
from daemon.search.store import MotionIndex, build_index

KEYFRAMES = Path(__file__).resolve().parents[1].parent / "shared" / "reference" / "manual-keyframes.json"


@dataclass(frozen=True)
class ClassResult:
    name: str
    relevant: int
    hits: int
    true_positives: int
    false_negatives: int
    false_positives: int
    kept: float  # share of the database's frames, 0..1
    seconds: float


def hdm05_rows(data: Path) -> list[ManifestRow]:
    """Every HDM05 cut clip, with its actor's skeleton; the class is the clip's directory."""
    rows = []
    for i, amc in enumerate(sorted((data / "hdm05" / "cut").glob("*/*.amc.gz")), start=2):
        asf = data / "hdm05" / "asf" / f"HDM_{amc.name.split('_')[1]}.asf"
        rows.append(ManifestRow(i, str(asf), str(amc), asf, amc))
    return rows


def evaluate(index: MotionIndex, classes: list[str], keyframes: Path = KEYFRAMES) -> list[ClassResult]:
    """Run every class of ``classes`` (the class of each document) that has published keyframes."""
    queries = parse_keyframe_queries(json.loads(keyframes.read_text()), str(keyframes))
    frames = [d.frames for d in index.documents]
    out = []
    for name in sorted(set(classes) & set(queries)):
        began = time.perf_counter()
        hits = keyframe_search(index.sets, frames, queries[name], index.rate)
        seconds = time.perf_counter() - began
        relevant = {d for d, c in enumerate(classes) if c == name}
        docs = hits.doc.tolist()
        tp = sum(d in relevant for d in docs)
        out.append(
            ClassResult(
                name,
                len(relevant),
                len(docs),
                tp,
                len(relevant - set(docs)),
                len(docs) - tp,
                hits.frames / index.n_frames,
                seconds,
            )
        )
    return out


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--data", type=Path, default=DATA)
    args = parser.parse_args()
    print(describe())
    rows = hdm05_rows(args.data)
    began = time.perf_counter()
    index = build_index(rows)
    print(
        f"database: {len(rows)} HDM05 cut clips, {index.n_frames} frames at 30 Hz, "
        f"indexed in {time.perf_counter() - began:.1f} s"
    )
    classes = [r.amc.parent.name for r in rows]
    print(f"{'class':30s} {'rel':>4s} {'hits':>5s} {'TP':>4s} {'FN':>4s} {'FP':>4s} {'%(D)':>6s} {'ms':>6s}")
    for r in evaluate(index, classes):
        print(
            f"{r.name:30s} {r.relevant:4d} {r.hits:5d} {r.true_positives:4d} {r.false_negatives:4d} "
            f"{r.false_positives:4d} {100 * r.kept:6.2f} {1e3 * r.seconds:6.2f}"
        )


if __name__ == "__main__":
    main()
