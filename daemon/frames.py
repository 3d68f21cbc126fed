"""A stream's frame numbers and index frames, in one place (DESIGN.md, "A stream's life" and
"Streaming confirmation").

- *Frame numbers* are the source's sequence numbers (a recording's AMC frame numbers), at the
  stream's native rate. They may have gaps (poses lost on the way, or dropped by a full queue); the
  recogniser takes a motion's frames consecutively: a gap of at most ``service.bridge_s`` is filled
  with interpolated frames (:func:`bridge`), a longer one ends the motion (:func:`bridged_runs`, the
  batch twin of the stream table's bridging). So a lost pose moves no later frame: index frames are
  sampled by frame number.
- *Index frames*, at the library's rate, counted from 0 at the motion's first frame: every
  ``step``-th frame (the toolbox's ``1:4:end`` at 120 Hz, reference facts section 0), or, at a rate
  the library's does not divide, the frame nearest each index frame's instant (100 Hz for 30 Hz:
  frames 0, 3, 7, 10, 13, 17, ...). The features are computed on the poses of the index frames
  alone (:func:`daemon.features.sampled_features`), so an index frame's come out when the index
  frame ``lead`` after it is pushed: the look-ahead of the centred velocity windows at the index
  rate (:func:`daemon.features.latency_frames`; :class:`FrameClock`).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np

from daemon.errors import InputError
from daemon.features import last_sample, latency_frames, sampling_ratio
from daemon.types import DEFAULT_BRIDGE_S, MAX_NATIVE_RATE, FloatArray, IntArray
from replay.amc import Motion


def check_native_rate(rate: float) -> None:
    """ValueError unless ``rate`` (Hz) is one features are computed at."""
    if not (math.isfinite(rate) and 0 < rate <= MAX_NATIVE_RATE):
        raise InputError(f"native rate must be in (0, {MAX_NATIVE_RATE:g}] Hz, got {rate}")


@dataclass(frozen=True)
class FrameClock:
    """Frame numbers ↔ index frames of one motion whose first frame is ``first`` (an argument of
    each translation): ``step`` frames hold ``per`` index frames (lowest terms; ``per`` = 1 at a rate
    the library's divides). Index frame ``j``'s instant is ``j·step/per`` frames after the first; it
    is frame ``first + ceil(j·step/per)``, the first at or after its instant, whose push gives its
    pose (the pose at its instant, :func:`daemon.features.sample_poses`), and its features are
    known when index frame ``j + lead``'s frame is pushed (the motion's last frame, if that comes
    first). ``step`` >= ``per`` >= 1, ``lead`` >= 0."""

    step: int
    lead: int
    per: int = 1

    def __post_init__(self) -> None:
        if not self.step >= self.per >= 1 or self.lead < 0 or math.gcd(self.step, self.per) != 1:
            raise ValueError(
                f"a frame clock needs step >= per >= 1 in lowest terms and lead >= 0, got step "
                f"{self.step}, per {self.per}, lead {self.lead}"
            )

    @classmethod
    def of(cls, native_rate: float, index_rate: float) -> FrameClock:
        """The clock of a stream at ``native_rate`` Hz for a library at ``index_rate`` Hz; ValueError
        unless features are computed at ``native_rate`` and ``index_rate`` does not exceed it."""
        check_native_rate(native_rate)
        step, per = sampling_ratio(native_rate, index_rate)
        return cls(step, latency_frames(native_rate * per / step), per)

    def start(self, first: int, j: int) -> int:
        """The frame number of index frame ``j``."""
        return first + (j * self.step + self.per - 1) // self.per

    def index(self, first: int, number: int) -> int:
        """The index frame that frame ``number`` (>= ``first``) falls in: the last one at or before it."""
        return last_sample(number - first, self.step, self.per)

    def keeps(self, first: int, number: int) -> bool:
        """Whether frame ``number`` is an index frame's (its push gives the index frame's pose)."""
        return self.start(first, self.index(first, number)) == number

    def span(self, first: int, start: int, end: int, now: int) -> tuple[int, int]:
        """Index frames ``start .. end`` (inclusive) as frame numbers: from index frame ``start``'s
        frame to the frame before index frame ``end + 1``'s, capped by frame ``now`` (the one being
        pushed: at the motion's end it can come first)."""
        return self.start(first, start), min(self.start(first, end + 1) - 1, now)

    def known(self, first: int, j: int, last: int) -> int:
        """The frame whose push gives index frame ``j``'s features, in a motion ending at frame
        ``last``: index frame ``j + lead``'s, or ``last`` (the motion's end gives the rest)."""
        return min(self.start(first, j + self.lead), last)

    def lag(self, index_frames: int) -> int:
        """Frames from an index frame to the push that gives the features of the index frame
        ``index_frames`` after it, at most (``(index_frames + lead)·step`` when ``per`` = 1)."""
        k = index_frames + self.lead
        return max(self.start(0, j + k) - self.start(0, j) for j in range(self.per))

    @property
    def delay(self) -> int:
        """Frames from an index frame to the push that gives its features, at most."""
        return self.lag(0)


def bridge_frames(bridge_s: float, rate: float) -> int:
    """The most missing frames at ``rate`` Hz that ``bridge_s`` seconds bridge."""
    return round(bridge_s * rate)


def bridge(
    before: FloatArray,
    after: FloatArray,
    missing: int,
    angles: IntArray | None = None,
    turn: float = 2 * math.pi,
) -> FloatArray:
    """The ``missing`` frames between frame ``before`` and frame ``after`` (any one shape, e.g.
    ``(C,)`` channels or ``(J, 3)`` positions), interpolated linearly: shape ``(missing, *shape)``.
    ``angles``: indexes of a channel vector's angles (a whole ``turn``: radians by default, 360 for
    degrees), interpolated along the shorter arc (an Euler angle that wraps from just under half a
    turn to just over minus half turns a little, not nearly once)."""
    delta = after - before
    if angles is not None and len(angles):
        delta[angles] = np.remainder(delta[angles] + turn / 2, turn) - turn / 2
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
