"""A stream's frame numbers and index frames, in one place (DESIGN.md, "A stream's life" and
"Streaming confirmation").

- *Frame numbers* are the source's sequence numbers (a recording's AMC frame numbers), at the
  stream's native rate. They may have gaps (poses lost on the way, or dropped by a full queue); the
  recogniser takes a motion's frames consecutively: a gap of at most ``service.bridge_s`` is filled
  with interpolated frames (:func:`bridge`), a longer one ends the motion (:func:`bridged_runs`, the
  batch twin of the stream table's bridging). So a lost pose moves no later frame: index frames are
  sampled by frame number.
- *Index frames*, at the library's rate, counted from 0 at the motion's first frame: every
  ``step``-th frame (the toolbox's ``1:4:end`` at 120 Hz, reference facts section 0). The features
  are computed on the poses of the index frames alone (:func:`daemon.features.sampled_features`),
  so an index frame's come out ``delay`` frames after it: the look-ahead of the centred velocity
  windows at the index rate, in index frames (:func:`daemon.features.latency_frames`), times
  ``step`` (:class:`FrameClock`).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np

from daemon.errors import InputError
from daemon.features import decimation_factor, latency_frames
from daemon.types import DEFAULT_BRIDGE_S, MAX_NATIVE_RATE, FloatArray, IntArray
from replay.amc import Motion


def check_native_rate(rate: float) -> None:
    """ValueError unless ``rate`` (Hz) is one features are computed at."""
    if not (math.isfinite(rate) and 0 < rate <= MAX_NATIVE_RATE):
        raise InputError(f"native rate must be in (0, {MAX_NATIVE_RATE:g}] Hz, got {rate}")


@dataclass(frozen=True)
class FrameClock:
    """Frame numbers ↔ index frames of one motion whose first frame is ``first`` (an argument of
    each translation): index frame ``j`` is frame ``first + j·step``, and its features are known
    when frame ``first + j·step + delay`` is pushed (the motion's last frame, if that comes first).
    ``step`` >= 1, ``delay`` >= 0."""

    step: int
    delay: int

    def __post_init__(self) -> None:
        if self.step < 1 or self.delay < 0:
            raise ValueError(f"a frame clock needs step >= 1 and delay >= 0, got {self.step}, {self.delay}")

    @classmethod
    def of(cls, native_rate: float, index_rate: float) -> FrameClock:
        """The clock of a stream at ``native_rate`` Hz for a library at ``index_rate`` Hz; ValueError
        unless features are computed at ``native_rate`` and ``index_rate`` divides it."""
        check_native_rate(native_rate)
        step = decimation_factor(native_rate, index_rate)
        return cls(step, latency_frames(native_rate / step) * step)

    def start(self, first: int, j: int) -> int:
        """The frame number of index frame ``j``."""
        return first + j * self.step

    def index(self, first: int, number: int) -> int:
        """The index frame that frame ``number`` (>= ``first``) falls in: the last one at or before it."""
        return (number - first) // self.step

    def span(self, first: int, start: int, end: int, now: int) -> tuple[int, int]:
        """Index frames ``start .. end`` (inclusive) as frame numbers: from index frame ``start``'s
        frame to the frame before index frame ``end + 1``'s, capped by frame ``now`` (the one being
        pushed: at the motion's end it can come first)."""
        return self.start(first, start), min(self.start(first, end + 1) - 1, now)

    def known(self, first: int, j: int, last: int) -> int:
        """The frame whose push gives index frame ``j``'s features, in a motion ending at frame
        ``last``: ``delay`` frames after it, or ``last`` (the motion's end gives the rest)."""
        return min(self.start(first, j) + self.delay, last)

    def lag(self, index_frames: int) -> int:
        """Frames from an index frame to the push that gives the features of the index frame
        ``index_frames`` after it: ``index_frames·step + delay``."""
        return index_frames * self.step + self.delay


def bridge_frames(bridge_s: float, rate: float) -> int:
    """The most missing frames at ``rate`` Hz that ``bridge_s`` seconds bridge."""
    return round(bridge_s * rate)


def bridge(before: FloatArray, after: FloatArray, missing: int, angles: IntArray | None = None) -> FloatArray:
    """The ``missing`` frames between frame ``before`` and frame ``after`` (any one shape, e.g.
    ``(C,)`` channels or ``(J, 3)`` positions), interpolated linearly: shape ``(missing, *shape)``.
    ``angles``: indexes of a channel vector's angles (radians), interpolated along the shorter arc
    (an Euler angle that wraps from just under π to just over -π turns a little, not nearly once)."""
    delta = after - before
    if angles is not None and len(angles):
        delta[angles] = np.remainder(delta[angles] + math.pi, 2 * math.pi) - math.pi
    at = np.arange(1, missing + 1, dtype=np.float64) / (missing + 1)
    out: FloatArray = before + at.reshape((missing,) + (1,) * before.ndim) * delta
    return out


def bridged_runs(
    numbers: IntArray, values: FloatArray, max_missing: int, angles: IntArray | None = None
) -> list[tuple[IntArray, FloatArray]]:
    """A recording's frames ``values`` (shape ``(N, ...)``) with frame numbers ``numbers`` (shape
    ``(N,)``, increasing, perhaps with gaps) as the live path takes them: a gap of at most
    ``max_missing`` frames filled by :func:`bridge` (so that every frame after it is the frame it
    would have been without the gap, and the index frames are sampled by frame number), a longer
    one ending a run. The runs as (consecutive frame numbers, values); ValueError if ``numbers``
    does not increase."""
    if len(numbers) and np.any(np.diff(numbers) < 1):
        raise InputError("frame numbers must increase")
    gaps = np.flatnonzero(np.diff(numbers) > 1)
    if not len(gaps):
        return [(numbers, values)] if len(numbers) else []
    runs: list[tuple[IntArray, FloatArray]] = []
    pieces: list[FloatArray] = [values[: gaps[0] + 1]]
    first = int(numbers[0])
    for k, at in enumerate(gaps):
        missing = int(numbers[at + 1] - numbers[at]) - 1
        if missing > max_missing:
            runs.append((np.arange(first, numbers[at] + 1, dtype=np.int64), np.concatenate(pieces)))
            pieces, first = [], int(numbers[at + 1])
        else:
            pieces.append(bridge(values[at], values[at + 1], missing, angles))
        end = gaps[k + 1] + 1 if k + 1 < len(gaps) else len(values)
        pieces.append(values[at + 1 : end])
    runs.append((np.arange(first, numbers[-1] + 1, dtype=np.int64), np.concatenate(pieces)))
    return runs


def motion_runs(motion: Motion, native_rate: float, bridge_s: float = DEFAULT_BRIDGE_S) -> list[Motion]:
    """``motion`` as the daemon takes a stream with the same frames (AMC frame numbers may skip:
    frames lost in capture or transit): its runs of consecutive frames, a gap of at most ``bridge_s``
    seconds filled by interpolation (channel angles along the shorter arc), a longer one beginning a
    new run (:func:`daemon.frames.bridged_runs`). A motion without gaps is one run, itself."""
    angles = np.asarray(motion.skeleton.angle_channels, dtype=np.intp)
    runs = bridged_runs(motion.frames, motion.channels, bridge_frames(bridge_s, native_rate), angles)
    if len(runs) == 1 and len(runs[0][0]) == len(motion):
        return [motion]
    return [dataclasses.replace(motion, frames=frames, channels=channels) for frames, channels in runs]
