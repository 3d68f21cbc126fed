"""Rig maps (:mod:`replay.rigs`): a BVH rig's joints onto the 26 standard joints, the map chosen by
the joint names, the joints a rig lacks derived in the body's proportions, and a rig no map fits
refused naming what is missing. Real data: Bandai Namco Research's motion dataset 2 (``bandai2``,
CC BY-NC-ND 4.0, read unmodified)."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest
import yaml

from daemon.features import features, sample_count
from daemon.library import default_library_path, load_library
from daemon.recognizer import detect_positions
from daemon.recordings import RateError, read_bvh_features, read_examples, read_training_manifest
from daemon.types import FloatArray
from replay import JOINT_NAMES
from replay.bvh import BvhHierarchy, BvhJoint, BvhKinematics, BvhMotion, parse_bvh, read_bvh
from replay.errors import MocapFormatError
from replay.rigs import (
    BUILT_IN,
    FINGERS_PER_FOREARM,
    HEAD_TOP_PER_THIGH,
    RigMap,
    bvh_standard_joints,
    parse_rig_map,
    rig_plan,
    up_axis,
)
from tests.helpers import assert_one_error_line, mocapd

BANDAI = Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "mocap" / "bandai2"
AT = {j: k for k, j in enumerate(JOINT_NAMES)}


def test_a_bandai2_rig_maps_its_joints_and_derives_the_head_top_and_the_fingers() -> None:
    motion = read_bvh(BANDAI / "dataset-2_wave-right-hand_normal_001.bvh.gz")
    joints, plan = bvh_standard_joints(motion)
    assert plan.rig == "upperarm"
    assert set(plan.derived) == {"headtop", "lfingers", "rfingers", "lthumb", "rthumb"}
    nodes = BvhKinematics(motion.hierarchy).positions(motion.channels)
    names = motion.hierarchy.names
    for joint, node in (("root", "Hips"), ("rhip", "UpperLeg_R"), ("lelbow", "LowerArm_L"), ("neck", "Neck")):
        assert np.array_equal(joints[:, AT[joint]], nodes[:, names.index(node)]), joint
    assert np.array_equal(joints[:, AT["lclavicle"]], joints[:, AT["neck"]])  # as the toolbox has it

    def length(a: str, b: str) -> FloatArray:
        d: FloatArray = np.linalg.norm(joints[:, AT[a]] - joints[:, AT[b]], axis=1)
        return d

    thigh = 0.5 * (length("lhip", "lknee") + length("rhip", "rknee"))
    np.testing.assert_allclose(length("head", "headtop"), HEAD_TOP_PER_THIGH * thigh)
    np.testing.assert_allclose(length("rwrist", "rfingers"), FINGERS_PER_FOREARM * length("relbow", "rwrist"))
    # the fingers continue the forearm; the head top is above the head, standing
    forearm = joints[:, AT["rwrist"]] - joints[:, AT["relbow"]]
    hand = joints[:, AT["rfingers"]] - joints[:, AT["rwrist"]]
    np.testing.assert_allclose(np.cross(forearm, hand), 0, atol=1e-9)
    assert (joints[:, AT["headtop"], 1] > joints[:, AT["head"], 1] + 10).all()
    assert np.array_equal(joints[:, AT["rthumb"]], joints[:, AT["rfingers"]])


def test_the_39_features_and_the_recogniser_run_on_a_bandai2_take_at_its_30_hz() -> None:
    motion = read_bvh(BANDAI / "dataset-2_walk_normal_001.bvh.gz")
    joints, _ = bvh_standard_joints(motion)
    assert np.isfinite(joints).all()
    assert features(joints, JOINT_NAMES, motion.rate).shape == (len(joints), 39)
    library = load_library(default_library_path())
    for d in detect_positions(joints, np.arange(len(joints)), library, motion.rate):
        assert 0 <= d.start_frame <= d.end_frame < len(joints)


def _rig(names: list[str]) -> BvhMotion:
    """A one-frame rig of ``names``, each joint a child of the one before, 10 cm apart."""
    joints = [
        BvhJoint(n, k - 1, (0.0, 10.0 if k else 0.0, 0.0), ("Zrotation",), k + 1) for k, n in enumerate(names)
    ]
    hierarchy = BvhHierarchy("rig.bvh", tuple(joints))
    return BvhMotion("rig.bvh", hierarchy, 1 / 60, np.zeros((1, len(names))))


MIXAMO = [
    f"mixamorig:{n}"
    for n in [
        "Hips",
        "Spine",
        "Spine1",
        "Spine2",
        "Neck",
        "Head",
        "HeadTop_End",
        "LeftShoulder",
        "LeftArm",
        "LeftForeArm",
        "LeftHand",
        "RightShoulder",
        "RightArm",
        "RightForeArm",
        "RightHand",
        "LeftUpLeg",
        "LeftLeg",
        "LeftFoot",
        "LeftToeBase",
        "LeftToe_End",
        "RightUpLeg",
        "RightLeg",
        "RightFoot",
        "RightToeBase",
        "RightToe_End",
    ]
]


def test_mixamo_names_without_fingers_map_by_the_leftupleg_scheme() -> None:
    joints, plan = bvh_standard_joints(_rig(MIXAMO))
    assert plan.rig == "leftupleg"
    assert set(plan.derived) == {"lfingers", "rfingers", "lthumb", "rthumb"}  # HeadTop_End is there
    assert plan.nodes[AT["chest"]] == MIXAMO.index("mixamorig:Spine2")
    assert plan.nodes[AT["ltoes"]] == MIXAMO.index("mixamorig:LeftToe_End")
    assert np.isfinite(joints).all()


def test_a_rig_no_map_fits_is_refused_naming_what_the_nearest_map_misses() -> None:
    names = [n for n in MIXAMO if "Leg" not in n]
    with pytest.raises(MocapFormatError) as caught:
        bvh_standard_joints(_rig(names))
    message = str(caught.value)
    assert message.startswith("rig.bvh: no rig map fits its joints: the nearest (leftupleg) finds no ")
    assert "lhip" in message and "rknee" in message and "\n" not in message


def test_an_end_site_at_its_joint_is_no_point_of_its_own() -> None:
    names = ["Hips", "UpperLeg_L", "Toes_L", "Toes_L/end"]
    plan = rig_plan(names, [True, True, True, False], "x", maps=[_only_toes()])
    assert plan.nodes[AT["ltoes"]] == 2
    plan = rig_plan(names, [True, True, True, True], "x", maps=[_only_toes()])
    assert plan.nodes[AT["ltoes"]] == 3


def _only_toes() -> RigMap:
    """A map that finds every joint at the hips but the left toes."""
    return RigMap("toes", {j: ("Hips",) for j in JOINT_NAMES} | {"ltoes": ("Toes_L/end", "Toes_L")})


@pytest.mark.parametrize(
    ("frame_time", "rate"), [("0.0333333", 30.0), ("0.008333", 120.0), ("0.033367", 1 / 0.033367)]
)
def test_the_rate_is_the_whole_number_the_frame_time_was_rounded_from(frame_time: str, rate: float) -> None:
    hierarchy = "HIERARCHY\nROOT a\n{\nOFFSET 0 0 0\nCHANNELS 1 Xposition\n}\n"
    text = f"{hierarchy}MOTION\nFrames: 1\nFrame Time: {frame_time}\n0\n"
    assert parse_bvh(text.encode()).rate == rate


def _bvh_manifest(where: Path, rows: list[tuple[str, str, str]]) -> Path:
    """A training manifest of bandai2 takes: (class, take name, actor) rows."""
    lines = ["class,bvh,actor", *(f"{c},{BANDAI / f'dataset-2_{t}.bvh.gz'},{actor}" for c, t, actor in rows)]
    path = where / "train.csv"
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")
    return path


def test_a_training_manifest_takes_a_bvh_column(tmp_path: Path) -> None:
    manifest = tmp_path / "train.csv"
    take = BANDAI / "dataset-2_walk_normal_001.bvh.gz"
    manifest.write_text(
        f"class,bvh,actor,start_frame,end_frame\nwalk,{take},normal,31,90\n", encoding="utf-8"
    )
    (row,) = read_training_manifest(manifest)
    assert (row.name, row.actor, row.row.bvh, row.start_frame) == ("walk", "normal", take, 31)
    examples = read_examples(manifest, rate=30.0)
    ((clip, matrix),) = examples["walk"]
    whole = read_bvh_features(take)
    assert np.array_equal(matrix, whole.matrix[30:90]) and clip.frames == 60
    with pytest.raises(RateError, match=r"walk_normal_001\.bvh\.gz: 60 Hz is above the native 30 Hz"):
        read_bvh_features(take, 60.0)
    assert read_bvh_features(take, 25.0).matrix.shape == (sample_count(len(whole.matrix), 6, 5), 39)


@pytest.mark.slow
def test_learn_from_bvh_takes_and_detect_in_one(tmp_path: Path) -> None:
    """``mocapd learn`` on a manifest of bandai2 takes (two actions, two styles as the actors) and
    ``mocapd detect --bvh`` with what it learned, both through a user's rig map; ``mocapd index``
    refuses such a manifest in one line."""
    rows = [
        (action, f"{action}_{style}_00{k}", style)
        for action in ("wave-right-hand", "raise-up-left-hand")
        for style in ("normal", "active")
        for k in (1, 2)
    ]
    manifest = _bvh_manifest(tmp_path, rows)
    rig = tmp_path / "studio.yaml"  # learned and detected through the same user's map
    rig.write_text(STUDIO, encoding="utf-8")
    learned = mocapd(
        "learn",
        "--manifest",
        manifest,
        "--out",
        tmp_path / "lib",
        "--no-calibrate",
        "--keyframes",
        "0",
        "--rig",
        rig,
    )
    assert learned.returncode == 0, learned.stderr
    found = mocapd(
        "detect",
        "--bvh",
        BANDAI / "dataset-2_wave-right-hand_normal_003.bvh.gz",
        "--library",
        tmp_path / "lib",
        "--rig",
        rig,
        "--json",
    )
    assert found.returncode == 0, found.stderr
    assert {json.loads(line)["class"] for line in found.stdout.splitlines()} == {"wave-right-hand"}
    built = mocapd("index", "build", "--manifest", manifest, "--out", tmp_path / "index", "--rig", rig)
    assert built.returncode == 0 and "documents:  8" in built.stdout, built.stderr  # the same manifest


STUDIO = """name: studio-a
joints:
  root: Hips
  lhip: UpperLeg_L
  lknee: LowerLeg_L
  lankle: Foot_L
  ltoes: [Toes_L/end, Toes_L]
  rhip: UpperLeg_R
  rknee: LowerLeg_R
  rankle: Foot_R
  rtoes: Toes_R
  belly: Spine
  chest: Chest
  neck: Neck
  head: Head
  lclavicle: Shoulder_L
  rclavicle: Shoulder_R
  lshoulder: UpperArm_L
  rshoulder: UpperArm_R
  lelbow: LowerArm_L
  relbow: LowerArm_R
  lwrist: Hand_L
  rwrist: Hand_R
"""


def test_a_users_rig_map_is_taken_before_the_built_in_ones(tmp_path: Path) -> None:
    """``--rig FILE``: a map in YAML (here bandai2's rig with the clavicle joints on its shoulder
    joints, where the built-in map puts them on the neck), the joints it does not name derived."""
    motion = read_bvh(BANDAI / "dataset-2_wave-right-hand_normal_001.bvh.gz")
    rig = parse_rig_map(yaml.safe_load(STUDIO), "studio.yaml")
    joints, plan = bvh_standard_joints(motion, (rig, *BUILT_IN))
    assert plan.rig == "studio-a" and set(plan.derived) == {
        "headtop",
        "lfingers",
        "rfingers",
        "lthumb",
        "rthumb",
    }
    shoulder = BvhKinematics(motion.hierarchy).positions(motion.channels)[
        :, motion.hierarchy.names.index("Shoulder_L")
    ]
    assert np.array_equal(joints[:, AT["lclavicle"]], shoulder)
    path = tmp_path / "studio.yaml"
    path.write_text(STUDIO, encoding="utf-8")
    take = BANDAI / "dataset-2_wave-right-hand_normal_001.bvh.gz"
    result = mocapd("detect", "--bvh", take, "--rig", path, "--json")
    assert (result.returncode, result.stderr) == (0, "")
    config = tmp_path / "config.yaml"  # the same map from the configuration (replay.rig_maps)
    config.write_text(f"replay:\n  rig_maps: [{path}]\n", encoding="utf-8")
    for how in (["--rig", str(path)], []):
        where: list[str | Path] = [] if how else ["--config", config]
        info = mocapd(*where, "info", "--bvh", take, *how, "--json")
        assert info.returncode == 0 and json.loads(info.stdout)["rig_map"] == "studio-a", info.stderr
    assert json.loads(mocapd("info", "--bvh", take, "--json").stdout)["rig_map"] == "upperarm"


@pytest.mark.parametrize(
    ("text", "says"),
    [
        ("[Hips]", "the rig map: must be a mapping"),
        ("joints: {root: Hips}\ncolour: red", "colour: unknown field"),
        ("joints: {pelvis: Hips}", "joints.pelvis: not a standard joint"),
        ("joints: {root: []}", "joints.root: must be a node name or a non-empty list"),
        ("joints: {root: [Hips, 3]}", "joints.root: must be a node name or a non-empty list"),
        ("name: ''\njoints: {root: Hips}", "name: must be a non-empty string"),
        ("joints: {}", "joints: must map standard joints"),
    ],
)
def test_a_bad_rig_map_is_one_line_naming_its_field(tmp_path: Path, text: str, says: str) -> None:
    with pytest.raises(MocapFormatError) as caught:
        parse_rig_map(yaml.safe_load(text), "rig.yaml")
    assert str(caught.value) == f"rig.yaml: {says}" or str(caught.value).startswith(f"rig.yaml: {says}")
    path = tmp_path / "rig.yaml"
    path.write_text(text, encoding="utf-8")
    line = assert_one_error_line(
        mocapd("detect", "--bvh", BANDAI / "dataset-2_walk_normal_001.bvh.gz", "--rig", path)
    )
    assert says in line and str(path) in line


def test_a_rig_that_stands_along_z_is_turned_to_stand_along_y() -> None:
    """bandai2's take under a root that turns it a quarter about X (as a Z-up tool exports it): its
    standard joints come out as the take's own (``up_axis`` from its frames, not its rest pose)."""
    motion = read_bvh(BANDAI / "dataset-2_walk_normal_001.bvh.gz")
    world = BvhJoint("World", -1, (0.0, 0.0, 0.0), ("Xrotation",), 1)
    shifted = tuple(
        dataclasses.replace(j, parent=j.parent + 1 if j.parent >= 0 else 0) for j in motion.hierarchy.joints
    )
    turned = BvhMotion(
        motion.source,
        BvhHierarchy(motion.source, (world, *shifted)),
        motion.frame_time,
        np.hstack([np.full((len(motion.channels), 1), 90.0), motion.channels]),
    )
    upright, _ = bvh_standard_joints(motion)
    lying, _ = bvh_standard_joints(turned)
    assert up_axis(upright) == "y"
    np.testing.assert_allclose(lying, upright, atol=1e-9 * np.abs(upright).max())
