"""``mocapd run`` that cannot start: a real daemon process, real sockets. Every startup failure ends
with status 2 and one line naming the setting (``zmq.poses: ...: address already in use``) before
"online" is published; none hangs or reports an internal error (issue 21)."""

from __future__ import annotations

import json
import signal
import socket
import subprocess
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from bench.processes import free_port
from tests.helpers import (
    HDM_AMC,
    HDM_ASF,
    MOCAPD_SCRIPT,
    Broker,
    Daemon,
    MqttCollector,
    ZmqCollector,
    assert_one_error_line,
    finished,
    mocapd,
    replay,
    wait_for,
)


@pytest.fixture
def taken() -> Iterator[int]:
    """A loopback TCP port something else listens on."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen()
        yield s.getsockname()[1]


def run(tmp_path: Path, sections: dict[str, dict[str, object]]) -> subprocess.CompletedProcess[str]:
    config: dict[str, dict[str, object]] = {
        "zmq": {"poses": f"tcp://127.0.0.1:{free_port()}", "detections": f"tcp://127.0.0.1:{free_port()}"},
        "metrics": {"port": 0},
    }
    for name, values in sections.items():
        config.setdefault(name, {}).update(values)
    path = tmp_path / "daemon.yaml"
    path.write_text(json.dumps(config), encoding="utf-8")
    return subprocess.run(
        [str(MOCAPD_SCRIPT), "--config", str(path), "run"], capture_output=True, text=True, timeout=30
    )


def check_refused(result: subprocess.CompletedProcess[str], line: str) -> None:
    """Status 2, the last stderr line exactly ``line``, and "online" never said or published."""
    assert result.returncode == 2, result.stderr
    assert result.stderr.splitlines()[-1] == line, result.stderr
    assert "Traceback" not in result.stderr and "internal error" not in result.stderr
    assert '"online"' not in result.stderr and '"online"' not in result.stdout


def test_poses_address_in_use(tmp_path: Path, taken: int) -> None:
    endpoint = f"tcp://127.0.0.1:{taken}"
    check_refused(
        run(tmp_path, {"zmq": {"poses": endpoint}}), f"mocapd: zmq.poses: {endpoint}: address already in use"
    )


def test_poses_and_detections_on_one_endpoint(tmp_path: Path) -> None:
    endpoint = f"tcp://127.0.0.1:{free_port()}"
    result = run(tmp_path, {"zmq": {"poses": endpoint, "detections": endpoint}})
    check_refused(result, f"mocapd: zmq.detections: {endpoint}: address already in use")


@pytest.mark.slow
@pytest.mark.parametrize(
    ("endpoint", "why"),
    [
        ("hello", "invalid argument"),
        ("udp://127.0.0.1:5999", "the protocol is not compatible with the socket type"),
    ],
)
def test_an_endpoint_zeromq_cannot_take(tmp_path: Path, endpoint: str, why: str) -> None:
    check_refused(run(tmp_path, {"zmq": {"poses": endpoint}}), f"mocapd: zmq.poses: {endpoint}: {why}")


def test_a_port_past_65535_is_refused_before_anything_binds(tmp_path: Path) -> None:
    """libzmq takes a port modulo 65536: ``:99999`` bound 34463 and the daemon said it was online
    (issue 32). The configuration refuses it, naming the field."""
    result = run(tmp_path, {"zmq": {"poses": "tcp://127.0.0.1:99999"}})
    check_refused(
        result,
        f"mocapd: {tmp_path / 'daemon.yaml'}: zmq.poses: tcp://127.0.0.1:99999: the port must be in "
        "1..65535 (or 0 or * to bind any free port), got '99999'",
    )


def test_a_host_to_connect_to_that_does_not_resolve(tmp_path: Path) -> None:
    """ZeroMQ connects in the background and retried a host that does not exist for ever, the
    daemon saying it was online (issue 32): it is refused at start, naming the setting."""
    spec = "connect tcp://no-such-host.invalid:5555"
    result = run(tmp_path, {"zmq": {"poses": spec}})
    line = result.stderr.splitlines()[-1] if result.stderr else ""
    assert line.startswith(f"mocapd: zmq.poses: {spec}: cannot resolve 'no-such-host.invalid': "), (
        result.stderr
    )
    check_refused(result, line)


def test_a_free_port_is_bound_and_said(tmp_path: Path) -> None:
    """``:0`` (and ZeroMQ's ``:*``) binds any free port; the "online" log line says which, so that a
    client can find it (it used to say nothing), and the daemon takes poses there."""
    daemon = Daemon(
        tmp_path, config={"zmq": {"poses": "tcp://127.0.0.1:0", "detections": "tcp://127.0.0.1:*"}}
    )
    try:
        daemon.start()
        (online,) = [e for e in daemon.logs() if e["event"] == "online"]
        poses, detections = online["endpoints"]["zmq.poses"], online["endpoints"]["zmq.detections"]
        for endpoint in (poses, detections):
            host, port = endpoint.removeprefix("tcp://").rsplit(":", 1)
            assert host == "127.0.0.1" and 0 < int(port) < 65536, endpoint
        assert poses != detections
        collector = ZmqCollector(detections)
        try:
            out = finished(replay(HDM_ASF, HDM_AMC, f"zmq+{poses}", stream="free"))
            assert out.startswith("replayed 140 frames")
            wait_for(lambda: daemon.metrics().get("mocapd_frames_in_total") == 140, 30, "the poses taken in")
            assert daemon.stop() == 0  # the stream flushed: its squat published on the free port
            wait_for(lambda: bool(collector.detections()), 10, "the detection on the free port")
        finally:
            collector.close()
    finally:
        daemon.stop()


def test_run_replay_needs_a_poses_port_it_can_send_to(tmp_path: Path) -> None:
    """``run --replay`` sends to ``zmq.poses`` as configured, so a free port there is refused."""
    config = tmp_path / "daemon.yaml"
    config.write_text(json.dumps({"zmq": {"poses": "tcp://127.0.0.1:0"}, "metrics": {"port": 0}}))
    result = mocapd("--config", config, "run", "--replay", HDM_ASF, HDM_AMC, timeout=60)
    assert assert_one_error_line(result) == (
        "mocapd: --replay: replays into zmq.poses, which binds any free port (tcp://127.0.0.1:0)"
    )


def test_metrics_port_in_use(tmp_path: Path, taken: int) -> None:
    result = run(tmp_path, {"metrics": {"port": taken}})
    check_refused(result, f"mocapd: metrics.port: 127.0.0.1:{taken}: address already in use")


def test_curve_key_file_missing(tmp_path: Path) -> None:
    missing = tmp_path / "nope.key_secret"
    result = run(tmp_path, {"zmq": {"curve_secret_key_file": str(missing)}})
    assert result.stderr.splitlines()[-1].startswith(f"mocapd: zmq.curve_secret_key_file: {missing}: ")
    check_refused(result, result.stderr.splitlines()[-1])


@pytest.mark.slow
def test_a_second_daemon_of_one_instance_is_refused(tmp_path: Path) -> None:
    """Two daemons with one instance name on one broker used to take each other's client id in
    turn (30 reconnects each in 15 s, health flapping): the second is refused at start, with one
    line, and the first serves on undisturbed; a daemon killed (its retained status still says
    online) does not keep a new one out: a dead daemon answers no probe."""
    broker = Broker(tmp_path).start()
    config: dict[str, dict[str, object]] = {"service": {"instance": "twin"}}
    places = [tmp_path / name for name in ("first", "second", "third")]
    for p in places:
        p.mkdir()
    first, second, third = (
        Daemon(p, sources=["mqtt"], sinks=["mqtt"], mqtt=broker.url, config=config) for p in places
    )
    try:
        first.start()
        second.start(wait=False)
        assert second.wait(30) == 2
        assert second.stderr_path.read_text().splitlines()[-1] == (
            f"mocapd: service.instance: 'twin' is served by a live daemon on {broker.url} already "
            "(client id mocapd-twin); give each daemon an instance of its own"
        )
        assert first.alive and first.health() == (200, "ok\n")
        assert first.process is not None
        first.process.kill()
        first.wait(10)
        third.start()  # at once: the broker may not have noticed the first is gone
        assert third.health() == (200, "ok\n")
    finally:
        for d in (first, second, third):
            d.stop()
        broker.stop()


@pytest.mark.slow
def test_a_daemon_without_its_broker_fails_before_online(tmp_path: Path) -> None:
    """An MQTT daemon whose broker does not answer said "online" and retried for ever (issue 32):
    after ``mqtt.startup_s`` (10 s) without a connection it ends with status 2 and one line naming
    ``mqtt.url`` and the last error. (Once it has been online, it reconnects for ever:
    test_service.py.)"""
    url = f"mqtt://127.0.0.1:{free_port()}"
    result = run(tmp_path, {"service": {"sources": ["mqtt"], "sinks": ["mqtt"]}, "mqtt": {"url": url}})
    check_refused(
        result,
        f"mocapd: mqtt.url: {url}: no connection within 10 s (mqtt.startup_s): "
        "[Errno 111] Connection refused",
    )


def twins(tmp_path: Path, broker: Broker, *names: str) -> list[Daemon]:
    """Daemons of the one instance ``twin`` over ``broker``, each in a directory of its own."""
    out = []
    for name in names:
        (tmp_path / name).mkdir()
        config = {"service": {"instance": "twin"}}
        out.append(Daemon(tmp_path / name, sources=["mqtt"], sinks=["mqtt"], mqtt=broker.url, config=config))
    return out


def takeovers(broker: Broker) -> int:
    """How often the broker gave a client id that was connected to another connection."""
    return (broker.where / "mosquitto.log").read_text().count("already connected, closing old connection")


def refused_line(daemon: Daemon) -> str:
    """The last line of a daemon that ended with status 2, which names service.instance."""
    assert daemon.process is not None and daemon.process.returncode == 2, daemon.stderr_path.read_text()
    line = daemon.stderr_path.read_text().splitlines()[-1]
    assert line.startswith("mocapd: service.instance: 'twin' is "), line
    assert line.endswith("; give each daemon an instance of its own"), line
    return line


def one_of_two(tmp_path: Path, broker: Broker, gap_s: float, names: tuple[str, str]) -> None:
    """Start two daemons of one instance ``gap_s`` apart: one serves, the other is refused before
    it is online, and nothing takes the client id from the one that serves."""
    daemons = twins(tmp_path, broker, *names)
    try:
        daemons[0].start(wait=False)
        time.sleep(gap_s)
        daemons[1].start(wait=False)
        wait_for(lambda: not all(d.alive for d in daemons), 30, "one of the two to be refused")
        (refused,) = [d for d in daemons if not d.alive]
        (serving,) = [d for d in daemons if d.alive]
        refused_line(refused)
        assert not [e for e in refused.logs() if e["event"] in ("online", "mqtt connected")]
        wait_for(lambda: serving.health() == (200, "ok\n"), 30, "the other to serve")
        time.sleep(2.0)  # long enough for a few of the old fight's reconnects
        assert serving.alive and serving.health() == (200, "ok\n")
        assert [e["event"] for e in serving.logs()].count("mqtt connected") == 1
        assert takeovers(broker) == 0
    finally:
        for d in daemons:
            d.stop()


@pytest.mark.slow
@pytest.mark.parametrize("gap_s", [0.0, 0.1, 0.2, 0.4])
def test_two_daemons_of_one_instance_started_together(tmp_path: Path, gap_s: float) -> None:
    """Two daemons of one instance started 0-0.4 s apart on one broker both ran and took each other's
    client id for ever, two reconnects a second each (issue 32): both asked before either answered.
    Now exactly one serves and the other is refused with one line. Twice per gap: how far apart
    the two ask depends on how long each takes to start."""
    broker = Broker(tmp_path).start()
    try:
        one_of_two(tmp_path, broker, gap_s, ("first", "second"))
        one_of_two(tmp_path, broker, gap_s, ("third", "fourth"))
    finally:
        broker.stop()


@pytest.mark.slow
def test_a_daemon_whose_client_id_is_taken_over_does_not_fight_for_it(tmp_path: Path) -> None:
    """A daemon that cannot answer (here stopped with SIGSTOP; a host cut off from the broker is
    the same) lets a second daemon of its instance start, which takes its client id. When the first
    went on, the two took it from each other for ever (issue 32). Now the one started later gives
    way at once (status 2, one line), the first serves on with its own status retained, and the
    client id stays where it is."""
    broker = Broker(tmp_path).start()
    first, second = twins(tmp_path, broker, "first", "second")
    watcher = None
    try:
        first.start()
        watcher = MqttCollector(broker.url, ["mocapd/twin/status"], client_id="status-watcher")
        wait_for(lambda: bool(watcher.statuses()), 10, "the first's status")
        started = watcher.statuses()[-1]["started"]
        first.signal(signal.SIGSTOP)
        try:
            second.start()  # the first answers nothing: the second serves, with the client id
        finally:
            first.signal(signal.SIGCONT)
        wait_for(lambda: not second.alive, 30, "the second to give way")
        line = refused_line(second)
        assert "is served by another live daemon" in line, line
        wait_for(lambda: first.health() == (200, "ok\n"), 30, "the first to serve again")
        settled = takeovers(broker)
        time.sleep(2.0)
        assert first.alive and first.health() == (200, "ok\n")
        assert takeovers(broker) == settled
        last = watcher.statuses()[-1]
        assert (last["state"], last["started"]) == ("online", started)
    finally:
        if watcher is not None:
            watcher.close()
        for d in (first, second):
            d.stop()
        broker.stop()


def test_a_forged_claim_does_not_stop_a_live_daemon(tmp_path: Path) -> None:
    """One message must not stop a daemon: a claim on its instance's ping and pong topics that
    would beat its own (live, and started at the epoch), from a client that is no daemon and took
    no client id, is logged and ignored while the daemon's connection is not contested."""
    import msgpack
    import paho.mqtt.client as paho
    from paho.mqtt.enums import CallbackAPIVersion

    broker = Broker(tmp_path).start()
    (daemon,) = twins(tmp_path, broker, "only")
    client = paho.Client(CallbackAPIVersion.VERSION2, client_id="forger")
    ranks: list[str] = []
    client.on_message = lambda c, u, m: ranks.append(msgpack.unpackb(m.payload)["rank"])
    client.connect("127.0.0.1", broker.port)
    client.subscribe("mocapd/twin/pong", qos=1)
    client.loop_start()
    try:
        daemon.start()
        claim = {
            "v": 1,
            "instance": "twin",
            "client_id": "mocapd-twin",
            "rank": "0" * 17 + "-forged",
            "live": True,
        }
        client.publish("mocapd/twin/ping", msgpack.packb({**claim, "type": "ping"}), qos=1).wait_for_publish(
            10
        )
        wait_for(lambda: bool(ranks), 10, "the daemon's answer to the forged ping")
        pong = {**claim, "type": "pong", "to": ranks[0]}
        client.publish("mocapd/twin/pong", msgpack.packb(pong), qos=1).wait_for_publish(10)
        time.sleep(1.0)
        assert daemon.alive and daemon.health() == (200, "ok\n")
        assert [e for e in daemon.logs() if e["event"] == "claim ignored"]
        assert daemon.stop() == 0
    finally:
        client.loop_stop()
        client.disconnect()
        daemon.stop()
        broker.stop()


@pytest.mark.slow
def test_a_second_daemon_on_one_client_id_is_refused(tmp_path: Path) -> None:
    """Two instances given one ``mqtt.client_id`` took it from each other for ever just as two
    daemons of one instance did: the second is refused at start, naming the setting."""
    broker = Broker(tmp_path).start()
    daemons = []
    for name in ("left", "right"):
        (tmp_path / name).mkdir()
        config = {"service": {"instance": name}, "mqtt": {"client_id": "shared"}}
        daemons.append(
            Daemon(tmp_path / name, sources=["mqtt"], sinks=["mqtt"], mqtt=broker.url, config=config)
        )
    left, right = daemons
    try:
        left.start()
        right.start(wait=False)
        assert right.wait(30) == 2
        assert right.stderr_path.read_text().splitlines()[-1] == (
            f"mocapd: mqtt.client_id: 'shared' is the client id of a daemon of instance 'left' on "
            f"{broker.url} already; give each daemon a client id of its own"
        )
        assert left.alive and left.health() == (200, "ok\n")
        assert takeovers(broker) == 0
    finally:
        for d in daemons:
            d.stop()
        broker.stop()
