"""The chaos harness (``bench/chaos.py``) in short: real mosquitto, daemon and replay processes; each
kind of disruption once (daemon SIGTERM and kill -9, broker restart, publisher pause past
``idle_s``, publisher restart renumbered, garbage flood) over three looping streams, then a storm of
40,000 stream ids in 4 rounds. Every disruption is survived, the detections in every span left
alone equal ``mocapd detect``'s on the same frames, no motion is published twice, the daemon's
streams and per-stream series are back where they were and its memory does not grow round by
round."""

from __future__ import annotations

import pytest

from bench.chaos import KINDS, Plan, run, table
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
