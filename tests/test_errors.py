"""Bad input gets a clear error naming the file and the line (``replay.errors.MocapFormatError``).

Every bad file here is derived from a real recording: the AMC text is decompressed, edited and written
to ``tmp_path``. For each damaged AMC both readers are checked: the streaming reader must yield exactly
the good frames before the bad one (with the values ``read_amc`` gives for the original file) and then
raise; ``read_amc`` must raise the same error (same line, same reason).

The last tests: every exception the project defines for what a user or a client can cause derives
from the one root, :class:`daemon.errors.MocapdError`, wire refusals included.
"""

from __future__ import annotations

import gzip
import importlib
import inspect
import pkgutil
import re
import zlib
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

from daemon import behaviours as bh
from daemon.cluster.ring import assignment
from daemon.errors import InputError, MocapdError
from daemon.features import decimation_factor
from daemon.frames import FrameClock
from daemon.recognizer import joint_order
from daemon.service.streams import Refused
from daemon.types import RecognitionSettings
from protocols.messages import WireError
from protocols.transport import StartupError
from protocols.urls import parse_etcd_url, parse_etcd_urls, parse_mqtt_url
from replay import AmcFrame, MocapFormatError, Motion, Skeleton, iter_amc, read_amc, read_asf
from tests.helpers import DATA

SOURCES = {
    "cmu": (DATA / "cmu" / "02" / "02.asf", DATA / "cmu" / "02" / "02_01.amc.gz"),
    "hdm05": (
        DATA / "hdm05" / "asf" / "HDM_bd.asf",
        DATA / "hdm05" / "cut" / "squat1Reps" / "HDM_bd_squat1Reps_001_120.amc.gz",
    ),
}
BAD = 4
"""Index of the frame that is damaged: four good frames come before it."""


def is_frame_number(line: str) -> bool:
    words = line.split()
    return len(words) == 1 and words[0].isdigit()


@dataclass(frozen=True)
class Clip:
    """A real recording: its skeleton, its values as ``read_amc`` gives them, and its decompressed AMC
    text as lines (split at ``\\n``; a ``\\r`` stays at the end of its line). Line numbers are 1-based."""

    asf: Path
    amc: Path
    skeleton: Skeleton
    good: Motion
    lines: tuple[str, ...]
    frame_lines: tuple[int, ...]

    @classmethod
    def load(cls, asf: Path, amc: Path) -> Clip:
        skeleton = read_asf(asf)
        lines = tuple(gzip.decompress(amc.read_bytes()).decode("latin-1").split("\n"))
        frame_lines = tuple(n for n, line in enumerate(lines, 1) if is_frame_number(line))
        return cls(asf, amc, skeleton, read_amc(amc, skeleton), lines, frame_lines)

    def frame_number(self, i: int) -> int:
        return int(self.good.frames[i])

    def frame_end(self, i: int) -> int:
        """The last line of frame ``i`` (0-based index)."""
        if i + 1 < len(self.frame_lines):
            return self.frame_lines[i + 1] - 1
        return max(n for n, line in enumerate(self.lines, 1) if line.strip())

    def bone_lines(self, i: int) -> list[int]:
        return list(range(self.frame_lines[i] + 1, self.frame_end(i) + 1))

    def bone_line(self, i: int, bone: str) -> int:
        """The line of ``bone`` in frame ``i``."""
        (found,) = [n for n in self.bone_lines(i) if self.lines[n - 1].split()[0] == bone]
        return found

    def edit(self) -> list[str]:
        return list(self.lines)


@pytest.fixture(scope="module", params=sorted(SOURCES))
def clip(request: pytest.FixtureRequest) -> Clip:
    asf, amc = SOURCES[request.param]
    return Clip.load(asf, amc)


def words_of(lines: Sequence[str], n: int) -> list[str]:
    return lines[n - 1].split()


def set_words(lines: list[str], n: int, words: Sequence[str]) -> None:
    """Replace line ``n`` by ``words``, keeping its line ending."""
    ending = "\r" if lines[n - 1].endswith("\r") else ""
    lines[n - 1] = " ".join(words) + ending


def write(path: Path, lines: Sequence[str]) -> Path:
    path.write_bytes("\n".join(lines).encode("latin-1"))
    return path


def check_bad_amc(clip: Clip, path: Path, line: int, good_frames: int, *mentions: str) -> MocapFormatError:
    """Both readers on a damaged file: the good frames, then an error at ``line`` naming ``mentions``."""
    got: list[AmcFrame] = []
    where = rf"^{re.escape(str(path))}:{line}: "
    with pytest.raises(MocapFormatError, match=where) as caught:
        for frame in iter_amc(path, clip.skeleton):  # consumed the way list(iter_amc(...)) would
            got.append(frame)
    err = caught.value
    assert [f.frame for f in got] == [clip.frame_number(i) for i in range(good_frames)]
    for i, frame in enumerate(got):
        np.testing.assert_array_equal(frame.channels, clip.good.channels[i])
    assert err.path == str(path)
    assert err.line == line, str(err)
    assert str(err) == f"{path}:{line}: {err.reason}"
    for word in mentions:
        assert word in err.reason, (word, str(err))

    with pytest.raises(MocapFormatError, match=f"^{re.escape(str(err))}$") as whole:
        read_amc(path, clip.skeleton)
    assert (whole.value.path, whole.value.line, whole.value.reason) == (err.path, err.line, err.reason)
    return err


# --------------------------------------------------------------------------------------------------
# AMC: truncated files


def test_truncated_between_lines(clip: Clip, tmp_path: Path) -> None:
    """Cut after a complete bone line in the middle of a frame: the missing line is the next one."""
    last = clip.bone_line(BAD, "rhumerus")
    lines = [*clip.lines[:last], ""]  # ends with the newline of line `last`
    path = write(tmp_path / "cut.amc", lines)
    next_bone = words_of(clip.lines, last + 1)[0]
    check_bad_amc(
        clip, path, last + 1, BAD, f"frame {clip.frame_number(BAD)} ", "file ends", next_bone, "ltoes"
    )


def test_truncated_mid_line(clip: Clip, tmp_path: Path) -> None:
    """Cut in the middle of a bone line (after two of its three values, no final newline)."""
    at = clip.bone_line(BAD, "rhumerus")
    lines = list(clip.lines[:at])
    set_words(lines, at, words_of(lines, at)[:3])
    lines[-1] = lines[-1].rstrip("\r")
    path = write(tmp_path / "cut.amc", lines)
    check_bad_amc(clip, path, at, BAD, "'rhumerus'", "needs 3 values, got 2")


def recoverable_text(data: bytes) -> bytes:
    """Everything zlib can inflate from a damaged gzip stream: the data up to where it breaks off."""
    inflate = zlib.decompressobj(wbits=31)
    return inflate.decompress(data) + inflate.flush()


@pytest.mark.parametrize("cut", ["half", "trailer"])
def test_truncated_gzip(clip: Clip, tmp_path: Path, cut: str) -> None:
    """A gzip stream cut short. ``half``: the compressed bytes are cut in the middle; ``trailer``: only
    the 8-byte CRC/size trailer is missing, so every line of the text is intact.

    The error is at the line where the recoverable data breaks off (the first line without its newline;
    with the trailer cut, the line after the last one), and every frame complete before it is yielded.
    Both readers agree."""
    compressed = gzip.compress("\n".join(clip.lines).encode("latin-1"), mtime=0)
    data = compressed[: len(compressed) // 2] if cut == "half" else compressed[:-8]
    recovered = recoverable_text(data)
    complete_lines = recovered.count(b"\n")
    if cut == "trailer":
        assert recovered == "\n".join(clip.lines).encode("latin-1")
    complete_frames = sum(1 for i in range(len(clip.good)) if clip.frame_end(i) <= complete_lines)
    path = tmp_path / "cut.amc.gz"
    path.write_bytes(data)

    got: list[AmcFrame] = []
    with pytest.raises(MocapFormatError, match=rf"^{re.escape(str(path))}:\d+: .*gzip") as caught:
        for frame in iter_amc(path, clip.skeleton):
            got.append(frame)
    err = caught.value
    assert err.path == str(path)
    assert str(err) == f"{path}:{err.line}: {err.reason}"
    assert "gzip" in err.reason
    # whatever was yielded is good data
    assert [f.frame for f in got] == [clip.frame_number(i) for i in range(len(got))]
    for i, frame in enumerate(got):
        np.testing.assert_array_equal(frame.channels, clip.good.channels[i])
    with pytest.raises(MocapFormatError, match=f"^{re.escape(str(err))}$") as whole:
        read_amc(path, clip.skeleton)
    assert (whole.value.path, whole.value.line, whole.value.reason) == (err.path, err.line, err.reason)

    # every complete frame before the break, and the line where the data breaks off
    assert (len(got), err.line) == (complete_frames, complete_lines + 1), (
        f"yielded {len(got)} of the {complete_frames} complete frames; error at line {err.line}, "
        f"the data breaks off at line {complete_lines + 1}"
    )


# --------------------------------------------------------------------------------------------------
# AMC: damaged frames


def test_frame_missing_a_bone_line(clip: Clip, tmp_path: Path) -> None:
    """The problem shows when the next frame number arrives: that line is reported."""
    lines = clip.edit()
    del lines[clip.bone_line(BAD, "upperback") - 1]
    path = write(tmp_path / "missing.amc", lines)
    next_frame_line = clip.frame_lines[BAD + 1] - 1  # one line earlier after the deletion
    n = clip.frame_number(BAD)
    check_bad_amc(
        clip, path, next_frame_line, BAD, f"frame {n} (line {clip.frame_lines[BAD]})", "no line for upperback"
    )


def test_last_frame_missing_a_bone_line(clip: Clip, tmp_path: Path) -> None:
    """In the last frame the problem shows at the end of the file: the line after the last."""
    last = len(clip.good) - 1
    lines = clip.edit()
    del lines[clip.bone_line(last, "lfemur") - 1]
    path = write(tmp_path / "missing.amc", lines)
    assert lines[-1] == ""  # the file ends with a newline: len(lines) - 1 lines of text
    check_bad_amc(clip, path, len(lines), last, "file ends", "no line for lfemur")


@pytest.mark.parametrize("value", ["abc", "nan", "inf", "-inf", "NaN", "1e999", "1.5.2"])
def test_value_not_a_finite_number(clip: Clip, tmp_path: Path, value: str) -> None:
    lines = clip.edit()
    at = clip.bone_line(BAD, "lowerback")
    words = words_of(lines, at)
    words[2] = value
    set_words(lines, at, words)
    path = write(tmp_path / "value.amc", lines)
    check_bad_amc(clip, path, at, BAD, f"value '{value}'", "bone 'lowerback'", "not a finite number")


def test_bone_not_in_the_skeleton(clip: Clip, tmp_path: Path) -> None:
    lines = clip.edit()
    at = clip.bone_line(BAD, "upperback")
    set_words(lines, at, ["midback", *words_of(lines, at)[1:]])
    path = write(tmp_path / "unknown.amc", lines)
    check_bad_amc(clip, path, at, BAD, "bone 'midback'", "not defined", str(clip.asf))


def test_extra_line_for_an_unknown_bone(clip: Clip, tmp_path: Path) -> None:
    lines = clip.edit()
    at = clip.bone_line(BAD, "thorax") + 1
    lines.insert(at - 1, "tail 1.0 2.0 3.0")
    path = write(tmp_path / "unknown.amc", lines)
    check_bad_amc(clip, path, at, BAD, "bone 'tail'", "not defined", str(clip.asf))


@pytest.mark.parametrize(("change", "count"), [("too few", 2), ("too many", 4)])
def test_wrong_number_of_values(clip: Clip, tmp_path: Path, change: str, count: int) -> None:
    lines = clip.edit()
    at = clip.bone_line(BAD, "thorax")
    words = words_of(lines, at)
    assert len(words) == 4
    set_words(lines, at, words[:-1] if change == "too few" else [*words, "0.5"])
    path = write(tmp_path / "count.amc", lines)
    check_bad_amc(clip, path, at, BAD, "bone 'thorax'", f"needs 3 values, got {count}")


def test_bone_with_one_value_given_two(clip: Clip, tmp_path: Path) -> None:
    lines = clip.edit()
    at = clip.bone_line(BAD, "ltibia")
    set_words(lines, at, [*words_of(lines, at), "1.0"])
    path = write(tmp_path / "count.amc", lines)
    check_bad_amc(clip, path, at, BAD, "bone 'ltibia'", "needs 1 values, got 2")


@pytest.mark.parametrize("delta", [-1, -2], ids=["repeat", "backwards"])
def test_frame_number_out_of_sequence(clip: Clip, tmp_path: Path, delta: int) -> None:
    """Frame BAD numbered n - 1 (the previous number again) or n - 2; a gap (n + 2) is read
    (frames lost in capture: see test_recordings_with_gaps.py)."""
    n = clip.frame_number(BAD)
    wrong = n + delta
    lines = clip.edit()
    set_words(lines, clip.frame_lines[BAD], [str(wrong)])
    path = write(tmp_path / "sequence.amc", lines)
    check_bad_amc(
        clip,
        path,
        clip.frame_lines[BAD],
        BAD,
        f"frame number {wrong} out of sequence (expected {n} or later)",
    )


def test_bone_line_twice_in_a_frame(clip: Clip, tmp_path: Path) -> None:
    lines = clip.edit()
    at = clip.bone_line(BAD, "upperback") + 1
    lines.insert(at - 1, lines[clip.bone_line(BAD, "lowerback") - 1])
    path = write(tmp_path / "twice.amc", lines)
    check_bad_amc(clip, path, at, BAD, "bone 'lowerback'", f"appears twice in frame {clip.frame_number(BAD)}")


def test_bone_line_twice_at_the_end_of_a_frame(clip: Clip, tmp_path: Path) -> None:
    """A repeat of a frame's last bone line: the frame was complete (and correct) when the repeat is
    read, so it is yielded; the repeat is reported on its own line."""
    lines = clip.edit()
    last = clip.frame_end(BAD)
    lines.insert(last, lines[last - 1])
    bone = words_of(lines, last)[0]
    path = write(tmp_path / "twice.amc", lines)
    check_bad_amc(
        clip, path, last + 1, BAD + 1, f"bone line '{bone} ", f"after frame {clip.frame_number(BAD)}"
    )


def test_frame_number_line_missing(clip: Clip, tmp_path: Path) -> None:
    lines = clip.edit()
    del lines[clip.frame_lines[BAD] - 1]
    path = write(tmp_path / "nonumber.amc", lines)
    check_bad_amc(
        clip,
        path,
        clip.frame_lines[BAD],
        BAD,
        "bone line 'root ",
        f"after frame {clip.frame_number(BAD - 1)}",
    )


# --------------------------------------------------------------------------------------------------
# AMC: layouts that are not errors


def read_both(clip: Clip, path: Path) -> tuple[list[AmcFrame], Motion]:
    return list(iter_amc(path, clip.skeleton)), read_amc(path, clip.skeleton)


def assert_same_as_original(clip: Clip, frames: list[AmcFrame], motion: Motion) -> None:
    assert [f.frame for f in frames] == clip.good.frames.tolist()
    np.testing.assert_array_equal(np.array([f.channels for f in frames]), clip.good.channels)
    np.testing.assert_array_equal(motion.frames, clip.good.frames)
    np.testing.assert_array_equal(motion.channels, clip.good.channels)
    assert motion.header == clip.good.header


def test_blank_lines_comments_and_bone_order(clip: Clip, tmp_path: Path) -> None:
    """Blank and whitespace-only lines, ``#`` comment lines (also indented, also at the end of a bone
    line), tabs between values, and bone lines in a different order in some frames: the same values as
    the original, from both readers."""
    header = list(clip.lines[: clip.frame_lines[0] - 1])
    out = [*header, "", "# a comment before the first frame"]
    for i in range(len(clip.good)):
        number = clip.lines[clip.frame_lines[i] - 1]
        bones = [clip.lines[n - 1] for n in clip.bone_lines(i)]
        if i == 1:
            bones.reverse()
        elif i == 3:
            bones = bones[7:] + bones[:7]
        elif i == len(clip.good) - 1:
            bones = bones[1:] + bones[:1]  # the root line last
        if i == 2:
            out += ["", "   ", "\r", "# comment between frames 2 and 3", "   # indented comment"]
        if i == 5:
            bones[0] = bones[0].rstrip("\r") + "   # trailing comment\r"
            bones[1] = "\t".join(bones[1].split()) + "\r"
            bones[2] = "  " + "    ".join(bones[2].split())
        out += [number, *bones]
    out += ["", "# the end", ""]
    path = write(tmp_path / "layout.amc", out)
    assert path.read_bytes() != "\n".join(clip.lines).encode("latin-1")
    assert_same_as_original(clip, *read_both(clip, path))

    packed = tmp_path / "layout.amc.gz"
    packed.write_bytes(gzip.compress(path.read_bytes(), mtime=0))
    assert_same_as_original(clip, *read_both(clip, packed))


def test_original_text_round_trip(clip: Clip, tmp_path: Path) -> None:
    """The derived files start from the exact decompressed text: unedited, it reads as the original."""
    path = write(tmp_path / "same.amc", clip.lines)
    assert_same_as_original(clip, *read_both(clip, path))


@pytest.mark.parametrize("where", ["first", "middle", "last"])
def test_bare_line_for_a_dofless_bone_is_tolerated(clip: Clip, tmp_path: Path, where: str) -> None:
    """README: "a line for a dof-less bone with no values is tolerated" — wherever it sits in a frame.

    ``lhipjoint`` has no dofs in these skeletons. The line is put first, in the middle, or last among
    the bone lines of frame BAD."""
    assert not clip.skeleton.bones[clip.skeleton.node_index("lhipjoint") - 1].dofs
    lines = clip.edit()
    at = {
        "first": clip.frame_lines[BAD] + 1,
        "middle": clip.bone_line(BAD, "thorax"),
        "last": clip.frame_end(BAD) + 1,
    }[where]
    lines.insert(at - 1, "lhipjoint\r")
    path = write(tmp_path / "dofless.amc", lines)
    assert_same_as_original(clip, *read_both(clip, path))


# --------------------------------------------------------------------------------------------------
# ASF


@pytest.fixture(scope="module")
def asf_lines(clip: Clip) -> tuple[str, ...]:
    return tuple(clip.asf.read_bytes().decode("latin-1").split("\n"))


def line_of(lines: Sequence[str], *words: str) -> int:
    """The one line whose words are ``words``."""
    (found,) = [n for n, line in enumerate(lines, 1) if line.split() == list(words)]
    return found


def bone_block(lines: Sequence[str], bone: str) -> tuple[int, int]:
    """``(begin line, end line)`` of the bone block of ``bone``."""
    name = line_of(lines, "name", bone)
    begin = max(n for n in range(1, name) if lines[n - 1].split() == ["begin"])
    end = min(n for n in range(name, len(lines) + 1) if lines[n - 1].split() == ["end"])
    return begin, end


def field_line(lines: Sequence[str], bone: str, field: str) -> int:
    begin, end = bone_block(lines, bone)
    (found,) = [n for n in range(begin, end) if lines[n - 1].split()[:1] == [field]]
    return found


def check_bad_asf(path: Path, line: int | None, *mentions: str) -> MocapFormatError:
    where = re.escape(f"{path}:{line}: " if line is not None else f"{path}: ")
    with pytest.raises(MocapFormatError, match=f"^{where}") as caught:
        read_asf(path)
    err = caught.value
    assert err.path == str(path)
    assert err.line == line, str(err)
    assert str(err) == (f"{path}:{line}: {err.reason}" if line is not None else f"{path}: {err.reason}")
    for word in mentions:
        assert word in err.reason, (word, str(err))
    return err


def test_asf_original_round_trip(clip: Clip, asf_lines: tuple[str, ...], tmp_path: Path) -> None:
    path = write(tmp_path / "same.asf", asf_lines)
    skeleton = read_asf(path)
    assert skeleton.bones == clip.skeleton.bones
    assert skeleton.parents == clip.skeleton.parents


@pytest.mark.parametrize(
    ("root_children", "closing", "named"),
    [
        # lowerback and upperback made each other's parent, lowerback taken off the root's line
        (["root", "lhipjoint", "rhipjoint"], ["upperback", "thorax", "lowerback"], "'lowerback'"),
        # ltoes made the parent of lhipjoint: a cycle through the whole left leg
        (["root", "rhipjoint", "lowerback"], ["lfoot", "ltoes", "lhipjoint"], "'lhipjoint'"),
    ],
)
def test_asf_hierarchy_cycle(
    asf_lines: tuple[str, ...], tmp_path: Path, root_children: list[str], closing: list[str], named: str
) -> None:
    lines = list(asf_lines)
    set_words(lines, line_of(lines, "root", "lhipjoint", "rhipjoint", "lowerback"), root_children)
    at = line_of(lines, *closing[:2])
    set_words(lines, at, closing)
    check_bad_asf(write(tmp_path / "cycle.asf", lines), at, "cycle", named)


def test_asf_hierarchy_cycle_with_a_bone_hanging_off_it(asf_lines: tuple[str, ...], tmp_path: Path) -> None:
    """The lowerback/upperback cycle, and lhipjoint (first in ``:bonedata``) re-attached to thorax, a
    child of the cycle. lhipjoint is not on the cycle and its line (``thorax ... lhipjoint``) holds no
    edge of it: the error must name a bone on the cycle and a line that closes it."""
    lines = list(asf_lines)
    set_words(lines, line_of(lines, "root", "lhipjoint", "rhipjoint", "lowerback"), ["root", "rhipjoint"])
    closing = line_of(lines, "upperback", "thorax")
    set_words(lines, closing, ["upperback", "thorax", "lowerback"])
    thorax = line_of(lines, "thorax", "lowerneck", "lclavicle", "rclavicle")
    set_words(lines, thorax, ["thorax", "lowerneck", "lclavicle", "rclavicle", "lhipjoint"])
    path = tmp_path / "cycle.asf"
    with pytest.raises(MocapFormatError, match=rf"^{re.escape(str(path))}:\d+: .*cycle") as caught:
        read_asf(write(path, lines))
    err = caught.value
    assert "cycle" in err.reason
    assert "'lowerback'" in err.reason or "'upperback'" in err.reason, str(err)
    assert err.line in (line_of(lines, "lowerback", "upperback"), closing), str(err)


def test_asf_hierarchy_unknown_bone(asf_lines: tuple[str, ...], tmp_path: Path) -> None:
    lines = list(asf_lines)
    at = line_of(lines, "lowerback", "upperback")
    set_words(lines, at, ["lowerback", "upperback", "tail"])
    check_bad_asf(write(tmp_path / "unknown.asf", lines), at, "unknown bone 'tail'")


def test_asf_hierarchy_unknown_parent(asf_lines: tuple[str, ...], tmp_path: Path) -> None:
    lines = list(asf_lines)
    at = line_of(lines, "lowerback", "upperback")
    set_words(lines, at, ["midback", "upperback"])
    check_bad_asf(write(tmp_path / "unknown.asf", lines), at, "unknown bone 'midback'")


def test_asf_bone_without_parent(asf_lines: tuple[str, ...], tmp_path: Path) -> None:
    """lowerback taken off the root's line: reported at the ``:hierarchy`` line, naming the bone."""
    lines = list(asf_lines)
    set_words(
        lines,
        line_of(lines, "root", "lhipjoint", "rhipjoint", "lowerback"),
        ["root", "lhipjoint", "rhipjoint"],
    )
    check_bad_asf(
        write(tmp_path / "orphan.asf", lines), line_of(lines, ":hierarchy"), "'lowerback'", "no parent"
    )


def test_asf_truncated_in_a_bone_block(asf_lines: tuple[str, ...], tmp_path: Path) -> None:
    """The file cut after the ``length`` line of ltoes: the bone block opened on its ``begin`` line is
    never closed. That is what is wrong with the file (the missing ``:hierarchy`` follows from it), and
    the line of the unclosed block is the one to report."""
    begin, _ = bone_block(asf_lines, "ltoes")
    lines = [*asf_lines[: field_line(asf_lines, "ltoes", "length")], ""]
    check_bad_asf(write(tmp_path / "cut.asf", lines), begin, "never closed", "'end'")


def test_asf_last_bone_block_without_end(asf_lines: tuple[str, ...], tmp_path: Path) -> None:
    """The last block's ``end`` is missing and ``:hierarchy`` follows: reported at its ``begin``."""
    lines = list(asf_lines)
    begin, end = bone_block(lines, "rthumb")
    del lines[end - 1]
    check_bad_asf(write(tmp_path / "noend.asf", lines), begin, "never closed", "'end'")


def test_asf_middle_bone_block_without_end(asf_lines: tuple[str, ...], tmp_path: Path) -> None:
    """ltibia's ``end`` is missing: the next ``begin`` is inside it; the message gives both lines."""
    lines = list(asf_lines)
    begin, end = bone_block(lines, "ltibia")
    del lines[end - 1]
    check_bad_asf(write(tmp_path / "noend.asf", lines), end, "'begin' inside", f"opened on line {begin}")


@pytest.mark.parametrize(
    ("field", "value", "words"),
    [
        ("direction", ["0.34202", "abc", "0"], ["direction", "'abc' is not a number"]),
        ("direction", ["0.34202", "inf", "0"], ["direction", "'inf' is not finite"]),
        ("direction", ["0.34202", "-0.939693"], ["direction", "needs 3 numbers, got 2"]),
        ("length", ["7.5x"], ["length", "'7.5x' is not a number"]),
        ("length", ["nan"], ["length", "'nan' is not a number"]),
        ("length", ["inf"], ["length", "'inf' is not finite"]),
        ("length", ["-1.0"], ["length is negative"]),
        ("dof", ["rx", "ry", "rq"], ["unknown dof 'rq'"]),
        ("dof", ["rx", "ry", "tx"], ["dof 'tx'", "only rotation dofs"]),
        ("dof", ["rx", "rx", "rz"], ["dof is listed twice"]),
    ],
)
def test_asf_bad_bone_field(
    asf_lines: tuple[str, ...], tmp_path: Path, field: str, value: list[str], words: list[str]
) -> None:
    lines = list(asf_lines)
    at = field_line(lines, "lfemur", field)
    set_words(lines, at, [field, *value])
    check_bad_asf(write(tmp_path / "field.asf", lines), at, *words)


def test_an_amc_that_does_not_fit_its_skeleton_names_the_asf_too(tmp_path: Path) -> None:
    """A damaged ASF can still parse: one bone lost a dof. Reading the (intact) AMC against it then
    fails on that bone's first line, and the error names the ASF as well, the file that is wrong
    (before: only the AMC, which the fuzz run of ``mocapd search`` took for a misattribution)."""
    asf, amc = SOURCES["hdm05"]
    text = asf.read_text(encoding="latin-1")
    # rfemur's rz, and its limits with it
    damaged = re.sub(
        r"(name rfemur\b.*?dof rx ry) rz(.*?\(.*?\).*?\(.*?\))\s*\(.*?\)", r"\1\2", text, count=1, flags=re.S
    )
    assert damaged != text
    path = tmp_path / "damaged.asf"
    path.write_text(damaged, encoding="latin-1")
    for read in (read_amc, lambda a, s: list(iter_amc(a, s))):
        with pytest.raises(MocapFormatError) as caught:
            read(amc, read_asf(path))
        assert "rfemur" in caught.value.reason and str(path) in caught.value.reason, str(caught.value)


# ------------------------------------------------------------------------------- one error root

NOT_USER_ERRORS = {
    "daemon.service.app._Stop",  # the service's own signal to end its task group, never shown
    "daemon.service.workers._Stop",  # the same of run --workers' front
    "daemon.service.view.server._Stop",  # the same of mocapd view
    "protocols.mqtt.MqttLost",  # a lost broker connection, mended by the transport, never shown
    "protocols.deliveries.ProtocolError",  # a broken NATS connection, mended (at start: StartupError)
}
"""Exceptions of the project that are not for a user or a client to cause, and why."""


def project_modules() -> list[str]:
    names = []
    for package in ("daemon", "protocols", "replay"):
        names.append(package)
        found = pkgutil.walk_packages(importlib.import_module(package).__path__, f"{package}.")
        names += [m.name for m in found if not m.name.endswith(".__main__")]  # __main__ runs the CLI
    return names


def test_every_user_error_derives_from_the_one_root() -> None:
    defined = {
        f"{name}.{cls.__qualname__}": cls
        for name in project_modules()
        for cls in vars(importlib.import_module(name)).values()
        if inspect.isclass(cls) and cls.__module__ == name and issubclass(cls, Exception)
    }
    assert {"protocols.messages.WireError", "daemon.service.streams.Refused"} <= defined.keys()
    assert {name for name, cls in defined.items() if not issubclass(cls, MocapdError)} == NOT_USER_ERRORS


def test_refusals_keep_their_reason_codes_and_sentences() -> None:
    wire = WireError("schema", "unknown field x")
    assert isinstance(wire, ValueError) and (wire.reason, wire.detail) == ("schema", "unknown field x")
    assert str(wire) == "schema: unknown field x"
    refused = Refused("duplicate", "seq 5 after 5")
    assert (refused.reason, refused.detail, str(refused)) == ("duplicate", "seq 5 after 5", "seq 5 after 5")
    startup = StartupError("zmq.poses", "address in use")
    assert (startup.setting, startup.reason) == ("zmq.poses", "address in use")
    assert str(startup) == "zmq.poses: address in use"


@pytest.mark.parametrize(
    ("call", "says"),
    [
        (lambda: decimation_factor(120.0, 7.0), "divided"),
        (lambda: RecognitionSettings(("a", "a")), "twice"),
        (lambda: parse_mqtt_url("http://h"), "mqtt://"),
        (lambda: parse_etcd_url("http://h:2379"), "etcd://"),
        (lambda: parse_etcd_url("etcd://h:port"), "etcd://"),
        (lambda: parse_etcd_urls("etcd://a:1,b:port"), "its member 'b:port'"),
        (lambda: parse_etcd_urls("a:1,b:2"), "etcd://"),
        (lambda: assignment(["a"], -1), "partitions"),
        (lambda: joint_order(["root"]), "must include"),
        (lambda: FrameClock.of(0.0, 30.0), "native rate"),
        (lambda: bh.PcaSegmenter(120.0, params=bh.PcaParams(k=0.001)), "frames at 120 Hz"),
    ],
)
def test_what_a_pure_module_refuses_of_its_input_is_a_user_error(
    call: Callable[[], object], says: str
) -> None:
    """A rate, a setting, an address or a window that a caller passes on from a user: the pure
    module raises InputError (a MocapdError and, for its older callers, a ValueError), which the
    caller completes with where the value came from."""
    with pytest.raises(InputError, match=says):
        call()


def test_a_coordinator_names_its_members_in_order_each_once() -> None:
    assert parse_etcd_urls("etcd://a:1,b,etcd://c:3,a:1") == [("a", 1), ("b", 2379), ("c", 3)]
