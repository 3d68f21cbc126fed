"""Motion-template learning and retrieval timings, one core.

    python -m bench.bench_templates [--repeat 3]

Learning: every HDM05 class in ../shared/data/mocap learned from the cut clips of actors bd and bk
(default toolbox steps), one run each. Retrieval: the quantised class template ranked (τ = 0.1, at
most 500 hits) over the whole >= 1 M-frame database of bench.bench_index (every AMC file, features at
30 Hz, repeated), then only inside the ranges a keyframe search kept with the learned and the
published keyframes (../shared/reference/manual-keyframes.json); ms (best of --repeat), share of the
database the DTW ran over and speed-up vs the whole-database search.
"""

from __future__ import annotations

import json
import math
import time
from functools import partial
from pathlib import Path

import numpy as np

from bench.bench_index import KEYFRAMES, repeated_documents, timed
from bench.common import arguments, load
from bench.eval_templates import hdm05_clips, training_sets
from bench.machine import describe
from daemon.keyframes import KeyframeQuery, parse_keyframe_queries
from daemon.learn.library import learn_class
from daemon.library import ClassTemplate
from daemon.search.retrieval import frame_codes, template_search
from daemon.search.store import MotionIndex, index_from_matrices
from daemon.templates import expand

TAU = 0.1
LIMIT = 500


def database(data: Path) -> tuple[MotionIndex, int, int]:
    """The index of bench.bench_index's database (30 Hz features of every AMC file, repeated to
    >= 1 M frames at 120 Hz); (index, AMC files, frames at 120 Hz)."""
    recs = load(data)
    matrices, documents, copies = repeated_documents(recs)
    return index_from_matrices(matrices, documents, 30.0), len(recs.pairs), recs.frames * copies


def main() -> None:
    args = arguments(__doc__)
    print(describe())

    clips = training_sets(hdm05_clips(args.data, ("bd", "bk")))
    print(f"\nlearning (toolbox steps), {sum(map(len, clips.values()))} bd/bk training clips, one run each")
    print(f"{'class':30s} {'train':>5s} {'soft K':>6s} {'iter':>4s} {'hard K':>6s} {'s':>7s}")
    learned: dict[str, ClassTemplate] = {}
    learn_s: list[float] = []
    for name in sorted(clips):
        t0 = time.perf_counter()
        cls = learn_class(name, clips[name])
        seconds = time.perf_counter() - t0
        learned[name] = cls
        learn_s.append(seconds)
        print(
            f"{name:30s} {len(clips[name]):5d} {cls.soft.length:6d} {cls.iterations:4d} "
            f"{cls.hard.length:6d} {seconds:7.2f}"
        )
    print(f"{'total':30s} {sum(map(len, clips.values())):5d} {'':6s} {'':4s} {'':6s} {sum(learn_s):7.2f}")

    t0 = time.perf_counter()
    index, files, frames120 = database(args.data)
    t_db = time.perf_counter() - t0
    t_codes, codes = timed(partial(frame_codes, index), args.repeat)
    print(
        f"\ndatabase: {files} AMC files repeated to {len(index.documents)} documents, {frames120:,} frames "
        f"at 120 Hz ({index.n_frames:,} at 30 Hz), built in {t_db:.1f} s; frame_codes: "
        f"{1e3 * t_codes:.1f} ms (once, not in the times below); best of {args.repeat}"
    )
    published = parse_keyframe_queries(json.loads(KEYFRAMES.read_text()), str(KEYFRAMES))
    print(
        f"retrieval, τ = {TAU}, at most {LIMIT} hits (ms; %(D) = share searched; x = speed-up vs whole)\n"
        f"{'class':30s} {'Kexp':>5s} {'whole ms':>9s} {'Mcells/s':>9s} {'hits':>5s} "
        f"{'learned ms':>10s} {'%(D)':>6s} {'x':>7s} {'publ. ms':>9s} {'%(D)':>6s} {'x':>7s}"
    )
    whole_ms: list[float] = []
    rates: list[float] = []
    speedups: dict[str, list[float]] = {"learned": [], "published": []}
    for name, cls in learned.items():
        expanded = expand(cls.quantised).length
        t_whole, hits = timed(
            partial(
                template_search, index, cls.quantised, tau=TAU, steps=cls.steps, limit=LIMIT, codes=codes
            ),
            args.repeat,
        )
        rate = expanded * hits.searched / t_whole
        whole_ms.append(1e3 * t_whole)
        rates.append(rate)
        cells = []
        queries: list[tuple[str, KeyframeQuery | None]] = [
            ("learned", cls.keyframes),
            ("published", published.get(name)),
        ]
        for label, query in queries:
            if query is None:
                cells.append(f"{'-':>10s} {'-':>6s} {'-':>7s}")
                continue
            t, kf_hits = timed(
                partial(
                    template_search,
                    index,
                    cls.quantised,
                    tau=TAU,
                    steps=cls.steps,
                    keyframes=query,
                    limit=LIMIT,
                    codes=codes,
                ),
                args.repeat,
            )
            speedups[label].append(t_whole / t)
            share = 100 * kf_hits.searched / index.n_frames
            cells.append(f"{1e3 * t:10.2f} {share:6.2f} {t_whole / t:6.1f}x")
        print(
            f"{name:30s} {expanded:5d} {1e3 * t_whole:9.1f} {rate / 1e6:9.1f} {len(hits):5d} "
            f"{cells[0]} {cells[1][1:]}"
        )

    def med(values: list[float]) -> float:
        return float(np.median(values)) if values else math.nan

    print(
        f"\nsummary (medians): learning {med(learn_s):.2f} s/class; whole-database search "
        f"{med(whole_ms):.1f} ms ({med(rates) / 1e6:.1f} M DTW cells/s); keyframe pre-selection speed-up "
        f"{med(speedups['learned']):.1f}x learned, {med(speedups['published']):.1f}x published"
    )


if __name__ == "__main__":
    main()
