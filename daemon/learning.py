"""A library learned from labelled examples, as ``mocapd learn`` learns it (the learning stack: the
runtime never imports this).

:func:`learn_library` calibrates every class together on folds that leave a group out
(:func:`daemon.calibration.calibrate`: τ on left-out streams, the keyframe gate or the stream-wide
DTW), then learns each class from all its examples (:func:`daemon.library.learn_class`) with what
calibration chose (a class of two styles: its own templates learned from the examples of one,
a :class:`~daemon.library.Variant` from the other's). Keyframes given by the user (e.g. the Bonn
toolbox's published ones) replace the learned gate of the classes they name.

Pure: examples in, a :class:`~daemon.library.Library` out; no I/O.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Mapping
from dataclasses import dataclass

from daemon.calibration import Calibrated, calibrate, groups
from daemon.dtw import Steps
from daemon.keyframes import KeyframeQuery
from daemon.library import DTW, GATED, PUBLISHED, ClassTemplate, Library, Variant, given, learn_class
from daemon.recordings import Examples
from daemon.templates import THESIS_KEYFRAMES, learn
from daemon.types import DEFAULT_INDEX_RATE


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

    With ``calibrate_classes``: τ, the gate and the mode by :func:`daemon.calibration.calibrate`
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
            gate = found.keyframes
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
            if found.members is not None and found.second is not None:
                second = [i for i, c in enumerate(found.members) if c == 1]
                template = learn([items[i][1] for i in second], delta=delta, keyframes=0).quantised
                cls = dataclasses.replace(
                    cls,
                    training=tuple(clip for clip, _ in items),
                    variants=(Variant(template, found.second.tau, found.second, tuple(second)),),
                )
        if name in given_keyframes:
            cls = dataclasses.replace(
                cls,
                keyframes=given_keyframes[name],
                keyframe_source=PUBLISHED,
                mode=GATED,
                mode_reason="keyframes given to mocapd learn",
            )
        classes[name] = cls
        if progress is not None:
            progress(
                f"[class {len(classes)}/{len(examples)}] {name}: {len(items)} examples, {len(cls.members)} "
                f"template{'s' if len(cls.members) > 1 else ''} of {cls.quantised.length} columns, "
                f"{cls.mode} mode"
            )
    return Learned(Library(rate, classes), calibrated)
