"""Build the library that ships inside mocapd (``daemon/data/library``, package data): the 11 HDM05
classes of actors bd, bk, dg and the 7 mocap6 exercise classes of CMU 13_29, 13_30, 14_14 (one
example per repetition), learned exactly as ``mocapd learn`` learns them, so ``mocapd detect`` needs
no training step.

    python -m bench.shipped_library [--data ../shared/data/mocap] [--out daemon/data/library]
                                    [--keyframes FILE]

1. The training set (:func:`daemon.tools.shipped.training_rows`): every HDM05 cut clip of the 11 classes
   by bd, bk and dg, and every repetition of the mocap6 runs cut by :mod:`daemon.tools.mocap6`; the actor
   is the HDM05 actor or the CMU subject (13_29 and 13_30 are both subject 13; 14_14 is read with
   13.asf, there being no 14.asf).
2. Every class learned by :func:`daemon.learn.library.learn_library`, the code ``mocapd learn`` runs with
   its defaults: soft, quantised and hard MT at 30 Hz; τ, the number of templates and the keyframe
   gate (or the stream-wide DTW) from folds that leave each of the five people out. No published
   keyframes: ``--keyframes FILE`` (e.g. ``../shared/reference/manual-keyframes.json``) gates the
   classes the file names with its keyframes, as ``mocapd learn --keyframes FILE`` does.
3. Written atomically as the library directory ``--out`` with ``training.csv``, the manifest used
   (paths relative to the repository root, ``../shared/...``; ``mocapd learn --manifest`` reads it
   when it lies in the repository root).

Progress goes to stderr; the table of classes (mode, τ and how it was obtained) and the times to
stdout.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

from bench.common import DATA
from bench.machine import describe
from daemon.keyframes import KeyframeQuery, parse_keyframe_queries
from daemon.learn.library import check_library_target, learn_library, save_library
from daemon.library import Library
from daemon.recordings import Examples, read_example
from daemon.tools.shipped import RATE, manifest_csv, training_items, training_rows

REPO = Path(__file__).resolve().parents[1]
OUT = REPO / "daemon" / "data" / "library"
MANIFEST = "training.csv"
TAU = 0.1


def log(message: str) -> None:
    print(message, file=sys.stderr, flush=True)


def read_training(data: Path, out: Path) -> tuple[str, Examples]:
    """The training manifest's text and every class's examples (features at :data:`RATE`)."""
    rows = training_rows(data, REPO, lambda trial, n: log(f"cut {trial}: {n} repetitions"))
    items = training_items(rows, REPO)
    source = out / MANIFEST
    examples: Examples = {}
    for i, item in enumerate(items, start=1):
        clip, matrix = read_example(item, source, rate=RATE)
        examples.setdefault(item.name, []).append((clip, matrix))
        if i % 25 == 0 or i == len(items):
            log(f"[{i}/{len(items)}] examples read")
    return manifest_csv(rows), examples


def print_classes(library: Library) -> None:
    print("\nclasses: how each is recognised and its τ (folds: the left-out people's streams)")
    print(
        f"{'class':28s} {'clips':>5s} {'actors':>6s} {'tmpl':>4s} {'mode':>9s} {'τ':>7s} {'recall':>6s} "
        f"{'prec.':>6s}  why"
    )
    for name, cls in library.classes.items():
        c = cls.provenance
        actors = len({t.actor for t in cls.training})
        rates = f"{c.recall:6.2f} {c.precision:6.2f}" if c.calibrated else f"{'-':>6s} {'-':>6s}"
        taus = "/".join(f"{t:.3f}" for _, t in cls.members)
        print(
            f"{name:28s} {len(cls.training):5d} {actors:6d} {len(cls.members):4d} {cls.mode:>9s} {taus:>7s} "
            f"{rates}  {cls.mode_reason}" + ("" if c.calibrated else f"; τ {c.method}")
        )


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--data", type=Path, default=DATA, help="the shared motion data")
    parser.add_argument("--out", type=Path, default=OUT, help="library directory to write (replaced)")
    parser.add_argument("--keyframes", type=Path, default=None, help="keyframes that gate the classes named")
    parser.add_argument("--tau", type=float, default=TAU, help="τ of a class that cannot be calibrated")
    args = parser.parse_args()
    print(describe())
    args.out.parent.mkdir(parents=True, exist_ok=True)
    check_library_target(args.out)  # before the long part
    began = time.perf_counter()
    manifest, examples = read_training(args.data, args.out)
    read = time.perf_counter() - began
    clips = sum(map(len, examples.values()))
    print(f"training set: {clips} examples of {len(examples)} classes, read in {read:.1f} s")
    given: dict[str, KeyframeQuery] = {}
    if args.keyframes is not None:
        given = parse_keyframe_queries(json.loads(args.keyframes.read_text()), str(args.keyframes))
    started = time.perf_counter()
    learned = learn_library(
        examples,
        tau=args.tau,
        rate=RATE,
        given_keyframes={n: q for n, q in given.items() if n in examples},
        progress=lambda m: log(f"[{time.perf_counter() - started:.0f} s] {m}"),
    )
    learning = time.perf_counter() - started
    if learned.calibrated is not None:
        c = learned.calibrated
        print(
            f"folds: {len(c.folds)} ({c.groups}); τ placed {c.position:g} of the way "
            f"(nested F1 {dict(c.position_f1)})"
        )
    print_classes(learned.library)
    save_library(learned.library, args.out, {MANIFEST: manifest})
    size = sum(p.stat().st_size for p in args.out.iterdir())
    print(
        f"\nlibrary: {args.out} ({len(learned.library.classes)} classes, {size / 1024:.0f} KiB); reading and "
        f"cutting {read:.1f} s, learning {learning:.1f} s, total {time.perf_counter() - began:.1f} s"
    )


if __name__ == "__main__":
    main()
