"""Biovision hierarchy files (BVH): a reader, its forward kinematics, and a writer.

A BVH file is a HIERARCHY of joints (``ROOT``, ``JOINT``, ``End Site``), each with an ``OFFSET``
from its parent and, but for End Sites, ``CHANNELS``: positions and Euler rotations in any order and
any count; then MOTION: ``Frames:``, ``Frame Time:`` and one row of channel values a frame, the
joints' channels in the order the hierarchy lists them. Tabs or spaces, CRLF or LF, braces on lines
of their own or not, plain or gzip (:mod:`replay.textio`).

Conventions (those of the exporters: MotionBuilder, Motive, Blender, the Bandai Namco and CMU BVH
conversions), for column vectors, angles in degrees:

* a joint's rotation is the product of its rotation channels in the order listed,
  ``CHANNELS 3 Zrotation Xrotation Yrotation`` being ``R = Rz @ Rx @ Ry`` (Y applied first);
* a joint's translation from its parent is its ``OFFSET``, with each position channel it has
  replacing that component (the offset is the rest pose; exporters that put 6 channels on every
  joint write the offset there, and a root's position channels are where it is);
* ``G_j = G_parent @ R_j`` and ``P_j = P_parent + G_parent @ t_j``; an End Site is a point at its
  offset from its joint: ``P = P_joint + G_joint @ offset``.

Every malformed file is a :class:`~replay.errors.MocapFormatError` naming the file and line.
"""

from __future__ import annotations

import math
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from daemon.types import FloatArray
from replay._kinematics import BvhFrameKinematics
from replay.errors import MocapFormatError
from replay.kinematics import quaternion_multiply, quaternion_rotate
from replay.textio import read_bytes

POSITIONS = ("Xposition", "Yposition", "Zposition")
ROTATIONS = ("Xrotation", "Yrotation", "Zrotation")
CHANNELS = POSITIONS + ROTATIONS
MOST_FRAMES = 10_000_000
"""The most frames a file may say it has (a count beyond is taken for a damaged header)."""


@dataclass(frozen=True)
class BvhJoint:
    """One node of the hierarchy: its ``name`` (an End Site's is its joint's name with ``/end``),
    its ``parent``'s index (-1: a root), its ``offset`` from the parent, its ``channels`` (none for
    an End Site) and the ``line`` it is declared on."""

    name: str
    parent: int
    offset: tuple[float, float, float]
    channels: tuple[str, ...]
    line: int
    end_site: bool = False


@dataclass(frozen=True)
class BvhHierarchy:
    """The joints of a BVH file, parents before children, as the file declares them."""

    source: str
    joints: tuple[BvhJoint, ...]

    @property
    def channel_names(self) -> tuple[str, ...]:
        """``joint.channel`` for each column of a MOTION row."""
        return tuple(f"{j.name}.{c}" for j in self.joints for c in j.channels)

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(j.name for j in self.joints)


@dataclass(frozen=True)
class BvhMotion:
    """A BVH file: its ``hierarchy``, ``frame_time`` in seconds and ``channels`` shape ``(N, C)``
    (float64, as written: positions in the file's units, angles in degrees)."""

    source: str
    hierarchy: BvhHierarchy
    frame_time: float
    channels: FloatArray

    @property
    def rate(self) -> float:
        """Frames a second: ``1 / frame_time``, or the whole number within 0.05 % of it (files write
        the frame time to 6 or 7 digits: ``0.0333333`` is 30 Hz, ``0.008333`` 120 Hz)."""
        exact = 1.0 / self.frame_time
        whole = round(exact)
        return float(whole) if whole and abs(exact - whole) <= 5e-4 * exact else exact


@dataclass(frozen=True)
class _Token:
    word: str
    line: int


def read_bvh(path: str | Path) -> BvhMotion:
    """The BVH file at ``path`` (plain or gzip); :class:`MocapFormatError` naming the file and line
    if it is malformed."""
    return parse_bvh(read_bytes(path), str(path))


def parse_bvh(data: bytes, source: str = "<bvh>") -> BvhMotion:
    """A BVH file's bytes (module docstring)."""
    lines = _lines(data.decode("latin-1"))
    hierarchy, motion_at = _hierarchy_of(lines, source)
    if motion_at is None:
        raise MocapFormatError(source, len(lines), "no MOTION section after the hierarchy")
    frames, frame_time, first = _motion_header(lines, motion_at + 1, source)
    width = len(hierarchy.channel_names)
    return BvhMotion(source, hierarchy, frame_time, _rows(lines, first, frames, width, source))


def _words(line: str) -> list[str]:
    """A hierarchy line's words, braces apart from names (``ROOT Hips{`` is three words)."""
    return line.replace("{", " { ").replace("}", " } ").split()


class _Tokens:
    def __init__(self, tokens: list[_Token], source: str, end_line: int) -> None:
        self._tokens = tokens
        self._at = 0
        self.source = source
        self.end_line = end_line

    def peek(self) -> _Token | None:
        return self._tokens[self._at] if self._at < len(self._tokens) else None

    def next(self, what: str) -> _Token:
        token = self.peek()
        if token is None:
            raise MocapFormatError(
                self.source, self.end_line, f"the hierarchy ends where {what} was expected"
            )
        self._at += 1
        return token

    def expect(self, word: str) -> _Token:
        token = self.next(repr(word))
        if token.word != word:
            raise self.error(token, f"expected {word!r}, found {token.word!r}")
        return token

    def error(self, token: _Token, reason: str) -> MocapFormatError:
        return MocapFormatError(self.source, token.line, reason)


def _parse_hierarchy(tokens: list[_Token], source: str, end_line: int) -> BvhHierarchy:
    t = _Tokens(tokens, source, end_line)
    if not tokens:
        raise MocapFormatError(source, 1, "a BVH file begins with HIERARCHY, found nothing")
    first = t.next("HIERARCHY")
    if first.word.upper() != "HIERARCHY":
        raise t.error(first, f"a BVH file begins with HIERARCHY, found {first.word!r}")
    joints: list[BvhJoint] = []
    lines: dict[str, int] = {}
    while (token := t.peek()) is not None:
        t.next("ROOT")
        if token.word != "ROOT":
            raise t.error(token, f"expected ROOT, found {token.word!r}")
        _parse_joint(t, -1, joints, lines, token)
    if not joints:
        raise MocapFormatError(source, end_line, "the hierarchy has no ROOT")
    return BvhHierarchy(source, tuple(joints))


def _parse_joint(
    t: _Tokens, parent: int, joints: list[BvhJoint], lines: dict[str, int], kind: _Token
) -> None:
    """A ROOT or JOINT block from its name on (``kind`` the keyword), its children after it."""
    name = t.next("a joint name")
    if name.word in ("{", "}"):
        raise t.error(name, f"{kind.word} without a name")
    if name.word in lines:
        raise t.error(name, f"joint {name.word!r} defined twice (first on line {lines[name.word]})")
    lines[name.word] = name.line
    t.expect("{")
    offset = _offset(t)
    channels_at = t.next("CHANNELS")
    if channels_at.word != "CHANNELS":
        raise t.error(channels_at, f"expected CHANNELS of joint {name.word!r}, found {channels_at.word!r}")
    channels = _channels(t, channels_at, name.word)
    me = len(joints)
    joints.append(BvhJoint(name.word, parent, offset, channels, name.line))
    while True:
        token = t.next("JOINT, End Site or '}'")
        if token.word == "}":
            return
        if token.word == "JOINT":
            _parse_joint(t, me, joints, lines, token)
        elif token.word == "End":
            site = t.next("Site")
            if site.word != "Site":
                raise t.error(site, f"expected 'End Site', found 'End {site.word}'")
            t.expect("{")
            joints.append(BvhJoint(f"{name.word}/end", me, _offset(t), (), token.line, end_site=True))
            t.expect("}")
        else:
            raise t.error(
                token, f"expected JOINT, End Site or '}}' in joint {name.word!r}, found {token.word!r}"
            )


def _offset(t: _Tokens) -> tuple[float, float, float]:
    at = t.expect("OFFSET")
    values = []
    for _ in range(3):
        token = t.next("an OFFSET value")
        if token.line != at.line:
            raise t.error(at, "OFFSET needs 3 numbers on its line")
        values.append(_number(token.word, t.source, token.line, "OFFSET"))
    nxt = t.peek()
    if nxt is not None and nxt.line == at.line:
        raise t.error(nxt, f"OFFSET has more than 3 numbers: {nxt.word!r}")
    return values[0], values[1], values[2]


def _channels(t: _Tokens, at: _Token, joint: str) -> tuple[str, ...]:
    count = t.next("the channel count")
    if not (count.word.isascii() and count.word.isdigit()) or not 0 < int(count.word) <= len(CHANNELS):
        raise t.error(count, f"CHANNELS of {joint!r}: a count of 1 to 6 expected, found {count.word!r}")
    names: list[str] = []
    for _ in range(int(count.word)):
        token = t.peek()
        if token is None or token.line != at.line:
            raise t.error(at, f"CHANNELS of {joint!r} says {count.word} but names {len(names)}")
        t.next("a channel")
        if token.word not in CHANNELS:
            raise t.error(
                token, f"unknown channel {token.word!r} of {joint!r} (one of {', '.join(CHANNELS)})"
            )
        if token.word in names:
            raise t.error(token, f"channel {token.word!r} of {joint!r} listed twice")
        names.append(token.word)
    extra = t.peek()
    if extra is not None and extra.line == at.line:
        raise t.error(extra, f"CHANNELS of {joint!r} says {count.word} but names more: {extra.word!r}")
    return tuple(names)


def _number(word: str, source: str, line: int, what: str) -> float:
    try:
        value = float(word)
    except ValueError:
        raise MocapFormatError(source, line, f"{what}: not a number: {word!r}") from None
    if not math.isfinite(value):
        raise MocapFormatError(source, line, f"{what}: not a finite number: {word!r}")
    return value


def _motion_header(lines: Sequence[str], start: int, source: str) -> tuple[int, float, int]:
    """``Frames:`` and ``Frame Time:`` from line index ``start`` on (blank lines between passed
    over): the frame count, the frame time and the index of the first row."""
    k = _next_filled(lines, start)
    if k is None or not lines[k].strip().startswith("Frames:"):
        raise MocapFormatError(
            source, min(k if k is not None else start, len(lines) - 1) + 1, "expected 'Frames: N'"
        )
    word = lines[k].strip()[len("Frames:") :].strip()
    if not (word.isascii() and word.isdigit()) or int(word) > MOST_FRAMES:
        raise MocapFormatError(
            source, k + 1, f"Frames: a count of 0 to {MOST_FRAMES} expected, found {word!r}"
        )
    frames = int(word)
    j = _next_filled(lines, k + 1)
    if j is None or not lines[j].strip().startswith("Frame Time:"):
        raise MocapFormatError(
            source, min(j if j is not None else k + 1, len(lines) - 1) + 1, "expected 'Frame Time: SECONDS'"
        )
    seconds = _number(lines[j].strip()[len("Frame Time:") :].strip(), source, j + 1, "Frame Time")
    if seconds <= 0:
        raise MocapFormatError(source, j + 1, f"Frame Time must be above 0 seconds, found {seconds!r}")
    return frames, seconds, j + 1


def _next_filled(lines: Sequence[str], start: int) -> int | None:
    return next((k for k in range(start, len(lines)) if lines[k].strip()), None)


def _rows(lines: Sequence[str], first: int, frames: int, width: int, source: str) -> FloatArray:
    """The ``frames`` rows of ``width`` numbers from line index ``first`` on: vectorised when every
    row is whole, else line by line to name the bad one."""
    filled = [k for k in range(first, len(lines)) if lines[k].strip()]
    body = filled[:frames]
    try:
        values = np.array(" ".join(lines[k] for k in body).split(), dtype=np.float64)
    except ValueError:
        values = None
    if values is not None and values.size == len(body) * width and np.isfinite(values).all():
        rows = values.reshape(len(body), width)
    else:
        for k in body:
            words = lines[k].split()
            if len(words) != width:
                raise MocapFormatError(
                    source, k + 1, f"a frame has {len(words)} values, the hierarchy's channels are {width}"
                )
            for word in words:
                _number(word, source, k + 1, "a channel value")
        raise AssertionError("unreachable: a row failed to parse but none is bad")  # pragma: no cover
    if len(body) < frames:
        at = (filled[-1] + 1) if filled else first
        raise MocapFormatError(
            source, at, f"Frames says {frames} but the file ends after {len(body)} (truncated?)"
        )
    if len(filled) > frames:
        raise MocapFormatError(source, filled[frames] + 1, f"more frame rows than Frames says ({frames})")
    return rows


class BvhKinematics:
    """Forward kinematics of one hierarchy (module docstring): channel rows in the layout of
    :attr:`BvhHierarchy.channel_names` to node positions. Every operation is elementwise over
    frames, so one frame alone (:meth:`positions_frame`) gives bit for bit its values in a batch."""

    def __init__(self, hierarchy: BvhHierarchy) -> None:
        self.hierarchy = hierarchy
        self.width = len(hierarchy.channel_names)
        self._plan: list[tuple[int, list[tuple[int, int]], list[tuple[int, int]]]] = []
        column = 0
        for k, joint in enumerate(hierarchy.joints):
            positions, rotations = [], []
            for channel in joint.channels:
                if channel in POSITIONS:
                    positions.append((POSITIONS.index(channel), column))
                else:
                    rotations.append((ROTATIONS.index(channel), column))
                column += 1
            self._plan.append((k, positions, rotations))
        self._offsets = np.array([j.offset for j in hierarchy.joints], dtype=np.float64).reshape(-1, 3)
        rotating = [r for _, _, rotations in self._plan for r in rotations]
        moving = [p for _, positions, _ in self._plan for p in positions]
        self._frame = BvhFrameKinematics(
            [j.parent for j in hierarchy.joints],
            rotating,
            np.cumsum([0] + [len(r) for _, _, r in self._plan]),
            moving,
            np.cumsum([0] + [len(p) for _, p, _ in self._plan]),
            self._offsets,
        )

    def _rows(self, channels: FloatArray) -> FloatArray:
        rows = np.asarray(channels, dtype=np.float64)
        if rows.ndim != 2 or rows.shape[1] != self.width:
            raise ValueError(f"channels must have shape (N, {self.width}), got {rows.shape}")
        return rows

    def _local(
        self, rows: FloatArray, rotations: list[tuple[int, int]], cos: FloatArray, sin: FloatArray
    ) -> FloatArray:
        """A joint's rotation relative to its parent from its rotation channels: shape ``(4, N)``."""
        local = np.zeros((4, rows.shape[0]))
        local[0] = 1.0
        for axis, column in rotations:  # R = R(c1) @ R(c2) @ ...: each next one on the right
            e = np.zeros((4, rows.shape[0]))
            e[0] = cos[column]
            e[1 + axis] = sin[column]
            local = quaternion_multiply(local, e)
        return local

    def positions(self, channels: FloatArray) -> FloatArray:
        """Every node's position (End Sites included): ``channels`` shape ``(N, C)`` gives shape
        ``(N, nodes, 3)``, in the file's units."""
        rows = self._rows(channels)
        n = rows.shape[0]
        half = np.radians(rows.T) * 0.5  # (C, N)
        cos, sin = np.cos(half), np.sin(half)
        joints = self.hierarchy.joints
        rot = np.zeros((4, len(joints), n))
        pos = np.zeros((3, len(joints), n))
        for k, positions, rotations in self._plan:
            joint = joints[k]
            local = self._local(rows, rotations, cos, sin)
            t = np.repeat(self._offsets[k][:, None], n, axis=1)
            for axis, column in positions:
                t[axis] = rows[:, column]
            if joint.parent < 0:
                rot[:, k] = local
                pos[:, k] = t
            else:
                parent = joint.parent
                rot[:, k] = quaternion_multiply(rot[:, parent], local)
                pos[:, k] = pos[:, parent] + quaternion_rotate(rot[:, parent], t)
        return np.ascontiguousarray(pos.transpose(2, 1, 0))

    def local_rotations(self, channels: FloatArray) -> FloatArray:
        """Every node's rotation relative to its parent as a unit quaternion ``(w, x, y, z)`` (the
        identity for an End Site or a joint without rotation channels): ``channels`` shape ``(N,
        C)`` gives shape ``(N, nodes, 4)``."""
        rows = self._rows(channels)
        half = np.radians(rows.T) * 0.5
        cos, sin = np.cos(half), np.sin(half)
        local = np.stack([self._local(rows, rotations, cos, sin) for _, _, rotations in self._plan])
        return np.ascontiguousarray(local.transpose(2, 0, 1))

    def positions_frame(self, channels: FloatArray) -> FloatArray:
        """:meth:`positions` of one frame: shape ``(C,)`` gives shape ``(nodes, 3)``, bit for bit
        the batch's values: the half angles' cosines and sines by numpy (the batch's functions),
        the rest in compiled code (:class:`replay._kinematics.BvhFrameKinematics`)."""
        row = np.ascontiguousarray(channels, dtype=np.float64)
        if row.shape != (self.width,):
            raise ValueError(f"channels must have shape ({self.width},), got {row.shape}")
        half = np.radians(row) * 0.5
        out: FloatArray = np.empty((len(self.hierarchy.joints), 3))
        self._frame.positions(row, np.cos(half), np.sin(half), out)
        return out


def hierarchy_text(hierarchy: BvhHierarchy) -> str:
    """The ``HIERARCHY`` section of ``hierarchy`` (tabs, LF, numbers in full: ``repr``), what a
    skeleton message carries on the wire (:func:`parse_bvh_hierarchy` reads it back)."""
    out: list[str] = ["HIERARCHY"]
    joints = hierarchy.joints
    children: dict[int, list[int]] = {}
    for k, j in enumerate(joints):
        children.setdefault(j.parent, []).append(k)

    def offset(values: tuple[float, float, float]) -> str:
        return " ".join(repr(float(v)) for v in values)

    def block(k: int, depth: int) -> Iterator[str]:
        j, pad = joints[k], "\t" * depth
        if j.end_site:
            yield from (f"{pad}End Site", f"{pad}{{", f"{pad}\tOFFSET {offset(j.offset)}", f"{pad}}}")
            return
        yield f"{pad}{'ROOT' if j.parent < 0 else 'JOINT'} {j.name}"
        yield f"{pad}{{"
        yield f"{pad}\tOFFSET {offset(j.offset)}"
        yield f"{pad}\tCHANNELS {len(j.channels)} {' '.join(j.channels)}"
        for c in children.get(k, []):
            yield from block(c, depth + 1)
        yield f"{pad}}}"

    for root in children.get(-1, []):
        out.extend(block(root, 0))
    return "\n".join(out) + "\n"


def parse_bvh_hierarchy(text: str, source: str = "<bvh>") -> BvhHierarchy:
    """The hierarchy of a BVH text: its ``HIERARCHY`` section (a ``MOTION`` section after it, if
    any, is not read). :class:`MocapFormatError` naming ``source`` and the line if malformed."""
    return _hierarchy_of(_lines(text), source)[0]


def _lines(text: str) -> list[str]:
    return text.replace("\r\n", "\n").replace("\r", "\n").split("\n")


def _hierarchy_of(lines: list[str], source: str) -> tuple[BvhHierarchy, int | None]:
    """The hierarchy of a BVH file's ``lines`` and the index of its ``MOTION`` line (None: none)."""
    motion_at = next((k for k, line in enumerate(lines) if line.strip().upper() == "MOTION"), None)
    tokens = [_Token(word, k + 1) for k, line in enumerate(lines[:motion_at]) for word in _words(line)]
    return _parse_hierarchy(tokens, source, len(lines) if motion_at is None else motion_at + 1), motion_at


def write_bvh(motion: BvhMotion) -> bytes:
    """``motion`` as a BVH file (tabs, LF; numbers written in full, ``repr``, so that reading it back
    gives the same values)."""
    out = [hierarchy_text(motion.hierarchy).rstrip("\n")]
    out += ["MOTION", f"Frames: {len(motion.channels)}", f"Frame Time: {motion.frame_time!r}"]
    out += [" ".join(repr(float(v)) for v in row) for row in motion.channels]
    return ("\n".join(out) + "\n").encode("ascii")
