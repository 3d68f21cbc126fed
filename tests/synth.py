"""Random synthetic ASF/AMC files for the property tests (hypothesis strategies).

A :class:`SkeletonSpec` / :class:`MotionSpec` holds what was generated (the ground truth); the
``data`` of :class:`AsfFile` / :class:`AmcFile` is the file text written from it, with random but
meaning-preserving formatting (comments, blank lines, indentation, CRLF or LF, section, field and
line order). Numbers are written so that ``float(token)`` is the intended value; the specs keep
the tokens and their ``float`` values.
"""

from __future__ import annotations

import dataclasses
import math
import random
import string
from dataclasses import dataclass

import numpy as np
from hypothesis import strategies as st

from daemon.features import SET_SLICES
from daemon.keyframes import Keyframe, KeyframeQuery
from daemon.library import ClassTemplate
from daemon.library import given as given_tau
from daemon.templates import MotionTemplate
from daemon.types import FEATURE_SETS, N_FEATURES, FeatureSet

ROT = ("rx", "ry", "rz")
ROOT_CHANNELS = ("tx", "ty", "tz", "rx", "ry", "rz")
NAME_FIRST = string.ascii_letters
NAME_REST = string.ascii_letters + string.digits + "_"
# Words the ASF reader treats specially in :hierarchy (it skips lines starting with begin/end).
RESERVED = frozenset({"root", "begin", "end"})
# Cosmetic choices and bulk values come from a seeded random.Random: one hypothesis draw instead of
# thousands (st.randoms() would draw from the test data on every call and overrun its buffer).
seeds = st.integers(0, 2**32 - 1)


# --------------------------------------------------------------------------------------------- ASF


@dataclass(frozen=True)
class BoneSpec:
    """One generated bone. ``parent`` is a node index (0 = root, k = k-th bone of :bonedata)."""

    name: str
    parent: int
    direction: tuple[float, float, float]  # as written, not normalised
    length: float
    axis: tuple[float, float, float]  # as written, in the ASF angle unit
    axis_order: str  # upper case, as the reader reports it
    dofs: tuple[str, ...]
    limits: tuple[tuple[float, float], ...]  # as written, ASF angle unit; () when not written
    bone_id: int | None


@dataclass(frozen=True)
class SkeletonSpec:
    name: str
    mass_unit: float
    length_unit: float
    angle_unit: str  # "deg" or "rad": what the reader must report
    root_order: tuple[str, ...]  # lower case
    root_axis: str  # upper case
    root_position: tuple[float, float, float]
    root_orientation: tuple[float, float, float]  # ASF angle unit
    bones: tuple[BoneSpec, ...]  # in :bonedata order

    @property
    def to_rad(self) -> float:
        return math.pi / 180 if self.angle_unit == "deg" else 1.0

    @property
    def parents(self) -> tuple[int, ...]:
        return (-1, *(b.parent for b in self.bones))

    @property
    def channel_names(self) -> tuple[str, ...]:
        names = [f"root.{c}" for c in self.root_order]
        for b in self.bones:
            names.extend(f"{b.name}.{d}" for d in b.dofs)
        return tuple(names)


@dataclass(frozen=True)
class AsfFile:
    spec: SkeletonSpec
    data: bytes


def _finish(rnd: random.Random, lines: list[str], *, comments: bool, mode: str) -> bytes:
    """Join logical lines, sprinkling comments/blank lines/indentation and choosing line ends."""
    out: list[str] = []
    for line in lines:
        if comments and rnd.random() < 0.12:
            out.append(rnd.choice(["# a comment line", "#", "   # indented comment (x y) :root", "", "  \t"]))
        indent = rnd.choice(["", "", " ", "  ", "\t"]) if comments else ""
        tail = rnd.choice(["", "", "", " ", "\t", "  # trailing comment"]) if comments else ""
        out.append(indent + line + tail)
    if mode == "lf":
        ends = ["\n"] * len(out)
    elif mode == "crlf":
        ends = ["\r\n"] * len(out)
    else:
        ends = [rnd.choice(["\n", "\r\n"]) for _ in out]
    text = "".join(line + end for line, end in zip(out, ends, strict=True))
    if rnd.random() < 0.2:  # no final line end
        text = text.rstrip("\r\n")
    return text.encode("ascii")


def _case(rnd: random.Random, word: str) -> str:
    return rnd.choice([word.upper(), word.lower(), word])


def _fmt(x: float) -> str:
    return repr(float(x))


@st.composite
def bone_names(draw: st.DrawFn) -> str:
    first = draw(st.sampled_from(NAME_FIRST))
    rest = draw(st.text(alphabet=NAME_REST, max_size=7))
    name = first + rest
    if name.lower() in RESERVED:
        name += "_"
    return name


@st.composite
def skeletons(draw: st.DrawFn, max_bones: int = 12) -> AsfFile:
    """A random skeleton and an ASF text for it."""
    n = draw(st.integers(1, max_bones))
    names = draw(st.lists(bone_names(), min_size=n, max_size=n, unique=True))
    angle_unit = draw(st.sampled_from(["deg", "rad"]))
    ang = 720.0 if angle_unit == "deg" else 4 * math.pi

    # A tree in topological order (parent -1 = root), then a random :bonedata order.
    shape = draw(st.sampled_from(["random", "chain", "star", "mixed"]))
    topo_parent: list[int] = []
    for t in range(n):
        if t == 0 or shape == "star":
            topo_parent.append(-1)
        elif shape == "chain" or (shape == "mixed" and draw(st.booleans())):
            topo_parent.append(t - 1)
        else:
            topo_parent.append(draw(st.integers(-1, t - 1)))
    perm = draw(st.permutations(range(n)))  # perm[i] = topological index of the i-th listed bone
    node_of_topo = {t: i + 1 for i, t in enumerate(perm)}

    bones: list[BoneSpec] = []
    for i in range(n):
        t = perm[i]
        parent = 0 if topo_parent[t] == -1 else node_of_topo[topo_parent[t]]
        zero_length = draw(st.integers(0, 9)) == 0
        comp = st.floats(-1.0, 1.0, allow_subnormal=False)
        direction: tuple[float, float, float]
        if zero_length:
            direction = draw(st.one_of(st.just((0.0, 0.0, 0.0)), st.tuples(comp, comp, comp)))
            length = 0.0
        else:
            direction = draw(st.tuples(comp, comp, comp))
            if math.hypot(*direction) < 0.05:
                direction = (direction[0], direction[1], 1.0)
            scale = draw(st.sampled_from([1.0, 1.0, 1.0, 0.25, 3.0]))
            direction = (direction[0] * scale, direction[1] * scale, direction[2] * scale)
            length = draw(st.floats(0.1, 10.0))
        a = st.floats(-ang / 2, ang / 2)
        axis = draw(st.one_of(st.tuples(a, a, a), st.just((0.0, 0.0, 0.0))))
        axis_order = "".join(draw(st.permutations("XYZ")))
        k = draw(st.integers(0, 3))
        dofs = tuple(draw(st.permutations(ROT))[:k])
        limits: tuple[tuple[float, float], ...] = ()
        write_limits = draw(st.booleans())
        if dofs and write_limits:
            lim = st.one_of(st.floats(-ang, ang), st.sampled_from([math.inf, -math.inf, 0.0]))
            limits = tuple(draw(st.tuples(lim, lim)) for _ in dofs)
        bone_id = draw(st.one_of(st.none(), st.integers(0, 99)))
        bones.append(BoneSpec(names[i], parent, direction, length, axis, axis_order, dofs, limits, bone_id))

    order_all = draw(st.permutations(ROOT_CHANNELS))
    keep = 6 if draw(st.integers(0, 4)) > 0 else draw(st.integers(1, 6))
    pos = st.floats(-100.0, 100.0)
    rot = st.floats(-ang, ang)
    spec = SkeletonSpec(
        name=draw(bone_names()),
        mass_unit=draw(st.sampled_from([1.0, 0.5, 2.0])),
        length_unit=draw(st.one_of(st.sampled_from([0.45, 1.0, 2.5, 1 / 0.45]), st.floats(0.01, 100.0))),
        angle_unit=angle_unit,
        root_order=tuple(order_all[:keep]),
        root_axis="".join(draw(st.permutations("XYZ"))),
        root_position=draw(st.tuples(pos, pos, pos)),
        root_orientation=draw(st.tuples(rot, rot, rot)),
        bones=tuple(bones),
    )
    rnd = random.Random(draw(seeds))
    mode = draw(st.sampled_from(["lf", "crlf", "mixed"]))
    return AsfFile(spec, render_asf(spec, rnd, mode=mode, comments=draw(st.booleans())))


def render_asf(spec: SkeletonSpec, rnd: random.Random, *, mode: str = "lf", comments: bool = True) -> bytes:
    """ASF text for ``spec`` with random, meaning-preserving formatting."""
    sections: list[list[str]] = []

    units = [f"mass {_fmt(spec.mass_unit)}", f"length {_fmt(spec.length_unit)}"]
    if spec.angle_unit == "rad" or rnd.random() < 0.7:
        units.append(f"angle {_case(rnd, spec.angle_unit)}")
    rnd.shuffle(units)
    if spec.angle_unit == "rad" or spec.length_unit != 1.0 or spec.mass_unit != 1.0 or rnd.random() < 0.8:
        sections.append([":units", *units])
    if rnd.random() < 0.3:
        sections.append([":documentation", "Synthetic skeleton for property tests", "more notes (1 2)"])

    root = [
        "order " + " ".join(_case(rnd, c) for c in spec.root_order),
        f"position {' '.join(_fmt(v) for v in spec.root_position)}",
        f"orientation {' '.join(_fmt(v) for v in spec.root_orientation)}",
    ]
    if spec.root_axis != "XYZ" or rnd.random() < 0.7:
        root.append(f"axis {_case(rnd, spec.root_axis)}")
    rnd.shuffle(root)
    sections.append([":root", *root])

    bonedata = [":bonedata"]
    for b in spec.bones:
        fields: list[list[str]] = [
            [f"name {b.name}"],
            [f"direction {' '.join(_fmt(v) for v in b.direction)}"],
            [f"length {_fmt(b.length)}"],
        ]
        if b.bone_id is not None:
            fields.append([f"id {b.bone_id}"])
        if any(b.axis) or b.axis_order != "XYZ" or rnd.random() < 0.8:
            fields.append([f"axis {' '.join(_fmt(v) for v in b.axis)} {_case(rnd, b.axis_order)}"])
        if b.dofs or rnd.random() < 0.2:
            fields.append(["dof " + " ".join(b.dofs) if b.dofs else "dof"])
        if b.limits:
            pairs = [rnd.choice(["({} {})", "( {} {} )", "({}  {})"]).format(*map(_fmt, p)) for p in b.limits]
            groups: list[list[str]] = [[pairs[0]]]
            for p in pairs[1:]:
                if rnd.random() < 0.7:
                    groups.append([p])
                else:
                    groups[-1].append(p)
            fields.append(["limits " + " ".join(groups[0]), *(" ".join(g) for g in groups[1:])])
        if rnd.random() < 0.2:
            fields.append(["bodymass 2.5"])
        rnd.shuffle(fields)
        bonedata.append("begin")
        for f in fields:
            bonedata.extend(f)
        bonedata.append("end")
    sections.append(bonedata)

    names = ("root", *(b.name for b in spec.bones))
    children: dict[int, list[str]] = {}
    for k, b in enumerate(spec.bones, 1):
        children.setdefault(b.parent, []).append(names[k])
    hier_lines: list[str] = []
    for parent, kids in children.items():
        rnd.shuffle(kids)
        chunk: list[str] = []
        for kid in kids:
            chunk.append(kid)
            if rnd.random() < 0.25:
                hier_lines.append(" ".join([names[parent], *chunk]))
                chunk = []
        if chunk:
            hier_lines.append(" ".join([names[parent], *chunk]))
    rnd.shuffle(hier_lines)
    sections.append([":hierarchy", "begin", *hier_lines, "end"])

    rnd.shuffle(sections)
    lines = [":version 1.10", f":name {spec.name}"]
    for s in sections:
        lines.extend(s)
    return _finish(rnd, lines, comments=comments, mode=mode)


# --------------------------------------------------------------------------------------------- AMC

_SPECIAL = (
    0.0,
    -0.0,
    5e-324,
    -2.2250738585072014e-308,
    1e-300,
    1.7976931348623157e308,
    -1e308,
    123456789012345.0,
    0.1,
    1 / 3,
    -2.5,
    1e16,
)


def value_token(rnd: random.Random, value: float) -> str:
    """A text for ``value`` that ``float()`` reads back (usually exactly ``value``)."""
    choice = rnd.random()
    if choice < 0.6:
        return repr(value)
    if choice < 0.7:
        return f"{value:.17g}"
    if choice < 0.75:
        return f"{value:.17e}"
    if choice < 0.8:
        return f"{value:.25e}"  # more digits than a double holds: needs correct rounding
    if choice < 0.9 and value.is_integer() and abs(value) < 1e15:
        return str(int(value))
    text = repr(value)
    if choice < 0.95 and not text.startswith("-"):
        return "+" + text
    if text.startswith("0."):
        return text[1:]
    if text.startswith("-0."):
        return "-" + text[2:]
    return f"{value:.6f}"  # rounded: float() of the token differs from value, which is fine


def random_value(rnd: random.Random, kind: str, unit: str, wide: bool) -> float:
    """A random channel value: ``kind`` is "t" (translation) or "r" (rotation, in ``unit``)."""
    if wide:
        if rnd.random() < 0.08:
            return rnd.choice(_SPECIAL)
        if rnd.random() < 0.2:  # anything down to subnormals and up to 1e308
            return rnd.uniform(-1.0, 1.0) * math.pow(10.0, rnd.uniform(-330.0, 308.0))
        return rnd.uniform(-1.0, 1.0) * math.pow(10.0, rnd.uniform(-12.0, 12.0))
    if kind == "t":
        return rnd.choice([rnd.uniform(-50.0, 50.0), rnd.uniform(-1e4, 1e4), 0.0])
    span = 720.0 if unit == "deg" else 4 * math.pi
    return rnd.choice([rnd.uniform(-span, span), rnd.uniform(-span / 4, span / 4), 0.0, -0.0])


@dataclass(frozen=True)
class FrameSpec:
    number: int
    tokens: dict[str, tuple[str, ...]]  # node name -> value tokens ("root" in root order)
    # byte offsets in the plain file: start of the frame-number token, start/end of the frame's last token
    start: int
    last_token: tuple[int, int]
    last_line: str  # node name of the frame's last line


@dataclass(frozen=True)
class AmcFile:
    skeleton: SkeletonSpec
    angle_unit: str  # effective unit of the AMC angles
    header_unit: str | None  # ":DEGREES", ":RADIANS" or None
    fully_specified: bool
    frame_rate: float | None
    frames: tuple[FrameSpec, ...]
    text: bytes  # the plain AMC text
    gzipped: bool
    regular: bool  # every frame has the first frame's line layout, no comments or blank lines in the body

    def channel_row(self, tokens: dict[str, tuple[str, ...]]) -> list[float]:
        """Expected channels of one frame: :attr:`Skeleton.channel_names` layout, angles in radians
        (``value * (pi / 180)`` for degrees)."""
        scale = math.pi / 180 if self.angle_unit == "deg" else 1.0
        row: list[float] = []
        for c, tok in zip(self.skeleton.root_order, tokens["root"], strict=True):
            row.append(float(tok) * scale if c in ROT else float(tok))
        for b in self.skeleton.bones:
            if b.dofs:
                row.extend(float(tok) * scale for tok in tokens[b.name])
        return row

    def channel_matrix(self) -> list[list[float]]:
        """Expected channels of every frame."""
        return [self.channel_row(f.tokens) for f in self.frames]


@st.composite
def motions(
    draw: st.DrawFn,
    skel: SkeletonSpec,
    *,
    wide: bool = False,
    body_noise: bool = True,
    allow_gzip: bool = True,
    dofless_lines: bool = False,
    max_frames: int = 40,
    first_frames: st.SearchStrategy[int] | None = None,
) -> AmcFile:
    """A random AMC file for ``skel``.

    ``wide``: values over the whole double range (else moderate values suitable for kinematics);
    ``body_noise``: comments, blank lines and per-frame shuffled bone order may occur;
    ``dofless_lines``: frames may also list bones without dofs (a name alone on a line);
    ``first_frames``: the number of the first frame (default: 1 or any up to a million).
    """
    rnd = random.Random(draw(seeds))
    n_frames = draw(st.integers(1, max_frames))
    first = draw(first_frames if first_frames is not None else st.one_of(st.just(1), st.integers(0, 10**6)))
    zeros = "0" * rnd.choice([0, 0, 0, 0, 0, 0, 1, 3])  # zero-padded frame numbers ("007")
    header_unit = draw(st.sampled_from([":DEGREES", ":RADIANS", None]))
    angle_unit = {":DEGREES": "deg", ":RADIANS": "rad", None: skel.angle_unit}[header_unit]
    fully = draw(st.booleans())
    frame_rate = draw(st.one_of(st.none(), st.sampled_from([120.0, 60.0, 29.97])))
    shuffle_mode = draw(st.sampled_from(["fixed", "fixed", "per-frame"] if body_noise else ["fixed"]))
    noise = body_noise and draw(st.booleans())
    mode = draw(st.sampled_from(["lf", "crlf", "mixed"]))
    gz = allow_gzip and draw(st.booleans())

    header: list[str] = []
    if fully:
        header.append(":FULLY-SPECIFIED")
    if header_unit is not None:
        header.append(rnd.choice([header_unit, header_unit.lower()]))
    if frame_rate is not None:
        header.append(f":SAMPLES-PER-SECOND {frame_rate!r}")
    rnd.shuffle(header)
    if draw(st.booleans()):
        header.insert(0, "#!OML:ASF F:\\data\\skel.asf")
    if rnd.random() < 0.3:
        header.insert(rnd.randrange(len(header) + 1), "# a comment in the header")
    # read_amc's vectorised path starts at the line after the last header line with content, so a
    # comment right before the first frame sends a file to the streaming reader (slower, same values)
    comment_last = bool(header) and header[-1].startswith("#")

    with_dofs = ["root", *(b.name for b in skel.bones if b.dofs)]
    dofless = [b.name for b in skel.bones if not b.dofs] if dofless_lines else []
    kinds = {"root": tuple("r" if c in ROT else "t" for c in skel.root_order)}
    kinds |= {b.name: tuple("r" for _ in b.dofs) for b in skel.bones}
    order = [*with_dofs, *dofless]
    rnd.shuffle(order)

    def end() -> str:
        if mode == "lf":
            return "\n"
        if mode == "crlf":
            return "\r\n"
        return rnd.choice(["\n", "\r\n"])

    out = bytearray()
    for line in header:
        out += (line + end()).encode("ascii")
    frames: list[FrameSpec] = []
    regular = not noise and shuffle_mode == "fixed" and not dofless and not comment_last
    for i in range(n_frames):
        if shuffle_mode == "per-frame":
            rnd.shuffle(order)
        start = len(out)
        out += (zeros + str(first + i) + end()).encode("ascii")
        tokens: dict[str, tuple[str, ...]] = {}
        last = (0, 0)
        last_line = ""
        for name in order:
            if noise and rnd.random() < 0.1:
                out += rnd.choice(["# comment", "", "   ", "\t# c"]).encode("ascii") + end().encode("ascii")
            toks = tuple(value_token(rnd, random_value(rnd, k, angle_unit, wide)) for k in kinds[name])
            tokens[name] = toks
            sep = rnd.choice([" ", " ", "  ", "\t"])
            line = (name + sep + sep.join(toks)) if toks else name
            begin_last = len(out) + len(line) - (len(toks[-1]) if toks else len(name))
            out += line.encode("ascii")
            last = (begin_last, len(out))
            last_line = name
            if rnd.random() < 0.1:
                out += rnd.choice([b" ", b"\t", b"  "])
            if noise and rnd.random() < 0.1:
                out += b" # trailing comment"
            out += end().encode("ascii")
        frames.append(FrameSpec(first + i, tokens, start, last, last_line))
    if rnd.random() < 0.2:
        out = bytearray(bytes(out).rstrip(b"\r\n"))
    elif rnd.random() < 0.2:
        # Blank lines at the end: as many newlines as a frame has lines send the file to read_amc's
        # streaming fallback (slower, same values), so the file no longer counts as regular.
        out += b"\n  \n"
        regular = False
    return AmcFile(
        skeleton=skel,
        angle_unit=angle_unit,
        header_unit=header_unit,
        fully_specified=fully,
        frame_rate=frame_rate,
        frames=tuple(frames),
        text=bytes(out),
        gzipped=gz,
        regular=regular,
    )


@st.composite
def cases(
    draw: st.DrawFn,
    *,
    wide: bool = False,
    body_noise: bool = True,
    allow_gzip: bool = True,
    dofless_lines: bool = False,
    max_bones: int = 12,
    max_frames: int = 40,
    first_frames: st.SearchStrategy[int] | None = None,
) -> tuple[AsfFile, AmcFile]:
    """A random skeleton with a random motion for it."""
    asf = draw(skeletons(max_bones=max_bones))
    amc = draw(
        motions(
            asf.spec,
            wide=wide,
            body_noise=body_noise,
            allow_gzip=allow_gzip,
            dofless_lines=dofless_lines,
            max_frames=max_frames,
            first_frames=first_frames,
        )
    )
    return asf, amc


# ------------------------------------------------------------------------ keyframe code streams

LOW_BITS = 3
"""Random code streams vary only the first bits of each feature set, so that random keyframes match."""


def stream_codes(codes: dict[FeatureSet, list[int]]) -> list[int]:
    """Per frame, the three sets' codes side by side in one 39-bit code."""
    n = len(codes["lower"])
    return [sum(codes[fs][t] << SET_SLICES[fs].start for fs in FEATURE_SETS) for t in range(n)]


@st.composite
def streams(draw: st.DrawFn, shortest: int = 1, longest: int = 60) -> dict[FeatureSet, list[int]]:
    n = draw(st.integers(shortest, longest))
    out: dict[FeatureSet, list[int]] = {}
    for fs in FEATURE_SETS:
        codes: list[int] = []
        while len(codes) < n:  # runs, so that list entries are longer than one frame
            codes += [draw(st.integers(0, (1 << LOW_BITS) - 1))] * draw(st.integers(1, 6))
        out[fs] = codes[:n]
    return out


@st.composite
def queries(
    draw: st.DrawFn,
    sets: tuple[FeatureSet, ...] = FEATURE_SETS,
    stiffnesses: tuple[float, ...] = (0.0, 0.0, 0.3, 0.5, 0.8, 1.0),
    tolerant: bool = False,
) -> KeyframeQuery:
    """1-4 random keyframes over ``sets`` (σ = 0 for an unbounded gap, equal positions for a zero
    gap), fixing only the low bits random streams vary (and 0 above them). ``tolerant``: each
    keyframe may miss 0-3 of its fixed entries, and may fix one high bit to 1, which random streams
    always miss."""
    k = draw(st.integers(1, 4))
    keyframes = []
    position = 0
    for j in range(k):
        fs = draw(st.sampled_from(sets))
        width = SET_SLICES[fs].stop - SET_SLICES[fs].start
        low = [draw(st.sampled_from([0.0, 1.0, 0.5, 0.5])) for _ in range(LOW_BITS)]
        high = [draw(st.sampled_from([0.0, 0.5])) for _ in range(width - LOW_BITS)]
        stiffness = None if j == k - 1 else draw(st.sampled_from(stiffnesses))
        mismatches = 0
        if tolerant:
            if draw(st.booleans()):
                high[draw(st.integers(0, width - LOW_BITS - 1))] = 1.0
            fixed = sum(v != 0.5 for v in low + high)
            mismatches = min(draw(st.sampled_from([0, 1, 1, 2, 3])), max(0, fixed - 1))
        keyframes.append(Keyframe(fs, tuple(low + high), position, stiffness, mismatches))
        position += draw(st.sampled_from([0, 0, 1, 2, 4, 7]))  # equal positions: zero gaps
    return KeyframeQuery("random", tuple(keyframes), 30.0)


def random_class(
    name: str, query: KeyframeQuery, rng: np.random.Generator, tau: float, columns: int | None = None
) -> ClassTemplate:
    """A class of a random template of 2 to 6 columns (``columns`` if given) over the features the
    random :func:`streams` vary, with ``query`` as its keyframes and ``tau``."""
    m = int(rng.integers(2, 7)) if columns is None else columns
    values = np.full((N_FEATURES, m), 0.5)
    for fs in FEATURE_SETS:  # random streams vary the first LOW_BITS features of each set
        low = SET_SLICES[fs].start
        values[low : low + LOW_BITS] = rng.choice([0.0, 0.5, 1.0], size=(LOW_BITS, m))
        values[low + LOW_BITS : SET_SLICES[fs].stop] = rng.choice(
            [0.0, 0.5], size=(SET_SLICES[fs].stop - low - LOW_BITS, m), p=[0.2, 0.8]
        )
    template = MotionTemplate(values, rng.uniform(0.6, 2.2, size=m))
    return ClassTemplate(
        name,
        template,
        template,
        template,
        dataclasses.replace(query, name=name),
        tau,
        0.1,
        "toolbox",
        1,
        (),
        given_tau(tau),
    )
