"""What every segmentation method shares: the cut it returns (:class:`Boundary`), the methods' names,
and the checks of its input.

**Frame counts in seconds.** Every window of the paper (Barbič et al. 2004) is given in seconds (the
paper's frames at its 120 Hz) and scaled to the stream's ``rate``: ``round(seconds * rate)`` frames
(:func:`count_frames`). Input that is not finite is a ``ValueError`` naming the frame.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import numpy as np
import numpy.typing as npt

from daemon.errors import InputError
from daemon.types import FloatArray

Method = Literal["pca", "ppca", "gmm"]
METHODS: tuple[Method, ...] = ("pca", "ppca", "gmm")


@dataclass(frozen=True)
class Boundary:
    """A cut between two behaviours. ``frame``: 0-based index of the first frame of the new
    behaviour (the previous one ends at ``frame - 1``); ``method``; ``score``: the method's signal at
    the cut (PCA: how far the error derivative ``d_i`` lies above the mean of the earlier ones, in
    standard deviations; PPCA: how far ``H`` rose from its valley to the peak; GMM: the mean log
    likelihood ratio, in nats per frame, of the new segment's frames under their cluster against the
    previous segment's); ``emitted``: the index of the last frame that had to be seen to know the cut
    (what an online method had been pushed when it returned it; ``N - 1`` for a batch-only cut)."""

    frame: int
    method: Method
    score: float
    emitted: int


def count_frames(seconds: float, rate: float, name: str, minimum: int = 1) -> int:
    """``round(seconds * rate)``, the window ``name`` in frames; ``ValueError`` below ``minimum``."""
    if not math.isfinite(seconds):
        raise InputError(f"{name} must be a finite number of seconds, got {seconds}")
    frames = round(seconds * rate)
    if frames < minimum:
        raise InputError(f"{name} = {seconds:g} s is {frames} frames at {rate:g} Hz; it must be >= {minimum}")
    return frames


def check_rate(rate: float) -> float:
    """``rate`` (frames per second) as a float; ``ValueError`` unless positive and finite."""
    if not (math.isfinite(rate) and rate > 0):
        raise InputError(f"rate must be a positive number of frames per second, got {rate}")
    return float(rate)


def check_fraction(value: float, name: str) -> None:
    """``ValueError`` unless ``0 < value < 1`` (a share of variance such as τ)."""
    if not 0.0 < value < 1.0:
        raise InputError(f"{name} must lie strictly between 0 and 1, got {value}")


def check_finite(values: FloatArray, what: str) -> None:
    """``ValueError`` naming the first frame (row) of ``values`` with a value that is not finite."""
    if values.size and not np.isfinite(values).all():
        bad = np.argwhere(~np.isfinite(values))[0]
        where = f"frame {int(bad[0])}" if values.ndim > 1 else "the frame"
        raise InputError(f"{what}: {where} has a value that is not finite ({values[tuple(bad)]})")


def check_frames(frames: npt.ArrayLike) -> FloatArray:
    """A batch method's input as a contiguous float64 array of shape ``(N, D)``, ``D >= 1``, finite."""
    x = np.ascontiguousarray(frames, dtype=np.float64)
    if x.ndim != 2 or x.shape[1] < 1:
        raise InputError(f"frames must have shape (N, D) with D >= 1, got {x.shape}")
    check_finite(x, "frames")
    return x
