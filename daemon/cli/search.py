"""Commands on motion databases: ``index build``, ``index info`` and ``search``."""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path
from typing import Any

from daemon.checks import read_structured
from daemon.cli import common
from daemon.config import Config
from daemon.dtw import STEPS
from daemon.errors import UsageError
from daemon.keyframes import KeyframeError, KeyframeQuery, parse_keyframe_queries
from daemon.library import load_library
from daemon.recordings import RateError, display_path, read_bvh_features, read_features, read_manifest
from daemon.search.index import (
    Hits,
    QueryError,
    adaptive_fuzzy_query,
    example_query,
    feature_selection,
    fuzzy_query,
    mismatch_query,
    ranked,
)
from daemon.search.keyframes import keyframe_search
from daemon.search.retrieval import template_search
from daemon.search.store import (
    INDEX_JSON,
    Document,
    MotionIndex,
    build_index,
    check_index_target,
    index_bytes,
    load_index,
    save_index,
)
from daemon.types import DEFAULT_INDEX_RATE, FEATURE_SETS

LIBRARY_KEYFRAMES = Path("<the library's keyframes>")
Row = dict[str, object]

ADAPTIVE_FUZZY = (
    "answered as an adaptive fuzzy query (MRC05 5.3): the database's segmentation is coarsened to the "
    "query's sets, so a hit is a run of consecutive stretches whose frames lie in the query's sets one "
    "after another; a larger --fuzzy makes neighbouring sets overlap more, stretches merge and fewer "
    "places split into the query's segments, so it can find fewer hits (--plain: every database "
    "segment checked against its own set instead)"
)


def register(sub: Any) -> None:
    index = sub.add_parser("index", help="build or describe a motion index (inverted lists of F-segments)")
    index_sub = index.add_subparsers(required=True, metavar="{build,info}")
    build = index_sub.add_parser(
        "build", help="index the recordings of a manifest CSV (columns asf and amc, or bvh)"
    )
    build.add_argument("--manifest", type=Path, required=True, help="CSV with columns asf and amc, or bvh")
    build.add_argument("--out", type=Path, required=True, help="index directory to write (replaced)")
    common.rate_option(build, DEFAULT_INDEX_RATE, "index rate (default 30)")
    common.native_rate_option(build)
    common.rig_option(build)
    build.set_defaults(func=_index_build)
    info = index_sub.add_parser("info", help="describe an index: documents, frames, segments, size")
    info.add_argument("index", type=Path, help="index directory")
    info.add_argument("--json", action="store_true", help="print one JSON object instead of text")
    info.set_defaults(func=_index_info)

    search = sub.add_parser(
        "search",
        help="find motions in an index: with a class's motion template (thesis ch. 3/5), "
        "by keyframes (ch. 4) or by example (MRC05)",
    )
    search.add_argument("--index", type=Path, required=True, help="index directory (mocapd index build)")
    search.add_argument(
        "--library", type=Path, help="rank by the motion template of --class from this library"
    )
    mode = search.add_mutually_exclusive_group()
    mode.add_argument(
        "--keyframes",
        type=Path,
        nargs="?",
        const=LIBRARY_KEYFRAMES,
        help="keyframe queries, JSON as manual-keyframes.json; with --library: pre-select by keyframes "
        "before ranking (the library's own when no file is given)",
    )
    mode.add_argument(
        "--example",
        nargs="+",
        metavar="ASF AMC|BVH START END",
        help=f"query by example: a recording (ASF and AMC, or a BVH take) and its frames START..END "
        f"(AMC frame numbers; a BVH's from 1), {ADAPTIVE_FUZZY}",
    )
    search.add_argument(
        "--class", dest="class_name", help="with --keyframes or --library: the class to search"
    )
    search.add_argument(
        "--tau",
        type=common.positive_float,
        default=None,
        help="with --library: cost threshold (default: the class's, calibrated when it was learned)",
    )
    search.add_argument(
        "--steps",
        choices=STEPS,
        default=None,
        help="with --library: DTW steps, thesis (1,0),(0,1),(1,1) or toolbox (1,1),(1,2),(2,1) "
        "(default: the class's)",
    )
    search.add_argument(
        "--extend",
        default=None,
        metavar="LEFT,RIGHT",
        help="with --keyframes: widen keyframe ranges by index frames (default 0,0; with --library: the "
        "template's columns before the first and after the last keyframe, x 1.5)",
    )
    search.add_argument("--features", help="with --example: comma-separated feature names, all from one set")
    search.add_argument(
        "--fuzzy",
        type=int,
        default=0,
        metavar="N",
        help="with --example: also accept vectors differing in up to N selected features (default 0)",
    )
    search.add_argument(
        "--plain", action="store_true", help="with --example: a plain fuzzy query instead of an adaptive one"
    )
    search.add_argument(
        "--mismatch", type=int, default=None, metavar="M", help="with --example: m-mismatch search"
    )
    common.native_rate_option(search)
    search.add_argument("--limit", type=int, default=None, help="print at most this many hits")
    search.add_argument("--json", action="store_true", help="one JSON object per hit and line")
    common.rig_option(search)
    search.set_defaults(func=_search)


# ------------------------------------------------------------------------------------------- index


def _index_build(args: argparse.Namespace, config: Config) -> int:
    began = time.perf_counter()
    rows = read_manifest(args.manifest, bvh=True)
    check_index_target(args.out)  # before the long part

    def progress(done: int, total: int, document: Document) -> None:
        print(
            f"[{done}/{total}] {display_path(args.manifest.parent, document.amc)} "
            f"({document.frames} frames at {args.fps:g} Hz)",
            file=sys.stderr,
            flush=True,
        )

    index = build_index(
        rows,
        rate=args.fps,
        progress=progress,
        default_native_rate=common.default_native_rate(args, config),
        base=args.manifest.parent,
        maps=common.rig_maps(args, config),
    )
    save_index(index, args.out)
    seconds = time.perf_counter() - began
    size = index_bytes(args.out)
    print(f"index:      {args.out}")
    print(f"documents:  {len(index.documents)}")
    print(f"frames:     {index.n_frames} at {index.rate:g} Hz")
    for s in FEATURE_SETS:
        print(f"{s + ':':<11} {index.sets[s].n_segments} segments")
    print(f"build time: {seconds:.2f} s")
    print(f"size:       {size} bytes")
    return 0


def _index_info(args: argparse.Namespace, config: Config) -> int:
    index = load_index(args.index)
    sets = {}
    for s in FEATURE_SETS:
        entry = index.sets[s]
        size = index_bytes(args.index, s)
        segments = entry.n_segments
        sets[s] = {
            "bits": entry.bits,
            "segments": segments,
            "nonempty_lists": entry.nonempty_lists,
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
        "bytes": index_bytes(args.index),
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


# ------------------------------------------------------------------------------------------ search


def _search(args: argparse.Namespace, config: Config) -> int:
    mode = "--library" if args.library else "--keyframes" if args.keyframes else "--example"
    if args.example is None and args.keyframes is None and args.library is None:
        raise UsageError("give --library, --keyframes or --example")
    given = {
        "--class": args.class_name is not None,
        "--extend": args.extend is not None,
        "--features": args.features is not None,
        "--fuzzy": args.fuzzy != 0,
        "--plain": args.plain,
        "--mismatch": args.mismatch is not None,
        "--tau": args.tau is not None,
        "--steps": args.steps is not None,
        "--example": args.example is not None,
        "--native-fps": args.native_fps is not None,
        "--rig": args.rig is not None,
    }
    allowed = {
        "--library": {"--class", "--extend", "--tau", "--steps"},
        "--keyframes": {"--class", "--extend"},
        "--example": {"--features", "--fuzzy", "--plain", "--mismatch", "--example", "--native-fps", "--rig"},
    }[mode]
    wrong = [k for k, v in given.items() if v and k not in allowed]
    if wrong:
        raise UsageError(f"{', '.join(wrong)} cannot be used with {mode}")
    if args.keyframes == LIBRARY_KEYFRAMES and args.library is None:
        raise UsageError("--keyframes needs a keyframe file unless --library is given")
    if args.limit is not None and args.limit < 0:
        raise UsageError(f"--limit must not be negative, got {args.limit}")
    if args.plain and args.mismatch is not None:
        raise UsageError("--plain and --mismatch are different queries: give one")
    index = load_index(args.index)
    began = time.perf_counter()
    if args.library is not None:
        rows, summary = _search_library(args, index)
    elif args.keyframes is not None:
        rows, summary = _search_keyframes(args, index)
    else:
        rows, summary = _search_example(args, config, index)
    elapsed = 1e3 * (time.perf_counter() - began)
    shown = rows if args.limit is None else rows[: args.limit]
    if args.json:
        for row in shown:
            print(json.dumps(row))
        return 0
    print(f"{summary}: {len(rows)} hits in {elapsed:.1f} ms")
    for rank, row in enumerate(shown, start=1):
        cost = f" cost {row['cost']}" if "cost" in row else ""
        print(f"{rank:5d}. {row['document']} frames {row['start_frame']}-{row['end_frame']}{cost}")
    return 0


def _extension(args: argparse.Namespace) -> tuple[int, int] | None:
    """--extend as (left, right); None when not given."""
    if args.extend is None:
        return None
    try:
        extend = tuple(int(x) for x in args.extend.split(","))
    except ValueError:
        extend = ()
    if len(extend) != 2 or min(extend) < 0:
        raise UsageError(f"--extend must be LEFT,RIGHT (two whole numbers >= 0), got '{args.extend}'")
    return extend[0], extend[1]


def _keyframe_query(path: Path, name: str) -> KeyframeQuery:
    queries = parse_keyframe_queries(read_structured(path, "json", KeyframeError), path)
    if name not in queries:
        raise UsageError(f"no class '{name}' (has: {', '.join(sorted(queries))})", path=path)
    return queries[name]


def _search_library(args: argparse.Namespace, index: MotionIndex) -> tuple[list[Row], str]:
    if args.class_name is None:
        raise UsageError("--library needs --class NAME")
    library = load_library(args.library, [args.class_name])
    cls = library.get(args.class_name)
    if not math.isclose(library.rate, index.rate):
        raise UsageError(
            f"{index.rate:g} Hz, but library {args.library} was learned at {library.rate:g} Hz",
            path=Path(args.index) / INDEX_JSON,
            field="rate",
        )
    query = None
    if args.keyframes == LIBRARY_KEYFRAMES:
        if cls.keyframes is None:
            raise UsageError(f"class {cls.name} has no keyframes", path=args.library)
        query = cls.keyframes
    elif args.keyframes is not None:
        query = _keyframe_query(args.keyframes, cls.name)
    elif args.extend is not None:
        raise UsageError("--extend needs --keyframes")
    # the class's own τ (calibrated by leave-one-actor-out, or given when learned) unless overridden
    tau = cls.tau if args.tau is None else args.tau
    source = "--tau" if args.tau is not None else "calibrated" if cls.provenance.calibrated else "given"
    steps = cls.steps if args.steps is None else args.steps
    hits = template_search(
        index, cls.quantised, tau=tau, steps=steps, keyframes=query, extend=_extension(args)
    )
    rows = [
        {**_hit_row(index, d, s, e), "cost": round(c, 6)}
        for d, s, e, c in zip(
            hits.doc.tolist(), hits.start.tolist(), hits.end.tolist(), hits.cost.tolist(), strict=True
        )
    ]
    summary = (
        f"motion template of {cls.name} ({cls.quantised.length} columns, tau {tau:g} {source}, {steps} steps"
    )
    if hits.keyframes is not None:
        share = 100 * hits.searched / max(index.n_frames, 1)
        summary += f"; keyframes kept {len(hits.keyframes)} ranges, {share:.2f} % of the database"
    return rows, summary + "), ranked by cost"


def _search_keyframes(args: argparse.Namespace, index: MotionIndex) -> tuple[list[Row], str]:
    if args.class_name is None:
        raise UsageError("--keyframes needs --class NAME")
    extend = _extension(args) or (0, 0)
    query = _keyframe_query(args.keyframes, args.class_name)
    frames = [d.frames for d in index.documents]
    hits = keyframe_search(index.sets, frames, query, index.rate, extend)
    rows = [
        _hit_row(index, d, s, e)
        for d, s, e in zip(hits.doc.tolist(), hits.start.tolist(), hits.end.tolist(), strict=True)
    ]
    share = 100 * hits.frames / max(index.n_frames, 1)
    summary = (
        f"keyframes of {args.class_name} ({len(query.keyframes)} keyframes, lists of "
        f"{sum(hits.list_lengths)} segments), {share:.2f} % of the database kept"
    )
    return rows, summary


def _search_example(args: argparse.Namespace, config: Config, index: MotionIndex) -> tuple[list[Row], str]:
    if len(args.example) not in (3, 4):
        raise UsageError(
            f"--example takes ASF AMC START END or BVH START END, got {len(args.example)} values"
        )
    *files, start_text, end_text = args.example
    if args.features is None:
        raise UsageError("--example needs --features NAME,NAME,...")
    try:
        feature_set, mask = feature_selection([n.strip() for n in args.features.split(",") if n.strip()])
    except QueryError as exc:
        raise UsageError(exc.reason, field="--features") from None
    try:
        first, last = int(start_text), int(end_text)
    except ValueError:
        raise UsageError(
            f"--example START END must be AMC frame numbers, got '{start_text} {end_text}'"
        ) from None
    if args.fuzzy < 0:
        raise UsageError(f"--fuzzy must not be negative, got {args.fuzzy}")
    amc = Path(files[-1])
    try:
        if len(files) == 1:
            got = read_bvh_features(amc, index.rate, common.rig_maps(args, config))
        else:
            got = read_features(files[0], amc, index.rate, common.default_native_rate(args, config))
    except RateError as exc:
        raise UsageError(f"{exc.reason} (the index rate)", path=amc) from None
    if not got.first_amc_frame <= first <= last <= got.last_amc_frame:
        raise UsageError(
            f"--example frames {first}..{last} are outside the recording's AMC frames "
            f"{got.first_amc_frame}..{got.last_amc_frame}",
            path=amc,
        )
    inside = (got.frames >= first) & (got.frames <= last)
    if not inside.any():
        raise UsageError(f"frames {first}..{last} hold no frame at {index.rate:g} Hz", path=amc)
    query = example_query(got.matrix[inside], feature_set, mask)
    sets = query.fuzzy_sets(args.fuzzy)
    set_index = index.sets[feature_set]
    hits: Hits
    if args.mismatch is not None:
        try:
            hits, kind = mismatch_query(set_index, sets, args.mismatch), f"{args.mismatch}-mismatch"
        except QueryError as exc:
            raise UsageError(exc.reason, field="--mismatch") from None
    elif args.plain:
        hits, kind = fuzzy_query(set_index, sets), "fuzzy"
    else:
        hits, kind = adaptive_fuzzy_query(set_index, sets), "adaptive fuzzy"
    order, cost = ranked(hits, query.lengths)
    rows = [
        {**_hit_row(index, int(hits.doc[i]), int(hits.start[i]), int(hits.end[i])), "cost": int(c)}
        for i, c in zip(order.tolist(), cost.tolist(), strict=True)
    ]
    summary = (
        f"{kind} query of {len(query.codes)} segments ({feature_set}: {args.features}; "
        f"fuzzy {args.fuzzy}), ranked by segment length difference"
    )
    return rows, summary


def _hit_row(index: MotionIndex, doc: int, start: int, end: int) -> Row:
    first, last = index.amc_frames(doc, start, end)
    return {"document": index.document_path(doc), "start_frame": first, "end_frame": last}
