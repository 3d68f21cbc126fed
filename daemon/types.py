"""Names and shapes shared by every module: array aliases, the feature sets, the frame rates."""

from __future__ import annotations

import re
from dataclasses import dataclass
from typing import Literal, get_args

import numpy as np
import numpy.typing as npt

FloatArray = npt.NDArray[np.float64]
BoolArray = npt.NDArray[np.bool_]
IntArray = npt.NDArray[np.int64]
CodeArray = npt.NDArray[np.uint64]
"""A frame's 39 features as one code: bit i = feature i (:data:`daemon.features.FEATURE_NAMES` order)."""

FeatureSet = Literal["lower", "upper", "mix"]
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

DEFAULT_HOLD_S = 5.0
"""Seconds the live recogniser may hold a detection while another template could still explain
the same motion more cheaply (config ``recognizer.hold_s``)."""
DEFAULT_MAX_GAP_S = 2.0
"""Seconds an unbounded keyframe gap (stiffness 0) may span in the live recogniser (config
``recognizer.max_gap_s``)."""


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
