"""The 39 relational features and F-segments over every AMC file in ../shared/data/mocap, one core.

    python -m bench.bench_features [--repeat 3]

Joint positions are computed first (not timed). Prints frames/s for: per-frame forward kinematics
(the baseline, measured in the same run, because this machine's speed drifts by up to 2x between
runs), batch features, incremental features (one pose per ``push``), batch and incremental
segmentation, and the segments per frame of each feature set at 120 and 30 Hz.
"""

from __future__ import annotations

import numpy as np

from bench.common import arguments, best_of, load
from bench.machine import describe
from daemon.features import SET_SLICES, FeatureStream, decimate, features, latency_frames
from daemon.search.segments import Segmenter, segment
from replay import JOINT_NAMES


def main() -> None:
    args = arguments(__doc__)
    data = load(args.data)
    clips = data.joints_cm()
    frames = data.frames
    print(describe())
    print(f"data: {len(data.pairs)} AMC files, {frames} frames, pinned to one core, best of {args.repeat}")
    sample_frames, fk_frame = data.fk_per_frame()

    matrices: list[np.ndarray] = []

    def batch() -> None:
        matrices[:] = [features(c, JOINT_NAMES, 120.0) for c in clips]

    def stream() -> None:
        for c in clips:
            s = FeatureStream(JOINT_NAMES, 120.0)
            for pose in c:
                s.push(pose)
            s.flush()

    def segments_batch() -> None:
        for m in matrices:
            for name in SET_SLICES:
                segment(m, name)

    def segments_stream() -> None:
        for m in matrices:
            segmenters = [Segmenter(name) for name in SET_SLICES]
            for row in m:
                for seg in segmenters:
                    seg.push(row)
            for seg in segmenters:
                seg.flush()

    t_fk = best_of(args.repeat, fk_frame)
    t_batch = best_of(args.repeat, batch)
    t_stream = best_of(args.repeat, stream)
    t_seg = best_of(args.repeat, segments_batch)
    t_seg_stream = best_of(args.repeat, segments_stream)
    base = sample_frames / t_fk
    rows = [
        ("forward kinematics, per frame (baseline)", base),
        ("features, batch", frames / t_batch),
        ("features, incremental (push per pose)", frames / t_stream),
        ("segmentation, batch (3 sets)", frames / t_seg),
        ("segmentation, incremental (3 sets)", frames / t_seg_stream),
    ]
    print(f"{'stage':44s} {'frames/s':>12s} {'vs baseline':>12s}")
    for name, rate in rows:
        print(f"{name:44s} {rate:12,.0f} {rate / base:11.2f}x")
    per_frame = t_stream / frames
    print(
        f"incremental: {1e6 * per_frame:.0f} us/pose, latency {latency_frames(120.0)} frames at 120 Hz; "
        f"one core keeps up with {1 / 120 / per_frame:.0f} streams at 120 Hz"
    )
    print(f"{'segments per frame':44s} {'120 Hz':>12s} {'30 Hz':>12s}")
    for name in SET_SLICES:
        at120 = sum(len(segment(m, name)) for m in matrices) / frames
        at30 = sum(len(segment(decimate(m, 4), name)) for m in matrices) / sum(len(m[::4]) for m in matrices)
        print(f"{name:44s} {at120:12.4f} {at30:12.4f}")


if __name__ == "__main__":
    main()
