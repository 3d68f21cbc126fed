"""Template libraries: what mocapd knows about each motion class, learned from labelled clips and
readable without them.

A library is a directory::

    LIB/library.json      {"format": "mocapd-templates", "version": 1, "rate": 30.0,
                           "features": [39 names, the row order of every template],
                           "classes": {name: {"file": "<name>.npz", "tau", "delta", "steps",
                                              "iterations", "training": [clip, ...],
                                              "keyframes": [keyframe, ...]}}}
    LIB/<name>.npz        soft, soft_weights, quantised, quantised_weights, hard, hard_weights

Templates are ``(39, K)`` float64 matrices (features in :data:`daemon.features.FEATURE_NAMES` order,
columns in frames at ``rate``) with weights ``(K,)``; the soft MT lies in [0, 1], the quantised and
hard MTs in {0, ½, 1}. A training clip is ``{"asf", "amc", "start_frame", "end_frame", "frames"}``
(AMC frame numbers, inclusive; ``frames`` at ``rate``). Keyframes use the entries of
``manual-keyframes.json`` (``set``, ``values``, ``position``, ``stiffness_to_next``), positions in
template columns. ``tau`` is the class's retrieval threshold, ``delta`` the quantisation threshold
and ``steps`` the DTW steps retrieval uses.
"""

from __future__ import annotations

import re
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from daemon.dtw import STEPS, Steps
from daemon.features import FEATURE_NAMES, BoolArray
from daemon.index_store import DEFAULT_NATIVE_RATE, ManifestError, ManifestRow, read_document, read_manifest
from daemon.keyframes import KeyframeError, KeyframeQuery, parse_keyframe_queries
from daemon.storage import JsonChecker, check_target, read_meta, replace_directory, write_json
from daemon.templates import MotionTemplate, learn

FORMAT = "mocapd-templates"
VERSION = 1
LIBRARY_JSON = "library.json"
ARRAYS = ("soft", "soft_weights", "quantised", "quantised_weights", "hard", "hard_weights")
CLASS_NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9_.-]*")


class LibraryFormatError(ValueError):
    """A library that cannot be loaded; the message names the file and the field."""


@dataclass(frozen=True)
class TrainingClip:
    """Where a training example came from: AMC frames ``start_frame .. end_frame`` of ``amc``
    (paths as the manifest wrote them), ``frames`` of them at the library's rate."""

    asf: str
    amc: str
    start_frame: int
    end_frame: int
    frames: int


@dataclass(frozen=True)
class ClassTemplate:
    """Everything retrieval and recognition need for one class."""

    name: str
    soft: MotionTemplate
    quantised: MotionTemplate
    hard: MotionTemplate
    keyframes: KeyframeQuery | None
    tau: float
    delta: float
    steps: Steps
    iterations: int
    training: tuple[TrainingClip, ...]


@dataclass(frozen=True)
class Library:
    """Classes learned at ``rate`` Hz."""

    rate: float
    classes: Mapping[str, ClassTemplate]

    def get(self, name: str) -> ClassTemplate:
        """The class ``name``; :class:`KeyError` listing the known classes otherwise."""
        try:
            return self.classes[name]
        except KeyError:
            raise KeyError(
                f"no class {name!r} in the library (it has {', '.join(sorted(self.classes))})"
            ) from None


# ----------------------------------------------------------------------------------- training data


@dataclass(frozen=True)
class TrainingRow:
    """One row of a training manifest: the class and the AMC frame range (None = whole clip)."""

    name: str
    row: ManifestRow
    start_frame: int | None
    end_frame: int | None


def read_training_manifest(path: str | Path) -> list[TrainingRow]:
    """The rows of a CSV with columns ``class, asf, amc`` and optionally ``start_frame, end_frame``
    (AMC frame numbers, inclusive; both or neither, per row). Raises :class:`ManifestError` naming
    the file and line."""
    rows = read_manifest(path, required=("class",))
    out = []
    for row in rows:
        name = row.extra["class"]
        if not CLASS_NAME.fullmatch(name):
            raise ManifestError(
                str(path), row.line, f"class {name!r}: use letters, digits, '_', '.', '-' (it names a file)"
            )
        bounds = []
        for column in ("start_frame", "end_frame"):
            text = row.extra.get(column, "")
            try:
                bounds.append(int(text) if text else None)
            except ValueError:
                raise ManifestError(str(path), row.line, f"{column} {text!r} is not an integer") from None
        start, end = bounds
        if (start is None) != (end is None):
            raise ManifestError(str(path), row.line, "give both start_frame and end_frame, or neither")
        if start is not None and end is not None and start > end:
            raise ManifestError(str(path), row.line, f"start_frame {start} is after end_frame {end}")
        out.append(TrainingRow(name, row, start, end))
    return out


def read_example(
    item: TrainingRow, rate: float = 30.0, default_native_rate: float = DEFAULT_NATIVE_RATE, source: str = ""
) -> tuple[TrainingClip, BoolArray]:
    """The features of one training example at ``rate``, shape ``(frames, 39)``: computed over the
    whole recording (so velocities at the range's edges see their neighbours), then cut to the
    samples inside the frame range."""
    document, matrix = read_document(item.row, rate, default_native_rate)
    first, last, step = document.first_amc_frame, document.last_amc_frame, document.step
    start = first if item.start_frame is None else item.start_frame
    end = last if item.end_frame is None else item.end_frame
    if start < first or end > last:
        raise ManifestError(
            source, item.row.line, f"frames {start}..{end} are outside the recording's {first}..{last}"
        )
    j0, j1 = -(-(start - first) // step), (end - first) // step
    if j1 < j0:
        raise ManifestError(source, item.row.line, f"frames {start}..{end} hold no sample at {rate:g} Hz")
    clip = TrainingClip(item.row.asf_text, item.row.amc_text, start, end, j1 - j0 + 1)
    return clip, matrix[j0 : j1 + 1]


def read_examples(
    path: str | Path,
    rate: float = 30.0,
    progress: Callable[[int, int, TrainingClip], None] | None = None,
    default_native_rate: float = DEFAULT_NATIVE_RATE,
) -> dict[str, list[tuple[TrainingClip, BoolArray]]]:
    """Every class's training examples from a training manifest, in manifest order."""
    rows = read_training_manifest(path)
    out: dict[str, list[tuple[TrainingClip, BoolArray]]] = {}
    for i, item in enumerate(rows, start=1):
        clip, matrix = read_example(item, rate, default_native_rate, str(path))
        out.setdefault(item.name, []).append((clip, matrix))
        if progress is not None:
            progress(i, len(rows), clip)
    return out


def learn_class(
    name: str,
    examples: Sequence[tuple[TrainingClip, BoolArray]],
    delta: float = 0.1,
    tau: float = 0.1,
    keyframes: int = 3,
    steps: Steps = "toolbox",
    rate: float = 30.0,
) -> ClassTemplate:
    """A class learned from its examples' ``(frames, 39)`` matrices at ``rate`` Hz: soft MT (toolbox
    strategy 5) and its quantisation by ``delta``, hard MT (thesis §3.3.1) and ``keyframes`` automatic
    keyframes from it (thesis ch. 6; 0 = none). ``steps``: the DTW steps retrieval will use; the
    toolbox's (1,1), (1,2), (2,1) by default, whose slopes between ½ and 2 keep a template from
    matching a much shorter or longer stretch (README: on HDM05 they raise precision at τ = 0.1 from
    0.09-0.6 to 0.3-1 on the weakest classes at the same recall)."""
    learned = learn([m for _, m in examples], delta, keyframes, name, rate)
    return ClassTemplate(
        name,
        learned.soft.template,
        learned.quantised,
        learned.hard.template,
        learned.keyframes,
        tau,
        delta,
        steps,
        learned.soft.iterations,
        tuple(clip for clip, _ in examples),
    )


# -------------------------------------------------------------------------------------- the format


def keyframe_entries(query: KeyframeQuery) -> list[dict[str, Any]]:
    """A keyframe query as entries of ``manual-keyframes.json``."""
    return [
        {
            "set": k.feature_set,
            "values": [0.5 if v == 0.5 else int(v) for v in k.values],
            "position": k.position,
            "stiffness_to_next": k.stiffness_to_next,
        }
        for k in query.keyframes
    ]


def save_library(library: Library, path: str | Path) -> None:
    """Write ``library`` as the directory ``path`` (replacing an earlier library or an empty
    directory; anything else raises :class:`FileExistsError`), never half written."""
    meta: dict[str, Any] = {
        "format": FORMAT,
        "version": VERSION,
        "rate": library.rate,
        "features": list(FEATURE_NAMES),
        "classes": {},
    }
    for name, c in library.classes.items():
        meta["classes"][name] = {
            "file": f"{name}.npz",
            "tau": c.tau,
            "delta": c.delta,
            "steps": c.steps,
            "iterations": c.iterations,
            "training": [vars(t) for t in c.training],
            "keyframes": [] if c.keyframes is None else keyframe_entries(c.keyframes),
        }

    def fill(temp: Path) -> None:
        for name, c in library.classes.items():
            arrays = {
                "soft": c.soft.values,
                "soft_weights": c.soft.weights,
                "quantised": c.quantised.values,
                "quantised_weights": c.quantised.weights,
                "hard": c.hard.values,
                "hard_weights": c.hard.weights,
            }
            with open(temp / f"{name}.npz", "wb") as out:
                np.savez(
                    out, allow_pickle=False, **{k: np.asarray(v, dtype=np.float64) for k, v in arrays.items()}
                )
        write_json(temp / LIBRARY_JSON, meta)

    replace_directory(Path(path), LIBRARY_JSON, "a mocapd template library", fill)


def check_library_target(path: str | Path) -> None:
    """Raise :class:`OSError` unless :func:`save_library` may write ``path``."""
    check_target(Path(path), LIBRARY_JSON, "a mocapd template library")


def load_library(path: str | Path) -> Library:
    """The library in directory ``path``. Raises :class:`LibraryFormatError` naming the file and the
    field if anything is missing or inconsistent."""
    path = Path(path)
    check, meta = read_meta(path, LIBRARY_JSON, "a mocapd template library", LibraryFormatError)
    root, rate = check.header(meta, {"format", "version", "rate", "features", "classes"}, FORMAT, VERSION)
    if root["features"] != list(FEATURE_NAMES):
        check.fail("features", "not the 39 features of this mocapd in its order")
    if not isinstance(root["classes"], dict) or not root["classes"]:
        check.fail("classes", "expected a non-empty object of class name -> class")
    classes = {}
    for name, entry in root["classes"].items():
        where = f"classes.{name}"
        if not CLASS_NAME.fullmatch(name):
            check.fail(where, "a class name uses letters, digits, '_', '.', '-'")
        keys = {"file", "tau", "delta", "steps", "iterations", "training", "keyframes"}
        e = check.mapping(entry, where, keys)
        if e["file"] != f"{name}.npz":
            check.fail(f"{where}.file", f"expected '{name}.npz', got {e['file']!r}")
        tau = check.positive_number(e["tau"], f"{where}.tau")
        delta = _number(check, e["delta"], f"{where}.delta", 0.0, 0.5)
        if e["steps"] not in STEPS:
            check.fail(f"{where}.steps", f"expected one of {', '.join(STEPS)}, got {e['steps']!r}")
        iterations = check.integer(e["iterations"], f"{where}.iterations")
        training = _training(check, e["training"], f"{where}.training")
        soft, quantised, hard = _templates(path / e["file"])
        keyframes = None
        if not isinstance(e["keyframes"], list):
            check.fail(f"{where}.keyframes", "expected a list (empty: no keyframes)")
        if e["keyframes"]:
            obj = {
                "frame_rate_hz": rate,
                "classes": {name: e["keyframes"]},
                "template_length": {name: hard.values.shape[1]},
            }
            try:
                keyframes = parse_keyframe_queries(obj, f"{check.source}: {where}.keyframes")[name]
            except KeyframeError as exc:
                raise LibraryFormatError(str(exc)) from None
        classes[name] = ClassTemplate(
            name, soft, quantised, hard, keyframes, tau, delta, e["steps"], iterations, training
        )
    return Library(rate, classes)


def _number(check: JsonChecker, value: object, field: str, low: float, high: float) -> float:
    if not isinstance(value, int | float) or isinstance(value, bool) or not low <= value < high:
        check.fail(field, f"expected a number in [{low:g}, {high:g}), got {value!r}")
    return float(value)


def _training(check: JsonChecker, value: object, where: str) -> tuple[TrainingClip, ...]:
    if not isinstance(value, list):
        check.fail(where, "expected a list of training clips")
    out = []
    for i, item in enumerate(value):
        here = f"{where}[{i}]"
        t = check.mapping(item, here, {"asf", "amc", "start_frame", "end_frame", "frames"})
        for key in ("asf", "amc"):
            if not isinstance(t[key], str) or not t[key]:
                check.fail(f"{here}.{key}", f"expected a path, got {t[key]!r}")
        start = check.integer(t["start_frame"], f"{here}.start_frame", minimum=None)
        end = check.integer(t["end_frame"], f"{here}.end_frame", minimum=start)
        frames = check.integer(t["frames"], f"{here}.frames", minimum=1)
        out.append(TrainingClip(t["asf"], t["amc"], start, end, frames))
    return tuple(out)


def _templates(file: Path) -> tuple[MotionTemplate, MotionTemplate, MotionTemplate]:
    if not file.is_file():
        raise LibraryFormatError(f"{file}: missing")
    try:
        with np.load(file, allow_pickle=False) as npz:
            arrays = {k: np.asarray(npz[k]) for k in npz.files}
    except (OSError, ValueError, EOFError) as exc:
        raise LibraryFormatError(f"{file}: not a readable .npz: {exc}") from None
    missing = set(ARRAYS) - arrays.keys()
    if missing:
        raise LibraryFormatError(f"{file}: missing arrays {', '.join(sorted(missing))}")
    out = []
    for kind in ("soft", "quantised", "hard"):
        values, weights = arrays[kind], arrays[f"{kind}_weights"]
        if values.dtype != np.float64 or values.ndim != 2 or values.shape[0] != len(FEATURE_NAMES):
            raise LibraryFormatError(f"{file}: {kind}: expected a float64 (39, K) array, got {values.shape}")
        if values.shape[1] < 1 or weights.shape != (values.shape[1],) or weights.dtype != np.float64:
            raise LibraryFormatError(
                f"{file}: {kind}_weights: expected {values.shape[1]} float64 weights, got {weights.shape}"
            )
        if not np.all(np.isfinite(weights) & (weights > 0)):
            raise LibraryFormatError(f"{file}: {kind}_weights: weights must be positive and finite")
        if kind == "soft":
            if not np.all((values >= 0) & (values <= 1)):
                raise LibraryFormatError(f"{file}: soft: values must lie in [0, 1]")
        elif not np.all(np.isin(values, (0.0, 0.5, 1.0))):
            raise LibraryFormatError(f"{file}: {kind}: values must be 0, 0.5 or 1")
        out.append(MotionTemplate(values, weights))
    return out[0], out[1], out[2]
