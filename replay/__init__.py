"""Recorded motion: ASF skeletons, AMC motions, forward kinematics to joint positions."""

from replay.amc import AmcFrame, AmcHeader, AmcStream, Motion, iter_amc, read_amc
from replay.asf import Bone, Root, Skeleton, parse_asf, read_asf
from replay.errors import MocapFormatError
from replay.joints import JOINT_BONE_END, JOINT_NAMES, TOOLBOX_JOINTS
from replay.kinematics import KinematicModel

__all__ = [
    "JOINT_BONE_END",
    "JOINT_NAMES",
    "TOOLBOX_JOINTS",
    "AmcFrame",
    "AmcHeader",
    "AmcStream",
    "Bone",
    "KinematicModel",
    "MocapFormatError",
    "Motion",
    "Root",
    "Skeleton",
    "iter_amc",
    "parse_asf",
    "read_amc",
    "read_asf",
]
