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
from daemon.features import FEATURE_NAMES, BoolArray, decimate, decimation_factor, features
from daemon.index_store import (
    ARRAYS,
    FEATURE_SETS,
    Document,
    IndexBuildError,
    IndexFormatError,
    ManifestError,
    array_file,
    check_index_target,
    index_files,
    index_from_matrices,
    load_index,
    read_document,
    read_manifest,
    save_index,
)
from daemon.plots import PlotUnavailable, feature_matrix_png
from replay import JOINT_NAMES, KinematicModel, MocapFormatError, Motion, read_amc, read_asf


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
    except (
        MocapFormatError,
        ConfigError,
        UsageError,
        PlotUnavailable,
        ManifestError,
        IndexFormatError,
        IndexBuildError,
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
    documents: list[Document] = []
    matrices: list[BoolArray] = []
    # build_index's loop, written out so that each progress line can give the document's frames
    for i, row in enumerate(rows, start=1):
        document, matrix = read_document(row, args.fps, config.replay.frame_rate_hz)
        documents.append(document)
        matrices.append(matrix)
        print(f"[{i}/{len(rows)}] {row.amc_text} ({document.frames} frames)", file=sys.stderr, flush=True)
    index = index_from_matrices(matrices, documents, args.fps)
    save_index(index, args.out)
    seconds = time.perf_counter() - began
    size = sum((args.out / name).stat().st_size for name in index_files())
    print(f"index:      {args.out}")
    print(f"documents:  {len(index.documents)}")
    print(f"frames:     {index.n_frames} at {index.rate:g} Hz")
    for s in FEATURE_SETS:
        print(f"{s + ':':<11} {index.sets[s].n_segments} segments")
    print(f"build time: {seconds:.2f} s")
    print(f"size:       {size} bytes")
    return 0


def _index_info(args: argparse.Namespace) -> int:
    index = load_index(args.index)
    sets = {}
    for s in FEATURE_SETS:
        entry = index.sets[s]
        size = sum((args.index / array_file(s, a)).stat().st_size for a in ARRAYS)
        segments = entry.n_segments
        sets[s] = {
            "bits": entry.bits,
            "segments": segments,
            "nonempty_lists": int(np.count_nonzero(np.diff(entry.offsets))),
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
        "bytes": sum((args.index / name).stat().st_size for name in index_files()),
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
