"""Behaviour segmentation (Barbič, Safonova, Pan, Faloutsos, Hodgins, Pollard: *Segmenting Motion
Capture Data into Distinct Behaviors*, GI 2004): cut a long take where one behaviour (walk, jump,
punch, ...) ends and the next begins, with no training.

One subsystem per module, each importing only the ones listed before it:

* :mod:`~daemon.behaviours.common`: :class:`Boundary`, the methods' names, windows in seconds, the
  checks of input;
* :mod:`~daemon.behaviours.quaternions`: the frame vectors (§3), joint rotations as sign-consistent
  quaternions, batch and stream;
* :mod:`~daemon.behaviours.moments`: a segment's incremental moments, their spectrum and Eq. 6's
  dimension;
* :mod:`~daemon.behaviours.online`: what the online segmenters share;
* :mod:`~daemon.behaviours.pca`: PCA (§3.1), online (:class:`PcaSegmenter`) with its batch twin
  :func:`pca_segment`;
* :mod:`~daemon.behaviours.ppca`: PPCA (§3.2), the forward pass online (:class:`PpcaSegmenter`, batch
  twin :func:`ppca_forward`), all passes in :func:`ppca_segment`;
* :mod:`~daemon.behaviours.gmm`: GMM (§3.3, batch only), :func:`gmm_segment`;
* :mod:`~daemon.behaviours.scoring`: cuts counted against true boundaries;
* :mod:`~daemon.behaviours.methods`: the methods by name.

Every method returns :class:`Boundary` values: ``frame`` is the 0-based index (into the frames given
or pushed) of the *first frame of the new behaviour*. The streams follow :mod:`daemon.stages`
(``push(frame) -> list[Boundary]``, ``flush() -> list[Boundary]`` then a fresh stream, bounded state)
and return exactly what their batch twins return for the same frames. Input that is not finite is a
``ValueError`` naming the frame. Pure: numpy in, frozen dataclasses out; no I/O.
"""

from daemon.behaviours.common import METHODS, Boundary, Method
from daemon.behaviours.gmm import GMM_PAPER, GmmParams, GmmResult, gmm_analysis, gmm_segment, merge_short_runs
from daemon.behaviours.methods import Params, analyse, online_segmenter, segment
from daemon.behaviours.moments import dimension, projection_error, spectrum
from daemon.behaviours.pca import (
    PCA_GRID,
    PCA_ONLINE,
    PCA_PAPER,
    PcaFrames,
    PcaParams,
    PcaResult,
    PcaSegmenter,
    pca_analysis,
    pca_segment,
)
from daemon.behaviours.ppca import (
    PPCA_DEFAULT,
    PPCA_ONLINE,
    PPCA_PUBLISHED,
    PpcaFrames,
    PpcaParams,
    PpcaResult,
    PpcaSegmenter,
    ppca_analysis,
    ppca_forward,
    ppca_segment,
)
from daemon.behaviours.quaternions import (
    PAPER_BONES,
    JointRotations,
    RigRotations,
    RotationStream,
    consistent_signs,
)
from daemon.behaviours.scoring import match_boundaries, pair_boundaries

__all__ = [
    "GMM_PAPER",
    "METHODS",
    "PAPER_BONES",
    "PCA_GRID",
    "PCA_ONLINE",
    "PCA_PAPER",
    "PPCA_DEFAULT",
    "PPCA_ONLINE",
    "PPCA_PUBLISHED",
    "Boundary",
    "GmmParams",
    "GmmResult",
    "JointRotations",
    "Method",
    "Params",
    "PcaFrames",
    "PcaParams",
    "PcaResult",
    "PcaSegmenter",
    "PpcaFrames",
    "PpcaParams",
    "PpcaResult",
    "PpcaSegmenter",
    "RigRotations",
    "RotationStream",
    "analyse",
    "consistent_signs",
    "dimension",
    "gmm_analysis",
    "gmm_segment",
    "match_boundaries",
    "merge_short_runs",
    "online_segmenter",
    "pair_boundaries",
    "pca_analysis",
    "pca_segment",
    "ppca_analysis",
    "ppca_forward",
    "ppca_segment",
    "projection_error",
    "segment",
    "spectrum",
]
