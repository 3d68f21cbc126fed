"""Real SIGINT and SIGTERM, sent with ``kill`` at random moments to the commands that write files
(``positions``, ``features`` with its PNG, ``index build``, ``learn`` with its PNG directory), each run
as its own ``python -m daemon`` process over an earlier output of the same name. Whatever the moment,
the command either finished first (status 0, every output complete and equal to an uninterrupted
run's) or stopped (130 "mocapd: interrupted" / 143 "mocapd: terminated", every previous output byte
for byte as it was); never a traceback, and nothing temporary left beside the outputs or inside the
PNG directory.

The moments are drawn from a seeded generator, one in each of several equal slices of the command's
measured run time (and a little beyond it), counted from the moment ``main()`` has installed its
SIGTERM handler (read from ``/proc/PID/status``), so they land during start-up imports, reading,
computing, drawing, writing and renaming, and none before Python could handle a signal at all."""

from __future__ import annotations

import os
import random
import re
import shutil
import signal
import subprocess
import sys
import time
import types
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import pytest

import daemon.cli as cli
from daemon import storage
from daemon.cli import Terminated
from tests.helpers import (
    CMU_AMC,
    CMU_ASF,
    DATA,
    INDEX_PATHS,
    REPO,
    TRAINING,
    training_rows,
    write_manifest,
    write_training,
)

LONG_ASF = DATA / "cmu" / "13" / "13.asf"
LONG_AMC = DATA / "cmu" / "13" / "13_29.amc.gz"
"""A long CMU trial (4592 frames): ~120k rows of positions, so writing takes a while."""

SEED = "mocapd-signals-1"
MOMENTS = {"positions": 5, "features": 5, "index": 5, "learn": 4}
"""Signals per command and signal kind: one in each slice of the run time (learn's run is longest)."""
BEYOND = 1.15
"""The moments span the measured run time times this, so some come after the command has finished."""
FRACTIONS = (0.4, 0.2, 0.1)
"""Where in its run time a run is stopped "halfway", each tried if the one before came too late."""

STOPS = {
    signal.SIGINT: (130, "mocapd: interrupted\n"),
    signal.SIGTERM: (143, "mocapd: terminated\n"),
}
PROGRESS = re.compile(r"\[(?:class |fold )?\d+/\d+\] .*\n")
"""A progress line of ``index build`` or ``learn`` on stderr."""
TIMING = ("build time:", "learn time:")

Snapshot = dict[str, bytes]
"""A file (key ".") or a directory's entries by relative name (directories end in "/")."""


def snapshot(path: Path) -> Snapshot:
    """Everything ``path`` holds, hidden entries included."""
    if path.is_file():
        return {".": path.read_bytes()}
    return {
        p.relative_to(path).as_posix() + ("/" if p.is_dir() else ""): b"" if p.is_dir() else p.read_bytes()
        for p in sorted(path.rglob("*"))
    }


def place(content: Snapshot, path: Path) -> None:
    """Write ``content`` (a :func:`snapshot`) as ``path``, in place of what is there."""
    if path.is_dir():
        shutil.rmtree(path)
    if "." in content:
        path.write_bytes(content["."])
        return
    path.mkdir()
    for name, data in content.items():
        if name.endswith("/"):
            (path / name).mkdir()
        else:
            (path / name).write_bytes(data)


# ------------------------------------------------------------------------------------------ running


def main_started(pid: int) -> bool | None:
    """Whether the process has installed ``main()``'s SIGTERM handler (None: no /proc to tell)."""
    try:
        status = Path(f"/proc/{pid}/status").read_text(encoding="ascii")
    except OSError:
        return None
    caught = next((line.split()[1] for line in status.splitlines() if line.startswith("SigCgt:")), "0")
    return bool(int(caught, 16) >> (signal.SIGTERM - 1) & 1)


@dataclass(frozen=True)
class Run:
    status: int
    stdout: str
    stderr: str
    seconds: float
    """From main() starting to the process ending."""


def run(argv: list[str], delay: float | None = None, signum: signal.Signals | None = None) -> Run:
    """Run ``python -m daemon ARGV``; with ``signum``, send it ``delay`` seconds after ``main()``
    started (unless the process has ended by then)."""
    proc = subprocess.Popen(
        [sys.executable, "-m", "daemon", *argv],
        cwd=REPO,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        began = time.monotonic()
        while proc.poll() is None and time.monotonic() - began < 60:
            started = main_started(proc.pid)
            if started is None:
                time.sleep(max(0.0, 0.15 - (time.monotonic() - began)))
                break
            if started:
                break
            time.sleep(0.001)
        began = time.monotonic()
        if signum is not None and delay is not None:
            time.sleep(delay)
            proc.send_signal(signum)  # nothing is sent once the process has been waited for
        stdout, stderr = proc.communicate(timeout=180)
        return Run(proc.returncode, stdout, stderr, time.monotonic() - began)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


def moments(seconds: float, count: int, key: str) -> list[float]:
    """``count`` delays, one drawn in each equal slice of ``seconds`` x :data:`BEYOND`."""
    rng = random.Random(f"{SEED}-{key}")
    span = seconds * BEYOND
    return [span * (i + rng.random()) / count for i in range(count)]


# ----------------------------------------------------------------------------------------- commands


@dataclass(frozen=True)
class Command:
    name: str
    argv: Callable[[Path], list[str]]
    """The command line writing its outputs into a directory."""
    previous: dict[str, Snapshot]
    """The outputs already there before each run, by name in that directory."""
    new: dict[str, Snapshot]
    """What an uninterrupted run writes."""
    stdout: list[str]
    """What an uninterrupted run prints (see :func:`printed`)."""
    seconds: float
    """How long an uninterrupted run takes from main() starting."""
    summary: bool
    """Whether it prints a summary after its outputs are in place."""


def printed(stdout: str, out: Path) -> list[str]:
    """``stdout`` with the output directory named OUT and the timing lines left out."""
    return [line.replace(str(out), "OUT") for line in stdout.splitlines() if not line.startswith(TIMING)]


def written(argv: Callable[[Path], list[str]], directory: Path, names: list[str]) -> dict[str, Snapshot]:
    """Run the command uninterrupted into ``directory``; its outputs ``names``."""
    directory.mkdir()
    result = run(argv(directory))
    assert result.status == 0, result.stderr
    return {name: snapshot(directory / name) for name in names}


class Commands:
    """The four commands, each prepared (inputs, previous and expected outputs, run time) once."""

    def __init__(self, root: Path) -> None:
        self.root = root
        self.inputs = root / "inputs"
        self.inputs.mkdir()
        self.prepared: dict[str, Command] = {}

    def get(self, name: str) -> Command:
        if name not in self.prepared:
            self.prepared[name] = getattr(self, f"_{name}")()
        return self.prepared[name]

    def _measured(
        self,
        name: str,
        argv: Callable[[Path], list[str]],
        previous: dict[str, Snapshot],
        summary: bool = False,
    ) -> Command:
        reference = self.root / f"{name}-reference"
        reference.mkdir()
        result = run(argv(reference))
        assert result.status == 0, result.stderr
        new = {out: snapshot(reference / out) for out in previous}
        assert all(new[out] != previous[out] for out in previous)  # so "intact" and "new" differ
        return Command(name, argv, previous, new, printed(result.stdout, reference), result.seconds, summary)

    def _positions(self) -> Command:
        def argv(d: Path) -> list[str]:
            return ["positions", "--asf", str(LONG_ASF), "--amc", str(LONG_AMC), "--csv", str(d / "out.csv")]

        return self._measured("positions", argv, {"out.csv": {".": b"previous,positions\n1,2\n"}})

    def _features(self) -> Command:
        def argv(d: Path) -> list[str]:
            return [
                "features", "--asf", str(CMU_ASF), "--amc", str(CMU_AMC), "--fps", "30",
                "--csv", str(d / "out.csv"), "--png", str(d / "out.png"),
            ]  # fmt: skip

        previous = {"out.csv": {".": b"previous,features\n"}, "out.png": {".": b"\x89PNG\r\n\x1a\nprevious"}}
        return self._measured("features", argv, previous)

    def _index(self) -> Command:
        manifest = write_manifest(self.inputs / "index.csv", INDEX_PATHS, extra=False)
        earlier = write_manifest(self.inputs / "earlier-index.csv", INDEX_PATHS[:2], extra=False)

        def argv(d: Path) -> list[str]:
            return ["index", "build", "--manifest", str(manifest), "--out", str(d / "idx")]

        def earlier_argv(d: Path) -> list[str]:
            return ["index", "build", "--manifest", str(earlier), "--out", str(d / "idx")]

        previous = written(earlier_argv, self.root / "index-previous", ["idx"])
        return self._measured("index", argv, previous, summary=True)

    def _learn(self) -> Command:
        # Two classes, so two PNGs (drawing them is most of the run); the earlier library from other
        # takes of the same classes.
        hop, squat = TRAINING[0], TRAINING[3]
        clips = write_training(self.inputs / "clips.csv", training_rows([hop, squat]))
        earlier = write_training(self.inputs / "earlier-clips.csv", training_rows([TRAINING[1], TRAINING[4]]))

        def argv(d: Path) -> list[str]:
            return ["learn", "--manifest", str(clips), "--out", str(d / "lib"), "--png", str(d / "png")]

        def earlier_argv(d: Path) -> list[str]:
            return ["learn", "--manifest", str(earlier), "--out", str(d / "lib")]

        previous = written(earlier_argv, self.root / "learn-previous", ["lib"])
        previous["png"] = {f"{c}.png": f"previous {c}".encode() for c, _, _ in (hop, squat)}
        return self._measured("learn", argv, previous, summary=True)


@pytest.fixture(scope="module")
def commands(tmp_path_factory: pytest.TempPathFactory) -> Commands:
    return Commands(tmp_path_factory.mktemp("signals"))


# -------------------------------------------------------------------------------------------- checks


def check_outcome(command: Command, result: Run, signum: signal.Signals, directory: Path) -> bool:
    """Assert the run finished (status 0, new outputs) or stopped (130/143 and its one line, the
    previous outputs intact) and left nothing else in ``directory``; whether it stopped."""
    context = f"{command.name} {signum.name}: status {result.status}, stderr {result.stderr!r}"
    assert "Traceback" not in result.stderr + result.stdout, context
    assert sorted(os.listdir(directory)) == sorted(command.previous), context
    outputs = {name: snapshot(directory / name) for name in command.previous}
    progress = "".join(PROGRESS.findall(result.stderr))
    if result.status == 0:
        assert result.stderr == progress, context
        assert printed(result.stdout, directory) == command.stdout, context
        assert outputs == command.new, context
        return False
    status, line = STOPS[signum]
    assert result.status == status, context
    assert result.stderr == progress + line, context
    if outputs == command.previous:
        assert result.stdout == "", context
    else:
        # Only a command that prints a summary once its outputs are in place can be stopped after
        # that: then every output is the new one and what it printed is the summary's beginning.
        assert command.summary, context
        assert outputs == command.new, context
        lines = printed(result.stdout, directory)
        assert lines == command.stdout[: len(lines)], context
    return True


# --------------------------------------------------------------------------------------------- tests

COMMANDS = ["positions", "features", "index", "learn"]


@pytest.mark.slow
@pytest.mark.parametrize("signum", list(STOPS), ids=lambda s: s.name)
@pytest.mark.parametrize("name", COMMANDS)
def test_a_signal_at_any_moment_leaves_the_previous_output_or_the_new_one(
    commands: Commands, name: str, signum: signal.Signals, tmp_path: Path
) -> None:
    """SIGINT or SIGTERM at random moments of the command's run: status 0 with every output equal
    to an uninterrupted run's, or 130/143 with exactly "mocapd: interrupted"/"terminated" (after any
    progress lines) and every previous output byte for byte intact; no traceback; the directory
    holds exactly the outputs (no .tmp, .old or .probe sibling, nothing extra in the PNG
    directory). At least one of the runs is stopped."""
    command = commands.get(name)
    stopped = []
    for i, delay in enumerate(moments(command.seconds, MOMENTS[name], f"{name}-{signum.name}")):
        directory = tmp_path / f"run{i}"
        directory.mkdir()
        for out, content in command.previous.items():
            place(content, directory / out)
        result = run(command.argv(directory), delay, signum)
        stopped.append(check_outcome(command, result, signum, directory))
    assert any(stopped), f"no run of {name} was stopped (run time {command.seconds:.2f} s)"


@pytest.mark.slow
@pytest.mark.parametrize("name", COMMANDS)
def test_a_run_after_an_interrupted_one_writes_the_whole_output(
    commands: Commands, name: str, tmp_path: Path
) -> None:
    """A run stopped halfway (SIGTERM at 40 % of its run time) leaves the previous output; running
    the same command again then writes the new one, equal to an uninterrupted run's, and leaves
    nothing else behind. A run that finished before the signal was sent (a loaded machine can hold
    the test's own sleep past a fraction of a second, as index build's 0.3 s once was in CI) must
    be whole too; the signal is then sent earlier, up to three times."""
    command = commands.get(name)
    for fraction in FRACTIONS:
        for out, content in command.previous.items():
            place(content, tmp_path / out)
        first = run(command.argv(tmp_path), fraction * command.seconds, signal.SIGTERM)
        if check_outcome(command, first, signal.SIGTERM, tmp_path):
            break
    else:
        pytest.fail(f"no run of {name} was stopped at {FRACTIONS} of its {command.seconds:.2f} s")
    again = run(command.argv(tmp_path))
    assert not check_outcome(command, again, signal.SIGTERM, tmp_path)


@pytest.mark.slow
@pytest.mark.parametrize("signum", list(STOPS), ids=lambda s: s.name)
def test_a_signal_while_writing_to_stdout_exits_with_one_line(
    commands: Commands, signum: signal.Signals
) -> None:
    """``positions --csv -`` stopped while it writes the CSV to stdout (its first bytes already read)
    exits 130/143 with exactly one line on stderr; what reached stdout is the beginning of the CSV."""
    whole = commands.get("positions").new["out.csv"]["."]
    proc = subprocess.Popen(
        [sys.executable, "-m", "daemon", "positions", "--asf", str(LONG_ASF), "--amc", str(LONG_AMC),
         "--csv", "-"],
        cwd=REPO,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
    )  # fmt: skip
    try:
        assert proc.stdout is not None
        first = os.read(proc.stdout.fileno(), 4096)  # unbuffered: communicate() reads the rest
        time.sleep(random.Random(f"{SEED}-stdout-{signum.name}").uniform(0.0, 0.05))
        proc.send_signal(signum)
        stdout, stderr = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    status, line = STOPS[signum]
    assert (proc.returncode, stderr.decode()) == (status, line)
    assert first.startswith(b"frame,joint,x,y,z\n")
    assert whole.startswith(first + stdout)
    assert len(first + stdout) < len(whole)


@pytest.mark.slow
def test_a_signal_inside_a_weakref_callback_is_not_lost() -> None:
    """Python cannot raise an exception out of a weak reference's callback: it prints "Exception
    ignored" and goes on. The CLI's unraisable hook sends such a signal again, so the command still
    stops."""
    script = (
        "import signal, sys, time, weakref\n"
        "from daemon import cli\n"
        "signal.signal(signal.SIGINT, cli._interrupt)\n"
        "sys.unraisablehook = cli._unraisable(sys.__unraisablehook__)\n"
        "class A: pass\n"
        "def callback(ref): raise cli.Interrupted\n"
        "a = A(); r = weakref.ref(a, callback)\n"
        "try:\n"
        "    del a\n"
        "    time.sleep(2)\n"
        "    print('lost')\n"
        "except KeyboardInterrupt:\n"
        "    print('stopped')\n"
    )
    result = subprocess.run(
        [sys.executable, "-c", script], capture_output=True, text=True, timeout=30, cwd=REPO
    )
    assert (result.stdout, result.stderr) == ("stopped\n", "")


@pytest.mark.parametrize(
    ("raised", "status", "line"), [("Terminated", 143, "terminated"), ("Interrupted", 130, "interrupted")]
)
def test_a_signal_wrapped_by_class_creation_still_stops_the_command(
    raised: str, status: int, line: str
) -> None:
    """A signal arriving while a class is made (``__set_name__``, as when matplotlib is imported) is
    wrapped by Python in a RuntimeError; the command still ends as that signal says, not as a bug."""
    script = (
        "import sys\n"
        "from unittest import mock\n"
        "from daemon import cli\n"
        "class D:\n"
        f"    def __set_name__(self, owner, name): raise cli.{raised}\n"
        "def command(args, config):\n"
        "    class C:\n"
        "        d = D()\n"
        "with mock.patch('daemon.cli.recordings._info', command):\n"
        "    sys.exit(cli.main(['info', '--asf', 'x', '--amc', 'y']))\n"
    )
    result = subprocess.run(
        [sys.executable, "-c", script], capture_output=True, text=True, timeout=30, cwd=REPO
    )
    assert (result.returncode, result.stderr) == (status, f"mocapd: {line}\n")


def test_a_signal_reaching_another_thread_waits_until_matplotlib_is_imported() -> None:
    """A signal sent to the process while matplotlib is imported lands in any thread that does not
    block it (OpenBLAS's workers do not), and Python runs its handler in the main thread at once. It
    must act only once the import is whole, never in the middle of it (a half-made extension module
    came back as "writing PNG needs matplotlib")."""
    script = (
        "import os, signal, sys, threading\n"
        "go = threading.Event()\n"
        "def send():\n"
        "    go.wait(); os.kill(os.getpid(), signal.SIGINT)\n"
        "sender = threading.Thread(target=send); sender.start()\n"
        "class Finder:\n"
        "    def find_spec(self, name, path, target=None):\n"
        "        if name == 'matplotlib.pyplot':\n"
        "            go.set(); sender.join()\n"
        "            sum(range(100000))\n"
        "        return None\n"
        "sys.meta_path.insert(0, Finder())\n"
        "from daemon import plots\n"
        "try:\n"
        "    plots.check_plotting()\n"
        "    print('not stopped')\n"
        "except KeyboardInterrupt:\n"
        "    print('stopped after the import:', 'matplotlib.pyplot' in sys.modules)\n"
    )
    result = subprocess.run(
        [sys.executable, "-c", script], capture_output=True, text=True, timeout=60, cwd=REPO
    )
    assert (result.stdout, result.stderr) == ("stopped after the import: True\n", "")


def test_an_error_after_a_signal_ends_the_command_as_the_signal_says() -> None:
    """An error of mocapd's own raised after a signal arrived (a half-made import reported as a missing
    package) is the signal's doing or beside the point: the command ends 130 "interrupted"."""
    script = (
        "import signal, sys\n"
        "from unittest import mock\n"
        "from daemon import cli\n"
        "from daemon.errors import UsageError\n"
        "def command(args, config):\n"
        "    cli._RECEIVED.append(signal.SIGINT)\n"
        "    raise UsageError('writing PNG needs matplotlib')\n"
        "with mock.patch('daemon.cli.recordings._info', command):\n"
        "    sys.exit(cli.main(['info', '--asf', 'x', '--amc', 'y']))\n"
    )
    result = subprocess.run(
        [sys.executable, "-c", script], capture_output=True, text=True, timeout=30, cwd=REPO
    )
    assert (result.returncode, result.stderr) == (130, "mocapd: interrupted\n")


@pytest.mark.parametrize(
    ("signum", "kind"), [(signal.SIGINT, KeyboardInterrupt), (signal.SIGTERM, Terminated)]
)
def test_a_signal_once_the_outputs_are_in_place_is_too_late(
    signum: signal.Signals, kind: type[BaseException], tmp_path: Path
) -> None:
    """The command line's handlers (in this process): a stop signal raises until an output is put in
    place, not after, nor when it came during the swap (deferred until it is over): a run stopped
    with 130 or 143 then always left the previous outputs (CI once saw ``positions`` exit 130 with its
    new CSV in place, the signal having come between the rename and the return)."""
    handler = cli._interrupt if signum == signal.SIGINT else cli._terminate
    previous = signal.signal(signum, handler)
    try:
        storage.forget_placed()
        with pytest.raises(kind):
            signal.raise_signal(signum)
        with storage.uninterrupted():  # the signal comes while the output is put in place
            signal.raise_signal(signum)
            with storage.output_file(tmp_path / "out.csv") as out:
                out.write("new\n")
        signal.raise_signal(signum)  # and after
        assert (tmp_path / "out.csv").read_text() == "new\n"
        storage.forget_placed()  # the next command
        with pytest.raises(kind):
            signal.raise_signal(signum)
    finally:
        signal.signal(signum, previous)
        storage.forget_placed()


def test_a_signal_while_the_storage_module_is_being_imported_stops_the_command(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """While ``daemon.storage`` is imported, ``sys.modules`` holds it without its functions yet (a
    rehearsal's ``index`` run ended 70, "partially initialized module", when SIGTERM came then)."""
    monkeypatch.setitem(sys.modules, "daemon.storage", types.ModuleType("daemon.storage"))
    previous = signal.signal(signal.SIGTERM, cli._terminate)
    try:
        with pytest.raises(Terminated):
            signal.raise_signal(signal.SIGTERM)
    finally:
        signal.signal(signal.SIGTERM, previous)
