"""Smoothed velocities (reference facts, section 0): the window length of a velocity signal, the
trajectories the compiled program smooths, and the batch window sums, which
:class:`daemon._features.FeatureCore` repeats frame by frame for the stream.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from daemon.types import FloatArray


def window_frames(window_ms: float, frame_rate: float) -> int:
    """Velocity window length L in frames: ``ceil(W / 1000 * fs)``, at least 1 (reference facts, 0)."""
    return max(1, math.ceil(window_ms / 1000.0 * frame_rate))


@dataclass(frozen=True)
class Trajectory:
    """``P(q) - P(c)`` (or ``P(q)`` when ``c`` is None) smoothed over a window of ``big_l`` frames
    ending ``big_l - h`` frames after the current one."""

    q: int
    c: int | None
    big_l: int

    @property
    def h(self) -> int:
        return math.ceil(self.big_l / 2)

    @property
    def lead(self) -> int:
        """Frames after ``t`` whose positions the smoothed velocity at ``t`` needs."""
        return self.big_l - self.h + 1


def _mirror(j: npt.NDArray[np.intp], m: int) -> npt.NDArray[np.intp]:
    """Indices ``j`` reflected into ``[0, m)`` with the edge repeated, periodically (``padarray``'s
    'symmetric' for pads of any size)."""
    r = np.mod(j, 2 * m)
    out: npt.NDArray[np.intp] = np.where(r < m, r, 2 * m - 1 - r)
    return out


def _interior(n: int, big_l: int, h: int) -> range:
    """The frames of an ``n``-frame trajectory whose whole window lies inside it, so that the window
    sum telescopes to ``x(t+L-h+1) - x(t-h+1)``; the others are edge frames."""
    return range(h - 1, n - big_l + h - 1)


def _edge_indices(t: npt.NDArray[np.intp], n: int, big_l: int, h: int) -> npt.NDArray[np.intp]:
    """For frames ``t`` shape ``(E,)`` of an ``n``-frame trajectory (``n >= 2``), the indices ``m``
    shape ``(E, L)`` of the forward differences ``x(m+1) - x(m)`` in their smoothing windows, mirrored
    as the toolbox does (reference facts, section 0, step 3): ``v(n-1) = v(n-2)``, ``padarray``
    'symmetric' at both ends, and for ``n < L`` a first symmetric padding of ``v`` up to length L."""
    j = t[:, None] + np.arange(big_l)[None, :] - (h - 1)
    m = _mirror(_mirror(j, big_l), n) if n < big_l else _mirror(j, n)
    out: npt.NDArray[np.intp] = np.minimum(m, n - 2)
    return out


def smooth(x: FloatArray, big_l: int, frame_rate: float) -> FloatArray:
    """Smoothed velocity of ``x`` shape ``(k, N)`` (k components of point trajectories), shape ``(k, N)``
    (reference facts, section 0).

    Away from the ends the window sum of forward differences telescopes to ``x(t+L-h+1) - x(t-h+1)``;
    near the ends the mirrored differences are summed one after another. :class:`FeatureStream` does
    the same per frame."""
    n = x.shape[1]
    out = np.zeros_like(x)
    if n < 2:
        return out
    h = math.ceil(big_l / 2)
    inner = _interior(n, big_l, h)
    if len(inner):
        out[:, inner.start : inner.stop] = (x[:, big_l:] - x[:, : n - big_l]) * (frame_rate / big_l)
    t = np.arange(n)
    edge = t[(t < inner.start) | (t >= inner.stop)]
    if edge.size:
        m = _edge_indices(edge, n, big_l, h)
        d = x[:, 1:] - x[:, :-1]
        acc = d[:, m[:, 0]]
        for k in range(1, big_l):
            acc = acc + d[:, m[:, k]]
        out[:, edge] = acc * (frame_rate / big_l)
    return out


def smoothed_velocity(x: FloatArray, window_ms: float, frame_rate: float) -> FloatArray:
    """Velocity of the trajectory ``x`` shape ``(N, 3)`` in units per second, box-averaged over a
    centred window of ``L = window_frames(window_ms)`` frames: forward differences
    ``v(t) = x(t+1) - x(t)`` (``v(N) = v(N-1)``), then the mean of ``v(t+1-h .. t+L-h)`` with
    ``h = ceil(L/2)``, indices mirrored at both ends (Matlab's ``padarray(..., 'symmetric')``).
    Returns shape ``(N, 3)``."""
    x = np.ascontiguousarray(np.asarray(x, dtype=np.float64).T)
    return smooth(x, window_frames(window_ms, frame_rate), frame_rate).T
