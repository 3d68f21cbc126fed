"""What every benchmark shares: the data, the options, pinning to one core, loading the recordings,
and the per-frame forward kinematics used as the baseline."""

from __future__ import annotations

import argparse
import os
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from daemon.errors import MocapdError
from daemon.library import Library, default_library_path, load_library
from daemon.recordings import motion_features
from daemon.types import BoolArray, FloatArray
from replay import KinematicModel, Motion, Skeleton, read_amc, read_asf
from replay.catalog import CMU_SUBSTITUTES, recordings
from replay.kinematics import joint_positions

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "mocap"


def shipped_library() -> Library:
    """The library mocapd ships, or exit 1 saying how to build it."""
    try:
        return load_library(default_library_path())
    except MocapdError as e:
        print(f"no shipped library ({e}); build it with python -m bench.shipped_library")
        raise SystemExit(1) from None


def best_of(repeat: int, run: Callable[[], object]) -> float:
    times = []
    for _ in range(repeat):
        start = time.perf_counter()
        run()
        times.append(time.perf_counter() - start)
    return min(times)


def arguments(doc: str | None, **counts: int) -> argparse.Namespace:
    """``--repeat``, ``--data`` and an integer option per keyword (its default); pins the process to
    one core."""
    parser = argparse.ArgumentParser(description=doc, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--data", type=Path, default=DATA)
    for name, default in counts.items():
        parser.add_argument(f"--{name}", type=int, default=default)
    args = parser.parse_args()
    if hasattr(os, "sched_setaffinity"):
        os.sched_setaffinity(0, {min(os.sched_getaffinity(0))})
    return args


@dataclass(frozen=True)
class Recordings:
    pairs: list[tuple[Path, Path]]
    skeletons: dict[Path, Skeleton]
    models: dict[Path, KinematicModel]
    motions: list[Motion]

    @property
    def frames(self) -> int:
        return sum(len(m) for m in self.motions)

    def joints_cm(self) -> list[FloatArray]:
        """Every motion's standard joints in centimetres, each ``(N, 26, 3)``."""
        return [joint_positions(m) for m in self.motions]

    def features_at(self, rate: float) -> list[BoolArray]:
        """Every motion's features at ``rate`` Hz (computed at 120 Hz, then decimated), ``(N, 39)``."""
        return [motion_features(m, rate).matrix for m in self.motions]

    def with_models(self) -> list[tuple[KinematicModel, Motion]]:
        """Each motion with the kinematic model of its skeleton."""
        return [(self.models[asf], m) for (asf, _), m in zip(self.pairs, self.motions, strict=True)]

    def fk_per_frame(self) -> tuple[int, Callable[[], None]]:
        """The baseline: per-frame forward kinematics of every 20th frame; (frames, run)."""
        sample = [(model, m.channels[::20]) for model, m in self.with_models()]

        def run() -> None:
            for model, channels in sample:
                for row in channels:
                    model.positions_frame(row)

        return sum(len(c) for _, c in sample), run


def load(data: Path) -> Recordings:
    """Every ASF/AMC pair under ``data``, read whole."""
    pairs = recordings(data, CMU_SUBSTITUTES)
    skeletons = {asf: read_asf(asf) for asf in {a for a, _ in pairs}}
    models = {asf: KinematicModel(s) for asf, s in skeletons.items()}
    return Recordings(pairs, skeletons, models, [read_amc(amc, skeletons[asf]) for asf, amc in pairs])
