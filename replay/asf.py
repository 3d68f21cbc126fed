"""Acclaim skeleton files (ASF): parsing into a frozen :class:`Skeleton`.

Conventions (Acclaim; the Bonn toolbox, reference facts section c):

* node 0 is the root, node ``k`` (k >= 1) is the k-th bone of ``:bonedata`` in file order; the
  ``id`` field is kept but not used for positions in arrays;
* angles are stored in radians whatever ``:units angle`` says;
* lengths are stored as written (ASF units); ``Skeleton.length_unit`` is the ``:units length``
  value the toolbox divides by before multiplying by 2.54 to get centimetres;
* an axis-order string lists the elementary rotations in the order they are applied, so ``XYZ``
  means ``Rz @ Ry @ Rx`` (x first) for column vectors.
"""

from __future__ import annotations

import functools
import math
import re
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path

from replay.errors import MocapFormatError
from replay.textio import read_text_lines

ROTATION_DOFS = ("rx", "ry", "rz")
TRANSLATION_DOFS = ("tx", "ty", "tz")
_AXIS_ORDER = re.compile(r"^[XYZ]{1,3}$")
_LIMIT = re.compile(r"\(\s*([^\s()]+)\s+([^\s()]+)\s*\)")


@dataclass(frozen=True)
class Root:
    """The ``:root`` section.

    ``order`` lists the AMC root channels in file order (lower case, e.g. ``("tx", ..., "rz")``);
    the rotation channels among them are applied in that order. ``axis_order`` is the order of the
    ``orientation`` rotation; ``position`` is in ASF units and ``orientation`` in radians.
    """

    order: tuple[str, ...]
    axis_order: str
    position: tuple[float, float, float]
    orientation: tuple[float, float, float]


@dataclass(frozen=True)
class Bone:
    """One ``begin ... end`` block of ``:bonedata``.

    ``direction`` is the unit bone direction in the global frame of the rest pose, ``length`` in ASF
    units, ``axis`` the local frame's Euler angles in radians applied in ``axis_order``. ``dofs`` are
    the bone's AMC channels in file order (rotations ``rx``/``ry``/``rz``, applied in that order);
    ``limits`` holds one (low, high) pair per dof, angles in radians.
    """

    name: str
    bone_id: int | None
    direction: tuple[float, float, float]
    length: float
    axis: tuple[float, float, float]
    axis_order: str
    dofs: tuple[str, ...]
    limits: tuple[tuple[float, float], ...]
    line: int


@dataclass(frozen=True)
class Skeleton:
    """A parsed ASF file. ``parents[k]`` is the parent node of node ``k`` (``-1`` for the root)."""

    source: str
    name: str
    mass_unit: float
    length_unit: float
    angle_unit: str
    root: Root
    bones: tuple[Bone, ...]
    parents: tuple[int, ...]

    @property
    def node_names(self) -> tuple[str, ...]:
        """Node names: ``"root"`` then the bone names in ``:bonedata`` order."""
        return ("root", *(b.name for b in self.bones))

    def node_index(self, name: str) -> int:
        """Node index of a bone name (or ``"root"``); ``ValueError`` if the skeleton has no such bone."""
        return self.node_names.index(name)

    @functools.cached_property
    def channel_names(self) -> tuple[str, ...]:
        """Names ``"<bone>.<dof>"`` of the AMC channels: root channels first, then each bone's dofs in
        ``:bonedata`` order. This is the layout of every channel vector the AMC readers return."""
        names = [f"root.{c}" for c in self.root.order]
        for bone in self.bones:
            names.extend(f"{bone.name}.{d}" for d in bone.dofs)
        return tuple(names)

    @property
    def channel_offsets(self) -> dict[str, tuple[int, int]]:
        """For each node with channels, ``(first channel index, channel count)``."""
        out: dict[str, tuple[int, int]] = {"root": (0, len(self.root.order))}
        at = len(self.root.order)
        for bone in self.bones:
            if bone.dofs:
                out[bone.name] = (at, len(bone.dofs))
                at += len(bone.dofs)
        return out

    @property
    def angle_channels(self) -> tuple[int, ...]:
        """Indices of the rotation channels (the ones an AMC angle unit applies to)."""
        return tuple(i for i, n in enumerate(self.channel_names) if n.rsplit(".", 1)[1] in ROTATION_DOFS)


@dataclass
class _Line:
    number: int
    words: list[str]


def read_asf(path: str | Path) -> Skeleton:
    """Read an ASF file (plain or gzip, CRLF or LF)."""
    return parse_asf(read_text_lines(path), source=str(path))


def parse_asf(lines: Sequence[str], source: str = "<asf>") -> Skeleton:
    """Parse the lines of an ASF file into a :class:`Skeleton`; errors name ``source`` and the line."""
    sections: dict[str, list[_Line]] = {}
    headers: dict[str, _Line] = {}
    current: list[_Line] | None = None
    for number, raw in enumerate(lines, 1):
        text = raw.split("#", 1)[0].strip()
        if not text:
            continue
        words = text.split()
        if words[0].startswith(":"):
            key = words[0][1:].lower()
            if key in headers and key in ("root", "bonedata", "hierarchy", "units"):
                raise MocapFormatError(source, number, f"section ':{key}' appears twice")
            headers[key] = _Line(number, words[1:])
            current = sections.setdefault(key, [])
            continue
        if current is None:
            raise MocapFormatError(source, number, f"'{words[0]}' before the first ':' section")
        current.append(_Line(number, words))

    for required in ("root", "bonedata"):
        if required not in headers:
            raise MocapFormatError(source, None, f"no ':{required}' section")

    mass, length_unit, angle_unit = _parse_units(sections.get("units", []), source)
    to_rad = math.pi / 180.0 if angle_unit == "deg" else 1.0
    root = _parse_root(sections["root"], headers["root"].number, to_rad, source)
    bones = _parse_bonedata(sections["bonedata"], to_rad, source)
    if "hierarchy" not in headers:
        raise MocapFormatError(source, None, "no ':hierarchy' section")
    parents = _parse_hierarchy(sections["hierarchy"], headers["hierarchy"].number, bones, source)
    name_words = headers["name"].words if "name" in headers else []
    return Skeleton(
        source=source,
        name=" ".join(name_words),
        mass_unit=mass,
        length_unit=length_unit,
        angle_unit=angle_unit,
        root=root,
        bones=tuple(bones),
        parents=parents,
    )


def _number(word: str, line: int, what: str, source: str) -> float:
    try:
        value = float(word)
    except ValueError:
        raise MocapFormatError(source, line, f"{what}: '{word}' is not a number") from None
    if math.isnan(value):
        raise MocapFormatError(source, line, f"{what}: '{word}' is not a number")
    return value


def _finite(word: str, line: int, what: str, source: str) -> float:
    value = _number(word, line, what, source)
    if not math.isfinite(value):
        raise MocapFormatError(source, line, f"{what}: '{word}' is not finite")
    return value


def _vector3(ln: _Line, what: str, source: str) -> tuple[float, float, float]:
    if len(ln.words) != 4:
        raise MocapFormatError(source, ln.number, f"'{what}' needs 3 numbers, got {len(ln.words) - 1}")
    x, y, z = (_finite(w, ln.number, what, source) for w in ln.words[1:])
    return (x, y, z)


def _axis_order(word: str, line: int, source: str) -> str:
    order = word.upper()
    if not _AXIS_ORDER.match(order) or len(set(order)) != len(order):
        raise MocapFormatError(source, line, f"axis order '{word}' is not a permutation of X, Y, Z")
    return order


def _parse_units(lines: list[_Line], source: str) -> tuple[float, float, str]:
    mass, length, angle = 1.0, 1.0, "deg"
    for ln in lines:
        key = ln.words[0].lower()
        if len(ln.words) != 2:
            raise MocapFormatError(source, ln.number, f"':units' entry '{key}' needs one value")
        if key == "mass":
            mass = _finite(ln.words[1], ln.number, "mass unit", source)
        elif key == "length":
            length = _finite(ln.words[1], ln.number, "length unit", source)
            if length <= 0:
                raise MocapFormatError(source, ln.number, f"length unit must be positive, got {length}")
        elif key == "angle":
            angle = ln.words[1].lower()
            if angle not in ("deg", "rad"):
                raise MocapFormatError(source, ln.number, f"angle unit must be 'deg' or 'rad', got '{angle}'")
        else:
            raise MocapFormatError(source, ln.number, f"unknown ':units' entry '{key}'")
    return mass, length, angle


def _parse_root(lines: list[_Line], header_line: int, to_rad: float, source: str) -> Root:
    order: tuple[str, ...] | None = None
    axis_order = "XYZ"
    position = (0.0, 0.0, 0.0)
    orientation = (0.0, 0.0, 0.0)
    for ln in lines:
        key = ln.words[0].lower()
        if key == "order":
            order = tuple(w.lower() for w in ln.words[1:])
            bad = [w for w in order if w not in ROTATION_DOFS + TRANSLATION_DOFS]
            if bad:
                raise MocapFormatError(source, ln.number, f"root order: unknown channel '{bad[0]}'")
            if len(set(order)) != len(order):
                raise MocapFormatError(source, ln.number, "root order names a channel twice")
        elif key == "axis":
            if len(ln.words) != 2:
                raise MocapFormatError(source, ln.number, "root axis needs one axis-order word, e.g. XYZ")
            axis_order = _axis_order(ln.words[1], ln.number, source)
        elif key == "position":
            position = _vector3(ln, "root position", source)
        elif key == "orientation":
            x, y, z = _vector3(ln, "root orientation", source)
            orientation = (x * to_rad, y * to_rad, z * to_rad)
        else:
            raise MocapFormatError(source, ln.number, f"unknown ':root' entry '{key}'")
    if order is None:
        raise MocapFormatError(source, header_line, "':root' has no 'order'")
    return Root(order=order, axis_order=axis_order, position=position, orientation=orientation)


def _bone_blocks(lines: list[_Line], source: str) -> Iterator[tuple[int, list[_Line]]]:
    block: list[_Line] | None = None
    start = 0
    for ln in lines:
        key = ln.words[0].lower()
        if key == "begin":
            if block is not None:
                raise MocapFormatError(
                    source, ln.number, f"'begin' inside the bone block opened on line {start}"
                )
            block, start = [], ln.number
        elif key == "end":
            if block is None:
                raise MocapFormatError(source, ln.number, "'end' without 'begin'")
            yield start, block
            block = None
        elif block is None:
            raise MocapFormatError(source, ln.number, f"'{ln.words[0]}' outside a bone block")
        else:
            block.append(ln)
    if block is not None:
        raise MocapFormatError(source, start, "bone block never closed with 'end' (truncated file?)")


def _parse_bonedata(lines: list[_Line], to_rad: float, source: str) -> list[Bone]:
    bones: list[Bone] = []
    seen: dict[str, int] = {}
    for start, block in _bone_blocks(lines, source):
        fields: dict[str, object] = {}
        limit_lines: list[_Line] = []
        in_limits = False
        for ln in block:
            key = ln.words[0].lower()
            if in_limits and ln.words[0].startswith("("):
                limit_lines.append(ln)
                continue
            in_limits = False
            if key in fields:
                raise MocapFormatError(source, ln.number, f"bone field '{key}' given twice")
            if key == "id":
                fields[key] = (
                    int(_finite(ln.words[1], ln.number, "bone id", source)) if len(ln.words) > 1 else None
                )
            elif key == "name":
                if len(ln.words) != 2:
                    raise MocapFormatError(source, ln.number, "bone 'name' needs one word")
                fields[key] = ln.words[1]
            elif key == "direction":
                fields[key] = _vector3(ln, "bone direction", source)
            elif key == "length":
                if len(ln.words) != 2:
                    raise MocapFormatError(source, ln.number, "bone 'length' needs one number")
                value = _finite(ln.words[1], ln.number, "bone length", source)
                if value < 0:
                    raise MocapFormatError(source, ln.number, f"bone length is negative ({value})")
                fields[key] = value
            elif key == "axis":
                if len(ln.words) != 5:
                    raise MocapFormatError(
                        source, ln.number, "bone 'axis' needs 3 angles and an order, e.g. 0 0 20 XYZ"
                    )
                ax = tuple(_finite(w, ln.number, "bone axis", source) * to_rad for w in ln.words[1:4])
                fields[key] = ax
                fields["axis_order"] = _axis_order(ln.words[4], ln.number, source)
            elif key == "dof":
                dofs = tuple(w.lower() for w in ln.words[1:])
                for d in dofs:
                    if d in TRANSLATION_DOFS or d == "l":
                        raise MocapFormatError(
                            source, ln.number, f"dof '{d}': only rotation dofs (rx, ry, rz) are supported"
                        )
                    if d not in ROTATION_DOFS:
                        raise MocapFormatError(source, ln.number, f"unknown dof '{d}'")
                if len(set(dofs)) != len(dofs):
                    raise MocapFormatError(source, ln.number, "a dof is listed twice")
                fields[key] = dofs
            elif key == "limits":
                limit_lines.append(_Line(ln.number, ln.words[1:]))
                in_limits = True
                fields[key] = True
            elif key in ("bodymass", "cofmass"):
                fields[key] = True
            else:
                raise MocapFormatError(source, ln.number, f"unknown bone field '{ln.words[0]}'")
        for required in ("name", "direction", "length"):
            if required not in fields:
                raise MocapFormatError(source, start, f"bone block has no '{required}'")
        name = str(fields["name"])
        if name.lower() == "root" or name in seen:
            raise MocapFormatError(
                source, start, f"bone name '{name}' is already taken (line {seen.get(name, '?')})"
            )
        seen[name] = start
        dofs_t: tuple[str, ...] = fields.get("dof", ())  # type: ignore[assignment]
        limits = _parse_limits(limit_lines, dofs_t, to_rad, start, source)
        direction: tuple[float, float, float] = fields["direction"]  # type: ignore[assignment]
        norm = math.sqrt(sum(c * c for c in direction))
        bone_length: float = fields["length"]  # type: ignore[assignment]
        if norm == 0.0 and bone_length != 0.0:
            raise MocapFormatError(source, start, f"bone '{name}' has a zero direction vector")
        unit = (direction[0] / norm, direction[1] / norm, direction[2] / norm) if norm else (0.0, 0.0, 0.0)
        axis: tuple[float, float, float] = fields.get("axis", (0.0, 0.0, 0.0))  # type: ignore[assignment]
        bone_id = fields.get("id")
        bones.append(
            Bone(
                name=name,
                bone_id=bone_id if isinstance(bone_id, int) else None,
                direction=unit,
                length=bone_length,
                axis=axis,
                axis_order=str(fields.get("axis_order", "XYZ")),
                dofs=dofs_t,
                limits=limits,
                line=start,
            )
        )
    return bones


def _parse_limits(
    lines: list[_Line], dofs: tuple[str, ...], to_rad: float, start: int, source: str
) -> tuple[tuple[float, float], ...]:
    if not lines:
        return ()
    pairs: list[tuple[float, float]] = []
    for ln in lines:
        text = " ".join(ln.words)
        found = _LIMIT.findall(text)
        if not found or _LIMIT.sub("", text).strip():
            raise MocapFormatError(source, ln.number, f"limits must be '(low high)' pairs, got '{text}'")
        for lo, hi in found:
            pairs.append((_number(lo, ln.number, "limit", source), _number(hi, ln.number, "limit", source)))
    if len(pairs) != len(dofs):
        raise MocapFormatError(source, lines[0].number, f"{len(pairs)} limits for {len(dofs)} dofs")
    return tuple((lo * to_rad, hi * to_rad) for lo, hi in pairs)


def _parse_hierarchy(lines: list[_Line], header_line: int, bones: list[Bone], source: str) -> tuple[int, ...]:
    index = {"root": 0} | {b.name: k + 1 for k, b in enumerate(bones)}
    parents = [-2] * (len(bones) + 1)
    parents[0] = -1
    where: dict[int, int] = {}
    body = [ln for ln in lines if ln.words[0].lower() not in ("begin", "end")]
    for ln in body:
        names = ln.words
        if len(names) < 2:
            raise MocapFormatError(source, ln.number, f"hierarchy line names '{names[0]}' but no children")
        for name in names:
            if name not in index:
                raise MocapFormatError(source, ln.number, f"hierarchy names unknown bone '{name}'")
        parent = index[names[0]]
        for child_name in names[1:]:
            child = index[child_name]
            if child == 0:
                raise MocapFormatError(source, ln.number, "the root cannot be a child")
            if parents[child] != -2:
                raise MocapFormatError(
                    source, ln.number, f"bone '{child_name}' already has a parent (line {where[child]})"
                )
            parents[child] = parent
            where[child] = ln.number
    for k, b in enumerate(bones, 1):
        if parents[k] == -2:
            raise MocapFormatError(source, header_line, f"bone '{b.name}' has no parent in ':hierarchy'")
    # Every bone has one parent, so a bone the root does not reach leads up, parent by parent, into a
    # cycle. Report the cycle's edge that comes last in the file: the one that closes it.
    reached = {0}
    for k in range(1, len(parents)):
        chain = []
        node = k
        while node not in reached and node not in chain:
            chain.append(node)
            node = parents[node]
        if node in reached:
            reached.update(chain)
            continue
        cycle = chain[chain.index(node) :]
        closing = max(cycle, key=lambda c: where[c])
        raise MocapFormatError(
            source, where[closing], f"hierarchy has a cycle through bone '{bones[closing - 1].name}'"
        )
    return tuple(parents)
