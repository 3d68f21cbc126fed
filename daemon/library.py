"""Template libraries: what mocapd knows about each motion class, learned from labelled clips and
readable without them.

A library is a directory::

    LIB/library.json      {"format": "mocapd-templates", "version": 4, "rate": 30.0,
                           "features": [39 names, the row order of every template],
                           "classes": {name: {"file": "<name>.npz", "sha256": {array: hex},
                                              "tau", "calibration", "delta", "steps",
                                              "iterations", "training": [clip, ...],
                                              "keyframes": [keyframe, ...],
                                              "mode", "mode_reason", "members": [member, ...],
                                              ["keyframe_source": "published"], ["slack": frames],
                                              ["window": [before, after]]}}}
    LIB/<name>.npz        soft, soft_weights, quantised, quantised_weights, hard, hard_weights
                          [, member1, member1_weights, ...]

Templates are ``(39, K)`` float64 matrices (features in :data:`daemon.features.FEATURE_NAMES` order,
columns in frames at ``rate``) with weights ``(K,)``; the soft MT lies in [0, 1], the quantised and
hard MTs in {0, ½, 1}. A training clip is ``{"asf", "amc", "start_frame", "end_frame", "frames",
"actor"}`` (AMC frame numbers, inclusive; ``frames`` at ``rate``; ``actor`` the person). Keyframes use
the entries of ``manual-keyframes.json`` (``set``, ``values``, ``position``, ``stiffness_to_next``,
and ``mismatches``, written only when not 0: how many fixed entries a frame may miss,
:class:`daemon.keyframes.Keyframe`), positions in template columns. ``tau`` is the class's retrieval
threshold and ``calibration`` how it was obtained (:class:`Calibration` without its τ: ``{"method",
"folds", "positives", "negatives", "recall", "precision"}``; folds 0 and recall and precision null for
a τ given, not calibrated), ``delta`` the quantisation threshold and ``steps`` the DTW steps retrieval
uses. ``mode`` (:data:`MODES`) says how the live recogniser finds the class, ``mode_reason`` why;
``members`` are the class's other templates (:class:`Variant`: ``{"tau", "calibration", "examples"}``,
the array ``member<i>`` its quantised template). ``sha256`` holds the SHA-256 of each array, checked
on loading, so arrays damaged, swapped or edited are refused. A class's arrays are read only when the
class is loaded, so a damaged class file does not keep the others from being used.

``window`` (optional) is the frames a keyframe-first class's confirmation window opens before a
keyframe match's range and after the frame that completes it, as its training examples needed
(absent: from the template's geometry), and ``slack`` (optional, 0 if absent) the frames more on
each side (:func:`daemon.recognizer.window_extent`).
``keyframe_source`` (optional) says where the keyframes come from: absent or ``"learned"``, the
automatic keyframes learned with the templates; ``"published"``, keyframes given to ``mocapd learn
--keyframes FILE`` (e.g. the Bonn toolbox's ``manual-keyframes.json``, positions in the columns of
the published template at ``rate``). A library directory may hold other files beside its own
(``extra`` of :func:`save_library`), which loading ignores.

**The shipped library.** :func:`default_library_path` is the library that ships inside the package
(:data:`DEFAULT_LIBRARY`): 18 classes learned by ``python -m bench.shipped_library`` from the HDM05
and CMU clips of ``../shared/data/mocap``, with the training manifest it used (``training.csv``,
paths relative to the repository root), so recognising needs no training step.

Version 3 (no ``mode``, no ``members``) loads with every class gated by its keyframes, as it was
recognised. Version 2 (no ``calibration``, no ``actor``) still loads: its τ is marked given, not
calibrated, and each clip's actor is its ASF path. Version 1 is refused with the advice to learn it
again.
"""

from __future__ import annotations

from collections.abc import Collection, Mapping
from dataclasses import dataclass
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np

from daemon.checks import Checker
from daemon.dtw import STEPS, Steps
from daemon.errors import MocapdError
from daemon.features import FEATURE_NAMES
from daemon.keyframes import KeyframeQuery, parse_keyframes
from daemon.storage import checksum, read_meta
from daemon.templates import MotionTemplate
from daemon.types import CLASS_NAME, N_FEATURES, TrainingClip

FORMAT = "mocapd-templates"
VERSION = 4
VERSIONS = (2, 3, 4)
LIBRARY_JSON = "library.json"
WHAT = "a mocapd template library"
ARRAYS = ("soft", "soft_weights", "quantised", "quantised_weights", "hard", "hard_weights")
MAX_WEIGHT = 1.5
"""Every weight of a learned template is below this (:func:`daemon.learn.templates.balance`)."""
CLASS_KEYS_V2 = ("file", "sha256", "tau", "delta", "steps", "iterations", "training", "keyframes")
CLASS_KEYS_V3 = (*CLASS_KEYS_V2, "calibration")
CLASS_KEYS = (*CLASS_KEYS_V3, "mode", "mode_reason", "members")
CALIBRATION_KEYS = ("method", "folds", "positives", "negatives", "recall", "precision")
MEMBER_KEYS = ("tau", "calibration", "examples")
CLASS_OPTIONAL = ("keyframe_source", "slack", "window")
"""Optional fields of a version 3 or 4 class entry."""
CLIP_KEYS_V2 = ("asf", "amc", "start_frame", "end_frame", "frames")
V2_TAU = "a version 2 library"
LEARNED = "learned"
PUBLISHED = "published"
KEYFRAME_SOURCES = (LEARNED, PUBLISHED)
"""Where a class's keyframes come from (``keyframe_source``)."""
GATED = "keyframes"
DTW = "dtw"
MODES = (GATED, DTW)
"""How the live recogniser finds a class's motions: a stream-wide DTW match counts only where a
keyframe match of the class overlaps it (``keyframes``), or every one counts (``dtw``)."""
DEFAULT_LIBRARY = "data/library"
"""The shipped library: this directory inside the ``daemon`` package (package data, installed with
it; :func:`default_library_path`). Rebuilt by ``python -m bench.shipped_library``, which writes
``library.json``, one ``<class>.npz`` per class and ``training.csv``, the training manifest."""


GIVEN = "given, not calibrated"


@dataclass(frozen=True)
class Calibration:
    """How a class's retrieval threshold ``tau`` was obtained: ``method`` in words, the number of
    ``folds`` (0: τ was given, not calibrated), the pooled ``positives`` (motions of the class in
    the left-out streams) and ``negatives`` (wrong detections at the largest τ tried) and the
    ``recall`` and ``precision`` τ gave on them (None when not calibrated)."""

    tau: float
    method: str
    folds: int = 0
    positives: int = 0
    negatives: int = 0
    recall: float | None = None
    precision: float | None = None

    @property
    def calibrated(self) -> bool:
        return self.folds > 0


def given(tau: float, why: str = "") -> Calibration:
    """A τ taken as given (``why``: the reason, shown after the method)."""
    return Calibration(tau, f"{GIVEN} ({why})" if why else GIVEN)


def default_library_path() -> Path:
    """The directory of the library that ships with mocapd (:data:`DEFAULT_LIBRARY`), found with
    :mod:`importlib.resources`, so it is the installed package's copy in an installed mocapd and
    the repository's in an editable install. Raises :class:`LibraryFormatError` if the package was
    installed without it (or not as plain files)."""
    path = Path(str(resources.files("daemon").joinpath(*DEFAULT_LIBRARY.split("/"))))
    if not (path / LIBRARY_JSON).is_file():
        raise LibraryFormatError(
            f"not {WHAT} (no {LIBRARY_JSON}): mocapd was installed without its shipped library; "
            "rebuild it with python -m bench.shipped_library",
            path=path,
        )
    return path


class LibraryFormatError(MocapdError, ValueError):
    """A library that cannot be loaded; the message names the file and the field."""


class UnknownClassError(MocapdError, KeyError):
    """A class the library does not have; the message lists the ones it has."""


@dataclass(frozen=True)
class Variant:
    """Another template of a class, for a style its own template does not cover: the quantised
    template learned from some of the class's examples (``examples``: their indices in its
    ``training``), with its own τ and how that was obtained."""

    quantised: MotionTemplate
    tau: float
    calibration: Calibration
    examples: tuple[int, ...]


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
    calibration: Calibration | None = None
    """How ``tau`` was obtained; None: given, not calibrated (as :func:`daemon.learn.calibration.given`)."""
    keyframe_source: str = LEARNED
    """Where ``keyframes`` come from, one of :data:`KEYFRAME_SOURCES`."""
    mode: str = ""
    """How the live recogniser finds the class, one of :data:`MODES` ("": keyframes if the class
    has any, else dtw)."""
    mode_reason: str = ""
    """Why that mode (how learning chose it)."""
    variants: tuple[Variant, ...] = ()
    """More templates of the class beside ``quantised`` (one per style: learning chooses how many)."""
    slack: int = 0
    """Keyframes first: the frames a window opens beyond what the training examples need on each
    side (:func:`daemon.recognizer.window_extent`; learning chooses it by folds)."""
    extent: tuple[int, int] | None = None
    """Keyframes first: the frames before a keyframe match's range and after the frame that
    completes it that the training examples need (:func:`daemon.recognizer.learned_extent`); None:
    the template's geometry."""

    def __post_init__(self) -> None:
        if self.keyframe_source not in KEYFRAME_SOURCES:
            raise ValueError(
                f"keyframe_source must be one of {KEYFRAME_SOURCES}, got {self.keyframe_source!r}"
            )
        if not self.mode:
            object.__setattr__(self, "mode", DTW if self.keyframes is None else GATED)
        if self.mode not in MODES:
            raise ValueError(f"mode must be one of {MODES}, got {self.mode!r}")
        if self.mode == GATED and self.keyframes is None:
            raise ValueError(f"class {self.name}: the keyframes mode needs keyframes")
        if isinstance(self.slack, bool) or not isinstance(self.slack, int) or self.slack < 0:
            raise ValueError(f"class {self.name}: slack must be frames >= 0, got {self.slack!r:.60}")
        if self.extent is not None and (
            len(self.extent) != 2
            or any(isinstance(x, bool) or not isinstance(x, int) or x < 0 for x in self.extent)
        ):
            raise ValueError(
                f"class {self.name}: extent must be two frame counts >= 0, got {self.extent!r:.60}"
            )

    @property
    def members(self) -> tuple[tuple[MotionTemplate, float], ...]:
        """The class's templates and their τ, the quantised template first."""
        return ((self.quantised, self.tau), *((v.quantised, v.tau) for v in self.variants))

    @property
    def provenance(self) -> Calibration:
        """:attr:`calibration`, a given τ's record when there is none."""
        return given(self.tau) if self.calibration is None else self.calibration


@dataclass(frozen=True)
class Library:
    """Classes learned at ``rate`` Hz."""

    rate: float
    classes: Mapping[str, ClassTemplate]

    def get(self, name: str) -> ClassTemplate:
        """The class ``name``; :class:`UnknownClassError` listing the known classes otherwise."""
        try:
            return self.classes[name]
        except KeyError:
            raise _unknown(name, self.classes) from None


def _unknown(name: str, known: Collection[str], path: Path | None = None) -> UnknownClassError:
    return UnknownClassError(
        f"no class {name!r} in the library (it has {', '.join(sorted(known))})", path=path
    )


# -------------------------------------------------------------------------------------- the format


def library_classes(path: str | Path) -> list[str]:
    """The names of the classes of the library in ``path`` (its metadata checked, no arrays read)."""
    return list(_read(Path(path))[2])


def load_library(path: str | Path, names: Collection[str] | None = None) -> Library:
    """The library in directory ``path``: every class, or only those of ``names`` (whose arrays
    alone are then read; a name the library lacks raises :class:`UnknownClassError`). Raises
    :class:`LibraryFormatError` naming the file and the field if anything is missing, damaged or
    inconsistent."""
    path = Path(path)
    check, rate, entries = _read(path)
    wanted = list(entries) if names is None else list(names)
    for name in wanted:
        if name not in entries:
            raise _unknown(name, entries, path)
    classes = {}
    for name in wanted:
        where = f"classes.{name}"
        e = entries[name]
        soft, quantised, hard, members = _templates(path / e["file"], e["sha256"], len(e["members"]))
        keyframes = None
        if e["keyframes"]:
            keyframes = parse_keyframes(e["keyframes"], check, f"{where}.keyframes", name, rate, hard.length)
        classes[name] = ClassTemplate(
            name,
            soft,
            quantised,
            hard,
            keyframes,
            e["tau"],
            e["delta"],
            e["steps"],
            e["iterations"],
            e["training"],
            e["calibration"],
            e["keyframe_source"],
            e["mode"],
            e["mode_reason"],
            tuple(
                Variant(t, m["tau"], m["calibration"], m["examples"])
                for t, m in zip(members, e["members"], strict=True)
            ),
            e["slack"],
            e["window"],
        )
    return Library(rate, classes)


def _calibration(check: Checker, value: object, where: str, tau: float) -> Calibration:
    e = check.mapping(value, where, CALIBRATION_KEYS)
    method = check.string(e["method"], f"{where}.method")
    counts = [check.integer(e[k], f"{where}.{k}") for k in ("folds", "positives", "negatives")]
    rates: list[float | None] = []
    for k in ("recall", "precision"):
        if e[k] is None:
            if counts[0]:
                check.fail(f"{where}.{k}", "a calibrated tau (folds > 0) needs a number in [0, 1]")
            rates.append(None)
        else:
            rates.append(check.number(e[k], f"{where}.{k}", low=0, high=1))
    return Calibration(tau, method, counts[0], counts[1], counts[2], rates[0], rates[1])


def _read(path: Path) -> tuple[Checker, float, dict[str, dict[str, Any]]]:
    """library.json checked: its checker, the rate, and each class's entry (numbers as floats,
    training clips as :class:`TrainingClip`)."""
    check, meta = read_meta(path, LIBRARY_JSON, WHAT, LibraryFormatError)
    keys = ("format", "version", "rate", "features", "classes")
    root = check.header(meta, keys, FORMAT, VERSIONS, "learn it again with mocapd learn")
    version = root["version"]
    rate = check.positive_number(root["rate"], "rate")
    if root["features"] != list(FEATURE_NAMES):
        check.fail("features", f"not the {N_FEATURES} features of this mocapd in its order")
    classes = check.mapping(root["classes"], "classes", others=True)
    if not classes:
        check.fail("classes", "must name at least one class")
    entries = {}
    for name, entry in classes.items():
        where = f"classes.{name}"
        if not CLASS_NAME.fullmatch(name):
            check.fail(where, "a class name uses letters, digits, '_', '.', '-'")
        if version == VERSION:
            e = dict(check.mapping(entry, where, CLASS_KEYS, CLASS_OPTIONAL))
        elif version == 3:
            e = dict(check.mapping(entry, where, CLASS_KEYS_V3, CLASS_OPTIONAL))
        else:
            e = dict(check.mapping(entry, where, CLASS_KEYS_V2))
        e["keyframe_source"] = check.choice(
            e.get("keyframe_source", LEARNED), f"{where}.keyframe_source", KEYFRAME_SOURCES
        )
        e["slack"] = check.integer(e.get("slack", 0), f"{where}.slack")
        window = e.get("window")
        if window is not None:
            pair = check.listing(window, f"{where}.window")
            if len(pair) != 2:
                check.fail(f"{where}.window", f"must be [before, after], got {len(pair)} entries")
            window = tuple(check.integer(x, f"{where}.window[{i}]") for i, x in enumerate(pair))
        e["window"] = window
        if e["file"] != f"{name}.npz":
            check.fail(f"{where}.file", f"must be '{name}.npz', got {e['file']!r:.60}")
        members = check.listing(e.get("members", []), f"{where}.members")
        arrays = (*ARRAYS, *(f"member{i}{w}" for i in range(1, len(members) + 1) for w in ("", "_weights")))
        sums = check.mapping(e["sha256"], f"{where}.sha256", arrays)
        for a in arrays:
            check.string(sums[a], f"{where}.sha256.{a}")
        e["tau"] = check.positive_number(e["tau"], f"{where}.tau")
        e["delta"] = check.number(e["delta"], f"{where}.delta", low=0, high=0.5, high_open=True)
        check.choice(e["steps"], f"{where}.steps", STEPS)
        e["iterations"] = check.integer(e["iterations"], f"{where}.iterations")
        e["training"] = _training(check, e["training"], f"{where}.training", version)
        if version >= 3:
            e["calibration"] = _calibration(check, e["calibration"], f"{where}.calibration", e["tau"])
        else:
            e["calibration"] = given(e["tau"], V2_TAU)
        check.listing(e["keyframes"], f"{where}.keyframes")
        if version == VERSION:
            check.choice(e["mode"], f"{where}.mode", MODES)
            if e["mode"] == GATED and not e["keyframes"]:
                check.fail(f"{where}.mode", "the keyframes mode needs keyframes")
            if not isinstance(e["mode_reason"], str):
                check.fail(f"{where}.mode_reason", f"must be a string, got {e['mode_reason']!r:.60}")
        else:  # gated by their keyframes, as those versions were recognised
            e["mode"], e["mode_reason"] = "", ""
        e["members"] = [
            _member(check, m, f"{where}.members[{i}]", len(e["training"])) for i, m in enumerate(members)
        ]
        entries[name] = e
    return check, rate, entries


def _member(check: Checker, value: object, where: str, clips: int) -> dict[str, Any]:
    m = dict(check.mapping(value, where, MEMBER_KEYS))
    m["tau"] = check.positive_number(m["tau"], f"{where}.tau")
    m["calibration"] = _calibration(check, m["calibration"], f"{where}.calibration", m["tau"])
    examples = check.listing(m["examples"], f"{where}.examples", nonempty=True)
    m["examples"] = tuple(
        check.integer(x, f"{where}.examples[{i}]", maximum=clips - 1) for i, x in enumerate(examples)
    )
    return m


def _training(check: Checker, value: object, where: str, version: int) -> tuple[TrainingClip, ...]:
    out = []
    keys = CLIP_KEYS_V2 if version < 3 else (*CLIP_KEYS_V2, "actor")
    for i, item in enumerate(check.listing(value, where)):
        here = f"{where}[{i}]"
        t = check.mapping(item, here, keys)
        asf, amc = check.string(t["asf"], f"{here}.asf"), check.string(t["amc"], f"{here}.amc")
        start = check.integer(t["start_frame"], f"{here}.start_frame", minimum=None)
        end = check.integer(t["end_frame"], f"{here}.end_frame", minimum=start)
        frames = check.integer(t["frames"], f"{here}.frames", minimum=1)
        actor = check.string(t["actor"], f"{here}.actor") if "actor" in t else asf
        out.append(TrainingClip(asf, amc, start, end, frames, actor))
    return tuple(out)


def _templates(
    file: Path, sums: Mapping[str, str], members: int = 0
) -> tuple[MotionTemplate, MotionTemplate, MotionTemplate, list[MotionTemplate]]:
    """The soft, quantised and hard templates of a class file and its ``members`` other quantised
    templates, their checksums and values checked."""
    if not file.is_file():
        raise LibraryFormatError("missing", path=file)
    try:
        with np.load(file, allow_pickle=False) as npz:
            arrays = {k: np.asarray(npz[k]) for k in npz.files}
    except Exception as exc:  # any failure to decode an untrusted file means the file is damaged
        reason = str(exc).split("\n")[0] or type(exc).__name__
        raise LibraryFormatError(f"not a readable .npz: {reason}", path=file) from None
    kinds = ["soft", "quantised", "hard", *(f"member{i}" for i in range(1, members + 1))]
    names = [n for kind in kinds for n in (kind, f"{kind}_weights")]
    missing = [a for a in names if a not in arrays]
    if missing:
        raise LibraryFormatError(f"missing arrays {', '.join(missing)}", path=file)
    for a in names:
        if checksum(arrays[a]) != sums[a]:
            raise LibraryFormatError(f"{a}: SHA-256 differs from library.json's", path=file)
    out = []
    for kind in kinds:
        values, weights = arrays[kind], arrays[f"{kind}_weights"]
        if values.dtype != np.float64 or values.ndim != 2 or values.shape[0] != N_FEATURES:
            raise LibraryFormatError(
                f"{kind}: expected a float64 ({N_FEATURES}, K) array, got {values.dtype} {values.shape}",
                path=file,
            )
        if values.shape[1] < 1 or weights.shape != (values.shape[1],) or weights.dtype != np.float64:
            raise LibraryFormatError(
                f"{kind}_weights: expected {values.shape[1]} float64 weights, "
                f"got {weights.dtype} {weights.shape}",
                path=file,
            )
        if not np.all(np.isfinite(weights) & (weights > 0)):
            raise LibraryFormatError(f"{kind}_weights: weights must be positive and finite", path=file)
        if not np.all(weights < MAX_WEIGHT):
            # retrieval repeats a column round(w) times: a huge weight would exhaust memory and time
            raise LibraryFormatError(
                f"{kind}_weights: weights must be below {MAX_WEIGHT:g} (a learned template is balanced, "
                f"thesis eq. 3.5), got {weights.max():g}",
                path=file,
            )
        if kind == "soft":
            if not np.all((values >= 0) & (values <= 1)):
                raise LibraryFormatError("soft: values must lie in [0, 1]", path=file)
        elif not np.all(np.isin(values, (0.0, 0.5, 1.0))):
            raise LibraryFormatError(f"{kind}: values must be 0, 0.5 or 1", path=file)
        out.append(MotionTemplate(values, weights))
    return out[0], out[1], out[2], out[3:]
