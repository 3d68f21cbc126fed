"""Progress events (issue 24): the compiled accessors against their definitions (the DTW's rows
within τ against the full cell-by-cell recursion, the automaton's partial matches and whole hits
against the brute force of Def. 4.4), the rate-limited stage against a naive reading of its rule,
its bounded state, the live path (a recogniser pushed frame by frame) against the batch twin on real
recordings, and what the events say on real recordings: a gated class's detection always comes
after an event that showed its whole keyframe hit, and every detection's class was shown far along
its template before it."""

from __future__ import annotations

import itertools
import math
from functools import cache
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from daemon import dtw
from daemon._dtw import StreamDTW
from daemon.automaton import KeyframeAutomaton
from daemon.dtw import INF, SCALE
from daemon.errors import InputError
from daemon.keyframes import query_bounds
from daemon.library import Library, default_library_path, load_library
from daemon.progress import (
    FLOOR,
    ClassState,
    ProgressEvent,
    ProgressStage,
    StreamProgress,
    detect_progress,
    min_gap,
)
from daemon.recognizer import Detection, Recognizer, detect, plans
from daemon.recordings import read_recording
from daemon.types import FeatureSet, FloatArray
from tests.helpers import DATA, hdm05_clip, small_library, takes
from tests.naive import in_keyframe, ref_subsequence, slow_progress_events
from tests.synth import queries, stream_codes, streams

SETTINGS = settings(max_examples=200, deadline=None, suppress_health_check=[HealthCheck.too_slow])
CMU_13 = DATA / "cmu" / "13" / "13.asf"
CMU_TRIALS = [
    (CMU_13, DATA / "cmu" / s / f"{s}_{t}.amc.gz") for s, t in (("13", "29"), ("13", "30"), ("14", "14"))
]
HIGH = 0.9
"""Before every detection its class was shown at least this far along its template."""


def ternary(f: int, n: int) -> st.SearchStrategy[FloatArray]:
    return st.lists(st.sampled_from([0.0, 0.5, 1.0]), min_size=f * n, max_size=f * n).map(
        lambda v: np.array(v, dtype=np.float64).reshape(f, n)
    )


# ------------------------------------------------------------------------------ the DTW's position


@SETTINGS
@given(st.integers(1, 3), st.integers(1, 30), st.data())
def test_stream_dtw_progress_reads_its_definition(k: int, n: int, data: st.DataObject) -> None:
    """At every frame, each template's furthest row i whose D(i) (the full recursion's, unpruned)
    satisfies D(i)·M <= τ·(i + 1), and that D; none: (-1, INF). With the toolbox's steps the
    columns keep only cells within τ, so this also shows those cells are the exact ones. Asked
    for paths that start after a frame, the furthest such row whose path (the recursion's start)
    starts after it."""
    f = 4
    templates = []
    for _ in range(k):
        m = data.draw(st.integers(1, 9))
        w = np.array(data.draw(st.lists(st.floats(0.5, 1.5), min_size=m, max_size=m)))
        templates.append(
            (
                dtw.retrieval_tables(data.draw(ternary(f, m)), w),
                data.draw(st.sampled_from(dtw.STEPS)),
                data.draw(st.sampled_from([0, SCALE // 20, SCALE // 4, SCALE, 3 * SCALE])),
            )
        )
    codes = np.array(data.draw(st.lists(st.integers(0, 2**f - 1), min_size=n, max_size=n)), dtype=np.uint64)
    stream = StreamDTW([(tb.masks, tb.values, tb.tables, thr, s == "toolbox") for tb, s, thr in templates])
    assert stream.progress(0) == (-1, INF)  # nothing pushed
    full = [
        ref_subsequence([[int(v) for v in row] for row in dtw.retrieval_matrix(tb, codes)], s)
        for tb, s, _ in templates
    ]
    for j, code in enumerate(codes.tolist()):
        stream.push(code)
        since = data.draw(st.integers(-1, j))
        for t, ((_, _, thr), (d, start)) in enumerate(zip(templates, full, strict=True)):
            m = len(d)
            rows = [i for i in range(m) if d[i][j] < INF and d[i][j] * m <= thr * (i + 1)]
            assert stream.progress(t) == ((rows[-1], d[rows[-1]][j]) if rows else (-1, INF))
            later = [i for i in rows if start[i][j] > since]
            assert stream.progress(t, since) == ((later[-1], d[later[-1]][j]) if later else (-1, INF))
    with pytest.raises(IndexError):
        stream.progress(k)


# ---------------------------------------------------------------------------- the keyframes found


def partial_hits(member: list[list[bool]], bounds: list[tuple[int, int]], t: int) -> list[tuple[int, ...]]:
    """Every tuple i_1 <= ... <= i_k <= t (k < K) of frames in keyframes 1..k's sets whose gaps are
    within the bounds (Def. 4.4 read directly, for a prefix of the keyframes)."""
    out: list[tuple[int, ...]] = []

    def grow(hit: tuple[int, ...]) -> None:
        if hit:
            out.append(hit)
        k = len(hit)
        if k == len(member) - 1:
            return
        lo = hit[-1] + bounds[k - 1][0] if hit else 0
        hi = hit[-1] + bounds[k - 1][1] if hit else t
        for i in range(lo, min(hi, t) + 1):
            if member[k][i]:
                grow((*hit, i))

    grow(())
    return out


@pytest.mark.parametrize("tolerant", [False, True], ids=["exact", "tolerant"])
@SETTINGS
@given(streams(), st.data(), st.integers(0, 8))
def test_automaton_partial_and_hit_read_the_hits(
    tolerant: bool, codes: dict[FeatureSet, list[int]], data: st.DataObject, max_gap: int
) -> None:
    """At every frame t, the keyframes of the most advanced partial match are frames of their sets,
    ascending, at most t, with gaps at least their lower bounds, and some partial hit of as many
    keyframes (frames <= t) lies in the same runs; and no partial hit of more keyframes (but fewer
    than all) could still be extended after t. A whole hit is reported at the frame it completes,
    its frames in keyframes 1..K's sets, its last the match's first frame of keyframe K. Also with
    keyframes that may miss some of their fixed entries (``tolerant``)."""
    query = data.draw(queries(tolerant=tolerant), label="query")
    automaton = KeyframeAutomaton(query, query.rate, max_gap, 1, components=False)
    core = automaton.core
    bounds = [(lo, hi) for lo, hi in query_bounds(query, query.rate, max_gap) if hi is not None]
    frames = stream_codes(codes)
    member = [[in_keyframe(c, kf) for c in codes[kf.feature_set]] for kf in query.keyframes]
    runs = []
    for m in member:  # a run id per frame of each keyframe's set
        ids, current = [], -1
        for i, x in enumerate(m):
            current += x and (i == 0 or not m[i - 1])
            ids.append(current if x else -1)
        runs.append(ids)
    K = len(query.keyframes)
    for t, code in enumerate(frames):
        automaton.push(code)
        got = core.partial()
        hits = partial_hits(member, bounds, t)
        alive = [h for h in hits if h[-1] + bounds[len(h) - 1][1] > t]
        assert len(got) >= max((len(h) for h in alive), default=0)
        if got:
            assert len(got) < K and list(got) == sorted(got) and got[-1] <= t
            assert all(member[j][f] for j, f in enumerate(got))
            assert all(b - a >= bounds[j][0] for j, (a, b) in enumerate(itertools.pairwise(got)))
            same_runs = [
                h
                for h in hits
                if len(h) == len(got) and all(runs[j][h[j]] == runs[j][got[j]] for j in range(len(h)))
            ]
            assert same_runs
        hit = core.hit()
        completed = [(first, at) for first, at in automaton.reached if at == t]
        if completed:
            assert hit is not None and hit[0] == t and (hit[1], hit[2]) in completed
            assert len(hit[3]) == K and hit[3][-1] == t == hit[2]
            assert all(member[j][f] for j, f in enumerate(hit[3]))
        else:
            assert hit is None or hit[0] < t
    automaton.flush()
    assert core.partial() == () and core.hit() is None


# ------------------------------------------------------------------------------------- the stage


def class_states(draw: st.DrawFn) -> tuple[ClassState, ...]:
    out = []
    for name in ("a", "b", "c"):
        if draw(st.booleans()):
            n = draw(st.sampled_from([0, 3]))
            k = draw(st.integers(0, n))
            out.append(
                ClassState(
                    name,
                    n,
                    tuple(range(10, 10 + 4 * k, 4)),
                    draw(st.sampled_from([0.5, 0.501, 0.52, 0.75, 1.0])),
                    draw(st.sampled_from([0.01, 0.0104, 0.012, 0.05])),
                    0.1,
                )
            )
    return tuple(out)


pushes = st.composite(
    lambda draw: [
        (number, class_states(draw))
        for number in np.cumsum(draw(st.lists(st.integers(1, 5), max_size=60))).tolist()
    ]
)


@SETTINGS
@given(pushes(), st.sampled_from([30.0, 120.0, 100.0]), st.sampled_from([0.5, 7.0, 10.0, 1000.0]))
def test_the_stage_equals_its_naive_reference(
    pushed: list[tuple[int, tuple[ClassState, ...]]], rate: float, per_s: float
) -> None:
    """Changes only, rate-limited, keyframe changes at once, one empty snapshot at the end: as the
    naive reference reads the rule; and what it says: consecutive events differ, a throttled one
    (same keyframes) comes at least the gap after the one before."""
    stage = ProgressStage(rate, per_s)
    got = [e for number, snapshot in pushed for e in stage.push(number, snapshot)] + stage.flush()
    assert [(e.frame, e.classes) for e in got] == slow_progress_events(pushed, rate, per_s)
    gap = math.ceil(rate / per_s)
    for a, b in itertools.pairwise(got):
        assert a.classes != b.classes
        if {c.class_name: c.matched for c in a.classes if c.matched} == {
            c.class_name: c.matched for c in b.classes if c.matched
        } and b is not got[-1]:
            assert b.frame - a.frame >= gap
    assert stage.flush() == []  # the flush started it anew


def test_the_stage_state_is_bounded_and_its_gap_is_the_rate_s() -> None:
    assert (min_gap(120.0, 10.0), min_gap(120.0, 7.0), min_gap(30.0, 1000.0)) == (12, 18, 1)
    with pytest.raises(InputError, match="per_s"):
        min_gap(120.0, 0.0)
    stage = ProgressStage(120.0, 10.0)
    state = ClassState("a", 0, (), 0.5, 0.01, 0.1)
    out = []
    for number in range(100_000):  # a stream as long as a day at 1 Hz: the state stays one snapshot
        out += stage.push(number, (state,) if number % 2 else ())
    assert len(vars(stage)) == 5 and len(stage._key) <= 1
    # it changes every frame; 12 frames on it is back to the snapshot last let out, so the next
    # change that goes out is at 13 frames' distance
    assert {b.frame - a.frame for a, b in itertools.pairwise(out)} == {13}


# ------------------------------------------------------------------------- live, batch, disabled


@cache
def shipped() -> Library:
    return load_library(default_library_path())


def live(asf: Path, amc: Path, library: Library) -> list[Detection | ProgressEvent]:
    """A recogniser pushed frame by frame, its progress followed (as ``mocapd detect --progress``)."""
    motion = read_recording(asf, amc)
    r = Recognizer.for_skeleton(library, motion.skeleton, 120.0, stream="s", session="")
    follow = StreamProgress(r.stage, 120.0)
    out: list[Detection | ProgressEvent] = []
    for number, channels in zip(motion.frames.tolist(), motion.channels, strict=True):
        detections = r.push(number, channels)
        out += follow.observe(number)
        out += detections
    detections = r.flush()
    return out + follow.end() + detections


REAL = [
    CMU_TRIALS[1],
    hdm05_clip("bd", "kickLFront1Reps", 1),
    hdm05_clip("dg", "squat1Reps", takes("squat1Reps", "dg")[0]),
]


@pytest.mark.parametrize("pair", REAL, ids=lambda p: p[1].name.split(".")[0])
def test_live_equals_the_batch_twin_and_progress_changes_no_detection(pair: tuple[Path, Path]) -> None:
    """Frame by frame through the live recogniser and its progress, as the batch twin gives them,
    event for event and in the same order; the detections among them are detect()'s (reading the
    progress changes nothing)."""
    motion = read_recording(*pair)
    batch = detect_progress(motion, shipped(), 120.0, stream="s")
    assert live(*pair, shipped()) == batch
    assert [d for d in batch if isinstance(d, Detection)] == detect(motion, shipped(), 120.0, stream="s")
    events = [e for e in batch if isinstance(e, ProgressEvent)]
    assert events and events[-1].classes == ()
    for e in events:
        assert [c.class_name for c in e.classes] == sorted(c.class_name for c in e.classes)
        for c in e.classes:
            assert 0 <= c.position <= 1 and c.cost >= 0 and c.tau > 0
            assert c.matched or c.position >= FLOOR
            assert len(c.matched) <= c.keyframes and list(c.matched) == sorted(c.matched)


def gates(library: Library) -> dict[str, int]:
    """The gated classes of ``library`` and their keyframes."""
    return {
        p.name: len(p.template.keyframes.keyframes)
        for p in plans(library)
        if p.template.keyframes and p.gated
    }


def gated_and_high(events: list[Detection | ProgressEvent], gated: dict[str, int]) -> int:
    """Every detection of a gated class (name: keyframes) comes after (or with) an event that shows
    a whole hit of its class (one hit, its range growing while its last keyframe holds, may gate
    several detections of a repeated motion); every detection of another class was shown at least
    :data:`HIGH` along its template from the detection's first frame on, before it. The detections
    checked."""
    whole: set[str] = set()
    best: dict[str, list[tuple[int, float]]] = {}
    checked = 0
    for item in events:
        if isinstance(item, ProgressEvent):
            for c in item.classes:
                if c.keyframes and len(c.matched) == c.keyframes:
                    whole.add(c.class_name)
                best.setdefault(c.class_name, []).append((item.frame, c.position))
            continue
        name = item.class_name
        if name in gated:
            assert name in whole, f"{name} {item.start_frame}-{item.end_frame}: no whole hit shown before it"
            checked += 1
            continue  # its DTW runs from the hit on, over frames already shown: the hit is its progress
        shown = [p for frame, p in best.get(name, []) if frame >= item.start_frame]
        assert max(shown, default=0.0) >= HIGH, (name, item.start_frame, item.end_frame, shown)
        checked += 1
    return checked


@pytest.mark.parametrize("pair", CMU_TRIALS, ids=lambda p: p[1].name.split(".")[0])
def test_on_cmu_trials_detections_come_after_their_progress(pair: tuple[Path, Path]) -> None:
    """The shipped library (its classes keyframes first as learned; ToeTouchOneHand, with no fold,
    is not) on the CMU trials."""
    events = detect_progress(read_recording(*pair), shipped(), 120.0)
    gated = gates(shipped())
    assert gated == {
        n: len(c.keyframes.keyframes)
        for n, c in shipped().classes.items()
        if c.mode == "keyframes" and c.keyframes
    }
    assert len(gated) >= 10 and "ToeTouchOneHand" not in gated
    assert gated_and_high(events, gated) > 5


def test_on_hdm05_clips_gated_detections_come_after_their_whole_hit(tmp_path: Path) -> None:
    """squat1Reps and hopBothLegs1hops gated by their published keyframes, on clips of bk and dg
    joined one after another in a stream per class."""
    library = small_library(tmp_path)
    gated = gates(library)
    assert gated, "the small library has gated classes"
    checked = 0
    for name in ("squat1Reps", "hopBothLegs1hops"):
        for actor in ("bk", "dg"):
            for take in takes(name, actor)[3:6]:
                events = detect_progress(read_recording(*hdm05_clip(actor, name, take)), library, 120.0)
                checked += gated_and_high(events, gated)
    assert checked >= 6
