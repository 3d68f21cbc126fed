"""Frame numbers translated in one place (:mod:`daemon.frames`): the clock between a motion's frame
numbers and its index frames against a slow enumeration of the frames (and against the feature
stream's real delay)."""

from __future__ import annotations

import math
from fractions import Fraction

import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from daemon.features import FeatureStream, latency_frames, sample_count, sample_rows
from daemon.frames import FrameClock
from daemon.recordings import read_recording
from replay import JOINT_NAMES
from replay.kinematics import joint_positions
from tests.helpers import DATA

# --------------------------------------------------------------------------------- the clock


def test_clock_of_rates() -> None:
    """The features are those of the index frames' poses: they come out the look-ahead at the index
    rate later (5 index frames at 30 Hz). A rate the library's does not divide samples the frame
    nearest each index frame's instant: 100 Hz holds 3 index frames in 10 frames."""
    assert FrameClock.of(120.0, 30.0) == FrameClock(4, latency_frames(30.0)) == FrameClock(4, 5)
    assert FrameClock.of(30.0, 30.0) == FrameClock(1, 5)
    assert FrameClock.of(60.0, 30.0) == FrameClock(2, 5)
    assert FrameClock.of(100.0, 30.0) == FrameClock(10, 5, 3)
    assert [FrameClock(10, 5, 3).start(0, j) for j in range(7)] == [0, 4, 7, 10, 14, 17, 20]
    assert FrameClock.of(120.0, 30.0).delay == 20 and FrameClock(10, 5, 3).delay == 17
    for native, index in ((25.0, 30.0), (math.nan, 30.0), (0.0, 30.0), (-120.0, 30.0), (1e6, 30.0)):
        with pytest.raises(ValueError):
            FrameClock.of(native, index)
    for step, lead, per in ((0, 0, 1), (1, -1, 1), (2, 0, 3), (4, 0, 2)):
        with pytest.raises(ValueError):
            FrameClock(step, lead, per)


@settings(max_examples=300, deadline=None)
@given(
    st.integers(1, 12),
    st.integers(1, 5),
    st.integers(0, 8),
    st.integers(-(10**6), 10**6),
    st.integers(1, 300),
)
def test_clock_equals_an_enumeration_of_the_frames(
    step: int, per: int, lead: int, first: int, n: int
) -> None:
    """Frames ``first .. first + n - 1`` pushed one by one, index frame ``j``'s instant ``j·step/per``
    frames after the first (while it is not past the last frame): its frame is the first at or
    after its instant (found by search), each frame falls in the last index frame at or before it,
    and index frame ``j``'s features come out when index frame ``j + lead``'s frame is pushed, or
    at the motion's end."""
    assume(step >= per and math.gcd(step, per) == 1)
    clock = FrameClock(step, lead, per)
    last = first + n - 1
    instants = [t for t in (Fraction(j * step, per) for j in range(n + 1)) if t <= n - 1]
    starts = [first + min(k for k in range(n) if k >= t) for t in instants]
    of_frame = {
        number: max(j for j, f in enumerate(starts) if f <= number) for number in range(first, last + 1)
    }
    known = {j: (starts[j + lead] if j + lead < len(starts) else last) for j in range(len(starts))}
    lowest = {j: min(f for f, k in of_frame.items() if k == j) for j in range(len(starts))}
    highest = {j: max(f for f, k in of_frame.items() if k == j) for j in range(len(starts))}
    assert sample_count(n, step, per) == len(starts)
    assert sample_rows(n, step, per).tolist() == [f - first for f in starts]
    for j, start in enumerate(starts):
        assert clock.start(first, j) == start
        assert clock.index(first, start) == j  # round trip
        assert clock.known(first, j, last) == known[j]
        for end in {*range(j, min(j + 4, len(starts))), len(starts) - 1}:
            assert clock.span(first, j, end, last) == (lowest[j], highest[end]), (j, end)
    for number, j in of_frame.items():
        assert clock.index(first, number) == j
        assert clock.keeps(first, number) == (number in starts)
        assert clock.start(first, j) <= number < clock.start(first, j + 1)  # round trip
    far = first + 10**6
    assert clock.lag(3) == max(clock.start(first, j + 3 + lead) - clock.start(first, j) for j in range(per))
    assert clock.delay == max(clock.known(first, j, far) - clock.start(first, j) for j in range(per))
    if per == 1:
        assert (clock.lag(3), clock.delay) == ((3 + lead) * step, lead * step)


@pytest.mark.parametrize(("every", "rate"), [(1, 120.0), (2, 60.0), (1, 100.0)], ids=["120", "60", "100"])
def test_clock_agrees_with_the_features_delay(every: int, rate: float) -> None:
    """The frame whose push gives each index frame's features, as the live path's
    :class:`~daemon.features.FeatureStream` gives them (at the index rate, on the index frames'
    poses alone), is the clock's (at 100 Hz, real poses taken for a 100 Hz stream)."""
    m = read_recording(DATA / "cmu" / "02" / "02.asf", DATA / "cmu" / "02" / "02_01.amc.gz")
    positions = joint_positions(m)[::every][:200]
    clock = FrameClock.of(rate, 30.0)
    stream = FeatureStream(JOINT_NAMES, rate * clock.per / clock.step)
    first = 1000
    last = first + len(positions) - 1
    index_frames: list[int] = []  # the frame whose push gave each vector, in order
    for k, pose in enumerate(positions):
        if clock.keeps(first, first + k):
            index_frames += [first + k] * len(stream.push(pose))
    index_frames += [last] * len(stream.flush())
    assert len(index_frames) == sample_count(len(positions), clock.step, clock.per)
    assert index_frames == [clock.known(first, j, last) for j in range(len(index_frames))]
