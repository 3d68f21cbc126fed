"""What the online segmenters of behaviour segmentation (:class:`~daemon.behaviours.pca.PcaSegmenter`,
:class:`~daemon.behaviours.ppca.PpcaSegmenter`) share: the check of each pushed frame, the frame
count, the start of the current segment and the method's state over it, and a ``flush`` that starts
a new stream. Each subclass is a stage (:mod:`daemon.stages`) with one ``push``.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Generic, TypeVar

import numpy as np
import numpy.typing as npt

from daemon.behaviours.common import Boundary, check_rate
from daemon.errors import InputError
from daemon.types import FloatArray

P = TypeVar("P")
F = TypeVar("F")
R = TypeVar("R")


class FrameCheck:
    """Validates pushed frames: shape ``(D,)`` fixed by the first, finite; returns a copy."""

    def __init__(self) -> None:
        self.dims: int | None = None

    def __call__(self, frame: npt.ArrayLike, index: int) -> FloatArray:
        x = np.array(frame, dtype=np.float64)
        if x.ndim != 1 or x.shape[0] < 1 or (self.dims is not None and x.shape[0] != self.dims):
            want = f"({self.dims},)" if self.dims is not None else "(D,) with D >= 1"
            raise InputError(f"frame {index} must have shape {want}, got {x.shape}")
        if not np.isfinite(x).all():
            raise InputError(f"frame {index} has a value that is not finite")
        self.dims = x.shape[0]
        return x


class OnlineSegmenter(Generic[P, F, R]):
    """An online segmenter at ``rate`` Hz with ``params`` (a method's parameters ``P``), ``frames``
    (its windows in frames ``F``) and, over the current segment, a run ``R`` made by ``run(params,
    frames)``: a new one at the start of the stream and at each cut (:meth:`_restart`). The state it
    keeps: the frame check, the count of frames pushed ``_t``, the segment's first frame ``_start``
    and ``_run``; a subclass adds its own in :meth:`_reset` (calling this one)."""

    def __init__(self, rate: float, params: P, frames: F, run: Callable[[P, F], R]) -> None:
        self.rate = check_rate(rate)
        self.params = params
        self.frames = frames
        self._new_run = run
        self._reset()

    def _reset(self) -> None:
        self._check = FrameCheck()
        self._t = 0
        self._restart(0)

    def _restart(self, start: int) -> None:
        """A new segment from frame ``start``."""
        self._start = start
        self._run = self._new_run(self.params, self.frames)

    def _take(self, frame: npt.ArrayLike) -> FloatArray:
        """The next frame ``(D,)``, checked (``ValueError``, the state unchanged) and counted."""
        x = self._check(frame, self._t)
        self._t += 1
        return x

    def flush(self) -> list[Boundary]:
        """[]: a cut is returned by the push that makes it known, none is pending; then a new stream."""
        self._reset()
        return []
