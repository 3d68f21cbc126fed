"""Acclaim motion files (AMC): a streaming reader and a whole-file reader with identical values.

Both return channel vectors in the layout of :attr:`replay.asf.Skeleton.channel_names` (root channels,
then each bone's dofs in ``:bonedata`` order), float64, rotation channels in radians whatever the
file's angle unit, translations in ASF units as written.

Frame numbers must increase; a gap (frames lost in capture) reads, and the frames keep their numbers
(``daemon.frames.motion_runs`` bridges it as the daemon bridges lost poses).

* :class:`AmcStream` reads one frame at a time with memory bounded by one frame. It yields every
  complete frame before a bad one, then raises :class:`~replay.errors.MocapFormatError` naming the
  file and line.
* :func:`read_amc` returns a :class:`Motion` with ``(frames, channels)`` arrays. It parses regular
  files (every frame lists the same bones in the same order, no blank or comment lines between
  frames) with vectorised numpy; anything else goes through :class:`AmcStream`, which decides.
"""

from __future__ import annotations

import io
import math
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from types import TracebackType
from typing import BinaryIO

import fastnumbers
import numpy as np

from daemon.types import FloatArray, IntArray
from replay.asf import Skeleton
from replay.errors import MocapFormatError
from replay.textio import GZIP_ERRORS, open_binary, read_bytes

DEG = math.pi / 180.0
_MAX_FRAME = 2**63 - 1


@dataclass(frozen=True)
class AmcHeader:
    """What an AMC file says before its first frame.

    ``angle_unit`` is ``"deg"`` or ``"rad"`` (from ``:DEGREES``/``:RADIANS``, else the ASF's unit);
    ``frame_rate`` is the ``:SAMPLES-PER-SECOND`` value if the file has one.
    """

    angle_unit: str
    fully_specified: bool
    frame_rate: float | None


@dataclass(frozen=True)
class AmcFrame:
    """One frame: its AMC frame number and its channel vector, shape ``(C,)``."""

    frame: int
    channels: FloatArray


@dataclass(frozen=True)
class Motion:
    """A whole AMC file: ``frames`` shape ``(N,)`` (AMC frame numbers, increasing; a file that lost
    frames skips their numbers), ``channels`` shape ``(N, C)``."""

    source: str
    skeleton: Skeleton
    header: AmcHeader
    frames: IntArray
    channels: FloatArray

    def __len__(self) -> int:
        return int(self.frames.shape[0])


class _Layout:
    """Per-skeleton lookup tables shared by both readers."""

    def __init__(self, skeleton: Skeleton) -> None:
        self.n_channels = len(skeleton.channel_names)
        self.slots: dict[bytes, tuple[int, int]] = {
            name.encode("latin-1"): span for name, span in skeleton.channel_offsets.items()
        }
        self.dofless = {b.name.encode("latin-1") for b in skeleton.bones if not b.dofs}
        self.angle_index = np.asarray(skeleton.angle_channels, dtype=np.intp)

    def scale_angles(self, channels: FloatArray, header: AmcHeader) -> None:
        if header.angle_unit == "deg":
            channels[..., self.angle_index] *= DEG


def _is_frame_number(words: list[bytes]) -> bool:
    return len(words) == 1 and words[0].isdigit()


class AmcStream:
    """Frames of an AMC file, one at a time (``for frame in stream``); use as a context manager.

    The header is read on construction; :attr:`header` holds it.
    """

    def __init__(self, path: str | Path, skeleton: Skeleton, *, _data: bytes | None = None) -> None:
        self.source = str(path)
        self.skeleton = skeleton
        self._layout = _Layout(skeleton)
        self._file: BinaryIO = io.BytesIO(_data) if _data is not None else open_binary(path)
        self._line = 0
        self._pending: tuple[int, list[bytes]] | None = None
        self.body_offset = 0
        try:
            self.header = self._read_header()
        except BaseException:
            self.close()
            raise

    def __enter__(self) -> AmcStream:
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()

    def close(self) -> None:
        self._file.close()

    def _error(self, reason: str, line: int | None = None) -> MocapFormatError:
        return MocapFormatError(self.source, self._line if line is None else line, reason)

    def _next_words(self) -> list[bytes] | None:
        """The next line with content, split into words; ``None`` at the end of the file."""
        while True:
            try:
                raw = self._file.readline()
            except GZIP_ERRORS as exc:
                raise self._error(f"damaged or truncated gzip data ({exc})", self._line + 1) from None
            if not raw:
                return None
            self._line += 1
            if b"#" in raw:
                raw = raw.split(b"#", 1)[0]
            words = raw.split()
            if words:
                return words

    def _read_header(self) -> AmcHeader:
        angle_unit = self.skeleton.angle_unit
        fully_specified = False
        frame_rate: float | None = None
        while True:
            before = self._file.tell() if isinstance(self._file, io.BytesIO) else 0
            words = self._next_words()
            if words is None:
                raise self._error("no frames (file is empty or truncated)", self._line + 1)
            if _is_frame_number(words):
                self._pending = (self._line, words)
                self.body_offset = before
                break
            key = words[0].decode("latin-1").upper()
            if key == ":FULLY-SPECIFIED":
                fully_specified = True
            elif key == ":DEGREES":
                angle_unit = "deg"
            elif key == ":RADIANS":
                angle_unit = "rad"
            elif key == ":SAMPLES-PER-SECOND":
                if len(words) != 2:
                    raise self._error(":SAMPLES-PER-SECOND needs one number")
                try:
                    frame_rate = float(words[1])
                except ValueError:
                    raise self._error(
                        f":SAMPLES-PER-SECOND '{words[1].decode('latin-1')}' is not a number"
                    ) from None
                if not (math.isfinite(frame_rate) and frame_rate > 0):
                    raise self._error(f":SAMPLES-PER-SECOND must be a positive number, got {frame_rate}")
            elif key.startswith(":"):
                continue
            else:
                text = b" ".join(words).decode("latin-1")
                raise self._error(f"expected a header line or a frame number, got '{text}'")
        return AmcHeader(angle_unit=angle_unit, fully_specified=fully_specified, frame_rate=frame_rate)

    def __iter__(self) -> Iterator[AmcFrame]:
        layout = self._layout
        required = len(layout.slots)
        expected: int | None = None
        words: list[bytes] | None
        if self._pending is None:
            return
        start, words = self._pending
        self._pending = None
        while words is not None:
            if words[0] in layout.dofless and len(words) == 1:
                words = self._next_words()
                continue
            if not _is_frame_number(words):
                text = b" ".join(words).decode("latin-1")
                if words[0] in layout.slots or words[0] in layout.dofless:
                    raise self._error(
                        f"bone line '{text}' after frame {expected - 1 if expected else '?'} was complete"
                    )
                raise self._error(f"expected a frame number, got '{text}'")
            number = int(words[0])
            if number > _MAX_FRAME:
                raise self._error(f"frame number {number} is too large (at most {_MAX_FRAME})")
            if expected is not None and number < expected:  # a gap is frames lost: it reads
                raise self._error(f"frame number {number} out of sequence (expected {expected} or later)")
            start = self._line
            buf = [0.0] * layout.n_channels
            seen: set[bytes] = set()
            while len(seen) < required:
                words = self._next_words()
                if words is None or _is_frame_number(words):
                    missing = [n.decode("latin-1") for n in layout.slots if n not in seen]
                    where = "the file ends" if words is None else f"frame {words[0].decode('latin-1')} starts"
                    raise self._error(
                        f"frame {number} (line {start}) is incomplete when {where}: no line for "
                        + ", ".join(missing)
                        + f" (bones of {self.skeleton.source})",
                        self._line + 1 if words is None else None,
                    )
                name = words[0]
                slot = layout.slots.get(name)
                if slot is None:
                    if name in layout.dofless and len(words) == 1:
                        continue
                    if name in layout.dofless:
                        raise self._error(
                            f"bone '{name.decode('latin-1')}' has no dofs in {self.skeleton.source} but "
                            f"{len(words) - 1} values"
                        )
                    raise self._error(
                        f"bone '{name.decode('latin-1')}' is not defined in {self.skeleton.source}"
                    )
                if name in seen:
                    raise self._error(f"bone '{name.decode('latin-1')}' appears twice in frame {number}")
                at, count = slot
                if len(words) - 1 != count:
                    raise self._error(
                        f"bone '{name.decode('latin-1')}' needs {count} values, got {len(words) - 1} "
                        f"({count} dofs in {self.skeleton.source})"
                    )
                for k in range(count):
                    try:
                        # float() takes "1_0"; a motion file does not
                        value = float(words[k + 1]) if b"_" not in words[k + 1] else math.nan
                    except ValueError:
                        value = math.nan
                    if not math.isfinite(value):
                        raise self._error(
                            f"value '{words[k + 1].decode('latin-1')}' for bone '{name.decode('latin-1')}' "
                            "is not a finite number"
                        )
                    buf[at + k] = value
                seen.add(name)
            channels = np.array(buf, dtype=np.float64)
            layout.scale_angles(channels, self.header)
            yield AmcFrame(frame=number, channels=channels)
            expected = number + 1
            words = self._next_words()


def iter_amc(path: str | Path, skeleton: Skeleton) -> Iterator[AmcFrame]:
    """Yield the frames of ``path`` one at a time (see :class:`AmcStream`)."""
    with AmcStream(path, skeleton) as stream:
        yield from stream


def read_amc(path: str | Path, skeleton: Skeleton) -> Motion:
    """Read a whole AMC file into arrays; the values equal :func:`iter_amc`'s exactly."""
    source = str(path)
    try:
        data = read_bytes(path)
    except MocapFormatError:
        return _collect(source, skeleton, None)  # the stream reports the line where the data breaks off
    with AmcStream(source, skeleton, _data=data) as stream:
        header = stream.header
        layout = stream._layout
        parsed = _parse_regular(data[stream.body_offset :], layout)
    if parsed is None:
        return _collect(source, skeleton, data)
    frames, channels = parsed
    layout.scale_angles(channels, header)
    return Motion(source=source, skeleton=skeleton, header=header, frames=frames, channels=channels)


def _collect(source: str, skeleton: Skeleton, data: bytes | None) -> Motion:
    with AmcStream(source, skeleton, _data=data) as stream:
        got = list(stream)
        header = stream.header
    channels = np.empty((len(got), len(skeleton.channel_names)), dtype=np.float64)
    for i, f in enumerate(got):
        channels[i] = f.channels
    frames = np.fromiter((f.frame for f in got), dtype=np.int64, count=len(got))
    return Motion(source=source, skeleton=skeleton, header=header, frames=frames, channels=channels)


_CHUNK_BYTES = 1 << 22


def _parse_regular(body: bytes, layout: _Layout) -> tuple[IntArray, FloatArray] | None:
    """Parse a body whose frames all have the first frame's exact line layout, without a Python loop
    over lines or values (list slicing, and fastnumbers' correctly rounded conversion, which equals
    ``float()``).

    Returns ``None`` (and the caller falls back to :class:`AmcStream`) on anything irregular, so this
    never accepts input the streaming reader would reject. Angles are returned as written.
    """
    head = body.split(b"\n", len(layout.slots) + 1)
    if len(head) < len(layout.slots) + 1:
        return None
    order = [line.split(None, 1)[0] if line.split() else b"" for line in head[1 : len(layout.slots) + 1]]
    if sorted(order) != sorted(layout.slots):
        return None
    # Newlines become ';' tokens, so one frame is always the same row of tokens:
    # [number, ';', name, values..., ';', name, values..., ';', ...]
    width = 2
    name_cols: list[tuple[int, bytes]] = []
    value_cols: list[int] = []
    value_dest: list[int] = []
    sep_cols = [1]
    for name in order:
        at, count = layout.slots[name]
        name_cols.append((width, name))
        value_cols.extend(range(width + 1, width + 1 + count))
        value_dest.extend(range(at, at + count))
        width += count + 2
        sep_cols.append(width - 1)
    lines_per_frame = 1 + len(order)

    if not body.endswith(b"\n"):
        body += b"\n"
    frames_out: list[IntArray] = []
    values_out: list[FloatArray] = []
    pos, end, size = 0, len(body), _CHUNK_BYTES
    while pos < end:
        stop = min(end, pos + size)
        newlines = np.flatnonzero(np.frombuffer(body, dtype=np.uint8, count=stop - pos, offset=pos) == 10)
        whole = (newlines.size // lines_per_frame) * lines_per_frame
        if whole == 0:
            if stop == end:
                if body[pos:].strip():
                    return None
                break
            size *= 4  # a frame larger than the chunk
            continue
        size = _CHUNK_BYTES
        cut = pos + int(newlines[whole - 1]) + 1
        tokens = body[pos:cut].replace(b"\n", b" ; ").split()
        n = whole // lines_per_frame
        if len(tokens) != n * width:
            return None
        if any(tokens[c::width].count(b";") != n for c in sep_cols):
            return None
        if any(tokens[c::width].count(name) != n for c, name in name_cols):
            return None
        numbers = tokens[0::width]
        if not all(map(bytes.isdigit, numbers)):
            return None
        column_major: list[bytes] = []
        for c in value_cols:
            column_major += tokens[c::width]
        try:
            frames = fastnumbers.try_array(numbers, dtype=np.int64)
            values = fastnumbers.try_array(column_major, dtype=np.float64).reshape(len(value_cols), n).T
        except (ValueError, OverflowError):
            return None
        if not np.all(np.isfinite(values)):
            return None
        frames_out.append(frames)
        values_out.append(values)
        pos = cut
    if not frames_out:
        return None
    all_frames = np.concatenate(frames_out)
    if not np.all(np.diff(all_frames) >= 1):
        return None
    channels = np.empty((all_frames.size, layout.n_channels), dtype=np.float64)
    channels[:, value_dest] = np.concatenate(values_out)
    return all_frames, channels
