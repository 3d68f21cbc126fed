"""Shared fixtures: the real recordings in ../shared/data/mocap (read in place, never copied)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import numpy.typing as npt
import pytest

from replay import KinematicModel, read_amc, read_asf
from replay.catalog import CMU_SUBSTITUTES, find_skeleton, recordings

REPO = Path(__file__).resolve().parents[1]
SHARED = REPO.parent / "shared"
DATA = SHARED / "data" / "mocap"
ORACLE = SHARED / "reference" / "oracle"


def skeleton_for(amc: Path) -> Path:
    """The ASF that goes with a shared-data AMC file."""
    return find_skeleton(amc, DATA, CMU_SUBSTITUTES)


def all_pairs() -> list[tuple[Path, Path]]:
    """Every (ASF, AMC) pair in the shared data; subject 14 has no ASF and uses 13.asf (same topology)."""
    if not DATA.is_dir():
        raise RuntimeError(f"the shared motion data is missing: {DATA}")
    return recordings(DATA, CMU_SUBSTITUTES)


PAIRS = all_pairs()


def joints_cm(asf: Path, amc: Path) -> npt.NDArray[np.float64]:
    """The 26 standard joint positions of a recording in centimetres, shape ``(N, 26, 3)``."""
    skeleton = read_asf(asf)
    model = KinematicModel(skeleton)
    return model.joints(model.positions(read_amc(amc, skeleton).channels, "cm"))


def pair_id(pair: tuple[Path, Path]) -> str:
    return pair[1].name.removesuffix(".gz").removesuffix(".amc")


@pytest.fixture(scope="session")
def data_dir() -> Path:
    return DATA
