"""The 39 boolean relational features (thesis Table 5.1; MRC05 section 3): the names the rest of
mocapd imports, re-exported from the modules that define them."""

from daemon.features.compiler import (
    FEATURE_NAMES,
    SET_SLICES,
    Decimator,
    FeatureStream,
    decimate,
    decimation_factor,
    feature_tracks,
    features,
    hysteresis,
    latency_frames,
    smoothed_velocity,
    window_frames,
)

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
    "latency_frames",
    "smoothed_velocity",
    "window_frames",
]
