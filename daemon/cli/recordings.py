"""Commands on one recording: ``info``, ``positions``, ``features``, ``convert``."""

from __future__ import annotations

import argparse
import gzip
import json
from pathlib import Path
from typing import IO, Any

import numpy as np

from daemon.cli import common
from daemon.config import Config
from daemon.errors import UsageError
from daemon.features import FEATURE_NAMES
from daemon.features.catalog import features_reading
from daemon.plots import feature_matrix_png
from daemon.recordings import RateError, motion_features, native_rate, read_bvh_features, read_recording
from daemon.storage import check_output_file, output_file, together
from daemon.types import BoolArray, FloatArray, IntArray
from replay import JOINT_NAMES, KinematicModel
from replay.bvh import write_bvh
from replay.convert import motion_to_bvh
from replay.kinematics import joint_positions
from replay.rigs import BvhTake, read_bvh_take


def register(sub: Any) -> None:
    info = sub.add_parser("info", help="describe a recording: frames, duration, bones, joints")
    common.recording_options(info, bvh=True)
    info.add_argument("--json", action="store_true", help="print one JSON object instead of text")
    info.set_defaults(func=_info)

    pos = sub.add_parser("positions", help="write joint positions as CSV: frame,joint,x,y,z")
    common.recording_options(pos, bvh=True)
    pos.add_argument("--csv", type=Path, required=True, help="output CSV ('-' for stdout)")
    pos.add_argument("--cm", action="store_true", help="centimetres (ASF length / :units length x 2.54)")
    pos.set_defaults(func=_positions)

    feat = sub.add_parser("features", help="write the 39 relational features as CSV: frame,<names>")
    common.recording_options(feat, bvh=True)
    feat.add_argument("--csv", type=Path, required=True, help="output CSV ('-' for stdout)")
    common.rate_option(
        feat, None, "output rate (default: the native rate, at which features are always computed)"
    )
    feat.add_argument("--png", type=Path, default=None, help="also draw the feature matrix as this .png file")
    feat.set_defaults(func=_features)

    conv = sub.add_parser(
        "convert", help="write an ASF/AMC recording as BVH (read back: the same joint positions)"
    )
    common.recording_options(conv)
    conv.add_argument(
        "--out", type=Path, required=True, help="the BVH file to write (gzip if its name ends in .gz)"
    )
    conv.set_defaults(func=_convert)


def _info(args: argparse.Namespace, config: Config) -> int:
    bvh = common.bvh_or_asf(args)
    if bvh is not None:
        return _bvh_info(bvh, read_bvh_take(bvh, common.rig_maps(args, config)), args.json)
    motion = read_recording(args.asf, args.amc)
    skeleton = motion.skeleton
    if motion.header.frame_rate is not None:
        rate_from = "from the AMC file"
    else:
        rate_from = "assumed" if args.native_fps is None else "given"
    rate = native_rate(motion, common.default_native_rate(args, config))
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


def _bvh_info(path: Path, take: BvhTake, as_json: bool) -> int:
    """``info --bvh``: the take, the rig map that fits it, and each joint derived with the features
    it reaches (:func:`daemon.features.catalog.features_reading`)."""
    derived = {j: list(features_reading(j)) for j in take.plan.derived}
    summary = {
        "bvh": str(path),
        "frames": len(take.frames),
        "frame_rate_hz": take.rate,
        "duration_s": len(take.frames) / take.rate,
        "rig_map": take.plan.rig,
        "joints": list(JOINT_NAMES),
        "derived": derived,
    }
    if as_json:
        print(json.dumps(summary))
        return 0
    print(f"bvh:        {path}")
    print(f"frames:     {len(take.frames)} ({len(take.frames) / take.rate:.3f} s at {take.rate:g} Hz)")
    print(f"rig map:    {take.plan.rig}")
    for joint, reached in derived.items():
        print(f"derived:    {joint} (reaches {', '.join(reached) or 'no feature'})")
    return 0


def _positions(args: argparse.Namespace, config: Config) -> int:
    common.check_csv_output(args.csv)
    bvh = common.bvh_or_asf(args)
    if bvh is not None:  # in the file's own units
        take = read_bvh_take(bvh, common.rig_maps(args, config))
        common.write_csv(args.csv, lambda out: _write_positions(out, take.frames, take.joints))
        return 0
    motion = read_recording(args.asf, args.amc)
    joints = joint_positions(motion, "cm" if args.cm or config.replay.units == "cm" else "asf")
    common.write_csv(args.csv, lambda out: _write_positions(out, motion.frames, joints))
    return 0


def _write_positions(out: IO[str], frames: IntArray, joints: FloatArray) -> None:
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
    common.check_csv_output(args.csv)
    if args.png is not None:
        common.check_png_output(args.png)
    bvh = common.bvh_or_asf(args)
    try:
        if bvh is not None:
            got = read_bvh_features(bvh, args.fps, common.rig_maps(args, config))
        else:
            got = motion_features(
                read_recording(args.asf, args.amc), args.fps, common.default_native_rate(args, config)
            )
    except RateError as exc:
        raise UsageError(exc.reason, field="--fps") from None
    with together():  # an interrupted run leaves both the previous CSV and PNG
        common.write_csv(args.csv, lambda out: _write_features(out, got.frames, got.matrix))
        if args.png is not None:
            title = f"{(bvh or args.amc).name}: {len(got.frames)} frames at {got.rate:g} Hz"
            common.write_png(
                args.png, lambda out: feature_matrix_png(got.matrix, got.frames, out, title, got.rate)
            )
    return 0


def _write_features(out: IO[str], frames: IntArray, matrix: BoolArray) -> None:
    """``frames`` shape ``(N,)``, ``matrix`` shape ``(N, 39)``: CSV ``frame,<39 names>`` of 0/1."""
    out.write(",".join(("frame", *FEATURE_NAMES)) + "\n")
    digits = np.where(matrix, "1", "0")
    out.writelines(f"{f},{','.join(row)}\n" for f, row in zip(frames.tolist(), digits.tolist(), strict=True))


def _convert(args: argparse.Namespace, config: Config) -> int:
    check_output_file(args.out)
    motion = read_recording(args.asf, args.amc)
    text = write_bvh(motion_to_bvh(motion, native_rate(motion, common.default_native_rate(args, config))))
    with output_file(args.out, "wb") as out:
        # mtime 0: the same recording gives the same bytes
        out.write(gzip.compress(text, mtime=0) if args.out.name.endswith(".gz") else text)
    return 0
