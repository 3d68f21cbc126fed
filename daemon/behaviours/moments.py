"""The statistics every method of behaviour segmentation (Barbič et al. 2004) rests on: a segment's
moments, folded in incrementally, and their spectrum.

A segment's frames are folded in as a count ``n``, the first frame ``o``, ``s1 = sum (x - o)`` and
``s2 = sum (x - o)(x - o)^T``, in blocks (``s2 += Y^T Y``); the centred scatter is ``s2 - s1 s1^T /
n`` (the paper's ``D^T D``, whose eigenvalues are the ``σ_j²`` of Eq. 4). Measuring from the first
frame keeps the subtraction well conditioned and makes a stream that stands still give a scatter of
exactly zero. Eigenvalues come from ``eigvalsh``/``eigh`` of that ``D x D`` matrix when a method
needs them; no SVD of the frames is ever taken.
"""

from __future__ import annotations

import numpy as np

from daemon.types import FloatArray


class Moments:
    """A segment's frames so far: count ``n``, first frame ``origin`` ``(D,)``, ``s1 = sum (x - o)``
    ``(D,)`` and ``s2 = sum (x - o)(x - o)^T`` ``(D, D)``."""

    def __init__(self) -> None:
        self.n = 0
        self.origin = np.zeros(0)
        self.s1 = np.zeros(0)
        self.s2 = np.zeros((0, 0))

    def add(self, block: FloatArray) -> None:
        """Fold in ``block`` shape ``(m, D)``."""
        if self.n == 0:
            self.origin = block[0].copy()
            d = block.shape[1]
            self.s1, self.s2 = np.zeros(d), np.zeros((d, d))
        y = block - self.origin
        self.s1 += y.sum(axis=0)
        self.s2 += y.T @ y
        self.n += block.shape[0]

    def mean(self) -> FloatArray:
        """Eq. 1's centre of motion ``(D,)``."""
        out: FloatArray = self.origin + self.s1 / self.n
        return out

    def scatter(self) -> FloatArray:
        """The centred scatter ``sum (x - mean)(x - mean)^T`` ``(D, D)``: Eq. 4's ``D^T D``."""
        out: FloatArray = self.s2 - np.outer(self.s1, self.s1) / self.n
        return out


def spectrum(scatter: FloatArray) -> FloatArray:
    """The eigenvalues ``σ_j²`` of a scatter matrix ``(D, D)`` in increasing order, rounding below
    zero clipped: shape ``(D,)``."""
    out: FloatArray = np.maximum(np.linalg.eigvalsh(scatter), 0.0)
    return out


def dimension(eigenvalues: FloatArray, tau: float) -> int:
    """Eq. 6's rule: the smallest ``r`` with ``E_r = sum_(j<=r) σ_j² / sum σ_j² > tau``, the
    eigenvalues ``(D,)`` given in increasing order; 0 when they are all zero (nothing to keep)."""
    cumulative = np.cumsum(eigenvalues[::-1])
    total = float(cumulative[-1])
    if total <= 0.0:
        return 0
    r = int(np.searchsorted(cumulative, tau * total, side="right")) + 1
    return min(r, int(eigenvalues.shape[0]))


def projection_error(eigenvalues: FloatArray, r: int) -> float:
    """Eq. 5: the sum of the ``D - r`` discarded ``σ_j²`` (eigenvalues ``(D,)`` increasing)."""
    return float(eigenvalues[: eigenvalues.shape[0] - r].sum())
