"""The features of a whole motion (daemon/features/batch.py): equal to the original toolbox's in
every frame, the hysteresis against a plain loop, invariance under translation, rotation about the
vertical and scale on real motion, and the errors of bad positions."""

from __future__ import annotations

import csv
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from daemon.features import FEATURE_NAMES, feature_tracks, features, hysteresis
from daemon.types import FloatArray
from replay import JOINT_NAMES
from tests.helpers import DATA, ORACLE, ORACLE_CLIPS, clip, joints_cm
from tests.naive import slow_hysteresis

N_JOINTS = len(JOINT_NAMES)


# ------------------------------------------------------------- the toolbox's output, the recurrence


def clip_features(clip: str) -> np.ndarray:
    asf, amc = ORACLE_CLIPS[clip]
    return features(joints_cm(DATA / asf, DATA / amc), JOINT_NAMES, 120.0)


@pytest.mark.parametrize("clip", sorted(ORACLE_CLIPS))
def test_features_match_toolbox(clip: str) -> None:
    with open(ORACLE / f"{clip}.features.csv", newline="") as f:
        rows = csv.reader(f)
        header = next(rows)
        oracle = np.array([[int(v) for v in row[1:]] for row in rows], dtype=bool)
    assert tuple(header[1:]) == FEATURE_NAMES
    ours = clip_features(clip)
    assert ours.shape == oracle.shape
    # every cell: a threshold moved by 2 degrees flips only a few frames of one feature
    differing = {
        name: np.flatnonzero(ours[:, f] != oracle[:, f]).tolist()
        for f, name in enumerate(FEATURE_NAMES)
        if np.any(ours[:, f] != oracle[:, f])
    }
    assert not differing, "features differing from the toolbox (0-based frames): " + "; ".join(
        f"{name}: {len(frames)} frames {frames[:10]}{' ...' if len(frames) > 10 else ''}"
        for name, frames in differing.items()
    )


@settings(max_examples=300, deadline=None)
@given(st.lists(st.tuples(st.booleans(), st.booleans()), min_size=1, max_size=60))
def test_hysteresis_equals_the_recurrence(pairs: list[tuple[bool, bool]]) -> None:
    f2 = [b for _, b in pairs]
    f1 = [a or b for a, b in pairs]  # nested tracks: f2 implies f1
    got = hysteresis(np.array(f1)[:, None], np.array(f2)[:, None])[:, 0]
    assert got.tolist() == slow_hysteresis(f1, f2)


# ------------------------------------------------------------------------ invariance, real motion

# HDM_bk_grabHighR_006 holds the signal value closest to a threshold in the whole data, 02_07 the
# one closest relative to what a transform changes (found by scanning every recording; see
# assert_invariant).
INVARIANCE_CLIPS = ("02_01", "13_29", "HDM_bk_grabHighR_006_120", "02_07")
clips = st.sampled_from(INVARIANCE_CLIPS)
translations = st.tuples(*[st.floats(-1000.0, 1000.0)] * 3)  # cm: anywhere in a 20 m room
angles = st.floats(-math.pi, math.pi)
scales = st.floats(0.25, 4.0)


def rotation_y(angle: float) -> FloatArray:
    """Rotation by ``angle`` radians about the vertical y axis."""
    c, s = math.cos(angle), math.sin(angle)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def assert_invariant(name: str, transformed: FloatArray) -> None:
    """The feature matrix (and the loose and strict tracks) of the transformed clip are those of the
    clip, bit for bit.

    Exact equality is justified, not lucky. The transforms are exact in real arithmetic; their
    rounding changes a signal by at most 2e-12 of its threshold's scale (the body length it is
    measured in; 1 for cosines), the worst being the 1-frame velocities of *MoveApartRelRoot after
    a translation. A scan of all 218 recordings (4 random transforms each: translation up to
    10 m, any rotation about y, scale 0.5 to 2, all three) found no signal closer to a threshold
    than 2.1e-7 of its scale (HDM_bk_grabHighR_006 frame 130, handRightRaisedRelSpine, T1 = 0),
    and the smallest ratio of distance-to-threshold over the change the transform caused was 8e6
    (02_07 frame 280, handLeftMoveApartRelRoot). No cell of f1, f2 or the output flipped."""
    original = clip(name)
    tracks = feature_tracks(original, JOINT_NAMES, 120.0)
    moved = feature_tracks(transformed, JOINT_NAMES, 120.0)
    for before, after in zip(tracks, moved, strict=True):
        assert np.array_equal(before, after), np.argwhere(before != after)[:10].tolist()
    assert np.array_equal(features(transformed, JOINT_NAMES), features(original, JOINT_NAMES))


@settings(max_examples=12, deadline=None)
@given(clips, translations)
def test_translation_invariance(name: str, offset: tuple[float, float, float]) -> None:
    assert_invariant(name, clip(name) + np.array(offset))


@settings(max_examples=12, deadline=None)
@given(clips, angles)
def test_vertical_rotation_invariance(name: str, angle: float) -> None:
    assert_invariant(name, clip(name) @ rotation_y(angle).T)


@settings(max_examples=12, deadline=None)
@given(clips, scales)
def test_scale_invariance(name: str, scale: float) -> None:
    assert_invariant(name, clip(name) * scale)


@settings(max_examples=12, deadline=None)
@given(clips, translations, angles, scales)
def test_rigid_motion_and_scale_invariance(
    name: str, offset: tuple[float, float, float], angle: float, scale: float
) -> None:
    assert_invariant(name, (clip(name) @ rotation_y(angle).T) * scale + np.array(offset))


def test_invariance_clips_exercise_the_features() -> None:
    """The clips are not trivial: between them every feature is on somewhere and off somewhere."""
    matrices = np.concatenate([features(clip(name), JOINT_NAMES) for name in INVARIANCE_CLIPS])
    on: list[bool] = np.asarray(matrices.any(axis=0)).tolist()
    off: list[bool] = np.asarray((~matrices).any(axis=0)).tolist()
    assert all(on) and all(off), [n for n, a, b in zip(FEATURE_NAMES, on, off, strict=True) if not (a and b)]


# ------------------------------------------------------------------------------------ errors


@pytest.mark.parametrize("value", [math.nan, math.inf, -math.inf])
@pytest.mark.parametrize("frame", [0, 5, 39])
def test_features_names_the_non_finite_frame(value: float, frame: int) -> None:
    positions = np.array(clip("02_01")[:40])
    positions[frame, 3, 2] = value
    with pytest.raises(ValueError, match=rf"not finite at frame index {frame}$"):
        features(positions, JOINT_NAMES)


@pytest.mark.parametrize("shape", [(10, N_JOINTS - 1, 3), (10, N_JOINTS), (N_JOINTS, 3)])
def test_features_rejects_a_wrong_shape(shape: tuple[int, ...]) -> None:
    with pytest.raises(ValueError, match="positions must have shape"):
        features(np.zeros(shape), JOINT_NAMES)
