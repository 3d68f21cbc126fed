"""``mocapd detect``: replay a recording through a live :class:`~daemon.recognizer.Recognizer` in this
process and print each detection when it is emitted (with ``--progress``, the progress events of
:class:`daemon.progress.StreamProgress` too, each before the detections of the same frame's push)."""

from __future__ import annotations

import argparse
import json
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from daemon.cli import common
from daemon.config import Config
from daemon.errors import InputError, UsageError
from daemon.frames import bridge_frames, bridged_runs
from daemon.library import Library, default_library_path, load_library
from daemon.plots import timeline_png
from daemon.progress import ProgressEvent, StreamProgress
from daemon.recognizer import Detection, Recognizer
from daemon.recordings import native_rate, read_labels, read_recording
from daemon.types import FloatArray, IntArray, RecognitionSettings
from replay.joints import JOINT_NAMES
from replay.rigs import read_bvh_take


def speed(text: str) -> float | None:
    """``--speed``: ``max`` (None: as fast as possible) or a positive factor of real time."""
    if text == "max":
        return None
    try:
        return common.positive_float(text)
    except argparse.ArgumentTypeError:
        raise argparse.ArgumentTypeError(
            f"must be 'max' or a positive factor of real time, got '{text}'"
        ) from None


def register(sub: Any) -> None:
    cmd = sub.add_parser(
        "detect", help="recognise motions in a recording, frame by frame as a live stream would arrive"
    )
    common.recording_options(cmd, bvh=True)
    cmd.add_argument(
        "--library", type=Path, default=None, help="template library directory (default: the shipped one)"
    )
    cmd.add_argument(
        "--classes", default=None, metavar="A,B", help="only these classes of the library (comma-separated)"
    )
    cmd.add_argument(
        "--speed",
        type=speed,
        default=None,
        metavar="1|X|max",
        help="replay pace: 1 = real time, X times real time, max = as fast as possible (default)",
    )
    cmd.add_argument(
        "--stream", default=None, help="stream id in the detections (default: the AMC file's name)"
    )
    cmd.add_argument("--json", action="store_true", help="print one JSON object per detection")
    cmd.add_argument(
        "--progress",
        action="store_true",
        help="also print the progress events (JSON lines, as the daemon publishes them) in emission order",
    )
    cmd.add_argument("--png", type=Path, default=None, help="draw the detections over time into this .png")
    cmd.add_argument(
        "--truth",
        type=Path,
        default=None,
        help="CSV of labelled segments (class or label_name, start_frame, end_frame; rows of another trial "
        "skipped) drawn beneath the detections in --png",
    )
    cmd.set_defaults(func=_detect)


@dataclass(frozen=True)
class _Recording:
    """What detect replays: frame numbers, each frame's values, the rate, the recogniser for them."""

    frames: IntArray
    values: FloatArray
    rate: float
    recognizer: Recognizer
    angles: IntArray | None = None  # columns of values that are angles (bridged along the shorter arc)


def _read(
    args: argparse.Namespace,
    config: Config,
    library: Library,
    settings: RecognitionSettings,
    stream: str,
    bvh: Path | None,
) -> _Recording:
    """The recording of ``bvh`` (its rig mapped onto the standard joints, :mod:`replay.rigs`;
    frames numbered from 1) or of ``--asf`` and ``--amc``, and a recogniser for it."""
    maps = common.rig_maps(args, config)
    try:
        if bvh is not None:
            take = read_bvh_take(bvh, maps)
            recognizer = Recognizer.for_positions(
                library, JOINT_NAMES, take.rate, settings=settings, stream=stream
            )
            return _Recording(take.frames, take.joints, take.rate, recognizer)
        amc = read_recording(args.asf, args.amc)
        rate = native_rate(amc, common.default_native_rate(args, config))
        recognizer = Recognizer.for_skeleton(library, amc.skeleton, rate, settings=settings, stream=stream)
        angles = np.asarray(amc.skeleton.angle_channels, dtype=np.intp)
        return _Recording(amc.frames, amc.channels, rate, recognizer, angles)
    except InputError as exc:  # a recording slower than the library: named with the recording
        raise UsageError(
            f"{exc} (the library's rate must not exceed the recording's)", path=bvh or args.amc
        ) from None


def _detect(args: argparse.Namespace, config: Config) -> int:
    if args.png is not None:
        common.check_png_output(args.png)
    elif args.truth is not None:
        raise UsageError("--truth is drawn in --png: give --png too", field="--truth")
    classes = None
    if args.classes is not None:
        classes = [c.strip() for c in args.classes.split(",")]
        if not all(classes):
            raise UsageError(f"an empty class name in '{args.classes}'", field="--classes")
    library = load_library(default_library_path() if args.library is None else args.library, classes)
    bvh = common.bvh_or_asf(args)
    source = bvh or args.amc
    trial = common.stream_name(source)
    truth = [] if args.truth is None else read_labels(args.truth, trial)
    stream = trial if args.stream is None else args.stream
    try:
        settings = config.recognizer.settings(classes)
    except InputError as exc:
        raise UsageError(str(exc), field="--classes") from None
    motion = _read(args, config, library, settings, stream, bvh)
    recognizer, rate = motion.recognizer, motion.rate
    found: list[Detection] = []
    first = int(motion.frames[0]) if len(motion.frames) else 0
    follow = StreamProgress(recognizer.stage, rate, config.progress.per_s) if args.progress else None

    def report(detections: list[Detection], events: Sequence[ProgressEvent] = ()) -> None:
        for e in events:  # the source time: seconds into the recording
            print(json.dumps(e.as_json(stream, (e.frame - first) / rate)), flush=True)
        for d in detections:
            found.append(d)
            print(json.dumps(d.as_json()) if args.json else _line(d, rate, motion.frames[0]), flush=True)

    began = time.perf_counter()
    pace = None if args.speed is None else 1.0 / (rate * args.speed)
    # frames missing from the recording are taken as the daemon takes lost poses
    gap = bridge_frames(config.service.bridge_s, rate)
    for frames, values in bridged_runs(motion.frames, motion.values, gap, motion.angles):
        for number, channels in zip(frames.tolist(), values, strict=True):
            if pace is not None:  # by the clock: a late frame does not delay the next ones
                ahead = began + (number - first) * pace - time.perf_counter()
                if ahead > 0:
                    time.sleep(ahead)
            detections = recognizer.push(number, channels)
            report(detections, follow.observe(number) if follow is not None else [])
        detections = recognizer.flush()
        report(detections, follow.end() if follow is not None else [])
    took = time.perf_counter() - began
    if not args.json:
        n = len(motion.frames)
        print(
            f"{len(found)} detections in {n} frames ({n / rate:.1f} s at {rate:g} Hz), "
            f"{len(recognizer.plans)} classes, in {took:.2f} s"
        )
    if args.png is not None:
        title = f"{source.name}: {len(found)} detections"
        rows = [(d.class_name, d.start_frame, d.end_frame) for d in found]
        labels = [(t.name, t.start_frame, t.end_frame) for t in truth]
        span = (int(motion.frames[0]), int(motion.frames[-1]))
        common.write_png(args.png, lambda out: timeline_png(rows, labels, span, rate, out, title))
    return 0


def _line(d: Detection, rate: float, first: int) -> str:
    """``class  start-end s  cost c (tau t)  latency l s``, times from the recording's first frame."""
    start, end = (d.start_frame - first) / rate, (d.end_frame + 1 - first) / rate
    latency = (d.emitted_at_frame - d.end_frame) / rate
    return (
        f"{d.class_name:<28} {start:8.2f}-{end:.2f} s  cost {d.cost:.3f} (tau {d.tau:.3f})  "
        f"latency {latency:.2f} s"
    )
