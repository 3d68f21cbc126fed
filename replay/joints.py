"""The standard joint set and where each joint sits on an ASF skeleton, written once, as data.

A joint is the end point of an ASF bone (the root joint is the root position). The mapping is the
Bonn toolbox's name map (reference facts, section c) keyed by bone *name*, so it holds for any bone
order. The clavicle joints coincide with the neck (end of ``thorax``), as in the toolbox; the
wrist is the end of the ``lwrist``/``rwrist`` bone, not of the radius. The thumbs are not in the
toolbox vocabulary; they come last so that :data:`TOOLBOX_JOINTS` is a prefix.
"""

from __future__ import annotations

from types import MappingProxyType

JOINT_BONE_END = MappingProxyType(
    {
        "root": "root",
        "lhip": "lhipjoint",
        "lknee": "lfemur",
        "lankle": "ltibia",
        "ltoes": "ltoes",
        "rhip": "rhipjoint",
        "rknee": "rfemur",
        "rankle": "rtibia",
        "rtoes": "rtoes",
        "belly": "lowerback",
        "chest": "upperback",
        "neck": "thorax",
        "head": "upperneck",
        "headtop": "head",
        "lclavicle": "thorax",
        "lshoulder": "lclavicle",
        "lelbow": "lhumerus",
        "lwrist": "lwrist",
        "lfingers": "lfingers",
        "rclavicle": "thorax",
        "rshoulder": "rclavicle",
        "relbow": "rhumerus",
        "rwrist": "rwrist",
        "rfingers": "rfingers",
        "lthumb": "lthumb",
        "rthumb": "rthumb",
    }
)

JOINT_NAMES: tuple[str, ...] = tuple(JOINT_BONE_END)
"""All standard joints, in the order of every joint-position array (26 joints)."""

TOOLBOX_JOINTS: tuple[str, ...] = JOINT_NAMES[:24]
"""The 24 names of the toolbox's name map (22 distinct points): what ``YBodyMin``/``YBodyMax`` range over."""
