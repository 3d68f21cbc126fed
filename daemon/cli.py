"""The ``mocapd`` command line (also ``python -m daemon``).

Exit status: 0 on success, 2 on bad input (unreadable or malformed files, bad options), with one
line on stderr naming the file and line.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import TextIO

import numpy as np

from daemon.config import Config, ConfigError, Units, load_config
from daemon.dtw import STEPS
from daemon.features import FEATURE_NAMES, decimate, decimation_factor, features
from daemon.index import Hits, adaptive_fuzzy_query, example_query, feature_selection, mismatch_query, ranked
from daemon.index_store import (
    FEATURE_SETS,
    Document,
    IndexBuildError,
    IndexFormatError,
    ManifestError,
    ManifestRow,
    MotionIndex,
    build_index,
    check_index_target,
    index_bytes,
    load_index,
    read_document,
    read_manifest,
    save_index,
)
from daemon.keyframes import KeyframeError, KeyframeQuery, keyframe_search, parse_keyframe_queries
from daemon.library import (
    Library,
    LibraryFormatError,
    TrainingClip,
    check_library_target,
    learn_class,
    load_library,
    read_examples,
    save_library,
)
from daemon.plots import PlotUnavailable, feature_matrix_png, template_png
from daemon.retrieval import template_search
from replay import JOINT_NAMES, KinematicModel, MocapFormatError, Motion, read_amc, read_asf

LIBRARY_KEYFRAMES = Path("<the library's keyframes>")


def _positive_float(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not (math.isfinite(value) and value > 0):
        raise argparse.ArgumentTypeError(f"must be a positive number, got '{text}'")
    return value


def _recording_options(command: argparse.ArgumentParser) -> None:
    command.add_argument("--asf", type=Path, required=True)
    command.add_argument("--amc", type=Path, required=True, help="AMC file, plain or gzip")


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="mocapd", description="Streaming motion recognition over ASF/AMC motion capture."
    )
    parser.add_argument(
        "--config", type=Path, default=None, help="config.yaml to read (default: built-in defaults)"
    )
    sub = parser.add_subparsers(dest="command", required=True)

    info = sub.add_parser("info", help="describe a recording: frames, duration, bones, joints")
    _recording_options(info)
    info.add_argument(
        "--fps",
        type=_positive_float,
        default=None,
        help="frame rate if the AMC states none (default: config, 120)",
    )
    info.add_argument("--json", action="store_true", help="print one JSON object instead of text")

    pos = sub.add_parser("positions", help="write joint positions as CSV: frame,joint,x,y,z")
    _recording_options(pos)
    pos.add_argument("--csv", type=Path, required=True, help="output CSV ('-' for stdout)")
    pos.add_argument("--cm", action="store_true", help="centimetres (ASF length / :units length x 2.54)")

    feat = sub.add_parser("features", help="write the 39 relational features as CSV: frame,<names>")
    _recording_options(feat)
    feat.add_argument("--csv", type=Path, required=True, help="output CSV ('-' for stdout)")
    feat.add_argument(
        "--fps",
        type=_positive_float,
        default=None,
        help="output rate: every k-th frame of the native rate, which it must divide (e.g. 30)",
    )
    feat.add_argument("--png", type=Path, default=None, help="also draw the feature matrix as a PNG")

    index = sub.add_parser("index", help="build or describe a motion index (inverted lists of F-segments)")
    index_sub = index.add_subparsers(dest="index_command", required=True)
    build = index_sub.add_parser("build", help="index the recordings of a manifest CSV (columns asf, amc)")
    build.add_argument("--manifest", type=Path, required=True, help="CSV with columns asf and amc")
    build.add_argument("--out", type=Path, required=True, help="index directory to write (replaced)")
    build.add_argument(
        "--fps",
        type=_positive_float,
        default=30.0,
        help="index rate: every k-th frame of the native rate, which it must divide (default 30)",
    )
    index_info = index_sub.add_parser("info", help="describe an index: documents, frames, segments, size")
    index_info.add_argument("index", type=Path, help="index directory")
    index_info.add_argument("--json", action="store_true", help="print one JSON object instead of text")

    learn = sub.add_parser("learn", help="learn motion templates and keyframes from labelled clips")
    learn.add_argument(
        "--manifest",
        type=Path,
        required=True,
        help="CSV with columns class, asf, amc and optionally start_frame, end_frame (AMC frames)",
    )
    learn.add_argument("--out", type=Path, required=True, help="library directory to write (replaced)")
    learn.add_argument(
        "--fps", type=_positive_float, default=30.0, help="learn at this rate (default 30, as the thesis)"
    )
    learn.add_argument("--png", type=Path, default=None, help="directory for a PNG of each class's MTs")
    learn.add_argument(
        "--tau", type=_positive_float, default=0.1, help="retrieval threshold stored per class (0.1)"
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

    search = sub.add_parser(
        "search",
        help="find motions in an index: with a class's motion template (thesis ch. 3/5), "
        "by keyframes (ch. 4) or by example (MRC05)",
    )
    search.add_argument("--index", type=Path, required=True, help="index directory (mocapd index build)")
    search.add_argument(
        "--library", type=Path, help="rank by the motion template of --class from this library"
    )
    mode = search.add_mutually_exclusive_group()
    mode.add_argument(
        "--keyframes",
        type=Path,
        nargs="?",
        const=LIBRARY_KEYFRAMES,
        help="keyframe queries, JSON as manual-keyframes.json; with --library: pre-select by keyframes "
        "before ranking (the library's own when no file is given)",
    )
    mode.add_argument(
        "--example",
        nargs=4,
        metavar=("ASF", "AMC", "START", "END"),
        help="query by example: a recording and its AMC frames START..END",
    )
    search.add_argument(
        "--class", dest="class_name", help="with --keyframes or --library: the class to search"
    )
    search.add_argument(
        "--tau", type=_positive_float, default=None, help="with --library: cost threshold (the class's)"
    )
    search.add_argument(
        "--steps",
        choices=STEPS,
        default=None,
        help="with --library: DTW steps, thesis (1,0),(0,1),(1,1) or toolbox (1,1),(1,2),(2,1) "
        "(default: the class's)",
    )
    search.add_argument(
        "--extend",
        default=None,
        metavar="LEFT,RIGHT",
        help="with --keyframes: widen keyframe ranges by index frames (default 0,0; with --library: the "
        "template's columns before the first and after the last keyframe, x 1.5)",
    )
    search.add_argument("--features", help="with --example: comma-separated feature names, all from one set")
    search.add_argument(
        "--fuzzy",
        type=int,
        default=0,
        metavar="N",
        help="with --example: also accept vectors differing in up to N selected features (default 0)",
    )
    search.add_argument(
        "--mismatch", type=int, default=None, metavar="M", help="with --example: m-mismatch search"
    )
    search.add_argument("--limit", type=int, default=None, help="print at most this many hits")
    search.add_argument("--json", action="store_true", help="one JSON object per hit and line")
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    try:
        config = load_config(args.config)
        if args.command == "info":
            return _info(args, config)
        if args.command == "positions":
            return _positions(args, config)
        if args.command == "features":
            return _features(args, config)
        if args.command == "index" and args.index_command == "build":
            return _index_build(args, config)
        if args.command == "index" and args.index_command == "info":
            return _index_info(args)
        if args.command == "learn":
            return _learn(args, config)
        if args.command == "search":
            return _search(args, config)
    except (
        MocapFormatError,
        ConfigError,
        UsageError,
        PlotUnavailable,
        ManifestError,
        IndexFormatError,
        IndexBuildError,
        KeyframeError,
        LibraryFormatError,
    ) as exc:
        print(f"mocapd: {exc}", file=sys.stderr)
        return 2
    except BrokenPipeError:
        # The reader of our stdout went away (``| head``): nothing is wrong, nothing more to say.
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 0
    except OSError as exc:
        print(f"mocapd: {exc.filename}: {exc.strerror}", file=sys.stderr)
        return 2
    raise AssertionError(args.command)


class UsageError(ValueError):
    """Options that do not fit the input."""


def _load(asf: Path, amc: Path) -> Motion:
    return read_amc(amc, read_asf(asf))


def _info(args: argparse.Namespace, config: Config) -> int:
    motion = _load(args.asf, args.amc)
    skeleton = motion.skeleton
    if motion.header.frame_rate is not None and args.fps is None:
        rate, rate_from = motion.header.frame_rate, "from the AMC file"
    elif args.fps is not None:
        rate, rate_from = args.fps, "given"
    else:
        rate, rate_from = config.replay.frame_rate_hz, "assumed"
    model = KinematicModel(skeleton)
    joints = [] if model.missing_joint_bones else list(JOINT_NAMES)
    summary = {
        "asf": str(args.asf),
        "amc": str(args.amc),
        "skeleton": skeleton.name,
        "frames": len(motion),
        "first_frame": int(motion.frames[0]),
        "last_frame": int(motion.frames[-1]),
        "frame_rate_hz": rate,
        "frame_rate_source": rate_from,
        "duration_s": len(motion) / rate,
        "angle_unit": motion.header.angle_unit,
        "length_unit": skeleton.length_unit,
        "bones": [b.name for b in skeleton.bones],
        "channels": len(skeleton.channel_names),
        "joints": joints,
        "missing_joint_bones": list(model.missing_joint_bones),
    }
    if args.json:
        print(json.dumps(summary))
        return 0
    units = f"length unit {skeleton.length_unit}, angles in {skeleton.angle_unit}"
    print(f"asf:        {args.asf} ({skeleton.name or 'unnamed'}; {units})")
    print(f"amc:        {args.amc} (angles in {motion.header.angle_unit})")
    print(f"frames:     {len(motion)} (AMC frames {motion.frames[0]}-{motion.frames[-1]})")
    print(f"duration:   {len(motion) / rate:.3f} s at {rate:g} Hz ({rate_from})")
    print(f"bones:      {len(skeleton.bones)}: {' '.join(b.name for b in skeleton.bones)}")
    print(f"channels:   {len(skeleton.channel_names)}")
    if joints:
        print(f"joints:     {len(joints)}: {' '.join(joints)}")
    else:
        print(f"joints:     none (skeleton lacks {', '.join(model.missing_joint_bones)})")
    return 0


def _positions(args: argparse.Namespace, config: Config) -> int:
    motion = _load(args.asf, args.amc)
    model = KinematicModel(motion.skeleton)
    unit: Units = "cm" if args.cm or config.replay.units == "cm" else "asf"
    joints = model.joints(model.positions(motion.channels, unit))
    if str(args.csv) == "-":
        _write_positions(sys.stdout, motion.frames, joints)
    else:
        with open(args.csv, "w", encoding="utf-8", newline="") as out:
            _write_positions(out, motion.frames, joints)
    return 0


def _write_positions(out: TextIO, frames: np.ndarray, joints: np.ndarray) -> None:
    """``frames`` shape ``(N,)``, ``joints`` shape ``(N, J, 3)`` in :data:`JOINT_NAMES` order."""
    out.write("frame,joint,x,y,z\n")
    names = np.array(JOINT_NAMES, dtype=object)
    block = len(JOINT_NAMES)
    for start in range(0, len(frames), 1024):
        f = frames[start : start + 1024]
        xyz = joints[start : start + 1024].reshape(-1, 3)
        rows = zip(
            np.repeat(f, block).tolist(), np.tile(names, len(f)).tolist(), *xyz.T.tolist(), strict=True
        )
        out.writelines(f"{fr},{j},{x:.6f},{y:.6f},{z:.6f}\n" for fr, j, x, y, z in rows)


def _features(args: argparse.Namespace, config: Config) -> int:
    motion = _load(args.asf, args.amc)
    native = motion.header.frame_rate or config.replay.frame_rate_hz
    try:
        factor = 1 if args.fps is None else decimation_factor(native, args.fps)
    except ValueError as exc:
        raise UsageError(f"--fps: {exc}") from None
    model = KinematicModel(motion.skeleton)
    joints = model.joints(model.positions(motion.channels, "cm"))
    matrix = decimate(features(joints, JOINT_NAMES, native), factor)
    frames = motion.frames[::factor]
    if str(args.csv) == "-":
        _write_features(sys.stdout, frames, matrix)
    else:
        with open(args.csv, "w", encoding="utf-8", newline="") as out:
            _write_features(out, frames, matrix)
    if args.png is not None:
        title = f"{args.amc.name}: {len(frames)} frames at {native / factor:g} Hz"
        feature_matrix_png(matrix, frames, args.png, title, native / factor)
    return 0


def _write_features(out: TextIO, frames: np.ndarray, matrix: np.ndarray) -> None:
    """``frames`` shape ``(N,)``, ``matrix`` shape ``(N, 39)``: CSV ``frame,<39 names>`` of 0/1."""
    out.write(",".join(("frame", *FEATURE_NAMES)) + "\n")
    digits = np.where(matrix, "1", "0")
    out.writelines(f"{f},{','.join(row)}\n" for f, row in zip(frames.tolist(), digits.tolist(), strict=True))


def _index_build(args: argparse.Namespace, config: Config) -> int:
    began = time.perf_counter()
    rows = read_manifest(args.manifest)
    check_index_target(args.out)  # before the long part

    def progress(done: int, total: int, document: Document) -> None:
        print(f"[{done}/{total}] {document.amc} ({document.frames} frames)", file=sys.stderr, flush=True)

    index = build_index(rows, args.fps, progress, config.replay.frame_rate_hz)
    save_index(index, args.out)
    seconds = time.perf_counter() - began
    size = index_bytes(args.out)
    print(f"index:      {args.out}")
    print(f"documents:  {len(index.documents)}")
    print(f"frames:     {index.n_frames} at {index.rate:g} Hz")
    for s in FEATURE_SETS:
        print(f"{s + ':':<11} {index.sets[s].n_segments} segments")
    print(f"build time: {seconds:.2f} s")
    print(f"size:       {size} bytes")
    return 0


def _learn(args: argparse.Namespace, config: Config) -> int:
    if not 0 <= args.delta < 0.5:
        raise UsageError(f"--delta must lie in [0, 0.5), got {args.delta:g}")
    if args.keyframes < 0:
        raise UsageError(f"--keyframes must not be negative, got {args.keyframes}")
    check_library_target(args.out)  # before the long part
    if args.png is not None:
        args.png.mkdir(parents=True, exist_ok=True)
    began = time.perf_counter()

    def progress(done: int, total: int, clip: TrainingClip) -> None:
        print(f"[{done}/{total}] {clip.amc} ({clip.frames} frames)", file=sys.stderr, flush=True)

    examples = read_examples(args.manifest, args.fps, progress, config.replay.frame_rate_hz)
    classes = {}
    for i, (name, items) in enumerate(examples.items(), start=1):
        started = time.perf_counter()
        cls = learn_class(name, items, args.delta, args.tau, args.keyframes, args.steps, args.fps)
        classes[name] = cls
        keyframes = 0 if cls.keyframes is None else len(cls.keyframes.keyframes)
        print(
            f"[class {i}/{len(examples)}] {name}: {len(items)} examples, soft MT {cls.soft.length} "
            f"columns after {cls.iterations} iterations, hard MT {cls.hard.length} columns, "
            f"{keyframes} keyframes ({time.perf_counter() - started:.1f} s)",
            file=sys.stderr,
            flush=True,
        )
        if args.png is not None:
            columns = [] if cls.keyframes is None else [k.position for k in cls.keyframes.keyframes]
            template_png(cls.soft.values, cls.hard.values, columns, args.png / f"{name}.png", name, args.fps)
    save_library(Library(args.fps, classes), args.out)
    print(f"library:    {args.out}")
    print(f"classes:    {len(classes)} ({', '.join(classes)})")
    print(f"examples:   {sum(len(c.training) for c in classes.values())} at {args.fps:g} Hz")
    print(f"learn time: {time.perf_counter() - began:.1f} s")
    return 0


def _index_info(args: argparse.Namespace) -> int:
    index = load_index(args.index)
    sets = {}
    for s in FEATURE_SETS:
        entry = index.sets[s]
        size = index_bytes(args.index, s)
        segments = entry.n_segments
        sets[s] = {
            "bits": entry.bits,
            "segments": segments,
            "nonempty_lists": entry.nonempty_lists,
            "bytes": size,
            "bytes_per_segment": size / segments if segments else None,
        }
    summary = {
        "index": str(args.index),
        "rate_hz": index.rate,
        "documents": len(index.documents),
        "frames": index.n_frames,
        "duration_s": sum(
            (d.last_amc_frame - d.first_amc_frame + 1) / d.native_rate for d in index.documents
        ),
        "bytes": index_bytes(args.index),
        "sets": sets,
    }
    if args.json:
        print(json.dumps(summary))
        return 0
    print(f"index:      {args.index}")
    print(f"rate:       {index.rate:g} Hz")
    print(f"documents:  {len(index.documents)}")
    print(f"frames:     {index.n_frames}")
    print(f"duration:   {summary['duration_s']:.3f} s")
    print(f"size:       {summary['bytes']} bytes")
    for s, e in sets.items():
        per = "-" if e["bytes_per_segment"] is None else f"{e['bytes_per_segment']:.1f}"
        print(
            f"{s + ':':<11} {e['bits']} bits, {e['segments']} segments, "
            f"{e['nonempty_lists']} non-empty lists, {e['bytes']} bytes ({per} bytes/segment)"
        )
    return 0


def _search(args: argparse.Namespace, config: Config) -> int:
    mode = "--library" if args.library else "--keyframes" if args.keyframes else "--example"
    if args.example is None and args.keyframes is None and args.library is None:
        raise UsageError("give --library, --keyframes or --example")
    given = {
        "--class": args.class_name is not None,
        "--extend": args.extend is not None,
        "--features": args.features is not None,
        "--fuzzy": args.fuzzy != 0,
        "--mismatch": args.mismatch is not None,
        "--tau": args.tau is not None,
        "--steps": args.steps is not None,
        "--example": args.example is not None,
    }
    allowed = {
        "--library": {"--class", "--extend", "--tau", "--steps"},
        "--keyframes": {"--class", "--extend"},
        "--example": {"--features", "--fuzzy", "--mismatch", "--example"},
    }[mode]
    wrong = [k for k, v in given.items() if v and k not in allowed]
    if wrong:
        raise UsageError(f"{', '.join(wrong)} cannot be used with {mode}")
    if args.keyframes == LIBRARY_KEYFRAMES and args.library is None:
        raise UsageError("--keyframes needs a keyframe file unless --library is given")
    if args.limit is not None and args.limit < 0:
        raise UsageError(f"--limit must not be negative, got {args.limit}")
    index = load_index(args.index)
    began = time.perf_counter()
    if args.library is not None:
        rows, summary = _search_library(args, index)
    elif args.keyframes is not None:
        rows, summary = _search_keyframes(args, index)
    else:
        rows, summary = _search_example(args, config, index)
    elapsed = 1e3 * (time.perf_counter() - began)
    shown = rows if args.limit is None else rows[: args.limit]
    if args.json:
        for row in shown:
            print(json.dumps(row))
        return 0
    print(f"{summary}: {len(rows)} hits in {elapsed:.1f} ms")
    for rank, row in enumerate(shown, start=1):
        cost = f" cost {row['cost']}" if "cost" in row else ""
        print(f"{rank:5d}. {row['document']} frames {row['start_frame']}-{row['end_frame']}{cost}")
    return 0


def _extension(args: argparse.Namespace) -> tuple[int, int] | None:
    """--extend as (left, right); None when not given."""
    if args.extend is None:
        return None
    try:
        extend = tuple(int(x) for x in args.extend.split(","))
    except ValueError:
        extend = ()
    if len(extend) != 2 or min(extend) < 0:
        raise UsageError(f"--extend must be LEFT,RIGHT (two whole numbers >= 0), got '{args.extend}'")
    return extend[0], extend[1]


def _keyframe_query(path: Path, name: str) -> KeyframeQuery:
    try:
        obj = json.loads(path.read_text(encoding="utf-8"))
    except json.JSONDecodeError as exc:
        raise UsageError(f"{path}:{exc.lineno}: not JSON: {exc.msg}") from None
    queries = parse_keyframe_queries(obj, str(path))
    if name not in queries:
        raise UsageError(f"{path}: no class '{name}' (has: {', '.join(sorted(queries))})")
    return queries[name]


def _search_library(args: argparse.Namespace, index: MotionIndex) -> tuple[list[dict[str, object]], str]:
    if args.class_name is None:
        raise UsageError("--library needs --class NAME")
    library = load_library(args.library)
    try:
        cls = library.get(args.class_name)
    except KeyError as exc:
        raise UsageError(f"{args.library}: {exc.args[0]}") from None
    if not math.isclose(library.rate, index.rate):
        raise UsageError(
            f"{args.library} was learned at {library.rate:g} Hz, {args.index} is indexed at {index.rate:g} Hz"
        )
    query = None
    if args.keyframes == LIBRARY_KEYFRAMES:
        if cls.keyframes is None:
            raise UsageError(f"{args.library}: class {cls.name} has no keyframes")
        query = cls.keyframes
    elif args.keyframes is not None:
        query = _keyframe_query(args.keyframes, cls.name)
    elif args.extend is not None:
        raise UsageError("--extend needs --keyframes")
    tau = cls.tau if args.tau is None else args.tau
    steps = cls.steps if args.steps is None else args.steps
    try:
        hits = template_search(index, cls.quantised, tau, steps, query, _extension(args), args.limit)
    except ValueError as exc:
        raise UsageError(f"class {cls.name}: {exc}") from None
    rows = [
        {**_hit_row(index, d, s, e), "cost": round(c, 6)}
        for d, s, e, c in zip(
            hits.doc.tolist(), hits.start.tolist(), hits.end.tolist(), hits.cost.tolist(), strict=True
        )
    ]
    summary = f"motion template of {cls.name} ({cls.quantised.length} columns, tau {tau:g}, {steps} steps"
    if hits.keyframes is not None:
        share = 100 * hits.searched / max(index.n_frames, 1)
        summary += f"; keyframes kept {len(hits.keyframes)} ranges, {share:.2f} % of the database"
    return rows, summary + "), ranked by cost"


def _search_keyframes(args: argparse.Namespace, index: MotionIndex) -> tuple[list[dict[str, object]], str]:
    if args.class_name is None:
        raise UsageError("--keyframes needs --class NAME")
    extend = _extension(args) or (0, 0)
    query = _keyframe_query(args.keyframes, args.class_name)
    frames = [d.frames for d in index.documents]
    try:
        hits = keyframe_search(index.sets, frames, query, index.rate, extend)
    except ValueError as exc:
        raise UsageError(f"{args.keyframes}: class {args.class_name}: {exc}") from None
    rows = [
        _hit_row(index, d, s, e)
        for d, s, e in zip(hits.doc.tolist(), hits.start.tolist(), hits.end.tolist(), strict=True)
    ]
    share = 100 * hits.frames / max(index.n_frames, 1)
    summary = (
        f"keyframes of {args.class_name} ({len(query.keyframes)} keyframes, lists of "
        f"{sum(hits.list_lengths)} segments), {share:.2f} % of the database kept"
    )
    return rows, summary


def _search_example(
    args: argparse.Namespace, config: Config, index: MotionIndex
) -> tuple[list[dict[str, object]], str]:
    asf, amc, start_text, end_text = args.example
    if args.features is None:
        raise UsageError("--example needs --features NAME,NAME,...")
    try:
        feature_set, mask = feature_selection([n.strip() for n in args.features.split(",") if n.strip()])
    except ValueError as exc:
        raise UsageError(f"--features: {exc}") from None
    try:
        first, last = int(start_text), int(end_text)
    except ValueError:
        raise UsageError(
            f"--example START END must be AMC frame numbers, got '{start_text} {end_text}'"
        ) from None
    try:
        document, matrix = read_document(
            ManifestRow(0, asf, amc, Path(asf), Path(amc)), index.rate, config.replay.frame_rate_hz
        )
    except IndexBuildError as exc:
        raise UsageError(str(exc)) from None
    sampled = document.first_amc_frame + document.step * np.arange(document.frames)
    inside = (sampled >= first) & (sampled <= last)
    if first > last or not inside.any():
        raise UsageError(
            f"{amc}: frames {first}..{last} hold no frame at {index.rate:g} Hz "
            f"(the recording has AMC frames {document.first_amc_frame}..{document.last_amc_frame})"
        )
    query = example_query(matrix[inside], feature_set, mask)
    if args.fuzzy < 0:
        raise UsageError(f"--fuzzy must not be negative, got {args.fuzzy}")
    sets = query.fuzzy_sets(args.fuzzy)
    set_index = index.sets[feature_set]
    hits: Hits
    if args.mismatch is None:
        hits, kind = adaptive_fuzzy_query(set_index, sets), "adaptive fuzzy"
    else:
        try:
            hits, kind = mismatch_query(set_index, sets, args.mismatch), f"{args.mismatch}-mismatch"
        except ValueError as exc:
            raise UsageError(f"--mismatch: {exc}") from None
    order, cost = ranked(hits, query.lengths)
    rows = [
        {**_hit_row(index, int(hits.doc[i]), int(hits.start[i]), int(hits.end[i])), "cost": int(c)}
        for i, c in zip(order.tolist(), cost.tolist(), strict=True)
    ]
    summary = (
        f"{kind} query of {len(query.codes)} segments ({feature_set}: {args.features}; "
        f"fuzzy {args.fuzzy}), ranked by segment length difference"
    )
    return rows, summary


def _hit_row(index: MotionIndex, doc: int, start: int, end: int) -> dict[str, object]:
    first, last = index.amc_frames(doc, start, end)
    return {"document": index.documents[doc].amc, "start_frame": first, "end_frame": last}
