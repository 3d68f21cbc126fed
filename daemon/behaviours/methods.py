"""The three methods of behaviour segmentation (Barbič et al. 2004) by name: the batch cuts
(:func:`segment`), the cuts with each method's signal (:func:`analyse`) and the online segmenters
(:func:`online_segmenter`), each with the paper's parameters unless others are given.
"""

from __future__ import annotations

from typing import TypeVar

import numpy.typing as npt

from daemon.behaviours.common import Boundary, Method
from daemon.behaviours.gmm import GMM_PAPER, GmmParams, GmmResult, gmm_analysis
from daemon.behaviours.pca import PCA_ONLINE, PCA_PAPER, PcaParams, PcaResult, PcaSegmenter, pca_analysis
from daemon.behaviours.ppca import (
    PPCA_DEFAULT,
    PPCA_ONLINE,
    PpcaParams,
    PpcaResult,
    PpcaSegmenter,
    ppca_analysis,
)
from daemon.errors import InputError

Params = PcaParams | PpcaParams | GmmParams
_P = TypeVar("_P", PcaParams, PpcaParams, GmmParams)


def segment(
    frames: npt.ArrayLike, rate: float, method: Method, *, params: Params | None = None
) -> list[Boundary]:
    """The cuts of ``frames`` shape ``(N, D)`` at ``rate`` Hz by ``method`` (batch; PPCA with all its
    passes), with ``params`` (the method's parameter class; None: the paper's): the boundaries of
    :func:`analyse`."""
    return analyse(frames, rate, method, params=params).boundaries


def analyse(
    frames: npt.ArrayLike, rate: float, method: Method, *, params: Params | None = None
) -> PcaResult | PpcaResult | GmmResult:
    """:func:`segment` with the method's signal (:func:`pca_analysis`, :func:`ppca_analysis`,
    :func:`gmm_analysis`): the same cuts in ``.boundaries``."""
    if method == "pca":
        return pca_analysis(frames, rate, params=_params(params, PcaParams, PCA_PAPER))
    if method == "ppca":
        return ppca_analysis(frames, rate, params=_params(params, PpcaParams, PPCA_DEFAULT))
    if method == "gmm":
        return gmm_analysis(frames, rate, params=_params(params, GmmParams, GMM_PAPER))
    raise InputError(f"unknown segmentation method {method!r}: pca, ppca or gmm")


def online_segmenter(
    rate: float, method: Method, *, params: Params | None = None
) -> PcaSegmenter | PpcaSegmenter:
    """A streaming segmenter for ``method`` at ``rate`` Hz: PCA (by default with
    :data:`~daemon.behaviours.pca.PCA_ONLINE`), or PPCA's forward pass (by default with
    :data:`~daemon.behaviours.ppca.PPCA_ONLINE`); GMM has none (``ValueError``)."""
    if method == "pca":
        return PcaSegmenter(rate, params=_params(params, PcaParams, PCA_ONLINE))
    if method == "ppca":
        return PpcaSegmenter(rate, params=_params(params, PpcaParams, PPCA_ONLINE))
    raise InputError(f"segmentation method {method!r} has no online form (pca and ppca do)")


def _params(given: Params | None, kind: type[_P], default: _P) -> _P:
    if given is None:
        return default
    if not isinstance(given, kind):
        raise InputError(f"parameters {type(given).__name__} do not fit {kind.__name__}")
    return given
