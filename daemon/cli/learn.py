"""``mocapd learn``: motion templates, thresholds and keyframe gates from labelled clips."""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from typing import Any

from daemon.checks import read_structured
from daemon.cli import common
from daemon.config import Config
from daemon.dtw import STEPS
from daemon.errors import UsageError
from daemon.keyframes import KeyframeError, KeyframeQuery, parse_keyframe_queries
from daemon.learn.library import check_library_target, learn_library, save_library
from daemon.library import GATED, Calibration, ClassTemplate
from daemon.plots import template_png
from daemon.recordings import read_example_rows, read_training_manifest
from daemon.storage import together
from daemon.tools.repetitions import periodic_examples
from daemon.types import DEFAULT_INDEX_RATE, TrainingClip


def keyframes_option(text: str) -> int | Path:
    """``--keyframes``: a count of keyframes to learn per class, or a keyframe file."""
    try:
        count = int(text)
    except ValueError:
        if not text.strip():
            raise argparse.ArgumentTypeError("must be a count of keyframes or a keyframe file") from None
        return Path(text)
    if count < 0:
        raise argparse.ArgumentTypeError(f"must not be negative, got {count}")
    return count


def register(sub: Any) -> None:
    learn = sub.add_parser("learn", help="learn motion templates and keyframes from labelled clips")
    learn.add_argument(
        "--manifest",
        type=Path,
        required=True,
        help="CSV with columns class, asf, amc (or class, bvh) and optionally start_frame, end_frame "
        "(frames of the recording) and actor (the person; default: the ASF or BVH file)",
    )
    learn.add_argument("--out", type=Path, required=True, help="library directory to write (replaced)")
    learn.add_argument(
        "--rig",
        type=Path,
        default=None,
        metavar="YAML",
        help="a rig map for the manifest's BVH takes, tried before the built-in ones",
    )
    common.rate_option(learn, DEFAULT_INDEX_RATE, "learn at this rate (default 30, as the thesis)")
    learn.add_argument("--png", type=Path, default=None, help="directory for a PNG of each class's MTs")
    learn.add_argument(
        "--tau",
        type=common.positive_float,
        default=0.1,
        help="retrieval threshold stored for a class that is not calibrated (default 0.1)",
    )
    learn.add_argument(
        "--no-calibrate",
        dest="calibrate",
        action="store_false",
        help="store --tau for every class instead of learning each class's threshold by leave-one-actor-"
        "out (the default when the manifest names at least 2 actors)",
    )
    learn.add_argument(
        "--delta", type=float, default=0.1, help="quantisation threshold δ in [0, 0.5) (default 0.1)"
    )
    learn.add_argument(
        "--keyframes",
        type=keyframes_option,
        default=3,
        metavar="K|FILE",
        help="keyframes learned per class: K (3; the folds choose among K-1 .. K+2 and how many "
        "mismatches each tolerates; 0: none, every class recognised by stream-wide DTW), or a JSON file "
        "as manual-keyframes.json whose keyframes the classes it names are recognised by (learned for "
        "the others)",
    )
    learn.add_argument(
        "--steps",
        choices=STEPS,
        default="toolbox",
        help="DTW steps for retrieval: toolbox (1,1),(1,2),(2,1) (default) or thesis (1,0),(0,1),(1,1)",
    )
    learn.add_argument(
        "--repetitions",
        type=common.non_negative_int,
        default=2,
        metavar="N",
        help="learn a periodic class (takes of walking, waving, ...: most of its examples hold two or more "
        "repetitions of one cycle and keep their heading) from the first N single repetitions of each "
        "example (default 2; 0: every example whole)",
    )
    common.native_rate_option(learn)
    learn.set_defaults(func=_learn)


def _learn(args: argparse.Namespace, config: Config) -> int:
    if not 0 <= args.delta < 0.5:
        raise UsageError(f"--delta must lie in [0, 0.5), got {args.delta:g}")
    given: dict[str, KeyframeQuery] = {}
    count = args.keyframes
    if isinstance(count, Path):
        given = parse_keyframe_queries(read_structured(count, "json", KeyframeError), count)
        count = 3
    check_library_target(args.out)  # before the long part
    if args.png is not None:
        common.check_png_output(args.png, directory=True)
    unknown = (
        sorted(set(given) - {row.name for row in read_training_manifest(args.manifest)}) if given else []
    )
    if unknown:
        raise UsageError(
            f"keyframes for classes the manifest lacks: {', '.join(unknown)}", path=args.keyframes
        )
    began = time.perf_counter()

    def progress(done: int, total: int, clip: TrainingClip) -> None:
        print(
            f"[{done}/{total}] {clip.amc} ({clip.frames} frames at {args.fps:g} Hz)",
            file=sys.stderr,
            flush=True,
        )

    rows = read_example_rows(
        args.manifest,
        rate=args.fps,
        progress=progress,
        default_native_rate=common.default_native_rate(args, config),
        maps=common.rig_maps(args, config),
    )
    examples = (
        periodic_examples(
            rows, args.fps, args.repetitions, lambda line: print(line, file=sys.stderr, flush=True)
        )
        if args.repetitions
        else {name: [(e.clip, e.matrix) for e in items] for name, items in rows.items()}
    )
    learned = learn_library(
        examples,
        tau=args.tau,
        delta=args.delta,
        keyframes=count,
        steps=args.steps,
        rate=args.fps,
        calibrate_classes=args.calibrate,
        given_keyframes={n: given[n] for n in given if n in examples},
        progress=lambda message: print(message, file=sys.stderr, flush=True),
    )
    library = learned.library
    with together():  # an interrupted run leaves the previous library and pictures, all of them
        if args.png is not None:
            for name, cls in library.classes.items():
                _draw(cls, args.png / f"{name}.png", args.fps)
        save_library(library, args.out)
    actors = {clip.actor for items in examples.values() for clip, _ in items}
    print(f"library:    {args.out}")
    print(f"classes:    {len(library.classes)} ({', '.join(library.classes)})")
    print(f"examples:   {sum(len(c.training) for c in library.classes.values())} at {args.fps:g} Hz")
    print(f"actors:     {len(actors)}")
    if learned.calibrated is not None:
        c = learned.calibrated
        print(
            f"folds:      {len(c.folds)} ({c.groups} left out); tau placed {c.position:g} of the way to the "
            f"next wrong detection; keyframes tolerate {c.spare} mismatch{'es' if c.spare != 1 else ''} more "
            f"than the folds need, and their windows open {c.wider} step{'s' if c.wider != 1 else ''} "
            "of slack wider"
        )
    for i, (name, cls) in enumerate(library.classes.items()):
        print(f"{'classes:' if i == 0 else '':<11} {name}: {_mode(cls)}; tau {_describe(cls.provenance)}")
    print(f"learn time: {time.perf_counter() - began:.1f} s")
    return 0


def _mode(cls: ClassTemplate) -> str:
    if cls.mode == GATED:
        assert cls.keyframes is not None
        why = cls.mode_reason or cls.keyframe_source
        return (
            why
            if why.startswith("keyframes first")
            else f"keyframes first, {len(cls.keyframes.keyframes)} ({why})"
        )
    return f"stream-wide DTW ({cls.mode_reason})" if cls.mode_reason else "stream-wide DTW"


def _describe(c: Calibration) -> str:
    if not c.calibrated:
        return f"{c.tau:.4g} {c.method}"
    return (
        f"{c.tau:.4g} calibrated: recall {c.recall:.2f}, precision {c.precision:.2f} on {c.positives} "
        f"left-out motions and {c.negatives} wrong candidates ({c.folds} folds)"
    )


def _draw(cls: ClassTemplate, path: Path, rate: float) -> None:
    """The class's soft and hard MT with its keyframe columns, as ``path``."""
    columns = [] if cls.keyframes is None else [k.position for k in cls.keyframes.keyframes]
    soft, hard = cls.soft.values, cls.hard.values
    common.write_png(path, lambda out: template_png(soft, hard, columns, out, cls.name, rate))
