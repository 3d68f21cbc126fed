"""``mocapd learn``: motion templates and keyframes from labelled clips."""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from typing import Any

from daemon.calibration import MOST_GENERAL, Calibration, ClassCalibration, calibrate_class, given
from daemon.cli import common
from daemon.config import Config
from daemon.dtw import STEPS, Steps
from daemon.errors import UsageError
from daemon.library import ClassTemplate, Library, check_library_target, learn_class, save_library
from daemon.plots import template_png
from daemon.recordings import Examples, TrainingClip, read_examples
from daemon.storage import together
from daemon.templates import THESIS_KEYFRAMES, Generalisation
from daemon.types import DEFAULT_INDEX_RATE


def register(sub: Any) -> None:
    learn = sub.add_parser("learn", help="learn motion templates and keyframes from labelled clips")
    learn.add_argument(
        "--manifest",
        type=Path,
        required=True,
        help="CSV with columns class, asf, amc and optionally start_frame, end_frame (AMC frames) and "
        "actor (the person; default: the ASF file)",
    )
    learn.add_argument("--out", type=Path, required=True, help="library directory to write (replaced)")
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
        "--keyframes", type=int, default=3, metavar="K", help="keyframes chosen per class (3; 0: none)"
    )
    learn.add_argument(
        "--steps",
        choices=STEPS,
        default="toolbox",
        help="DTW steps for retrieval: toolbox (1,1),(1,2),(2,1) (default) or thesis (1,0),(0,1),(1,1)",
    )
    common.native_rate_option(learn)
    learn.set_defaults(func=_learn)


def _learn(args: argparse.Namespace, config: Config) -> int:
    if not 0 <= args.delta < 0.5:
        raise UsageError(f"--delta must lie in [0, 0.5), got {args.delta:g}")
    if args.keyframes < 0:
        raise UsageError(f"--keyframes must not be negative, got {args.keyframes}")
    check_library_target(args.out)  # before the long part
    if args.png is not None:
        common.check_png_output(args.png, directory=True)
    began = time.perf_counter()

    def progress(done: int, total: int, clip: TrainingClip) -> None:
        print(
            f"[{done}/{total}] {clip.amc} ({clip.frames} frames at {args.fps:g} Hz)",
            file=sys.stderr,
            flush=True,
        )

    examples = read_examples(
        args.manifest,
        rate=args.fps,
        progress=progress,
        default_native_rate=common.default_native_rate(args, config),
    )
    actors = {clip.actor for items in examples.values() for clip, _ in items}
    classes: dict[str, ClassTemplate] = {}
    for i, (name, items) in enumerate(examples.items(), start=1):
        started = time.perf_counter()
        cls, found = learn_one(
            examples,
            name,
            tau=args.tau,
            delta=args.delta,
            keyframes=args.keyframes,
            steps=args.steps,
            rate=args.fps,
            calibrate=args.calibrate,
        )
        generalisation = THESIS_KEYFRAMES if found is None else found.keyframes
        classes[name] = cls
        keyframes = 0 if cls.keyframes is None else len(cls.keyframes.keyframes)
        print(
            f"[class {i}/{len(examples)}] {name}: {len(items)} examples, soft MT {cls.soft.length} "
            f"columns after {cls.iterations} iterations, hard MT {cls.hard.length} columns, "
            f"{keyframes} keyframes{_widened(generalisation) if keyframes else ''}, tau {cls.tau:.4g} "
            f"({time.perf_counter() - started:.1f} s)",
            file=sys.stderr,
            flush=True,
        )
    with together():  # an interrupted run leaves the previous library and pictures, all of them
        if args.png is not None:
            for name, cls in classes.items():
                _draw(cls, args.png / f"{name}.png", args.fps)
        save_library(Library(args.fps, classes), args.out)
    print(f"library:    {args.out}")
    print(f"classes:    {len(classes)} ({', '.join(classes)})")
    print(f"examples:   {sum(len(c.training) for c in classes.values())} at {args.fps:g} Hz")
    print(f"actors:     {len(actors)}")
    for i, (name, cls) in enumerate(classes.items()):
        print(f"{'tau:' if i == 0 else '':<11} {name} {_describe(cls.provenance)}")
    print(f"learn time: {time.perf_counter() - began:.1f} s")
    return 0


def learn_one(
    examples: Examples,
    name: str,
    *,
    tau: float = 0.1,
    delta: float = 0.1,
    keyframes: int = 3,
    steps: Steps = "toolbox",
    rate: float = DEFAULT_INDEX_RATE,
    calibrate: bool = True,
) -> tuple[ClassTemplate, ClassCalibration | None]:
    """Class ``name`` of ``examples`` (every class's clips and their ``(frames, 39)`` features at
    ``rate`` Hz, as :func:`daemon.recordings.read_examples` gives them) learned as ``mocapd learn``
    learns it: τ and the keyframe generalisation by leave-one-actor-out over all classes
    (:func:`daemon.calibration.calibrate_class`) when ``calibrate`` and the examples name at least
    2 actors; with one actor ``tau`` given (and why) and the most general keyframes
    (:data:`daemon.calibration.MOST_GENERAL`). Returns the class and its calibration (None with
    ``calibrate`` False: τ given, the thesis' keyframes)."""
    found: ClassCalibration | None = None
    if not calibrate:
        calibration, generalisation = given(tau, "--no-calibrate"), THESIS_KEYFRAMES
    else:
        actors = {clip.actor for items in examples.values() for clip, _ in items}
        if len(actors) < 2:
            why = f"{len(actors)} actor in the manifest: no leave-one-actor-out"
            found = ClassCalibration(given(tau, why), MOST_GENERAL, ())
        else:
            labelled = {n: [(clip.actor, m) for clip, m in items] for n, items in examples.items()}
            found = calibrate_class(
                labelled, name, tau=tau, delta=delta, keyframes=keyframes, steps=steps, rate=rate
            )
        calibration, generalisation = found.calibration, found.keyframes
    cls = learn_class(
        name,
        examples[name],
        delta=delta,
        tau=tau,
        keyframes=keyframes,
        steps=steps,
        rate=rate,
        calibration=calibration,
        generalisation=generalisation,
    )
    return cls, found


def _widened(g: Generalisation) -> str:
    if g == THESIS_KEYFRAMES:
        return ""
    fixed = "all" if g.fixed is None else g.fixed
    return (
        f" (generalised: window {g.window}, gap margin {g.margin:g}, min gap {g.min_gap}, "
        f"{fixed} fixed features)"
    )


def _describe(c: Calibration) -> str:
    if not c.calibrated:
        return f"{c.tau:.4g} {c.method}"
    return (
        f"{c.tau:.4g} calibrated: recall {c.recall:.2f}, precision {c.precision:.2f} on {c.positives} "
        f"positive and {c.negatives} negative left-out clips ({c.folds} folds)"
    )


def _draw(cls: ClassTemplate, path: Path, rate: float) -> None:
    """The class's soft and hard MT with its keyframe columns, as ``path``."""
    columns = [] if cls.keyframes is None else [k.position for k in cls.keyframes.keyframes]
    soft, hard = cls.soft.values, cls.hard.values
    common.write_png(path, lambda out: template_png(soft, hard, columns, out, cls.name, rate))
