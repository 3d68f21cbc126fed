"""The features of a whole motion, all frames at once: the compiled program
(:mod:`daemon.features.compiler`) run on float64 arrays, one row per pose component, with the
velocities as window sums (:func:`daemon.features.velocity.smooth`), then the hysteresis that
combines the loose and strict tracks (reference facts, section b).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from daemon.errors import InputError
from daemon.features.compiler import compiled, unpack
from daemon.features.language import BodyLengths, body_lengths
from daemon.features.velocity import smooth
from daemon.types import N_FEATURES, BoolArray, FloatArray

# (sqrt, minimum of a list, maximum of a list) for the compiled frame function.
_ARRAY_OPS = (np.sqrt, np.minimum.reduce, np.maximum.reduce)


def hysteresis(f1: BoolArray, f2: BoolArray) -> BoolArray:
    """``out(t) = f2(t) or (out(t-1) and f1(t))`` along axis 0, ``out(-1) = 0`` (nested tracks, f2 => f1;
    reference facts, section b).

    Vectorised: a frame is on iff the last frame at or before it where f2 holds is reachable through
    an unbroken run of f1."""
    n = f1.shape[0]
    idx = np.arange(n)[:, None] * np.ones(f1.shape[1:], dtype=np.intp)[None]
    last_f2 = np.maximum.accumulate(np.where(f2, idx, -1), axis=0)
    last_break = np.maximum.accumulate(np.where(~f1 & ~f2, idx, -1), axis=0)
    on: BoolArray = (last_f2 >= 0) & (last_f2 > last_break)
    return on


def _check_positions(positions: FloatArray, n_joints: int) -> FloatArray:
    p = np.asarray(positions, dtype=np.float64)
    if p.ndim != 3 or p.shape[1:] != (n_joints, 3):
        raise InputError(f"positions must have shape (N, {n_joints}, 3), got {p.shape}")
    if not np.isfinite(p).all():
        bad = int(np.argwhere(~np.isfinite(p))[0][0])
        raise InputError(f"positions are not finite at frame index {bad}")
    return p


def feature_tracks(
    positions: FloatArray, joint_names: Sequence[str], frame_rate: float, lengths: BodyLengths | None = None
) -> tuple[BoolArray, BoolArray]:
    """The loose and strict tracks ``(f1, f2)`` of ``positions`` shape ``(N, J, 3)``, each ``(N, 39)``."""
    program = compiled(joint_names, frame_rate)
    p = _check_positions(positions, len(program.joint_names))
    n = p.shape[0]
    if n == 0:
        return np.ones((0, N_FEATURES), dtype=bool), np.ones((0, N_FEATURES), dtype=bool)
    poses = np.ascontiguousarray(p.reshape(n, -1).T)  # (3J, N): each component a contiguous row
    thresholds = program.thresholds(lengths or body_lengths(p[0], program.joint_names))
    # Degenerate or huge poses give nan/inf signals (features off), as Python floats do in the stream.
    with np.errstate(all="ignore"):
        points = np.array(program.points(list(poses)))  # (3K, N)
        velocities = np.empty_like(points)
        for big_l, _, first, end in program.windows:
            velocities[first:end] = smooth(points[first:end], big_l, frame_rate)
        f1, f2 = program.frame(list(poses), velocities, thresholds, *_ARRAY_OPS)
    return unpack(f1), unpack(f2)


def features(positions: FloatArray, joint_names: Sequence[str], frame_rate: float = 120.0) -> BoolArray:
    """The 39 features of a whole motion: ``positions`` shape ``(N, J, 3)`` (joints named by
    ``joint_names``) gives a boolean matrix shape ``(N, 39)`` in :data:`FEATURE_NAMES` order."""
    f1, f2 = feature_tracks(positions, joint_names, frame_rate)
    return hysteresis(f1, f2)
