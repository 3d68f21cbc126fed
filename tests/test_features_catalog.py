"""The catalog (daemon/features/catalog.py): its three sets, and the features mean what they say:
semantic checks on real clips (../shared/data/mocap).

Every expectation here comes from the motion itself (joint heights, ankle positions along the walking
direction, wrist speeds, all computed below straight from the joint positions) or from the data's
labels (the HDM05 class of a cut clip), never from feature output. The features are then checked
against it. Thresholds are in centimetres (``KinematicModel.positions(..., "cm")``) and chosen well
away from the features' own thresholds, which are multiples of body lengths measured at frame 1
(the humerus ``h`` is 26-31 cm for the actors used here, so e.g. "foot raised" means about 26-37 cm
above the lowest body point); each one is explained where it is used.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cache
from itertools import pairwise
from pathlib import Path

import numpy as np
import pytest

from daemon.features import FEATURE_NAMES, SET_SLICES, features
from daemon.types import BoolArray, FeatureSet, FloatArray
from replay import JOINT_NAMES
from tests.helpers import joints_cm, pair_id, recording_pairs

Pair = tuple[Path, Path]

FPS = 120.0
UP = np.array([0.0, 1.0, 0.0])


# --------------------------------------------------------------------------------------------------
# the catalog


def test_catalog_sets() -> None:
    assert len(FEATURE_NAMES) == 39
    assert [s.stop - s.start for s in SET_SLICES.values()] == [12, 14, 13]


# --------------------------------------------------------------------------------------------------
# clips


@dataclass(frozen=True)
class Clip:
    name: str
    joints: FloatArray  # (N, 26, 3) in cm, JOINT_NAMES order, y up
    matrix: BoolArray  # (N, 39) in FEATURE_NAMES order

    def __len__(self) -> int:
        return len(self.joints)

    def p(self, joint: str) -> FloatArray:
        """Trajectory of ``joint``, shape (N, 3)."""
        out: FloatArray = self.joints[:, JOINT_NAMES.index(joint)]
        return out

    def y(self, joint: str) -> FloatArray:
        """Height of ``joint``, shape (N,)."""
        return self.p(joint)[:, 1]

    def f(self, name: str, feature_set: FeatureSet) -> BoolArray:
        """Feature ``name``, shape (N,); also checks that it belongs to ``feature_set``."""
        k = FEATURE_NAMES.index(name)
        part = SET_SLICES[feature_set]
        assert part.start <= k < part.stop, (name, feature_set)
        out: BoolArray = self.matrix[:, k]
        return out

    def floor(self) -> float:
        """Floor level: the median over frames of the lowest foot joint (toes, ankles). In all the
        clips used here at least one foot touches the floor most of the time; the median ignores the
        few frames where a marker dips below the floor or both feet are off it."""
        feet = [JOINT_NAMES.index(j) for j in ("ltoes", "rtoes", "lankle", "rankle")]
        return float(np.median(self.joints[:, feet, 1].min(axis=1)))


@cache
def clip(asf: Path, amc: Path) -> Clip:
    joints = joints_cm(asf, amc)
    return Clip(pair_id((asf, amc)), joints, features(joints, JOINT_NAMES, FPS))


def load(pair: Pair) -> Clip:
    return clip(*pair)


def hdm05_class(name: str) -> list[Pair]:
    """Every HDM05 cut clip of one motion class present in the data (the folder is the class label)."""
    return [p for p in recording_pairs() if p[1].parent.name == name and p[1].parent.parent.name == "cut"]


def cmu(trial: str) -> Pair:
    (pair,) = [p for p in recording_pairs() if pair_id(p) == trial]
    return pair


SQUATS = hdm05_class("squat1Reps")
LIE_DOWN = hdm05_class("lieDownFloor")
KICKS = hdm05_class("kickLFront1Reps")
GRAB_HIGH = hdm05_class("grabHighR")
DEPOSIT_FLOOR = hdm05_class("depositFloorR")


def test_the_labelled_classes_are_all_here() -> None:
    """Guards the parametrizations below against an empty selection (MANIFEST, section 2: actors bd,
    bk and dg are present)."""
    counts = {
        "squat1Reps": len(SQUATS),
        "lieDownFloor": len(LIE_DOWN),
        "kickLFront1Reps": len(KICKS),
        "grabHighR": len(GRAB_HIGH),
        "depositFloorR": len(DEPOSIT_FLOOR),
    }
    assert counts == {
        "squat1Reps": 36,
        "lieDownFloor": 14,
        "kickLFront1Reps": 18,
        "grabHighR": 16,
        "depositFloorR": 18,
    }


# --------------------------------------------------------------------------------------------------
# helpers


def moving_average(x: FloatArray, k: int) -> FloatArray:
    """Centred box average over ``k`` (odd) samples, edges repeated."""
    half = k // 2
    padded = np.pad(x, (half, half), mode="edge")
    out: FloatArray = np.convolve(padded, np.ones(k) / k, mode="valid")
    return out


def runs(mask: BoolArray) -> list[tuple[int, int]]:
    """Maximal runs of True as ``(start, stop)``, stop exclusive."""
    edges = np.flatnonzero(np.diff(np.concatenate(([0], mask.astype(np.int8), [0]))))
    return [(int(a), int(b)) for a, b in zip(edges[::2], edges[1::2], strict=True)]


def fraction(on: BoolArray, where: BoolArray) -> float:
    """Fraction of the frames ``where`` on which ``on`` holds (``where`` must not be empty)."""
    assert where.any(), "the motion-derived frame selection is empty"
    return float(on[where].mean())


def facing(c: Clip) -> FloatArray:
    """Unit horizontal forward direction per frame, shape (N, 3): perpendicular to the hip axis
    (``up x (rhip - lhip)`` points to the front for a y-up, right-handed frame). Not the torso plane
    of the features (neck, rhip, lhip)."""
    forward = np.cross(UP, c.p("rhip") - c.p("lhip"))
    forward[:, 1] = 0.0
    out: FloatArray = forward / np.linalg.norm(forward, axis=1, keepdims=True)
    return out


# --------------------------------------------------------------------------------------------------
# lower


@pytest.mark.parametrize("pair", SQUATS, ids=pair_id)
def test_knees_bent_at_the_bottom_of_a_squat(pair: Pair) -> None:
    """kneeRightBent and kneeLeftBent at the bottom of every HDM05 squat: the frame where the pelvis
    (root) is lowest, and 50 ms (6 frames) either side of it. The clips are cut from standing to
    standing, so at the first and last frames, where the pelvis is still in the top quarter of its
    range, neither knee counts as bent."""
    c = load(pair)
    root = c.y("root")
    bottom = int(np.argmin(root))
    drop = float(root.max() - root[bottom])
    # A real squat: the pelvis goes down by 44-66 cm in these clips (a good part of the leg length),
    # and the bottom is well inside the clip.
    assert drop > 30.0
    assert 6 <= bottom < len(c) - 6
    near = slice(bottom - 6, bottom + 7)
    right, left = c.f("kneeRightBent", "lower"), c.f("kneeLeftBent", "lower")
    assert right[near].all() and left[near].all(), (bottom, right[near], left[near])
    for edge in (0, len(c) - 1):
        assert root.max() - root[edge] < 0.25 * drop  # still (or again) standing up
        assert not right[edge] and not left[edge], edge


def walking_direction(c: Clip) -> FloatArray:
    """Unit horizontal direction from the first to the last root position."""
    travel = c.p("root")[-1] - c.p("root")[0]
    travel[1] = 0.0
    distance = float(np.linalg.norm(travel))
    assert distance > 200.0, distance  # 02_01 and 35_01 cover 3.4 and 3.8 m in a straight line
    out: FloatArray = travel / distance
    return out


@pytest.mark.parametrize("trial", ["02_01", "35_01"])
def test_feet_behind_alternate_with_the_steps_of_a_walk(trial: str) -> None:
    """footRightBackRelLegLeft / footLeftBackRelLegRight follow the steps of a straight walk.

    Steps from the trajectory alone: ``d = (rankle - lankle) . walking direction`` is negative while
    the right foot is behind the left one and positive in the other half of the gait cycle; each
    change of sign is a step. Ankles that are within 15 cm of each other along the path count as
    neither (a dead band around the crossing: the ankles reach 60-67 cm apart at full stride). Then:

    * the on-intervals of the two features, taken in time order, alternate right, left, right, ...,
      start with the foot that is behind first, and there are as many as there are step phases (+-1
      for a phase cut by the ends of the clip);
    * where the right foot is clearly behind (d < -15 cm) footRightBack is on on >= 90 % of the
      frames and footLeftBack on none (<= 2 %), and the other way round;
    * each feature switches within 0.1 s (12 frames) of a change of sign of d: the features change
      with the steps, not somewhere in between.
    """
    c = load(cmu(trial))
    d = np.einsum("ij,j->i", c.p("rankle") - c.p("lankle"), walking_direction(c))
    band = 15.0
    right_behind, left_behind = d < -band, d > band

    phases: list[str] = []  # "R" = right foot behind, "L" = left foot behind, in time order
    for _, _, side in sorted(
        [(a, b, "R") for a, b in runs(right_behind)] + [(a, b, "L") for a, b in runs(left_behind)]
    ):
        if not phases or phases[-1] != side:
            phases.append(side)
    assert len(phases) >= 5, phases  # about three seconds of walking: 5-6 steps

    f_right = c.f("footRightBackRelLegLeft", "lower")
    f_left = c.f("footLeftBackRelLegRight", "lower")
    intervals = sorted([(a, b, "R") for a, b in runs(f_right)] + [(a, b, "L") for a, b in runs(f_left)])
    sides = [side for _, _, side in intervals]
    assert all(x != y for x, y in pairwise(sides)), sides
    assert sides[0] == phases[0], (sides, phases)
    assert abs(len(sides) - len(phases)) <= 1, (sides, phases)

    assert fraction(f_right, right_behind) >= 0.9
    assert fraction(f_left, right_behind) <= 0.02
    assert fraction(f_left, left_behind) >= 0.9
    assert fraction(f_right, left_behind) <= 0.02

    crossings = np.flatnonzero(np.diff(np.sign(d)) != 0)
    switches = [int(t) for a, b, _ in intervals for t in (a, b) if 0 < t < len(c)]
    assert switches
    for t in switches:
        assert np.min(np.abs(crossings - t)) <= 12, (t, crossings)


@pytest.mark.parametrize("pair", KICKS, ids=pair_id)
def test_foot_raised_during_a_front_kick(pair: Pair) -> None:
    """footLeftRaisedRelYBodyMin while the left foot kicks high, footRightRaisedRelYBodyMin never
    while the right foot stands on the floor; neither while both feet are on the floor.

    "Kicking high": the left toes more than 50 cm above the floor level (Clip.floor); the kicks reach
    1-1.65 m. "On the floor": toes within 8 cm of the floor level (standing toes are 0-7 cm)."""
    c = load(pair)
    floor = c.floor()
    left_toes, right_toes = c.y("ltoes") - floor, c.y("rtoes") - floor
    left, right = c.f("footLeftRaisedRelYBodyMin", "lower"), c.f("footRightRaisedRelYBodyMin", "lower")
    kicking = left_toes > 50.0
    assert kicking.sum() >= 24  # the foot stays up for at least 0.2 s
    top = int(np.argmax(left_toes))
    assert left[top] and not right[top]
    assert fraction(left, kicking) >= 0.95
    assert fraction(right, kicking & (right_toes < 8.0)) == 0.0
    standing = (left_toes < 8.0) & (right_toes < 8.0)
    assert fraction(left | right, standing) == 0.0


# --------------------------------------------------------------------------------------------------
# upper


def test_right_hand_to_the_front_during_strikes() -> None:
    """handRightToFrontRelTorso during the strikes of CMU 02_05 (punch/strike; the Bonn manual
    classification labels the whole file 'punch', so the strikes are found from the motion).

    Strikes: the right wrist's forward velocity relative to the pelvis, along the facing direction
    (perpendicular to the hip axis), smoothed over 0.1 s, has a peak above 1 m/s; peaks closer than
    0.4 s are one strike. The clip has 9 such strikes; between them the hand is drawn back slowly.
    Then:

    * the feature is on at the peak of >= 80 % of the strikes;
    * every on-interval holds at most one strike, and at most 2 on-intervals hold none (the hands
      rise into the guard at the start of the clip);
    * it is off (>= 95 % of the frames) while the hand is still: wrist speed relative to the pelvis
      under 20 cm/s;
    * it is off (>= 95 %) while the hand is drawn back (forward velocity below -50 cm/s).
    """
    c = load(cmu("02_05"))
    forward = facing(c)
    # sanity: the hip-axis normal points the way the toes do
    toes = c.p("rtoes") - c.p("rankle")
    assert np.mean(np.einsum("ij,ij->i", forward, toes) > 0) > 0.9

    wrist = c.p("rwrist") - c.p("root")
    reach = np.einsum("ij,ij->i", wrist, forward)
    velocity = moving_average(np.gradient(reach) * FPS, 13)
    peaks = [
        t
        for t in range(1, len(c) - 1)
        if velocity[t] > 100.0 and velocity[t] >= velocity[t - 1] and velocity[t] > velocity[t + 1]
    ]
    strikes: list[int] = []
    for t in peaks:
        if strikes and t - strikes[-1] < 48:
            if velocity[t] > velocity[strikes[-1]]:
                strikes[-1] = t
        else:
            strikes.append(t)
    assert len(strikes) >= 6, strikes

    feature = c.f("handRightToFrontRelTorso", "upper")
    assert np.mean(feature[strikes]) >= 0.8, (strikes, feature[strikes])
    per_interval = [sum(a <= t < b for t in strikes) for a, b in runs(feature)]
    assert max(per_interval) <= 1, per_interval
    assert per_interval.count(0) <= 2, per_interval

    speed = moving_average(np.linalg.norm(np.gradient(wrist, axis=0), axis=1) * FPS, 13)
    assert fraction(~feature, speed < 20.0) >= 0.95
    assert fraction(~feature, velocity < -50.0) >= 0.95


@pytest.mark.parametrize("pair", GRAB_HIGH, ids=pair_id)
def test_hand_raised_when_reaching_high(pair: Pair) -> None:
    """handRightRaisedRelSpine while the right hand reaches for a high shelf (HDM05 grabHighR).

    "Raised": the right wrist above the head joint (top of the neck) or at its highest point of the
    clip; "down": the wrist more than 15 cm below the right shoulder (a margin, because the
    feature's plane is perpendicular to the spine and through the neck, which tilts as the actor
    stretches). The left hand takes no part: it stays below the left shoulder throughout, and
    handLeftRaisedRelSpine stays off."""
    c = load(pair)
    right = c.f("handRightRaisedRelSpine", "upper")
    wrist = c.y("rwrist")
    assert right[int(np.argmax(wrist))]
    above_head = wrist > c.y("head")
    if above_head.any():  # 12 of the 16 clips; the others reach just below head height
        assert right[above_head].all()
    assert fraction(~right, wrist < c.y("rshoulder") - 15.0) == 1.0
    assert (c.y("lwrist") < c.y("lshoulder")).all()
    assert not c.f("handLeftRaisedRelSpine", "upper").any()


# --------------------------------------------------------------------------------------------------
# mix


@pytest.mark.parametrize("pair", LIE_DOWN, ids=pair_id)
def test_spine_horizontal_and_body_low_while_lying_on_the_floor(pair: Pair) -> None:
    """spineHorizontalRelY and bodyExtentRelY while lying on the floor (HDM05 lieDownFloor), and
    neither while standing.

    "Lying": both the head and the pelvis within 25 cm of the floor level (Clip.floor): the head
    alone can be low when kneeling bent over, the pelvis alone when sitting. Every clip ends lying.
    "Standing": the head at >= 90 % of its height at frame 1, where every clip starts standing
    upright (the first 0.25 s included)."""
    c = load(pair)
    floor = c.floor()
    head, pelvis = c.y("head") - floor, c.y("root") - floor
    lying = (head < 25.0) & (pelvis < 25.0)
    standing = head >= 0.9 * head[0]
    assert head[0] > 140.0 and lying[-1]
    assert standing[:30].all()

    spine = c.f("spineHorizontalRelY", "mix")
    low = c.f("bodyExtentRelY", "mix")
    assert fraction(spine, lying) >= 0.9
    assert fraction(low, lying) >= 0.9
    assert not spine[standing].any()
    assert not low[standing].any()


@pytest.mark.parametrize("pair", DEPOSIT_FLOOR, ids=pair_id)
def test_hand_low_when_depositing_an_object_on_the_floor(pair: Pair) -> None:
    """handRightLowRelYBodyMin while the right hand puts an object on the floor (HDM05
    depositFloorR): on wherever the right fingers are within 20 cm of the floor level, off wherever
    they are more than 60 cm above it (at the start, standing, they are 74-115 cm up)."""
    c = load(pair)
    fingers = c.y("rfingers") - c.floor()
    feature = c.f("handRightLowRelYBodyMin", "mix")
    assert feature[int(np.argmin(fingers))]
    assert fraction(feature, fingers < 20.0) == 1.0
    assert fraction(~feature, fingers > 60.0) == 1.0


@pytest.mark.parametrize("trial", ["02_03", "09_06"])
def test_root_fast_while_running(trial: str) -> None:
    """rootHighVel throughout a run (CMU 02_03 run/jog, 09_06 run): the pelvis moves at more than
    1.5 m/s on every frame (frame-to-frame speed from the root trajectory)."""
    c = load(cmu(trial))
    speed = np.linalg.norm(np.gradient(c.p("root"), axis=0), axis=1) * FPS
    assert speed.min() > 150.0
    assert c.f("rootHighVel", "mix").all()


def test_root_not_fast_while_standing_in_place() -> None:
    """No rootHighVel while the pelvis is nearly still (under 20 cm/s) in CMU 02_05, where the actor
    strikes from one spot (76 % of the frames)."""
    c = load(cmu("02_05"))
    speed = np.linalg.norm(np.gradient(c.p("root"), axis=0), axis=1) * FPS
    still = speed < 20.0
    assert still.mean() > 0.5
    assert not c.f("rootHighVel", "mix")[still].any()
