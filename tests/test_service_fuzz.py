"""The fuzz run of ``bench/fuzz.py`` (issues 21 and 32), short: 20,000 fuzzed messages on ZeroMQ and
MQTT and 10,000 on NATS beside a good stream, through a real daemon (and a real mosquitto), or a
real cluster (nats-server, etcd, two ``mocapd run --cluster`` workers): no crash, no worker started
again or fenced, a clean log, every message that reached the daemon counted once under a reason,
the good stream's detections exactly ``mocapd detect``'s. The 1,000,000-message run is ``python -m
bench.fuzz``."""

from __future__ import annotations

from pathlib import Path

import pytest

from bench import fuzz


@pytest.mark.slow
@pytest.mark.parametrize("transport", ["zmq", "mqtt", "nats"])
def test_fuzzed_messages_are_counted_and_spoil_nothing(tmp_path: Path, transport: str) -> None:
    messages = 10_000 if transport == "nats" else 20_000
    # a 6 s lease over NATS: a CI machine busy with other work must not fence a worker; what this
    # test is about is the messages (the 1,000,000-message run keeps the shipped 2 s)
    r = fuzz.run(transport, messages, seed=21, where=tmp_path, lease_s=6.0)
    report = fuzz.report(r)
    assert r.exit_code == 0, report  # alive throughout, and a clean exit on SIGTERM
    assert r.fuzz_routed > 0.85 * messages and r.good > 2465, report
    assert r.counted == r.expected, report
    assert r.detections == r.expected_detections > 0, report
    kinds = {"random", "mutated", "valid", "topic"} | ({"subject", "inbox"} if transport == "nats" else set())
    assert r.kinds.keys() == kinds, report
    assert r.restarts == 0, report
    if transport == "nats":
        assert r.stored == r.fuzz_stored + r.good and r.refused == r.refused_predicted > 0, report
        assert r.series['mocapd_drops_total{reason="nats_foreign"}'] > 0, report
    assert r.failures == [], report
