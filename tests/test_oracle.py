"""Joint positions against the original Bonn toolbox's output (../shared/reference/oracle)."""

from __future__ import annotations

import csv

import numpy as np
import pytest

from replay import JOINT_NAMES, KinematicModel, read_amc, read_asf
from tests.helpers import DATA, ORACLE, ORACLE_CLIPS


@pytest.mark.parametrize("clip", sorted(ORACLE_CLIPS))
def test_positions_match_toolbox(clip: str) -> None:
    asf, amc = ORACLE_CLIPS[clip]
    skeleton = read_asf(DATA / asf)
    motion = read_amc(DATA / amc, skeleton)
    model = KinematicModel(skeleton)
    nodes = model.positions(motion.channels, "cm")
    joints = model.joints(nodes)
    rest = model.positions_frame(np.zeros(len(skeleton.channel_names)), "cm")
    height = float(np.ptp(rest[:, 1]))
    assert 100.0 < height < 250.0

    with open(ORACLE / f"{clip}.positions.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    assert {int(r["frame"]) for r in rows} == set(range(1, 101))
    named = 0
    for row in rows:
        frame = int(row["frame"]) - 1
        want = np.array([float(row["x"]), float(row["y"]), float(row["z"])])
        # Every node, found by the ASF bone it ends, and every standard joint name on it.
        node = skeleton.node_index(row["asf_bone_end"])
        assert np.max(np.abs(nodes[frame, node] - want)) <= 1e-6 * height, row
        for name in filter(None, row["joint"].split("|")):
            assert np.max(np.abs(joints[frame, JOINT_NAMES.index(name)] - want)) <= 1e-6 * height, row
            named += 1
    assert named == 100 * 24  # all 24 toolbox names, neck|lclavicle|rclavicle counted three times
