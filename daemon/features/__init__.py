"""The 39 boolean relational features (thesis Table 5.1; MRC05 section 3) as data, compiled once into
Python that evaluates them on a whole motion (:func:`features`) or one pose at a time
(:class:`FeatureStream`) with bit-identical results.

Every feature is a *signal* (a real-valued function of the joint positions per frame, built from a
few geometric primitives) compared with two thresholds: a loose ``T1`` giving the track ``f1`` and a
strict ``T2`` giving ``f2``. The hysteresis of the toolbox's ``features_combine_robust`` (reference
facts, section b) combines them: ``out(t) = f2(t) or (out(t-1) and f1(t))``, ``out(0) = 0``. Every
threshold is a multiple of a body length measured at the first frame, so features do not change with
the actor's size, position or heading. Definitions: ``../shared/reference/bonn-toolbox-facts.md``
sections a and 0.

One subsystem per module, each importing only those listed before it:

* :mod:`~daemon.features.language`: the signals, tests and features the catalog is written in, and
  the body lengths thresholds are multiples of;
* :mod:`~daemon.features.catalog`: the 39 features, their names and the three sets;
* :mod:`~daemon.features.velocity`: window lengths and smoothed velocities;
* :mod:`~daemon.features.assembler`: generated Python, read back as register-machine code;
* :mod:`~daemon.features.compiler`: the catalog compiled to Python for a joint order and a rate;
* :mod:`~daemon.features.batch`: the features of a whole motion;
* :mod:`~daemon.features.stream`: the features one pose at a time, their latency, decimation.

This package re-exports the names the rest of mocapd imports.
"""

from daemon.features.batch import feature_tracks, features, hysteresis
from daemon.features.catalog import FEATURE_NAMES, SET_SLICES
from daemon.features.stream import (
    Decimator,
    FeatureStream,
    decimate,
    decimation_factor,
    last_sample,
    latency_frames,
    sample_count,
    sample_poses,
    sample_rows,
    sampled_features,
    sampling_ratio,
)
from daemon.features.velocity import smoothed_velocity, window_frames

__all__ = [
    "FEATURE_NAMES",
    "SET_SLICES",
    "Decimator",
    "FeatureStream",
    "decimate",
    "decimation_factor",
    "feature_tracks",
    "features",
    "hysteresis",
    "last_sample",
    "latency_frames",
    "sample_count",
    "sample_poses",
    "sample_rows",
    "sampled_features",
    "sampling_ratio",
    "smoothed_velocity",
    "window_frames",
]
