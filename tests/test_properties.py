"""Property tests of the ASF/AMC readers and the forward kinematics on random synthetic files.

The generators live in :mod:`tests.synth`; this module holds the properties and a slow,
obviously-correct forward-kinematics reference written with plain floats and 3x3 lists.
"""

from __future__ import annotations

import gzip
import itertools
import math
import random
import re
import signal
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from types import FrameType
from typing import Any
from unittest.mock import patch

import numpy as np
import numpy.typing as npt
import pytest
from hypothesis import HealthCheck, Phase, assume, event, given, settings
from hypothesis import strategies as st

import replay.amc as amc_module
from daemon.types import FloatArray
from replay.amc import AmcFrame, AmcStream, iter_amc, read_amc
from replay.asf import Skeleton, read_asf
from replay.errors import MocapFormatError
from replay.kinematics import KinematicModel
from tests.naive import apply, elementary, euler, mul, reference_pose
from tests.synth import AmcFile, AsfFile, cases, seeds, skeletons

Mat = list[list[float]]
Vec = list[float]

# Base settings: no deadline (file I/O), big generated inputs are fine.
BASE = settings(deadline=None, suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])


# ------------------------------------------------------------------------------------ helpers


@contextmanager
def written(asf: AsfFile, amc_bytes: bytes | None = None, *, gzip_asf: bool = False) -> Iterator[Path]:
    """A temporary directory holding ``skel.asf`` and (if given) ``motion.amc`` with these bytes."""
    with tempfile.TemporaryDirectory() as tmp:
        d = Path(tmp)
        (d / "skel.asf").write_bytes(gzip.compress(asf.data, mtime=0) if gzip_asf else asf.data)
        if amc_bytes is not None:
            (d / "motion.amc").write_bytes(amc_bytes)
        yield d


def amc_bytes_on_disk(amc: AmcFile) -> bytes:
    return gzip.compress(amc.text, mtime=0) if amc.gzipped else amc.text


def bits(a: FloatArray) -> bytes:
    """The exact bit pattern of a float64 array (so -0.0 != 0.0 and shapes must match too)."""
    return np.ascontiguousarray(a, dtype=np.float64).tobytes() + repr(a.shape).encode()


def as_array(rows: list[list[float]], n_channels: int) -> FloatArray:
    return np.array(rows, dtype=np.float64).reshape(len(rows), n_channels)


@contextmanager
def time_limit(seconds: float) -> Iterator[None]:
    """Raise ``TimeoutError`` in the block if it runs longer than ``seconds`` (SIGALRM, main thread)."""

    def expire(signum: int, frame: FrameType | None) -> None:
        raise TimeoutError(f"still running after {seconds} s")

    previous = signal.signal(signal.SIGALRM, expire)
    signal.setitimer(signal.ITIMER_REAL, seconds)
    try:
        yield
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, previous)


def stream_all(path: Path, skel: Skeleton) -> tuple[list[AmcFrame], MocapFormatError | None]:
    """Every frame ``iter_amc`` yields, and the format error it stops with (if any)."""
    got: list[AmcFrame] = []
    try:
        for frame in iter_amc(path, skel):
            got.append(frame)
    except MocapFormatError as exc:
        return got, exc
    return got, None


# ------------------------------------------------------------------ reference forward kinematics


def test_reference_kinematics_sanity() -> None:
    """The reference itself on hand-checked cases: Rz(90) maps x to y; "XYZ" is Rz @ Ry @ Rx."""
    r = elementary("Z", math.pi / 2)
    assert np.allclose(apply(r, [1.0, 0.0, 0.0]), [0.0, 1.0, 0.0])
    r = elementary("X", math.pi / 2)
    assert np.allclose(apply(r, [0.0, 1.0, 0.0]), [0.0, 0.0, 1.0])
    r = elementary("Y", math.pi / 2)
    assert np.allclose(apply(r, [0.0, 0.0, 1.0]), [1.0, 0.0, 0.0])
    a, b, c = 0.3, -1.1, 2.0
    expected = mul(elementary("Z", c), mul(elementary("Y", b), elementary("X", a)))
    assert np.allclose(euler((a, b, c), "XYZ"), expected)
    expected = mul(elementary("X", c), mul(elementary("Z", b), elementary("Y", a)))
    assert np.allclose(euler((a, b, c), "YZX"), expected)


# -------------------------------------------------------------------------------------- ASF


@pytest.mark.slow
@settings(BASE, max_examples=60)
@given(skeletons(), st.booleans())
def test_asf_reader_returns_the_generated_skeleton(asf: AsfFile, gzip_asf: bool) -> None:
    spec = asf.spec
    with written(asf, gzip_asf=gzip_asf) as d:
        skel = read_asf(d / "skel.asf")
    r = spec.to_rad
    assert skel.name == spec.name
    assert (skel.mass_unit, skel.length_unit, skel.angle_unit) == (
        spec.mass_unit,
        spec.length_unit,
        spec.angle_unit,
    )
    assert skel.root.order == spec.root_order
    assert skel.root.axis_order == spec.root_axis
    assert skel.root.position == spec.root_position
    assert skel.root.orientation == tuple(v * r for v in spec.root_orientation)
    assert skel.node_names == ("root", *(b.name for b in spec.bones))
    assert skel.parents == spec.parents
    assert skel.channel_names == spec.channel_names
    for got, want in zip(skel.bones, spec.bones, strict=True):
        assert got.name == want.name
        assert got.bone_id == want.bone_id
        assert got.length == want.length
        assert got.axis == tuple(v * r for v in want.axis)
        assert got.axis_order == want.axis_order
        assert got.dofs == want.dofs
        assert got.limits == tuple((lo * r, hi * r) for lo, hi in want.limits)
        norm = math.sqrt(sum(x * x for x in want.direction))
        if norm > 0:
            assert math.isclose(math.hypot(*got.direction), 1.0, rel_tol=1e-12)
            for g, w in zip(got.direction, want.direction, strict=True):
                assert math.isclose(g, w / norm, rel_tol=1e-12, abs_tol=1e-15)
        else:
            assert got.direction == (0.0, 0.0, 0.0)


# -------------------------------------------------------------------------------------- AMC


@pytest.mark.slow
@settings(BASE, max_examples=60)
@given(cases(wide=True))
def test_amc_readers_agree_bitwise_and_return_the_written_values(case: tuple[AsfFile, AmcFile]) -> None:
    """Properties 1 and 2: ``read_amc`` == ``iter_amc`` bit for bit == the generated values, in the
    ``channel_names`` layout, angles ``value * (pi / 180)`` for degrees, as written for radians."""
    asf, amc = case
    fast_path: list[bool] = []
    real_parse_regular = amc_module._parse_regular

    def spy(body: bytes, layout: Any) -> tuple[npt.NDArray[np.int64], FloatArray] | None:
        result = real_parse_regular(body, layout)
        fast_path.append(result is not None)
        return result

    with written(asf, amc_bytes_on_disk(amc)) as d:
        skel = read_asf(d / "skel.asf")
        path = d / "motion.amc"
        with patch.object(amc_module, "_parse_regular", spy):
            motion = read_amc(path, skel)
        streamed, error = stream_all(path, skel)
        with AmcStream(path, skel) as stream:
            header = stream.header
    assert error is None, f"the streaming reader rejects a valid file: {error}"

    n_channels = len(skel.channel_names)
    expected_frames = [f.number for f in amc.frames]
    expected = as_array(amc.channel_matrix(), n_channels)
    stacked = as_array([f.channels.tolist() for f in streamed], n_channels)

    # 1. both readers, bit for bit
    assert [f.frame for f in streamed] == expected_frames
    assert motion.frames.dtype == np.int64
    assert motion.frames.tolist() == expected_frames
    assert motion.channels.dtype == np.float64
    assert np.array_equal(motion.channels, stacked)
    assert bits(motion.channels) == bits(stacked)
    assert all(f.channels.dtype == np.float64 and f.channels.shape == (n_channels,) for f in streamed)
    # 2. the values written
    assert bits(motion.channels) == bits(expected)
    # header
    assert motion.header == header
    assert header.angle_unit == amc.angle_unit
    assert header.fully_specified == amc.fully_specified
    assert header.frame_rate == amc.frame_rate
    assert len(motion) == len(amc.frames)
    # the vectorised path is really exercised on regular files
    event(f"read_amc fast path: {fast_path}; gzip: {amc.gzipped}")
    if amc.regular:
        assert fast_path == [True], "a regular file did not take read_amc's vectorised path"


# --------------------------------------------------------------------------- forward kinematics


@settings(BASE, max_examples=40)
@given(cases(wide=False), seeds)
def test_forward_kinematics_matches_a_slow_reference(case: tuple[AsfFile, AmcFile], seed: int) -> None:
    """Properties 3 to 6: positions equal the reference (ASF units and cm), one frame alone equals
    its row of the batch bit for bit, bone lengths are kept, and the root rotation channels do not
    change any distance between nodes."""
    asf, amc = case
    spec = asf.spec
    rnd = random.Random(seed)
    with written(asf, amc_bytes_on_disk(amc)) as d:
        skel = read_asf(d / "skel.asf")
        motion = read_amc(d / "motion.amc", skel)
    rows = amc.channel_matrix()
    channels = motion.channels
    assert bits(channels) == bits(as_array(rows, len(skel.channel_names)))

    model = KinematicModel(skel)
    pos = model.positions(channels)
    pos_cm = model.positions(channels, "cm")
    n_nodes = len(spec.bones) + 1
    assert pos.shape == pos_cm.shape == (len(rows), n_nodes, 3)

    rotations = model.rotations(channels)
    local = model.local_rotations(channels)
    assert rotations.shape == (len(rows), n_nodes, 3, 3)
    poses = [reference_pose(spec, row) for row in rows]
    # positions are bounded by |root position| + the sum of the bone lengths
    scale = sum(b.length for b in spec.bones) + max(max(map(abs, p[0])) for _, p in poses) + 1.0
    tol = 1e-9 * scale
    cm = 2.54 / spec.length_unit
    assert np.allclose(pos_cm, pos * cm, rtol=1e-14, atol=1e-300)

    for i, (ref_rot, ref_pos) in enumerate(poses):
        ref = np.array(ref_pos)
        # 3. the reference, in ASF units and in centimetres (and the global rotations)
        err = float(np.max(np.abs(pos[i] - ref)))
        assert err <= tol, f"frame {i}: positions differ from the reference by {err} (tolerance {tol})"
        err_cm = float(np.max(np.abs(pos_cm[i] - ref * cm)))
        assert err_cm <= tol * cm, f"frame {i}: cm positions differ from the reference by {err_cm}"
        err_rot = float(np.max(np.abs(rotations[i] - np.array(ref_rot))))
        assert err_rot <= 1e-9, f"frame {i}: global rotations differ from the reference by {err_rot}"
        # 4. one frame alone == its row of the batch, bit for bit
        assert bits(model.positions_frame(channels[i])) == bits(pos[i])
        assert bits(model.positions_frame(channels[i], "cm")) == bits(pos_cm[i])
        assert bits(model.local_rotations_frame(channels[i])) == bits(local[i])

    # 5. bone lengths in every frame
    for k, bone in enumerate(spec.bones, 1):
        lengths = np.linalg.norm(pos[:, k] - pos[:, bone.parent], axis=1)
        assert np.all(np.abs(lengths - bone.length) <= tol), (bone.name, lengths, bone.length)

    # 6. other root rotation channels: the same distances between all nodes
    turned = channels.copy()
    for c, name in enumerate(skel.channel_names):
        if name in ("root.rx", "root.ry", "root.rz"):
            turned[:, c] = [rnd.uniform(-4 * math.pi, 4 * math.pi) for _ in range(len(rows))]
    pos_turned = model.positions(turned)
    dist = np.linalg.norm(pos[:, :, None, :] - pos[:, None, :, :], axis=-1)
    dist_turned = np.linalg.norm(pos_turned[:, :, None, :] - pos_turned[:, None, :, :], axis=-1)
    assert np.all(np.abs(dist - dist_turned) <= 4 * tol)
    assert np.array_equal(pos_turned[:, 0], pos[:, 0])  # the root position does not depend on rotations


# ------------------------------------------------------------------------------ truncated files


@pytest.mark.slow
@settings(BASE, max_examples=100)
@given(cases(body_noise=False, allow_gzip=False, max_bones=6, max_frames=6), st.data())
def test_truncated_amc_yields_the_complete_frames_then_a_located_error(
    case: tuple[AsfFile, AmcFile], data: st.DataObject
) -> None:
    asf, amc = case
    text, frames = amc.text, amc.frames
    where = data.draw(
        st.sampled_from(["anywhere", "at a line end", "near a frame end", "inside a last number"])
    )
    j = data.draw(st.integers(0, len(frames) - 1))
    if where == "anywhere":
        cut = data.draw(st.integers(0, len(text)))
    elif where == "at a line end":  # the usual truncation: whole lines, the frame in progress cut short
        ends = [i + 1 for i, byte in enumerate(text) if byte == 0x0A]
        cut = data.draw(st.sampled_from(ends)) if ends else len(text)
    elif where == "near a frame end":
        cut = min(len(text), max(0, frames[j].last_token[1] + data.draw(st.integers(-3, 3))))
    else:
        cut = data.draw(st.integers(*frames[j].last_token))
    truncated = text[:cut]

    # What must come out. Frame k is complete once its last token is whole; the bytes between two
    # frames are only whitespace. Cut inside the last token of a frame, the frame may still parse,
    # with the number the prefix spells ("12.345" cut to "12.3").
    complete = sum(1 for f in frames if f.last_token[1] <= cut)
    expected_rows = amc.channel_matrix()[:complete]
    ok: bool
    if complete == len(frames):
        ok = True
    else:
        nxt = frames[complete]
        start, end = nxt.last_token
        if cut <= nxt.start:
            ok = complete > 0  # nothing of the next frame; no frame at all is an error
        elif start < cut < end:
            prefix = text[start:cut].decode("ascii")
            try:
                value = float(prefix)
            except ValueError:
                value = math.nan
            ok = math.isfinite(value)
            if ok:
                tokens = dict(nxt.tokens)
                tokens[nxt.last_line] = (*tokens[nxt.last_line][:-1], prefix)
                expected_rows = [*expected_rows, amc.channel_row(tokens)]
        else:
            ok = False
    event(f"{where}: {'reads' if ok else 'error'}")

    n_channels = len(asf.spec.channel_names)
    expected = as_array(expected_rows, n_channels)
    expected_numbers = [f.number for f in frames[: len(expected_rows)]]
    with written(asf, truncated) as d:
        skel = read_asf(d / "skel.asf")
        path = d / "motion.amc"
        streamed, error = stream_all(path, skel)
        whole: MocapFormatError | None = None
        try:
            motion = read_amc(path, skel)
        except MocapFormatError as exc:
            whole = exc

    # The stream yields exactly the complete frames, with their exact values...
    assert [f.frame for f in streamed] == expected_numbers
    assert bits(as_array([f.channels.tolist() for f in streamed], n_channels)) == bits(expected)
    if ok:
        assert error is None, f"cut at {cut}: unexpected error {error}"
        assert whole is None, f"cut at {cut}: read_amc fails: {whole}"
        assert motion.frames.tolist() == expected_numbers
        assert bits(motion.channels) == bits(expected)
        return
    # ... then stops with an error naming the file and a line; read_amc fails the same way.
    assert error is not None, f"cut at {cut} of {len(text)}: the truncated file reads without error"
    assert error.path == str(path)
    assert error.line is not None
    assert 1 <= error.line <= len(truncated.split(b"\n")) + 1  # the line after the last: end of file
    assert whole is not None, f"cut at {cut}: read_amc accepts a truncated file"
    assert whole.path == str(path)
    assert whole.line == error.line


# ------------------------------------------------------------------------- bones without dofs


@settings(BASE, max_examples=30)
@given(cases(dofless_lines=True, body_noise=False, max_frames=5))
def test_bone_lines_without_dofs_are_accepted_anywhere_in_a_frame(case: tuple[AsfFile, AmcFile]) -> None:
    """The AMC readers skip a line naming a bone that has no dofs (``AmcStream`` does so explicitly);
    where in a frame that line stands must not matter."""
    asf, amc = case
    assume(any(not b.dofs for b in asf.spec.bones))
    with written(asf, amc_bytes_on_disk(amc)) as d:
        skel = read_asf(d / "skel.asf")
        path = d / "motion.amc"
        streamed, error = stream_all(path, skel)
    last = [f.last_line for f in amc.frames]
    assert error is None, f"dof-less bone lines (frames end with {last}) rejected: {error}"
    n_channels = len(skel.channel_names)
    assert bits(as_array([f.channels.tolist() for f in streamed], n_channels)) == bits(
        as_array(amc.channel_matrix(), n_channels)
    )


# ------------------------------------------------------------- read_amc's chunked vectorised path

NOT_FINISHED = "read_amc did not finish within 2 s on a body whose frames are larger than its chunk"


@settings(BASE, max_examples=40, phases=[Phase.explicit, Phase.reuse, Phase.generate])  # no shrinking:
@given(cases(wide=True, body_noise=False), st.integers(1, 2048))  # a failure costs a 2 s time limit
def test_read_amc_values_do_not_depend_on_the_chunk_size(case: tuple[AsfFile, AmcFile], chunk: int) -> None:
    """``read_amc`` parses a regular body in chunks of ``_CHUNK_BYTES`` (4 MiB); with a small chunk
    the boundaries fall inside frames, and a frame may be larger than a chunk. The values must be
    those of ``iter_amc`` whatever the chunk size, and reading must end."""
    asf, amc = case
    starts = [f.start for f in amc.frames] + [len(amc.text)]
    frame_bytes = max(b - a for a, b in itertools.pairwise(starts))
    event("frame larger than the chunk" if frame_bytes > chunk else "frames fit in a chunk")
    with written(asf, amc_bytes_on_disk(amc)) as d:
        skel = read_asf(d / "skel.asf")
        path = d / "motion.amc"
        streamed, error = stream_all(path, skel)
        assert error is None
        finished = False
        try:
            with patch.object(amc_module, "_CHUNK_BYTES", chunk), time_limit(2.0):
                motion = read_amc(path, skel)
            finished = True
        except TimeoutError:
            pass
    assert finished, f"{NOT_FINISHED} (chunk {chunk} bytes, largest frame {frame_bytes} bytes)"
    n_channels = len(skel.channel_names)
    assert motion.frames.tolist() == [f.frame for f in streamed]
    assert bits(motion.channels) == bits(as_array([f.channels.tolist() for f in streamed], n_channels))


ONE_BONE_ASF = b"""\
:units
  angle deg
:root
  order TX TY TZ RX RY RZ
:bonedata
  begin
    name a
    direction 0 1 0
    length 2
    dof rx rz
  end
:hierarchy
  begin
    root a
  end
"""


def test_read_amc_reads_a_frame_larger_than_its_4_mib_chunk() -> None:
    """The same, unpatched: a valid AMC whose frame takes more than 4 MiB (here, a bone line padded
    with whitespace; a very long number does the same). ``iter_amc`` reads it in milliseconds."""
    pad = b" " * (5 << 20)
    body = b"".join(b"%d\nroot 1 2 3 4 5 6\na%s7 8\n" % (i, pad) for i in (1, 2))
    with tempfile.TemporaryDirectory() as tmp:
        d = Path(tmp)
        (d / "skel.asf").write_bytes(ONE_BONE_ASF)
        (d / "motion.amc").write_bytes(body)
        skel = read_asf(d / "skel.asf")
        streamed, error = stream_all(d / "motion.amc", skel)
        assert error is None and [f.frame for f in streamed] == [1, 2]
        finished = False
        try:
            with time_limit(5.0):
                motion = read_amc(d / "motion.amc", skel)
            finished = True
        except TimeoutError:
            pass
    assert finished, f"{NOT_FINISHED} (a 5 MiB frame, _CHUNK_BYTES = {amc_module._CHUNK_BYTES})"
    assert bits(motion.channels) == bits(np.stack([f.channels for f in streamed]))


# ------------------------------------------------------------------------- big frame numbers


@settings(BASE, max_examples=20, phases=[Phase.explicit, Phase.reuse, Phase.generate])  # no shrinking
@given(
    cases(
        body_noise=False,
        allow_gzip=False,
        max_bones=3,
        max_frames=6,
        first_frames=st.integers(2**63 - 6, 2**64),
    )
)
def test_frame_numbers_beyond_int64_are_read_alike_or_rejected_as_format_errors(
    case: tuple[AsfFile, AmcFile],
) -> None:
    """Frame numbers are int64 in ``read_amc``. Past 2**63 - 1 both readers refuse the file with a
    ``MocapFormatError`` naming it: never another exception, and never other frames than the stream's."""
    asf, amc = case
    with written(asf, amc_bytes_on_disk(amc)) as d:
        skel = read_asf(d / "skel.asf")
        path = d / "motion.amc"
        streamed, error = stream_all(path, skel)
        too_large = any(f.number > 2**63 - 1 for f in amc.frames)
        assert (error is not None) == too_large, error
        if error is not None:
            assert isinstance(error, MocapFormatError) and "too large" in error.reason
            with pytest.raises(MocapFormatError, match=f"^{re.escape(str(error))}$") as caught:
                read_amc(path, skel)
            assert (caught.value.path, caught.value.line) == (error.path, error.line)
            return
        assert [f.frame for f in streamed] == [f.number for f in amc.frames]
        other: Exception | None = None
        try:
            motion = read_amc(path, skel)
        except MocapFormatError as exc:
            assert exc.path == str(path)
            return
        except Exception as exc:  # the property: nothing but MocapFormatError
            other = exc
    assert other is None, (
        f"read_amc raises {type(other).__name__} ({other}) on frame numbers "
        f"{amc.frames[0].number}..{amc.frames[-1].number}, which iter_amc reads"
    )
    assert motion.frames.tolist() == [f.frame for f in streamed]
