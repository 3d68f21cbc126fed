"""§3.3 of Barbič et al. 2004, behaviour segmentation by a Gaussian mixture (batch only): the frames,
projected onto their leading principal components, clustered by EM; a cut wherever the most likely
cluster changes, once segments shorter than the shortest behaviour are merged away.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from daemon.behaviours.common import Boundary, check_frames, check_rate, count_frames
from daemon.behaviours.moments import dimension
from daemon.errors import InputError
from daemon.types import FloatArray, IntArray


@dataclass(frozen=True)
class GmmParams:
    """§3.3's parameters: ``variance`` the share of variance the PCA keeps (0.9), ``clusters`` k
    (4), ``min_length`` the seconds below which a segment is merged into its neighbours (1 s = 120
    frames). Not in the paper: ``seed`` of the initial means (one random frame from each of k
    consecutive parts of the recording, the paper's slightly better initialisation),
    ``regularizer`` added to every covariance's diagonal relative to the data's mean variance per
    dimension (so no covariance is ever singular), and EM's stopping rule: ``max_iterations``, or a
    gain of the mean log likelihood below ``tolerance`` nats per frame."""

    variance: float = 0.9
    clusters: int = 4
    min_length: float = 1.0
    seed: int = 0
    regularizer: float = 1e-6
    max_iterations: int = 200
    tolerance: float = 1e-6

    def check(self, rate: float) -> int:
        """The minimum length in frames at ``rate`` Hz; ``ValueError`` if a parameter is unusable."""
        rate = check_rate(rate)
        if not 0.0 < self.variance <= 1.0:
            raise InputError(f"variance must lie in (0, 1], got {self.variance}")
        if self.clusters < 1 or self.max_iterations < 1:
            raise InputError("clusters and max_iterations must be at least 1")
        if not (self.regularizer > 0 and self.tolerance >= 0):
            raise InputError("regularizer must be positive and tolerance non-negative")
        return count_frames(self.min_length, rate, "min_length", 0)


GMM_PAPER = GmmParams()
"""§3.3's parameters: PCA to 90 % of the variance, k = 4, segments under 1 s merged."""


@dataclass(frozen=True)
class GmmResult:
    """:func:`gmm_analysis`: the ``boundaries``; ``labels`` ``(N,)`` after merging and
    ``raw_labels`` ``(N,)`` (each frame's most likely cluster); ``dims`` the PCA's components;
    ``iterations`` of EM; ``log_likelihood`` its final mean per frame."""

    boundaries: list[Boundary]
    labels: IntArray
    raw_labels: IntArray
    dims: int
    iterations: int
    log_likelihood: float


def _log_densities(y: FloatArray, means: FloatArray, covariances: FloatArray) -> FloatArray:
    """``log N(y_i | m_j, Σ_j)``: ``y`` ``(N, d)``, ``means`` ``(k, d)``, ``covariances`` ``(k, d,
    d)`` give ``(N, k)``."""
    n, d = y.shape
    out = np.empty((n, means.shape[0]))
    for j in range(means.shape[0]):
        lower = np.linalg.cholesky(covariances[j])
        z = np.linalg.solve(lower, (y - means[j]).T)
        out[:, j] = -0.5 * ((z * z).sum(axis=0) + d * math.log(2 * math.pi)) - np.log(np.diag(lower)).sum()
    return out


def merge_short_runs(labels: npt.ArrayLike, min_length: int) -> IntArray:
    """§3.3's heuristic on ``labels`` shape ``(N,)``, giving shape ``(N,)``: while a run of equal
    labels is shorter than ``min_length`` frames (and not the only run), the shortest (the first of
    equals) is split in two halves that take the labels of the runs before and after it (the first
    ``floor(length / 2)`` frames the one before); a run at either end joins its one neighbour whole."""
    out = np.array(labels, dtype=np.int64).reshape(-1)
    while True:
        starts = np.flatnonzero(np.concatenate([[True], out[1:] != out[:-1]]))
        ends = np.concatenate([starts[1:], [out.shape[0]]])
        lengths = ends - starts
        if starts.shape[0] < 2 or lengths.min() >= min_length:
            return out
        i = int(np.argmin(lengths))
        a, b = int(starts[i]), int(ends[i])
        if i == 0:
            out[a:b] = out[b]
        elif i == starts.shape[0] - 1:
            out[a:b] = out[a - 1]
        else:
            middle = a + (b - a) // 2
            out[a:middle] = out[a - 1]
            out[middle:b] = out[b]


def gmm_analysis(frames: npt.ArrayLike, rate: float, *, params: GmmParams = GMM_PAPER) -> GmmResult:
    """§3.3 over ``frames`` shape ``(N, D)`` at ``rate`` Hz: project the centred frames onto the
    fewest principal components that keep ``variance`` of the total (Eq. 6's rule with ``τ =
    variance``); fit a mixture of ``clusters`` full-covariance Gaussians by EM (the standard updates
    the paper refers to, its ref. [8]; the means started at one seeded random frame from each of
    ``clusters`` consecutive parts, every covariance at the data's, equal weights); label each frame
    with its most likely cluster; merge runs shorter than ``min_length`` (:func:`merge_short_runs`);
    a boundary at every change of label. Deterministic for a given seed. Fewer frames than clusters,
    or frames that do not vary, give one segment and no boundary."""
    x = check_frames(frames)
    min_length = params.check(rate)
    n = x.shape[0]
    none = np.zeros(n, dtype=np.int64)
    # Measured from the first frame, frames that do not vary centre to exactly zero.
    shifted = x - x[0] if n else x
    centred = shifted - shifted.mean(axis=0) if n else x
    eigenvalues, vectors = np.linalg.eigh(centred.T @ centred)
    eigenvalues = np.maximum(eigenvalues, 0.0)
    dims = dimension(eigenvalues, params.variance) if params.variance < 1 else int((eigenvalues > 0).sum())
    k = params.clusters
    if n < max(k, 2) or dims == 0:
        return GmmResult([], none, none.copy(), dims, 0, 0.0)
    y = centred @ vectors[:, ::-1][:, :dims]
    spread = np.cov(y, rowvar=False).reshape(dims, dims)
    ridge = params.regularizer * float(np.trace(spread)) / dims * np.eye(dims)
    rng = np.random.default_rng(params.seed)
    parts = np.linspace(0, n, k + 1).astype(np.int64)
    means = y[[int(rng.integers(parts[j], parts[j + 1])) for j in range(k)]]
    covariances = np.repeat((spread + ridge)[None], k, axis=0)
    weights = np.full(k, 1.0 / k)
    previous, iterations, tiny = -math.inf, 0, np.finfo(np.float64).tiny
    while iterations < params.max_iterations:
        iterations += 1
        joint = _log_densities(y, means, covariances) + np.log(np.maximum(weights, tiny))
        top = joint.max(axis=1, keepdims=True)
        norm = top[:, 0] + np.log(np.exp(joint - top).sum(axis=1))
        responsibilities = np.exp(joint - norm[:, None])
        likelihood = float(norm.mean())
        mass = responsibilities.sum(axis=0)
        weights = mass / n
        safe = np.maximum(mass, tiny)
        means = (responsibilities.T @ y) / safe[:, None]
        for j in range(k):
            deviation = y - means[j]
            covariances[j] = (responsibilities[:, j, None] * deviation).T @ deviation / safe[j] + ridge
        if likelihood - previous < params.tolerance:
            break
        previous = likelihood
    densities = _log_densities(y, means, covariances)
    raw = np.argmax(densities + np.log(np.maximum(weights, tiny)), axis=1).astype(np.int64)
    labels = merge_short_runs(raw, min_length)
    changes = np.flatnonzero(labels[1:] != labels[:-1]) + 1
    edges = [0, *changes.tolist(), n]
    boundaries = []
    for i, c in enumerate(changes.tolist()):
        new, old = int(labels[c]), int(labels[c - 1])
        segment = densities[c : edges[i + 2]]
        score = float((segment[:, new] - segment[:, old]).mean())
        boundaries.append(Boundary(c, "gmm", score, n - 1))
    return GmmResult(boundaries, labels, raw, dims, iterations, likelihood)


def gmm_segment(frames: npt.ArrayLike, rate: float, *, params: GmmParams = GMM_PAPER) -> list[Boundary]:
    """§3.3's cuts of ``frames`` shape ``(N, D)`` at ``rate`` Hz (batch only; :func:`gmm_analysis`)."""
    return gmm_analysis(frames, rate, params=params).boundaries
