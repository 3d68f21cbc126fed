"""Build the library that ships inside mocapd (``daemon/data/library``, package data): the 11 HDM05
classes of actors bd, bk, dg and the 7 mocap6 exercise classes of CMU 13_29, 13_30, 14_14 (one
example per repetition), learned as ``mocapd learn`` learns them, so ``mocapd detect`` needs no
training step.

    python -m bench.shipped_library [--data ../shared/data/mocap] [--out daemon/data/library]

1. The training set (:func:`daemon.shipped.training_rows`): every HDM05 cut clip of the 11 classes
   by bd, bk and dg, and every repetition of the mocap6 runs cut by :mod:`daemon.mocap6`; the actor
   is the HDM05 actor or the CMU subject (13_29 and 13_30 are both subject 13; 14_14 is read with
   13.asf, there being no 14.asf).
2. Every class learned by :func:`daemon.cli.learn.learn_one`, the code ``mocapd learn`` runs: soft,
   quantised and hard MT at 30 Hz, τ by leave-one-actor-out (best F1 with recall >= 0.95 on the
   left-out actor), keyframes generalised as that calibration chooses; a class of one actor gets
   τ = ``--tau``, recorded as given. Classes are learned in parallel (``--workers``), each exactly
   as ``mocapd learn`` would.
3. The HDM05 classes' published keyframes (``../shared/reference/manual-keyframes.json``) replace
   the learned ones where they do better on the training data, judged by the same
   leave-one-actor-out folds: for each left-out actor, the learned keyframes (learned on the other
   actors, generalised as calibration chose) and the published ones are run over the actor's clips;
   a clip of the class is kept when the keyframe search returns a component in it, a clip of
   another class of that actor with a component is a false hit. Rule: published replaces learned
   when, pooled over the folds, it keeps at least as many held-out clips and has no more false hits
   (:func:`daemon.calibration.prefer_published`). The generalisation was chosen on the same folds,
   which favours the learned keyframes, so the rule errs towards keeping them.
4. Written atomically as the library directory ``--out`` with ``training.csv``, the manifest used
   (paths relative to the repository root, ``../shared/...``; ``mocapd learn --manifest`` reads it
   when it lies in the repository root).

Progress goes to stderr; the keyframe table, the τ table and the times to stdout.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import sys
import time
from concurrent.futures import Future, ProcessPoolExecutor, as_completed
from pathlib import Path

from bench.common import DATA
from bench.eval_keyframes import KEYFRAMES
from bench.machine import describe
from daemon.calibration import (
    ClassCalibration,
    HeldOutKeyframes,
    held_out_learned,
    held_out_query,
    prefer_published,
)
from daemon.cli.learn import learn_one
from daemon.keyframes import KeyframeQuery, parse_keyframe_queries
from daemon.library import PUBLISHED, ClassTemplate, Library, check_library_target, save_library
from daemon.recordings import Examples, read_example
from daemon.shipped import HDM05_CLASSES, RATE, manifest_csv, training_items, training_rows
from daemon.templates import THESIS_KEYFRAMES, Generalisation

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
        log(
            f"[{i}/{len(items)}] {item.name}: {clip.amc} frames {clip.start_frame}..{clip.end_frame} "
            f"({clip.frames} frames at {RATE:g} Hz)"
        )
    return manifest_csv(rows), examples


Learned = tuple[ClassTemplate, ClassCalibration | None, float]


def _learn(examples: Examples, name: str, tau: float) -> Learned:
    began = time.perf_counter()
    cls, found = learn_one(examples, name, tau=tau, rate=RATE)
    return cls, found, time.perf_counter() - began


def learn_all(examples: Examples, tau: float, workers: int) -> dict[str, Learned]:
    """Every class learned by :func:`daemon.cli.learn.learn_one`, ``workers`` classes at a time."""
    done: dict[str, Learned] = {}
    with ProcessPoolExecutor(max_workers=workers) as pool:
        # the slowest (longest templates, most clips) first, so the workers finish together
        order = sorted(examples, key=lambda n: -sum(len(m) for _, m in examples[n]))
        futures: dict[Future[Learned], str] = {pool.submit(_learn, examples, n, tau): n for n in order}
        for future in as_completed(futures):
            name = futures[future]
            done[name] = cls, _, seconds = future.result()
            keyframes = 0 if cls.keyframes is None else len(cls.keyframes.keyframes)
            log(
                f"[class {len(done)}/{len(examples)}] {name}: {len(cls.training)} examples, soft MT "
                f"{cls.soft.length} columns, {keyframes} keyframes, tau {cls.tau:.4g} ({seconds:.1f} s)"
            )
    return {name: done[name] for name in examples}


def _g(g: Generalisation) -> str:
    if g == THESIS_KEYFRAMES:
        return "thesis rule"
    return f"w{g.window} r{g.margin:g} g{g.min_gap} n{'-' if g.fixed is None else g.fixed}"


def _pooled(h: list[HeldOutKeyframes]) -> str:
    kept, clips = sum(x.kept for x in h), sum(x.clips for x in h)
    false, others = sum(x.false for x in h), sum(x.others for x in h)
    folds = " ".join(f"{x.kept}/{x.clips}" for x in h)
    return f"{kept:3d}/{clips:<3d} ({folds:14s}) {false:3d}/{others:<4d}"


def keyframe_choice(
    examples: Examples, learned: dict[str, Learned], published: dict[str, KeyframeQuery]
) -> dict[str, tuple[bool, list[HeldOutKeyframes], list[HeldOutKeyframes]]]:
    """Per HDM05 class learned with calibration and published: whether
    :func:`daemon.calibration.prefer_published` takes the published keyframes, and the held-out
    figures of the learned and of the published ones."""
    labelled = {n: [(clip.actor, m) for clip, m in items] for n, items in examples.items()}
    out = {}
    for name in HDM05_CLASSES:
        query = published.get(name)
        if name not in learned or query is None or learned[name][1] is None:
            continue
        found = learned[name][1]
        assert found is not None
        mine = held_out_learned(found)
        theirs = held_out_query(labelled, name, query, [h.actor for h in mine], RATE)
        out[name] = (prefer_published(mine, theirs), mine, theirs)
    return out


def with_keyframes(
    learned: dict[str, Learned],
    published: dict[str, KeyframeQuery],
    choice: dict[str, tuple[bool, list[HeldOutKeyframes], list[HeldOutKeyframes]]],
) -> dict[str, ClassTemplate]:
    """The classes, with the published keyframes where ``choice`` takes them."""
    out = {name: cls for name, (cls, _, _) in learned.items()}
    for name, (use, _, _) in choice.items():
        if use:
            out[name] = dataclasses.replace(out[name], keyframes=published[name], keyframe_source=PUBLISHED)
    return out


def choose_keyframes(
    examples: Examples, learned: dict[str, Learned], published: dict[str, KeyframeQuery]
) -> dict[str, ClassTemplate]:
    """The classes with the published keyframes in place of the learned ones where
    :func:`daemon.calibration.prefer_published` says so; prints the table."""
    choice = keyframe_choice(examples, learned, published)
    print(
        "\nKeyframes, leave-one-actor-out on the training data: held-out clips of the class kept "
        "(per fold) and false hits (clips of other classes of the left-out actor with a hit)"
    )
    print(
        f"{'class':28s} {'learned: kept (bd bk dg)':>28s} {'false':>8s} "
        f"{'published: kept (bd bk dg)':>28s} {'false':>8s}  chosen     learned generalisation"
    )
    for name, (use, mine, theirs) in choice.items():
        found = learned[name][1]
        assert found is not None
        print(
            f"{name:28s} {_pooled(mine)} {_pooled(theirs)}  {'published' if use else 'learned':10s} "
            f"{_g(found.keyframes)}"
        )
    return with_keyframes(learned, published, choice)


def print_taus(classes: dict[str, ClassTemplate], learned: dict[str, Learned]) -> None:
    print("\nτ per class and how it was obtained")
    print(
        f"{'class':28s} {'clips':>5s} {'actors':>6s} {'τ':>7s} {'recall':>6s} {'prec.':>6s} "
        f"{'pos/neg':>8s} {'s':>6s}  method"
    )
    for name, cls in classes.items():
        c = cls.provenance
        actors = len({t.actor for t in cls.training})
        rates = f"{c.recall:6.2f} {c.precision:6.2f}" if c.calibrated else f"{'-':>6s} {'-':>6s}"
        counts = f"{c.positives}/{c.negatives}" if c.calibrated else "-"
        print(
            f"{name:28s} {len(cls.training):5d} {actors:6d} {cls.tau:7.4f} {rates} {counts:>8s} "
            f"{learned[name][2]:6.1f}  {c.method}"
        )


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--data", type=Path, default=DATA, help="the shared motion data")
    parser.add_argument("--out", type=Path, default=OUT, help="library directory to write (replaced)")
    parser.add_argument("--published", type=Path, default=KEYFRAMES, help="the published keyframes")
    parser.add_argument("--tau", type=float, default=TAU, help="τ of a class that cannot be calibrated")
    parser.add_argument("--workers", type=int, default=os.cpu_count() or 1)
    args = parser.parse_args()
    print(describe())
    args.out.parent.mkdir(parents=True, exist_ok=True)
    check_library_target(args.out)  # before the long part
    began = time.perf_counter()
    manifest, examples = read_training(args.data, args.out)
    read = time.perf_counter() - began
    clips = sum(map(len, examples.values()))
    print(f"training set: {clips} examples of {len(examples)} classes, read in {read:.1f} s")
    published = parse_keyframe_queries(json.loads(args.published.read_text()), str(args.published))
    started = time.perf_counter()
    learned = learn_all(examples, args.tau, args.workers)
    learning = time.perf_counter() - started
    classes = choose_keyframes(examples, learned, published)
    print_taus(classes, learned)
    save_library(Library(RATE, classes), args.out, {MANIFEST: manifest})
    size = sum(p.stat().st_size for p in args.out.iterdir())
    print(
        f"\nlibrary: {args.out} ({len(classes)} classes, {size / 1024:.0f} KiB); reading and cutting "
        f"{read:.1f} s, learning {learning:.1f} s on {args.workers} workers "
        f"({sum(s for *_, s in learned.values()):.1f} s of work), total {time.perf_counter() - began:.1f} s"
    )


if __name__ == "__main__":
    main()
