"""What a boundary says of the behaviour that ended (issue 38): its first frame, and the detections
published before the boundary that lie wholly inside it; ``daemon.service.streams._Segmenting``
against a plain reading of the emitted sequence, on a real recording with random detections."""

from __future__ import annotations

from functools import cache

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from daemon.behaviours import JointRotations
from daemon.recordings import read_recording
from daemon.service.streams import _Segmenting
from protocols.messages import DetectionMessage
from tests.helpers import DATA, SegmentSummary, check_segment_summaries

TAKE = (DATA / "cmu" / "13" / "13.asf", DATA / "cmu" / "13" / "13_30.amc.gz")
FRAMES = 1600  # two cuts of PCA's in it


@cache
def take() -> tuple[JointRotations, np.ndarray]:
    m = read_recording(*TAKE)
    return JointRotations(m.skeleton), m.channels[:FRAMES]


def detection(k: int, start: int, end: int) -> DetectionMessage:
    return DetectionMessage(f"d{k}", "s", f"class{k % 3}", start, end, 0.1, 0.2, end, 0.0, 0.0)


@settings(max_examples=15, deadline=None)
@given(
    st.integers(0, 10_000),
    st.lists(st.tuples(st.integers(0, FRAMES - 1), st.integers(0, 400), st.integers(0, 200)), max_size=60),
    st.integers(0, 2),
)
def test_each_boundary_names_its_behaviours_start_and_the_detections_inside(
    first: int, spans: list[tuple[int, int, int]], restarts: int
) -> None:
    """Detections (start, end) published at frame ``at`` (end <= at), some crossing the cuts (fewer
    than a boundary may list); and ``restarts`` ends of the motion part way."""
    rotations, channels = take()
    segmenting = _Segmenting(rotations, "pca", 120.0)
    by_frame: dict[int, list[DetectionMessage]] = {}
    for k, (at, back, length) in enumerate(spans):
        end = first + at
        by_frame.setdefault(end, []).append(detection(k, end - back - length, end - back))
    ends = {first + FRAMES * (r + 1) // (restarts + 1) for r in range(restarts)}
    events: list[DetectionMessage | SegmentSummary | int] = []  # int: the motion ended, the next begins there
    for i, c in enumerate(channels):
        frame = first + i
        if frame in ends:
            events += [*segmenting.restart(), frame]
        for d in by_frame.get(frame, []):
            segmenting.detected(d)
            events.append(d)
        events += segmenting.push(frame, c)
    events += segmenting.restart()
    assert check_segment_summaries(events, first) > 0
