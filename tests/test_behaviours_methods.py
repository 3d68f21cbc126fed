"""The methods of behaviour segmentation by name (daemon.behaviours.methods): each runs, and what
does not fit is refused."""

from __future__ import annotations

import numpy as np
import pytest

from daemon.behaviours.gmm import gmm_segment
from daemon.behaviours.methods import analyse, online_segmenter, segment
from daemon.behaviours.pca import pca_segment
from daemon.behaviours.ppca import PpcaParams, PpcaSegmenter, ppca_segment
from tests.behaviour_data import PPCA_SMALL, frames


def test_the_dispatch_runs_each_method() -> None:
    x = frames("13_30")[:1000]
    assert segment(x, 120.0, "pca") == pca_segment(x, 120.0)
    assert segment(x, 120.0, "ppca", params=PPCA_SMALL) == ppca_segment(x, 120.0, params=PPCA_SMALL)
    assert segment(x, 120.0, "gmm") == gmm_segment(x, 120.0)
    assert isinstance(online_segmenter(120.0, "ppca"), PpcaSegmenter)


def test_the_dispatch_refuses_what_does_not_fit() -> None:
    with pytest.raises(ValueError, match="online"):
        online_segmenter(120.0, "gmm")
    with pytest.raises(ValueError, match="do not fit"):
        segment(np.zeros((10, 4)), 120.0, "pca", params=PpcaParams())
    with pytest.raises(ValueError, match="do not fit"):
        analyse(np.zeros((10, 4)), 120.0, "gmm", params=PpcaParams())
