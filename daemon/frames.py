"""A stream's frame numbers, and every translation between them, in one place.

Three numberings (DESIGN.md, "A stream's life" and "Streaming confirmation"):

- *sequence numbers*, the source's, on the wire: they may have gaps (poses lost on the way, or
  dropped by a full queue);
- *frame numbers*, the recogniser's, at the stream's native rate and consecutive within one motion:
  a motion's first pose keeps its sequence number, each pose after it takes the next frame number
  (a bridged gap is closed up; :class:`Renumbering`);
- *index frames*, at the library's rate, counted from 0 at the motion's first frame: every
  ``step``-th frame (the toolbox's ``1:4:end`` at 120 Hz, reference facts section 0), whose
  features come out ``delay`` frames after it (the velocity windows are centred;
  :func:`daemon.features.latency_frames`) (:class:`FrameClock`).
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass

from daemon.errors import InputError
from daemon.features import decimation_factor, latency_frames
from daemon.types import MAX_NATIVE_RATE


def check_native_rate(rate: float) -> None:
    """ValueError unless ``rate`` (Hz) is one features are computed at."""
    if not (math.isfinite(rate) and 0 < rate <= MAX_NATIVE_RATE):
        raise InputError(f"native rate must be in (0, {MAX_NATIVE_RATE:g}] Hz, got {rate}")


@dataclass(frozen=True)
class FrameClock:
    """Frame numbers ↔ index frames of one motion whose first frame is ``first`` (an argument of
    each translation): index frame ``j`` is frame ``first + j·step``, and its features are known
    when frame ``first + j·step + delay`` is pushed (the motion's last frame, if that comes first).
    ``step`` >= 1, ``delay`` >= 0."""

    step: int
    delay: int

    def __post_init__(self) -> None:
        if self.step < 1 or self.delay < 0:
            raise ValueError(f"a frame clock needs step >= 1 and delay >= 0, got {self.step}, {self.delay}")

    @classmethod
    def of(cls, native_rate: float, index_rate: float) -> FrameClock:
        """The clock of a stream at ``native_rate`` Hz for a library at ``index_rate`` Hz; ValueError
        unless features are computed at ``native_rate`` and ``index_rate`` divides it."""
        check_native_rate(native_rate)
        return cls(decimation_factor(native_rate, index_rate), latency_frames(native_rate))

    def start(self, first: int, j: int) -> int:
        """The frame number of index frame ``j``."""
        return first + j * self.step

    def index(self, first: int, number: int) -> int:
        """The index frame that frame ``number`` (>= ``first``) falls in: the last one at or before it."""
        return (number - first) // self.step

    def span(self, first: int, start: int, end: int, now: int) -> tuple[int, int]:
        """Index frames ``start .. end`` (inclusive) as frame numbers: from index frame ``start``'s
        frame to the frame before index frame ``end + 1``'s, capped by frame ``now`` (the one being
        pushed: at the motion's end it can come first)."""
        return self.start(first, start), min(self.start(first, end + 1) - 1, now)

    def known(self, first: int, j: int, last: int) -> int:
        """The frame whose push gives index frame ``j``'s features, in a motion ending at frame
        ``last``: ``delay`` frames after it, or ``last`` (the motion's end gives the rest)."""
        return min(self.start(first, j) + self.delay, last)

    def lag(self, index_frames: int) -> int:
        """Frames from an index frame to the push that gives the features of the index frame
        ``index_frames`` after it: ``index_frames·step + delay``."""
        return index_frames * self.step + self.delay


class Renumbering:
    """A stream's frame numbers for its sequence numbers: :meth:`frame` numbers each pose fed to the
    recogniser, :meth:`seq` maps a frame number back (a frame at most ``horizon`` frames before the
    last one numbered). Frame ``f`` has sequence number ``f + offset`` with the offset of the last
    change at or before ``f``; a change is kept while a frame within the horizon needs it, so the
    state is bounded by the gaps in ``horizon`` frames."""

    def __init__(self, horizon: int) -> None:
        self.horizon = horizon
        self._changes: deque[tuple[int, int]] = deque()  # (first frame, seq - frame from it on)
        self._next = 0

    def frame(self, seq: int, *, first: bool) -> int:
        """The frame number of the pose with sequence number ``seq`` fed next: ``seq`` itself if it
        is the ``first`` of a motion, else the one after the last numbered (or after the last
        :meth:`refused`)."""
        if first:
            self._changes.clear()
            self._next = seq
        frame = self._next
        changes = self._changes
        if changes and changes[-1][0] == frame:
            changes.pop()  # a refused pose's, numbered the same
        if not changes or changes[-1][1] != seq - frame:
            changes.append((frame, seq - frame))
        self._next = frame + 1
        while len(changes) > 1 and changes[1][0] < frame - self.horizon:
            changes.popleft()
        return frame

    def __len__(self) -> int:
        """The changes kept."""
        return len(self._changes)

    def refused(self, frame: int) -> None:
        """The pose numbered ``frame`` (the last) did not reach the recogniser: the next pose takes
        its number."""
        self._next = frame

    def seq(self, frame: int) -> int:
        """The sequence number of frame ``frame`` (numbered, and within the horizon)."""
        offset = 0
        for start, value in self._changes:
            if start > frame:
                break
            offset = value
        return frame + offset
