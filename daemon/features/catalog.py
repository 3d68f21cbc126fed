"""The catalog: the 39 features of thesis Table 5.1 written in the signal language
(:mod:`daemon.features.language`; thresholds from the toolbox, reference facts section a), in the
toolbox's order: lower 1-12, upper 13-26, mix 27-39. Also what the compiler asks of it: its velocity
signals and the joints it reads.
"""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

from daemon.features.language import (
    REFERENCE_PAIRS,
    Absolute,
    AngleToVertical,
    Difference,
    Feature,
    HeightAboveLowest,
    HorizontalExtent,
    JointAngle,
    NormalPlane,
    NormalPlaneVelocity,
    Plane,
    PlaneVelocity,
    SegmentAngle,
    Speed,
    Test,
    VerticalExtent,
)
from daemon.types import N_FEATURES, FeatureSet
from replay.joints import TOOLBOX_JOINTS


def _feature(name: str, feature_set: FeatureSet, *tests: Test) -> Feature:
    return Feature(name, feature_set, tests)


_HIP_AXIS = ("lhip", "rhip")
_TORSO_FORWARD = ("neck", "rhip", "lhip")  # plane(neck, rhip, lhip), fixture lhip: normal points forward
_NAME_MAP_XZ = ("lankle", "rankle", "lwrist", "rwrist", "headtop", "root")

CATALOG: tuple[Feature, ...] = (
    # lower (AK_lower), global 1-12
    _feature(
        "footRightBackRelLegLeft",
        "lower",
        Test(Plane("root", "lhip", "lankle", "rankle"), ">=", 0.0, 0.375, "h_R"),
    ),
    _feature(
        "footLeftBackRelLegRight",
        "lower",
        Test(Plane("root", "rankle", "rhip", "lankle"), ">=", 0.0, 0.375, "h_R"),
    ),
    _feature("footRightRaisedRelYBodyMin", "lower", Test(HeightAboveLowest("rtoes"), ">=", 1.0, 1.2, "h_R")),
    _feature("footLeftRaisedRelYBodyMin", "lower", Test(HeightAboveLowest("ltoes"), ">=", 1.0, 1.2, "h_R")),
    _feature(
        "feetApartRelHips",
        "lower",
        Test(Absolute(NormalPlane("lhip", "rhip", "lankle", "rankle")), ">=", 1.8, 2.1, "h_R"),
    ),
    _feature("kneeRightBent", "lower", Test(JointAngle("rhip", "rknee", "rankle"), "<=", 120.0, 110.0)),
    _feature("kneeLeftBent", "lower", Test(JointAngle("lhip", "lknee", "lankle"), "<=", 120.0, 110.0)),
    _feature(
        "footCrossover",
        "lower",
        Test(
            Difference(
                NormalPlane("lhip", "rhip", "lhip", "rankle"), NormalPlane("lhip", "rhip", "lhip", "lankle")
            ),
            "<=",
            0.0,
            -0.125,
            "hip_width",
        ),
    ),
    _feature(
        "feetMoveTogetherRelHips",
        "lower",
        Test(
            Difference(
                NormalPlaneVelocity(*_HIP_AXIS, "rhip", "lankle", 100.0),
                NormalPlaneVelocity(*_HIP_AXIS, "rhip", "rankle", 100.0),
            ),
            ">=",
            1.3,
            1.5,
            "h_R",
        ),
    ),
    _feature(
        "feetMoveApartRelHips",
        "lower",
        Test(
            Difference(
                NormalPlaneVelocity(*_HIP_AXIS, "rhip", "rankle", 100.0),
                NormalPlaneVelocity(*_HIP_AXIS, "rhip", "lankle", 100.0),
            ),
            ">=",
            1.3,
            1.5,
            "h_R",
        ),
    ),
    _feature(
        "footRightHighVel",
        "lower",
        Test(Speed("rtoes", 100.0), ">=", 2.0, 2.5, "h_R"),
        Test(Speed("rankle", 100.0), ">=", 2.0, 2.5, "h_R"),
    ),
    _feature(
        "footLeftHighVel",
        "lower",
        Test(Speed("ltoes", 100.0), ">=", 2.0, 2.5, "h_R"),
        Test(Speed("lankle", 100.0), ">=", 2.0, 2.5, "h_R"),
    ),
    # upper (AK_upper), global 13-26
    _feature(
        "handRightToFrontRelTorso",
        "upper",
        Test(PlaneVelocity(*_TORSO_FORWARD, "rwrist", 250.0), ">", 1.3, 1.8, "h_L"),
    ),
    _feature(
        "handLeftToFrontRelTorso",
        "upper",
        Test(PlaneVelocity(*_TORSO_FORWARD, "lwrist", 250.0), ">", 1.3, 1.8, "h_L"),
    ),
    _feature(
        "handRightRaisedRelSpine",
        "upper",
        Test(NormalPlane("chest", "neck", "neck", "rwrist"), ">=", 0.0, 0.2, "chest"),
    ),
    _feature(
        "handLeftRaisedRelSpine",
        "upper",
        Test(NormalPlane("chest", "neck", "neck", "lwrist"), ">=", 0.0, 0.2, "chest"),
    ),
    _feature(
        "handRightToTopRelSpine",
        "upper",
        Test(NormalPlaneVelocity("chest", "neck", "neck", "rwrist", 250.0), ">", 1.3, 1.8, "h_L"),
    ),
    _feature(
        "handLeftToTopRelSpine",
        "upper",
        Test(NormalPlaneVelocity("chest", "neck", "neck", "lwrist", 250.0), ">", 1.3, 1.8, "h_L"),
    ),
    _feature(
        "elbowRightBent", "upper", Test(JointAngle("rshoulder", "relbow", "rwrist"), "<=", 120.0, 110.0)
    ),
    _feature("elbowLeftBent", "upper", Test(JointAngle("lshoulder", "lelbow", "lwrist"), "<=", 120.0, 110.0)),
    _feature(
        "handsApartRelShoulders",
        "upper",
        Test(
            Absolute(NormalPlane("lshoulder", "rshoulder", "lwrist", "rwrist")),
            ">=",
            2.0,
            2.5,
            "shoulder_width",
        ),
    ),
    _feature(
        "handsMoveTogether",
        "upper",
        Test(NormalPlaneVelocity("lwrist", "rwrist", "rwrist", "lwrist", 100.0), ">=", 1.2, 1.4, "h_R"),
    ),
    _feature(
        "handRightMoveApartRelRoot",
        "upper",
        Test(NormalPlaneVelocity("rwrist", "root", "rwrist", "root", 0.0), ">=", 1.2, 1.4, "h_R"),
    ),
    _feature(
        "handLeftMoveApartRelRoot",
        "upper",
        Test(NormalPlaneVelocity("lwrist", "root", "lwrist", "root", 0.0), ">=", 1.2, 1.4, "h_R"),
    ),
    _feature("handRightHighVel", "upper", Test(Speed("rfingers", 100.0), ">=", 2.0, 2.5, "h_R")),
    _feature("handLeftHighVel", "upper", Test(Speed("lfingers", 100.0), ">=", 2.0, 2.5, "h_R")),
    # mix (AK_mix), global 27-39
    _feature(
        "humerusRightAbductRelSpine",
        "mix",
        Test(SegmentAngle("neck", "root", "relbow", "rshoulder"), "<", 155.0, 150.0),
    ),
    _feature(
        "humerusLeftAbductRelSpine",
        "mix",
        Test(SegmentAngle("neck", "root", "lelbow", "lshoulder"), "<", 155.0, 150.0),
    ),
    _feature(
        "femurRightAbductRelSpine",
        "mix",
        Test(SegmentAngle("neck", "root", "rhip", "rknee"), ">", 45.0, 50.0),
    ),
    _feature(
        "femurLeftAbductRelSpine", "mix", Test(SegmentAngle("neck", "root", "lhip", "lknee"), ">", 45.0, 50.0)
    ),
    _feature(
        "rootBehindFeetLeftRightNeck",
        "mix",
        Test(Plane("lankle", "neck", "rankle", "root"), "<", -0.35, -0.5, "h_R"),
    ),
    _feature(
        "spineHorizontalRelY",
        "mix",
        Test(AngleToVertical("root", "neck"), "within", (60.0, 120.0), (70.0, 110.0)),
    ),
    _feature(
        "handRightLowRelYBodyMin",
        "mix",
        Test(HeightAboveLowest("rfingers", ("rfingers", "rwrist")), "<", 1.4, 1.2, "h_R"),
    ),
    _feature(
        "handLeftLowRelYBodyMin",
        "mix",
        Test(HeightAboveLowest("lfingers", ("lfingers", "lwrist")), "<", 1.4, 1.2, "h_R"),
    ),
    _feature(
        "shouldersRotatedRightRelHip",
        "mix",
        Test(
            Difference(
                Plane("rhip", "lhip", "neck", "lshoulder"), Plane("rhip", "lhip", "neck", "rshoulder")
            ),
            ">",
            0.35,
            0.40,
            "h_L",
        ),
    ),
    _feature(
        "shouldersRotatedLeftRelHip",
        "mix",
        Test(
            Difference(
                Plane("rhip", "lhip", "neck", "lshoulder"), Plane("rhip", "lhip", "neck", "rshoulder")
            ),
            "<",
            -0.35,
            -0.40,
            "h_L",
        ),
    ),
    _feature("bodyExtentRelY", "mix", Test(VerticalExtent(), "<=", 0.9, 0.8, "body")),
    _feature(
        "bodyExtentExtremitiesRelXZ", "mix", Test(HorizontalExtent(_NAME_MAP_XZ), ">=", 3.0, 3.25, "h_R")
    ),
    _feature("rootHighVel", "mix", Test(Speed("root", 0.0), ">=", 2.0, 2.3, "h_R")),
)

FEATURE_NAMES: tuple[str, ...] = tuple(f.name for f in CATALOG)
SET_SLICES: dict[FeatureSet, slice] = {"lower": slice(0, 12), "upper": slice(12, 26), "mix": slice(26, 39)}
assert len(FEATURE_NAMES) == N_FEATURES == SET_SLICES["mix"].stop


# ---------------------------------------------------------------------------------- queries


def _subsignals(signal: Any) -> Iterator[Any]:
    yield signal
    for value in vars(signal).values():
        if not isinstance(value, str | int | float | tuple):
            yield from _subsignals(value)


def velocity_signals() -> set[PlaneVelocity | NormalPlaneVelocity | Speed]:
    """The catalog's velocity signals, each once (the compiler smooths one trajectory for each)."""
    return {
        s
        for f in CATALOG
        for t in f.tests
        for s in _subsignals(t.signal)
        if isinstance(s, PlaneVelocity | NormalPlaneVelocity | Speed)
    }


def _signal_joints(signal: Any) -> set[str]:
    names: set[str] = set()
    for s in _subsignals(signal):
        for value in vars(s).values():
            if isinstance(value, str):
                names.add(value)
            elif isinstance(value, tuple):
                names.update(v for v in value if isinstance(v, str))
    return names


def catalog_joints() -> set[str]:
    """The joints the catalog reads: those its signals name and the toolbox's name map (lowest and
    highest points)."""
    return set(TOOLBOX_JOINTS).union(*(_signal_joints(t.signal) for f in CATALOG for t in f.tests))


def features_reading(joint: str) -> tuple[str, ...]:
    """The features whose value depends on ``joint``'s position: a test's signal names it, ranges
    over the toolbox's name map it is in (lowest or highest point), or is scaled by a body length
    measured from it (:class:`~daemon.features.language.BodyLengths`)."""

    def reads(test: Test) -> bool:
        ranged = any(
            (isinstance(s, HeightAboveLowest) and joint not in s.exclude) or isinstance(s, VerticalExtent)
            for s in _subsignals(test.signal)
        )
        return (
            joint in _signal_joints(test.signal)
            or (ranged and joint in TOOLBOX_JOINTS)
            or any(joint in pair for pair in REFERENCE_PAIRS.get(test.reference, ()))
        )

    return tuple(f.name for f in CATALOG if any(reads(t) for t in f.tests))
