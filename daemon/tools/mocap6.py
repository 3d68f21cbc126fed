"""The mocap6 exercise labels (Fox et al. 2014) of the CMU trials 13_29, 13_30 and 14_14 as training
rows of single repetitions: the file adapter around :mod:`daemon.tools.repetitions`.

``segments_120hz.csv`` (``../shared/data/mocap/annotations/mocap6/per_frame_120hz/``) has the columns
``trial,start_frame,end_frame,label_id,label_name``: one labelled run per row, AMC frame numbers at
120 Hz, inclusive. Each run of one of :data:`CLASSES` is cut into repetitions
(:func:`daemon.tools.repetitions.cut_run` on the run's features, computed over the whole recording so the
velocities at a run's edges see their neighbours, and its joint positions), and every repetition
becomes a :class:`RepetitionRow` ``(class, asf, amc, start_frame, end_frame, actor)``: a row of a
``mocapd learn`` manifest with the trial id as the actor, so a leave-one-out evaluation can treat the
trials as people.

**Subject 14 has no ASF in the data**: :func:`trial_recording` gives ``cmu/13/13.asf`` for 14_14
(:data:`replay.catalog.CMU_SUBSTITUTES`; same bones and channels, so the joint angles are exact, but
the positions carry subject 13's bone lengths).
"""

from __future__ import annotations

import csv
import io
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

from daemon.checks import csv_records
from daemon.errors import MocapdError
from daemon.features import sample_rows
from daemon.recordings import RecordingFeatures, motion_features, read_recording, sample_index
from daemon.tools.repetitions import Cutting, cut_run
from daemon.types import DEFAULT_INDEX_RATE, BoolArray, IntArray
from replay import Motion
from replay.catalog import CMU_SUBSTITUTES, find_skeleton
from replay.kinematics import joint_positions

CLASSES = ("JumpJack", "Twist", "ArmCircle", "ToeTouchOneHand", "KneeRaise", "Squat", "Jog")
"""The exercise classes taken from mocap6, spelled as mocap6 spells them."""

TRIALS = ("13_29", "13_30", "14_14")
"""The mocap6 trials whose AMC is in the shared data (13_31 and 14_20 are held out)."""

SEGMENTS = Path("annotations") / "mocap6" / "per_frame_120hz" / "segments_120hz.csv"
"""The labels file, below the data root (``../shared/data/mocap``)."""

COLUMNS = ("trial", "start_frame", "end_frame", "label_id", "label_name")
ROW_COLUMNS = ("class", "asf", "amc", "start_frame", "end_frame", "actor")


class Mocap6Error(MocapdError, ValueError):
    """A mocap6 labels file that cannot be used, or labels that do not fit their recording;
    ``str``: ``path:line: reason``."""


@dataclass(frozen=True)
class Segment:
    """One labelled run: AMC frames ``start_frame .. end_frame`` (120 Hz, inclusive) of ``trial``
    labelled ``label`` (id ``label_id``); ``line`` is its line in ``source``."""

    trial: str
    start_frame: int
    end_frame: int
    label_id: int
    label: str
    source: str
    line: int


def read_segments(path: str | Path) -> list[Segment]:
    """The rows of a ``segments_120hz.csv`` in file order. Raises :class:`Mocap6Error` naming the
    file and line for a missing column, a blank or non-integer field, a run ending before it starts
    and runs of one trial that overlap or are out of order; :class:`daemon.errors.FileAccessError`
    if the file cannot be read."""
    source = str(path)
    out: list[Segment] = []
    last: dict[str, Segment] = {}
    for line, value in csv_records(path, Mocap6Error, COLUMNS):
        numbers = {}
        for name in ("start_frame", "end_frame", "label_id"):
            try:
                numbers[name] = int(value[name])
            except ValueError:
                raise Mocap6Error(f"{name} {value[name]!r} is not an integer", path=path, line=line) from None
        start, end = numbers["start_frame"], numbers["end_frame"]
        if start > end:
            raise Mocap6Error(f"start_frame {start} is after end_frame {end}", path=path, line=line)
        segment = Segment(value["trial"], start, end, numbers["label_id"], value["label_name"], source, line)
        before = last.get(segment.trial)
        if before is not None and start <= before.end_frame:
            raise Mocap6Error(
                f"trial {segment.trial}: frames {start}..{end} start before the run of line "
                f"{before.line} ends ({before.end_frame})",
                path=path,
                line=line,
            )
        last[segment.trial] = segment
        out.append(segment)
    return out


def trial_recording(data_root: str | Path, trial: str) -> tuple[Path, Path]:
    """The (ASF, AMC) of the CMU trial ``trial`` (e.g. ``"13_29"``) below ``data_root``:
    ``cmu/<subject>/<trial>.amc.gz`` and the subject's ASF, which for subject 14 (no ASF in the data)
    is ``cmu/13/13.asf``."""
    root = Path(data_root)
    amc = root / "cmu" / trial.split("_")[0] / f"{trial}.amc.gz"
    return find_skeleton(amc, root, CMU_SUBSTITUTES), amc


@dataclass(frozen=True)
class RunCut:
    """One labelled run of a trial and its :class:`daemon.tools.repetitions.Cutting`; ``samples`` are the
    rows of the trial's features inside the run, shape ``(n,)``."""

    segment: Segment
    samples: IntArray
    cutting: Cutting

    def amc_frames(self, features: RecordingFeatures) -> list[tuple[int, int]]:
        """Each repetition's first and last AMC frame (inclusive)."""
        frames = features.frames[self.samples]
        return [(int(frames[r.start]), int(frames[r.end])) for r in self.cutting.repetitions]

    def cut_frames(self, features: RecordingFeatures) -> list[int]:
        """The AMC frames of the cuts."""
        return [int(features.frames[self.samples][c]) for c in self.cutting.cuts]


@dataclass(frozen=True)
class TrialCuts:
    """The runs of :data:`CLASSES` in one trial, cut: the trial's features (at the rate cut at) and
    one :class:`RunCut` per run, in file order."""

    trial: str
    features: RecordingFeatures
    runs: tuple[RunCut, ...]

    def anchors(self) -> dict[str, BoolArray]:
        """Per class, the features ``(39,)`` of the reference frame of its first run that gave
        repetitions: the phase the class was cut at."""
        out: dict[str, BoolArray] = {}
        for run in self.runs:
            if run.cutting.repetitions and run.segment.label not in out:
                out[run.segment.label] = self.features.matrix[run.samples[run.cutting.reference]]
        return out


def cut_trial(
    motion: Motion,
    segments: Sequence[Segment],
    trial: str,
    *,
    rate: float | None = DEFAULT_INDEX_RATE,
    classes: Sequence[str] = CLASSES,
    anchors: Mapping[str, BoolArray] | None = None,
) -> TrialCuts:
    """Cut every run of ``trial`` in ``segments`` labelled with one of ``classes`` into repetitions,
    on ``motion``'s features and joint positions at ``rate`` Hz (None: the native rate), each at the
    phase of its class's anchor if ``anchors`` has one (:func:`daemon.tools.repetitions.cut_run`). Raises
    :class:`Mocap6Error` naming the labels file and line if a run lies outside the recording."""
    anchors = {} if anchors is None else anchors
    features = motion_features(motion, rate)
    joints = joint_positions(motion)[sample_rows(len(motion.frames), features.step, features.per)]
    runs = []
    for segment in segments:
        if segment.trial != trial or segment.label not in classes:
            continue
        first, last = features.first_amc_frame, features.last_amc_frame
        if segment.start_frame < first or segment.end_frame > last:
            raise Mocap6Error(
                f"frames {segment.start_frame}..{segment.end_frame} are outside the recording's "
                f"{first}..{last} ({motion.source})",
                path=segment.source,
                line=segment.line,
            )
        samples = sample_index(features.frames, segment.start_frame, segment.end_frame)
        anchor = anchors.get(segment.label)
        cutting = cut_run(features.matrix[samples], features.rate, joints[samples], anchor=anchor)
        runs.append(RunCut(segment, samples, cutting))
    return TrialCuts(trial, features, tuple(runs))


def cut_trials(
    data_root: str | Path,
    segments: Sequence[Segment],
    trials: Sequence[str] = TRIALS,
    *,
    rate: float | None = DEFAULT_INDEX_RATE,
    classes: Sequence[str] = CLASSES,
) -> Iterator[tuple[Motion, TrialCuts]]:
    """Each of ``trials`` (below ``data_root``, :func:`trial_recording`) read and cut by
    :func:`cut_trial`, in order, every class at the phase it was first cut at (the anchors of the
    trials before)."""
    anchors: dict[str, BoolArray] = {}
    for trial in trials:
        motion = read_recording(*trial_recording(data_root, trial))
        cuts = cut_trial(motion, segments, trial, rate=rate, classes=classes, anchors=anchors)
        anchors = {**cuts.anchors(), **anchors}
        yield motion, cuts


@dataclass(frozen=True)
class RepetitionRow:
    """One repetition as a training row: ``name`` (the class), ``asf``/``amc`` as they are to be
    written, AMC frames ``start_frame .. end_frame`` (120 Hz, inclusive) and ``actor`` (the trial id);
    ``period`` (s) and ``confidence`` of its run."""

    name: str
    asf: str
    amc: str
    start_frame: int
    end_frame: int
    actor: str
    period: float
    confidence: float

    def cells(self) -> tuple[str, str, str, str, str, str]:
        """The row under :data:`ROW_COLUMNS`."""
        return (self.name, self.asf, self.amc, str(self.start_frame), str(self.end_frame), self.actor)


def repetition_rows(cuts: TrialCuts, asf: str, amc: str) -> list[RepetitionRow]:
    """One :class:`RepetitionRow` per repetition of ``cuts``, with the paths written as ``asf`` and
    ``amc`` and the trial id as the actor; runs without repetitions give none."""
    return [
        RepetitionRow(
            run.segment.label,
            asf,
            amc,
            start,
            end,
            cuts.trial,
            run.cutting.period_seconds,
            run.cutting.period.confidence,
        )
        for run in cuts.runs
        for start, end in run.amc_frames(cuts.features)
    ]


def rows_csv(rows: Sequence[RepetitionRow]) -> str:
    """``rows`` as CSV text under the header :data:`ROW_COLUMNS` (a ``mocapd learn`` manifest whose
    extra ``actor`` column the learner ignores)."""
    out = io.StringIO()
    writer = csv.writer(out, lineterminator="\n")
    writer.writerow(ROW_COLUMNS)
    writer.writerows(row.cells() for row in rows)
    return out.getvalue()
