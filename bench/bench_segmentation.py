"""Behaviour segmentation speed (daemon.behaviours, Barbič et al. 2004) on the real files of the
evaluation and 135_06, one core.

    python -m bench.bench_segmentation [--repeat 3] [--data DIR]

Prints frames/s for: the baselines, measured in the same run because this machine's speed drifts
between runs (per-frame forward kinematics of every 20th frame, as the other benchmarks; the frame
representation, batch and one frame at a time); PCA (§3.1) online, one ``push`` per frame, with the
error evaluated every frame (the paper) and every ℓ frames (``PCA_GRID``); PPCA's forward pass online
(§3.2); the same online methods from channels, each frame's representation computed as it comes
(``live``: what a segmented stream of the daemon runs per pose, PCA every frame and as the daemon
runs it, every 1/12 s: ``PCA_ONLINE``); and the batch functions: PCA both
ways, PPCA's forward pass and all its passes, GMM (§3.3). The other segmenter rows take the
representation's frames (computed once, not timed).

The process is pinned to one core, so it runs with OpenBLAS on one thread (it starts itself again
with ``OPENBLAS_NUM_THREADS=1`` if that is not set): BLAS threads sharing one core make a 112 x 112
``eigvalsh`` several times slower.
"""

from __future__ import annotations

import os
import sys
from collections.abc import Callable

from bench.common import arguments, best_of
from bench.machine import describe
from daemon import behaviours as bh
from daemon.recordings import native_rate, read_recording
from daemon.tools.mocap6 import trial_recording
from daemon.types import FloatArray
from replay import KinematicModel, Motion

TRIALS = ("86_01", "13_29", "13_30", "14_14", "135_06")


def _one_blas_thread() -> None:
    if os.environ.get("OPENBLAS_NUM_THREADS") != "1":
        env = {**os.environ, "OPENBLAS_NUM_THREADS": "1", "OMP_NUM_THREADS": "1"}
        os.execve(sys.executable, [sys.executable, "-m", "bench.bench_segmentation", *sys.argv[1:]], env)


def main() -> None:
    _one_blas_thread()
    args = arguments(__doc__)
    motions: list[Motion] = [read_recording(*trial_recording(args.data, t)) for t in TRIALS]
    rates = [native_rate(m) for m in motions]
    rotations = [bh.JointRotations(m.skeleton) for m in motions]
    xs: list[FloatArray] = [r(m.channels) for r, m in zip(rotations, motions, strict=True)]
    frames = sum(len(m) for m in motions)
    print(describe())
    print(
        f"data: {', '.join(TRIALS)} ({frames} frames at {rates[0]:g} Hz, D = {rotations[0].dims}); pinned to "
        f"one core, OpenBLAS threads {os.environ.get('OPENBLAS_NUM_THREADS')}, best of {args.repeat}"
    )
    models = [KinematicModel(m.skeleton) for m in motions]
    sample = [m.channels[::20] for m in motions]
    sampled = sum(len(s) for s in sample)

    def fk() -> None:
        for model, channels in zip(models, sample, strict=True):
            for row in channels:
                model.positions_frame(row)

    def representation_batch() -> None:
        for r, m in zip(rotations, motions, strict=True):
            r(m.channels)

    def representation_stream() -> None:
        for r, m in zip(rotations, motions, strict=True):
            stream = r.stream()
            for row in m.channels:
                stream.frame(row)

    def online(make: Callable[[float], bh.PcaSegmenter | bh.PpcaSegmenter]) -> Callable[[], None]:
        def go() -> None:
            for x, rate in zip(xs, rates, strict=True):
                segmenter = make(rate)
                for row in x:
                    segmenter.push(row)
                segmenter.flush()

        return go

    def live(make: Callable[[float], bh.PcaSegmenter | bh.PpcaSegmenter]) -> Callable[[], None]:
        def go() -> None:
            for r, m, rate in zip(rotations, motions, rates, strict=True):
                stream, segmenter = r.stream(), make(rate)
                for row in m.channels:
                    segmenter.push(stream.frame(row))
                segmenter.flush()

        return go

    def batch(method: Callable[[FloatArray, float], object]) -> Callable[[], None]:
        def go() -> None:
            for x, rate in zip(xs, rates, strict=True):
                method(x, rate)

        return go

    base = sampled / best_of(args.repeat, fk)
    rows: list[tuple[str, float]] = [
        ("forward kinematics, per frame (baseline)", base),
        ("representation, batch", frames / best_of(args.repeat, representation_batch)),
        ("representation, per frame (RotationStream)", frames / best_of(args.repeat, representation_stream)),
    ]
    cases: list[tuple[str, Callable[[], None]]] = [
        ("PCA online, every frame (paper)", online(lambda rate: bh.PcaSegmenter(rate))),
        (
            "PCA online, every ℓ frames (PCA_GRID)",
            online(lambda rate: bh.PcaSegmenter(rate, params=bh.PCA_GRID)),
        ),
        ("PPCA online (forward pass)", online(lambda rate: bh.PpcaSegmenter(rate))),
        ("live: channels -> PCA online, every frame", live(lambda rate: bh.PcaSegmenter(rate))),
        (
            "live: channels -> PCA every 1/12 s (daemon)",
            live(lambda rate: bh.PcaSegmenter(rate, params=bh.PCA_ONLINE)),
        ),
        ("live: channels -> PPCA online", live(lambda rate: bh.PpcaSegmenter(rate))),
        ("PCA batch, every frame", batch(lambda x, rate: bh.pca_segment(x, rate))),
        ("PCA batch, every ℓ frames", batch(lambda x, rate: bh.pca_segment(x, rate, params=bh.PCA_GRID))),
        ("PPCA batch, forward pass", batch(lambda x, rate: bh.ppca_forward(x, rate))),
        ("PPCA batch, all passes", batch(lambda x, rate: bh.ppca_segment(x, rate))),
        ("GMM batch (k = 4)", batch(lambda x, rate: bh.gmm_segment(x, rate))),
    ]
    rows += [(name, frames / best_of(args.repeat, go)) for name, go in cases]
    print(f"{'stage':46s} {'frames/s':>12s} {'vs baseline':>12s} {'streams at 120 Hz':>18s}")
    for name, speed in rows:
        print(f"{name:46s} {speed:12,.0f} {speed / base:11.2f}x {speed / 120:18,.0f}")


if __name__ == "__main__":
    main()
