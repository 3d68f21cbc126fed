"""The merge of a partition's buffered and live copies (:mod:`protocols.merge`) against what a
reader of both paths must get: every message that reached the worker on either path, once, each
stream's in the order they were published, the buffer's sequence numbers all accounted for, on
random deliveries (losses on one path or both, either path late, a replay before live)."""

from __future__ import annotations

import math
from collections import Counter
from dataclasses import dataclass

from hypothesis import given
from hypothesis import strategies as st

from protocols.merge import Merge, Passed, Twice


@dataclass(frozen=True)
class Message:
    index: int  # in the order published; its buffer sequence is index + 1
    stream: int
    payload: str


@dataclass(frozen=True)
class Run:
    messages: list[Message]
    before: int  # messages published before the partition was taken: buffered only, replayed
    replay_s: float  # how long their replay takes (a loaded worker reads a long buffer slowly)
    buffered: list[tuple[float, int]]  # (arrival, index), in arrival order
    live: list[tuple[float, int]]
    hold_s: float


@st.composite
def runs(draw: st.DrawFn, regime: str, repeats: bool = False) -> Run:
    """Deliveries of random messages of 1-3 streams, 0.1 s apart, those published before the take
    replayed over ``replay_s`` after it (the live copies of those published meanwhile held).
    ``regime``: ``buffer_loses`` (the live path loses nothing and its copies come first),
    ``live_loses`` (the buffer loses nothing and brings each message at most ``0.9 hold_s`` after
    its live copy would have come, or with the end of the replay), ``both_lose`` (anything).
    ``repeats``: some messages are a stream's skeleton, identical each time."""
    n = draw(st.integers(1, 50))
    streams = draw(st.lists(st.integers(0, 2), min_size=n, max_size=n))
    messages: list[Message] = []
    seqs: Counter[int] = Counter()
    for i, s in enumerate(streams):
        seqs[s] += 1
        skeleton = repeats and draw(st.integers(0, 4)) == 0
        messages.append(Message(i, s, f"{s}:skeleton" if skeleton else f"{s}:{seqs[s]}"))
    before = draw(st.integers(0, n))
    hold_s = draw(st.sampled_from([0.05, 0.5, 1.0, 2.0]))
    replay_s = draw(st.sampled_from([0.0, 0.5, 3.0])) if before else 0.0
    lags = st.floats(0.0, 3.0)
    buffered: list[tuple[float, int]] = []
    live: list[tuple[float, int]] = []
    taken = 0.1 * before
    last_b = last_l = 0.0
    for m in messages:
        published = 0.1 * m.index
        live_lag = draw(lags)
        if regime == "buffer_loses":
            buffer_lag = live_lag + draw(lags)
        elif regime == "live_loses":  # the buffer within hold_s of the live path
            buffer_lag = draw(st.floats(0.0, live_lag + 0.9 * hold_s))
        else:
            buffer_lag = draw(lags)
        if m.index < before:
            last_b = max(last_b, taken + replay_s * (m.index + 1) / before)
        else:
            last_b = max(last_b, published + buffer_lag)
            last_l = max(last_l, published + live_lag)
        lost_b = regime != "live_loses" and m.index >= before and draw(st.booleans())
        lost_l = regime != "buffer_loses" and draw(st.booleans())
        if not lost_b:
            buffered.append((last_b, m.index))
        if m.index >= before and not lost_l:
            live.append((last_l, m.index))
    return Run(messages, before, replay_s, buffered, live, hold_s)


def merged(run: Run, remember_s: float = math.inf) -> list[Passed[Message]]:
    """Feed the deliveries in the order they arrive (live first at equal times), releasing held
    copies as time goes; the buffer turns live once it delivered the last message held before the
    take."""
    merge: Merge[Message] = Merge(run.hold_s, remember_s, most=1 << 20)
    merge.replaying = run.before > 0
    events = sorted([(t, 0, i) for t, i in run.live] + [(t, 1, i) for t, i in run.buffered])
    out: list[Passed[Message]] = []
    for t, buffered, i in events:
        out += merge.release(t)
        m = run.messages[i]
        key = None if m.payload.endswith("skeleton") else hash(m.payload)
        if buffered:
            out += merge.push(key, m, t, seq=i + 1)
            if merge.replaying and i >= run.before - 1:
                merge.went_live(t)
                out += merge.release(t)
        else:
            out += merge.push(key, m, t)
    merge.went_live(events[-1][0] if events else 0.0)
    out += merge.release(math.inf)
    assert merge.held == 0
    return out


def reached(run: Run) -> list[Message]:
    """The reference: every message delivered on either path, in the order published."""
    indices = {i for _, i in run.buffered} | {i for _, i in run.live}
    return [m for m in run.messages if m.index in indices]


def per_stream(messages: list[Message]) -> dict[int, list[str]]:
    out: dict[int, list[str]] = {}
    for m in messages:
        out.setdefault(m.stream, []).append(m.payload)
    return out


def check_positions(run: Run, out: list[Passed[Message]]) -> None:
    """Every buffered copy gives one output, passed or a marker, in the buffer's order."""
    assert [seq for seq, _ in out if seq >= 0] == [i + 1 for _, i in run.buffered]


@given(runs("buffer_loses"))
def test_a_buffer_that_loses_messages_loses_none_of_the_live_ones(run: Run) -> None:
    out = merged(run)
    check_positions(run, out)
    assert [m for _, m in out if m is not None] != [] or not run.messages
    assert per_stream([m for _, m in out if m is not None]) == per_stream(reached(run))


@given(runs("live_loses"))
def test_a_live_path_that_loses_messages_is_filled_from_the_buffer(run: Run) -> None:
    out = merged(run)
    check_positions(run, out)
    assert per_stream([m for _, m in out if m is not None]) == per_stream(reached(run))


@given(runs("both_lose"))
def test_whatever_either_path_loses_each_message_is_passed_once(run: Run) -> None:
    out = merged(run)
    check_positions(run, out)
    assert sorted(m.index for _, m in out if m is not None) == sorted(m.index for m in reached(run))


def check_repeats(run: Run, out: list[Passed[Message]]) -> None:
    """Messages repeated identically (a skeleton announced again, given no key) are passed once
    from each path that brought them, in that path's order; the others exactly once, each stream's
    in order."""
    got = [m for _, m in out if m is not None]
    came = [run.messages[i] for _, i in run.buffered] + [run.messages[i] for _, i in run.live]
    repeats = [m.index for m in got if m.payload.endswith("skeleton")]
    assert Counter(repeats) == Counter(m.index for m in came if m.payload.endswith("skeleton"))
    unique = [m for m in reached(run) if not m.payload.endswith("skeleton")]
    assert per_stream([m for m in got if not m.payload.endswith("skeleton")]) == per_stream(unique)


@given(runs("buffer_loses", repeats=True))
def test_identical_messages_from_a_buffer_that_loses_some(run: Run) -> None:
    out = merged(run)
    check_positions(run, out)
    check_repeats(run, out)


@given(runs("live_loses", repeats=True))
def test_identical_messages_filled_from_the_buffer(run: Run) -> None:
    out = merged(run)
    check_positions(run, out)
    check_repeats(run, out)


def test_a_held_live_copy_waits_while_replaying_and_hold_s_after() -> None:
    merge: Merge[str] = Merge(hold_s=1.0, remember_s=10.0, most=100)
    assert merge.push(1, "a", 0.0) == []
    assert merge.release(5.0) == []  # replaying: held however long
    merge.went_live(4.0)
    assert merge.release(4.9) == []  # hold_s from when the buffer went live
    merge.went_live(4.5)  # live already: the hold does not start again
    assert merge.release(5.0) == [(-1, "a")]
    assert merge.awaiting(5.0)  # its buffered copy not seen: a position now would precede it
    assert merge.stalled(5.5, 0.4) and not merge.stalled(5.5, 0.6)  # passed alone since 5.0
    assert merge.push(1, "a", 6.0, seq=7) == [(7, None)]  # the marker
    assert not merge.awaiting(6.0) and not merge.stalled(6.0, 0.0)
    assert merge.push(2, "b", 7.0) == []
    assert merge.release(7.9) == []
    assert merge.release(8.0) == [(-1, "b")]
    assert merge.stalled(9.5, 1.0)  # since 8.0, not since 5.0: "a" was confirmed at 6.0
    assert not merge.stalled(8.5, 1.0)
    merge.rewatch()  # a consumer made again: its own chance
    assert not merge.stalled(9.5, 1.0)
    assert not merge.awaiting(18.1)  # never confirmed, but older than remember_s


def test_what_is_remembered_is_forgotten_after_remember_s() -> None:
    merge: Merge[str] = Merge(hold_s=1.0, remember_s=10.0, most=100)
    merge.went_live(0.0)
    assert merge.push(1, "a", 0.0, seq=1) == [(1, "a")]
    assert merge.push(1, "a", 5.0) == []  # its buffered copy was passed
    assert merge.push(2, "b", 6.0, seq=2) == [(2, "b")]
    merge.release(16.5)
    assert merge.push(2, "b", 16.5) == []  # held: "b" passed more than 10 s ago is forgotten
    assert merge.held == 1


def test_past_most_the_oldest_held_copy_is_dropped() -> None:
    merge: Merge[str] = Merge(hold_s=1.0, remember_s=10.0, most=2)
    for k, item in enumerate("abc"):
        merge.push(k, item, 0.0)
    assert merge.held == 2 and merge.dropped == 1
    merge.went_live(0.0)
    assert merge.release(2.0) == [(-1, "b"), (-1, "c")]


@st.composite
def twin_paths(draw: st.DrawFn) -> tuple[int, list[tuple[float, int, int]], bool]:
    """``n`` distinct messages published 0.01 s apart, each path delivering them in order, late by
    a random delay that grows with time (as a connection's queue does) and losing random runs of
    them (a server away): (n, the copies as (arrival, path, index) in arrival order, whether
    either path lost one)."""
    n = draw(st.integers(0, 40))
    copies: list[tuple[float, int, int]] = []
    lost = False
    for path in (0, 1):
        kept = draw(st.lists(st.booleans(), min_size=n, max_size=n))
        lost = lost or not all(kept)
        delay = 0.0
        for i in range(n):
            delay += draw(st.floats(0, 0.02))
            if kept[i]:
                copies.append((i * 0.01 + delay, path, i))
    copies.sort()
    return n, copies, lost


@given(twin_paths())
def test_of_two_live_paths_each_message_is_passed_once_and_in_order_when_neither_lost_one(
    drawn: tuple[int, list[tuple[float, int, int]], bool],
) -> None:
    n, copies, lost = drawn
    twice = Twice(remember_s=10.0)
    passed = [i for at, path, i in copies if twice.first(hash(("s", i)), path, at)]
    assert sorted(passed) == sorted({i for _, _, i in copies})  # every message that came, once
    if not lost:
        assert passed == list(range(n))
    assert twice.twins == len(copies) - len(passed)


def test_a_twin_later_than_remember_s_is_passed_again_and_repeated_messages_always() -> None:
    twice = Twice(remember_s=1.0)
    assert twice.first(7, 0, 0.0) and not twice.first(7, 1, 0.5)
    assert twice.first(8, 0, 1.0) and twice.first(8, 1, 2.5)  # forgotten: passed again
    assert twice.first(None, 0, 3.0) and twice.first(None, 1, 3.0)
    assert twice.first(9, 0, 4.0) and twice.first(9, 0, 4.0)  # the same message published twice
    assert not twice.first(9, 1, 4.1) and not twice.first(9, 1, 4.2) and twice.first(9, 1, 4.3)
