"""The live recogniser: pushed frame by frame it equals its batch twin ``detect`` on every real
recording; the candidate/confirmation stage equals a slow reading of its definition on random code
streams; one motion gives one detection per class while a repetition right after gives another;
bad frames raise :class:`FrameError` and change nothing."""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from fractions import Fraction
from functools import cache
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from daemon.dtw import INF, SCALE, pack, retrieval_matrix, retrieval_tables, threshold
from daemon.features import SET_SLICES
from daemon.keyframes import KeyframeQuery, query_bounds
from daemon.library import ClassTemplate, Library, Variant, default_library_path, load_library
from daemon.recognizer import (
    CodeRecognizer,
    Detection,
    FrameError,
    Recognizer,
    completions,
    detect,
    detect_positions,
    learned_extent,
    plans,
    windows,
)
from daemon.recordings import native_rate, read_recording
from daemon.templates import expand
from daemon.types import FEATURE_SETS, N_FEATURES, FeatureSet, RecognitionSettings
from replay import JOINT_NAMES, Motion
from replay.kinematics import joint_positions
from tests.helpers import hdm05_clip, pair_id, recording_pairs, small_library, takes
from tests.naive import (
    keyframe_matches,
    ref_subsequence,
    slow_blocks,
    slow_extent,
    slow_windows,
)
from tests.synth import queries, random_class, stream_codes, streams

SESSION = "test"


@pytest.fixture(scope="module")
def library(tmp_path_factory: pytest.TempPathFactory) -> Library:
    return small_library(tmp_path_factory.mktemp("lib"))


@cache
def motion(asf: Path, amc: Path) -> Motion:
    return read_recording(asf, amc)


def pushed(recognizer: Recognizer, m: Motion) -> list[Detection]:
    out = [
        d
        for number, channels in zip(m.frames.tolist(), m.channels, strict=True)
        for d in recognizer.push(number, channels)
    ]
    return out + recognizer.flush()


@pytest.fixture(scope="module")
def shipped() -> Library:
    return load_library(default_library_path())


@pytest.mark.slow
@pytest.mark.parametrize("pair", recording_pairs(), ids=pair_id)
def test_push_equals_detect(pair: tuple[Path, Path], shipped: Library) -> None:
    """With the shipped library's 18 classes (learned and published keyframes)."""
    library = shipped
    m = read_recording(*pair)
    rate = native_rate(m)
    recognizer = Recognizer.for_skeleton(library, m.skeleton, rate, stream="s", session=SESSION)
    got = pushed(recognizer, m)
    assert got == detect(m, library, rate, stream="s", session=SESSION)
    for d in got:
        assert d.start_frame <= d.end_frame <= d.emitted_at_frame
        assert d.cost <= d.tau
    assert len({d.id for d in got}) == len(got)
    assert pushed(recognizer, m) == got  # flush started a fresh stream


@pytest.mark.parametrize("mode", ["dtw", "keyframes"])
def test_the_mode_setting_overrides_the_library(shipped: Library, mode: str) -> None:
    """recognizer.mode ``dtw`` finds every class as a library whose classes are all in mode
    ``dtw`` does, ``keyframes`` every class with keyframes as one whose classes are all keyframes
    first; ``library`` as the library says."""
    m = read_recording(*recording_pairs()[0])
    rate = native_rate(m)
    relabelled = Library(
        shipped.rate,
        {
            n: dataclasses.replace(c, mode=mode if mode == "dtw" or c.keyframes is not None else "dtw")
            for n, c in shipped.classes.items()
        },
    )
    forced = detect(m, shipped, rate, session=SESSION, settings=RecognitionSettings(mode=mode))  # type: ignore[arg-type]
    assert forced == detect(m, relabelled, rate, session=SESSION)
    assert detect(m, shipped, rate, session=SESSION) == detect(
        m, shipped, rate, session=SESSION, settings=RecognitionSettings(mode="library")
    )


def test_positions_in_any_joint_order(library: Library) -> None:
    """Joint positions announced in another order, with a joint the features do not use, give the
    detections of the channels they came from; the batch twin on positions agrees."""
    asf, amc = hdm05_clip("dg", "squat1Reps", takes("squat1Reps", "dg")[0])
    m = motion(asf, amc)
    rate = native_rate(m)
    positions = joint_positions(m)  # (N, 26, 3) cm
    order = np.random.default_rng(3).permutation(len(JOINT_NAMES))
    names = [JOINT_NAMES[i] for i in order] + ["prop"]
    frames = np.concatenate([positions[:, order], np.zeros((len(m), 1, 3))], axis=1)
    recognizer = Recognizer.for_positions(library, names, rate, session=SESSION)
    got = [
        d for n, f in zip(m.frames.tolist(), frames, strict=True) for d in recognizer.push(n, f)
    ] + recognizer.flush()
    assert got
    assert got == detect(m, library, rate, session=SESSION)
    assert got == detect_positions(positions, m.frames, library, rate, session=SESSION)


def test_one_motion_one_detection_and_a_repetition_right_after(library: Library) -> None:
    """A dg squat gives one squat detection: of the first of the two classes with the same template
    when classes compete (the same cost, end and motion: the earlier template wins), of each on its
    own; the same squat twice in a row gives two, the second after the first."""
    asf, amc = hdm05_clip("dg", "squat1Reps", takes("squat1Reps", "dg")[0])
    m = motion(asf, amc)
    rate = native_rate(m)
    once = [d for d in detect(m, library, rate, session=SESSION) if d.class_name.startswith("squat")]
    assert [d.class_name for d in once] == ["squat1Reps"]
    alone = [
        d
        for d in detect(m, library, rate, session=SESSION, settings=RecognitionSettings(compete=False))
        if d.class_name.startswith("squat")
    ]
    assert sorted(d.class_name for d in alone) == ["squat1Reps", "squat1Reps.published"]
    n = len(m)
    twice = Motion(
        m.source, m.skeleton, m.header, np.arange(1, 2 * n + 1), np.concatenate([m.channels, m.channels])
    )
    found = [d for d in detect(twice, library, rate, session=SESSION) if d.class_name == "squat1Reps"]
    assert len(found) == 2
    for d, (first, last) in zip(found, [(1, n), (n + 1, 2 * n)], strict=True):  # mostly in its copy
        assert 2 * (min(last, d.end_frame) - max(first, d.start_frame) + 1) > d.end_frame - d.start_frame + 1


# ------------------------------------------------------------------ candidates and confirmation


def slow_recognizer(
    codes: list[int],
    classes: Sequence[ClassTemplate],
    max_gap: int,
    compete: bool,
    hold: int,
    progress: list[dict[int, tuple[int, int, int]]] | None = None,
) -> list[tuple[str, int, int, int, int]]:
    """:class:`CodeRecognizer`'s definition read slowly. A class in mode ``dtw``: each template's
    subsequence DTW cell by cell over the whole stream (fixed point, :func:`tests.naive.ref_subsequence`).
    A keyframe-first class: every keyframe match by brute force (Def. 4.4-4.6, gaps capped) gives,
    at the frame that completes it, the window :func:`tests.naive.slow_windows` opens (the extent of
    :func:`tests.naive.slow_extent`), and each template's subsequence DTW runs over each window's
    frames alone (Δ infinite outside), known from the frame the window opened. Each template's
    local minima within its τ are found one frame after their end, or when their window opens (the
    last frame's at the end); at each frame, the candidates found arrive in the order (cost, end,
    template, start): one is dropped when a candidate that arrived before it comes before it in that
    order and is the same motion (of its class, or of any class when competing) or when it is the
    same motion as a published detection; else it is held, and drops the held ones it comes before.
    A held candidate is final after ``hold`` frames or when :func:`tests.naive.slow_blocks` (over
    the columns known at that frame) says no template (of its class unless competing) can still end
    a cheaper match of its motion; the final ones are published by (end, start, class). Each as
    (class, start, end, cost, frame it comes out at).

    ``progress``, if given, gets per frame (after its arrivals and publications) and per class
    the (template, row, D) furthest along as a share of its template's length (ties: the lower
    D·M/(row + 1), then the first) among the rows of the column known at that frame with
    D·M <= τ·(row + 1) whose path starts after the class's spent frame: the latest start of its
    candidates published, beaten by another class's, the same motion as a detection published,
    or dropped from the held for another class's."""
    n = len(codes)
    sets = {
        fs: [
            (c >> SET_SLICES[fs].start) & ((1 << (SET_SLICES[fs].stop - SET_SLICES[fs].start)) - 1)
            for c in codes
        ]
        for fs in FEATURE_SETS
    }
    frames = np.array([[(c >> i) & 1 for i in range(N_FEATURES)] for c in codes], dtype=bool)
    owner: list[int] = []
    full = []  # per template: D and starts over the stream (INF outside its windows), toolbox, τ
    opened: list[list[int]] = []  # per template and frame: the frame its column became known
    found: dict[int, list[tuple[int, int, int, int]]] = {}  # frame -> (cost, end, template, start)
    for k, cls in enumerate(classes):
        spans = [(0, n - 1, 0, 0)]
        if cls.mode == "keyframes" and cls.keyframes is not None:
            before, after = slow_extent(cls.keyframes, cls.hard.length, cls.slack, cls.extent)
            back = sum(hi or 0 for _, hi in query_bounds(cls.keyframes, 30.0, max_gap)) + before
            matches = keyframe_matches(sets, cls.keyframes, max_gap)
            spans = [
                (a, min(b, n - 1), at, lowest)
                for a, b, at, lowest in slow_windows([(f, at) for f, at, _ in matches], before, after, back)
            ]
        for template, tau in cls.members:
            u = len(owner)
            owner.append(k)
            t = expand(template)
            tables = retrieval_tables(t.values, t.weights)
            thr = threshold(tau)
            d_all = [[INF] * n for _ in range(t.weights.shape[0])]
            s_all = [[-1] * n for _ in range(t.weights.shape[0])]
            known = [n + 1] * n
            for a, b, at, lowest in spans:
                cost = retrieval_matrix(tables, pack(frames[a : b + 1]))
                d, st = ref_subsequence([[int(v) for v in row] for row in cost], "toolbox")
                for i in range(len(d)):  # the frames before ``lowest``: the last window's columns
                    for c in range(lowest - a, b - a + 1):
                        d_all[i][a + c] = d[i][c]
                        s_all[i][a + c] = st[i][c] + a if st[i][c] >= 0 else -1
                last = d[-1]
                for c in range(lowest - a, b - a + 1):
                    known[a + c] = at
                    e = a + c
                    prev = last[c - 1] if c > 0 else INF
                    nxt = None if e == n - 1 else INF if e == b else last[c + 1]
                    if (
                        last[c] < INF
                        and last[c] <= thr
                        and last[c] < prev
                        and (nxt is None or last[c] <= nxt)
                    ):
                        found.setdefault(n if e == n - 1 else max(e + 1, at), []).append(
                            (last[c], e, u, st[-1][c] + a)
                        )
            full.append((d_all, s_all, True, thr))
            opened.append(known)

    def columns_at(j: int) -> list[tuple[list[list[int]], list[list[int]], bool, int]]:
        """The templates' matrices with the columns j - 1 and j as known at frame j."""
        out = []
        for (d, st, toolbox, thr), known in zip(full, opened, strict=True):
            hidden = [c for c in (j - 1, j) if 0 <= c < n and known[c] > j]
            if hidden:
                d = [row[:] for row in d]
                for row in d:
                    for c in hidden:
                        row[c] = INF
            out.append((d, st, toolbox, thr))
        return out

    def same(x: tuple[int, int, int, int], y: tuple[int, int, int, int]) -> bool:
        shared = set(range(x[3], x[1] + 1)) & set(range(y[3], y[1] + 1))
        return (compete or owner[x[2]] == owner[y[2]]) and 2 * len(shared) > min(x[1] - x[3], y[1] - y[3]) + 1

    arrived: list[tuple[int, int, int, int]] = []
    held: list[tuple[int, int, int, int]] = []
    published: list[tuple[int, int, int, int]] = []
    spent = [-1] * len(classes)

    def spend(x: tuple[int, int, int, int]) -> None:
        spent[owner[x[2]]] = max(spent[owner[x[2]]], x[3])

    out = []
    for j in range(n + 1):  # frame n: the flush
        for y in sorted(found.get(j, [])):
            rivals = [x for x in arrived if x < y and same(x, y)]
            told = any(same(y, p) for p in published)
            if told or any(owner[x[2]] != owner[y[2]] for x in rivals):
                spend(y)
            arrived.append(y)
            if not (rivals or told):
                for x in held:
                    if y < x and same(x, y) and owner[x[2]] != owner[y[2]]:
                        spend(x)
                held = [x for x in held if not (y < x and same(x, y))] + [y]
        frame = min(j, n - 1)
        final = []
        view = columns_at(j) if held and j < n else full
        for x in list(held):
            k = owner[x[2]]
            lo, hi = (0, len(full)) if compete else (owner.index(k), len(owner) - owner[::-1].index(k))
            if j == n or j > x[1] + hold or not slow_blocks(view, x[0], x[3], x[1], j, lo, hi):
                final.append(x)
                held.remove(x)
        for x in sorted(final, key=lambda x: (x[1], x[3], owner[x[2]])):
            k = owner[x[2]]
            published.append(x)
            spend(x)
            out.append((classes[k].name, x[3], x[1], x[0], frame))
        if progress is not None and j < n:
            progress.append(slow_progress_at(columns_at(j), owner, spent, j))
    return out


def slow_progress_at(
    columns: list[tuple[list[list[int]], list[list[int]], bool, int]],
    owner: list[int],
    spent: list[int],
    j: int,
) -> dict[int, tuple[int, int, int]]:
    """Per class, the (template, row, D) :func:`slow_recognizer` gives as its progress at frame ``j``."""
    best: dict[int, tuple[Fraction, Fraction, int, int, int]] = {}
    for u, ((d, start, _, thr), k) in enumerate(zip(columns, owner, strict=True)):
        m = len(d)
        rows = [
            i for i in range(m) if d[i][j] < INF and d[i][j] * m <= thr * (i + 1) and start[i][j] > spent[k]
        ]
        if rows:
            i = rows[-1]
            key = (-Fraction(i + 1, m), Fraction(d[i][j] * m, i + 1), u, i, d[i][j])
            best[k] = min(best.get(k, key), key)
    return {k: (u, i, d) for k, (_, _, u, i, d) in best.items()}


def confirmations(
    classes: list[ClassTemplate], stream: list[int], settings: RecognitionSettings, frames: tuple[int, int]
) -> list[tuple[str, int, int, int, int]]:
    """A :class:`CodeRecognizer` of ``classes`` over ``stream`` (its hold and gap cap ``frames``):
    each confirmation as (class, start, end, fixed-point cost, frame it came out at)."""
    recognizer = CodeRecognizer(plans(Library(30.0, {c.name: c for c in classes}), settings), 30.0, settings)
    assert (recognizer.hold, recognizer.plans[0].max_gap) == frames
    got = [
        (p.name, m.start, m.end, round(m.cost * SCALE), j)
        for j, c in enumerate(stream)
        for p, m, _ in recognizer.push(c)
    ]
    return got + [
        (p.name, m.start, m.end, round(m.cost * SCALE), len(stream) - 1) for p, m, _ in recognizer.flush()
    ]


@settings(max_examples=120, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    streams(),
    queries(),
    queries(tolerant=True),
    st.integers(0, 2**32 - 1),
    st.sampled_from([0.05, 0.2, 0.5]),
    st.integers(1, 8),
    st.booleans(),
    st.integers(0, 6),
    st.sampled_from(["keyframes", "dtw"]),
    st.booleans(),
    st.integers(0, 4),
)
def test_confirmations_equal_the_definition(
    codes: dict[FeatureSet, list[int]],
    q1: KeyframeQuery,
    q2: KeyframeQuery,
    seed: int,
    tau: float,
    max_gap: int,
    compete: bool,
    hold: int,
    mode: str,
    two: bool,
    slack: int,
) -> None:
    """Random code streams, two classes (one keyframes-first or not and its keyframes tolerant, one
    of them with two templates, windows ``slack`` frames wider): the recogniser equals
    :func:`slow_recognizer`; nothing comes out before its last frame."""
    rng = np.random.default_rng(seed)
    a = dataclasses.replace(random_class("a", q1, rng, tau), slack=slack)
    b = dataclasses.replace(random_class("b", q2, rng, tau), mode=mode, slack=slack)
    if two:
        other = random_class("a2", q1, rng, tau * 0.8)
        a = dataclasses.replace(a, variants=(Variant(other.quantised, other.tau, other.provenance, (0,)),))
    classes = [a, b]
    stream = stream_codes(codes)
    settings = RecognitionSettings(max_gap_s=max_gap / 30.0, compete=compete, hold_s=hold / 30.0)
    got = confirmations(classes, stream, settings, (hold, max_gap))
    assert got == slow_recognizer(stream, classes, max_gap, compete, hold)
    for _, _, end, _, emitted in got:
        assert end <= emitted  # never before its last frame was seen


@settings(max_examples=80, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    streams(shortest=20, longest=120),
    queries(),
    queries(tolerant=True),
    st.integers(0, 2**32 - 1),
    st.sampled_from([0.2, 0.5]),
    st.booleans(),
    st.integers(0, 6),
    st.sampled_from(["keyframes", "dtw"]),
    st.booleans(),
)
def test_progress_equals_the_definition(
    codes: dict[FeatureSet, list[int]],
    q1: KeyframeQuery,
    q2: KeyframeQuery,
    seed: int,
    tau: float,
    compete: bool,
    hold: int,
    mode: str,
    two: bool,
) -> None:
    """At every frame, each class's progress in the compiled competition (its template, row and D
    along paths that start after the class's spent frame) is :func:`slow_recognizer`'s: reported for
    every class in mode ``dtw`` that has one (floor 0), and for a gated class whenever it is."""
    rng = np.random.default_rng(seed)
    a = random_class("a", q1, rng, tau)
    b = dataclasses.replace(random_class("b", q2, rng, tau), mode=mode)
    if two:
        other = random_class("a2", q1, rng, tau * 0.8)
        a = dataclasses.replace(a, variants=(Variant(other.quantised, other.tau, other.provenance, (0,)),))
    classes = [a, b]
    stream = stream_codes(codes)
    settings = RecognitionSettings(max_gap_s=4 / 30.0, compete=compete, hold_s=hold / 30.0)
    recognizer = CodeRecognizer(plans(Library(30.0, {c.name: c for c in classes}), settings), 30.0, settings)
    core = recognizer.core
    assert core is not None
    want: list[dict[int, tuple[int, int, int]]] = []
    slow_recognizer(stream, classes, 4, compete, hold, want)
    for code, expected in zip(stream, want, strict=True):
        recognizer.push(code)
        got = {k: (u, i, d) for k, u, i, d, _ in core.progress(1e-12)}
        for k, found in got.items():
            assert found == expected.get(k, (-1, -1, INF))
        for k in expected:
            assert recognizer.keyframes[k] or k in got


@settings(max_examples=80, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    streams(shortest=40, longest=160),
    queries(tolerant=True),
    st.integers(0, 2**32 - 1),
    st.sampled_from([0.2, 0.35, 0.5]),
    st.integers(0, 4),
    st.integers(0, 8),
    st.integers(0, 6),
    st.booleans(),
    st.one_of(st.none(), st.tuples(st.integers(0, 12), st.integers(0, 12))),
)
def test_windows_equal_the_definition(
    codes: dict[FeatureSet, list[int]],
    query: KeyframeQuery,
    seed: int,
    tau: float,
    extra: int,
    slack: int,
    hold: int,
    compete: bool,
    extent: tuple[int, int] | None,
) -> None:
    """Longer streams and a keyframes-first class whose template spans its keyframes (so that its
    windows open, are extended, close and open again over frames the last one searched), its
    windows' extent learned or from its geometry, beside a class in mode ``dtw``: the recogniser
    equals :func:`slow_recognizer`."""
    rng = np.random.default_rng(seed)
    columns = query.keyframes[-1].position + 1 + extra
    a = dataclasses.replace(random_class("a", query, rng, tau, columns), slack=slack, extent=extent)
    b = dataclasses.replace(random_class("b", query, rng, tau), mode="dtw")
    classes = [a, b]
    stream = stream_codes(codes)
    settings = RecognitionSettings(max_gap_s=4 / 30.0, compete=compete, hold_s=hold / 30.0)
    got = confirmations(classes, stream, settings, (hold, 4))
    assert got == slow_recognizer(stream, classes, 4, compete, hold)


@settings(max_examples=60, deadline=None)
@given(st.lists(streams(shortest=1, longest=30), min_size=1, max_size=4), queries(tolerant=True))
def test_learned_extent_is_the_examples_spread(
    examples: list[dict[FeatureSet, list[int]]], query: KeyframeQuery
) -> None:
    """Per example (its own stream), the keyframe match completed first (brute force; ties: the
    earliest R(M) start) needs its R(M) start frames before it and the frames after the frame that
    completes it to the example's end; the extent is the most of each over the examples with a
    match, and a window of that extent around that match holds the whole example."""
    need = []
    for codes in examples:
        matches = keyframe_matches(codes, query, 4)
        if matches:
            first, at, _ = min(matches, key=lambda m: (m[1], m[0]))
            need.append((first, len(codes["lower"]) - 1 - at))
    got = learned_extent(query, [stream_codes(c) for c in examples], 30.0, 4)
    assert got == (None if not need else (max(b for b, _ in need), max(a for _, a in need)))
    for codes in examples:
        made = windows(completions(query, 30.0, 4, stream_codes(codes)), *(got or (0, 0)), 10**6)
        assert not made or (made[0][0] == 0 and made[0][1] >= len(codes["lower"]) - 1)


# ------------------------------------------------------------------------------- bad frames


BAD = ("short", "long", "nan", "inf", "repeat", "back", "jump", "float", "text")


@settings(max_examples=25, deadline=None)
@given(st.lists(st.tuples(st.integers(0, 178), st.sampled_from(BAD)), max_size=8))
def test_bad_frames_change_nothing(library: Library, bad: list[tuple[int, str]]) -> None:
    asf, amc = hdm05_clip("dg", "squat1Reps", takes("squat1Reps", "dg")[0])
    m = motion(asf, amc)
    rate = native_rate(m)
    clean = pushed(Recognizer.for_skeleton(library, m.skeleton, rate, session=SESSION), m)
    recognizer = Recognizer.for_skeleton(library, m.skeleton, rate, session=SESSION)
    before = {i: [kind for j, kind in bad if j == i] for i in range(len(m))}
    got: list[Detection] = []
    for i, (number, channels) in enumerate(zip(m.frames.tolist(), m.channels, strict=True)):
        for kind in before[i]:
            problem, wrong_number, wrong = damaged(kind, i, number, channels)
            if problem is None:
                continue
            with pytest.raises(FrameError, match=r"\bframe\b") as caught:
                recognizer.push(wrong_number, wrong)  # type: ignore[arg-type]
            assert caught.value.problem == problem
        got += recognizer.push(number, channels)
    assert got + recognizer.flush() == clean


def damaged(kind: str, i: int, number: int, channels: np.ndarray) -> tuple[str | None, object, object]:
    """The frame ``kind`` makes of frame ``i`` (number, channels) and the problem it must raise;
    None where the kind makes no bad frame there (no previous frame to repeat or jump from)."""
    bad = channels.copy()
    if kind == "short":
        return "shape", number, channels[:-1]
    if kind == "long":
        return "shape", number, np.append(channels, 0.0)
    if kind in ("nan", "inf"):
        bad[i % len(bad)] = np.nan if kind == "nan" else -np.inf
        return "non_finite", number, bad
    if kind == "float":
        return "type", float(number), channels
    if kind == "text":
        return "type", str(number), channels
    if i == 0:  # the first frame may have any number
        return None, number, channels
    if kind == "jump":
        return "jump", number + 1 + i % 3, channels
    return ("repeat", number - 1, channels) if kind == "repeat" else ("back", number - 2 - i % 3, channels)
