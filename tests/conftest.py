"""Shared fixtures: the real recordings in ../shared/data/mocap (read in place, never copied)."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
SHARED = REPO.parent / "shared"
DATA = SHARED / "data" / "mocap"
ORACLE = SHARED / "reference" / "oracle"


def skeleton_for(amc: Path) -> Path:
    """The ASF that goes with an AMC file: CMU subject's own (13.asf for subject 14, which has none),
    HDM05 actor's ``HDM_<actor>.asf``."""
    name = amc.name
    match = re.match(r"HDM_([a-z]+)_", name)
    if match:
        return DATA / "hdm05" / "asf" / f"HDM_{match.group(1)}.asf"
    subject = name.split("_")[0]
    if subject == "14":
        subject = "13"
    return DATA / "cmu" / subject / f"{subject}.asf"


def all_pairs() -> list[tuple[Path, Path]]:
    """Every (ASF, AMC) pair in the shared data, sorted by AMC path."""
    if not DATA.is_dir():
        raise RuntimeError(f"the shared motion data is missing: {DATA}")
    amcs = sorted(DATA.rglob("*.amc.gz")) + sorted(DATA.rglob("*.amc"))
    return [(skeleton_for(a), a) for a in amcs]


PAIRS = all_pairs()


def pair_id(pair: tuple[Path, Path]) -> str:
    return pair[1].name.removesuffix(".gz").removesuffix(".amc")


@pytest.fixture(scope="session")
def data_dir() -> Path:
    return DATA
