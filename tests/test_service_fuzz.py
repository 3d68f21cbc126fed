"""The fuzz run of ``bench/fuzz.py`` (issue 21), short: 20,000 fuzzed messages on each transport beside
a good stream, through a real daemon (and a real mosquitto): no crash and a clean log, every message
that reached the daemon counted once under a reason, the good stream's detections exactly
``mocapd detect``'s. The 1,000,000-message run is ``python -m bench.fuzz``."""

from __future__ import annotations

from pathlib import Path

import pytest

from bench import fuzz


@pytest.mark.slow
@pytest.mark.parametrize("transport", ["zmq", "mqtt"])
def test_fuzzed_messages_are_counted_and_spoil_nothing(tmp_path: Path, transport: str) -> None:
    r = fuzz.run(transport, 20_000, seed=21, where=tmp_path)
    report = fuzz.report(r)
    assert r.exit_code == 0, report  # alive throughout, and a clean exit on SIGTERM
    assert r.fuzz_routed > 18_000 and r.good > 2465, report
    assert r.counted == r.expected, report
    assert r.detections == r.expected_detections > 0, report
    assert r.kinds.keys() == {"random", "mutated", "valid", "topic"}, report
    assert r.failures == [], report
