"""``mocapd segment``: cut a recording into distinct behaviours (Barbič et al. 2004; the methods of
:mod:`daemon.behaviours`) and print the cuts."""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path
from typing import Any

import numpy as np

from daemon import behaviours as bh
from daemon.cli import common
from daemon.config import Config
from daemon.errors import InputError, UsageError
from daemon.plots import segmentation_png
from daemon.recordings import continuous, native_rate, read_boundaries, read_recording
from replay.bvh import read_bvh
from replay.rigs import hierarchy_plan


def register(sub: Any) -> None:
    cmd = sub.add_parser(
        "segment",
        help="cut a recording into distinct behaviours (PCA, PPCA or GMM; Barbič et al. 2004)",
        description="Cut a recording where one behaviour ends and the next begins, without training "
        "(Barbič et al., GI 2004). Every window is in seconds (the paper's frames at 120 Hz in the "
        "help), scaled to the recording's rate; the defaults are the paper's. A cut is printed as the "
        "AMC frame number (a BVH's frames count from 1) where the new behaviour starts.",
    )
    common.recording_options(cmd, bvh=True)
    cmd.add_argument("--method", choices=bh.METHODS, default="ppca", help="the method (default: ppca)")
    cmd.add_argument(
        "--json", action="store_true", help='one JSON object per cut: {"frame", "method", "score"}'
    )
    cmd.add_argument(
        "--png", type=Path, default=None, help="draw the method's signal and cuts into this .png"
    )
    cmd.add_argument(
        "--truth",
        type=Path,
        default=None,
        help="CSV of labelled segments (cmu86_segments.csv with its end_lo/end_hi bands, or class/"
        "label_name, start_frame, end_frame ± 0.5 s; rows of another trial skipped): the true "
        "boundaries, drawn in --png and scored (precision, recall)",
    )
    pca = cmd.add_argument_group("pca (§3.1)")
    p = bh.PCA_PAPER
    pca.add_argument(
        "--k", type=float, default=p.k, help=f"s that fix the dimension r (default {p.k:g}: 240)"
    )
    pca.add_argument(
        "--ell", type=float, default=p.ell, help=f"s of the derivative's lag ℓ (default {p.ell:g}: 60)"
    )
    pca.add_argument(
        "--i0", type=float, default=p.i0, help=f"s before the first test (default {p.i0:g}: 300)"
    )
    pca.add_argument(
        "--k-sigma", type=float, default=p.k_sigma, help=f"kσ of the test (default {p.k_sigma:g})"
    )
    pca.add_argument("--pca-tau", type=float, default=p.tau, help=f"τ of the dimension (default {p.tau:g})")
    ppca = cmd.add_argument_group("ppca (§3.2)")
    q = bh.PPCA_DEFAULT
    ppca.add_argument(
        "--window",
        type=float,
        default=q.window,
        help=f"s of T, the first K and the look-ahead (default {q.window:g}: 150)",
    )
    ppca.add_argument(
        "--delta", type=float, default=q.delta, help=f"s of Δ, K's step (default {q.delta:.4g}: 10)"
    )
    ppca.add_argument(
        "--rise", type=float, default=q.rise, help=f"R, a peak's rise over its valley (default {q.rise:g})"
    )
    ppca.add_argument("--ppca-tau", type=float, default=q.tau, help=f"τ of the dimension (default {q.tau:g})")
    ppca.add_argument(
        "--shortest",
        type=float,
        default=q.shortest,
        help="s of the shortest behaviour, a peak earlier in its segment no cut (default 3 T; "
        "0: the algorithm as published)",
    )
    gmm = cmd.add_argument_group("gmm (§3.3)")
    g = bh.GMM_PAPER
    gmm.add_argument(
        "--clusters", type=int, default=g.clusters, help=f"k, the Gaussians (default {g.clusters})"
    )
    gmm.add_argument(
        "--variance",
        type=float,
        default=g.variance,
        help=f"share of variance the PCA keeps (default {g.variance:g})",
    )
    gmm.add_argument(
        "--min-length",
        type=float,
        default=g.min_length,
        help=f"s below which a segment is merged (default {g.min_length:g})",
    )
    gmm.add_argument("--seed", type=int, default=g.seed, help=f"seed of the initial means (default {g.seed})")
    cmd.set_defaults(func=_segment)


def params(args: argparse.Namespace) -> bh.PcaParams | bh.PpcaParams | bh.GmmParams:
    """The chosen method's parameters from the options."""
    if args.method == "pca":
        return bh.PcaParams(k=args.k, ell=args.ell, i0=args.i0, tau=args.pca_tau, k_sigma=args.k_sigma)
    if args.method == "ppca":
        return bh.PpcaParams(
            window=args.window, delta=args.delta, rise=args.rise, tau=args.ppca_tau, shortest=args.shortest
        )
    return bh.GmmParams(
        variance=args.variance, clusters=args.clusters, min_length=args.min_length, seed=args.seed
    )


def _segment(args: argparse.Namespace, config: Config) -> int:
    if args.png is not None:
        common.check_png_output(args.png)
    bvh = common.bvh_or_asf(args)
    source: Path = bvh or args.amc
    trial = common.stream_name(source)
    rotations: bh.JointRotations | bh.RigRotations
    if bvh is not None:  # frames from 1, at the file's rate
        take = read_bvh(bvh)
        plan = hierarchy_plan(take.hierarchy, common.rig_maps(args, config))
        rotations = bh.RigRotations(take.hierarchy, plan)
        rate, frame_numbers, channels = take.rate, np.arange(1, len(take.channels) + 1), take.channels
    else:
        motion = read_recording(args.asf, args.amc)
        rate = native_rate(motion, common.default_native_rate(args, config))
        motion = continuous(motion, config.service.bridge_s, rate)
        rotations = bh.JointRotations(motion.skeleton)
        frame_numbers, channels = motion.frames, motion.channels
    bands = [] if args.truth is None else read_boundaries(args.truth, trial, rate=rate)
    began = time.perf_counter()
    try:
        result = bh.analyse(rotations(channels), rate, args.method, params=params(args))
    except InputError as exc:  # a window too short or long for the rate, a share out of range, ...
        raise UsageError(str(exc), field=f"--method {args.method}") from None
    took = time.perf_counter() - began
    frames = frame_numbers.tolist()
    cuts = [int(frames[b.frame]) for b in result.boundaries]
    for b, frame in zip(result.boundaries, cuts, strict=True):
        if args.json:
            print(json.dumps({"frame": frame, "method": b.method, "score": b.score}), flush=True)
        else:
            print(
                f"cut at frame {frame:6d} ({(frame - frames[0]) / rate:7.2f} s)  score {b.score:.4g}",
                flush=True,
            )
    if not args.json:
        seconds = len(frames) / rate
        print(
            f"{len(cuts)} cuts by {args.method} in {len(frames)} frames ({seconds:.1f} s at {rate:g} Hz), "
            f"{len(rotations.bones)} joints, in {took:.2f} s"
        )
        if bands:
            hits = bh.match_boundaries(cuts, bands)
            precision, recall = hits / len(cuts) if cuts else 0.0, hits / len(bands)
            print(f"truth: {hits} of {len(bands)} boundaries, precision {precision:.2f}, recall {recall:.2f}")
    if args.png is not None:
        title = f"{source.name}: behaviour segmentation by {args.method} (Barbič et al. 2004)"
        span = (int(frames[0]), int(frames[-1]))
        common.write_png(args.png, lambda out: segmentation_png(out, title, rate, span, [result], bands))
    return 0
