"""The index, its queries and keyframe search on a database of >= 1 M frames at 120 Hz (every AMC file
in ../shared/data/mocap, repeated), one core.

    python -m bench.bench_index [--repeat 3] [--queries 200]

Features are computed once (timed, as the baseline of the build) and the 30 Hz feature matrices
repeated. Prints: index build from feature matrices (120 Hz frames/s), size on disk per segment and
per frame, load time; median/p95 latency of random exact and adaptive fuzzy queries with 5, 10 and 20
segments in the upper index that have at least one hit (MRC05 Table 3: drawn from the database;
fuzzy sets of 64 codes), against a numpy scan of all segments as baseline; keyframe search latency for
every published class (../shared/reference/manual-keyframes.json), against the published algorithm
on the unpruned lists.
"""

from __future__ import annotations

import json
import math
import tempfile
import time
from collections.abc import Callable
from functools import partial
from pathlib import Path
from typing import TypeVar

import numpy as np

from bench.common import Recordings, arguments, best_of, load
from bench.machine import describe
from daemon.features import features
from daemon.keyframes import parse_keyframe_queries
from daemon.search.index import SetIndex, adaptive_fuzzy_query, exact_query, fuzzy_query, matching_codes
from daemon.search.keyframes import keyframe_search
from daemon.search.store import Document, index_bytes, index_from_matrices, load_index, save_index
from replay import JOINT_NAMES

T = TypeVar("T")
KEYFRAMES = Path(__file__).resolve().parents[1].parent / "shared" / "reference" / "manual-keyframes.json"
TARGET_FRAMES = 1_000_000


def scan_exact(index: SetIndex, codes: np.ndarray) -> np.ndarray:
    """Baseline: compare the query with every window of the segment codes (numpy, no index)."""
    k = len(codes)
    n = index.n_segments - k + 1
    ok = np.ones(n, dtype=bool)
    for i, c in enumerate(codes.tolist()):
        ok &= index.code[i : i + n] == c
    start = np.flatnonzero(ok)
    out: np.ndarray = start[index.doc[start] == index.doc[start + k - 1]]
    return out


def percentiles(times: list[float]) -> tuple[float, float]:
    """Median and 95th percentile in ms (nan if nothing was timed)."""
    if not times:
        return math.nan, math.nan
    a = 1e3 * np.asarray(times)
    return float(np.median(a)), float(np.percentile(a, 95))


def timed(run: Callable[[], T], repeat: int) -> tuple[float, T]:
    """Best time of ``repeat`` runs, and the result."""
    best = math.inf
    for _ in range(repeat):
        t = time.perf_counter()
        out = run()
        best = min(best, time.perf_counter() - t)
    return best, out


def repeated_documents(data: Recordings) -> tuple[list[np.ndarray], list[Document], int]:
    """The 30 Hz features (every 4th frame) of every recording and its :class:`Document`, all repeated
    to at least TARGET_FRAMES frames at 120 Hz; (matrices, documents, copies)."""
    matrices30 = data.features_at(30.0)
    copies = math.ceil(TARGET_FRAMES / data.frames)
    docs = [
        Document(str(amc), str(asf), int(m.frames[0]), int(m.frames[-1]), 4, len(x), 120.0)
        for (asf, amc), m, x in zip(data.pairs, data.motions, matrices30, strict=True)
    ]
    return matrices30 * copies, docs * copies, copies


def main() -> None:
    args = arguments(__doc__, queries=200)
    data = load(args.data)
    print(describe())
    clips = data.joints_cm()
    t_features = best_of(1, lambda: [features(c, JOINT_NAMES, 120.0) for c in clips])
    matrices, documents, copies = repeated_documents(data)
    frames120 = data.frames * copies
    print(
        f"database: {len(data.pairs)} AMC files x {copies} = {len(documents)} documents, "
        f"{frames120:,} frames at 120 Hz ({sum(d.frames for d in documents):,} at 30 Hz), one core, "
        f"best of {args.repeat}"
    )

    t_build = best_of(args.repeat, lambda: index_from_matrices(matrices, documents, 30.0))
    index = index_from_matrices(matrices, documents, 30.0)
    base_rate = data.frames / t_features
    print(f"\n{'stage':44s} {'frames/s':>12s} {'vs features':>12s}")
    print(f"{'features, batch (baseline)':44s} {base_rate:12,.0f} {1:11.2f}x")
    build_rate = frames120 / t_build
    print(f"{'index build from feature matrices':44s} {build_rate:12,.0f} {build_rate / base_rate:11.2f}x")
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "idx"
        save_index(index, path)
        sizes = {fs: index_bytes(path, fs) for fs in index.sets}
        t_load = best_of(args.repeat, lambda: load_index(path))
    print(
        f"\n{'index':8s} {'segments':>10s} {'lists':>7s} {'MB':>7s} {'bytes/seg':>10s} {'bytes/frame':>12s}"
    )
    for fs, set_index in index.sets.items():
        size = sizes[fs]
        lists = set_index.nonempty_lists
        per_segment = size / set_index.n_segments
        print(
            f"{fs:8s} {set_index.n_segments:10,d} {lists:7d} {size / 2**20:7.2f} {per_segment:10.1f} "
            f"{size / frames120:12.2f}"
        )
    print(f"load (memory-mapped): {1e3 * t_load:.1f} ms")

    rng = np.random.default_rng(7)
    upper = index.sets["upper"]
    print(f"\nrandom queries with >= 1 hit, upper index, {args.queries} per row (ms; scan = numpy baseline)")
    print(f"{'query':28s} {'median':>8s} {'p95':>8s} {'hits med':>9s} {'scan med':>9s} {'speed-up':>9s}")
    for k in (5, 10, 20):
        starts: list[int] = []
        while len(starts) < args.queries:
            s = int(rng.integers(0, upper.n_segments - k))
            if upper.doc[s] == upper.doc[s + k - 1]:
                starts.append(s)
        exact_t: list[float] = []
        fuzzy_t: list[float] = []
        adaptive_t: list[float] = []
        scan_t: list[float] = []
        exact_h: list[int] = []
        fuzzy_h: list[int] = []
        adaptive_h: list[int] = []
        for s in starts:
            codes = upper.code[s : s + k]
            t, hits = timed(partial(exact_query, upper, codes.tolist()), args.repeat)
            assert s in hits.first.tolist()
            exact_t.append(t)
            exact_h.append(len(hits))
            t, found = timed(partial(scan_exact, upper, codes), args.repeat)
            assert np.array_equal(found, hits.first)
            scan_t.append(t)
            masks = [sum(1 << int(b) for b in rng.choice(upper.bits, 8, replace=False)) for _ in range(k)]
            sets = [matching_codes(upper.bits, int(c), m) for c, m in zip(codes.tolist(), masks, strict=True)]
            t, hits = timed(partial(fuzzy_query, upper, sets), args.repeat)
            assert s in hits.first.tolist()
            fuzzy_t.append(t)
            fuzzy_h.append(len(hits))
            for _ in range(50):  # a fuzzy query built from a stretch need not be an adaptive hit there
                t, hits = timed(partial(adaptive_fuzzy_query, upper, sets), args.repeat)
                if len(hits):
                    adaptive_t.append(t)
                    adaptive_h.append(len(hits))
                    break
                masks = [sum(1 << int(b) for b in rng.choice(upper.bits, 8, replace=False)) for _ in range(k)]
                sets = [
                    matching_codes(upper.bits, int(c), m) for c, m in zip(codes.tolist(), masks, strict=True)
                ]
        for label, ts, hs in (
            ("exact", exact_t, exact_h),
            ("fuzzy (64)", fuzzy_t, fuzzy_h),
            ("adaptive fuzzy (64)", adaptive_t, adaptive_h),
        ):
            med, p95 = percentiles(ts)
            scan_med = percentiles(scan_t)[0]
            print(
                f"{label + f', {k} segs':28s} {med:8.2f} {p95:8.2f} {np.median(hs):9.0f} {scan_med:9.2f} "
                f"{scan_med / med:8.1f}x"
            )

    queries = parse_keyframe_queries(json.loads(KEYFRAMES.read_text()), str(KEYFRAMES))
    frames30 = [d.frames for d in documents]
    rows = []
    for name, q in queries.items():
        t, found_k = timed(partial(keyframe_search, index.sets, frames30, q, 30.0), args.repeat)
        t_plain, plain = timed(partial(keyframe_search, index.sets, frames30, q, 30.0, prune=False), 1)
        assert np.array_equal(plain.start, found_k.start) and np.array_equal(plain.end, found_k.end)
        rows.append(
            (name, len(q.keyframes), sum(found_k.list_lengths), t, t_plain, found_k.frames, len(found_k))
        )
    ts = [r[3] for r in rows]
    med, p95 = percentiles(ts)
    plain_med = percentiles([r[4] for r in rows])[0]
    print(
        f"\nkeyframe search, {len(rows)} published classes (ms, incl. list unions): median {med:.2f}, "
        f"p95 {p95:.2f}, max {1e3 * max(ts):.2f} ({max(rows, key=lambda r: r[3])[0]}); published "
        f"algorithm on unpruned lists: median {plain_med:.2f} ({plain_med / med:.1f}x slower)"
    )
    total30 = sum(frames30)
    print(f"{'class':56s} {'#KF':>4s} {'sum l':>7s} {'ms':>7s} {'%(D)':>6s} {'hits':>6s}")
    for name, kf, sl, t, _, covered, n in sorted(rows, key=lambda r: -r[3])[:12]:
        print(f"{name:56s} {kf:4d} {sl:7d} {1e3 * t:7.2f} {100 * covered / total30:6.2f} {n:6d}")


if __name__ == "__main__":
    main()
