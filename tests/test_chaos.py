"""The chaos harness (``bench/chaos.py``) in short: real mosquitto, daemon and replay processes; each
kind of disruption once (daemon SIGTERM and kill -9, broker restart, publisher pause past
``idle_s``, publisher restart renumbered, garbage flood) over three looping streams, then a storm of
40,000 stream ids in 4 rounds. Every disruption is survived, the detections in every span left
alone equal ``mocapd detect``'s on the same frames, no motion is published twice, the daemon's
streams and per-stream series are back where they were and its memory does not grow round by
round. The harness's check itself: a replay that started late (a loaded machine) is checked from
its first pose."""

from __future__ import annotations

import numpy as np
import pytest

from bench.chaos import (
    CLIPS,
    KINDS,
    RATE,
    SETTLE_S,
    Clip,
    Disruption,
    Plan,
    Replay,
    check,
    clip_files,
    run,
    table,
)
from daemon.library import default_library_path, load_library
from daemon.recognizer import detect_positions
from daemon.recordings import read_recording
from daemon.types import RecognitionSettings
from replay.kinematics import joint_positions
from tests.helpers import DATA


@pytest.mark.slow
def test_every_disruption_is_survived_and_detections_stay_exact() -> None:
    plan = Plan(
        streams=3,
        seconds=12.0 * (len(KINDS) + 1),
        every=12.0,
        hold_s=2.0,
        flood=20_000,
        storm=40_000,
        data=DATA,
    )
    outcome = run(plan)
    report = table(outcome)
    assert [d.kind for d in outcome.disruptions[1:]] == list(KINDS), report
    assert all(d.survived for d in outcome.disruptions), report
    assert len(outcome.spans) >= 3 * 2 and sum(len(s.expected) for s in outcome.spans) >= 30, report
    assert all(s.got == s.expected for s in outcome.spans), report
    assert outcome.doubled == 0, report
    assert outcome.streams_after_storm == outcome.streams_live == outcome.series_after_storm == 3, report
    assert len(outcome.rss_rounds) == 4 and outcome.rss_growth <= 1.1, report


def test_a_replay_that_started_late_is_checked_from_its_first_pose() -> None:
    """On a loaded machine a replay can send its first pose later than ``SETTLE_S`` after the
    harness started it, so the first span left alone begins before the run did. The daemon then
    gives ``detect``'s detections of the frames from the run's first pose on, and the check must
    expect exactly those (before: its reference reached back before the run's first pose, wrapped
    around to the clip's end, and expected detections of frames never sent)."""
    plan = Plan(streams=1, hold_s=2.0)
    library = load_library(default_library_path())
    name = CLIPS[0]
    motion = read_recording(*clip_files(DATA, name))
    clip = Clip(int(motion.frames[0]), joint_positions(motion))
    begin, late, seconds = 1_000_000.0, SETTLE_S + 0.5, 20.0
    replay = Replay(*clip_files(DATA, name), "mqtt://127.0.0.1:1", "s0")  # never started: its run's times
    replay.started.append(begin + late)
    numbers = np.arange(clip.first, clip.first + int(seconds * RATE), dtype=np.int64)
    positions = clip.positions[(numbers - clip.first) % len(clip.positions)]
    sent = detect_positions(
        positions, numbers, library, RATE, settings=RecognitionSettings(hold_s=plan.hold_s), stream="s0"
    )
    published = [
        (0.0, {**d.as_json(), "source_time": begin + late + (d.emitted_at_frame - clip.first) / RATE})
        for d in sent
    ]
    start = Disruption("start", ("s0",), begin, begin)
    spans = check(
        plan, [start], begin + late + seconds, {"s0": name}, {"s0": replay}, published, {name: clip}, library
    )
    assert len(spans) == 1 and spans[0].first < clip.first  # the span reaches back before the run
    assert len(spans[0].got) >= 5
    assert spans[0].expected == spans[0].got
