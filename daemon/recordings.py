"""Recordings in, features out: the one path from an ASF/AMC pair to its 39 features, and the
manifests that list recordings.

The pipeline (:func:`read_features`): read the recording, take its native rate (:func:`native_rate`:
the AMC's ``:SAMPLES-PER-SECOND``, else the configured default, 120 Hz), compute the joint positions in
centimetres, the 39 features at the native rate (the velocity windows are in milliseconds), then keep
every k-th frame from the first for a lower rate (the toolbox's ``1:4:end`` for 30 Hz). Everything
that turns recordings into features (``mocapd features``, the index, template learning, the tests and
the benchmarks) calls it.

A *manifest* is a CSV listing recordings: columns ``asf`` and ``amc`` (paths relative to the
manifest), a *training manifest* also ``class`` and optionally ``start_frame``, ``end_frame`` and
``actor`` (the person performing the clip; without the column, the ASF file stands for the person).
"""

from __future__ import annotations

import csv
import io
import os
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from daemon.checks import csv_records, read_structured, read_text
from daemon.errors import InputError, MocapdError
from daemon.features import last_sample, sample_rows, sampled_features, sampling_ratio
from daemon.frames import motion_runs
from daemon.types import (
    CLASS_NAME,
    DEFAULT_BRIDGE_S,
    DEFAULT_INDEX_RATE,
    DEFAULT_NATIVE_RATE,
    Band,
    BoolArray,
    FloatArray,
    IntArray,
    TrainingClip,
)
from replay import JOINT_NAMES, Motion, read_amc, read_asf
from replay.kinematics import joint_positions
from replay.rigs import BUILT_IN, RigMap, parse_rig_map, read_bvh_take

MAX_ACTOR = 200


class ManifestError(MocapdError, ValueError):
    """A manifest that cannot be used; ``str``: ``path:line: reason``."""


class RecordingError(MocapdError, ValueError):
    """A recording that reads but cannot be turned into features (non-finite positions); the message
    names the file."""


class RateError(RecordingError):
    """A rate that does not divide a recording's native rate; the message names the file."""


# ------------------------------------------------------------------------------------ the pipeline


def read_recording(asf: str | Path, amc: str | Path) -> Motion:
    """The whole AMC file ``amc`` read with the skeleton of ``asf``."""
    return read_amc(amc, read_asf(asf))


def native_rate(motion: Motion, default: float = DEFAULT_NATIVE_RATE) -> float:
    """The rate a recording was captured at: its AMC's ``:SAMPLES-PER-SECOND``, else ``default``
    (``config.yaml``'s ``replay.frame_rate_hz``)."""
    return motion.header.frame_rate or default


def continuous(
    motion: Motion, bridge_s: float = DEFAULT_BRIDGE_S, default_native_rate: float = DEFAULT_NATIVE_RATE
) -> Motion:
    """``motion`` with its missing frames interpolated as the daemon bridges lost poses
    (:func:`~daemon.frames.motion_runs`); :class:`RecordingError` naming the file and the frames
    for a gap longer than ``bridge_s`` seconds, which features, indexes and templates cannot span."""
    runs = motion_runs(motion, native_rate(motion, default_native_rate), bridge_s)
    if len(runs) > 1:
        a, b = int(runs[0].frames[-1]) + 1, int(runs[1].frames[0]) - 1
        raise RecordingError(
            f"frames {a}-{b} are missing, longer than the {bridge_s:g} s bridged: cut the recording there",
            path=motion.source,
        )
    return runs[0] if runs else motion


@dataclass(frozen=True)
class RecordingFeatures:
    """A recording's features at ``native_rate · per / step`` Hz: ``matrix`` shape ``(N, 39)`` and the
    AMC frame number of each row, ``frames`` shape ``(N,)`` (every ``step``-th frame from the first, or
    the frames :func:`daemon.features.sample_rows` names when ``per`` > 1); the
    recording has AMC frames ``first_amc_frame .. last_amc_frame``. ``heading`` shape ``(N,)``: the
    body's heading at each row (radians, unwrapped; :func:`body_heading`)."""

    matrix: BoolArray
    frames: IntArray
    native_rate: float
    step: int
    per: int
    first_amc_frame: int
    last_amc_frame: int
    heading: FloatArray

    @property
    def rate(self) -> float:
        return self.native_rate * self.per / self.step

    def rows(self, first: int, last: int) -> tuple[int, int]:
        """The first and last rows whose frames lie in AMC frames ``first .. last`` (the first after
        the last if none does)."""
        begin, step, per = self.first_amc_frame, self.step, self.per
        return last_sample(first - begin - 1, step, per) + 1, last_sample(last - begin, step, per)


def _sampling(native: float, rate: float | None, source: str | Path) -> tuple[int, int]:
    """``(step, per)`` from the native rate to ``rate`` (None: the native rate), or a
    :class:`RateError` naming ``source``."""
    if rate is None:
        return 1, 1
    try:
        return sampling_ratio(native, rate)
    except InputError as exc:
        raise RateError(str(exc), path=source) from None


def motion_features(
    motion: Motion, rate: float | None = None, default_native_rate: float = DEFAULT_NATIVE_RATE
) -> RecordingFeatures:
    """The features of ``motion`` at ``rate`` Hz (None: the native rate): those of the poses of every
    k-th frame from the first, joints in centimetres (:func:`daemon.features.sampled_features`, as
    the recogniser computes them)."""
    native = native_rate(motion, default_native_rate)
    step, per = _sampling(native, rate, motion.source)
    motion = continuous(motion, default_native_rate=default_native_rate)
    joints = joint_positions(motion)
    try:
        matrix = sampled_features(joints, JOINT_NAMES, native, step, per)
    except InputError as exc:
        raise RecordingError(str(exc), path=motion.source) from None
    rows = sample_rows(len(joints), step, per)
    return RecordingFeatures(
        matrix,
        motion.frames[rows],
        native,
        step,
        per,
        int(motion.frames[0]),
        int(motion.frames[-1]),
        _heading(joints[rows]),
    )


def read_features(
    asf: str | Path,
    amc: str | Path,
    rate: float | None = None,
    default_native_rate: float = DEFAULT_NATIVE_RATE,
) -> RecordingFeatures:
    """:func:`motion_features` of the recording ``asf``/``amc``."""
    return motion_features(read_recording(asf, amc), rate, default_native_rate)


def read_bvh_features(
    path: str | Path, rate: float | None = None, maps: Sequence[RigMap] = BUILT_IN
) -> RecordingFeatures:
    """The features of the BVH recording at ``path`` at ``rate`` Hz (None: its own rate), its rig
    mapped onto the standard joints by the first of ``maps`` that fits (:mod:`replay.rigs`; the
    file's units taken for centimetres), its frames numbered from 1."""
    take = read_bvh_take(path, maps)
    step, per = _sampling(take.rate, rate, path)
    try:
        matrix = sampled_features(take.joints, JOINT_NAMES, take.rate, step, per)
    except InputError as exc:
        raise RateError(str(exc), path=path) from None
    rows = sample_rows(len(take.joints), step, per)
    return RecordingFeatures(
        matrix, take.frames[rows], take.rate, step, per, 1, len(take.joints), _heading(take.joints[rows])
    )


def body_heading(joints: FloatArray, left: int, right: int) -> FloatArray:
    """The body's heading in the floor plane at each frame, shape ``(n,)`` in radians, unwrapped:
    the direction of the line from joint ``right`` to joint ``left`` (the hips) of ``joints`` shape
    ``(n, J, 3)``, y up."""
    across = joints[:, left] - joints[:, right]
    out: FloatArray = np.unwrap(np.arctan2(across[:, 2], across[:, 0]))
    return out


def _heading(joints: FloatArray) -> FloatArray:
    return body_heading(joints, JOINT_NAMES.index("lhip"), JOINT_NAMES.index("rhip"))


def read_rig_maps(paths: Sequence[str | Path]) -> tuple[RigMap, ...]:
    """The rig maps of the YAML files at ``paths``, in order, then the built-in ones
    (:data:`replay.rigs.BUILT_IN`); an error naming the file and the field for a bad one."""
    users = (parse_rig_map(read_structured(Path(p), "yaml", InputError), str(p)) for p in paths)
    return (*users, *BUILT_IN)


# --------------------------------------------------------------------------------------- manifests


def display_path(base: str | Path, written: str) -> str:
    """A path a manifest in the directory ``base`` wrote as ``written``, for a reader in the working
    directory: absolute as written; relative, resolved against ``base`` and then written relative to
    the working directory if it lies below it, else absolute. ``base`` "" leaves it as written."""
    path = Path(written)
    if path.is_absolute() or not str(base):
        return written
    full = Path(os.path.normpath(Path(base).absolute() / path))
    try:
        return str(full.relative_to(Path.cwd()))
    except ValueError:
        return str(full)


@dataclass(frozen=True)
class ManifestRow:
    """One recording of a manifest: ``asf_text``/``amc_text`` as written, ``asf``/``amc`` resolved
    against the manifest's directory; ``line`` is the row's (last) line in the manifest; ``extra``
    the row's other cells by lower-case column name."""

    line: int
    asf_text: str
    amc_text: str
    asf: Path
    amc: Path
    extra: Mapping[str, str] = field(default_factory=dict)
    bvh: Path | None = None
    """A BVH recording's path (then ``asf_text`` and ``amc_text`` are its path as written, and
    ``asf`` and ``amc`` are ``bvh``: what a library records of where its examples came from)."""


def read_manifest(
    path: str | Path, required: Sequence[str] = (), optional: Sequence[str] = (), *, bvh: bool = False
) -> list[ManifestRow]:
    """The rows of a manifest CSV whose header names the columns ``asf`` and ``amc`` (with ``bvh``:
    or the column ``bvh`` instead) and every column of ``required`` (in any order, among any others;
    ``optional`` only names the columns an error message mentions). ``extra`` holds each row's other
    cells by lower-case column name (empty cells of optional columns included). Blank lines are
    skipped. Raises :class:`ManifestError`."""
    path = Path(path)
    columns_wanted: tuple[str, ...] = ("asf", "amc", *required)
    files: tuple[str, ...] = ("asf", "amc")
    text = read_text(path, ManifestError)
    reader = csv.reader(io.StringIO(text, newline=""))
    header: list[str] | None = None
    columns: dict[str, int] = {}
    rows: list[ManifestRow] = []
    try:
        for record in reader:
            line = reader.line_num
            cells = [f.strip() for f in record]
            if not any(cells):
                continue
            if header is None:
                header = [f.lower() for f in cells]
                if bvh and "bvh" in header and "asf" not in header and "amc" not in header:
                    columns_wanted, files = ("bvh", *required), ("bvh",)
                for name in columns_wanted:
                    if header.count(name) != 1:
                        how = "lacks" if name not in header else "repeats"
                        raise ManifestError(
                            f"header {how} the column '{name}': {','.join(record)}", path=path, line=line
                        )
                    columns[name] = header.index(name)
                continue
            if len(cells) != len(header):
                raise ManifestError(
                    f"{len(cells)} fields, the header has {len(header)}", path=path, line=line
                )
            texts = {name: cells[i] for name, i in columns.items()}
            for name, value in texts.items():
                if not value:
                    raise ManifestError(f"the '{name}' field is blank", path=path, line=line)
            resolved = {name: path.parent / texts[name] for name in files}
            for name, file in resolved.items():
                if not file.is_file():
                    raise ManifestError(f"{name} file not found: {file}", path=path, line=line)
            others = {name: cells[i] for i, name in enumerate(header) if name not in files}
            if "bvh" in resolved:
                take = resolved["bvh"]
                rows.append(ManifestRow(line, texts["bvh"], texts["bvh"], take, take, others, bvh=take))
            else:
                rows.append(
                    ManifestRow(line, texts["asf"], texts["amc"], resolved["asf"], resolved["amc"], others)
                )
    except csv.Error as exc:
        raise ManifestError(f"not valid CSV: {exc}", path=path, line=reader.line_num) from None
    needs = ", ".join([*columns_wanted, *(f"[{c}]" for c in optional)])
    if header is None:
        raise ManifestError(
            f"empty manifest: no header line (it needs the columns {needs})", path=path, line=1
        )
    if not rows:
        raise ManifestError(
            "empty manifest: no recordings after the header", path=path, line=max(reader.line_num, 1)
        )
    return rows


@dataclass(frozen=True)
class TrainingRow:
    """One row of a training manifest: the class, the AMC frame range (None = whole clip) and the
    person performing it (``actor``: the manifest's ``actor`` cell, else the ASF path resolved)."""

    name: str
    row: ManifestRow
    start_frame: int | None
    end_frame: int | None
    actor: str


def read_training_manifest(path: str | Path) -> list[TrainingRow]:
    """The rows of a CSV with columns ``class, asf, amc`` and optionally ``start_frame, end_frame``
    (AMC frame numbers, inclusive; both or neither, per row) and ``actor``: the person performing
    the clip, which calibration keeps apart (leave one actor out). With the column, every row names
    its actor (a blank cell would silently make the ASF a second person); without it, the actor is
    the ASF path resolved (one skeleton file per person, as in HDM05 and CMU). Raises
    :class:`ManifestError` naming the file and line."""
    rows = read_manifest(path, required=("class",), optional=("start_frame", "end_frame", "actor"), bvh=True)
    out = []
    for row in rows:
        name = row.extra["class"]
        if not CLASS_NAME.fullmatch(name):
            raise ManifestError(
                f"class {name!r}: use letters, digits, '_', '.', '-' (it names a file)",
                path=path,
                line=row.line,
            )
        bounds = []
        for column in ("start_frame", "end_frame"):
            text = row.extra.get(column, "")
            try:
                bounds.append(int(text) if text else None)
            except ValueError:
                raise ManifestError(
                    f"{column} {text!r} is not an integer", path=path, line=row.line
                ) from None
        start, end = bounds
        if (start is None) != (end is None):
            raise ManifestError("give both start_frame and end_frame, or neither", path=path, line=row.line)
        if start is not None and end is not None and start > end:
            raise ManifestError(f"start_frame {start} is after end_frame {end}", path=path, line=row.line)
        out.append(TrainingRow(name, row, start, end, _actor(row, path)))
    return out


def _actor(row: ManifestRow, path: str | Path) -> str:
    if "actor" not in row.extra:
        return str(row.asf.resolve())
    actor = row.extra["actor"]
    if not actor:
        raise ManifestError(
            "the 'actor' field is blank: name the person of every row, or leave out the column",
            path=path,
            line=row.line,
        )
    if not actor.isprintable() or len(actor) > MAX_ACTOR:
        raise ManifestError(
            f"actor {actor[:60]!r}: at most {MAX_ACTOR} printable characters", path=path, line=row.line
        )
    return actor


# ---------------------------------------------------------------------------------------- examples


def read_example(
    item: TrainingRow,
    source: str | Path,
    *,
    rate: float,
    default_native_rate: float = DEFAULT_NATIVE_RATE,
    maps: Sequence[RigMap] = BUILT_IN,
) -> tuple[TrainingClip, BoolArray]:
    """The features of one training example at ``rate``, shape ``(frames, 39)``: computed over the
    whole recording (so velocities at the range's edges see their neighbours), then cut to the
    samples inside the frame range. ``source``: the manifest, for errors."""
    got, j0, j1, clip = _example_rows(item, source, rate, default_native_rate, maps)
    return clip, got.matrix[j0 : j1 + 1]


def _example_rows(
    item: TrainingRow, source: str | Path, rate: float, default_native_rate: float, maps: Sequence[RigMap]
) -> tuple[RecordingFeatures, int, int, TrainingClip]:
    """The recording's features, the first and last of its rows the example holds, and its clip."""
    if item.row.bvh is not None:
        got = read_bvh_features(item.row.bvh, rate, maps)
    else:
        got = read_features(item.row.asf, item.row.amc, rate, default_native_rate)
    first, last = got.first_amc_frame, got.last_amc_frame
    start = first if item.start_frame is None else item.start_frame
    end = last if item.end_frame is None else item.end_frame
    if start < first or end > last:
        raise ManifestError(
            f"frames {start}..{end} are outside the recording's {first}..{last}",
            path=source,
            line=item.row.line,
        )
    j0, j1 = got.rows(start, end)
    if j1 < j0:
        raise ManifestError(
            f"frames {start}..{end} hold no sample at {rate:g} Hz", path=source, line=item.row.line
        )
    clip = TrainingClip(item.row.asf_text, item.row.amc_text, start, end, j1 - j0 + 1, item.actor)
    return got, j0, j1, clip


Examples = dict[str, list[tuple[TrainingClip, BoolArray]]]


@dataclass(frozen=True)
class ExampleRows:
    """A training example as read: its ``clip``, its features ``matrix`` shape ``(n, 39)``, the AMC
    frame number of each row ``frames`` shape ``(n,)`` and the body's ``heading`` at each row shape
    ``(n,)`` (:func:`body_heading`)."""

    clip: TrainingClip
    matrix: BoolArray
    frames: IntArray
    heading: FloatArray


def read_example_rows(
    path: str | Path,
    *,
    rate: float = DEFAULT_INDEX_RATE,
    progress: Callable[[int, int, TrainingClip], object] | None = None,
    default_native_rate: float = DEFAULT_NATIVE_RATE,
    maps: Sequence[RigMap] = BUILT_IN,
) -> dict[str, list[ExampleRows]]:
    """Every class's training examples from a training manifest, in manifest order, at ``rate`` Hz
    (BVH takes through the first of ``maps`` that fits their rig); ``progress(done, total, clip)``
    after each."""
    rows = read_training_manifest(path)
    out: dict[str, list[ExampleRows]] = {}
    for i, item in enumerate(rows, start=1):
        got, j0, j1, clip = _example_rows(item, path, rate, default_native_rate, maps)
        at = slice(j0, j1 + 1)
        out.setdefault(item.name, []).append(
            ExampleRows(clip, got.matrix[at], got.frames[at], got.heading[at])
        )
        if progress is not None:
            progress(i, len(rows), clip)
    return out


def read_examples(
    path: str | Path,
    *,
    rate: float = DEFAULT_INDEX_RATE,
    progress: Callable[[int, int, TrainingClip], object] | None = None,
    default_native_rate: float = DEFAULT_NATIVE_RATE,
    maps: Sequence[RigMap] = BUILT_IN,
) -> Examples:
    """:func:`read_example_rows`, each example as its clip's provenance and its features."""
    read = read_example_rows(
        path, rate=rate, progress=progress, default_native_rate=default_native_rate, maps=maps
    )
    return {name: [(e.clip, e.matrix) for e in items] for name, items in read.items()}


def sample_index(frames: IntArray, first: int, last: int) -> IntArray:
    """The rows of ``frames`` (AMC frame numbers of the samples) inside ``first .. last``."""
    return np.flatnonzero((frames >= first) & (frames <= last))


# ------------------------------------------------------------------------------------------ labels


class LabelError(MocapdError, ValueError):
    """A labels file that cannot be used; the message names the file and line."""


@dataclass(frozen=True)
class Label:
    """A labelled segment: class ``name`` over AMC frames ``start_frame .. end_frame`` (inclusive)."""

    name: str
    start_frame: int
    end_frame: int


def read_labels(path: str | Path, trial: str | None = None) -> list[Label]:
    """The segments of a labels CSV with columns ``start_frame``, ``end_frame`` and ``class`` (or
    mocap6's ``label_name``), in file order. With a ``trial`` column (as mocap6's
    ``segments_120hz.csv``), only the rows of ``trial`` (e.g. ``13_29``; None: all). Raises
    :class:`LabelError` naming the file and line."""
    records = list(csv_records(path, LabelError, ("start_frame", "end_frame")))
    out = []
    for line, value in records:
        name = value.get("class") or value.get("label_name")
        if not name:
            raise LabelError("no class: give a 'class' (or 'label_name') field", path=path, line=line)
        if trial is not None and value.get("trial", trial) != trial:
            continue
        try:
            start, end = int(value["start_frame"]), int(value["end_frame"])
        except ValueError:
            raise LabelError("start_frame and end_frame must be integers", path=path, line=line) from None
        if start > end:
            raise LabelError(f"start_frame {start} is after end_frame {end}", path=path, line=line)
        out.append(Label(name, start, end))
    return out


BOUNDARY_TOLERANCE_S = 0.5
"""A labelled boundary's tolerance either side when the labels give none (mocap6's ± 60 frames at
120 Hz)."""


def read_boundaries(
    path: str | Path,
    trial: str | None = None,
    *,
    rate: float = 120.0,
    tolerance_s: float = BOUNDARY_TOLERANCE_S,
) -> list[Band]:
    """The true behaviour boundaries of a labels CSV, in AMC frame numbers, each with the frames a
    cut may fall on to find it (:class:`daemon.types.Band`). Two layouts: with columns
    ``end_frame``, ``end_lo`` and ``end_hi`` (as ``cmu86_segments.csv``), a boundary after each
    segment but the last (the next behaviour starts at ``end_frame + 1``; found by a cut starting
    it at ``end_lo + 1 .. end_hi + 1``), segments in the order of a ``segment`` column if there is
    one; otherwise the segments of :func:`read_labels` (``class`` or ``label_name``), a boundary at
    the first frame of each but the first, ± ``tolerance_s`` seconds at ``rate`` Hz. A ``trial``
    column filters the rows to ``trial`` (None: all). Raises :class:`LabelError` naming the file and
    line."""
    records = list(csv_records(path, LabelError, ("start_frame", "end_frame")))
    if records and {"end_lo", "end_hi"} <= records[0][1].keys():
        rows: list[tuple[int, int, int, int]] = []
        for line, value in records:
            if trial is not None and value.get("trial", trial) != trial:
                continue
            try:
                end, lo, hi = (int(value[k]) for k in ("end_frame", "end_lo", "end_hi"))
                order = int(value.get("segment", len(rows)))
            except ValueError:
                raise LabelError(
                    "end_frame, end_lo, end_hi and segment must be integers", path=path, line=line
                ) from None
            rows.append((order, end, lo, hi))
        rows.sort()
        return [Band(end + 1, lo + 1, hi + 1) for _, end, lo, hi in rows[:-1]]
    labels = sorted(read_labels(path, trial), key=lambda label: label.start_frame)
    reach = round(tolerance_s * rate)
    return [
        Band(label.start_frame, label.start_frame - reach, label.start_frame + reach) for label in labels[1:]
    ]
