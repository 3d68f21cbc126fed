"""A capture session's disruptions, survived (issue 21): a real mosquitto, real ``mocapd run`` and
``mocapd replay`` processes, disrupted on a schedule, and what came out checked.

    python -m bench.chaos [--seconds 300] [--streams 10] [--every 20] [--storm 100000] [--data DIR]

Set-up: mosquitto on a loopback port (persistence on), ``mocapd run`` over MQTT (``idle_s`` 3,
per-stream metric labels), ``--streams`` looping real-time replays of short HDM05 clips (a squat, a
hop, an elbow-to-knee, a kick), each its own stream, and a subscriber of every detection, skeleton
and status. Every ``--every`` seconds one disruption, in turn (``--seconds`` / ``--every`` - 1 of them,
all made even when a loaded machine makes them late):

* ``daemon SIGTERM`` and ``daemon kill -9``: the daemon stopped, and started again at once;
* ``broker restart``: mosquitto stopped and started again on its port;
* ``publisher pause``: one replay stopped (SIGSTOP) for twice ``idle_s``, so the daemon forgets it;
* ``publisher restart``: one replay ended and started again: a new run, numbered from its start;
* ``garbage flood``: ``--flood`` undecodable messages on one stream's pose topic.

Then a storm of ``--storm`` distinct stream ids (in up to 10 rounds: a pose of each, no skeleton; every
100th announces a skeleton first) beside the live streams, each round forgotten before the next:
the daemon's streams and per-stream series must be back where they were, and its memory must not
grow from round to round (see :attr:`Outcome.rss_rounds`).

Measured per disruption, from when things are *back* (the new daemon's metrics port answers, the
broker listens, the publisher's new run's skeleton reaches the broker, SIGCONT, the flood's last
message sent) for every stream concerned (all for the daemon and the broker, one otherwise): the
time until the daemon takes the stream's poses again (its ``frames_in`` series grows), and until
its first detection of poses sent after the disruption began was published.

Checked, per stream, in every span it is left alone — from ``SETTLE_S`` after it is back to
``hold_s`` + :data:`SLACK_S` before the next disruption concerning it (more when the stream's
detections arrived later than that after their poses were sent, on a loaded machine: a motion
ending later would be published after the disruption began, and a kill loses it by design): the
detections equal ``mocapd detect``'s
on the same frames (the looped clip's poses by sequence number, from ``CONTEXT_S`` before the span
but never before the run's first pose, decimated in the phase the daemon's detections show). Also
counted: ids delivered more than once (QoS 1 may), and one motion published under two ids (never
allowed).
"""

from __future__ import annotations

import argparse
import getpass
import math
import shutil
import signal
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from collections import Counter, defaultdict
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import msgpack
import numpy as np

from bench.common import DATA
from bench.machine import describe
from bench.processes import free_port, listening, rss_kib, scrape
from daemon.features import decimation_factor
from daemon.library import Library, default_library_path, load_library
from daemon.recognizer import detect_positions
from daemon.recordings import read_recording
from daemon.types import DEFAULT_HOLD_S, FloatArray, RecognitionSettings
from protocols.messages import PoseMessage, SkeletonMessage, encode
from replay import JOINT_NAMES
from replay.kinematics import joint_positions

MOCAPD = Path(sys.executable).parent / "mocapd"
RATE = 120.0
CLIPS = ("squat1Reps", "hopBothLegs1hops", "elbowToKnee1RepsLelbowStart", "kickLFront1Reps")
KINDS = (
    "daemon SIGTERM",
    "daemon kill -9",
    "broker restart",
    "publisher pause",
    "publisher restart",
    "garbage flood",
)
CONTEXT_S = 4.0
"""Frames before a checked span that the reference sees (longer than any template's match)."""
SETTLE_S = CONTEXT_S + 1.5
"""A checked span starts this long after the stream is back: the daemon must have its frames from
``CONTEXT_S`` before the span, so it has 1.5 s to recover."""
SLACK_S = 1.0
"""A checked span ends ``hold_s`` + this before the next disruption at least, or ``hold_s`` +
:data:`AFTER_LAG_S` more than the worst lag (a detection's arrival after its pose was sent) seen
in the span and up to the disruption."""
AFTER_LAG_S = 0.5
GIVE_UP_S = 30.0
GARBAGE = b"\xc1" * 400
"""Not msgpack, a pose's size."""


@dataclass(frozen=True)
class Plan:
    streams: int = 10
    seconds: float = 300.0
    every: float = 20.0
    idle_s: float = 3.0
    hold_s: float = DEFAULT_HOLD_S
    flood: int = 20_000
    storm: int = 100_000
    data: Path = DATA


@dataclass
class Disruption:
    kind: str
    streams: tuple[str, ...]
    """The streams it concerns."""
    at: float
    back: float
    """Wall-clock seconds: when it began, when things were back."""
    taken: dict[str, float] = field(default_factory=dict)
    """Per stream: seconds from ``back`` until the daemon took its poses again."""
    detected: dict[str, float] = field(default_factory=dict)
    """Per stream: seconds from ``back`` until its first detection arrived."""

    @property
    def survived(self) -> bool:
        return set(self.taken) == set(self.streams) and set(self.detected) == set(self.streams)


@dataclass(frozen=True)
class Span:
    """One stream's frames ``first``…``last`` (sequence numbers) left alone, and its detections."""

    stream: str
    first: int
    last: int
    expected: frozenset[tuple[str, int, int]]
    got: frozenset[tuple[str, int, int]]
    lag: float
    """The worst seconds from a pose sent to the detection it emitted arriving, from the span's
    start to the next disruption (0: none arrived)."""
    straddling: frozenset[tuple[str, int, int]] = frozenset()
    """Detections of the run overlapping the span's frames but not within them (not checked: said
    when the span differs, to tell a missing motion from one whose frames moved)."""


@dataclass(frozen=True)
class Outcome:
    plan: Plan
    disruptions: list[Disruption]
    spans: list[Span]
    detections: int
    redelivered: int
    """Ids that arrived more than once (QoS 1 allows it; a consumer drops the repeat)."""
    doubled: int
    """Motions (stream, run, class, frames) published under more than one id."""
    rss_live: float
    """The daemon's resident memory (MiB) before the storm, all streams up."""
    rss_rounds: list[float]
    """Its resident memory after each round of the storm. The first round fills the intake queue
    with messages of distinct streams and the table with streams, and the allocator keeps some of
    what that peak took (+3 to +4 MiB, two CPU-bound processes beside it): the rounds after it are
    the measure (:attr:`rss_growth`); memory that grew with the ids would grow round after round,
    as the front's cache of routes did until it was bounded by the streams the workers may hold
    (+2.5 MiB a round up to 100,000 topics)."""
    streams_live: int
    streams_after_storm: int
    series_after_storm: int
    """Per-stream ``frames_in`` series on /metrics after the storm."""
    storm_refused: int

    @property
    def rss_after_storm(self) -> float:
        return self.rss_rounds[-1]

    @property
    def rss_growth(self) -> float:
        """The last round's memory over the second's (the first round's peak aside)."""
        return self.rss_after_storm / self.rss_rounds[min(1, len(self.rss_rounds) - 1)]

    @property
    def ok(self) -> bool:
        return (
            all(d.survived for d in self.disruptions)
            and all(s.expected == s.got for s in self.spans)
            and self.doubled == 0
            and self.streams_after_storm == self.streams_live == self.series_after_storm
            and self.rss_growth <= 1.1
        )


# ------------------------------------------------------------------------------------ processes


def wait(condition: Callable[[], bool], timeout: float, step: float = 0.02) -> bool:
    deadline = time.monotonic() + timeout
    while not condition():
        if time.monotonic() > deadline:
            return False
        time.sleep(step)
    return True


def clip_files(data: Path, name: str) -> tuple[Path, Path]:
    return (
        data / "hdm05" / "asf" / "HDM_bd.asf",
        data / "hdm05" / "cut" / name / f"HDM_bd_{name}_001_120.amc.gz",
    )


class Broker:
    def __init__(self, where: Path) -> None:
        self.port = free_port()
        self.config = where / "mosquitto.conf"
        self.config.write_text(
            f"listener {self.port} 127.0.0.1\nallow_anonymous true\nset_tcp_nodelay true\n"
            f"persistence true\npersistence_location {where}/\nmax_queued_messages 200000\n"
            f"log_dest none\nuser {getpass.getuser()}\n",
            encoding="utf-8",
        )
        self.url = f"mqtt://127.0.0.1:{self.port}"
        self.process: subprocess.Popen[bytes] | None = None

    def start(self) -> None:
        binary = shutil.which("mosquitto") or "/usr/sbin/mosquitto"
        self.process = subprocess.Popen(
            [binary, "-c", str(self.config)], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL
        )
        if not wait(lambda: listening(self.port), 10):
            raise RuntimeError("mosquitto did not start")

    def stop(self) -> None:
        if self.process is not None and self.process.poll() is None:
            self.process.terminate()
            self.process.wait(10)


class DaemonProcess:
    def __init__(self, where: Path, plan: Plan, broker: str) -> None:
        self.metrics_port = free_port()
        self.config = where / "daemon.yaml"
        self.config.write_text(
            yaml_text(
                {
                    "service": {
                        "instance": "chaos",
                        "sources": ["mqtt"],
                        "sinks": ["mqtt"],
                        "idle_s": plan.idle_s,
                        "max_streams": 100,
                    },
                    "recognizer": {"hold_s": plan.hold_s},
                    "mqtt": {"url": broker, "reconnect_max_s": 0.5},
                    "metrics": {"port": self.metrics_port, "stream_labels": True},
                }
            ),
            encoding="utf-8",
        )
        self.err = where / "daemon.err"
        self.process: subprocess.Popen[bytes] | None = None

    def start(self) -> None:
        with self.err.open("ab") as err:
            self.process = subprocess.Popen(
                [str(MOCAPD), "run", "--config", str(self.config)], stdout=subprocess.DEVNULL, stderr=err
            )
        if not wait(self.answers, 30):
            raise RuntimeError(f"the daemon did not start: {self.err.read_text()[-800:]}")

    def answers(self) -> bool:
        try:
            self.metrics()
        except OSError:
            return False
        return True

    def stop(self, sig: int = signal.SIGTERM) -> None:
        if self.process is not None and self.process.poll() is None:
            self.process.send_signal(sig)
            self.process.wait(30)

    def metrics(self) -> dict[str, float]:
        return scrape(self.metrics_port)

    def taken(self, stream: str) -> float:
        try:
            return self.metrics().get(f'mocapd_frames_in_total{{stream="{stream}"}}', 0.0)
        except OSError:
            return 0.0

    def rss_mib(self) -> float:
        assert self.process is not None
        return rss_kib(self.process.pid) / 1024


def yaml_text(config: dict[str, Any]) -> str:
    import yaml

    text: str = yaml.safe_dump(config)
    return text


class Replay:
    def __init__(self, asf: Path, amc: Path, to: str, stream: str) -> None:
        self.args = [
            str(MOCAPD), "replay", "--asf", str(asf), "--amc", str(amc), "--to", to,
            "--stream", stream, "--loop", "--speed", "1",
        ]  # fmt: skip
        self.process: subprocess.Popen[bytes] | None = None
        self.started: list[float] = []
        """When each run began (wall clock): a pose sent after belongs to it."""

    def start(self) -> None:
        self.started.append(time.time())
        self.process = subprocess.Popen(self.args, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)

    def stop(self) -> None:
        if self.process is not None and self.process.poll() is None:
            self.process.send_signal(signal.SIGCONT)
            self.process.terminate()
            try:
                self.process.wait(30)
            except subprocess.TimeoutExpired:  # still draining to a broker that is slow to take it
                self.process.kill()
                self.process.wait(10)

    def run_of(self, when: float) -> int:
        """The run that sent a pose at ``when``."""
        return max(0, sum(1 for t in self.started if t <= when) - 1)


class Listener:
    """Every detection, the first arrival of every run's skeleton, over a persistent session."""

    def __init__(self, url: str) -> None:
        import paho.mqtt.client as paho
        from paho.mqtt.enums import CallbackAPIVersion

        host, port = url.removeprefix("mqtt://").split(":")
        self.lock = threading.Lock()
        self.detections: list[tuple[float, dict[str, Any]]] = []
        self.skeletons: dict[tuple[str, str], float] = {}
        self.client = paho.Client(
            CallbackAPIVersion.VERSION2, client_id="chaos-listener", clean_session=False
        )
        self.client.reconnect_delay_set(1, 1)
        self.client.on_connect = self._connect_answered
        self.client.on_message = self._message_arrived
        self.client.connect(host, int(port))
        self.client.loop_start()

    @staticmethod
    def _connect_answered(client: Any, userdata: Any, flags: Any, reason: Any, properties: Any) -> None:
        client.subscribe([("mocap/+/detections", 1), ("mocap/+/skeleton", 1)])

    def _message_arrived(self, client: Any, userdata: Any, message: Any) -> None:
        now = time.time()
        if not message.payload:
            return
        body = msgpack.unpackb(message.payload, raw=False)
        with self.lock:
            if body.get("type") == "detection":
                self.detections.append((now, body))
            else:
                self.skeletons.setdefault((body["stream"], str(body.get("epoch"))), now)

    def first_detection(self, stream: str, since: float) -> float | None:
        """When the daemon published its first detection of ``stream``'s poses sent ``since``."""
        with self.lock:
            times = [
                d["emit_time"]
                for _, d in self.detections
                if d["stream"] == stream and d["source_time"] >= since
            ]
        return min(times, default=None)

    def new_skeleton(self, stream: str, after: float) -> float | None:
        with self.lock:
            return next((t for (s, _), t in self.skeletons.items() if s == stream and t > after), None)

    def close(self) -> None:
        self.client.loop_stop()
        self.client.disconnect()


@contextmanager
def sender(url: str, name: str) -> Iterator[Any]:
    """A plain MQTT publisher (QoS 0)."""
    import paho.mqtt.client as paho
    from paho.mqtt.enums import CallbackAPIVersion

    host, port = url.removeprefix("mqtt://").split(":")
    client = paho.Client(CallbackAPIVersion.VERSION2, client_id=name)
    client.max_queued_messages_set(0)
    client.connect(host, int(port))
    client.loop_start()
    try:
        yield client
    finally:
        client.loop_stop()
        client.disconnect()


def publish_all(client: Any, messages: Iterator[tuple[str, bytes]]) -> None:
    last = None
    for t, payload in messages:
        last = client.publish(t, payload, qos=0)
    if last is not None:
        last.wait_for_publish(60)


# ---------------------------------------------------------------------------------- reference


@dataclass(frozen=True)
class Clip:
    first: int
    positions: FloatArray
    """Joint positions shape ``(N, 26, 3)`` of the clip; a looping replay's pose ``seq`` is row
    ``(seq - first) % N``."""


def reference(
    clip: Clip, library: Library, first: int, last: int, phase: int, step: int, hold_s: float
) -> frozenset[tuple[str, int, int]]:
    """``mocapd detect``'s detections (class, start, end) lying in frames ``first``…``last`` of the
    looping clip, seen from ``CONTEXT_S`` before (decimated in ``phase`` modulo ``step``) to
    ``hold_s`` + ``CONTEXT_S`` after, but never from before the run's first pose: every run of a
    replay begins at the clip's first frame number, and the daemon saw nothing before it (a
    replay that started late, on a loaded machine, leaves less context than ``CONTEXT_S`` before a
    span, or none)."""
    lo = first - int(CONTEXT_S * RATE)
    lo -= (lo - phase) % step
    lo = max(lo, clip.first)
    numbers = np.arange(lo, last + int((hold_s + CONTEXT_S) * RATE), dtype=np.int64)
    positions = clip.positions[(numbers - clip.first) % len(clip.positions)]
    found = detect_positions(positions, numbers, library, RATE, settings=RecognitionSettings(hold_s=hold_s))
    return frozenset(
        (d.class_name, d.start_frame, d.end_frame)
        for d in found
        if d.start_frame >= first and d.end_frame <= last
    )


# ------------------------------------------------------------------------------------ the run


def run(plan: Plan, say: Callable[[str], None] = lambda _: None) -> Outcome:
    library = load_library(default_library_path())
    clips = {}
    for name in CLIPS:
        motion = read_recording(*clip_files(plan.data, name))
        clips[name] = Clip(int(motion.frames[0]), joint_positions(motion))
    streams = {f"s{k}": CLIPS[k % len(CLIPS)] for k in range(plan.streams)}
    disruptions: list[Disruption] = []
    with tempfile.TemporaryDirectory() as tmp:
        where = Path(tmp)
        broker = Broker(where)
        broker.start()
        listener = Listener(broker.url)
        daemon = DaemonProcess(where, plan, broker.url)
        replays = {s: Replay(*clip_files(plan.data, name), broker.url, s) for s, name in streams.items()}
        try:
            daemon.start()
            begin = time.time()
            for r in replays.values():
                r.start()
            # up when the last replay's skeleton reached the broker: starting them takes seconds on a
            # loaded machine, and the first spans must not begin before the streams did
            wait(lambda: all(listener.new_skeleton(s, begin) is not None for s in streams), GIVE_UP_S)
            up = max(listener.new_skeleton(s, begin) or time.time() for s in streams)
            start = Disruption("start", tuple(streams), begin, up)
            measure(start, daemon, listener, base={})
            disruptions.append(start)
            began = time.monotonic()
            # a count, each due ``every`` s after the last: on a loaded machine they run late (a
            # daemon restart takes seconds), and a schedule by the clock would leave some out
            for k in range(disruptions_in(plan)):
                time.sleep(max(0.0, began + (k + 1) * plan.every - time.monotonic()))
                kind = KINDS[k % len(KINDS)]
                target = f"s{(k * 3) % plan.streams}"
                d = disrupt(kind, target, plan, broker, daemon, replays, listener)
                disruptions.append(d)
                which = ",".join(d.streams) if len(d.streams) < 3 else "all"
                taken = max(d.taken.values(), default=math.nan)
                say(
                    f"[{time.monotonic() - began:5.0f} s] {kind:18s} {which}: poses taken after {taken:.2f} s"
                )
            time.sleep(plan.hold_s + 1.5)
            end = time.time()
            streams_live = int(daemon.metrics()["mocapd_streams"])
            rss_live = daemon.rss_mib()
            refused, rss_rounds = storm(plan, broker.url, daemon)
            m = daemon.metrics()
            series = sum(1 for key in m if key.startswith("mocapd_frames_in_total{stream="))
            streams_after = int(m["mocapd_streams"])
        finally:
            for r in replays.values():
                r.stop()
            daemon.stop()
            listener.close()
            broker.stop()
    spans = check(plan, disruptions, end, streams, replays, listener.detections, clips, library)
    ids = Counter(det["id"] for _, det in listener.detections)
    motions: dict[tuple[Any, ...], set[str]] = defaultdict(set)
    for _, det in listener.detections:
        run_ = replays[det["stream"]].run_of(det["source_time"])
        motions[(det["stream"], run_, det["class"], det["start_frame"], det["end_frame"])].add(det["id"])
    return Outcome(
        plan,
        disruptions,
        spans,
        detections=len(ids),
        redelivered=sum(1 for n in ids.values() if n > 1),
        doubled=sum(1 for v in motions.values() if len(v) > 1),
        rss_live=rss_live,
        rss_rounds=rss_rounds,
        streams_live=streams_live,
        streams_after_storm=streams_after,
        series_after_storm=series,
        storm_refused=refused,
    )


def disruptions_in(plan: Plan) -> int:
    """How many disruptions a run makes: one every ``plan.every`` s of ``plan.seconds``, the first
    after ``every`` s and the last ``every`` s before the end."""
    return max(0, math.floor(plan.seconds / plan.every + 1e-9) - 1)


def disrupt(
    kind: str,
    target: str,
    plan: Plan,
    broker: Broker,
    daemon: DaemonProcess,
    replays: dict[str, Replay],
    listener: Listener,
) -> Disruption:
    everyone = tuple(replays)
    at = time.time()
    base: dict[str, float] = {}
    if kind in ("daemon SIGTERM", "daemon kill -9"):
        daemon.stop(signal.SIGTERM if kind == "daemon SIGTERM" else signal.SIGKILL)
        daemon.start()
        concerned = everyone
    elif kind == "broker restart":
        broker.stop()
        broker.start()
        concerned = everyone
        base = {s: daemon.taken(s) for s in concerned}
    elif kind == "publisher pause":
        process = replays[target].process
        assert process is not None
        process.send_signal(signal.SIGSTOP)
        time.sleep(2 * plan.idle_s)
        concerned = (target,)
        process.send_signal(signal.SIGCONT)
    elif kind == "publisher restart":
        replays[target].stop()
        replays[target].start()
        concerned = (target,)
        base = {target: daemon.taken(target)}
        if not wait(lambda: listener.new_skeleton(target, at) is not None, GIVE_UP_S):
            return Disruption(kind, concerned, at, time.time())
        back = listener.new_skeleton(target, at)
        assert back is not None
        d = Disruption(kind, concerned, at, back)
        measure(d, daemon, listener, base)
        return d
    else:
        concerned = (target,)
        with sender(broker.url, "chaos-flood") as client:
            publish_all(client, ((f"mocap/{target}/pose", GARBAGE) for _ in range(plan.flood)))
        base = {target: daemon.taken(target)}
    d = Disruption(kind, concerned, at, time.time())
    measure(d, daemon, listener, base)
    return d


def measure(d: Disruption, daemon: DaemonProcess, listener: Listener, base: dict[str, float]) -> None:
    """Fill ``d.taken`` and ``d.detected`` (within :data:`GIVE_UP_S`)."""
    deadline = d.back + GIVE_UP_S
    while time.time() < deadline and len(d.taken) < len(d.streams):
        for s in d.streams:
            if s not in d.taken and daemon.taken(s) > base.get(s, 0.0):
                d.taken[s] = time.time() - d.back
        time.sleep(0.02)
    while time.time() < deadline and len(d.detected) < len(d.streams):
        for s in d.streams:
            t = listener.first_detection(s, d.at)
            if s not in d.detected and t is not None:
                d.detected[s] = max(0.0, t - d.back)  # 0: during the flood
        time.sleep(0.05)


def storm(plan: Plan, url: str, daemon: DaemonProcess) -> tuple[int, list[float]]:
    """``plan.storm`` distinct stream ids in up to 10 rounds, each left to be forgotten: the poses
    refused for want of a skeleton or of room, and the daemon's RSS (MiB) after each round."""
    rounds = max(1, min(10, plan.storm // 10_000))
    per = plan.storm // rounds
    joints = np.zeros((len(JOINT_NAMES), 3), np.float32)

    def messages(r: int) -> Iterator[tuple[str, bytes]]:
        for k in range(per):
            name = f"storm-{r}-{k}"
            if k % 100 == 0:
                yield f"mocap/{name}/skeleton", encode(SkeletonMessage(name, RATE, JOINT_NAMES))
            yield f"mocap/{name}/pose", encode(PoseMessage(name, 1, time.time(), positions=joints))

    def refused() -> float:
        m = daemon.metrics()
        return sum(
            m.get(f'mocapd_rejects_total{{reason="{r}"}}', 0) for r in ("no_skeleton", "too_many_streams")
        )

    def streams() -> float:
        return daemon.metrics().get("mocapd_streams", 0.0)

    before, live = refused(), streams()
    rss = []
    with sender(url, "chaos-storm") as client:
        for r in range(rounds):
            publish_all(client, messages(r))
            time.sleep(plan.idle_s)
            # forgotten: idle_s after the daemon took the round's last message, which a loaded
            # machine delays by seconds (within GIVE_UP_S, or the outcome says how many are left)
            wait(lambda: streams() <= live, GIVE_UP_S, step=0.2)
            time.sleep(2.0)  # the housekeeping gives the memory back
            rss.append(daemon.rss_mib())
    return int(refused() - before), rss


def check(
    plan: Plan,
    disruptions: list[Disruption],
    end: float,
    streams: dict[str, str],
    replays: dict[str, Replay],
    detections: list[tuple[float, dict[str, Any]]],
    clips: dict[str, Clip],
    library: Library,
) -> list[Span]:
    """Per stream, each span it was left alone: the detections against ``mocapd detect``'s."""
    step = decimation_factor(RATE, library.rate)
    by_run: dict[tuple[str, int], list[tuple[float, dict[str, Any]]]] = defaultdict(list)
    for arrived, det in detections:
        by_run[(det["stream"], replays[det["stream"]].run_of(det["source_time"]))].append((arrived, det))
    spans = []
    for s, name in streams.items():
        mine = [d for d in disruptions if s in d.streams]
        for d, following in zip(mine, [*mine[1:], None], strict=True):
            t0 = d.back + SETTLE_S
            until = following.at if following else end
            run_ = replays[s].run_of(t0)
            found = [x for _, x in by_run[(s, run_)]]
            lag = max((a - x["source_time"] for a, x in by_run[(s, run_)] if t0 <= a < until), default=0.0)
            t1 = until - plan.hold_s - max(SLACK_S, lag + AFTER_LAG_S)
            if t1 - t0 < 1.0 or not found:
                continue
            # a pose's sequence number from its send time, by the run's detections (robust to a burst)
            offset = statistics.median(x["emitted_at_frame"] - RATE * x["source_time"] for x in found)
            first, last = math.ceil(RATE * t0 + offset), math.floor(RATE * t1 + offset)
            got = frozenset(
                (x["class"], x["start_frame"], x["end_frame"])
                for x in found
                if x["start_frame"] >= first and x["end_frame"] <= last
            )
            straddling = (
                frozenset(
                    (x["class"], x["start_frame"], x["end_frame"])
                    for x in found
                    if x["start_frame"] <= last and x["end_frame"] >= first
                )
                - got
            )
            phases = Counter(start % step for _, start, _ in got)
            phase = phases.most_common(1)[0][0] if phases else 0
            expected = reference(clips[name], library, first, last, phase, step, plan.hold_s)
            spans.append(Span(s, first, last, expected, got, lag, straddling))
    return spans


# ---------------------------------------------------------------------------------- reporting


def table(outcome: Outcome) -> str:
    def stat(values: list[float]) -> str:
        return f"{statistics.median(values):5.2f} / {max(values):5.2f}" if values else "    - /     -"

    lines = [
        f"{outcome.plan.streams} streams looping in real time for {outcome.plan.seconds:.0f} s, "
        f"{len(outcome.disruptions) - 1} disruptions",
        "",
        "| disruption | survived | poses taken again, s after back (median / worst) "
        "| first detection, s after back (median / worst) |",
        "|---|---|---|---|",
    ]
    for kind in KINDS:
        these = [d for d in outcome.disruptions if d.kind == kind]
        if not these:
            continue
        taken = [v for d in these for v in d.taken.values()]
        detected = [v for d in these for v in d.detected.values()]
        survived = sum(d.survived for d in these)
        lines.append(f"| {kind} | {survived} / {len(these)} | {stat(taken)} | {stat(detected)} |")
    expected = sum(len(s.expected) for s in outcome.spans)
    got = sum(len(s.got) for s in outcome.spans)
    equal = sum(len(s.expected & s.got) for s in outcome.spans)
    wrong = [s for s in outcome.spans if s.expected != s.got]
    seconds = sum(s.last - s.first + 1 for s in outcome.spans) / RATE
    rounds = ", ".join(f"{r:.1f}" for r in outcome.rss_rounds)
    lines += [
        "",
        f"spans left alone: {len(outcome.spans)} ({seconds:.0f} s of frames); detections there: "
        f"expected {expected}, got {got}, equal {equal}; spans that differ: {len(wrong)}; worst lag "
        f"of a detection in a span: {max((s.lag for s in outcome.spans), default=0.0):.2f} s",
        f"detections: {outcome.detections} ids; delivered twice: {outcome.redelivered}; "
        f"one motion under two ids: {outcome.doubled}",
        f"storm of {outcome.plan.storm:,} stream ids ({outcome.storm_refused:,} poses refused): daemon RSS "
        f"{outcome.rss_live:.1f} MiB before, after each round {rounds} MiB (last / second: "
        f"{outcome.rss_growth:.3f})",
        f"streams {outcome.streams_live} before the storm, {outcome.streams_after_storm} after; "
        f"per-stream series after: {outcome.series_after_storm}",
    ]
    for s in wrong[:5]:
        missing, extra = sorted(s.expected - s.got), sorted(s.got - s.expected)
        lines.append(
            f"  {s.stream} {s.first}-{s.last} (lag {s.lag:.2f} s): missing {missing}, extra {extra}, "
            f"straddling its ends {sorted(s.straddling)}"
        )
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    defaults = Plan()
    parser.add_argument("--seconds", type=float, default=defaults.seconds)
    parser.add_argument("--streams", type=int, default=defaults.streams)
    parser.add_argument("--every", type=float, default=defaults.every)
    parser.add_argument("--flood", type=int, default=defaults.flood)
    parser.add_argument("--storm", type=int, default=defaults.storm)
    parser.add_argument("--data", type=Path, default=DATA)
    args = parser.parse_args()
    print(describe(), flush=True)
    plan = Plan(args.streams, args.seconds, args.every, flood=args.flood, storm=args.storm, data=args.data)
    outcome = run(plan, lambda line: print(line, file=sys.stderr, flush=True))
    print(table(outcome))
    sys.exit(0 if outcome.ok else 1)


if __name__ == "__main__":
    main()
