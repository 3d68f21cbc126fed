"""What several test modules share (test modules never import each other): where the real data is,
the clips the tests use, the ``mocapd`` subprocess runner and the checks of its output, and writers
of manifests. The recordings are read in place from ../shared/data/mocap, never copied."""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import getpass
import json
import math
import os
import re
import shutil
import signal
import socket
import subprocess
import sys
import threading
import time
import urllib.error
import urllib.request
from collections import Counter
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from pathlib import Path
from typing import Any, Protocol

import msgpack
import numpy as np

from bench.processes import free_port, json_lines, samples
from daemon.keyframes import parse_keyframe_queries
from daemon.learn.library import learn_class
from daemon.library import ClassTemplate, Library
from daemon.recordings import read_examples, read_recording
from daemon.search.segments import Segment, Segmenter
from daemon.types import BoolArray, FloatArray
from protocols.messages import DetectionMessage, SegmentDetection
from replay import Motion
from replay.catalog import CMU_SUBSTITUTES, recordings
from replay.kinematics import joint_positions

REPO = Path(__file__).resolve().parents[1]
SHARED = REPO.parent / "shared"
DATA = SHARED / "data" / "mocap"
ORACLE = SHARED / "reference" / "oracle"
KEYFRAMES = SHARED / "reference" / "manual-keyframes.json"
"""The published manual keyframes of the toolbox (thesis ch. 5)."""

CMU_ASF = DATA / "cmu" / "02" / "02.asf"
CMU_AMC = DATA / "cmu" / "02" / "02_01.amc.gz"
HDM_ASF = DATA / "hdm05" / "asf" / "HDM_bd.asf"
HDM_AMC = DATA / "hdm05" / "cut" / "squat1Reps" / "HDM_bd_squat1Reps_001_120.amc.gz"
SOURCES = {"cmu": (CMU_ASF, CMU_AMC), "hdm05": (HDM_ASF, HDM_AMC)}

ORACLE_CLIPS = {
    "02_01": ("cmu/02/02.asf", "cmu/02/02_01.amc.gz"),
    "02_05": ("cmu/02/02.asf", "cmu/02/02_05.amc.gz"),
    "13_29": ("cmu/13/13.asf", "cmu/13/13_29.amc.gz"),
    "HDM_bd_squat1Reps_001_120": (
        "hdm05/asf/HDM_bd.asf",
        "hdm05/cut/squat1Reps/HDM_bd_squat1Reps_001_120.amc.gz",
    ),
}
"""The clips the original toolbox's output is stored for (../shared/reference/oracle), paths below DATA."""

MOCAPD_SCRIPT = Path(sys.executable).parent / "mocapd"


# ------------------------------------------------------------------------------------- recordings


def hdm05_clip(actor: str, motion_class: str, take: int) -> tuple[Path, Path]:
    """The (ASF, AMC) of an HDM05 cut clip."""
    amc = DATA / "hdm05" / "cut" / motion_class / f"HDM_{actor}_{motion_class}_{take:03d}_120.amc.gz"
    return DATA / "hdm05" / "asf" / f"HDM_{actor}.asf", amc


INDEX_CLIPS = [
    ("bd", "squat1Reps", 1, 140),
    ("bk", "hopBothLegs1hops", 20, 56),
    ("dg", "rotateArmsBothBackward1Reps", 10, 86),
    ("bd", "kickLFront1Reps", 1, 161),
]
"""(actor, class, take, AMC frames) of a small database: 140, 56, 86 and 161 frames, so the last
index frame of the last two covers fewer than 4 AMC frames."""
INDEX_PATHS = [hdm05_clip(a, c, t) for a, c, t, _ in INDEX_CLIPS]

TRAINING = [("hopBothLegs1hops", "bd", t) for t in (1, 2, 3)] + [("squat1Reps", "bd", t) for t in (1, 2)]
"""(class, actor, take) of a small training set."""

DG_CLIPS = [("dg", "squat1Reps", 25), ("dg", "squat1Reps", 26), ("dg", "hopBothLegs1hops", 22)]
"""A small database of three dg clips (actor, class, take), for building an index."""

CONTROL = re.compile(r"[\x00-\x1f\x7f-\x9f]")
"""Control characters, which no error line may contain."""


def recording_pairs() -> list[tuple[Path, Path]]:
    """Every (ASF, AMC) pair in the shared data (none if it is missing: the ``shared_data`` fixture
    then fails every test with a clear message); subject 14 has no ASF and uses 13.asf (same
    topology)."""
    return recordings(DATA, CMU_SUBSTITUTES) if DATA.is_dir() else []


def pair_id(pair: tuple[Path, Path]) -> str:
    return pair[1].name.removesuffix(".gz").removesuffix(".amc")


def joints_cm(asf: Path, amc: Path) -> FloatArray:
    """The 26 standard joint positions of a recording in centimetres, shape ``(N, 26, 3)``."""
    return joint_positions(read_recording(asf, amc))


@functools.cache
def clip(name: str) -> FloatArray:
    """Joint positions of the recording ``name`` (its :func:`pair_id`), computed once per run."""
    matches = [pair for pair in recording_pairs() if pair_id(pair) == name]
    assert len(matches) == 1, f"no single recording named {name}"
    out = joints_cm(*matches[0])
    out.setflags(write=False)
    return out


def run_segmenter(segmenter: Segmenter, vectors: Iterable[BoolArray]) -> list[Segment]:
    """Every segment the segmenter closes on ``vectors`` (at most one a push), then the one its flush
    closes."""
    closed = [segmenter.push(v) for v in vectors] + [segmenter.flush()]
    assert all(len(c) <= 1 for c in closed)
    return [s for c in closed for s in c]


# --------------------------------------------------------------------------------------- manifests


def write_manifest(path: Path, rows: Sequence[tuple[str | Path, str | Path]], extra: bool = True) -> Path:
    """A manifest ``class,amc,start_frame,asf`` (the required columns among others, out of order), or
    plain ``asf,amc`` without ``extra``."""
    lines = ["class,amc,start_frame,asf"] if extra else ["asf,amc"]
    for asf, amc in rows:
        lines.append(f"x,{amc},1,{asf}" if extra else f"{asf},{amc}")
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")
    return path


def write_training(path: Path, rows: list[str], header: str = "class,asf,amc,start_frame,end_frame") -> Path:
    path.write_text("\n".join([header, *rows]) + "\n", encoding="utf-8")
    return path


def training_rows(items: Sequence[tuple[str, str, int]]) -> list[str]:
    """Training manifest rows (whole clips) of (class, actor, take)."""
    rows = []
    for c, a, t in items:
        asf, amc = hdm05_clip(a, c, t)
        rows.append(f"{c},{asf},{amc},,")
    return rows


# ------------------------------------------------------------------------------ running the command


def mocapd(
    *args: str | Path, script: bool = False, cwd: Path = REPO, timeout: float = 120
) -> subprocess.CompletedProcess[str]:
    """Run ``python -m daemon ARGS`` (or the ``mocapd`` console script) and capture its output."""
    command = [str(MOCAPD_SCRIPT)] if script else [sys.executable, "-m", "daemon"]
    return subprocess.run(
        [*command, *map(str, args)], cwd=cwd, capture_output=True, text=True, timeout=timeout, check=False
    )


def assert_ok(result: subprocess.CompletedProcess[str]) -> None:
    assert (result.returncode, result.stderr) == (0, ""), result.stderr


def assert_one_error_line(result: subprocess.CompletedProcess[str]) -> str:
    """Exit status 2 and exactly one line on stderr, no traceback, nothing on stdout; returns that
    line."""
    assert result.returncode == 2, (result.returncode, result.stderr)
    assert "Traceback" not in result.stderr, result.stderr
    assert result.stderr.endswith("\n") and result.stderr.count("\n") == 1, result.stderr
    assert result.stdout == ""
    return result.stderr.rstrip("\n")


def csv_written(command: str, out: Path, asf: Path, amc: Path, *extra: str | Path) -> str:
    """Run ``mocapd COMMAND --asf ASF --amc AMC --csv OUT EXTRA``: it succeeds silently; the CSV's
    text."""
    result = mocapd(command, "--asf", asf, "--amc", amc, "--csv", out, *extra)
    assert_ok(result)
    assert result.stdout == ""
    return out.read_text(encoding="utf-8")


def hits_json(stdout: str) -> list[dict[str, object]]:
    """The hits ``mocapd search --json`` printed, one object per line."""
    return [json.loads(line) for line in stdout.splitlines()]


# ---------------------------------------------------------------------------------------- libraries


def takes(motion_class: str, actor: str) -> list[int]:
    """The take numbers of an actor's HDM05 clips of a class."""
    folder = DATA / "hdm05" / "cut" / motion_class
    return sorted(int(p.name.split("_")[3]) for p in folder.glob(f"HDM_{actor}_*"))


def small_library(where: Path) -> Library:
    """squat1Reps and hopBothLegs1hops learned (τ 0.1 given) from three clips of bd and of bk, each
    also with the published keyframes (``<class>.published``); ``where`` takes the manifest."""
    items = [
        (c, a, t) for c in ("squat1Reps", "hopBothLegs1hops") for a in ("bd", "bk") for t in takes(c, a)[:3]
    ]
    examples = read_examples(write_training(where / "clips.csv", training_rows(items)))
    published = parse_keyframe_queries(json.loads(KEYFRAMES.read_text(encoding="utf-8")), KEYFRAMES)
    classes: dict[str, ClassTemplate] = {}
    for name, clips in examples.items():
        learned = learn_class(name, clips)
        classes[name] = learned
        classes[f"{name}.published"] = dataclasses.replace(
            learned, name=f"{name}.published", keyframes=published[name]
        )
    return Library(30.0, classes)


# ------------------------------------------------------------------------ the service's real parts


@contextlib.contextmanager
def raw_publisher(address: str, linger_ms: int = 5000) -> Iterator[Any]:
    """An XPUB socket connected to a daemon's ZeroMQ poses ``address``, yielded once the daemon's
    subscription has arrived (so nothing sent is dropped for want of a subscriber); closed after."""
    import zmq

    ctx = zmq.Context()
    sock = ctx.socket(zmq.XPUB)
    sock.setsockopt(zmq.LINGER, linger_ms)
    try:
        sock.connect(address)
        assert sock.poll(10_000) and sock.recv()[:1] == b"\x01", "the daemon did not subscribe"
        yield sock
    finally:
        sock.close()
        ctx.term()


def wait_for(condition: Callable[[], bool], timeout: float, what: str, step: float = 0.02) -> None:
    """Poll ``condition`` until it holds; AssertionError saying ``what`` after ``timeout`` seconds."""
    deadline = time.monotonic() + timeout
    while not condition():
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out after {timeout:g} s waiting for {what}")
        time.sleep(step)


def freeze(process: subprocess.Popen[bytes]) -> None:
    """SIGSTOP ``process`` and return once every thread of it has stopped: the signal is delivered
    asynchronously, and a server still running for a moment answers what a test sends it next."""

    def stopped() -> bool:
        states = []
        for task in Path(f"/proc/{process.pid}/task").iterdir():
            with contextlib.suppress(FileNotFoundError):  # a thread that ended meanwhile
                states.append((task / "stat").read_text().rsplit(")", 1)[1].split()[0])
        return all(state in ("T", "t") for state in states)

    process.send_signal(signal.SIGSTOP)
    wait_for(stopped, 5, f"process {process.pid} to stop", step=0.001)


def _accepts(port: int) -> bool:
    with socket.socket() as s:
        s.settimeout(0.2)
        return s.connect_ex(("127.0.0.1", port)) == 0


def http_get(port: int, path: str) -> tuple[int, str]:
    """(status, body) of GET ``path`` on a daemon's metrics port on loopback; (0, "") if nothing
    answers within 2 s."""
    try:
        with urllib.request.urlopen(f"http://127.0.0.1:{port}{path}", timeout=2) as r:
            return r.status, r.read().decode()
    except urllib.error.HTTPError as e:
        return e.code, e.read().decode()
    except OSError:
        return 0, ""


def cluster_load(to: str, streams: int, seconds: float, rate: float) -> subprocess.Popen[str]:
    """:mod:`bench.cluster_load` publishing ``streams`` looping streams at ``rate`` Hz for
    ``seconds`` to ``to`` (``mqtt://`` or ``nats://``), as a process: what it sent, a JSON object,
    on its stdout."""
    options = ["--streams", str(streams), "--seconds", str(seconds), "--rate", str(rate)]
    return subprocess.Popen(
        [sys.executable, "-m", "bench.cluster_load", "--to", to, *options],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        cwd=REPO,
        env={**os.environ, "PYTHONPATH": str(REPO)},
    )


def burner() -> subprocess.Popen[bytes]:
    """A CPU-bound process (the load a test runs beside)."""
    return subprocess.Popen([sys.executable, "-c", "while True: pass"])


def log_events(log: Path, name: str) -> list[dict[str, Any]]:
    """The JSON log lines of event ``name`` in a daemon's log file ``log``."""
    return [e for e in json_lines(log) if e.get("event") == name]


class SegmentSummary(Protocol):
    """What a boundary says of the behaviour that ended (a BoundaryMessage, a segmenter's cut)."""

    @property
    def frame(self) -> int: ...
    @property
    def start(self) -> int | None: ...
    @property
    def detections(self) -> Sequence[SegmentDetection]: ...


def check_segment_summaries(events: Iterable[DetectionMessage | SegmentSummary | int], first: int) -> int:
    """Walk what a segmented stream gave, in order: detections published (DetectionMessage),
    boundaries (anything with ``frame``, ``start`` and ``detections``) and ints (the motion ended;
    the next begins at that frame), ``first`` the first motion's first frame. Each boundary must say
    its behaviour began at the motion's first frame or at the boundary before, and list the
    detections published since the motion began that lie wholly inside it. The boundaries seen."""
    begun, boundaries = first, 0
    published: list[tuple[str, int, int]] = []
    for e in events:
        if isinstance(e, int):
            begun, published = e, []
        elif isinstance(e, DetectionMessage):
            published.append((e.class_name, e.start_frame, e.end_frame))
        else:
            assert e.start == begun, (e.frame, e.start, begun)
            inside = [d for d in published if begun <= d[1] and d[2] < e.frame]
            assert [(d.class_name, d.start_frame, d.end_frame) for d in e.detections] == inside
            begun = e.frame
            boundaries += 1
    return boundaries


def stop_all(*parts: Any) -> None:
    """What a test started, in turn: a process killed (if it runs) and waited for, a collector
    closed, a server stopped; None passed over."""
    for part in parts:
        if part is None:
            continue
        if isinstance(part, subprocess.Popen):
            if part.poll() is None:
                part.kill()
                part.wait(10)
        elif hasattr(part, "stop"):
            part.stop()
        else:
            part.close()


def cluster_worker(
    where: Path, nats: str, etcd: str, metrics_port: int, cluster: Mapping[str, object] | None = None
) -> subprocess.Popen[bytes]:
    """``mocapd run --cluster NATS --coordinator ETCD`` as a process, its configuration
    (``cluster``: settings of its ``cluster`` section; streams idle after 2 s, debug logs) in
    ``where/worker.yaml`` and its log in ``where/worker.err``."""
    config = where / "worker.yaml"
    sections: dict[str, object] = {
        "service": {"idle_s": 2},
        "metrics": {"port": metrics_port},
        "logging": {"level": "debug"},
    }
    if cluster:
        sections["cluster"] = dict(cluster)
    config.write_text(json.dumps(sections), encoding="utf-8")
    with (where / "worker.err").open("wb") as log:
        return subprocess.Popen(
            [str(MOCAPD_SCRIPT), "--config", str(config), "run", "--cluster", nats, "--coordinator", etcd],
            stdout=subprocess.DEVNULL,
            stderr=log,
            env={**os.environ, "PYTHONPATH": str(REPO)},
        )


class NatsCollector:
    """A NATS subscriber on ``mocap.*.detections`` in its own thread: every message as it arrives."""

    def __init__(self, url: str) -> None:
        import asyncio

        import nats

        self.messages: list[dict[str, Any]] = []
        self.ready = threading.Event()
        self.done = threading.Event()
        self.loop = asyncio.new_event_loop()

        async def main() -> None:
            nc = await nats.connect(url)

            async def got(msg: Any) -> None:
                self.messages.append(msgpack.unpackb(msg.data, raw=False))

            await nc.subscribe("mocap.*.detections", cb=got)
            await nc.flush()
            self.ready.set()
            while not self.done.is_set():
                await asyncio.sleep(0.05)
            await nc.close()

        self.thread = threading.Thread(target=self.loop.run_until_complete, args=(main(),), daemon=True)
        self.thread.start()
        assert self.ready.wait(10), "the NATS collector did not connect"

    def close(self) -> None:
        self.done.set()
        self.thread.join(10)


@functools.cache
def looped_detections(asf: str, amc: str, last: int) -> list[dict[str, Any]]:
    """``mocapd detect``'s detections of a stream that looped the recording for sequence numbers
    0 .. ``last`` (as :mod:`bench.cluster_load` publishes it)."""
    from daemon.library import default_library_path, load_library
    from daemon.recognizer import detect

    motion = read_recording(Path(asf), Path(amc))
    seqs = np.arange(last + 1)
    looped = Motion(
        motion.source, motion.skeleton, motion.header, seqs, motion.channels[seqs % len(motion.channels)]
    )
    return [d.as_json() for d in detect(looped, load_library(default_library_path()), 120.0)]


def each_once_as_detect(
    sent: Mapping[str, Mapping[str, Any]],
    detections: Callable[[], list[dict[str, Any]]],
    within: float,
    excused: Callable[[list[dict[str, Any]]], Counter[tuple[str, str]]] | None = None,
) -> int:
    """What ``detections()`` gives comes to be ``mocapd detect``'s detections of what was ``sent``
    (per stream id, its recording's ``asf`` and ``amc`` looped up to sequence number ``last``, as
    :mod:`bench.cluster_load` prints it), of no other stream, each id once: waits up to ``within``
    seconds for every stream's count, then a second for a repeat, and says per stream what is
    missing or extra. ``excused``, given what came, counts per (stream, class) the detections that
    may be missing (a loss the design documents, each proven by the logs). The detections
    expected."""
    wants = {n: detection_keys(looped_detections(s["asf"], s["amc"], s["last"])) for n, s in sent.items()}

    def complete() -> bool:
        arrived: dict[str, int] = {}
        for d in detections():
            arrived[d["stream"]] = arrived.get(d["stream"], 0) + 1
        return all(arrived.get(n, 0) >= len(want) for n, want in wants.items())

    with contextlib.suppress(AssertionError):  # what is missing is said below, per stream
        wait_for(complete, within, "every stream's detections")
    time.sleep(1.0)
    got = detections()
    ids = [d["id"] for d in got]
    assert len(set(ids)) == len(ids), "a detection delivered twice"
    assert {d["stream"] for d in got} <= set(sent)
    allowed = Counter() if excused is None else excused(got)
    for n, want in wants.items():
        have = Counter(detection_keys([d for d in got if d["stream"] == n]))
        for key in sorted((Counter(want) - have).elements()):
            if allowed[(n, key[0])] > 0:
                allowed[(n, key[0])] -= 1
                have[key] += 1
        assert have == Counter(want), (
            f"{n}: missing {sorted((Counter(want) - have).elements())}, "
            f"extra {sorted((have - Counter(want)).elements())}"
        )
    return sum(len(want) for want in wants.values())


class ServerProcess:
    """A server the tests run as a process (``process``, None when stopped): :meth:`stop` sends
    ``sig`` (SIGTERM) and waits, :meth:`kill` is SIGKILL."""

    process: subprocess.Popen[bytes] | None = None

    def stop(self, sig: int = signal.SIGTERM) -> None:
        if self.process is not None and self.process.poll() is None:
            self.process.send_signal(sig)
            self.process.wait(10)
        self.process = None

    def kill(self) -> None:
        self.stop(signal.SIGKILL)


class Broker(ServerProcess):
    """A real mosquitto on a free loopback port with persistence on (its database in ``where``) and
    ``settings`` (default: anonymous clients allowed) for its listener;
    :meth:`start`, :meth:`stop` (SIGTERM: it saves its sessions), :meth:`kill`, start again on the
    same port."""

    def __init__(self, where: Path, settings: str = "allow_anonymous true\n") -> None:
        self.where = where
        self.port = free_port()
        self.config = where / "mosquitto.conf"
        self.config.write_text(
            f"listener {self.port} 127.0.0.1\n{settings}set_tcp_nodelay true\npersistence true\n"
            f"persistence_location {where}/\nautosave_interval 1\nmax_queued_messages 100000\n"
            f"log_dest file {where}/mosquitto.log\n"
            f"user {getpass.getuser()}\n",  # as root it would switch to 'mosquitto' and not reach ``where``
            encoding="utf-8",
        )
        self.process: subprocess.Popen[bytes] | None = None

    @property
    def url(self) -> str:
        return f"mqtt://127.0.0.1:{self.port}"

    def start(self) -> Broker:
        binary = shutil.which("mosquitto") or "/usr/sbin/mosquitto"
        if not Path(binary).exists():
            raise AssertionError(
                "mosquitto is not installed (.ci/run installs it: apt-get install mosquitto)"
            )
        self.process = subprocess.Popen(
            [binary, "-c", str(self.config)], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL
        )
        wait_for(lambda: _accepts(self.port), 10, f"mosquitto on port {self.port}")
        return self


PORT_RETRIES = 3


class Daemon:
    """``mocapd run`` as a real process on free ports: ZeroMQ poses/detections endpoints, the metrics
    port, the MQTT broker ``mqtt`` if given, ``workers`` recognition processes (default one: the
    single process), more ``config`` sections merged in. Its stdout (the
    stdout sink's JSON lines) and stderr (structured logs) go to files in ``where``."""

    def __init__(
        self,
        where: Path,
        *,
        sources: Sequence[str] = ("zmq",),
        sinks: Sequence[str] = ("zmq", "stdout"),
        mqtt: str | None = None,
        config: Mapping[str, Mapping[str, object]] | None = None,
        env: dict[str, str] | None = None,
        workers: int = 1,
    ) -> None:
        self.where = where
        self.poses = f"tcp://127.0.0.1:{free_port()}"
        self.detections = f"tcp://127.0.0.1:{free_port()}"
        self.metrics_port = free_port()
        sections: dict[str, dict[str, object]] = {
            "service": {
                "instance": f"test-{self.metrics_port}",
                "sources": list(sources),
                "sinks": list(sinks),
                "workers": workers,
            },
            "zmq": {"poses": self.poses, "detections": self.detections},
            "metrics": {"port": self.metrics_port},
            "logging": {"level": "debug"},
        }
        if mqtt is not None:
            sections["mqtt"] = {"url": mqtt, "reconnect_max_s": 0.5}
        for name, values in (config or {}).items():
            sections.setdefault(name, {}).update(values)
        self.instance = str(sections["service"]["instance"])
        self.config = where / "daemon.yaml"
        self.config.write_text(json.dumps(sections), encoding="utf-8")  # JSON is YAML
        self.stdout_path, self.stderr_path = where / "daemon.out", where / "daemon.err"
        self.env = {**os.environ, **(env or {})}
        self.process: subprocess.Popen[bytes] | None = None
        self._retries = 0

    def start(self, wait: bool = True, *, group: bool = False, command: Sequence[str] = ()) -> Daemon:
        """Start it (``wait``: until ``/healthz`` says ok); ``group``: as the leader of a process
        group of its own (its workers in it), as a terminal's job is; ``command``: run under it
        (``["nohup"]``)."""
        with self.stdout_path.open("ab") as out, self.stderr_path.open("ab") as err:
            self.process = subprocess.Popen(
                [*command, str(MOCAPD_SCRIPT), "--config", str(self.config), "run"],
                stdin=subprocess.DEVNULL,
                stdout=out,
                stderr=err,
                env=self.env,
                process_group=0 if group else None,
            )
        if wait:
            wait_for(lambda: self.health()[0] == 200 or not self.alive, 30, "the daemon's /healthz")
            if not self.alive and self._ports_taken():
                return self.start(wait, group=group, command=command)
            assert self.alive, self.stderr_path.read_text()
        return self

    def _ports_taken(self) -> bool:
        """Whether the daemon just stopped because a port :func:`free_port` gave was taken before
        it bound it (another process's outgoing connection may get it as its own port): if so, the
        configuration gets fresh ports, at most :data:`PORT_RETRIES` times."""
        if self._retries >= PORT_RETRIES or "address already in use" not in self.stderr_path.read_text():
            return False
        self._retries += 1
        sections = json.loads(self.config.read_text(encoding="utf-8"))
        self.poses = sections["zmq"]["poses"] = f"tcp://127.0.0.1:{free_port()}"
        self.detections = sections["zmq"]["detections"] = f"tcp://127.0.0.1:{free_port()}"
        self.metrics_port = sections["metrics"]["port"] = free_port()
        self.config.write_text(json.dumps(sections), encoding="utf-8")
        return True

    @property
    def alive(self) -> bool:
        return self.process is not None and self.process.poll() is None

    def http(self, path: str) -> tuple[int, str]:
        return http_get(self.metrics_port, path)

    def health(self) -> tuple[int, str]:
        return self.http("/healthz")

    def metrics(self) -> dict[str, float]:
        """The /metrics samples by name with labels, e.g. ``mocapd_rejects_total{reason="shape"}``."""
        _, text = self.http("/metrics")
        return samples(text)

    def signal(self, sig: int) -> None:
        assert self.process is not None
        self.process.send_signal(sig)

    def wait(self, timeout: float) -> int:
        assert self.process is not None
        code = self.process.wait(timeout)
        return code

    def stop(self) -> int:
        if not self.alive:
            return self.process.returncode if self.process else 0
        self.signal(signal.SIGTERM)
        return self.wait(30)

    def printed(self) -> list[dict[str, Any]]:
        """The messages the stdout sink printed (decoded JSON lines)."""
        return json_lines(self.stdout_path)

    def detections_printed(self) -> list[dict[str, Any]]:
        return [m for m in self.printed() if m.get("type") == "detection"]

    def logs(self) -> list[dict[str, Any]]:
        return json_lines(self.stderr_path)


def replay(
    asf: Path, amc: Path, to: str, *extra: str, stream: str | None = None, speed: str = "max"
) -> subprocess.Popen[str]:
    """``mocapd replay`` as a process (not waited for)."""
    args = [str(MOCAPD_SCRIPT), "replay", "--asf", str(asf), "--amc", str(amc), "--to", to, "--speed", speed]
    if stream is not None:
        args += ["--stream", stream]
    return subprocess.Popen([*args, *extra], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def finished(process: subprocess.Popen[str], timeout: float = 120) -> str:
    """The output of a process that must succeed."""
    out, err = process.communicate(timeout=timeout)
    assert process.returncode == 0, err
    return out


class MqttCollector:
    """A subscriber in its own thread (paho): QoS 1 on ``topics`` with a persistent session (fixed
    ``client_id``, so the broker keeps what arrives while it is away), reconnecting by itself;
    :attr:`messages` holds (topic, decoded message dict) as they arrive, :attr:`qos` how each came."""

    def __init__(self, url: str, topics: Sequence[str], client_id: str = "collector") -> None:
        import paho.mqtt.client as paho
        from paho.mqtt.enums import CallbackAPIVersion

        host, port = url.removeprefix("mqtt://").split(":")
        self.messages: list[tuple[str, dict[str, Any]]] = []
        self.qos: list[tuple[int, bool]] = []
        """Each message's (QoS it was delivered at, retained flag), in the order of :attr:`messages`."""
        self.lock = threading.Lock()
        self.client = paho.Client(CallbackAPIVersion.VERSION2, client_id=client_id, clean_session=False)
        self.client.reconnect_delay_set(1, 1)
        self.topics = list(topics)
        self.connected = threading.Event()

        def on_connect(client: Any, userdata: Any, flags: Any, reason: Any, properties: Any) -> None:
            for t in self.topics:
                client.subscribe(t, qos=1)
            self.connected.set()

        def on_message(client: Any, userdata: Any, message: Any) -> None:
            body = msgpack.unpackb(message.payload, raw=False)
            with self.lock:
                self.messages.append((message.topic, body))
                self.qos.append((message.qos, bool(message.retain)))

        self.client.on_connect = on_connect
        self.client.on_message = on_message
        self.client.connect(host, int(port), keepalive=10)
        self.client.loop_start()
        assert self.connected.wait(10), "the collector did not connect"

    def detections(self) -> list[dict[str, Any]]:
        with self.lock:
            return [m for _, m in self.messages if m.get("type") == "detection"]

    def statuses(self) -> list[dict[str, Any]]:
        with self.lock:
            return [m for _, m in self.messages if m.get("type") == "status"]

    def boundaries(self) -> list[tuple[str, dict[str, Any]]]:
        """(topic, message) of every behaviour boundary."""
        with self.lock:
            return [(t, m) for t, m in self.messages if m.get("type") == "boundary"]

    def close(self) -> None:
        self.client.loop_stop()
        self.client.disconnect()


class ZmqCollector:
    """A SUB socket on the daemon's detections endpoint in its own thread; returns once connected."""

    def __init__(self, endpoint: str) -> None:
        import zmq

        self.ctx = zmq.Context()
        self.sock = self.ctx.socket(zmq.SUB)
        self.sock.setsockopt(zmq.LINGER, 0)
        self.sock.setsockopt(zmq.RCVHWM, 1_000_000)
        monitor = self.sock.get_monitor_socket(zmq.EVENT_HANDSHAKE_SUCCEEDED)
        self.sock.setsockopt(zmq.SUBSCRIBE, b"mocap")
        self.sock.connect(endpoint)
        assert monitor.poll(10_000), "the collector's SUB socket did not connect"
        self.sock.disable_monitor()
        monitor.close()
        time.sleep(0.2)  # the subscription reaches the publisher just after the handshake
        self.messages: list[dict[str, Any]] = []
        self.running = True
        self.thread = threading.Thread(target=self._collect, daemon=True)
        self.thread.start()

    def _collect(self) -> None:
        import zmq

        while self.running:
            if self.sock.poll(50):
                _, payload = self.sock.recv_multipart(zmq.NOBLOCK)
                self.messages.append(msgpack.unpackb(payload, raw=False))

    def detections(self) -> list[dict[str, Any]]:
        return [m for m in list(self.messages) if m.get("type") == "detection"]

    def close(self) -> None:
        self.running = False
        self.thread.join(5)
        self.sock.close()
        self.ctx.term()


DETECTION_KEY = ("class", "start_frame", "end_frame", "cost", "tau", "emitted_at_frame")


def detection_keys(items: Sequence[dict[str, Any]]) -> list[tuple[Any, ...]]:
    """What must agree between a detection on the wire and ``mocapd detect``'s: all but the id."""
    return [tuple(d[k] for k in DETECTION_KEY) for d in items]


class View(ServerProcess):
    """``mocapd view`` as a real process on a free port, watching ``bus`` (and the daemon's metrics
    at ``metrics``): :meth:`start` waits for its ``/api/status``; :meth:`status` reads it; its stderr
    (JSON log lines) goes to ``where/view.err``."""

    def __init__(
        self, where: Path, bus: str, *extra: str, metrics: str | None = None, token: str | None = None
    ) -> None:
        self.where = where
        self.port = free_port()
        self.token = token
        self.args = [str(MOCAPD_SCRIPT), "view", "--bus", bus, "--port", str(self.port), *extra]
        if metrics is not None:
            self.args += ["--metrics", metrics]
        if token is not None:
            self.args += ["--token", token]
        self.stderr_path = where / "view.err"

    @property
    def url(self) -> str:
        return f"http://127.0.0.1:{self.port}/"

    def start(self) -> View:
        """Start it and wait until it serves (its ``serving`` log line)."""
        with self.stderr_path.open("ab") as err:
            process = self.process = subprocess.Popen(self.args, stdout=subprocess.DEVNULL, stderr=err)
        wait_for(
            lambda: any(e["event"] == "serving" for e in self.logs()) or process.poll() is not None,
            30,
            "mocapd view",
        )
        assert process.poll() is None, self.stderr_path.read_text()
        return self

    def status(self) -> dict[str, Any] | None:
        """``/api/status``; None while it does not answer."""
        request = urllib.request.Request(f"{self.url}api/status")
        if self.token is not None:
            request.add_header("Authorization", f"Bearer {self.token}")
        try:
            with urllib.request.urlopen(request, timeout=2) as r:
                out: dict[str, Any] = json.loads(r.read())
                return out
        except OSError:
            return None

    def logs(self) -> list[dict[str, Any]]:
        """Its log lines written so far (whole lines only)."""
        return json_lines(self.stderr_path)


def resampled_motion(motion: Motion, native: float, rate: float) -> Motion:
    """``motion`` at ``native`` Hz resampled to ``rate`` Hz, frames numbered from 1: each channel
    interpolated linearly between the two frames around an instant, angles (radians) the short way
    round."""
    n = int((len(motion) - 1) * rate / native) + 1
    t = np.arange(n) * native / rate
    i = np.minimum(t.astype(int), len(motion) - 2)
    w = (t - i)[:, None]
    channels = np.asarray(motion.channels, dtype=np.float64)
    step = channels[i + 1] - channels[i]
    angles = np.asarray(motion.skeleton.angle_channels, dtype=np.intp)
    step[:, angles] = np.remainder(step[:, angles] + math.pi, 2 * math.pi) - math.pi
    return dataclasses.replace(motion, frames=np.arange(1, n + 1), channels=channels[i] + w * step)
