"""Slow, obviously-correct references the tests check the fast code against: plain loops over
plain Python values, read straight off the definitions they cite. Nothing here is fast and
nothing here is shared with the code under test."""

from __future__ import annotations

import dataclasses
import itertools
import math
from collections.abc import Iterator, Sequence
from fractions import Fraction
from itertools import pairwise, product
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
import numpy.typing as npt

from daemon import dtw
from daemon.dtw import INF, SCALE, Match, local_minima, retrieval_cost, subsequence_dtw, suppress
from daemon.features import features, window_frames
from daemon.keyframes import Keyframe, KeyframeQuery, query_bounds
from daemon.learn.templates import Generalisation
from daemon.library import ClassTemplate
from daemon.recognizer import completions
from daemon.search.index import SetIndex
from daemon.search.segments import Segment
from daemon.templates import expand
from daemon.types import BoolArray, FeatureSet, FloatArray
from replay import JOINT_NAMES, KinematicModel, read_amc, read_asf
from tests.synth import ROT, SkeletonSpec

Mat = list[list[float]]
Vec = list[float]


# -------------------------------------------------------- features: hysteresis, smoothed velocities


def slow_hysteresis(f1: list[bool], f2: list[bool]) -> list[bool]:
    out, on = [], False
    for a, b in zip(f1, f2, strict=True):
        on = b or (on and a)
        out.append(on)
    return out


def reflect(j: int, m: int) -> int:
    """Index ``j`` mirrored into ``0..m-1``, edge repeated: ..., 1, 0 | 0, 1, ..., m-1 | m-1, m-2, ..."""
    while j < 0 or j >= m:
        j = -j - 1 if j < 0 else 2 * m - j - 1
    return j


def slow_velocity(x: np.ndarray, window_ms: float, fs: float) -> np.ndarray:
    n, big_l = len(x), window_frames(window_ms, fs)
    v = [x[t + 1] - x[t] for t in range(n - 1)] + ([x[n - 1] - x[n - 2]] if n > 1 else [np.zeros(3)])
    if n < big_l:
        v = [v[reflect(j, n)] for j in range(big_l)]
    h = math.ceil(big_l / 2)
    rows = [sum(v[reflect(t + k - h + 1, len(v))] for k in range(big_l)) / big_l * fs for t in range(n)]
    return np.array(rows, dtype=np.float64)


# --------------------------------------------------------------- segments and the velocity features


def slow_runs(codes: Sequence[int]) -> list[Segment]:
    """Maximal runs of equal codes, by a plain loop."""
    runs: list[Segment] = []
    for i, code in enumerate(codes):
        if runs and runs[-1].code == code:
            runs[-1] = Segment(runs[-1].start, i, code)
        else:
            runs.append(Segment(i, i, code))
    return runs


# The slow reference of the 14 velocity features: each test as (signal (N,), op, T1, T2, reference),
# a feature is on in a track where all of its tests hold. Definitions: thesis Table 5.1 /
# daemon/features/catalog.py.
Check = tuple[FloatArray, str, float, float, str]


def slow_velocity_checks(p: FloatArray, frame_rate: float) -> dict[str, list[Check]]:
    j = {name: p[:, i] for i, name in enumerate(JOINT_NAMES)}

    def ratio(a: float, b: float) -> float:
        """``a / b``, nan for a degenerate normal (the feature is then off; not compared)."""
        return a / b if b else math.nan

    def vel(q: str, fixture: str | None, window_ms: float) -> FloatArray:
        x = j[q] - j[fixture] if fixture else j[q]
        out: FloatArray = slow_velocity(x, window_ms, frame_rate)
        return out

    def along(a: str, b: str, v: FloatArray) -> FloatArray:
        """Component of ``v`` along ``unit(j[b] - j[a])``, frame by frame."""
        n = j[b] - j[a]
        return np.array(
            [ratio(float(np.dot(n[t], v[t])), math.sqrt(float(np.dot(n[t], n[t])))) for t in range(len(v))]
        )

    def plane_normal_along(a: str, b: str, c: str, v: FloatArray) -> FloatArray:
        """Component of ``v`` along ``unit((a - c) x (b - c))``."""
        n = np.cross(j[a] - j[c], j[b] - j[c])
        return np.array(
            [ratio(float(np.dot(n[t], v[t])), math.sqrt(float(np.dot(n[t], n[t])))) for t in range(len(v))]
        )

    def speed(q: str, window_ms: float) -> FloatArray:
        return np.array([math.sqrt(float(np.dot(row, row))) for row in vel(q, None, window_ms)])

    hips = ("lhip", "rhip")
    feet_together = along(*hips, vel("lankle", "rhip", 100.0)) - along(*hips, vel("rankle", "rhip", 100.0))
    return {
        "feetMoveTogetherRelHips": [(feet_together, ">=", 1.3, 1.5, "h_R")],
        "feetMoveApartRelHips": [(-feet_together, ">=", 1.3, 1.5, "h_R")],
        "footRightHighVel": [
            (speed("rtoes", 100.0), ">=", 2.0, 2.5, "h_R"),
            (speed("rankle", 100.0), ">=", 2.0, 2.5, "h_R"),
        ],
        "footLeftHighVel": [
            (speed("ltoes", 100.0), ">=", 2.0, 2.5, "h_R"),
            (speed("lankle", 100.0), ">=", 2.0, 2.5, "h_R"),
        ],
        "handRightToFrontRelTorso": [
            (plane_normal_along("neck", "rhip", "lhip", vel("rwrist", "lhip", 250.0)), ">", 1.3, 1.8, "h_L")
        ],
        "handLeftToFrontRelTorso": [
            (plane_normal_along("neck", "rhip", "lhip", vel("lwrist", "lhip", 250.0)), ">", 1.3, 1.8, "h_L")
        ],
        "handRightToTopRelSpine": [
            (along("chest", "neck", vel("rwrist", "neck", 250.0)), ">", 1.3, 1.8, "h_L")
        ],
        "handLeftToTopRelSpine": [
            (along("chest", "neck", vel("lwrist", "neck", 250.0)), ">", 1.3, 1.8, "h_L")
        ],
        "handsMoveTogether": [
            (along("lwrist", "rwrist", vel("lwrist", "rwrist", 100.0)), ">=", 1.2, 1.4, "h_R")
        ],
        "handRightMoveApartRelRoot": [
            (along("rwrist", "root", vel("root", "rwrist", 0.0)), ">=", 1.2, 1.4, "h_R")
        ],
        "handLeftMoveApartRelRoot": [
            (along("lwrist", "root", vel("root", "lwrist", 0.0)), ">=", 1.2, 1.4, "h_R")
        ],
        "handRightHighVel": [(speed("rfingers", 100.0), ">=", 2.0, 2.5, "h_R")],
        "handLeftHighVel": [(speed("lfingers", 100.0), ">=", 2.0, 2.5, "h_R")],
        "rootHighVel": [(speed("root", 0.0), ">=", 2.0, 2.3, "h_R")],
    }


# ---------------------------------------------- forward kinematics, with plain floats and 3x3 lists


IDENTITY: Mat = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]


def elementary(axis: str, t: float) -> Mat:
    """Rotation by ``t`` radians about the x, y or z axis (column vectors, right-handed)."""
    c, s = math.cos(t), math.sin(t)
    if axis == "X":
        return [[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]]
    if axis == "Y":
        return [[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]]
    assert axis == "Z"
    return [[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]


def mul(a: Mat, b: Mat) -> Mat:
    return [[a[i][0] * b[0][j] + a[i][1] * b[1][j] + a[i][2] * b[2][j] for j in range(3)] for i in range(3)]


def transpose(a: Mat) -> Mat:
    return [[a[j][i] for j in range(3)] for i in range(3)]


def apply(a: Mat, v: Vec) -> Vec:
    return [a[i][0] * v[0] + a[i][1] * v[1] + a[i][2] * v[2] for i in range(3)]


def euler(angles: tuple[float, float, float], order: str) -> Mat:
    """Euler rotation: the i-th angle about the axis named by the i-th letter of ``order``, the first
    letter applied first (``"XYZ"`` gives ``Rz @ Ry @ Rx``)."""
    r = IDENTITY
    for angle, letter in zip(angles, order, strict=True):
        r = mul(elementary(letter, angle), r)
    return r


def dof_rotation(dofs: tuple[str, ...], values: list[float]) -> Mat:
    """Product of the dof rotations, the first listed dof applied first."""
    r = IDENTITY
    for dof, value in zip(dofs, values, strict=True):
        r = mul(elementary(dof[1].upper(), value), r)
    return r


def reference_pose(spec: SkeletonSpec, row: list[float]) -> tuple[list[Mat], list[Vec]]:
    """Global rotations and node positions (ASF units) of one frame, straight from the generated
    specification (not from the parsed skeleton)."""
    value = dict(zip(spec.channel_names, row, strict=True))
    to_rad = spec.to_rad
    root_rot = [c for c in spec.root_order if c in ROT]
    translation = [value.get(f"root.t{a}", 0.0) for a in "xyz"]
    orientation = euler(
        (
            spec.root_orientation[0] * to_rad,
            spec.root_orientation[1] * to_rad,
            spec.root_orientation[2] * to_rad,
        ),
        spec.root_axis,
    )
    n = len(spec.bones) + 1
    rotation: list[Mat | None] = [None] * n
    position: list[Vec | None] = [None] * n
    rotation[0] = mul(orientation, dof_rotation(tuple(root_rot), [value[f"root.{c}"] for c in root_rot]))
    position[0] = [translation[i] + spec.root_position[i] for i in range(3)]

    def solve(k: int) -> tuple[Mat, Vec]:
        g, p = rotation[k], position[k]
        if g is not None and p is not None:
            return g, p
        bone = spec.bones[k - 1]
        g_parent, p_parent = solve(bone.parent)
        c = euler((bone.axis[0] * to_rad, bone.axis[1] * to_rad, bone.axis[2] * to_rad), bone.axis_order)
        m = dof_rotation(bone.dofs, [value[f"{bone.name}.{d}"] for d in bone.dofs])
        g = mul(g_parent, mul(mul(c, m), transpose(c)))
        norm = math.sqrt(sum(x * x for x in bone.direction))
        unit = [x / norm for x in bone.direction] if norm > 0 else [0.0, 0.0, 0.0]
        step = apply(g, [u * bone.length for u in unit])
        p = [p_parent[i] + step[i] for i in range(3)]
        rotation[k], position[k] = g, p
        return g, p

    pose = [solve(k) for k in range(n)]
    return [g for g, _ in pose], [p for _, p in pose]


# ------------------------------------------------------------------ index queries (MRC05 section 5)


def doc_segments(index: SetIndex) -> list[list[int]]:
    """Per document, the global numbers of its segments."""
    out: list[list[int]] = [[] for _ in range(int(index.doc.max()) + 1 if index.n_segments else 0)]
    for s, d in enumerate(index.doc.tolist()):
        out[d].append(s)
    return out


def brute_fuzzy(index: SetIndex, query: list[set[int]], mismatches: int = 0) -> list[list[int]]:
    """Bounds [k, k+1, ..., k+K] of every hit: positions agree except at most ``mismatches``."""
    hits = []
    code = index.code.tolist()
    for segs in doc_segments(index):
        for p in range(len(segs) - len(query) + 1):
            agree = sum(code[segs[p + i]] in v for i, v in enumerate(query))
            if agree >= len(query) - mismatches:
                hits.append([segs[p] + i for i in range(len(query) + 1)])
    return sorted(hits)


def brute_adaptive(index: SetIndex, query: list[set[int]]) -> list[list[int]]:
    hits = []
    code = index.code.tolist()
    for segs in doc_segments(index):
        w = [code[s] for s in segs]
        for k1 in range(len(w)):
            if w[k1] not in query[0] or (k1 > 0 and w[k1 - 1] in query[0]):
                continue
            bounds, k = [k1], k1
            for v in query:
                if k >= len(w) or w[k] not in v:
                    break
                while k < len(w) and w[k] in v:
                    k += 1
                bounds.append(k)
            else:
                hits.append([segs[0] + b for b in bounds])
    return sorted(hits)


# ------------------------------------------------------------ keyframe search (thesis Def. 4.4-4.8)


Lists = list[tuple[list[int], list[int]]]


def hits_of_match(
    lists: Lists, match: tuple[int, ...], deltas: list[int], sigma: float
) -> list[tuple[int, ...]]:
    """Every hit (Def. 4.4) with frame k inside segment match[k] of list k, by enumeration."""
    s = Fraction(repr(sigma))
    ranges = [range(lists[k][0][i], lists[k][1][i] + 1) for k, i in enumerate(match)]
    return [
        h
        for h in product(*ranges)
        if all(allowed(b - a, d, s) for a, b, d in zip(h, h[1:], deltas, strict=False))
    ]


def allowed(gap: int, delta: int, sigma: Fraction, max_gap: int | None = None) -> bool:
    """Condition (4.6): σδ <= gap <= δ/σ, no upper bound for σ = 0 (or ``max_gap``, if given)."""
    if sigma == 0:
        return max_gap is None or gap <= max_gap
    return sigma * delta <= gap and gap * sigma <= delta


def keyframe_brute_force(
    docs: dict[FeatureSet, list[list[int]]],
    query: KeyframeQuery,
    extend: tuple[int, int],
    max_gap: int | None = None,
) -> list[tuple[int, int, int]]:
    """Ω^Z of all matches by Def. 4.4-4.8 read directly (gaps with σ = 0 at most ``max_gap``): per
    document, a keyframe's list is the maximal runs of frames whose code lies in V_k; every hit is
    enumerated frame by frame; a match is the runs its frames lie in; R(M) = (min i_1, max i_K) over
    the match's hits; components are the connected sets of ranges that share frames (pairwise, by a
    graph search)."""
    out = []
    for d in range(len(docs["lower"])):
        n = len(docs["lower"][d])
        document = {fs: docs[fs][d] for fs in docs}
        spans = sorted((first, last) for first, _, last in keyframe_matches(document, query, max_gap))
        components = connected(spans)
        if extend != (0, 0):
            components = connected(
                [(max(0, s - extend[0]), min(n - 1, t + extend[1])) for s, t in components]
            )
        out += [(d, s, t) for s, t in components]
    return out


def in_keyframe(code: int, keyframe: Keyframe) -> bool:
    """Whether the frame whose set code is ``code`` lies in the keyframe's set V (Def. 4.3, widened
    by its ``mismatches``): its 0/1 entries compared one by one with the code's bits, at most
    ``mismatches`` of them different."""
    wrong = sum(1 for i, v in enumerate(keyframe.values) if v != 0.5 and (code >> i) & 1 != v)
    return wrong <= keyframe.mismatches


def keyframe_matches(
    codes: dict[FeatureSet, list[int]], query: KeyframeQuery, max_gap: int | None = None
) -> list[tuple[int, int, int]]:
    """Every match of ``query`` in one document (Def. 4.4-4.6 read directly): a keyframe's list is
    the maximal runs of frames whose code lies in V_k (:func:`in_keyframe`); every hit is enumerated
    frame by frame; a match is the runs its frames lie in. Per match (min i_1, min i_K, max i_K) over
    its hits: R(M) is (min i_1, max i_K), and min i_K is the first frame at which the match is
    complete; sorted."""
    deltas = [b.position - a.position for a, b in zip(query.keyframes, query.keyframes[1:], strict=False)]
    sigmas = [Fraction(repr(kf.stiffness_to_next)) for kf in query.keyframes[:-1]]
    n = len(codes["lower"])
    member = []
    run_id = []
    for kf in query.keyframes:
        m = [in_keyframe(c, kf) for c in codes[kf.feature_set]]
        ids, current = [], -1
        for i in range(n):
            if m[i] and (i == 0 or not m[i - 1]):
                current += 1
            ids.append(current)
        member.append(m)
        run_id.append(ids)
    found: dict[tuple[int, ...], list[int]] = {}
    for hit in all_hits(member, deltas, sigmas, max_gap):
        key = tuple(run_id[j][i] for j, i in enumerate(hit))
        r = found.setdefault(key, [hit[0], hit[-1], hit[-1]])
        r[0], r[1], r[2] = min(r[0], hit[0]), min(r[1], hit[-1]), max(r[2], hit[-1])
    return sorted((a, b, c) for a, b, c in found.values())


def all_hits(
    member: list[list[bool]], deltas: list[int], sigmas: list[Fraction], max_gap: int | None = None
) -> Iterator[list[int]]:
    """Every frame tuple i_1 <= ... <= i_K with member[k][i_k] and the distance condition (4.6)."""

    def grow(hit: list[int]) -> Iterator[list[int]]:
        k = len(hit)
        if k == len(member):
            yield hit
            return
        for i in range(hit[-1] if hit else 0, len(member[k])):
            if not member[k][i]:
                continue
            if hit and not allowed(i - hit[-1], deltas[k - 1], sigmas[k - 1], max_gap):
                continue
            yield from grow([*hit, i])

    return grow([])


def connected(spans: list[tuple[int, int]]) -> list[tuple[int, int]]:
    seen: set[int] = set()
    out = []
    for i in range(len(spans)):
        if i in seen:
            continue
        todo, group = [i], []
        seen.add(i)
        while todo:
            j = todo.pop()
            group.append(spans[j])
            for k, other in enumerate(spans):
                if k not in seen and other[0] <= spans[j][1] and spans[j][0] <= other[1]:
                    seen.add(k)
                    todo.append(k)
        out.append((min(s for s, _ in group), max(t for _, t in group)))
    return sorted(out)


# ------------------------------------------- DTW cell by cell, in fixed point (thesis Alg. 3.1/3.2)


Grid = list[list[int]]


Column = tuple[list[int], list[int]]  # (D, start) of one database column, template rows 0..M-1


WarpPath = list[tuple[int, int]]


Order = tuple[int, int, int]


TIE_ORDER: Order = (0, 1, 2)  # diagonal, database, template step; toolbox: (1,1), (1,2), (2,1)


def grid(cost: FloatArray) -> Grid:
    """The fixed-point cost matrix as plain Python ints."""
    return [[int(v) for v in row] for row in dtw.fixed(cost)]


def as_cost(d: int) -> float:
    """A fixed-point accumulated cost as the module reports it."""
    return float("inf") if d >= INF else d / SCALE


def pick(options: list[tuple[int, int, int]], c: int) -> tuple[int, int]:
    """(D, start) of a cell of fixed cost ``c`` from its predecessors ``(D, start, weight)`` listed in tie
    order: the first smallest D wins, then its weight multiplies ``c``. No predecessor, or only
    unreachable ones: unreachable (INF, start -1)."""
    best: tuple[int, int, int] | None = None
    for option in options:
        if best is None or option[0] < best[0]:
            best = option
    if best is None or best[0] >= INF:
        return INF, -1
    d = min(best[0] + best[2] * c, INF)
    return d, (best[1] if d < INF else -1)


def ref_full(c: Grid) -> tuple[Grid, WarpPath]:
    """Alg. 3.1 (D(0,0) = C(0,0), first row and column accumulated) and Alg. 3.2's backtracking."""
    m, n = len(c), len(c[0])
    d = [[0] * n for _ in range(m)]
    for i in range(m):
        for j in range(n):
            if i == 0 and j == 0:
                d[i][j] = c[0][0]
            elif i == 0:
                d[i][j] = min(d[i][j - 1] + c[i][j], INF)
            elif j == 0:
                d[i][j] = min(d[i - 1][j] + c[i][j], INF)
            else:
                d[i][j] = min(c[i][j] + min(d[i - 1][j - 1], d[i][j - 1], d[i - 1][j]), INF)
    i, j = m - 1, n - 1
    path = [(i, j)]
    while (i, j) != (0, 0):
        if i == 0:
            j -= 1
        elif j == 0:
            i -= 1
        else:
            best = (i - 1, j - 1)  # diagonal, then database step (i, j-1), then template step (i-1, j)
            for a, b in ((i, j - 1), (i - 1, j)):
                if d[a][b] < d[best[0]][best[1]]:
                    best = (a, b)
            i, j = best
        path.append((i, j))
    return d, path[::-1]


def predecessors(steps: str, i: int, j: int, order: Order = TIE_ORDER) -> list[tuple[int, int, int]]:
    """Predecessor cells (row, column, weight) of cell (i, j) in tie order (``order`` permutes it, to
    show that the tests see a wrong one)."""
    if steps == "thesis":
        cells = [(i - 1, j - 1, 1), (i, j - 1, 1), (i - 1, j, 1)]
    else:
        cells = [(i - 1, j - 1, 1), (i - 1, j - 2, 1), (i - 2, j - 1, 2)]
    return [cells[k] for k in order]


def ref_subsequence(c: Grid, steps: str, order: Order = TIE_ORDER) -> tuple[Grid, Grid]:
    """Subsequence DTW: D(0, j) = C(0, j) starting at j (free start), rows i >= 1 by the recursion, the
    start carried from the chosen predecessor; predecessors outside the matrix are skipped."""
    m, n = len(c), len(c[0])
    d = [[INF] * n for _ in range(m)]
    s = [[-1] * n for _ in range(m)]
    for j in range(n):
        d[0][j], s[0][j] = c[0][j], (j if c[0][j] < INF else -1)
    for i in range(1, m):
        for j in range(n):
            inside = [(a, b, w) for a, b, w in predecessors(steps, i, j, order) if a >= 0 and b >= 0]
            options = [(d[a][b], s[a][b], w) for a, b, w in inside]
            d[i][j], s[i][j] = pick(options, c[i][j])
    return d, s


def ref_column(c: list[int], t: int, kept: list[Column], steps: str, order: Order = TIE_ORDER) -> Column:
    """Column ``t`` of the subsequence recursion from the kept columns (``kept[-1]`` is column t-1,
    ``kept[-2]`` column t-2); a missing column is skipped like a cell outside the matrix."""
    m = len(c)
    d, s = [INF] * m, [-1] * m
    d[0], s[0] = c[0], (t if c[0] < INF else -1)
    by_offset = {1: kept[-1] if kept else None, 2: kept[-2] if len(kept) > 1 else None}
    for i in range(1, m):
        options = []
        for a, b, w in predecessors(steps, i, t, order):
            if a < 0:
                continue
            if b == t:  # the template step inside this column
                options.append((d[a], s[a], w))
            elif (col := by_offset[t - b]) is not None:
                options.append((col[0][a], col[1][a], w))
        d[i], s[i] = pick(options, c[i])
    return d, s


def slow_minimum(d: list[int], thr: int, e: int, last: int) -> bool:
    """Δ(e) is a local minimum at or below ``thr`` with frames ``0 .. last`` seen."""
    before = d[e - 1] if e > 0 else INF
    return d[e] < INF and d[e] <= thr and d[e] < before and (e == last or d[e] <= d[e + 1])


def slow_blocks(
    full: list[tuple[list[list[int]], list[list[int]], bool, int]],
    cost: int,
    start: int,
    end: int,
    j: int,
    lo: int,
    hi: int,
) -> bool:
    """:meth:`StreamDTW.blocks` read from its docstring over the full matrices (D, starts) of the
    templates, their step kind and threshold."""
    for d, s, toolbox, thr in full[lo:hi]:
        m = len(d)
        for r in (0, 1):
            col = j - r
            if col < 0:
                continue
            for i in range(m):
                if d[i][col] >= cost or d[i][col] > thr or not 0 <= s[i][col] <= end:
                    continue
                e = max(j, col + (m - i) // 2 if toolbox else col)
                shared = end - max(start, s[i][col]) + 1
                if 2 * shared > min(end - start, e - s[i][col]) + 1:
                    return True
    return False


def ref_spring(cost: FloatArray, tau: float, steps: str, order: Order = TIE_ORDER) -> list[Match]:
    """SPRING's disjoint-match rule, frame by frame: after column t, report the candidate once every
    live cell (kept columns) costs at least as much or starts after it ends, and drop the live paths
    starting at or before its end; then column t's last cell becomes the candidate if it is at or below
    tau and better than the pending one. A candidate pending at the end is reported."""
    c = grid(cost)
    m, n = len(c), len(c[0])
    width = 1 if steps == "thesis" else 2
    tau_fixed = int(dtw.fixed(tau))
    kept: list[Column] = []
    cand: tuple[int, int, int] | None = None  # (D, start, end)
    out: list[Match] = []
    for t in range(n):
        column = ref_column([c[i][t] for i in range(m)], t, kept, steps, order)
        kept = [*kept, column][-width:]
        if cand is not None:
            dmin, ts, te = cand
            if all(dd >= dmin or ss > te for d, s in kept for dd, ss in zip(d, s, strict=True)):
                out.append(Match(ts, te, as_cost(dmin)))
                cand = None
                kept = [
                    (
                        [INF if ss <= te else dd for dd, ss in zip(d, s, strict=True)],
                        [-1 if ss <= te else ss for ss in s],
                    )
                    for d, s in kept
                ]
        last_d, last_s = kept[-1][0][-1], kept[-1][1][-1]
        if last_d <= tau_fixed and (cand is None or last_d < cand[0]):
            cand = (last_d, last_s, t)
    if cand is not None:
        out.append(Match(cand[1], cand[2], as_cost(cand[0])))
    return out


def ref_local_minima(delta: FloatArray, start: npt.NDArray[np.int64], tau: float) -> list[Match]:
    n = len(delta)
    out = []
    for b in range(n):
        if (
            delta[b] <= tau
            and (b == 0 or delta[b] < delta[b - 1])
            and (b == n - 1 or delta[b] <= delta[b + 1])
        ):
            out.append(Match(int(start[b]), b, float(delta[b])))
    return out


def ceil_div(a: int, b: int) -> int:
    return -(-a // b)


def ref_suppress(candidates: list[Match], limit: int | None) -> list[Match]:
    """Candidates by increasing (cost, end); drop one whose end is masked; one whose start lies in the
    start-exclusion zone of a kept hit is dropped and masks ends with that hit's length L; a kept hit
    masks starts [s - ⌈L/10⌉, s + ⌈L/2⌉]; both mask ends [e - ⌈L/2⌉, e + ⌈L/10⌉]."""
    kept: list[Match] = []
    zone_length: dict[int, int] = {}  # start column -> length of the first kept hit whose zone holds it
    masked_ends: set[int] = set()
    for m in sorted(candidates, key=lambda m: (m.cost, m.end)):
        if limit is not None and len(kept) == limit:
            break
        if m.end in masked_ends:
            continue
        if m.start in zone_length:
            length = zone_length[m.start]
        else:
            length = m.end - m.start + 1
            kept.append(m)
            for x in range(m.start - ceil_div(length, 10), m.start + ceil_div(length, 2) + 1):
                zone_length.setdefault(x, length)
        masked_ends.update(range(m.end - ceil_div(length, 2), m.end + ceil_div(length, 10) + 1))
    return kept


def brute_and(t: FloatArray, s: FloatArray) -> list[list[float]]:
    f = t.shape[0]
    return [
        [
            sum(0.0 if 0.5 in (t[k, a], s[k, b]) else abs(t[k, a] - s[k, b]) for k in range(f))
            for b in range(s.shape[1])
        ]
        for a in range(t.shape[1])
    ]


# --------------------------------------------------------------- template retrieval, range by range


def template_brute_force(
    cls: ClassTemplate, matrices: list[npt.NDArray[np.bool_]], tau: float, ranges: list[tuple[int, int, int]]
) -> list[tuple[float, int, int, int]]:
    """Each range searched on its own from the float cost matrix, hits suppressed per range."""
    t = expand(cls.quantised)
    out = []
    for d, s, e in ranges:
        frames = matrices[d][s : e + 1].T.astype(np.float64)
        sub = subsequence_dtw(retrieval_cost(t.values, t.weights, frames))
        for m in suppress(local_minima(sub.delta, sub.start, tau)):
            out.append((m.cost, d, s + m.start, s + m.end))
    return sorted(out)


# ---------------------------------------------------------------------------- recording to features


def slow_sample_poses(positions: FloatArray, step: int, per: int = 1) -> FloatArray:
    """The pose at each instant ``j·step/per`` frames (exact fractions) while it is not past the
    last frame, one by one: the frame there, or the blend ``a + w·(b - a)`` of the frames around it,
    ``w`` the instant's fraction of a frame. Shape ``(M, J, 3)``."""
    out = []
    j = 0
    while Fraction(j * step, per) <= len(positions) - 1:
        t = Fraction(j * step, per)
        below, w = int(t), t - int(t)
        if w == 0:
            out.append(positions[below])
        else:
            a, b = positions[below], positions[below + 1]
            out.append(a + (w.numerator / w.denominator) * (b - a))
        j += 1
    return np.array(out).reshape(-1, *positions.shape[1:])


def naive_features(
    asf: Path, amc: Path, step: int = 1, native_rate: float = 120.0, per: int = 1
) -> BoolArray:
    """A recording's features written out from the parts (reader, forward kinematics in centimetres,
    the poses at the instants ``j·step/per`` frames from the first (:func:`slow_sample_poses`), the
    batch features at ``native_rate · per / step``), independently of :mod:`daemon.recordings`:
    shape ``(N, 39)``."""
    skeleton = read_asf(asf)
    model = KinematicModel(skeleton)
    joints = model.joints(model.positions(read_amc(amc, skeleton).channels, "cm"))
    out: BoolArray = features(slow_sample_poses(joints, step, per), JOINT_NAMES, native_rate * per / step)
    return out


# ------------------------------------------------------- behaviour segmentation (Barbič et al. 2004)


def slow_dimension(singular_values: Sequence[float], tau: float) -> int:
    """Eq. 6 read literally: the smallest ``r`` with ``sum_(j<=r) σ_j² / sum σ_j² > tau``, the
    singular values given in decreasing order; 0 when they are all zero."""
    squares = [float(s) ** 2 for s in singular_values]
    total = sum(squares)
    if total == 0:
        return 0
    kept = 0.0
    for r, square in enumerate(squares, 1):
        kept += square
        if kept / total > tau:
            return r
    return len(squares)


def slow_projection_error(frames: FloatArray, r: int) -> float:
    """Eq. 5: the squared singular values of the centred ``frames`` ``(i, D)`` beyond the ``r``
    largest (the SVD of Eq. 4)."""
    singular = np.linalg.svd(frames - frames.mean(axis=0), compute_uv=False)
    return sum(float(s) ** 2 for s in singular[r:])


def slow_pca_segment(
    x: FloatArray, k: int, ell: int, i0: int, tau: float, k_sigma: float
) -> tuple[list[tuple[int, float]], list[tuple[int, float, float]]]:
    """§3.1 read literally, an SVD of the segment's frames 1..i for every i: ``r`` from the first
    ``k`` frames, ``d_i = e_i - e_(i-ℓ)`` for ``i >= k``, a cut at frame ``i > i0`` when ``d_i`` lies
    more than ``k_sigma`` (population) standard deviations above the mean of the earlier ``d_j``
    (deviation > 0), the next segment starting at the cut frame. Returns the cuts ``(frame,
    (d - mean) / std)`` and every ``(frame, e_i, d_i)`` (frames 0-based)."""
    cuts: list[tuple[int, float]] = []
    trace: list[tuple[int, float, float]] = []
    start = 0
    while x.shape[0] - start >= k:
        segment = x[start:]
        first = segment[:k]
        r = slow_dimension(np.linalg.svd(first - first.mean(axis=0), compute_uv=False).tolist(), tau)
        earlier: list[float] = []
        cut = None
        for i in range(k, segment.shape[0] + 1):
            e = slow_projection_error(segment[:i], r)
            d = e - slow_projection_error(segment[: i - ell], r)
            trace.append((start + i - 1, e, d))
            if i > i0 and earlier:
                mean = sum(earlier) / len(earlier)
                std = math.sqrt(sum((v - mean) ** 2 for v in earlier) / len(earlier))
                if std > 0 and d > mean + k_sigma * std:
                    cut = (start + i - 1, (d - mean) / std)
                    break
            earlier.append(d)
        if cut is None:
            break
        cuts.append(cut)
        start = cut[0]
    return cuts, trace


def slow_ppca_h(model: FloatArray, window: FloatArray, tau: float) -> float:
    """Eqs. 7-10 read literally: the PPCA Gaussian of the frames ``model`` ``(K, D)`` (K > D) from
    the SVD of the centred frames (σ² the mean of the discarded squared singular values, ``W = V_r
    (Σ_r² - σ² I)^(1/2)``, ``C = (W W^T + σ² I) / (K - 1)``) and the mean Mahalanobis distance ``H``
    of the frames ``window`` ``(T, D)`` under it (a linear solve and a square root per frame)."""
    mean = model.mean(axis=0)
    _, singular, vt = np.linalg.svd(model - mean)
    dims = model.shape[1]
    r = slow_dimension(singular.tolist(), tau)
    sigma2 = sum(float(s) ** 2 for s in singular[r:]) / (dims - r) if r < dims else 0.0
    w = vt[:r].T @ np.diag(np.sqrt(np.maximum(singular[:r] ** 2 - sigma2, 0.0)))
    c = (w @ w.T + sigma2 * np.eye(dims)) / (model.shape[0] - 1)
    return sum(math.sqrt(float(v @ np.linalg.solve(c, v))) for v in window - mean) / int(window.shape[0])


def slow_peak(hs: list[tuple[int, float]], rise: float, shortest: int) -> tuple[int, float] | None:
    """§3.2's test on the ``(K, H)`` so far, ``hs``, the last one just computed: ``(K, rise)`` of the
    one before it if that is a peak (higher than its neighbours) at ``K >= shortest``, lying ``rise``
    or more above the lowest valley before it (lower than the ``H`` before it, not higher than the one
    after), else None."""
    h = [v for _, v in hs]
    j = len(h) - 2
    if j < 1 or not h[j - 1] < h[j] > h[j + 1] or hs[j][0] < shortest:
        return None
    valleys = [h[i] for i in range(1, j) if h[i - 1] > h[i] <= h[i + 1]]
    if not valleys or h[j] - min(valleys) < rise:
        return None
    return hs[j][0], h[j] - min(valleys)


def slow_ppca_forward(
    x: FloatArray, window: int, delta: int, rise: float, tau: float, shortest: int = 0
) -> tuple[list[tuple[int, float, int]], list[tuple[int, float]]]:
    """§3.2's forward pass read literally: ``K = T``; ``H`` (:func:`slow_ppca_h`) of frames ``K + 1
    .. K + T`` under the model of frames ``1 .. K``; ``K += Δ``; a cut at the first peak of ``H`` (higher
    than the ``H`` on either side) at ``K >= shortest`` that lies ``rise`` or more above the lowest
    valley before it (a valley: lower than the ``H`` before it, not higher than the one after); cut
    frame: the first frame after the model's ``K``; the search restarts at the cut. Returns the
    cuts ``(frame, rise, frame seen last)`` and every ``(K's frame, H)``."""
    cuts: list[tuple[int, float, int]] = []
    trace: list[tuple[int, float]] = []
    start, n = 0, x.shape[0]
    while start + window <= n:
        big_k, cut = window, None
        hs: list[tuple[int, float]] = []
        while start + big_k + window <= n:
            h = slow_ppca_h(x[start : start + big_k], x[start + big_k : start + big_k + window], tau)
            trace.append((start + big_k, h))
            hs.append((big_k, h))
            peak = slow_peak(hs, rise, shortest)
            if peak is not None:
                cut = (start + peak[0], peak[1], start + big_k + window - 1)
                break
            big_k += delta
        if cut is None:
            break
        cuts.append(cut)
        start = cut[0]
    return cuts, trace


def slow_ppca_segment(
    x: FloatArray, window: int, delta: int, rise: float, tau: float, shortest: int = 0
) -> list[int]:
    """§3.2's passes: the forward pass, then passes alternating direction inside each segment the
    cuts so far leave (backward: the segment reversed, a cut ``p`` frames from its end at ``end -
    p``), until a pass adds no cut."""
    cuts = {c[0] for c in slow_ppca_forward(x, window, delta, rise, tau, shortest)[0]}
    forward = False
    while True:
        edges = [0, *sorted(cuts), x.shape[0]]
        found = set()
        for a, b in pairwise(edges):
            part = x[a:b] if forward else x[a:b][::-1]
            for c, _, _ in slow_ppca_forward(part, window, delta, rise, tau, shortest)[0]:
                found.add(a + c if forward else b - c)
        if not found:
            return sorted(cuts)
        cuts |= found
        forward = not forward


# ----------------------------------------------------------- calibration: the detections of a fold

FoldCandidate = tuple[float, int, int, int]
"""A candidate of a fold as plain values: (cost, end, template, start)."""


def frames_shared(a: tuple[int, int], b: tuple[int, int]) -> int:
    """How many frames two inclusive ranges have in common, counted as sets."""
    return len(set(range(a[0], a[1] + 1)) & set(range(b[0], b[1] + 1)))


def slow_same_motion(a: tuple[int, int], b: tuple[int, int]) -> bool:
    """More than half of the shorter range's frames shared."""
    shorter = min(a[1] - a[0] + 1, b[1] - b[0] + 1)
    return 2 * frames_shared(a, b) > shorter


def slow_survivors(
    candidates: Sequence[FoldCandidate], owner: Sequence[int], taus: Sequence[float | None]
) -> list[bool]:
    """For each candidate of ``sorted(candidates)``: not beaten, i.e. no candidate before it in that
    order is the same motion and of its class (``owner`` of their templates) or within its own
    template's τ (a τ of None: none)."""
    ordered = sorted(candidates)
    out = []
    for i, (_, end, template, start) in enumerate(ordered):
        beaten = False
        for cost2, end2, template2, start2 in ordered[:i]:
            tau = taus[template2]
            rival = owner[template2] == owner[template] or (tau is not None and cost2 <= tau)
            if rival and slow_same_motion((start, end), (start2, end2)):
                beaten = True
        out.append(not beaten)
    return out


def slow_motion_of(
    candidate: FoldCandidate, owner: Sequence[int], truth: Sequence[tuple[int, int, int]]
) -> int | None:
    """The first motion of ``truth`` (class, first, last) of the candidate's class that holds at
    least half of the candidate's frames."""
    _, end, template, start = candidate
    for i, (k, first, last) in enumerate(truth):
        if k == owner[template] and 2 * frames_shared((start, end), (first, last)) >= end - start + 1:
            return i
    return None


def slow_outcomes(
    candidates: Sequence[FoldCandidate],
    owner: Sequence[int],
    truth: Sequence[tuple[int, int, int]],
    learned: set[int] | frozenset[int],
    taus: Sequence[float | None],
) -> tuple[list[list[float]], list[list[float]]]:
    """Per template, its positives and negatives: the surviving candidates are the detections; each
    motion of a learned class (in ``truth`` order) gives one positive, the cost of its cheapest right
    detection (ties: the first in the order) to that detection's template, or ``inf`` to the class's
    first template; each wrong detection is a negative of its template."""
    ordered = sorted(candidates)
    detections = [x for x, ok in zip(ordered, slow_survivors(candidates, owner, taus), strict=True) if ok]
    positives: list[list[float]] = [[] for _ in owner]
    negatives: list[list[float]] = [[] for _ in owner]
    for x in detections:
        if slow_motion_of(x, owner, truth) is None:
            negatives[x[2]].append(x[0])
    for i, (k, _, _) in enumerate(truth):
        if k not in learned:
            continue
        right = [x for x in detections if slow_motion_of(x, owner, truth) == i]
        if right:
            best = min(right)
            positives[best[2]].append(best[0])
        else:
            positives[owner.index(k)].append(math.inf)
    return positives, negatives


def slow_scored(
    candidates: Sequence[FoldCandidate],
    owner: Sequence[int],
    truth: Sequence[tuple[int, int, int]],
    learned: set[int] | frozenset[int],
    taus: Sequence[float | None],
    k: int | None = None,
) -> tuple[int, int, int]:
    """True positives, false positives, false negatives (of class ``k`` alone, if given): the
    detections within their template's τ are kept (those of class ``k``); a motion of a learned
    class (``k``) is found when one of them is right for it, each of them right for no motion is a
    false positive."""
    ordered = sorted(candidates)
    survive = slow_survivors(candidates, owner, taus)
    found: set[int] = set()
    fp = 0
    for x, ok in zip(ordered, survive, strict=True):
        tau = taus[x[2]]
        if not ok or tau is None or x[0] > tau or (k is not None and owner[x[2]] != k):
            continue
        i = slow_motion_of(x, owner, truth)
        if i is None:
            fp += 1
        else:
            found.add(i)
    motions = [i for i, (c, _, _) in enumerate(truth) if c in learned and (k is None or c == k)]
    tp = sum(i in found for i in motions)
    return tp, fp, len(motions) - tp


class GateFold(NamedTuple):
    """A fold as plain values for :func:`slow_gate`: its candidates, the class of each template, its
    motions, its stream's codes and, for the class gated, each keyframe trial as (generalisation,
    query, left-out examples of the class kept)."""

    candidates: list[FoldCandidate]
    owner: Sequence[int]
    truth: Sequence[tuple[int, int, int]]
    codes: list[int]
    trials: list[tuple[Generalisation, KeyframeQuery, list[bool], int, tuple[int, int] | None]]


def slow_windows(
    found: Sequence[tuple[int, int]], before: int, after: int, back: int
) -> list[tuple[int, int, int, int]]:
    """A keyframe-first class's windows read frame by frame: at each frame j that completes matches
    ``found`` ((R(M) start, j)), the frames from the earliest max(start - before, j - back, 0) to
    j + after are wanted; if the class's window still covered frame j - 1 its end moves there,
    else a new one opens whose candidates end after the last one; (first, last, frame opened,
    first frame a candidate may end at)."""
    out: list[tuple[int, int, int, int]] = []
    for j in range(max((at for _, at in found), default=-1) + 1):
        wanted = [max(first - before, j - back, 0) for first, at in found if at == j]
        if not wanted:
            continue
        if out and out[-1][1] >= j - 1:
            out[-1] = (out[-1][0], max(out[-1][1], j + after), out[-1][2], out[-1][3])
        else:
            start = min(wanted)
            out.append((start, j + after, j, max(start, out[-1][1] + 1) if out else start))
    return out


def slow_extent(
    query: KeyframeQuery, length: int, slack: int, extent: tuple[int, int] | None = None
) -> tuple[int, int]:
    """Frames a window opens before a match and after its completion: ``extent`` (the training
    examples' needs), else two frames per template column before the first keyframe and after the
    last; plus ``slack``."""
    if extent is not None:
        return extent[0] + slack, extent[1] + slack
    first, last = query.keyframes[0].position, query.keyframes[-1].position
    return 2 * first + slack, 2 * max(0, length - 1 - last) + slack


def slow_gate(
    folds: Sequence[GateFold],
    k: int,
    taus: Sequence[float | None],
    min_kept: float,
    rate: float,
    max_gap: int,
    spare: int = 0,
    slacks: Sequence[int] = (0,),
) -> tuple[Generalisation, float, int] | None:
    """Class ``k``'s keyframe windows by their definition, the share of other classes' motion
    frames they cover and their slack, or None. A generalisation holds at a slack when in every
    fold its keyframes keep at least ``min_kept`` of the left-out examples of the class and the
    class's detections (surviving, within their template's τ) that lie inside one of its windows
    (:func:`slow_windows` of the matches the automaton completes) still find at least ``min_kept``
    of the motions found without it; of a design (all but the mismatches) only the first that
    holds counts, at the first of ``slacks`` at which it holds, and it runs with ``spare``
    mismatches more (at most 3, if tried and it holds so). Of those: the fewest wrong detections
    left, then the smallest share of the frames of other classes' motions inside a window, then the
    first tried."""
    detections = []
    for f in folds:
        alive = slow_survivors(f.candidates, f.owner, taus)
        mine = []
        for x, ok in zip(sorted(f.candidates), alive, strict=True):
            tau = taus[x[2]]
            if ok and f.owner[x[2]] == k and tau is not None and x[0] <= tau:
                mine.append((x, slow_motion_of(x, f.owner, f.truth)))
        detections.append(mine)
    tried: list[Generalisation] = []
    for f in folds:
        for g, _, _, _, _ in f.trials:
            if g not in tried:
                tried.append(g)

    def run(g: Generalisation, slack: int) -> tuple[bool, int, float]:
        qualifies, wrong_g, covered, frames = True, 0, 0, 0
        for f, mine in zip(folds, detections, strict=True):
            for generalisation, query, kept_examples, length, extent in f.trials:
                if generalisation != g:
                    continue
                if kept_examples and sum(kept_examples) < min_kept * len(kept_examples):
                    qualifies = False
                before, after = slow_extent(query, length, slack, extent)
                back = sum(hi or 0 for _, hi in query_bounds(query, rate, max_gap)) + before
                spans = slow_windows(completions(query, rate, max_gap, f.codes), before, after, back)
                kept = [(x, i) for x, i in mine if any(a <= x[3] and x[1] <= b for a, b, _, _ in spans)]
                motions = {i for _, i in mine if i is not None}
                if len({i for _, i in kept if i is not None}) < min_kept * len(motions) - 1e-9:
                    qualifies = False
                wrong_g += sum(i is None for _, i in kept)
                for c, first, last in f.truth:
                    if c != k:
                        frames += last - first + 1
                        covered += sum(
                            any(a <= i <= b for a, b, _, _ in spans) for i in range(first, last + 1)
                        )
        return qualifies, wrong_g, covered / frames if frames else 0.0

    best: tuple[int, float, int] | None = None
    chosen = None
    held: list[Generalisation] = []
    for order, g in enumerate(tried):
        design = dataclasses.replace(g, mismatches=0)
        if design in held:
            continue
        at = next((s for s in slacks if run(g, s)[0]), None)
        if at is None:
            continue
        _, wrong_g, share = run(g, at)
        held.append(design)
        wider = dataclasses.replace(g, mismatches=min(g.mismatches + spare, 3))
        if spare and wider in tried and (widened := run(wider, at))[0]:
            g = wider
            _, wrong_g, share = widened
        if best is None or (wrong_g, share, order) < best:
            best, chosen = (wrong_g, share, order), (g, share, at)
    return chosen


def slow_fair_queue(ops: list[tuple[str, str] | None], size: int) -> tuple[list[str], int]:
    """:class:`protocols.fair.FairQueue` read literally, on a list: ``ops`` puts (key, label) or
    takes (None); per key a list, and when its length last changed; the turn order a list of keys.
    Returns the labels taken and how many puts dropped a message."""
    queues: dict[str, list[str]] = {}
    changed: dict[str, int] = {}
    clock = itertools.count()
    turns: list[str] = []
    taken: list[str] = []
    dropped = 0
    for op in ops:
        if op is None:
            if turns:
                key = turns.pop(0)
                taken.append(queues[key].pop(0))
                changed[key] = next(clock)
                if queues[key]:
                    turns.append(key)
                else:
                    del queues[key]
            continue
        if sum(len(q) for q in queues.values()) >= size:
            most = max(len(q) for q in queues.values())
            # of the keys holding the most, the one that came to hold that many first
            largest = min((k for k in queues if len(queues[k]) == most), key=lambda k: changed[k])
            queues[largest].pop(0)
            changed[largest] = next(clock)
            dropped += 1
            if not queues[largest]:
                del queues[largest]
                turns.remove(largest)
        key, label = op
        if key not in queues:
            queues[key] = []
            turns.append(key)
        queues[key].append(label)
        changed[key] = next(clock)
    return taken, dropped


def slow_bounded_rendezvous(members: Sequence[str], partitions: int) -> dict[str, set[int]]:
    """Rendezvous hashing with bounded loads by its definition: while a partition has no owner, the
    pair of an unowned partition and a member with fewer than ``ceil(P / N)`` partitions that has
    the highest score (ties: the smaller name, then the smaller partition) is matched
    (``daemon.cluster.ring``'s :func:`score` is the hash itself)."""
    from daemon.cluster.ring import score

    live = sorted(set(members))
    out: dict[str, set[int]] = {m: set() for m in live}
    if not live:
        return out
    room = math.ceil(partitions / len(live))
    free = set(range(partitions))
    while free:
        _, m, p = min((-score(m, p), m, p) for m in live if len(out[m]) < room for p in free)
        out[m].add(p)
        free.discard(p)
    return out


def slow_progress_events(
    pushes: Sequence[tuple[int, tuple[Any, ...]]], rate: float, per_s: float
) -> list[tuple[int, tuple[Any, ...]]]:
    """The progress events of ``pushes`` ((sequence number, snapshot of class states)) read from
    the rule: a snapshot goes out when, with cost to 0.001 and position to 0.01, it differs from the
    last one out (none yet: as an empty one), and either some class's keyframes matched differ (a
    class absent as one with none) or it is at least ceil(rate / per_s) numbers after the last one
    out (or none went out yet); at the end, an empty snapshot at the last number if the last one
    out was not empty."""
    gap = max(1, math.ceil(rate / per_s))

    def shown(snapshot: tuple[Any, ...]) -> list[dict[str, Any]]:
        return [
            {
                "class": c.class_name,
                "keyframes": c.keyframes,
                "matched": list(c.matched),
                "position": round(c.position, 2),
                "cost": round(c.cost, 3),
                "tau": c.tau,
            }
            for c in snapshot
        ]

    def keys(snapshot: tuple[Any, ...]) -> dict[str, tuple[int, ...]]:
        return {c.class_name: tuple(c.matched) for c in snapshot if c.matched}

    out: list[tuple[int, tuple[Any, ...]]] = []
    last: tuple[Any, ...] = ()
    last_number: int | None = None
    for number, snapshot in pushes:
        if shown(snapshot) == shown(last):
            continue
        if keys(snapshot) != keys(last) or last_number is None or number - last_number >= gap:
            out.append((number, snapshot))
            last, last_number = snapshot, number
    if last and pushes:
        out.append((pushes[-1][0], ()))
    return out


def slow_bvh_positions(
    joints: Sequence[tuple[int, tuple[float, float, float], Sequence[str]]], row: Sequence[float]
) -> list[tuple[float, float, float]]:
    """Every node's position for one frame of a BVH hierarchy, read off the format's definition
    with 3x3 rotation matrices as lists: ``joints`` as (parent index or -1, offset, channel names)
    in file order, ``row`` the frame's channel values (degrees). A joint's rotation is the product of
    its rotation channels in the order listed; its translation is its offset with each position
    channel replacing that component; ``G = G_parent R``, ``P = P_parent + G_parent t``."""

    def elementary(axis: str, degrees: float) -> list[list[float]]:
        c, s = math.cos(math.radians(degrees)), math.sin(math.radians(degrees))
        if axis == "X":
            return [[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]]
        if axis == "Y":
            return [[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]]
        return [[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]

    def matmul(a: list[list[float]], b: list[list[float]]) -> list[list[float]]:
        return [[sum(a[i][k] * b[k][j] for k in range(3)) for j in range(3)] for i in range(3)]

    def apply(m: list[list[float]], v: list[float]) -> list[float]:
        return [sum(m[i][k] * v[k] for k in range(3)) for i in range(3)]

    identity = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]
    rotations: list[list[list[float]]] = []
    positions: list[tuple[float, float, float]] = []
    column = 0
    for parent, offset, channels in joints:
        local, t = identity, list(offset)
        for channel in channels:
            value = row[column]
            column += 1
            axis = channel[0]
            if channel.endswith("rotation"):
                local = matmul(local, elementary(axis, value))
            else:
                t["XYZ".index(axis)] = value
        if parent < 0:
            rotations.append(local)
            positions.append((t[0], t[1], t[2]))
        else:
            moved = apply(rotations[parent], t)
            p = positions[parent]
            rotations.append(matmul(rotations[parent], local))
            positions.append((p[0] + moved[0], p[1] + moved[1], p[2] + moved[2]))
    return positions
