"""DTW throughput (daemon.dtw) in cells per second, cells = M·N (template columns x database frames),
one core, and the subsequence pass against dtaidistance's C implementation.

    python -m bench.bench_dtw [--repeat 3] [--template 50] [--frames 250000] [--matrix 20000]
                              [--dtai 250000]

Inputs: the 39 features of every AMC file in ../shared/data/mocap at 30 Hz (computed once, not
timed), the documents repeated to ``--frames`` database frames, each followed by two blocked columns
as ranked retrieval lays them out (daemon.search.retrieval); random booleans with the real data's density
if no recordings are found. The template is a real ``--template``-frame stretch of one document with
~30 % of its entries set to ½ (a quantised template over {0, ½, 1}) and weights in [1, 10].

Prints cells/s of: full DTW (``full_dtw`` on random 60x60 and 200x200 cost matrices, including the
fixed-point conversion and the path); subsequence DTW over the whole database with the cost rows
computed lazily from packed codes (``retrieval_rows``, the retrieval path), both step sets; the same
from a precomputed float cost matrix of ``--matrix`` frames (``subsequence_dtw``); the stream
(``SubsequenceStream.push``, one database frame per call, µs per frame against the 8.3 ms of a frame
at 120 Hz). Every figure is also given relative to one plain numpy pass over as many cells
(``np.minimum`` of two (M, N) int64 arrays), measured in the same run. Then the subsequence
matching curve of the first ``--dtai`` database frames (at most ``--frames``) against
dtaidistance's C implementation (``pip install -e '.[bench]'``; the section is skipped without it).
"""

from __future__ import annotations

import math
import tracemalloc
from collections.abc import Callable
from dataclasses import dataclass
from functools import partial
from pathlib import Path
from unittest import mock

import numpy as np

from bench.common import arguments, best_of, load
from bench.machine import describe
from daemon.dtw import (
    INF,
    STEPS,
    Steps,
    SubsequenceStream,
    fixed,
    full_dtw,
    pack,
    retrieval_cost,
    retrieval_rows,
    subsequence_dtw,
    subsequence_fixed,
    to_cost,
)
from daemon.types import BoolArray, FloatArray

N_FEATURES = 39
SEPARATOR = 2  # blocked columns after each document, as daemon.search.retrieval lays out the database
HALF_SHARE = 0.3
FRAME_120HZ_US = 1e6 / 120
DENSITY = 0.21  # mean share of true features in the 30 Hz feature matrices of ../shared/data/mocap


@dataclass(frozen=True)
class Database:
    frames: BoolArray  # (N, 39), blocked columns all False
    blocked: BoolArray  # (N,)


def real_documents(root: Path) -> list[BoolArray]:
    """The 30 Hz feature matrices of every recording under ``root`` (empty if there is none)."""
    return load(root).features_at(30.0)


def database(documents: list[BoolArray], n: int) -> Database:
    """The documents repeated to ``n`` columns, each followed by :data:`SEPARATOR` blocked columns."""
    parts: list[BoolArray] = []
    marks: list[BoolArray] = []
    total = 0
    while total < n:
        for doc in documents:
            parts += [doc, np.zeros((SEPARATOR, N_FEATURES), dtype=bool)]
            marks += [np.zeros(len(doc), dtype=bool), np.ones(SEPARATOR, dtype=bool)]
            total += len(doc) + SEPARATOR
            if total >= n:
                break
    return Database(np.concatenate(parts)[:n], np.concatenate(marks)[:n])


def quantised_template(
    documents: list[BoolArray], m: int, rng: np.random.Generator
) -> tuple[FloatArray, FloatArray]:
    """A real ``m``-frame stretch as an ``(39, m)`` template over {0, ½, 1} (~30 % ½) and its weights."""
    long_enough = [d for d in documents if len(d) >= m]
    if long_enough:
        doc = long_enough[int(rng.integers(len(long_enough)))]
        first = int(rng.integers(len(doc) - m + 1))
        values = doc[first : first + m].T.astype(np.float64)
    else:
        values = (rng.random((N_FEATURES, m)) < DENSITY).astype(np.float64)
    values[rng.random(values.shape) < HALF_SHARE] = 0.5
    return values, rng.uniform(1.0, 10.0, m)


@dataclass(frozen=True)
class Row:
    label: str
    cells: int
    seconds: float
    note: str = ""


def cells_per_second(
    label: str, m: int, n: int, repeat: int, run: Callable[[], object], calls: int = 1
) -> Row:
    """Best of ``repeat`` timings of ``calls`` runs over an ``m`` x ``n`` matrix, per run."""

    def many() -> None:
        for _ in range(calls):
            run()

    return Row(label, m * n, best_of(repeat, many) / calls)


def print_table(rows: list[Row], base: float) -> None:
    print(f"\n{'pass':62s} {'cells':>12s} {'ms':>9s} {'Mcells/s':>9s} {'vs numpy':>9s}  note")
    for r in rows:
        rate = r.cells / r.seconds
        print(
            f"{r.label:62s} {r.cells:12,d} {1e3 * r.seconds:9.2f} {rate / 1e6:9.2f} "
            f"{rate / base:8.3f}x  {r.note}"
        )


def numpy_pass(m: int, n: int, repeat: int, rng: np.random.Generator) -> float:
    """The baseline: one ``np.minimum`` of two ``(m, n)`` int64 arrays into a third; seconds."""
    a = rng.integers(0, INF, (m, n), dtype=np.int64)
    b = rng.integers(0, INF, (m, n), dtype=np.int64)
    out = np.empty_like(a)
    return best_of(repeat, lambda: np.minimum(a, b, out=out))


def peak_mb(run: Callable[[], object]) -> float:
    """Peak traced allocation of one run (numpy reports its buffers to tracemalloc), MB."""
    tracemalloc.start()
    try:
        run()
        return tracemalloc.get_traced_memory()[1] / 2**20
    finally:
        tracemalloc.stop()


def stream_pass(columns: FloatArray, tau: float, steps: Steps) -> int:
    """Push every column (one database frame's template costs) into a stream; the number of matches."""
    stream = SubsequenceStream(columns.shape[1], tau, steps)
    found = sum(stream.push(c) is not None for c in columns)
    return found + (stream.flush() is not None)


def compare_dtaidistance(
    values: FloatArray, weights: FloatArray, frames: BoolArray, repeat: int, numpy_rate: float
) -> None:
    """Our subsequence matching curve (lazy retrieval rows, thesis steps) against dtaidistance's C
    ``warping_paths_ndim`` (what ``subsequence_alignment(..., use_c=True).align()`` runs) on the same
    template and frames."""
    m, n = values.shape[1], len(frames)
    print(
        f"\nsubsequence DTW against dtaidistance, M = {m}, N = {n:,}: the first N database frames (the "
        "separator columns as all-zero frames, not blocked, for both)"
    )
    try:
        from dtaidistance import dtw as dta_dtw
        from dtaidistance.subsequence.dtw import subsequence_alignment
    except ImportError:
        print("  dtaidistance is not installed: pip install -e '.[bench]' (section skipped)")
        return
    dtw_cc = dta_dtw.dtw_cc
    if dtw_cc is None:
        print("  dtaidistance's C library (dtw_cc) cannot be imported, only its Python code (skipped)")
        return
    codes = pack(frames)
    query = np.ascontiguousarray(values.T)  # (M, 39)
    series = frames.astype(np.float64)  # (N, 39)

    def dtai_curve(q: FloatArray, s: FloatArray) -> tuple[FloatArray, FloatArray]:
        sa = subsequence_alignment(q, s, penalty=0.0, use_c=True)
        sa.align()
        return np.asarray(sa.matching_function()), np.asarray(sa.warping_paths())

    # the C function runs (and nothing else computes the matrix), and both give the same DTW: with a
    # template without ½ and weights 1, our cost is the squared Euclidean distance / (39 M)
    hard = np.rint(values[:, : min(m, 40)])
    k = min(n, 3000)
    with mock.patch.object(dtw_cc, "warping_paths_ndim", wraps=dtw_cc.warping_paths_ndim) as c_call:
        _, paths = dtai_curve(np.ascontiguousarray(hard.T), series[:k])
    assert c_call.call_count == 1, "dtaidistance did not run its C warping_paths_ndim"
    ours = to_cost(subsequence_fixed(retrieval_rows(hard, np.ones(hard.shape[1]), codes[:k]))[0])
    assert np.array_equal(np.rint(ours * N_FEATURES * hard.shape[1]), paths[-1, 1:]), "different DTW"

    def ours_run() -> FloatArray:
        return to_cost(subsequence_fixed(retrieval_rows(values, weights, codes), "thesis")[0])

    # interleaved, so that a drift of the machine's speed hits both alike
    t_ours = t_dtai = math.inf
    for _ in range(repeat):
        t_ours = min(t_ours, best_of(1, ours_run))
        t_dtai = min(t_dtai, best_of(1, lambda: dtai_curve(query, series)))
    mb_ours, mb_dtai = peak_mb(ours_run), peak_mb(lambda: dtai_curve(query, series))
    rows = [
        Row("ours: subsequence_fixed(retrieval_rows(codes)), thesis steps", m * n, t_ours),
        Row("dtaidistance 2.x C: subsequence_alignment(use_c=True).align()", m * n, t_dtai),
    ]
    print_table(rows, numpy_rate)
    print(
        f"  ours / dtaidistance: {t_ours / t_dtai:.2f}x the time (verified on {k:,} frames: same DTW, "
        f"C function called)\n"
        f"  peak memory (tracemalloc, numpy's buffers): ours {mb_ours:.0f} MB, dtaidistance {mb_dtai:.0f} MB "
        f"(its (M+1) x (N+1) float64 matrix: {(m + 1) * (n + 1) * 8 / 2**20:.0f} MB)\n"
        "  what differs: dtaidistance computes squared Euclidean costs over the 39 float64 dimensions in C,\n"
        "  fills the full accumulated matrix (steps (1,0), (0,1), (1,1), no penalty, free start/end by\n"
        "  psi) and divides the last row by M; ours computes the c& retrieval cost per template column from\n"
        "  64-bit codes with popcount (numpy, row by row), accumulates exactly in int64 fixed point, tracks\n"
        "  every cell's start column instead of keeping the matrix, and converts Δ back to floats. Both\n"
        "  give the full matching curve (N values); input conversion (pack / astype) is not timed."
    )


def main() -> None:
    args = arguments(__doc__, template=50, frames=250_000, matrix=20_000, dtai=250_000)
    print(describe())
    rng = np.random.default_rng(11)
    documents = real_documents(args.data)
    if documents:
        source = f"real features of {len(documents)} AMC files ({sum(len(d) for d in documents):,} frames)"
    else:
        documents = [rng.random((100, N_FEATURES)) < DENSITY for _ in range(200)]
        source = f"no recordings under {args.data}: random booleans, density {DENSITY}, 100-frame documents"
    db = database(documents, args.frames)
    m, n = args.template, args.frames
    values, weights = quantised_template(documents, m, rng)
    codes = pack(db.frames)
    print(
        f"database: {n:,} frames at 30 Hz, 39 features, {source}, repeated, 2 blocked columns after each "
        f"document; template M = {m} ({np.mean(values == 0.5):.0%} ½); one core, best of {args.repeat}"
    )

    t_base = numpy_pass(m, n, args.repeat, rng)
    base = m * n / t_base
    rows = [Row(f"numpy np.minimum of two ({m}, {n:,}) int64 arrays (baseline)", m * n, t_base)]

    for size in (60, 200):
        cost = rng.random((size, size))
        label = f"full_dtw {size}x{size} random costs (fixed point + path)"
        calls = max(1, 1_000_000 // size**2)
        rows.append(cells_per_second(label, size, size, args.repeat, partial(full_dtw, cost), calls))

    def lazy_pass(steps: Steps | None) -> object:
        costs = retrieval_rows(values, weights, codes, db.blocked)
        return list(costs) if steps is None else subsequence_fixed(costs, steps)

    label = "cost rows only: list(retrieval_rows(codes, blocked))"
    rows.append(cells_per_second(label, m, n, args.repeat, partial(lazy_pass, None)))
    for steps in STEPS:
        label = f"subsequence_fixed(retrieval_rows(codes, blocked)), {steps}"
        rows.append(cells_per_second(label, m, n, args.repeat, partial(lazy_pass, steps)))

    # a continuous stretch (no blocked columns) as a float cost matrix, and as a stream of columns
    k = min(args.matrix, n)
    contiguous = db.frames[~db.blocked][:k]
    cost = retrieval_cost(values, weights, contiguous.T.astype(np.float64))
    columns = np.ascontiguousarray(cost.T)
    matches: dict[str, int] = {}
    for steps in STEPS:
        sub = subsequence_dtw(cost, steps)
        lazy = subsequence_fixed(retrieval_rows(values, weights, pack(contiguous)), steps)
        assert np.array_equal(fixed(sub.delta), lazy[0]) and np.array_equal(sub.start, lazy[1])
        label = f"subsequence_dtw(float ({m}, {k:,}) matrix), {steps}"
        rows.append(cells_per_second(label, m, k, args.repeat, partial(subsequence_dtw, cost, steps)))
        tau = float(np.quantile(sub.delta[np.isfinite(sub.delta)], 0.01))
        matches[steps] = stream_pass(columns, tau, steps)
        label = f"SubsequenceStream.push, {steps}, tau = 1% quantile of Δ"
        row = cells_per_second(label, m, k, args.repeat, partial(stream_pass, columns, tau, steps))
        per_frame = 1e6 * row.seconds / k
        note = f"{per_frame:.1f} µs/frame = {per_frame / FRAME_120HZ_US:.2%} of a 120 Hz frame"
        rows.append(Row(row.label, row.cells, row.seconds, note))
    print_table(rows, base)
    print(
        f"  stream: {k:,} frames, one push each (column costs precomputed), "
        f"{matches['thesis']} / {matches['toolbox']} disjoint matches (thesis / toolbox)"
    )

    n_dtai = min(args.dtai, n)
    compare_dtaidistance(values, weights, db.frames[:n_dtai], args.repeat, base)


if __name__ == "__main__":
    main()
