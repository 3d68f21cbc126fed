"""Motion templates (thesis ch. 3): the ``(f, K)`` matrix with column weights that learning
produces (:mod:`daemon.learn.templates`) and retrieval and recognition match, and its expansion Ω^E.

A motion template (MT) is an ``(f, K)`` float64 matrix, features by columns (f = 39 for the AK
features in :data:`daemon.features.FEATURE_NAMES` order: lower, upper, mix; the toolbox orders the
rows upper, lower, mix), with ``(K,)`` positive column weights. Examples are ``(N, f)`` boolean
feature matrices (frames by features, at 30 Hz) or :class:`MotionTemplate` objects; a matrix
becomes ``values = frames.T`` with weights 1.

Pure: numpy in, frozen dataclasses out; no I/O.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from daemon.types import FloatArray


@dataclass(frozen=True)
class MotionTemplate:
    """``values`` shape ``(f, K)`` (features by columns) and ``weights`` shape ``(K,)``, both float64,
    stored as read-only copies. Weights are positive: the time each column stands for, in frames."""

    values: FloatArray
    weights: FloatArray

    def __post_init__(self) -> None:
        values = np.array(self.values, dtype=np.float64)
        weights = np.array(self.weights, dtype=np.float64)
        if values.ndim != 2 or values.shape[0] < 1 or values.shape[1] < 1:
            raise ValueError(f"template values must have shape (f >= 1, K >= 1), got {values.shape}")
        if weights.shape != (values.shape[1],):
            raise ValueError(f"expected {values.shape[1]} weights, got shape {weights.shape}")
        if not (np.all(np.isfinite(weights)) and np.all(weights > 0)):
            raise ValueError("template weights must be positive and finite")
        if not np.all(np.isfinite(values)):
            raise ValueError("template values must be finite")
        values.setflags(write=False)
        weights.setflags(write=False)
        object.__setattr__(self, "values", values)
        object.__setattr__(self, "weights", weights)

    @property
    def length(self) -> int:
        """K, the number of columns."""
        return int(self.values.shape[1])

    @property
    def features(self) -> int:
        """f, the number of features (rows)."""
        return int(self.values.shape[0])

    @classmethod
    def from_frames(cls, frames: npt.ArrayLike) -> MotionTemplate:
        """An example: ``(N, f)`` frames (boolean or 0/1) as values ``(f, N)`` with weights 1."""
        f = np.asarray(frames)
        if f.ndim != 2:
            raise ValueError(f"expected an (N, f) feature matrix, got shape {f.shape}")
        return cls(f.T.astype(np.float64), np.ones(f.shape[0]))


Example = MotionTemplate | npt.NDArray[np.generic]


def as_template(example: Example) -> MotionTemplate:
    """A :class:`MotionTemplate` as is, an ``(N, f)`` matrix via :meth:`MotionTemplate.from_frames`."""
    return example if isinstance(example, MotionTemplate) else MotionTemplate.from_frames(example)


def round_half_away(x: npt.ArrayLike) -> FloatArray:
    """Matlab's ``round`` for x >= 0: halves go up (2.5 -> 3), unlike Python's banker's rounding."""
    return np.asarray(np.floor(np.asarray(x, dtype=np.float64) + 0.5))


def expand(t: MotionTemplate) -> MotionTemplate:
    """Ω^E (thesis §3.3.1; reference facts, section d): column ``a`` repeated ``max(1, round(w_a))``
    times, each copy with weight ``w_a / max(1, round(w_a))``; rounding is half away from zero, so a
    weight >= 1.5 splits and the copies' weights lie in [0.75, 1.5). Weights below 0.5 stay as they
    are; the total weight is kept."""
    copies = np.maximum(1, round_half_away(t.weights)).astype(np.int64)
    idx = np.repeat(np.arange(t.length), copies)
    return MotionTemplate(t.values[:, idx], (t.weights / copies)[idx])
