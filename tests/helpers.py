"""What several test modules share (test modules never import each other): where the real data is,
the clips the tests use, the ``mocapd`` subprocess runner and the checks of its output, and writers
of manifests. The recordings are read in place from ../shared/data/mocap, never copied."""

from __future__ import annotations

import dataclasses
import json
import subprocess
import sys
from collections.abc import Sequence
from pathlib import Path

from daemon.keyframes import parse_keyframe_queries
from daemon.library import ClassTemplate, Library, learn_class
from daemon.recordings import joint_positions, read_examples, read_recording
from daemon.types import FloatArray
from replay.catalog import CMU_SUBSTITUTES, recordings

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
