"""The features one pose at a time (:class:`FeatureStream`, the incremental twin of
:func:`daemon.features.batch.features`, bit for bit), their latency, and the change of frame rate
by keeping every k-th frame (:class:`Decimator` and its batch twin :func:`decimate`).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from fractions import Fraction

import numpy as np

from daemon._features import FeatureCore
from daemon.errors import InputError
from daemon.features.batch import features
from daemon.features.compiler import compiled, unpack
from daemon.features.language import body_lengths
from daemon.types import BoolArray, FloatArray, IntArray
from replay.joints import JOINT_NAMES


def latency_frames(frame_rate: float) -> int:
    """How many frames after frame ``t`` arrives :class:`FeatureStream` can emit its vector: the
    longest velocity window's look-ahead ``L - ceil(L/2) + 1`` (16 at 120 Hz, 5 at 30 Hz)."""
    return compiled(JOINT_NAMES, frame_rate).lead


class FeatureStream:
    """The 39 features of a stream, one pose at a time: the incremental twin of :func:`features`.

    ``push(pose)`` with ``pose`` shape ``(J, 3)`` returns the vectors that became final, each a bool
    array shape ``(39,)``: the vector of frame ``t`` comes out when frame ``t + latency`` arrives
    (``latency`` = :func:`latency_frames`, 16 frames = 133 ms at 120 Hz, because the 250 ms velocity
    windows are centred), and :meth:`flush` returns the last ``latency`` vectors when the stream ends
    (the windows are then mirrored at the end, exactly as in the batch) and makes the object ready
    for a new stream. Body lengths are measured on the first pose. Memory is bounded: a ring of the
    last ``latency + L/2 + 1`` poses. The output equals :func:`features` on the same frames bit for
    bit: both run the same program and the same window sums, on arrays there and here in compiled
    code (:class:`daemon._features.FeatureCore`: the program as register-machine code on doubles
    with numpy's arithmetic)."""

    def __init__(self, joint_names: Sequence[str], frame_rate: float = 120.0) -> None:
        self._program = compiled(joint_names, frame_rate)
        self.latency = self._program.lead
        self._keep = self.latency + max((tr.h for tr in self._program.trajectories), default=1) + 1
        self._core = FeatureCore(self._program.bytecode, self._keep, self.latency)

    @property
    def frames(self) -> int:
        """Poses pushed since the stream began."""
        return self._core.n

    @property
    def keep(self) -> int:
        """Poses held: the last ``keep`` (``latency + L/2 + 1``)."""
        return self._keep

    @property
    def core(self) -> FeatureCore:
        """The compiled state (the live recogniser steps it directly)."""
        return self._core

    def thresholds_of(self, rows: FloatArray) -> FloatArray:
        """The flat thresholds of a stream whose first pose is ``rows`` (flat, ``3j + c``)."""
        return self._program.flat_thresholds(body_lengths(rows.reshape(-1, 3), self._program.joint_names))

    def push(self, pose: FloatArray) -> list[BoolArray]:
        """Add the next pose; return the vectors that became final (at most one)."""
        program = self._program
        p = np.ascontiguousarray(pose, dtype=np.float64)
        if p.shape != (len(program.joint_names), 3):
            raise InputError(f"pose must have shape ({len(program.joint_names)}, 3), got {p.shape}")
        rows = p.reshape(-1)
        if not np.isfinite(rows).all():
            raise InputError(f"pose {self._core.n} is not finite")
        return [] if (code := self.push_rows(rows)) is None else [unpack(code)]

    def push_rows(self, rows: FloatArray) -> int | None:
        """:meth:`push` of a pose already checked: finite, contiguous float64, flat (``3j + c``,
        shape ``(3J,)``); the vector that became final as a code (bit k = feature k), or None."""
        core = self._core
        if core.n == 0:
            core.set_thresholds(self.thresholds_of(rows))
        code = core.push(rows)
        return None if code < 0 else code

    def flush(self) -> list[BoolArray]:
        """End the stream: the vectors of its last frames, then a fresh state."""
        return [unpack(code) for code in self.flush_codes()]

    def flush_codes(self) -> list[int]:
        """:meth:`flush` giving codes (bit k = feature k)."""
        return self._core.flush()


# ---------------------------------------------------------------------------------- frame rates


def decimation_factor(native_hz: float, target_hz: float) -> int:
    """How many native frames make one frame at ``target_hz`` (4 for 120 -> 30 Hz); the target must
    divide the native rate."""
    if not (math.isfinite(target_hz) and target_hz > 0):
        raise InputError(f"target frame rate must be a positive number, got {target_hz}")
    ratio = native_hz / target_hz
    factor = round(ratio) if math.isfinite(ratio) else 0  # a subnormal target overflows the ratio
    if factor < 1 or not math.isclose(native_hz / factor, target_hz, rel_tol=1e-9):
        raise InputError(f"{target_hz:g} Hz is not the native {native_hz:g} Hz divided by a whole number")
    return factor


MAX_PER = 1000
"""The most index frames a whole number of native frames may hold (a rate ratio's denominator)."""
MAX_STEP = 1e6
"""The most native frames to one index frame (beyond it, frame counts overflow 64 bits)."""


def sampling_ratio(native_hz: float, target_hz: float) -> tuple[int, int]:
    """``(step, per)``: ``step`` native frames make ``per`` frames at ``target_hz``, in lowest terms
    (``(4, 1)`` for 120 -> 30 Hz, ``(10, 3)`` for 100 -> 30 Hz); the target must not exceed the
    native rate."""
    if not (math.isfinite(target_hz) and target_hz > 0):
        raise InputError(f"target frame rate must be a positive number, got {target_hz}")
    ratio = native_hz / target_hz
    if not (math.isfinite(ratio) and ratio >= 1 - 1e-9):
        raise InputError(f"{target_hz:g} Hz is above the native {native_hz:g} Hz")
    if ratio > MAX_STEP:
        raise InputError(
            f"{target_hz:g} Hz is below the native {native_hz:g} Hz by more than {MAX_STEP:g} times"
        )
    fraction = Fraction(ratio).limit_denominator(MAX_PER)
    step, per = fraction.numerator, fraction.denominator
    if not math.isclose(native_hz * per / step, target_hz, rel_tol=1e-9):
        raise InputError(
            f"{target_hz:g} Hz is not the native {native_hz:g} Hz times a ratio of whole numbers"
        )
    return step, per


def sample_count(n: int, step: int, per: int = 1) -> int:
    """How many index frames ``n`` native frames hold: those whose instant ``j·step/per`` (in native
    frames from the first) is at most the last frame's."""
    return 0 if n <= 0 else (n - 1) * per // step + 1


def sample_rows(n: int, step: int, per: int = 1) -> IntArray:
    """The native frame (from 0) that stands for each index frame among ``n``: the first at or after
    its instant, ``ceil(j·step/per)`` (the one whose arrival gives its pose); every ``step``-th
    frame when ``per`` = 1. Shape ``(M,)``, ``M`` = :func:`sample_count`."""
    j = np.arange(sample_count(n, step, per), dtype=np.int64)
    out: IntArray = (j * step + per - 1) // per
    return out


def last_sample(m: int, step: int, per: int = 1) -> int:
    """The index frame native frame ``m`` (from 0) falls in: the last one whose instant is at or
    before it (-1 before 0)."""
    return m * per // step


def sample_poses(positions: FloatArray, step: int, per: int = 1) -> FloatArray:
    """The poses at the index frames' instants, shape ``(M, J, 3)`` of ``positions`` ``(N, J, 3)``:
    every ``step``-th pose when ``per`` = 1; else at instant ``t = j·step/per`` the pose ``a + w·(b -
    a)`` between frames ``a = floor(t)`` and ``b = a + 1``, ``w = t - a`` (``r/per`` for the
    remainder ``r`` of ``j·step / per``), or frame ``t`` itself when it falls on one. The live path
    (:class:`daemon._live.LiveStream`) blends the same doubles the same way."""
    if per == 1:
        out: FloatArray = positions[::step]
        return out
    ticks = np.arange(sample_count(len(positions), step, per), dtype=np.int64) * step
    below, remainder = ticks // per, ticks % per
    poses: FloatArray = positions[below].copy()
    between = remainder > 0
    a, b = poses[between], positions[below[between] + 1]
    poses[between] = a + (remainder[between] / per)[:, None, None] * (b - a)
    return poses


def sampled_features(
    positions: FloatArray, joint_names: Sequence[str], native_hz: float, step: int, per: int = 1
) -> BoolArray:
    """The features at ``native_hz · per / step`` Hz as every recogniser, index and template of
    mocapd takes them: of the poses at the index frames' instants alone (:func:`sample_poses`: every
    ``step``-th pose from the first when ``per`` = 1) of ``positions`` shape ``(N, J, 3)`` (so the
    velocity windows and the hysteresis run on the same instants whatever the native rate, and a
    recording at 120 Hz gives the bits it gives resampled to 30 Hz). Shape ``(M, 39)``. Not the
    toolbox's ``1:4:end`` of the native rate's matrix (:func:`decimate`): its windows span native
    frames, so the bits change with the rate."""
    return features(sample_poses(positions, step, per), joint_names, native_hz * per / step)


def decimate(matrix: BoolArray, factor: int) -> BoolArray:
    """Every ``factor``-th row of ``matrix``, starting with the first (the toolbox's ``1:4:end``, no
    filtering; reference facts, section 0). Batch twin of :class:`Decimator`."""
    out: BoolArray = matrix[::factor]
    return out


class Decimator:
    """``push(vector)`` passes on every ``factor``-th vector, starting with the first (a list of it, or
    an empty list); :meth:`flush` has nothing pending and starts a new stream. The streaming twin of
    :func:`decimate`. State: a frame counter."""

    def __init__(self, factor: int) -> None:
        if factor < 1:
            raise InputError(f"decimation factor must be at least 1, got {factor}")
        self.factor = factor
        self._n = 0

    def push(self, vector: BoolArray) -> list[BoolArray]:
        keep = self._n % self.factor == 0
        self._n += 1
        return [vector] if keep else []

    def flush(self) -> list[BoolArray]:
        self._n = 0
        return []
