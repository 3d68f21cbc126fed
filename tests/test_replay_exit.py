"""``mocapd replay`` refuses a stream id no transport carries whole, and stops at one SIGTERM on
every transport, whatever its peer does: over MQTT while it sends as fast as it can (a
signal's handler raising inside the event loop's callbacks, where paho writes, used to be swallowed
by asyncio: a replay went on until a second signal), and over ZeroMQ after its subscriber has gone
(it used to linger 10 s over what it had queued). Real processes, a real mosquitto and real ZeroMQ
sockets.

The bound is not the promise's second: eight replays writing flat out on CI's two cores share them
during the 0.5 s drain and the interpreter's exit, and took 1.0-1.2 s here (0.5 s alone). What the
bound tells apart is the faults: a replay that never stopped, or one that lingered 10 s."""

from __future__ import annotations

import signal
import subprocess
import time
from pathlib import Path

import pytest
import zmq

from bench.processes import free_port
from tests.helpers import CMU_AMC, CMU_ASF, Broker, replay, wait_for

STOP_S = 3.0
"""The most a replay may take to exit after SIGTERM, on a loaded machine."""


def stopped(processes: list[subprocess.Popen[str]]) -> list[tuple[float, int | None, str]]:
    """SIGTERM to every process at once; per process the seconds until it exited (inf: not within
    5 s, then killed), its status and its stderr."""
    sent = time.monotonic()
    for p in processes:
        p.send_signal(signal.SIGTERM)
    out = []
    for p in processes:
        try:
            p.wait(max(0.0, sent + 5 - time.monotonic()))
            took = time.monotonic() - sent
        except subprocess.TimeoutExpired:
            took = float("inf")
            p.kill()
            p.wait(5)
        assert p.stderr is not None
        out.append((took, p.returncode, p.stderr.read()))
    return out


@pytest.mark.slow  # 6-10 s: eight replays at full speed
@pytest.mark.exclusive  # a bound in real time: no other test beside it under xdist
def test_replays_over_mqtt_stop_at_one_sigterm(tmp_path: Path) -> None:
    broker = Broker(tmp_path).start()
    try:
        replays = [
            replay(CMU_ASF, CMU_AMC, broker.url, "--loop", stream=f"s{i}", speed="max") for i in range(8)
        ]
        log = tmp_path / "mosquitto.log"
        wait_for(lambda: log.read_text().count("New client connected") >= 8, 30, "every replay connected")
        time.sleep(0.5)  # sending
        for took, status, err in stopped(replays):
            assert took < STOP_S and status == 128 + signal.SIGTERM, (took, status, err[-500:])
            assert err.strip().splitlines()[-1] == "mocapd: terminated", err[-500:]
    finally:
        broker.stop()


@pytest.mark.exclusive  # a bound in real time: no other test beside it under xdist
def test_a_replay_over_zeromq_whose_daemon_has_gone_stops_promptly_at_sigterm() -> None:
    port = free_port()
    ctx = zmq.Context()
    daemon = ctx.socket(zmq.SUB)
    daemon.setsockopt(zmq.LINGER, 0)
    daemon.setsockopt(zmq.SUBSCRIBE, b"")
    daemon.bind(f"tcp://127.0.0.1:{port}")
    try:
        sender = replay(CMU_ASF, CMU_AMC, f"zmq+tcp://127.0.0.1:{port}", "--loop", speed="1")
        daemon.setsockopt(zmq.RCVTIMEO, 30_000)
        daemon.recv_multipart()  # it sends
        daemon.close()  # and its daemon goes away, with poses on their way
        time.sleep(0.5)
        ((took, status, err),) = stopped([sender])
        assert took < STOP_S and status == 128 + signal.SIGTERM, (took, status, err[-500:])
    finally:
        daemon.close()
        ctx.term()


def test_a_stream_id_with_a_dot_is_refused_in_one_line_before_anything_is_sent() -> None:
    """A ``.`` splits a NATS subject: in cluster mode such a stream reconnected for ever."""
    done = replay(CMU_ASF, CMU_AMC, "mqtt://127.0.0.1:9", stream="a.b")
    out, err = done.communicate(timeout=60)
    assert done.returncode == 2 and out == ""
    assert err.splitlines() == [
        "mocapd: --stream: 'a.b' is not a stream id (letters, digits, _:@-, at most 128)"
    ]
