"""The training set of the shipped library (:func:`daemon.library.default_library_path`): which clips
of ``../shared/data/mocap`` it is learned from, as rows of a ``mocapd learn`` manifest. The file
adapter that ``python -m bench.shipped_library`` builds the library with and the tests check the
shipped library against (a library learned from other clips than today's data gives is stale).

* **HDM05**: every cut clip of :data:`HDM05_CLASSES` by the actors :data:`HDM05_ACTORS`
  (``hdm05/cut/<class>/HDM_<actor>_<class>_<NNN>_120.amc.gz`` with ``hdm05/asf/HDM_<actor>.asf``,
  as ``bench.eval_templates.hdm05_clips`` finds them), whole clips; the actor is the HDM05 actor.
* **CMU / mocap6**: the exercise classes :data:`daemon.tools.mocap6.CLASSES` labelled in the trials
  :data:`daemon.tools.mocap6.TRIALS`, one row per single repetition as :func:`daemon.tools.mocap6.cut_trial`
  cuts it (at :data:`RATE` Hz); 14_14 is read with ``cmu/13/13.asf`` (there is no 14.asf). The
  actor is the CMU subject (``13`` or ``14``): 13_29 and 13_30 are the same person.

Rows are in that order (HDM05 by class directory and file name, then the trials in order); paths are
written relative to a ``base`` directory (the repository root: ``../shared/data/mocap/...``).
"""

from __future__ import annotations

import csv
import io
import os
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

from daemon.errors import MocapdError
from daemon.recordings import ManifestRow, TrainingRow
from daemon.tools import mocap6
from daemon.types import DEFAULT_INDEX_RATE

HDM05_CLASSES = (
    "depositFloorR",
    "elbowToKnee1RepsLelbowStart",
    "grabHighR",
    "hopBothLegs1hops",
    "jogLeftCircle4StepsRstart",
    "kickLFront1Reps",
    "lieDownFloor",
    "rotateArmsBothBackward1Reps",
    "sneak2StepsLStart",
    "squat1Reps",
    "throwBasketball",
)
"""The HDM05 classes of the shared data (actors bd, bk, dg)."""

HDM05_ACTORS = ("bd", "bk", "dg")
"""The HDM05 actors of the shared data (mm and tr are held out)."""

CMU_CLASSES = mocap6.CLASSES
"""The mocap6 exercise classes, spelled as mocap6 spells them."""

CLASSES = (*HDM05_CLASSES, *CMU_CLASSES)
"""Every class of the shipped library, 18."""

RATE = DEFAULT_INDEX_RATE
"""The rate the library is learned and the repetitions are cut at (Hz)."""

COLUMNS = ("class", "asf", "amc", "start_frame", "end_frame", "actor")
"""The manifest's columns (``start_frame``/``end_frame`` blank for a whole clip)."""


class ShippedDataError(MocapdError, ValueError):
    """The shared data does not hold what the shipped library is learned from."""


@dataclass(frozen=True)
class Row:
    """One training example: class ``name``, ``asf``/``amc`` as written (relative to the base),
    AMC frames ``start_frame .. end_frame`` (120 Hz, inclusive; None: the whole clip) and ``actor``."""

    name: str
    asf: str
    amc: str
    start_frame: int | None
    end_frame: int | None
    actor: str

    def cells(self) -> tuple[str, str, str, str, str, str]:
        """The row under :data:`COLUMNS`."""
        start = "" if self.start_frame is None else str(self.start_frame)
        end = "" if self.end_frame is None else str(self.end_frame)
        return (self.name, self.asf, self.amc, start, end, self.actor)


def _written(path: Path, base: Path) -> str:
    return Path(os.path.relpath(path.absolute(), base.absolute())).as_posix()


def hdm05_rows(data: Path, base: Path) -> list[Row]:
    """The HDM05 cut clips of :data:`HDM05_CLASSES` by :data:`HDM05_ACTORS` below ``data``."""
    out = []
    for amc in sorted((data / "hdm05" / "cut").glob("*/*.amc.gz")):
        name, actor = amc.parent.name, amc.name.split("_")[1]
        if name in HDM05_CLASSES and actor in HDM05_ACTORS:
            asf = data / "hdm05" / "asf" / f"HDM_{actor}.asf"
            out.append(Row(name, _written(asf, base), _written(amc, base), None, None, actor))
    return out


def cmu_rows(
    data: Path,
    base: Path,
    progress: Callable[[str, int], object] | None = None,
    trials: Sequence[str] = mocap6.TRIALS,
) -> list[Row]:
    """One row per repetition of the mocap6 runs of :data:`CMU_CLASSES` in ``trials`` below ``data``
    (cut by :func:`daemon.tools.mocap6.cut_trials`: each class at the phase of its first run), the CMU
    subject as the actor; ``progress(trial, repetitions)`` after each trial."""
    segments = mocap6.read_segments(data / mocap6.SEGMENTS)
    out = []
    for _, cuts in mocap6.cut_trials(data, segments, trials, rate=RATE, classes=CMU_CLASSES):
        trial = cuts.trial
        asf, amc = mocap6.trial_recording(data, trial)
        subject = trial.split("_")[0]
        rows = mocap6.repetition_rows(cuts, _written(asf, base), _written(amc, base))
        out += [Row(r.name, r.asf, r.amc, r.start_frame, r.end_frame, subject) for r in rows]
        if progress is not None:
            progress(trial, len(rows))
    return out


def training_rows(
    data: str | Path, base: str | Path, progress: Callable[[str, int], object] | None = None
) -> list[Row]:
    """Every training example of the shipped library below ``data`` (``../shared/data/mocap``),
    paths relative to ``base``: :func:`hdm05_rows`, then :func:`cmu_rows`. Raises
    :class:`ShippedDataError` if a class of :data:`CLASSES` has no example."""
    data, base = Path(data), Path(base)
    rows = hdm05_rows(data, base) + cmu_rows(data, base, progress)
    missing = [c for c in CLASSES if not any(r.name == c for r in rows)]
    if missing:
        raise ShippedDataError(f"no training examples of {', '.join(missing)}", path=data)
    return rows


def manifest_csv(rows: Sequence[Row]) -> str:
    """``rows`` as a ``mocapd learn`` manifest: CSV text under the header :data:`COLUMNS`."""
    out = io.StringIO()
    writer = csv.writer(out, lineterminator="\n")
    writer.writerow(COLUMNS)
    writer.writerows(r.cells() for r in rows)
    return out.getvalue()


def training_items(rows: Sequence[Row], base: str | Path) -> list[TrainingRow]:
    """``rows`` as the parsed rows of their manifest placed in ``base`` (what
    :func:`daemon.recordings.read_training_manifest` would give; line = the row's line in
    :func:`manifest_csv`), for :func:`daemon.recordings.read_example`."""
    base = Path(base)
    return [
        TrainingRow(
            r.name,
            ManifestRow(
                line, r.asf, r.amc, base / r.asf, base / r.amc, dict(zip(COLUMNS, r.cells(), strict=True))
            ),
            r.start_frame,
            r.end_frame,
            r.actor,
        )
        for line, r in enumerate(rows, start=2)
    ]
