"""What the tests of behaviour segmentation (``tests/test_behaviours*.py``) share: the real takes and
their frame vectors, random piecewise stationary frames and the strategy drawing them, and the
small windows they run at."""

from __future__ import annotations

import functools

import numpy as np
from hypothesis import HealthCheck, settings
from hypothesis import strategies as st

from daemon.behaviours import JointRotations, PpcaParams
from daemon.recordings import read_recording
from daemon.tools.mocap6 import trial_recording
from daemon.types import FloatArray
from replay import Motion
from tests.helpers import DATA

SETTINGS = settings(deadline=None, max_examples=25, suppress_health_check=[HealthCheck.too_slow])
REAL = ("86_01", "13_29", "13_30", "14_14", "135_06")
"""The files the evaluation uses, and 135_06 (its root angles go past ±180° too)."""

RATE = 10.0
"""Random streams run at 10 Hz so the paper's windows are few frames: PCA k = 20, ℓ = 5, i₀ = 25."""
PPCA_SMALL = PpcaParams(window=1.5, delta=0.2, rise=15.0, shortest=3.0)
"""T = 15, Δ = 2 frames at 10 Hz, R = 15, the shortest behaviour 2 T = 30 frames."""

Regimes = tuple[int, int, list[int]]
"""The arguments of :func:`regimes`: seed, dimensions, run lengths."""


@functools.cache
def motion(trial: str) -> Motion:
    return read_recording(*trial_recording(DATA, trial))


@functools.cache
def frames(trial: str) -> FloatArray:
    m = motion(trial)
    out: FloatArray = JointRotations(m.skeleton)(m.channels)
    return out


def regimes(seed: int, dims: int, lengths: list[int]) -> FloatArray:
    """Piecewise stationary random frames ``(sum(lengths), dims)``: each run has its own centre,
    latent dimension and spread, plus a little isotropic noise."""
    rng = np.random.default_rng(seed)
    parts = []
    for n in lengths:
        latent = int(rng.integers(1, dims + 1))
        basis = rng.normal(size=(latent, dims)) * rng.uniform(0.2, 3.0)
        centre = 2.0 * rng.normal(size=dims)
        parts.append(centre + rng.normal(size=(n, latent)) @ basis + 0.05 * rng.normal(size=(n, dims)))
    return np.concatenate(parts)


def regime_cases(
    dims: tuple[int, int], lengths: tuple[int, int], runs: tuple[int, int] = (1, 4)
) -> st.SearchStrategy[Regimes]:
    """Arguments of :func:`regimes`: any seed, ``dims`` and each run's length within the bounds
    given (inclusive), ``runs`` runs."""
    return st.tuples(
        st.integers(0, 2**32 - 1),
        st.integers(*dims),
        st.lists(st.integers(*lengths), min_size=runs[0], max_size=runs[1]),
    )
