"""Names and shapes shared by every module: array aliases, the feature sets, the frame rates."""

from __future__ import annotations

import math
import re
from dataclasses import dataclass
from typing import Literal, get_args

import numpy as np
import numpy.typing as npt

from daemon.errors import InputError

FloatArray = npt.NDArray[np.float64]
BoolArray = npt.NDArray[np.bool_]
IntArray = npt.NDArray[np.int64]
CodeArray = npt.NDArray[np.uint64]
"""A frame's 39 features as one code: bit i = feature i (:data:`daemon.features.FEATURE_NAMES` order)."""

FeatureSet = Literal["lower", "upper", "mix"]
RecognitionMode = Literal["library", "keyframes", "dtw"]
"""How the live recogniser finds the classes (config ``recognizer.mode``)."""
FEATURE_SETS: tuple[FeatureSet, ...] = get_args(FeatureSet)
"""The three feature sets of thesis Table 5.1, segmented and indexed separately, in feature order."""

N_FEATURES = 39
"""Features per frame (thesis Table 5.1: 12 lower, 14 upper, 13 mix)."""

DEFAULT_NATIVE_RATE = 120.0
"""Hz assumed for a recording that states no rate (CMU and HDM05 record at 120 Hz)."""

MAX_NATIVE_RATE = 10_000.0
"""The highest rate (Hz) features are computed at: the velocity windows grow with the rate (2500
frames at 10 kHz), so an absurd rate (a typo, a damaged file) would exhaust memory and time."""

DEFAULT_INDEX_RATE = 30.0
"""Hz at which indexes, templates and keyframes work (the toolbox's every 4th frame of 120 Hz)."""

DEFAULT_BRIDGE_S = 0.25
"""The longest run of missing frames (seconds) bridged by interpolation (config ``service.bridge_s``);
a longer one ends the motion (:func:`daemon.frames.bridged_runs`)."""

DEFAULT_HOLD_S = 5.0
"""Seconds the live recogniser may hold a detection while another template could still explain
the same motion more cheaply (config ``recognizer.hold_s``)."""
DEFAULT_MAX_GAP_S = 2.0
"""Seconds an unbounded keyframe gap (stiffness 0) may span in the live recogniser (config
``recognizer.max_gap_s``)."""


@dataclass(frozen=True)
class RecognitionSettings:
    """What the live recogniser does, the same for every stream it serves (config ``recognizer``,
    :meth:`daemon.config.RecognizerConfig.settings`): the library's ``classes`` it recognises (None:
    all, in the library's order), the seconds an unbounded keyframe gap (stiffness 0, thesis ch. 4)
    may span (``max_gap_s``), whether classes ``compete`` for a motion (the cheaper template wins),
    and the seconds a detection may be held while another template could still explain its motion
    more cheaply (``hold_s``), and how the classes are found (``mode``: ``library``, each as the
    library says; ``keyframes``, every class with keyframes keyframes first; ``dtw``, every class
    by the stream-wide DTW). ValueError for a value out of range."""

    classes: tuple[str, ...] | None = None
    max_gap_s: float = DEFAULT_MAX_GAP_S
    compete: bool = True
    hold_s: float = DEFAULT_HOLD_S
    mode: RecognitionMode = "library"

    def __post_init__(self) -> None:
        if self.classes is not None:
            if not isinstance(self.classes, tuple) or not all(isinstance(c, str) and c for c in self.classes):
                raise InputError(f"classes must be a tuple of class names, got {self.classes!r}")
            if len(set(self.classes)) != len(self.classes):
                raise InputError(f"a class is named twice in {self.classes!r}")
        if not (_seconds(self.max_gap_s) and self.max_gap_s > 0):
            raise InputError(f"max_gap_s must be positive seconds, got {self.max_gap_s!r}")
        if not isinstance(self.compete, bool):
            raise InputError(f"compete must be true or false, got {self.compete!r}")
        if not (_seconds(self.hold_s) and self.hold_s >= 0):
            raise InputError(f"hold_s must be seconds >= 0, got {self.hold_s!r}")
        if self.mode not in get_args(RecognitionMode):
            raise InputError(f"mode must be one of {', '.join(get_args(RecognitionMode))}, got {self.mode!r}")

    def max_gap(self, rate: float) -> int:
        """``max_gap_s`` in frames at ``rate`` Hz, at least 1."""
        return max(1, round(self.max_gap_s * rate))

    def hold(self, rate: float) -> int:
        """``hold_s`` in frames at ``rate`` Hz."""
        return round(self.hold_s * rate)


def _seconds(value: object) -> bool:
    """Whether ``value`` is a finite real number (not a bool)."""
    return isinstance(value, int | float) and not isinstance(value, bool) and math.isfinite(value)


@dataclass(frozen=True)
class Band:
    """A true boundary: ``frame`` where the new behaviour starts, and the frames a cut may fall on
    to find it (``lo .. hi``, inclusive). Any frame numbering, the cuts' the same."""

    frame: int
    lo: int
    hi: int


CLASS_NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9_.-]*")
"""A class name: it names a file of a template library."""


@dataclass(frozen=True)
class TrainingClip:
    """Where a training example came from: AMC frames ``start_frame .. end_frame`` of ``amc``
    (paths as the manifest wrote them), ``frames`` of them at the library's rate, performed by
    ``actor`` ("" when constructed without one: then the ASF path as written stands for the person)."""

    asf: str
    amc: str
    start_frame: int
    end_frame: int
    frames: int
    actor: str = ""

    def __post_init__(self) -> None:
        if not self.actor:
            object.__setattr__(self, "actor", self.asf)
