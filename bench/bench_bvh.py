"""BVH forward kinematics over bandai2's takes (Bandai Namco Research, CC BY-NC-ND 4.0, read
unmodified), on one core: what a daemon spends per pose of a BVH stream.

    python -m bench.bench_bvh [--repeat 3] [--takes 20]

Prints frames/s for: batch forward kinematics of whole takes (the baseline), one frame at a time
in compiled code (``BvhKinematics.positions_frame``, what a BVH stream's poses take), the same
done by the batch code on one-row arrays (the per-frame path before it was compiled), and a
frame's standard joints (``BvhPoses.joints``: forward kinematics and the rig map). Each figure is
the best of ``--repeat`` runs.
"""

from __future__ import annotations

from pathlib import Path

from bench.common import arguments, best_of
from bench.machine import describe
from replay.bvh import read_bvh
from replay.rigs import BvhPoses

BANDAI = Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "mocap" / "bandai2"


def main() -> None:
    args = arguments(__doc__, takes=20)
    takes = [read_bvh(p) for p in sorted(BANDAI.glob("dataset-2_*.bvh.gz"))[: args.takes]]
    poses = [BvhPoses(t.hierarchy) for t in takes]
    frames = sum(len(t.channels) for t in takes)
    print(describe())
    print(f"data: {len(takes)} bandai2 takes, {frames} frames, pinned to one core, best of {args.repeat}")

    def batch() -> None:
        for p, t in zip(poses, takes, strict=True):
            p.kinematics.positions(t.channels)

    def compiled() -> None:
        for p, t in zip(poses, takes, strict=True):
            for row in t.channels:
                p.kinematics.positions_frame(row)

    def one_row_batch() -> None:
        for p, t in zip(poses, takes, strict=True):
            for row in t.channels:
                p.kinematics.positions(row[None])

    def joints() -> None:
        for p, t in zip(poses, takes, strict=True):
            for row in t.channels:
                p.joints(row)

    base = best_of(args.repeat, batch)
    rows = [
        ("batch forward kinematics (baseline)", base),
        ("per frame, compiled", best_of(args.repeat, compiled)),
        ("per frame, batch code on one row", best_of(args.repeat, one_row_batch)),
        ("per frame, standard joints (FK + rig map)", best_of(args.repeat, joints)),
    ]
    for name, seconds in rows:
        per = seconds / frames * 1e6
        print(f"{name:<44} {frames / seconds:>12,.0f} frames/s  {base / seconds:>8.3f}x  {per:8.1f} us/frame")


if __name__ == "__main__":
    main()
