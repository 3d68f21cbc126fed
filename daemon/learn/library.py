"""A library learned from labelled examples, as ``mocapd learn`` learns it (the learning stack: the
runtime never imports this).

:func:`learn_library` calibrates every class together on folds that leave a group out
(:func:`daemon.learn.calibration.calibrate`: τ on left-out streams, the keyframe gate or the stream-wide
DTW), then learns each class from all its examples (:func:`daemon.learn.library.learn_class`) with what
calibration chose (a class of two styles: its own templates learned from the examples of one,
a :class:`~daemon.library.Variant` from the other's). Keyframes given by the user (e.g. the Bonn
toolbox's published ones) replace the learned gate of the classes they name.

Pure: examples in, a :class:`~daemon.library.Library` out; no I/O.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from daemon.dtw import Steps, pack
from daemon.features import FEATURE_NAMES
from daemon.keyframes import KeyframeQuery
from daemon.learn.calibration import DEFAULT_SLACK, Calibrated, calibrate, groups
from daemon.learn.templates import THESIS_KEYFRAMES, Generalisation, learn
from daemon.library import (
    DTW,
    FORMAT,
    GATED,
    LEARNED,
    LIBRARY_JSON,
    PUBLISHED,
    VERSION,
    WHAT,
    Calibration,
    ClassTemplate,
    Library,
    Variant,
    given,
)
from daemon.recognizer import learned_extent
from daemon.recordings import Examples
from daemon.storage import check_target, checksum, replace_directory, sync, write_json
from daemon.types import DEFAULT_INDEX_RATE, DEFAULT_MAX_GAP_S, BoolArray, TrainingClip


@dataclass(frozen=True)
class Learned:
    """The library and the calibration it came from (None with ``calibrate`` off)."""

    library: Library
    calibrated: Calibrated | None


def learn_library(
    examples: Examples,
    *,
    tau: float = 0.1,
    delta: float = 0.1,
    keyframes: int = 3,
    steps: Steps = "toolbox",
    rate: float = DEFAULT_INDEX_RATE,
    calibrate_classes: bool = True,
    given_keyframes: Mapping[str, KeyframeQuery] | None = None,
    progress: Callable[[str], object] | None = None,
) -> Learned:
    """Every class of ``examples`` (each class's clips and their ``(frames, 39)`` features at
    ``rate`` Hz, as :func:`daemon.recordings.read_examples` gives them), in their order.

    With ``calibrate_classes``: τ, the gate and the mode by :func:`daemon.learn.calibration.calibrate`
    over the actors (at least 2) or over groups of one actor's examples; without: ``tau`` given and
    the thesis' keyframes as the gate of every class. ``given_keyframes``: per class named, the
    keyframes that gate it instead of learned ones (``keyframe_source`` ``published``).
    ``progress(message)`` after each fold and class."""
    given_keyframes = given_keyframes or {}
    calibrated = None
    if calibrate_classes:
        names = [n for n, items in examples.items() for _ in items]
        actors = [clip.actor for items in examples.values() for clip, _ in items]
        labels, groups_are = groups(actors, names)
        it = iter(labels)
        labelled = {n: [(next(it), m) for _, m in items] for n, items in examples.items()}
        calibrated = calibrate(
            labelled,
            groups_are=groups_are,
            tau=tau,
            delta=delta,
            keyframes=keyframes,
            steps=steps,
            rate=rate,
            progress=progress,
        )
    classes: dict[str, ClassTemplate] = {}
    for name, items in examples.items():
        if calibrated is None:
            cls = learn_class(
                name,
                items,
                delta=delta,
                tau=tau,
                keyframes=keyframes,
                steps=steps,
                rate=rate,
                calibration=given(tau, "--no-calibrate"),
                generalisation=THESIS_KEYFRAMES,
            )
        else:
            found = calibrated.classes[name]
            gate = None if found.keyframes is None else found.keyframes.generalisation
            own = (
                items
                if found.members is None
                else [x for x, c in zip(items, found.members, strict=True) if c == 0]
            )
            cls = learn_class(
                name,
                own,
                delta=delta,
                tau=tau,
                keyframes=keyframes if gate is not None else 0,
                steps=steps,
                rate=rate,
                calibration=found.calibration,
                generalisation=THESIS_KEYFRAMES if gate is None else gate,
                mode=DTW if gate is None else GATED,
                mode_reason=found.reason,
            )
            if found.keyframes is not None:
                cls = dataclasses.replace(cls, slack=found.keyframes.slack)
            if found.members is not None and found.second is not None:
                second = [i for i, c in enumerate(found.members) if c == 1]
                template = learn([items[i][1] for i in second], delta=delta, keyframes=0).quantised
                # the gate opens for both styles: its keyframes come from every example, as in the folds
                query = (
                    None
                    if gate is None
                    else learn(
                        [m for _, m in items], keyframes=keyframes, name=name, rate=rate, generalisation=gate
                    ).keyframes
                )
                cls = dataclasses.replace(
                    cls,
                    training=tuple(clip for clip, _ in items),
                    variants=(Variant(template, found.second.tau, found.second, tuple(second)),),
                    keyframes=query,
                )
        if name in given_keyframes:
            cls = dataclasses.replace(
                cls,
                keyframes=given_keyframes[name],
                keyframe_source=PUBLISHED,
                mode=GATED,
                mode_reason="keyframes given to mocapd learn",
                slack=cls.slack or DEFAULT_SLACK,
            )
        if cls.mode == GATED and cls.keyframes is not None:
            codes = [pack(m).tolist() for _, m in items]
            max_gap = max(1, round(DEFAULT_MAX_GAP_S * rate))
            cls = dataclasses.replace(cls, extent=learned_extent(cls.keyframes, codes, rate, max_gap))
        classes[name] = cls
        if progress is not None:
            progress(
                f"[class {len(classes)}/{len(examples)}] {name}: {len(items)} examples, {len(cls.members)} "
                f"template{'s' if len(cls.members) > 1 else ''} of {cls.quantised.length} columns, "
                f"{cls.mode} mode"
            )
    return Learned(Library(rate, classes), calibrated)


def learn_class(
    name: str,
    examples: Sequence[tuple[TrainingClip, BoolArray]],
    *,
    delta: float = 0.1,
    tau: float = 0.1,
    keyframes: int = 3,
    steps: Steps = "toolbox",
    rate: float = DEFAULT_INDEX_RATE,
    calibration: Calibration | None = None,
    generalisation: Generalisation = THESIS_KEYFRAMES,
    mode: str = "",
    mode_reason: str = "",
) -> ClassTemplate:
    """A class learned from its examples' ``(frames, 39)`` matrices at ``rate`` Hz: soft MT (toolbox
    strategy 5) and its quantisation by ``delta``, hard MT (thesis §3.3.1) and ``keyframes`` automatic
    keyframes from it (thesis ch. 6; 0 = none). ``steps``: the DTW steps retrieval will use; the
    toolbox's (1,1), (1,2), (2,1) by default, whose slopes between ½ and 2 keep a template from
    matching a much shorter or longer stretch (measured in docs/search-and-templates.md).
    ``calibration``: the class's calibrated τ (:func:`daemon.learn.calibration.calibrate`), which then
    replaces ``tau``; without it, ``tau`` is recorded as given. ``generalisation``: how far the
    keyframes reach beyond the training actors (:class:`daemon.learn.templates.Generalisation`;
    calibration chooses it). ``mode`` and
    ``mode_reason``: how the live recogniser finds the class and why (:data:`MODES`; "": keyframes
    when there are any)."""
    learned = learn(
        [m for _, m in examples],
        delta=delta,
        keyframes=keyframes,
        name=name,
        rate=rate,
        generalisation=generalisation,
    )
    return ClassTemplate(
        name,
        learned.soft.template,
        learned.quantised,
        learned.hard.template,
        learned.keyframes,
        tau if calibration is None else calibration.tau,
        delta,
        steps,
        learned.soft.iterations,
        tuple(clip for clip, _ in examples),
        given(tau) if calibration is None else calibration,
        mode=mode,
        mode_reason=mode_reason,
    )


# ------------------------------------------------------------------------------------- writing


def keyframe_entries(query: KeyframeQuery) -> list[dict[str, Any]]:
    """A keyframe query as entries of ``manual-keyframes.json``; ``mismatches`` only where it is not
    0, so that files of exact keyframes stay as they were."""
    out: list[dict[str, Any]] = []
    for k in query.keyframes:
        entry: dict[str, Any] = {
            "set": k.feature_set,
            "values": [0.5 if v == 0.5 else int(v) for v in k.values],
            "position": k.position,
            "stiffness_to_next": k.stiffness_to_next,
        }
        if k.mismatches:
            entry["mismatches"] = k.mismatches
        out.append(entry)
    return out


def _arrays(c: ClassTemplate) -> dict[str, np.ndarray]:
    arrays = {
        "soft": c.soft.values,
        "soft_weights": c.soft.weights,
        "quantised": c.quantised.values,
        "quantised_weights": c.quantised.weights,
        "hard": c.hard.values,
        "hard_weights": c.hard.weights,
    }
    for i, v in enumerate(c.variants, start=1):
        arrays[f"member{i}"] = v.quantised.values
        arrays[f"member{i}_weights"] = v.quantised.weights
    return {k: np.ascontiguousarray(v, dtype=np.float64) for k, v in arrays.items()}


def save_library(library: Library, path: str | Path, extra: Mapping[str, str] | None = None) -> None:
    """Write ``library`` as the directory ``path`` (replacing an earlier library or an empty
    directory; anything else raises :class:`~daemon.errors.FileAccessError`), never half written.
    ``extra``: other text files to write into the directory with it (name -> UTF-8 text; plain
    names, neither ``library.json`` nor ``*.npz``), e.g. the training manifest."""
    arrays = {name: _arrays(c) for name, c in library.classes.items()}
    extra = dict(extra or {})
    for file in extra:
        if Path(file).name != file or file in (LIBRARY_JSON, ".", "..") or file.endswith(".npz"):
            raise ValueError(
                f"an extra file of a library must be a plain name, not {LIBRARY_JSON} or *.npz: {file!r}"
            )
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
            "sha256": {k: checksum(v) for k, v in arrays[name].items()},
            "tau": c.tau,
            "calibration": _calibration_entry(c.provenance),
            "delta": c.delta,
            "steps": c.steps,
            "iterations": c.iterations,
            "training": [vars(t) for t in c.training],
            "keyframes": [] if c.keyframes is None else keyframe_entries(c.keyframes),
            "mode": c.mode,
            "mode_reason": c.mode_reason,
            "members": [
                {"tau": v.tau, "calibration": _calibration_entry(v.calibration), "examples": list(v.examples)}
                for v in c.variants
            ],
        }
        if c.keyframe_source != LEARNED:
            meta["classes"][name]["keyframe_source"] = c.keyframe_source
        if c.slack:
            meta["classes"][name]["slack"] = c.slack
        if c.extent is not None:
            meta["classes"][name]["window"] = list(c.extent)

    def fill(temp: Path) -> None:
        for name, values in arrays.items():
            with open(temp / f"{name}.npz", "wb") as out:
                np.savez(out, allow_pickle=False, **values)
        write_json(temp / LIBRARY_JSON, meta)
        for file, text in extra.items():
            with open(temp / file, "w", encoding="utf-8", newline="") as out:
                out.write(text)
                sync(out)

    replace_directory(path, LIBRARY_JSON, WHAT, fill)


def check_library_target(path: str | Path) -> None:
    """Raise :class:`~daemon.errors.FileAccessError` unless :func:`save_library` may write ``path``."""
    check_target(path, LIBRARY_JSON, WHAT)


def _calibration_entry(c: Calibration) -> dict[str, Any]:
    return {
        "method": c.method,
        "folds": c.folds,
        "positives": c.positives,
        "negatives": c.negatives,
        "recall": c.recall,
        "precision": c.precision,
    }
