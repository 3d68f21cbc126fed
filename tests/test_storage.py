"""Writing outputs (daemon/storage.py), the error root (daemon/errors.py) and the structure checker
(daemon/checks.py), in-process on real files in a temporary directory: outputs replace their target
only when complete, signals wait for renames and clean-up, errors name the target and the field."""

from __future__ import annotations

import os
import signal
from pathlib import Path

import pytest

from daemon.checks import Checker, number_reason, read_structured
from daemon.config import ConfigError
from daemon.errors import FileAccessError, MocapdError, UsageError, printable
from daemon.keyframes import KeyframeError
from daemon.storage import check_output_file, output_file, replace_directory, uninterrupted


class Boom(Exception):
    """Something failing in the middle of writing."""


def test_output_file_replaces_the_target_only_when_complete(tmp_path: Path) -> None:
    target = tmp_path / "out.csv"
    target.write_text("previous\n")
    os.chmod(target, 0o640)
    with pytest.raises(Boom, match="half way"), output_file(target) as out:
        out.write("new, half")
        raise Boom("half way")
    assert target.read_text() == "previous\n"
    assert os.listdir(tmp_path) == ["out.csv"]
    with output_file(target) as out:
        out.write("new\n")
    assert target.read_text() == "new\n"
    assert oct(target.stat().st_mode & 0o777) == oct(0o640)  # an existing file keeps its permissions
    assert os.listdir(tmp_path) == ["out.csv"]


def test_output_file_follows_a_link_and_writes_devices_in_place(tmp_path: Path) -> None:
    (tmp_path / "real.csv").write_text("old")
    (tmp_path / "link.csv").symlink_to(tmp_path / "real.csv")
    with output_file(tmp_path / "link.csv") as out:
        out.write("new")
    assert (tmp_path / "link.csv").is_symlink() and (tmp_path / "real.csv").read_text() == "new"
    with output_file("/dev/null", "wb") as out:
        out.write(b"bytes")
    assert Path("/dev/null").is_char_device()
    with (
        pytest.raises(FileAccessError, match=r"^/dev/full: No space left on device$"),
        output_file("/dev/full") as out,
    ):
        out.write("x" * 100_000)


@pytest.mark.parametrize(
    ("target", "message"),
    [
        ("missing/out.csv", "No such file or directory"),
        ("directory", "is a directory"),
    ],
)
def test_output_targets_are_checked_first(tmp_path: Path, target: str, message: str) -> None:
    (tmp_path / "directory").mkdir()
    with pytest.raises(FileAccessError, match=f"^{tmp_path / target}: {message}$"):
        check_output_file(tmp_path / target)
    with pytest.raises(FileAccessError, match=r"^/sys/out\.csv: "):
        check_output_file("/sys/out.csv")


def test_replace_directory_keeps_the_old_one_on_failure(tmp_path: Path) -> None:
    target = tmp_path / "idx"
    target.mkdir()
    (target / "marker").write_text("old")

    def fail(temp: Path) -> None:
        (temp / "marker").write_text("new")
        raise Boom("in the middle")

    with pytest.raises(Boom, match="in the middle"):
        replace_directory(target, "marker", "a test directory", fail)
    assert (target / "marker").read_text() == "old" and os.listdir(tmp_path) == ["idx"]

    def succeed(temp: Path) -> None:
        (temp / "marker").write_text("new")

    replace_directory(target, "marker", "a test directory", succeed)
    assert (target / "marker").read_text() == "new" and os.listdir(tmp_path) == ["idx"]


def test_uninterrupted_holds_signals_until_the_block_ends() -> None:
    """SIGINT and SIGTERM raised inside the block take effect after it, with the handler in force."""
    ran_to_the_end = False
    terminated: list[int] = []
    previous = signal.signal(signal.SIGTERM, lambda number, frame: terminated.append(number))
    try:
        with pytest.raises(KeyboardInterrupt, match=r"^$"), uninterrupted():  # Python's handler: no text
            os.kill(os.getpid(), signal.SIGINT)
            os.kill(os.getpid(), signal.SIGINT)
            ran_to_the_end = True
        assert ran_to_the_end
        with uninterrupted():
            os.kill(os.getpid(), signal.SIGTERM)
            assert terminated == []
        assert terminated == [signal.SIGTERM]
        assert signal.getsignal(signal.SIGINT) is signal.default_int_handler
    finally:
        signal.signal(signal.SIGTERM, previous)


# ------------------------------------------------------------------------------------------- errors


def test_every_error_a_user_can_cause_is_a_mocapd_error() -> None:
    from daemon.library import LibraryFormatError, UnknownClassError
    from daemon.plots import PlotUnavailable
    from daemon.recordings import ManifestError, RateError, RecordingError
    from daemon.search.store import IndexFormatError
    from replay import MocapFormatError

    kinds = [
        MocapFormatError,
        ManifestError,
        KeyframeError,
        IndexFormatError,
        LibraryFormatError,
        UnknownClassError,
        ConfigError,
        UsageError,
        FileAccessError,
        PlotUnavailable,
        RecordingError,
        RateError,
    ]
    assert all(issubclass(k, MocapdError) for k in kinds)
    assert str(MocapFormatError("a.amc", 3, "bad")) == "a.amc:3: bad"
    assert (
        str(MocapdError("bad", path="lib/library.json", field="classes.x.tau"))
        == "lib/library.json: classes.x.tau: bad"
    )
    assert str(UsageError("must be positive", field="--fps")) == "--fps: must be positive"


def test_messages_escape_what_a_terminal_would_obey() -> None:
    assert printable("ok\x1b[2J\x00\nÜ") == "ok\\x1b[2J\\x00\\nÜ"
    assert printable("Ü\xff", ascii_only=True) == "\\xdc\\xff"
    assert str(MocapdError("value '\x07\x9b'", path="a\nb.amc", line=2)) == "a\\nb.amc:2: value '\\x07\\x9b'"


# ------------------------------------------------------------------------------------------ checker


def test_checker_names_source_and_field() -> None:
    check = Checker("f.json", ConfigError, prefix="classes.a")
    with pytest.raises(
        ConfigError, match=r"^f\.json: classes\.a\[2\]\.tau: must be a positive number, got 0$"
    ):
        check.positive_number(0, "[2].tau")
    with pytest.raises(ConfigError, match=r"^f\.json: classes\.a\.x: unknown field \(allowed: y, z\)$"):
        check.mapping({"x": 1}, "", optional=("z", "y"))
    with pytest.raises(ConfigError, match=r"^f\.json: classes\.a\.k: missing a, b$"):
        check.mapping({}, "k", ("a", "b"))


@pytest.mark.parametrize(
    ("value", "limits", "reason"),
    [
        (True, {}, "must be a number, got True"),
        (10**400, {}, "must be a number, got " + "1" + "0" * 59),
        (float("nan"), {"low": 0}, "must be a number >= 0, got nan"),
        (0.5, {"low": 0, "high": 0.5, "high_open": True}, "must be a number in [0, 0.5), got 0.5"),
        (0, {"low": 0, "low_open": True}, "must be a positive number, got 0"),
        (2.0, {"integer": True}, "must be an integer, got 2.0"),
        (3, {"low": 0, "high": 5, "integer": True}, None),
    ],
)
def test_number_reasons(value: object, limits: dict[str, float], reason: str | None) -> None:
    assert number_reason(value, **limits) == reason  # type: ignore[arg-type]


def test_structured_files_name_file_and_line(tmp_path: Path) -> None:
    bad = tmp_path / "k.json"
    bad.write_text('{\n  "classes": [1,\n}\n')
    with pytest.raises(KeyframeError, match=rf"^{bad}:3: not valid JSON: "):
        read_structured(bad, "json", KeyframeError)
    bad.write_bytes(b"a: 1\nb: \xff\n")
    with pytest.raises(ConfigError, match=rf"^{bad}:2: not UTF-8 text \(byte 8\)$"):
        read_structured(bad, "yaml", ConfigError)
    with pytest.raises(FileAccessError, match=r"nothing\.yaml: No such file or directory$"):
        read_structured(tmp_path / "nothing.yaml", "yaml", ConfigError)
