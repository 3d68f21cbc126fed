"""Frame numbers translated in one place (:mod:`daemon.frames`): the clock between a motion's frame
numbers and its index frames against a slow enumeration of the frames (and against the feature
stream's real delay)."""

from __future__ import annotations

import math
from collections import deque

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from daemon.features import FeatureStream, latency_frames
from daemon.frames import FrameClock
from daemon.recordings import read_recording
from replay import JOINT_NAMES
from replay.kinematics import joint_positions
from tests.helpers import DATA

# --------------------------------------------------------------------------------- the clock


def test_clock_of_rates() -> None:
    """The features are those of the index frames' poses: their delay is the look-ahead at the index
    rate (5 index frames at 30 Hz), in native frames."""
    assert FrameClock.of(120.0, 30.0) == FrameClock(4, 4 * latency_frames(30.0)) == FrameClock(4, 20)
    assert FrameClock.of(30.0, 30.0) == FrameClock(1, 5)
    assert FrameClock.of(60.0, 30.0) == FrameClock(2, 10)
    for native, index in ((100.0, 30.0), (math.nan, 30.0), (0.0, 30.0), (-120.0, 30.0), (1e6, 30.0)):
        with pytest.raises(ValueError):
            FrameClock.of(native, index)
    for step, delay in ((0, 0), (1, -1)):
        with pytest.raises(ValueError):
            FrameClock(step, delay)


@settings(max_examples=200, deadline=None)
@given(st.integers(1, 12), st.integers(0, 40), st.integers(-(10**6), 10**6), st.integers(1, 300))
def test_clock_equals_an_enumeration_of_the_frames(step: int, delay: int, first: int, n: int) -> None:
    """Frames ``first .. first + n - 1`` pushed one by one: every ``step``-th from the first is the
    next index frame, its features come out ``delay`` pushes later or at the motion's end."""
    clock = FrameClock(step, delay)
    last = first + n - 1
    starts: list[int] = []  # index frame j's frame number
    of_frame: dict[int, int] = {}  # each frame's index frame
    known: dict[int, int] = {}  # index frame j: the frame whose push gave its features
    pending: deque[int] = deque()  # frames whose features are not out yet, oldest first
    for number in range(first, last + 1):
        if (number - first) % step == 0:
            starts.append(number)
        of_frame[number] = len(starts) - 1
        pending.append(number)
        if len(pending) > delay:
            out = pending.popleft()
            if out in starts:
                known[starts.index(out)] = number
    for out in pending:  # the flush
        if out in starts:
            known[starts.index(out)] = last
    lowest = {j: min(f for f, k in of_frame.items() if k == j) for j in range(len(starts))}
    highest = {j: max(f for f, k in of_frame.items() if k == j) for j in range(len(starts))}
    for j, start in enumerate(starts):
        assert clock.start(first, j) == start
        assert clock.index(first, start) == j  # round trip
        assert clock.known(first, j, last) == known[j]
        for end in {*range(j, min(j + 4, len(starts))), len(starts) - 1}:
            assert clock.span(first, j, end, last) == (lowest[j], highest[end]), (j, end)
    for number, j in of_frame.items():
        assert clock.index(first, number) == j
        assert clock.start(first, j) <= number < clock.start(first, j + 1)  # round trip
    assert clock.lag(3) == clock.known(first, 3, 10**9) - clock.start(first, 0)


@pytest.mark.parametrize("every", [1, 2], ids=["120 Hz", "60 Hz"])
def test_clock_agrees_with_the_features_delay(every: int) -> None:
    """The frame whose push gives each index frame's features, as the live path's
    :class:`~daemon.features.FeatureStream` gives them (at the index rate, on the index frames'
    poses alone), is the clock's."""
    m = read_recording(DATA / "cmu" / "02" / "02.asf", DATA / "cmu" / "02" / "02_01.amc.gz")
    positions = joint_positions(m)[::every][:200]
    rate = 120.0 / every
    clock = FrameClock.of(rate, 30.0)
    stream = FeatureStream(JOINT_NAMES, rate / clock.step)
    first = 1000
    last = first + len(positions) - 1
    index_frames: list[int] = []  # the frame whose push gave each vector, in order
    for k, pose in enumerate(positions):
        if k % clock.step == 0:
            index_frames += [first + k] * len(stream.push(pose))
    index_frames += [last] * len(stream.flush())
    assert len(index_frames) == len(positions[:: clock.step])
    assert index_frames == [clock.known(first, j, last) for j in range(len(index_frames))]
