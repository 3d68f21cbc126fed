"""The streaming keyframe automaton against its batch twin (``keyframe_search`` with the same gap cap)
and the brute force of Def. 4.4-4.8, on random code streams and on every real recording; its latency
bound and its bounded state."""

from __future__ import annotations

import dataclasses
import json
import random
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from daemon._automaton import AutomatonCore
from daemon.automaton import Component, KeyframeAutomaton
from daemon.features import SET_SLICES
from daemon.keyframes import Keyframe, KeyframeQuery, parse_keyframe_queries
from daemon.library import default_library_path, load_library
from daemon.recordings import motion_features, read_recording
from daemon.search.index import index_from_codes
from daemon.search.keyframes import keyframe_search
from daemon.search.segments import set_codes
from daemon.tools.shipped import HDM05_CLASSES
from daemon.types import FEATURE_SETS, FeatureSet
from tests.helpers import KEYFRAMES, pair_id, recording_pairs
from tests.naive import keyframe_brute_force, keyframe_matches
from tests.synth import queries, stream_codes, streams


def run(
    automaton: KeyframeAutomaton, codes: list[int], reached: list[tuple[int, int, int]] | None = None
) -> list[tuple[Component, int]]:
    """Every component with the frame after whose push it came out (the last frame for the flush);
    ``reached`` collects (start of R(M), first frame of keyframe K, frame pushed) of every match
    the automaton reports reaching the frame pushed."""
    out = []
    for t, code in enumerate(codes):
        out += [(c, t) for c in automaton.push(code)]
        if reached is not None:
            reached += [(first, at, t) for first, at in automaton.reached]
    return out + [(c, len(codes) - 1) for c in automaton.flush()]


def batch(
    codes: dict[FeatureSet, list[int]], query: KeyframeQuery, max_gap: int | None
) -> list[tuple[int, int]]:
    sets = {
        fs: index_from_codes(
            [np.asarray(codes[fs], dtype=np.int64)], SET_SLICES[fs].stop - SET_SLICES[fs].start, fs
        )
        for fs in FEATURE_SETS
    }
    found = keyframe_search(sets, [len(codes["lower"])], query, query.rate, max_gap=max_gap)
    return list(zip(found.start.tolist(), found.end.tolist(), strict=True))


def check_stream(
    codes: dict[FeatureSet, list[int]],
    query: KeyframeQuery,
    max_gap: int | None,
    period: int = 0,
    brute_force: bool = True,
) -> None:
    """Components as the batch search, each within the latency bound; the matches reached as the
    brute force enumerates them (unless ``brute_force`` is off: real recordings have too many hits),
    the same without components; no state left after the flush."""
    automaton = KeyframeAutomaton(query, query.rate, max_gap, period)
    reached: list[tuple[int, int, int]] = []
    got = run(automaton, stream_codes(codes), reached)
    assert [(c.start, c.end) for c, _ in got] == batch(codes, query, max_gap)
    if brute_force:  # every match when it completes, and every period later while its last keyframe holds
        expected = [
            (first, at, t)
            for first, at, last in keyframe_matches(codes, query, max_gap)
            for t in range(at, last + 1, period or 1 << 30)
        ]
        assert sorted(reached) == sorted(expected)
    matches_only = KeyframeAutomaton(query, query.rate, max_gap, period, components=False)
    alone: list[tuple[int, int, int]] = []
    assert run(matches_only, stream_codes(codes), alone) == []
    assert alone == reached  # the same matches at the same frames, in the same order
    for component, pushed in got:
        assert component.emitted_at == pushed
        assert component.end <= component.emitted_at <= component.end + automaton.latency
    assert automaton.state_size == 0


@pytest.mark.parametrize("tolerant", [False, True], ids=["exact", "tolerant"])
@settings(max_examples=200, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(streams(), st.data(), st.integers(0, 8), st.integers(0, 4))
def test_automaton_emits_the_batch_components(
    tolerant: bool, codes: dict[FeatureSet, list[int]], data: st.DataObject, max_gap: int, period: int
) -> None:
    """Components, order and emission frames within the latency bound, matches as they complete and
    grow; batch and brute force agree; with keyframes that may miss some fixed entries too."""
    query = data.draw(queries(tolerant=tolerant), label="query")
    check_stream(codes, query, max_gap, period)
    expected = keyframe_brute_force({fs: [c] for fs, c in codes.items()}, query, (0, 0), max_gap)
    assert batch(codes, query, max_gap) == [(s, e) for _, s, e in expected]


def test_latency_bound_is_reached() -> None:
    """Two keyframes 4 frames apart with σ = 0.5 (gaps 2..8): keyframe 1 holding on frames 0-1 keeps
    the component of the hit (1, 3) open until frame 1 + 8 = 9, when no later frame of keyframe 2 can
    be 8 frames or less after a frame of keyframe 1, so the whole (0, 3) is final."""
    lower = [0b001, 0b001, 0b000, 0b010, 0b000, 0b000, 0b000, 0b000, 0b000, 0b000, 0b000, 0b000]
    codes: dict[FeatureSet, list[int]] = {"lower": lower, "upper": [0] * len(lower), "mix": [0] * len(lower)}
    width = SET_SLICES["lower"].stop
    first = Keyframe("lower", (1.0,) + (0.5,) * (width - 1), 0, 0.5)
    second = Keyframe("lower", (0.5, 1.0) + (0.5,) * (width - 2), 4, None)
    query = KeyframeQuery("two", (first, second), 30.0)
    automaton = KeyframeAutomaton(query, 30.0)
    assert automaton.latency == 8
    got = run(automaton, stream_codes(codes))
    assert got == [(Component(0, 3, 9), 9)]
    assert batch(codes, query, None) == [(0, 3)]


def test_a_tolerant_keyframe_holds_on_frames_missing_up_to_its_mismatches() -> None:
    """One keyframe fixing 4 lower bits (1, 1, 1, 0): frames missing none, one, two or three of them;
    with k mismatches the components are the runs of frames missing at most k, in the automaton, the
    batch search and the brute force alike."""
    lower = [0b0111, 0b0011, 0b1011, 0b1111, 0b0000, 0b0110, 0b1000, 0b0111]
    codes: dict[FeatureSet, list[int]] = {"lower": lower, "upper": [0] * len(lower), "mix": [0] * len(lower)}
    values = (1.0, 1.0, 1.0, 0.0) + (0.5,) * (SET_SLICES["lower"].stop - 4)
    expected = {
        0: [(0, 0), (7, 7)],
        1: [(0, 1), (3, 3), (5, 5), (7, 7)],
        2: [(0, 3), (5, 5), (7, 7)],
        3: [(0, 5), (7, 7)],
    }
    for k, components in expected.items():
        query = KeyframeQuery("one", (Keyframe("lower", values, 0, None, k),), 30.0)
        got = run(KeyframeAutomaton(query, 30.0), stream_codes(codes))
        assert [(c.start, c.end) for c, _ in got] == components
        assert batch(codes, query, None) == components
        assert [
            (s, e) for _, s, e in keyframe_brute_force({fs: [c] for fs, c in codes.items()}, query, (0, 0))
        ] == (components)


def test_the_core_refuses_bad_tolerances() -> None:
    """A keyframe may miss fewer bits than it fixes (0 when it fixes none), and its value lies within
    its mask (a bit outside could never match exactly, but would be missed within a tolerance)."""
    assert AutomatonCore([0b11], [0b01], [], [], 0, True, [1]).state_size == 0
    assert AutomatonCore([0], [0], [], [], 0, True, [0]).state_size == 0
    for masks, values, mismatches in (([0b11], [0b01], [2]), ([0], [0], [1]), ([0b01], [0b11], [0])):
        with pytest.raises(
            ValueError, match="keyframe 0: the value must lie within the mask and fewer bits may be missed"
        ):
            AutomatonCore(masks, values, [], [], 0, True, mismatches)
    with pytest.raises(ValueError, match="a number of mismatches"):
        AutomatonCore([0b11, 0b11], [0, 0], [0], [1], 0, True, [0])


def test_unbounded_gap_needs_a_cap() -> None:
    width = SET_SLICES["upper"].stop - SET_SLICES["upper"].start
    values = (1.0,) + (0.5,) * (width - 1)
    query = KeyframeQuery(
        "loose", (Keyframe("upper", values, 0, 0.0), Keyframe("upper", values, 3, None)), 30.0
    )
    with pytest.raises(ValueError, match=r"^loose: a gap with stiffness 0 needs a maximum gap"):
        KeyframeAutomaton(query, 30.0)
    assert KeyframeAutomaton(query, 30.0, max_gap=90).latency == 90


def test_state_stays_bounded_over_an_hour() -> None:
    """One hour at 30 Hz of random runs against a query with an unbounded gap capped at 2 s: the
    partial matches held never exceed what the query's span allows, in the last minutes as in the
    first."""
    rng = random.Random(7)
    width = SET_SLICES["lower"].stop
    query = KeyframeQuery(
        "hour",
        (
            Keyframe("lower", (1.0,) + (0.5,) * (width - 1), 0, 0.0),
            Keyframe("lower", (0.5, 1.0) + (0.5,) * (width - 2), 5, 0.5),
            Keyframe("lower", (0.0, 0.0) + (0.5,) * (width - 2), 9, None),
        ),
        30.0,
    )
    automaton = KeyframeAutomaton(query, 30.0, max_gap=60)
    span = automaton.latency
    largest = [0, 0]
    emitted = [0, 0]
    n = 30 * 3600
    code = 0
    for t in range(n):
        if rng.random() < 0.1:
            code = rng.randrange(8)
        emitted[t >= n // 2] += len(automaton.push(code))
        largest[t >= n // 2] = max(largest[t >= n // 2], automaton.state_size)
    assert min(emitted) > 50  # components come out all through the hour
    # one partial per run of keyframe 1 and per pair of runs inside the span; runs last >= 1 frame
    assert max(largest) <= (span + 1) ** 2
    assert largest[1] <= 2 * largest[0] + span


@pytest.fixture(scope="module")
def shipped() -> list[KeyframeQuery]:
    """Real keyframe queries: the toolbox's published ones (11 HDM05 classes) and those that gate a
    class of the shipped library."""
    learned = [c.keyframes for c in load_library(default_library_path()).classes.values()]
    published = parse_keyframe_queries(json.loads(KEYFRAMES.read_text(encoding="utf-8")), KEYFRAMES)
    queries = [*(published[c] for c in HDM05_CLASSES), *(q for q in learned if q is not None)]
    assert len(queries) > len(HDM05_CLASSES)
    return queries


def test_tolerant_keyframes_on_a_real_recording(shipped: list[KeyframeQuery]) -> None:
    """The shipped queries with every keyframe allowed 1, then 2 mismatches (where it fixes enough
    entries) on a real recording (CMU 13_30, 617 frames), where every feature varies: the automaton
    equals the batch search, and more ranges are kept than with exact keyframes."""
    asf, amc = next(p for p in recording_pairs() if pair_id(p) == "13_30")
    got = motion_features(read_recording(asf, amc), 30.0)
    codes = {fs: set_codes(got.matrix, fs).tolist() for fs in FEATURE_SETS}
    kept = []
    for k in (0, 1, 2):
        found = 0
        for query in shipped:
            keyframes = tuple(
                dataclasses.replace(kf, mismatches=min(k, kf.max_mismatches)) for kf in query.keyframes
            )
            tolerant = dataclasses.replace(query, keyframes=keyframes)
            check_stream(codes, tolerant, 60, 10, brute_force=False)
            found += len(batch(codes, tolerant, 60))
        kept.append(found)
    assert kept[0] < kept[1] < kept[2]


@pytest.mark.slow
@pytest.mark.parametrize("pair", recording_pairs(), ids=pair_id)
def test_automaton_equals_batch_on_real_recordings(
    pair: tuple[Path, Path], shipped: list[KeyframeQuery]
) -> None:
    got = motion_features(read_recording(*pair), 30.0)
    codes = {fs: set_codes(got.matrix, fs).tolist() for fs in FEATURE_SETS}
    for query in shipped:
        check_stream(codes, query, 60, 10, brute_force=False)
