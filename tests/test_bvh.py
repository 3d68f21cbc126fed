"""BVH files (:mod:`replay.bvh`): Bandai Namco Research's motion dataset 2 (``bandai2``, CC BY-NC-ND
4.0, read unmodified) read whole; forward kinematics against a slow matrix reference and one frame
against its batch, bit for bit; the writer read back; and every kind of malformed file one error
naming its line."""

from __future__ import annotations

import gzip
import math
import re
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from replay.bvh import (
    CHANNELS,
    BvhHierarchy,
    BvhJoint,
    BvhKinematics,
    BvhMotion,
    parse_bvh,
    read_bvh,
    write_bvh,
)
from replay.errors import MocapFormatError
from tests.naive import slow_bvh_positions

BANDAI = Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "mocap" / "bandai2"
TAKES = sorted(BANDAI.glob("*.bvh.gz"))
JOINTS = (
    *("joint_Root", "Hips", "Spine", "Chest", "Neck", "Head", "Head/end"),
    *("Shoulder_L", "UpperArm_L", "LowerArm_L", "Hand_L", "Hand_L/end"),
    *("Shoulder_R", "UpperArm_R", "LowerArm_R", "Hand_R", "Hand_R/end"),
    *("UpperLeg_L", "LowerLeg_L", "Foot_L", "Toes_L", "Toes_L/end"),
    *("UpperLeg_R", "LowerLeg_R", "Foot_R", "Toes_R", "Toes_R/end"),
)


def test_every_bandai2_take_reads_with_its_skeleton_at_30_frames_a_second() -> None:
    assert len(TAKES) == 210
    for path in TAKES:
        motion = read_bvh(path)
        assert motion.hierarchy.names == tuple(JOINTS), path
        assert motion.channels.shape[1] == 6 * 22 and len(motion.channels) > 0
        assert motion.rate == 30.0


def test_a_bandai2_walk_stands_on_the_floor_with_rigid_bones() -> None:
    """The conventions (module docstring) on real data: position channels replace the offset (added
    to it, the hips would float 90 cm above where the toes touch the floor), bones keep their
    lengths, and the walk goes somewhere."""
    motion = read_bvh(BANDAI / "dataset-2_walk_normal_001.bvh.gz")
    p = BvhKinematics(motion.hierarchy).positions(motion.channels)
    at = {name: k for k, name in enumerate(JOINTS)}
    toes = min(p[:, at["Toes_L"], 1].min(), p[:, at["Toes_R"], 1].min())
    assert 0 < toes < 10  # cm above the floor, Y up
    assert 70 < p[:, at["Hips"], 1].mean() < 110
    for joint in ("LowerLeg_L", "Foot_R", "LowerArm_L", "Head"):
        parent = motion.hierarchy.joints[at[joint]].parent
        length = np.linalg.norm(p[:, at[joint]] - p[:, parent], axis=1)
        assert length.max() - length.min() < 1e-3 * length.mean(), joint
    assert np.linalg.norm(p[-1, at["Hips"]] - p[0, at["Hips"]]) > 300  # cm walked


@st.composite
def motions(draw: st.DrawFn) -> BvhMotion:
    """A random hierarchy in file order (each joint a child of the joint before it or of one of
    that one's ancestors; 1-6 channels in any order; End Sites among them) and random frames."""
    n = draw(st.integers(1, 6))
    numbers = st.floats(-200, 200, allow_nan=False)
    joints: list[BvhJoint] = []
    for k in range(n):
        path = []  # the joint before and its ancestors, End Sites passed over
        at = k - 1
        while at >= 0:
            if not joints[at].end_site:
                path.append(at)
            at = joints[at].parent
        parent = draw(st.sampled_from([*path, -1])) if path else -1
        end = parent >= 0 and draw(st.booleans())
        channels = () if end else tuple(draw(st.permutations(CHANNELS))[: draw(st.integers(1, 6))])
        offset = (draw(numbers), draw(numbers), draw(numbers))
        name = f"{joints[parent].name}/end" if end else f"j{k}"
        joints.append(BvhJoint(name, parent, offset, channels, k + 1, end_site=end))
    hierarchy = BvhHierarchy("<random>", tuple(joints))
    width, frames = len(hierarchy.channel_names), draw(st.integers(1, 4))
    values = draw(st.lists(numbers, min_size=frames * width, max_size=frames * width))
    return BvhMotion("<random>", hierarchy, 1 / 30, np.array(values, dtype=np.float64).reshape(frames, width))


def _shape(
    hierarchy: BvhHierarchy,
) -> list[tuple[str, int, tuple[float, float, float], tuple[str, ...], bool]]:
    return [(j.name, j.parent, j.offset, j.channels, j.end_site) for j in hierarchy.joints]


@given(motions())
def test_forward_kinematics_is_the_matrix_definition_and_one_frame_is_the_batchs_bit_for_bit(
    motion: BvhMotion,
) -> None:
    kinematics = BvhKinematics(motion.hierarchy)
    batch = kinematics.positions(motion.channels)
    spec = [(j.parent, j.offset, j.channels) for j in motion.hierarchy.joints]
    for f, row in enumerate(motion.channels):
        assert np.array_equal(kinematics.positions_frame(row), batch[f])
        expected = np.array(slow_bvh_positions(spec, list(row)))
        np.testing.assert_allclose(batch[f], expected, rtol=1e-9, atol=1e-9 * (1 + np.abs(expected).max()))


@given(motions())
def test_what_is_written_reads_back_the_same(motion: BvhMotion) -> None:
    back = parse_bvh(write_bvh(motion), "<written>")
    assert _shape(back.hierarchy) == _shape(motion.hierarchy)
    assert np.array_equal(back.channels, motion.channels)
    assert back.frame_time == motion.frame_time


def test_a_bandai2_take_written_reads_back_the_same() -> None:
    motion = read_bvh(TAKES[0])
    back = parse_bvh(write_bvh(motion))
    assert np.array_equal(back.channels, motion.channels)
    assert _shape(back.hierarchy) == _shape(motion.hierarchy)


GOOD = """HIERARCHY
ROOT Hips
{
\tOFFSET 0 0 0
\tCHANNELS 6 Xposition Yposition Zposition Zrotation Xrotation Yrotation
\tJOINT Leg
\t{
\t\tOFFSET 0 -40 0
\t\tCHANNELS 3 Zrotation Xrotation Yrotation
\t\tEnd Site
\t\t{
\t\t\tOFFSET 0 -40 0
\t\t}
\t}
}
MOTION
Frames: 2
Frame Time: 0.0333333
0 90 0 0 0 0 10 20 30
0 91 0 0 0 0 11 21 31
"""


def test_the_good_file_reads_with_crlf_tabs_braces_beside_names_and_gzip(tmp_path: Path) -> None:
    plain = parse_bvh(GOOD.encode())
    variant = GOOD.replace("ROOT Hips\n{", "ROOT Hips {").replace("\n", "\r\n")
    path = tmp_path / "good.bvh.gz"
    path.write_bytes(gzip.compress(variant.encode()))
    read = read_bvh(path)
    assert np.array_equal(read.channels, plain.channels)
    assert read.hierarchy.channel_names == plain.hierarchy.channel_names
    assert plain.hierarchy.names == ("Hips", "Leg", "Leg/end")
    hips, leg, foot = BvhKinematics(plain.hierarchy).positions(plain.channels)[0]
    assert np.array_equal(hips, [0, 90, 0]) and np.allclose(leg, [0, 50, 0])
    assert math.isclose(np.linalg.norm(foot - leg), 40) and not np.allclose(foot, [0, 10, 0])


MALFORMED = [
    (lambda s: "", 1, "begins with HIERARCHY"),
    (lambda s: s.replace("HIERARCHY", "HIERARCHIE"), 1, "begins with HIERARCHY"),
    (lambda s: s.replace("ROOT Hips", "ROOT"), 3, "without a name"),
    (lambda s: s.replace("OFFSET 0 -40 0\n\t\tCHANNELS", "OFFSET 0 -40\n\t\tCHANNELS"), 8, "OFFSET needs 3"),
    (lambda s: s.replace("OFFSET 0 -40 0\n\t\tCHANNELS", "OFFSET 0 x 0\n\t\tCHANNELS"), 8, "not a number"),
    (lambda s: s.replace("OFFSET 0 0 0", "OFFSET 0 nan 0"), 4, "not a finite number"),
    (lambda s: s.replace("CHANNELS 3", "CHANNELS 4"), 9, "says 4 but names 3"),
    (lambda s: s.replace("CHANNELS 3", "CHANNELS 2"), 9, "names more"),
    (lambda s: s.replace("CHANNELS 3", "CHANNELS 0"), 9, "a count of 1 to 6"),
    (
        lambda s: s.replace("3 Zrotation Xrotation", "3 Zrotation Wrotation"),
        9,
        "unknown channel",
    ),
    (
        lambda s: s.replace("3 Zrotation Xrotation", "3 Zrotation Zrotation"),
        9,
        "listed twice",
    ),
    (lambda s: s.replace("JOINT Leg", "JOINT Hips"), 6, "defined twice"),
    (lambda s: s.replace("\t}\n}\nMOTION", "\t}\nMOTION"), 15, "the hierarchy ends"),
    (lambda s: s.replace("End Site", "End Sight"), 10, "expected 'End Site'"),
    (lambda s: s.replace("\t\tCHANNELS 3 Zrotation Xrotation Yrotation\n", ""), 9, "expected CHANNELS"),
    (lambda s: s.split("MOTION")[0], 16, "no MOTION section"),
    (lambda s: s.replace("Frames: 2", "Frames: two"), 17, "Frames: a count"),
    (lambda s: s.replace("Frames: 2", "Frames: \u00b2"), 17, "Frames: a count"),  # a digit, not ASCII
    (lambda s: s.replace("CHANNELS 3", "CHANNELS \u00b3"), 9, "a count of 1 to 6"),
    (lambda s: s.replace("Frames: 2", "Frame: 2"), 17, "expected 'Frames: N'"),
    (lambda s: s.replace("Frame Time: 0.0333333", "Frame Time: 0"), 18, "above 0 seconds"),
    (lambda s: s.replace("Frame Time: 0.0333333", "FrameTime: 0.03"), 18, "expected 'Frame Time"),
    (lambda s: s.replace("0 91 0 0 0 0 11 21 31", "0 91 0 0 0 0 11 21"), 20, "has 8 values"),
    (lambda s: s.replace("0 91 0 0 0 0 11 21 31", "0 91 0 0 0 0 11 21 inf"), 20, "not a finite number"),
    (lambda s: s.replace("0 91 0 0 0 0 11 21 31", "0 91 0 0 0 0 11 21 3I"), 20, "not a number"),
    (lambda s: s.replace("0 91 0 0 0 0 11 21 31\n", ""), 19, "Frames says 2 but the file ends after 1"),
    (lambda s: s + "1 2 3 4 5 6 7 8 9\n", 21, "more frame rows"),
    (lambda s: s.replace("}\nMOTION", "}\nJOINT Arm\nMOTION"), 16, "expected ROOT"),
]


@pytest.mark.parametrize(("damage", "line", "says"), MALFORMED)
def test_each_malformed_file_is_one_error_naming_its_line(damage: object, line: int, says: str) -> None:
    text = damage(GOOD)  # type: ignore[operator]
    with pytest.raises(MocapFormatError) as caught:
        parse_bvh(text.encode(), "take.bvh")
    message = str(caught.value)
    assert message.startswith(f"take.bvh:{line}: "), message
    assert says in message, message
    assert "\n" not in message and len(re.findall(r"take\.bvh", message)) == 1
