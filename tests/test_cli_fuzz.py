"""Fuzzing the command line: every command is given random bytes as each of its input files (fully
random, a valid file truncated, a few bytes flipped, empty, binary junk with control characters and
non-UTF-8 bytes, tokens spliced in, JSON values swapped, arrays rewritten with matching checksums)
and random values for each of its options. Whatever it gets, ``mocapd`` either succeeds or exits
with status 2 and one line on stderr naming the input (the damaged file, the option or its value),
free of raw control characters, with nothing on stdout and every output file as it was.

The commands run in-process through :func:`daemon.cli.main` (an exception escaping it is the
in-process form of a traceback) and, for a handful of cases, as real ``mocapd`` processes."""

from __future__ import annotations

import gzip
import hashlib
import io
import json
import os
import re
import shutil
import tempfile
import warnings
from collections.abc import Iterator, Sequence
from contextlib import contextmanager, suppress
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from daemon import cli
from daemon.errors import printable
from tests.helpers import (
    KEYFRAMES,
    REPO,
    hdm05_clip,
    mocapd,
    training_rows,
    write_manifest,
    write_training,
)

CONTROL = re.compile(r"[\x00-\x1f\x7f-\x9f]")
PROGRESS = re.compile(r"\[(?:class |fold )?\d+/\d+\] .*")
"""The progress lines ``index build`` and ``learn`` print on stderr before a later input fails."""
QUIET_WARNINGS = (DeprecationWarning, PendingDeprecationWarning, ImportWarning, ResourceWarning)
"""Warning categories Python does not print by default; any other warning is a line on stderr."""

RECORDING = hdm05_clip("bk", "hopBothLegs1hops", 20)
"""56 AMC frames: the recording of info/positions/features and of --example."""
INDEXED = [RECORDING, hdm05_clip("dg", "rotateArmsBothBackward1Reps", 10)]
"""The recordings ``index build`` is fuzzed on (56 and 86 frames)."""
DATABASE = [*INDEXED, hdm05_clip("bd", "squat1Reps", 1)]
"""The recordings of the prepared index."""
TRAINING_CLIPS = [("hopBothLegs1hops", "bd", 1), ("hopBothLegs1hops", "bd", 2), ("squat1Reps", "bd", 1)]
CLASSES = ("hopBothLegs1hops", "squat1Reps")
INDEX_FILES = ["index.json"] + [
    f"{s}.{a}.npy"
    for s in ("lower", "upper", "mix")
    for a in ("doc", "start", "length", "code", "offsets", "postings")
]
LIBRARY_FILES = ["library.json", *(f"{c}.npz" for c in CLASSES)]
FEATURES = ("kneeRightBent", "kneeLeftBent", "feetApartRelHips", "handRightRaisedRelSpine", "rootHighVel")


def fuzz(examples: int) -> settings:
    """Hypothesis settings of a fuzz test: ``examples`` examples, no deadline (a run takes 10-100 ms,
    a PNG a second), the function-scoped ``capsys`` shared by the examples (each reads it out).
    ``FUZZ_SCALE=10`` in the environment runs ten times as many (a ``MOCAPD_`` name would be read as a
    configuration override and refused)."""
    return settings(
        max_examples=round(examples * float(os.environ.get("FUZZ_SCALE", "1"))),
        deadline=None,
        suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow],
        database=None,
    )


# ------------------------------------------------------------------------------------ valid inputs


@dataclass(frozen=True)
class Valid:
    """Valid inputs, prepared once: ``idx`` (an index of :data:`DATABASE`), ``lib`` (the classes of
    :data:`TRAINING_CLIPS`), ``keyframes.json`` (the published keyframes of those classes) and
    ``png`` (a PNG, the known content of pre-created PNG outputs); ``scratch`` holds the workspaces
    of the examples."""

    root: Path
    scratch: Path

    @property
    def index(self) -> Path:
        return self.root / "idx"

    @property
    def library(self) -> Path:
        return self.root / "lib"

    @property
    def keyframes(self) -> Path:
        return self.root / "keyframes.json"

    @property
    def png(self) -> Path:
        return self.root / "known.png"


@pytest.fixture(scope="module")
def valid(tmp_path_factory: pytest.TempPathFactory) -> Valid:
    root = tmp_path_factory.mktemp("valid")
    manifest = write_manifest(root / "db.csv", DATABASE, extra=False)
    training = write_training(root / "clips.csv", training_rows(TRAINING_CLIPS))
    for argv in (
        ["index", "build", "--manifest", manifest, "--out", root / "idx"],
        [
            "learn",
            "--manifest",
            training,
            "--out",
            root / "lib",
            "--no-calibrate",
        ],  # keyframes for every class
    ):
        assert cli.main([str(a) for a in argv]) == 0
    published = json.loads(KEYFRAMES.read_text(encoding="utf-8"))
    published["classes"] = {c: published["classes"][c] for c in CLASSES}
    published["template_length"] = {c: published["template_length"][c] for c in CLASSES}
    (root / "keyframes.json").write_text(json.dumps(published, indent=1), encoding="utf-8")
    (root / "known.png").write_bytes(b"\x89PNG\r\n\x1a\nnot really, known content\n")
    return Valid(root, tmp_path_factory.mktemp("scratch"))


@contextmanager
def workspace(valid: Valid) -> Iterator[Path]:
    """A fresh directory for one example."""
    with tempfile.TemporaryDirectory(dir=valid.scratch) as where:
        yield Path(where)


def copy_index(valid: Valid, where: Path) -> Path:
    return Path(shutil.copytree(valid.index, where / "idx"))


def copy_library(valid: Valid, where: Path) -> Path:
    return Path(shutil.copytree(valid.library, where / "lib"))


# --------------------------------------------------------------------------------- running mocapd


def snapshot(where: Path) -> dict[str, bytes | None]:
    """Every file (its bytes) and directory (None) below ``where``."""
    return {
        str(p.relative_to(where)): None if p.is_dir() else p.read_bytes() for p in sorted(where.rglob("*"))
    }


def named(line: str, names: Sequence[str]) -> bool:
    """Whether ``line`` names one of ``names``: as a whole word or path, or quoted, as printed."""
    for name in names:
        for shown in {name, printable(name)}:
            if shown and re.search(rf"(?<![\w.]){re.escape(shown)}(?!\w)", line):
                return True
            if f"'{shown}'" in line or printable(repr(name)) in line:
                return True
    return False


def check_outcome(status: int, out: str, err: str, names: Sequence[str]) -> None:
    """Success, or status 2 with one error line (after any progress lines) naming one of ``names``,
    without raw control characters, and nothing on stdout."""
    assert "Traceback" not in err, err
    assert status in (0, 2), f"status {status}: {err}"
    if status == 0:
        return
    assert out == "", out
    assert err.endswith("\n"), repr(err)
    *progress, line = err[:-1].split("\n")
    assert all(PROGRESS.fullmatch(p) for p in progress), repr(err)
    assert line.startswith("mocapd: "), repr(err)
    assert not any(CONTROL.search(x) for x in (*progress, line)), repr(err)
    assert named(line, names), f"{line!r} names none of {names}"


def run(
    capsys: pytest.CaptureFixture[str], where: Path, argv: Sequence[object], names: Sequence[object]
) -> int:
    """``mocapd ARGV`` in-process in the workspace ``where``; checks its outcome (see
    :func:`check_outcome`), that it issued no warning, and on failure that nothing below ``where``
    changed. Returns the exit status."""
    before = snapshot(where)
    capsys.readouterr()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        status = cli.main([str(a) for a in argv])
    out, err = capsys.readouterr()
    shown = [
        f"{w.category.__name__}: {w.message}" for w in caught if not issubclass(w.category, QUIET_WARNINGS)
    ]
    assert not shown, shown
    check_outcome(status, out, err, [str(n) for n in names])
    if status != 0:
        assert snapshot(where) == before, "a failing run changed its outputs"
    return status


# --------------------------------------------------------------------------------------- damage

JUNK = bytes([*range(0x00, 0x20), 0x7F, *range(0x80, 0x100)])
TOKENS = tuple(
    t.encode("utf-8") if isinstance(t, str) else t
    for t in (
        "nan", "inf", "-inf", "1e400", "-1", "0", "1e300", "5e9", "1e-300", "99999999999999999999",
        "\n", "\r\n", "\r", "\t", " ", ":", "#", ",", '"', "{", "}", "[", "]", "null", "true", "-", ".",
        "\x00", "\x1b[2J", "\x85", "\u2028", "\x0c", "\x0b", "\ufeff", b"\xff\xfe", b"\xc3", b"\x80",
        ":SAMPLES-PER-SECOND 5e9\n", ":RADIANS\n", ":DEGREES\n", "1\n", "root ", "&a", "*a",
        "!!python/object",
    )
)  # fmt: skip
"""Tokens spliced into valid files: numbers that are not, line breaks of every kind, syntax of the
formats read (JSON, YAML, CSV, ASF, AMC), control characters and bytes that are not UTF-8."""


def _xor(data: bytes, edits: list[tuple[int, int]]) -> bytes:
    out = bytearray(data)
    for at, mask in edits:
        out[at % len(out)] ^= mask
    return bytes(out)


def _splice(data: bytes, edits: list[tuple[int, int, bytes]]) -> bytes:
    for at, cut, token in edits:
        at %= len(data) + 1
        data = data[:at] + token + data[at + cut :]
    return data


def damaged_bytes(valid: bytes) -> st.SearchStrategy[bytes]:
    """Random bytes, ``valid`` truncated, with bytes flipped or tokens spliced in, empty, junk."""
    at = st.integers(0, max(len(valid) - 1, 0))
    junk = st.lists(st.sampled_from(JUNK), min_size=1, max_size=300).map(bytes)
    return st.one_of(
        st.binary(max_size=600),
        st.just(b""),
        at.map(lambda k: valid[:k]),
        st.lists(st.tuples(at, st.integers(1, 255)), min_size=1, max_size=6).map(lambda e: _xor(valid, e)),
        junk,
        st.lists(
            st.tuples(at, st.integers(0, 8), st.sampled_from(TOKENS) | junk), min_size=1, max_size=4
        ).map(lambda e: _splice(valid, e)),
    )


def damaged_recording(valid: bytes) -> st.SearchStrategy[bytes]:
    """For a gzip file: its compressed bytes damaged, or its text damaged (then compressed or not)."""
    if valid[:2] != b"\x1f\x8b":
        return damaged_bytes(valid)
    text = gzip.decompress(valid)
    return st.one_of(
        damaged_bytes(valid), damaged_bytes(text), damaged_bytes(text).map(lambda d: gzip.compress(d, 1))
    )


INTERESTING: list[Any] = [
    None, True, False, 0, -1, 1, 2, 3, 30, 2**31, 2**63, 2**64, -(2**63) - 1, 0.5, -0.0, 1e308, 1e-308,
    float("nan"), float("inf"), "", "x", "lower", "mix", "squat1Reps", "../x", "\x1b[2J\n", [], {}, [0],
    [[0]], {"": 0}, [1, 2, 3],
]  # fmt: skip


def _nodes(value: Any, path: tuple[Any, ...] = ()) -> Iterator[tuple[Any, ...]]:
    """The path of every node of a parsed JSON document below the root."""
    children = (
        value.items() if isinstance(value, dict) else enumerate(value) if isinstance(value, list) else ()
    )
    for key, child in children:
        yield (*path, key)
        yield from _nodes(child, (*path, key))


@st.composite
def json_edited(draw: st.DrawFn, valid: bytes) -> bytes:
    """Valid JSON with 1-3 values replaced (by odd values or other nodes), deleted or added."""
    doc = json.loads(valid)
    for _ in range(draw(st.integers(1, 3))):
        paths = list(_nodes(doc))
        if not paths:
            break
        *parent_path, key = draw(st.sampled_from(paths))
        parent = doc
        for k in parent_path:
            parent = parent[k]
        what = draw(st.sampled_from(["replace", "replace", "other", "delete", "add"]))
        if what == "delete":
            del parent[key]
        elif what == "add" and isinstance(parent, dict):
            parent[draw(st.sampled_from(["extra", "", "0"]))] = draw(st.sampled_from(INTERESTING))
        elif what == "other":
            other = doc
            for k in draw(st.sampled_from(paths)):
                other = other[k]
            parent[key] = json.loads(json.dumps(other))
        else:
            parent[key] = json.loads(json.dumps(draw(st.sampled_from(INTERESTING))))
    return json.dumps(doc, indent=draw(st.sampled_from([None, 1]))).encode("utf-8")


def damaged_json(valid: bytes) -> st.SearchStrategy[bytes]:
    return damaged_bytes(valid) | json_edited(valid)


def damaged_yaml(valid: bytes) -> st.SearchStrategy[bytes]:
    values = st.sampled_from(
        ["120", "0", "-5", "5e9", "1e300", "1.0e-300", ".nan", ".inf", "0x10", "[1]", "{a: 1}", "''", "cm",
         "asf", "yes", "~", "&a 1", "*a", "!!binary AAAA", "\"\\x1b\"", "2001-01-01"]
    )  # fmt: skip
    edited = st.tuples(values, values).map(
        lambda v: f"replay:\n  frame_rate_hz: {v[0]}\n  units: {v[1]}\n".encode()
    )
    return damaged_bytes(valid) | edited


# ------------------------------------------------------------------------------------ option values

ODD_TEXT = st.text(
    st.characters(exclude_characters="\x00", exclude_categories=["Cs"]) | st.sampled_from("\udcff\udc80"),
    max_size=10,
)
"""Any text an argument can hold: no NUL; lone surrogates only as the OS makes them of bytes that are
not UTF-8."""


def number_text(*typical: str) -> st.SearchStrategy[str]:
    """Texts for a numeric option: ``typical`` values, odd numbers, and any text."""
    odd = [
        "0", "-1", "-0", "1e300", "5e9", "1e-300", "nan", "inf", "-inf", "1e309", "0x10", "", " ", "1_0",
        "\u0663", " 30 ", "30\n", "+30", "7", "0.5", "2.5", "1e18", "9223372036854775808", "-2",
    ]  # fmt: skip
    return st.one_of(
        st.sampled_from([*typical, *odd]),
        st.integers(-(2**70), 2**70).map(str),
        st.floats(allow_nan=True, allow_infinity=True).map(repr),
        ODD_TEXT,
    )


@dataclass(frozen=True)
class Opt:
    """An option of a command: its ``typical`` values (None: a flag) and ``odd`` ones (None: not
    fuzzed); a ``required`` option is always given."""

    name: str
    typical: st.SearchStrategy[str] | None = None
    odd: st.SearchStrategy[str] | None = None
    required: bool = False


@st.composite
def chosen(draw: st.DrawFn, spec: Sequence[Opt]) -> dict[str, str | None]:
    """Options of ``spec`` (name: value, None for a flag), some with typical values and one with an
    odd value: one at a time, so that refusing one odd value first hides no defect behind another."""
    odd_one = draw(st.sampled_from([o.name for o in spec if o.odd is not None]))
    out: dict[str, str | None] = {}
    for o in spec:
        if o.name == odd_one and o.odd is not None:
            out[o.name] = draw(o.odd)
        elif o.required or draw(st.booleans()):
            out[o.name] = None if o.typical is None else draw(o.typical)
    return out


def arguments(options: dict[str, str | None]) -> list[str]:
    """``options`` on a command line: ``--name value``, or ``--name=value`` for a value that starts
    with '-' (else it would be read as an option)."""
    out: list[str] = []
    for name, value in options.items():
        if value is None:
            out.append(name)
        elif value.startswith("-"):
            out.append(f"{name}={value}")
        else:
            out += [name, value]
    return out


def option_names(options: dict[str, str | None]) -> list[str]:
    """What an error about ``options`` may name: an option, or a value (as given or as the number it
    is, printed)."""
    out = []
    for name, value in options.items():
        out.append(name)
        if value is not None:
            out.append(value)
            with suppress(ValueError, OverflowError):
                out.append(f"{float(value):g}")
            with suppress(ValueError):
                out.append(str(int(value)))
    return out


def typical(*values: str) -> st.SearchStrategy[str]:
    return st.sampled_from(values)


RATE = Opt("--native-fps", typical("120", "60"), number_text("120", "60", "10000", "10001"))
LIMIT = Opt("--limit", typical("0", "1", "5"), number_text("0", "1", "5"))
JSON = Opt("--json")
CLASS_TEXT = st.one_of(
    typical(*CLASSES, "kickLFront1Reps", "", "x", "../lib/squat1Reps", "squat1Reps.npz", "library", "-"),
    ODD_TEXT,
)
EXTEND_TEXT = st.one_of(
    typical("0,0", "1,2", "-1,0", "1", "1,2,3", ",", "x,y", "1e9,1", " 1, 2", "1,-0"),
    st.tuples(st.integers(-(2**70), 2**70), st.integers(-(2**70), 2**70)).map(lambda e: f"{e[0]},{e[1]}"),
    ODD_TEXT,
)
STEPS_TEXT = typical("toolbox", "thesis", "x", "", "TOOLBOX", "toolbox ") | ODD_TEXT
FEATURES_TEXT = st.one_of(
    st.lists(st.sampled_from(FEATURES), max_size=4).map(",".join),
    typical("", ",", "kneeRightBent,,", "nosuch", "kneeRightBent,handRightRaisedRelSpine", " kneeRightBent "),
    ODD_TEXT,
)
OUTPUT_NAMES = typical("new", "file", "nonempty", "no/such", ".", "file/sub", "")
"""Odd output paths in a workspace (see :func:`outputs`)."""


def outputs(where: Path) -> None:
    """Pre-create in ``where`` what :data:`OUTPUT_NAMES` name: a file and a directory not mocapd's."""
    (where / "file").write_text("known content\n")
    (where / "nonempty").mkdir()
    (where / "nonempty" / "keep").write_text("known content\n")


# --------------------------------------------------------------------- info, positions, features


def recording_argv(command: str, where: Path, asf: Path, amc: Path) -> list[str | Path]:
    argv: list[str | Path] = [command, "--asf", asf, "--amc", amc]
    if command not in ("info", "segment"):
        (where / "out.csv").write_text("known content\n")
        argv += ["--csv", where / "out.csv"]
    return argv


@pytest.mark.slow
@given(
    command=st.sampled_from(["info", "positions", "features", "segment"]),
    damaged=st.sampled_from(["asf", "amc", "config"]).flatmap(
        lambda which: st.tuples(
            st.just(which),
            damaged_bytes(RECORDING[0].read_bytes())
            if which == "asf"
            else damaged_recording(RECORDING[1].read_bytes())
            if which == "amc"
            else damaged_yaml((REPO / "config.yaml").read_bytes()),
        )
    ),
    extra=st.sampled_from([[], ["--json"], ["--cm"], ["--fps", "30"], ["--native-fps", "60"], ["--png"]]),
)
@fuzz(150)
def test_recording_commands_with_damaged_files(
    valid: Valid,
    capsys: pytest.CaptureFixture[str],
    command: str,
    damaged: tuple[str, bytes],
    extra: list[str],
) -> None:
    which, data = damaged
    with workspace(valid) as where:
        asf, amc = RECORDING
        target = where / {"asf": "x.asf", "amc": "x.amc.gz", "config": "config.yaml"}[which]
        target.write_bytes(data)
        asf = target if which == "asf" else asf
        amc = target if which == "amc" else amc
        config = ["--config", target] if which == "config" else []
        argv = [*config, *recording_argv(command, where, asf, amc)]
        usable = {
            "info": ["--json"],
            "positions": ["--cm"],
            "features": ["--fps", "--png"],
            "segment": ["--json"],
        }[command]
        if extra == ["--png"] and command == "features":
            shutil.copy(valid.png, where / "out.png")  # the PNG output, pre-created
            argv += ["--png", where / "out.png"]
        elif extra and extra[0] in (*usable, "--native-fps"):
            argv += extra
        run(capsys, where, argv, [target])


BVH_TAKE = REPO / ".." / "shared" / "data" / "mocap" / "bandai2" / "dataset-2_walk_normal_001.bvh.gz"
"""A bandai2 take (CC BY-NC-ND 4.0): damaged here only in memory and in the test's workspace."""


@pytest.mark.slow
@given(data=damaged_recording(BVH_TAKE.read_bytes()), extra=st.sampled_from([[], ["--json"]]))
@fuzz(150)
def test_detect_with_a_damaged_bvh(
    valid: Valid, capsys: pytest.CaptureFixture[str], data: bytes, extra: list[str]
) -> None:
    with workspace(valid) as where:
        target = where / "x.bvh.gz"
        target.write_bytes(data)
        run(capsys, where, ["detect", "--bvh", target, *extra], [target])


CSV = Opt(
    "--csv", typical("out.csv", "-"), typical("out", "new.csv", "no/such/out.csv", ".", "file/x", ""), True
)
RECORDING_OPTIONS = {
    "info": [RATE, JSON],
    "positions": [RATE, Opt("--cm"), CSV],
    "features": [RATE, Opt("--fps", typical("30", "60", "120"), number_text("30", "60", "120")), CSV],
    "segment": [
        RATE,
        JSON,
        Opt("--method", typical("pca", "ppca", "gmm"), typical("PCA", "", "svd") | ODD_TEXT),
        Opt("--window", typical("0.2", "1.25"), number_text("0.2", "1.25")),
        Opt("--rise", typical("15", "0"), number_text("15", "0")),
        Opt("--shortest", typical("0", "2.5"), number_text("0", "2.5")),
        Opt("--k-sigma", typical("3"), number_text("3")),
        Opt("--ell", typical("0.1", "0.5"), number_text("0.1", "0.5")),
        Opt("--clusters", typical("2", "4"), number_text("2", "4")),
        Opt("--variance", typical("0.9", "1"), number_text("0.9", "1")),
    ],
}


@pytest.mark.slow
@given(
    options=st.sampled_from(sorted(RECORDING_OPTIONS)).flatmap(
        lambda c: st.tuples(st.just(c), chosen(RECORDING_OPTIONS[c]))
    )
)
@fuzz(100)
def test_recording_commands_with_random_options(
    valid: Valid, capsys: pytest.CaptureFixture[str], options: tuple[str, dict[str, str | None]]
) -> None:
    command, given_options = options
    with workspace(valid) as where:
        outputs(where)
        (where / "out.csv").write_text("known content\n")
        csv = given_options.get("--csv")
        if csv not in (None, "-"):
            given_options["--csv"] = str(where / str(csv))
        argv = [command, "--asf", RECORDING[0], "--amc", RECORDING[1], *arguments(given_options)]
        run(capsys, where, argv, option_names(given_options))


@pytest.mark.slow
@given(
    png=st.one_of(
        st.sampled_from(
            ["out.PNG", "out.png.txt", "out", ".png", "out.pdf", "out.png/", "dir", "dir/x.png", "no/x.png",
             "out.p ng", "out.\u2028png", "out\x1b.png", "out.png\x7f", "\udcff.png", "known.png"]
        ),
        ODD_TEXT,
    ),
    native_fps=st.sampled_from([[], ["--native-fps", "7"], ["--native-fps", "0"]]),
)  # fmt: skip
@fuzz(20)
def test_features_png_paths(
    valid: Valid, capsys: pytest.CaptureFixture[str], png: str, native_fps: list[str]
) -> None:
    """``--png`` with odd names and extensions: refused naming the path or option before any CSV is
    written (drawing is slow: a valid path is drawn only for a few examples)."""
    with workspace(valid) as where:
        (where / "dir").mkdir()
        shutil.copy(valid.png, where / "known.png")
        target = where / png if png else Path(png)
        argv = [*recording_argv("features", where, *RECORDING), "--png", target, *native_fps]
        run(capsys, where, argv, ["--png", target, *native_fps])


# ------------------------------------------------------------------------------------ index build


def index_manifest(where: Path, recordings: Sequence[tuple[Path, Path]]) -> Path:
    return write_manifest(where / "db.csv", recordings, extra=False)


@pytest.mark.slow
@given(
    damaged=st.sampled_from(["manifest", *(f"{k}{i}" for i in range(len(INDEXED)) for k in ("asf", "amc"))]),
    data=st.data(),
    rate=st.sampled_from([[], ["--fps", "60"], ["--native-fps", "60"]]),
)
@fuzz(80)
def test_index_build_with_damaged_files(
    valid: Valid, capsys: pytest.CaptureFixture[str], damaged: str, data: st.DataObject, rate: list[str]
) -> None:
    with workspace(valid) as where:
        out = copy_index(valid, where)  # the output, pre-created
        if damaged == "manifest":
            target = index_manifest(where, INDEXED)
            target.write_bytes(data.draw(damaged_bytes(target.read_bytes()), label="manifest"))
            manifest = target
        else:
            i, kind = int(damaged[3:]), damaged[:3]
            column = 0 if kind == "asf" else 1
            target = where / f"r{i}.{kind}{'.gz' if kind == 'amc' else ''}"
            target.write_bytes(data.draw(damaged_recording(INDEXED[i][column].read_bytes()), label=damaged))
            rows: list[list[Path]] = [list(r) for r in INDEXED]
            rows[i][column] = Path(target.name)  # relative to the manifest
            manifest = index_manifest(where, [(a, b) for a, b in rows])
        run(capsys, where, ["index", "build", "--manifest", manifest, "--out", out, *rate], [target])


INDEX_BUILD_OPTIONS = [
    Opt("--fps", typical("30", "60"), number_text("30", "60", "120", "240")),
    RATE,
    Opt("--out", typical("idx"), OUTPUT_NAMES, True),
]


@pytest.mark.slow
@given(options=chosen(INDEX_BUILD_OPTIONS))
@fuzz(50)
def test_index_build_with_random_options(
    valid: Valid, capsys: pytest.CaptureFixture[str], options: dict[str, str | None]
) -> None:
    with workspace(valid) as where:
        copy_index(valid, where)
        argv = ["index", "build", "--manifest", index_manifest(where, INDEXED)]
        run_with_options(capsys, where, argv, options)


def run_with_options(
    capsys: pytest.CaptureFixture[str], where: Path, argv: list[object], options: dict[str, str | None]
) -> None:
    """``argv`` with ``options`` in ``where`` beside earlier outputs, ``--out`` below ``where``."""
    outputs(where)
    options["--out"] = str(where / str(options["--out"]))
    run(capsys, where, [*argv, *arguments(options)], option_names(options))


# ------------------------------------------------------------------------- index info and search


def reseal_index(index: Path, file: str) -> None:
    """Write the SHA-256 of ``file`` (``<set>.<array>.npy``) into index.json, as a crafted index would."""
    meta = json.loads((index / "index.json").read_text())
    feature_set, array, _ = file.split(".")
    values = np.load(index / file)
    meta["sets"][feature_set]["sha256"][array] = hashlib.sha256(np.ascontiguousarray(values).data).hexdigest()
    (index / "index.json").write_text(json.dumps(meta))


VALUES = st.sampled_from([0, 1, -1, 2, 3, 7, 2**12, 2**14, 2**31, 2**62, 2**63 - 1, -(2**63)])


@st.composite
def crafted_npy(draw: st.DrawFn, valid: bytes) -> bytes:
    """A valid int64 array with a few entries changed, or cut, grown, reversed or zeroed."""
    values = np.load(io.BytesIO(valid)).copy()
    how = draw(st.sampled_from(["set", "set", "cut", "grow", "reverse", "zero"]))
    if how == "set" and len(values):
        for _ in range(draw(st.integers(1, 3))):
            values[draw(st.integers(0, len(values) - 1))] = draw(VALUES)
    elif how == "cut":
        values = values[: draw(st.integers(0, len(values)))]
    elif how == "grow":
        values = np.concatenate([values, np.array([draw(VALUES)], dtype=np.int64)])
    elif how == "reverse":
        values = values[::-1].copy()
    else:
        values[:] = 0
    buffer = io.BytesIO()
    np.save(buffer, values)
    return buffer.getvalue()


def damage_index(valid: Valid, where: Path, file: str, data: st.DataObject) -> Path:
    """A copy of the index with ``file`` damaged (a crafted .npy: with its checksum resealed)."""
    index = copy_index(valid, where)
    target = index / file
    original = target.read_bytes()
    if file.endswith(".json"):
        target.write_bytes(data.draw(damaged_json(original), label=file))
    elif data.draw(st.booleans(), label="crafted"):
        target.write_bytes(data.draw(crafted_npy(original), label=file))
        reseal_index(index, file)
    else:
        target.write_bytes(data.draw(damaged_bytes(original), label=file))
    return target


SEARCHES = ("keyframes", "library", "library+keyframes", "example")


def search_argv(where: Path, mode: str, index: Path) -> list[str | Path]:
    """A valid search of ``mode`` over ``index`` (the library, keyframe file and recording copied or
    read in place)."""
    argv: list[str | Path] = ["search", "--index", index]
    if mode == "keyframes":
        return [*argv, "--keyframes", where / "keyframes.json", "--class", "squat1Reps"]
    if mode.startswith("library"):
        argv += ["--library", where / "lib", "--class", "squat1Reps"]
        return argv + (["--keyframes", where / "keyframes.json"] if mode == "library+keyframes" else [])
    return [*argv, "--example", *RECORDING, "1", "40", "--features", "kneeRightBent,kneeLeftBent"]


def prepare_search(valid: Valid, where: Path) -> None:
    copy_library(valid, where)
    shutil.copy(valid.keyframes, where / "keyframes.json")


@pytest.mark.slow
@given(
    command=st.sampled_from(["info", *SEARCHES]),
    file=st.sampled_from(INDEX_FILES),
    data=st.data(),
    json_output=st.booleans(),
)
@fuzz(120)
def test_index_info_and_search_with_damaged_index(
    valid: Valid,
    capsys: pytest.CaptureFixture[str],
    command: str,
    file: str,
    data: st.DataObject,
    json_output: bool,
) -> None:
    with workspace(valid) as where:
        prepare_search(valid, where)
        target = damage_index(valid, where, file, data)
        index = where / "idx"
        argv = ["index", "info", index] if command == "info" else search_argv(where, command, index)
        names = [target, target.name]  # the arrays and index.json name each other
        run(capsys, where, [*argv, *(["--json"] if json_output else [])], names)


@st.composite
def crafted_npz(draw: st.DrawFn, valid: bytes) -> dict[str, Any]:
    """The arrays of a class file, one changed (values, shape or dtype)."""
    with np.load(io.BytesIO(valid)) as npz:
        arrays = {k: npz[k].copy() for k in npz.files}
    name = draw(st.sampled_from(sorted(arrays)))
    values = arrays[name]
    how = draw(st.sampled_from(["set", "set", "shape", "dtype", "huge", "empty"]))
    if how == "set":
        flat = values.reshape(-1)
        for _ in range(draw(st.integers(1, 3))):
            flat[draw(st.integers(0, flat.size - 1))] = draw(
                st.sampled_from([0.0, 0.5, 1.0, 2.0, -1.0, 1e-300, 1e300, np.nan, np.inf, 3.0, 0.25])
            )
    elif how == "shape":
        values = values.reshape(-1) if values.ndim == 2 else values[:, None]
    elif how == "dtype":
        values = values.astype(draw(st.sampled_from([np.float32, np.int64, np.bool_, np.complex128])))
    elif how == "huge":
        values = np.full_like(values, draw(st.sampled_from([1e6, 1e12, 1e300, 2.0**62])))
    else:
        values = values[..., :0]
    arrays[name] = values
    return arrays


def reseal_library(library: Path, name: str, arrays: dict[str, Any]) -> None:
    """Save ``arrays`` as ``<name>.npz`` with library.json's checksums made to match."""
    np.savez(library / f"{name}.npz", **arrays)
    meta = json.loads((library / "library.json").read_text())
    meta["classes"][name]["sha256"] = {
        a: hashlib.sha256(np.ascontiguousarray(v).data).hexdigest() for a, v in arrays.items()
    }
    (library / "library.json").write_text(json.dumps(meta))


@pytest.mark.slow
@given(
    mode=st.sampled_from(SEARCHES),
    file=st.sampled_from(["keyframes.json", *LIBRARY_FILES, "example.asf", "example.amc"]),
    data=st.data(),
    class_name=st.sampled_from(CLASSES),
)
@fuzz(150)
def test_search_with_damaged_queries(
    valid: Valid,
    capsys: pytest.CaptureFixture[str],
    mode: str,
    file: str,
    data: st.DataObject,
    class_name: str,
) -> None:
    """The keyframe file, the library's files and the example's recording damaged, for every search
    that reads them (a library class file also crafted, with matching checksums)."""
    with workspace(valid) as where:
        prepare_search(valid, where)
        index = where / "idx"
        shutil.copytree(valid.index, index)
        argv = search_argv(where, mode, index)
        if "--class" in argv:
            argv[argv.index("--class") + 1] = class_name
        if file == "keyframes.json":
            target = where / file
            target.write_bytes(data.draw(damaged_json(target.read_bytes()), label=file))
            if mode == "library":
                argv += ["--keyframes", target]
        elif file in LIBRARY_FILES:
            target = where / "lib" / file
            name = file.removesuffix(".npz")
            if file.endswith(".npz") and data.draw(st.booleans(), label="crafted"):
                reseal_library(where / "lib", name, data.draw(crafted_npz(target.read_bytes()), label=file))
            elif file.endswith(".npz"):
                target.write_bytes(data.draw(damaged_bytes(target.read_bytes()), label=file))
            else:
                target.write_bytes(data.draw(damaged_json(target.read_bytes()), label=file))
            if mode == "library" and data.draw(st.booleans(), label="learned keyframes"):
                argv += ["--keyframes"]
        else:
            kind = file.removeprefix("example.")
            original = RECORDING[0] if kind == "asf" else RECORDING[1]
            target = where / f"x.{kind}"
            target.write_bytes(data.draw(damaged_recording(original.read_bytes()), label=file))
            if mode == "example":
                argv[argv.index(original)] = target
        names = [target, target.name] if file in LIBRARY_FILES else [target]  # files name each other
        run(capsys, where, argv, names)


CLASS = Opt("--class", typical(*CLASSES), CLASS_TEXT, True)
EXTEND = Opt("--extend", typical("0,0", "1,2", "3,0"), EXTEND_TEXT)
TAU = Opt("--tau", typical("0.1", "0.3", "1"), number_text("0.1", "0.3", "1"))
STEPS = Opt("--steps", typical("toolbox", "thesis"), STEPS_TEXT)
SEARCH_OPTIONS = {
    "keyframes": [CLASS, EXTEND, LIMIT, JSON],
    "library": [CLASS, TAU, STEPS, Opt("--keyframes"), EXTEND, LIMIT, JSON],
    "library+keyframes": [CLASS, TAU, STEPS, EXTEND, LIMIT, JSON],
    "example": [
        Opt("START", typical("1", "10"), number_text("1", "56", "57", "0")),
        Opt("END", typical("40", "56"), number_text("1", "56", "57", "0")),
        Opt("--features", typical("kneeRightBent", "kneeRightBent,kneeLeftBent"), FEATURES_TEXT, True),
        Opt("--fuzzy", typical("0", "1", "2"), number_text("0", "1", "2", "12")),
        Opt("--mismatch", typical("0", "1"), number_text("0", "1", "2")),
        Opt("--plain"),
        RATE,
        LIMIT,
        JSON,
    ],
}


@pytest.mark.slow
@given(options=st.sampled_from(SEARCHES).flatmap(lambda m: st.tuples(st.just(m), chosen(SEARCH_OPTIONS[m]))))
@fuzz(150)
def test_search_with_random_options(
    valid: Valid, capsys: pytest.CaptureFixture[str], options: tuple[str, dict[str, str | None]]
) -> None:
    mode, given_options = options
    with workspace(valid) as where:
        prepare_search(valid, where)
        index = where / "idx"
        shutil.copytree(valid.index, index)
        argv: list[str | Path] = ["search", "--index", index]
        names: list[str] = []
        if mode == "example":
            frames = [given_options.pop("START", None) or "1", given_options.pop("END", None) or "40"]
            argv += ["--example", *RECORDING, *frames]
            names = ["--example", *frames]
        if mode.startswith("library"):
            argv += ["--library", where / "lib"]
        if mode in ("keyframes", "library+keyframes"):
            argv += ["--keyframes", where / "keyframes.json"]
        argv += arguments(given_options)
        run(capsys, where, argv, [*names, *option_names(given_options)])


# ------------------------------------------------------------------------------------------ learn


@pytest.mark.slow
@given(
    damaged=st.sampled_from(
        ["manifest", *(f"{k}{i}" for i in range(len(TRAINING_CLIPS)) for k in ("asf", "amc"))]
    ),
    data=st.data(),
)  # fmt: skip
@fuzz(60)
def test_learn_with_damaged_files(
    valid: Valid, capsys: pytest.CaptureFixture[str], damaged: str, data: st.DataObject
) -> None:
    with workspace(valid) as where:
        out = copy_library(valid, where)  # the output, pre-created
        (where / "png").mkdir()
        shutil.copy(valid.png, where / "png" / "squat1Reps.png")
        rows = [r.split(",") for r in training_rows(TRAINING_CLIPS)]
        if damaged == "manifest":
            manifest = write_training(where / "clips.csv", [",".join(r) for r in rows])
            target = manifest
            target.write_bytes(data.draw(damaged_bytes(manifest.read_bytes()), label="manifest"))
        else:
            i, kind = int(damaged[3:]), damaged[:3]
            column = 1 if kind == "asf" else 2
            target = where / f"r{i}.{kind}{'.gz' if kind == 'amc' else ''}"
            original = Path(rows[i][column])
            target.write_bytes(data.draw(damaged_recording(original.read_bytes()), label=damaged))
            rows[i][column] = target.name
            manifest = write_training(where / "clips.csv", [",".join(r) for r in rows])
        png = ["--png", where / "png"] if data.draw(st.booleans(), label="png") else []
        run(capsys, where, ["learn", "--manifest", manifest, "--out", out, *png], [target])


LEARN_OPTIONS = [
    Opt("--fps", typical("30", "60"), number_text("30", "60", "120", "240")),
    TAU,
    Opt("--delta", typical("0.1", "0", "0.49"), number_text("0.1", "0", "0.49", "0.5")),
    Opt("--keyframes", typical("3", "0", "1"), number_text("3", "0", "1", "40", "1000")),
    STEPS,
    RATE,
    Opt("--out", typical("lib"), OUTPUT_NAMES, True),
]


@pytest.mark.slow
@given(options=chosen(LEARN_OPTIONS))
@fuzz(60)
def test_learn_with_random_options(
    valid: Valid, capsys: pytest.CaptureFixture[str], options: dict[str, str | None]
) -> None:
    with workspace(valid) as where:
        copy_library(valid, where)
        manifest = write_training(where / "clips.csv", training_rows(TRAINING_CLIPS[:2]))
        run_with_options(capsys, where, ["learn", "--manifest", manifest], options)


@pytest.mark.slow
@given(
    png=st.sampled_from(["png", "known.png", "new/dir", "no\x1b/x", ".", "png/squat1Reps.png"]),
    fps=st.sampled_from(["30", "7"]),
)
@fuzz(8)
def test_learn_png_directories(valid: Valid, capsys: pytest.CaptureFixture[str], png: str, fps: str) -> None:
    with workspace(valid) as where:
        out = copy_library(valid, where)
        (where / "png").mkdir()
        shutil.copy(valid.png, where / "png" / "squat1Reps.png")
        shutil.copy(valid.png, where / "known.png")
        manifest = write_training(where / "clips.csv", training_rows(TRAINING_CLIPS[:1]))
        argv = ["learn", "--manifest", manifest, "--out", out, "--png", where / png, "--fps", fps]
        run(capsys, where, argv, ["--png", where / png, "--fps", fps])


# -------------------------------------------------------------------------- in real processes

BINARY = b"{\n \x00\x01\x1b[31m\xff\xfe\x85 nan\r\n" + bytes(range(256))
"""Binary junk with control characters, bytes that are not UTF-8 and line breaks of every kind."""


@pytest.mark.slow
@pytest.mark.parametrize(
    "case", ["info-amc", "features-asf", "config", "index-build-amc", "index-info-npy", "search-keyframes",
             "search-npz", "learn-manifest"]
)  # fmt: skip
def test_damaged_inputs_in_a_real_process(valid: Valid, tmp_path: Path, case: str) -> None:
    """The same outcome from the ``mocapd`` program itself: one line, status 2, outputs unchanged."""
    prepare_search(valid, tmp_path)
    index = copy_index(valid, tmp_path)
    (tmp_path / "out.csv").write_text("known content\n")
    shutil.copy(valid.png, tmp_path / "out.png")
    asf, amc = RECORDING
    target = tmp_path / {"info-amc": "x.amc.gz", "features-asf": "x.asf", "config": "c.yaml"}.get(case, "x")
    if case == "info-amc":
        target.write_bytes(gzip.compress(gzip.decompress(amc.read_bytes())[:3000] + BINARY))
        argv: list[str | Path] = ["info", "--asf", asf, "--amc", target]
    elif case == "features-asf":
        target.write_bytes(asf.read_bytes()[:2000] + BINARY)
        argv = [
            "features",
            "--asf",
            target,
            "--amc",
            amc,
            "--csv",
            tmp_path / "out.csv",
            "--png",
            tmp_path / "out.png",
        ]
    elif case == "config":
        target.write_bytes(BINARY)
        argv = ["--config", target, "positions", "--asf", asf, "--amc", amc, "--csv", tmp_path / "out.csv"]
    elif case == "index-build-amc":
        target = tmp_path / "x.amc"
        target.write_bytes(gzip.decompress(INDEXED[1][1].read_bytes())[:5000])
        manifest = write_manifest(tmp_path / "db.csv", [INDEXED[0], (INDEXED[1][0], target)], extra=False)
        argv = ["index", "build", "--manifest", manifest, "--out", index]
    elif case == "index-info-npy":
        target = index / "upper.code.npy"
        target.write_bytes(target.read_bytes()[:100] + BINARY)
        argv = ["index", "info", index]
    elif case == "search-keyframes":
        target = tmp_path / "keyframes.json"
        target.write_bytes(target.read_bytes()[:500] + BINARY)
        argv = ["search", "--index", index, "--keyframes", target, "--class", "squat1Reps"]
    elif case == "search-npz":
        target = tmp_path / "lib" / "squat1Reps.npz"
        target.write_bytes(BINARY + target.read_bytes()[300:])
        argv = ["search", "--index", index, "--library", tmp_path / "lib", "--class", "squat1Reps"]
    else:
        target = tmp_path / "clips.csv"
        target.write_bytes(b"class,asf,amc\n" + BINARY)
        argv = ["learn", "--manifest", target, "--out", tmp_path / "lib"]
    before = snapshot(tmp_path)
    result = mocapd(*argv)
    check_outcome(result.returncode, result.stdout, result.stderr, [str(target)])
    assert result.returncode == 2
    assert snapshot(tmp_path) == before


@pytest.mark.slow
@pytest.mark.parametrize(
    ("options", "status"),
    [
        (["features", "--native-fps", "5e9"], 2),
        (["info", "--native-fps", "1e300"], 2),
        (["features", "--fps", "2.2e-309"], 2),
        (["features", "--png", "out.p\x1bng"], 2),
        (["keyframes", "--extend", "99999999999999999999,0"], 0),
        (["keyframes", "--extend", "9223372036854775807,9223372036854775807"], 0),
        (["library", "--keyframes", "--extend", "99999999999999999999,0"], 0),
    ],
)
def test_random_options_in_a_real_process(
    valid: Valid, tmp_path: Path, options: list[str], status: int
) -> None:
    """Option values that crashed mocapd (status 70: memory exhausted, int64 overflow) or were
    reported without naming the option, in the ``mocapd`` program itself."""
    prepare_search(valid, tmp_path)
    index = copy_index(valid, tmp_path)
    (tmp_path / "out.csv").write_text("known content\n")
    kind, *rest = options
    argv: list[str | Path]
    if kind in ("info", "features"):
        rest = [str(tmp_path / r) if r.startswith("out.") else r for r in rest]
        argv = [kind, "--asf", RECORDING[0], "--amc", RECORDING[1], *rest]
        argv += ["--csv", tmp_path / "out.csv"] if kind == "features" else []
    else:
        argv = [*search_argv(tmp_path, kind, index), *rest]
    before = snapshot(tmp_path)
    result = mocapd(*argv)
    check_outcome(result.returncode, result.stdout, result.stderr, [*rest[:2], *(printable(r) for r in rest)])
    assert result.returncode == status, result.stderr
    if result.returncode:
        assert snapshot(tmp_path) == before


# ------------------------------------------------------------------- the defects fuzzing found


def test_crafted_library_weights_are_refused(valid: Valid, capsys: pytest.CaptureFixture[str]) -> None:
    """A class file whose weights were edited (checksums made to match): a weight of 1e6 made the
    search run for minutes, 1e12 exhausted memory (status 70), 1e300 printed a numpy warning and a
    reason naming no file."""
    with workspace(valid) as where:
        prepare_search(valid, where)
        index = copy_index(valid, where)
        npz = where / "lib" / "squat1Reps.npz"
        for weight in (1e6, 1e12, 1e300, 1.5):
            with np.load(npz) as stored:
                arrays = {k: stored[k].copy() for k in stored.files}
            arrays["quantised_weights"][0] = weight
            reseal_library(where / "lib", "squat1Reps", arrays)
            assert run(capsys, where, search_argv(where, "library", index), [npz]) == 2


def test_crafted_index_names_every_array_it_checks_together(
    valid: Valid, capsys: pytest.CaptureFixture[str]
) -> None:
    """Segments that do not tile the documents were reported naming only the start array, also when
    the length array was the one edited; lists that do not match the codes named only the postings."""
    for file in ("mix.length.npy", "upper.code.npy"):
        with workspace(valid) as where:
            index = copy_index(valid, where)
            values = np.load(index / file)
            values[0] = values[0] + 1
            np.save(index / file, values)
            reseal_index(index, file)
            assert run(capsys, where, ["index", "info", index], [file]) == 2


def test_config_rate_and_characters_yaml_refuses(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """A config rate of 5e9 Hz exhausted memory (status 70); a control character gave "not valid
    YAML: ReaderError" with no line."""
    config = tmp_path / "config.yaml"
    argv = ["--config", config, "features", "--asf", RECORDING[0], "--amc", RECORDING[1], "--csv", "-"]
    config.write_text("replay:\n  frame_rate_hz: 5.0e+9\n")
    assert run(capsys, tmp_path, argv, [config]) == 2
    config.write_text("replay:\n  units: a\x01b\n")
    status = cli.main([str(a) for a in argv])
    assert (status, capsys.readouterr().err) == (
        2,
        f"mocapd: {config}:2: not valid YAML: character U+0001: special characters are not allowed\n",
    )
