"""ASF/AMC written as BVH (:mod:`replay.convert`, ``mocapd convert``): read back, every node lies where
the AMC puts it within 1e-9 of the recording's extent, on every shared recording; the Euler angles
give back their rotation in every order; the converted file is recognised as the AMC is."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from hypothesis import example, given
from hypothesis import strategies as st

from daemon.recordings import native_rate, read_recording
from replay import KinematicModel
from replay.bvh import BvhKinematics, parse_bvh, read_bvh, write_bvh
from replay.convert import asf_nodes, euler_angles, euler_order, motion_to_bvh
from replay.kinematics import euler_quaternion, joint_positions, quaternion_matrix
from replay.rigs import bvh_standard_joints
from tests.helpers import CMU_AMC, CMU_ASF, HDM_AMC, HDM_ASF, assert_ok, mocapd, pair_id, recording_pairs

ORDERS = ("XYZ", "XZY", "YXZ", "YZX", "ZXY", "ZYX")


def round_trip_error(asf: Path, amc: Path) -> float:
    """The largest distance between an AMC's node and the same node of its BVH read back, as a
    share of the largest coordinate's size."""
    motion = read_recording(asf, amc)
    back = parse_bvh(write_bvh(motion_to_bvh(motion, native_rate(motion))), "written")
    nodes = asf_nodes(back.hierarchy, motion.skeleton.node_names)
    got = BvhKinematics(back.hierarchy).positions(back.channels)[:, nodes]
    want = KinematicModel(motion.skeleton).positions(motion.channels, "cm")
    return float(np.abs(got - want).max() / np.abs(want).max())


@pytest.mark.parametrize(("asf", "amc"), [(CMU_ASF, CMU_AMC), (HDM_ASF, HDM_AMC)], ids=["cmu", "hdm05"])
def test_a_recording_read_back_from_bvh_has_its_positions_and_its_standard_joints(
    asf: Path, amc: Path
) -> None:
    assert round_trip_error(asf, amc) < 1e-9
    motion = read_recording(asf, amc)
    joints, plan = bvh_standard_joints(parse_bvh(write_bvh(motion_to_bvh(motion, 120.0)), "written"))
    want = joint_positions(motion)
    assert (plan.rig, plan.derived) == ("asf", ())
    assert np.abs(joints - want).max() < 1e-9 * np.abs(want).max()


@pytest.mark.slow
def test_every_shared_recording_round_trips_through_bvh() -> None:
    pairs = recording_pairs()
    assert len(pairs) > 200
    worst = {pair_id(p): round_trip_error(*p) for p in pairs}
    assert max(worst.values()) < 1e-9, max(worst, key=worst.__getitem__)


@given(
    st.lists(st.floats(-1, 1, allow_nan=False), min_size=4, max_size=4).filter(
        lambda q: sum(x * x for x in q) > 1e-3
    ),
    st.sampled_from(ORDERS),
)
@example([1.0, 0.0, 1.0, 0.0], "XYZ")  # 90° about Y: XYZ's middle angle at its pole
@example([1.0, 1e-9, 1.0, 0.0], "ZYX")  # next to it
def test_euler_angles_give_back_their_rotation_in_every_order(q: list[float], order: str) -> None:
    """``R = R_a(a) @ R_b(b) @ R_c(c)``: rebuilt with the elementary rotations applied last axis first
    (``euler_quaternion`` takes application order), the matrix comes back."""
    unit = np.array(q) / np.linalg.norm(q)
    matrix = quaternion_matrix(unit)
    angles = euler_angles(matrix[None], order)[0]
    rebuilt = quaternion_matrix(euler_quaternion(angles[::-1], order[::-1]))
    assert np.abs(rebuilt - matrix).max() < 1e-12
    assert abs(angles[1]) <= np.pi / 2


def test_the_written_order_keeps_a_joint_turned_about_its_middle_axis_away_from_gimbal_lock() -> None:
    """Rotations near 90° about Y: the middle angle of XYZ (or ZYX) sits near its pole, where the
    angles lose digits; the order chosen has its middle angle far from it."""
    rng = np.random.default_rng(3)
    small = rng.normal(scale=0.05, size=(200, 3))
    turned = np.array([quaternion_matrix(euler_quaternion([0.0, np.pi / 2, 0.0], "XYZ"))] * 200)
    matrices = turned @ np.array([quaternion_matrix(euler_quaternion(a, "XYZ")) for a in small])
    assert np.abs(euler_angles(matrices, "XYZ")[:, 1]).max() > np.radians(75)
    order = euler_order(matrices)
    assert np.abs(euler_angles(matrices, order)[:, 1]).max() < np.radians(30)


def test_mocapd_convert_writes_a_bvh_that_detect_recognises_as_the_amc(tmp_path: Path) -> None:
    out = tmp_path / "02_05.bvh.gz"
    asf, amc = next(p for p in recording_pairs() if pair_id(p) == "02_05")
    assert_ok(mocapd("convert", "--asf", asf, "--amc", amc, "--out", out))
    assert read_bvh(out).rate == 120.0
    from_bvh = mocapd("detect", "--bvh", out, "--json")
    from_amc = mocapd("detect", "--asf", asf, "--amc", amc, "--json")
    assert_ok(from_bvh)

    def found(output: str) -> list[dict[str, object]]:  # ids differ: each run is a session of its own
        return [{k: v for k, v in json.loads(line).items() if k != "id"} for line in output.splitlines()]

    assert found(from_bvh.stdout) == found(from_amc.stdout) and found(from_amc.stdout)
