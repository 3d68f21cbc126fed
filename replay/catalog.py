"""Finding the skeleton of a recording in the CMU and HDM05 directory conventions."""

from __future__ import annotations

import re
from collections.abc import Mapping
from pathlib import Path

CMU_SUBSTITUTES = {"14": "13"}
"""CMU subject 14 has no ASF here; subject 13's has the same topology (joint angles exact, bone
lengths subject 13's)."""

_HDM05 = re.compile(r"HDM_([A-Za-z]+)_")


def find_skeleton(amc: Path, data_root: Path, substitutes: Mapping[str, str] | None = None) -> Path:
    """The ASF for ``amc`` under ``data_root``: ``hdm05/asf/HDM_<actor>.asf`` for an HDM05 clip
    ``HDM_<actor>_...``, else the CMU subject's ``cmu/<subject>/<subject>.asf`` for ``<subject>_<trial>``.
    ``substitutes`` maps a subject without an ASF to one with the same topology (CMU 14 -> 13)."""
    match = _HDM05.match(amc.name)
    if match:
        return data_root / "hdm05" / "asf" / f"HDM_{match.group(1)}.asf"
    subject = amc.name.split("_")[0]
    subject = (substitutes or {}).get(subject, subject)
    return data_root / "cmu" / subject / f"{subject}.asf"


def recordings(data_root: Path, substitutes: Mapping[str, str] | None = None) -> list[tuple[Path, Path]]:
    """Every ``(asf, amc)`` pair under ``data_root`` (``*.amc`` and ``*.amc.gz``), sorted by AMC path."""
    amcs = sorted([*data_root.rglob("*.amc.gz"), *data_root.rglob("*.amc")])
    return [(find_skeleton(a, data_root, substitutes), a) for a in amcs]
