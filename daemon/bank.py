"""Many streams' recognisers in one: each :meth:`RecognizerBank.push` advances any number of streams
by one frame each (DESIGN.md, "Scale").

A stream is a :class:`~daemon.recognizer.Recognizer`; what made one Python call chain per stream too
slow (forward kinematics, the feature program, the keyframe automata and the DTW confirmation on
Python floats) runs in compiled code (:mod:`replay._kinematics`, :mod:`daemon._features`,
:mod:`daemon._automaton`, :mod:`daemon._dtw`), a few microseconds per frame. What is left per
stream is a handful of array operations; the bank does the one numpy function of the live path, the
cosines and sines of the half angles of forward kinematics, for the channel frames of all streams
in one pass, and checks each frame as the stream's recogniser does (a bad frame is reported as
``(stream, FrameError)`` and changes nothing). So the detections equal those of one
:class:`~daemon.recognizer.Recognizer` per stream bit for bit: the same objects do the same
operations on the same values.

Bounded state: per stream the recogniser's rings (poses, codes) and its automata's partial matches,
none growing with the frames pushed.

Pure: numpy in, dataclasses out; no I/O.
"""

from __future__ import annotations

import math
from collections.abc import Collection, Sequence
from dataclasses import dataclass
from itertools import accumulate

import numpy as np
import numpy.typing as npt

from daemon._live import push_channels_many
from daemon.library import Library
from daemon.recognizer import (
    ClassPlan,
    Detection,
    FrameError,
    Recognizer,
    check_native_rate,
    non_finite_channels,
    plans,
    skeleton_model,
)
from daemon.types import DEFAULT_HOLD_S, DEFAULT_MAX_GAP_S, FloatArray
from replay import Skeleton

Frame = tuple[str, int, npt.ArrayLike]
"""One stream's next frame: (stream, frame number, channels ``(C,)`` or joint positions ``(J, 3)``)."""


@dataclass(frozen=True)
class BankResult:
    """What one :meth:`RecognizerBank.push` gave: the detections emitted (in the order of the frames
    pushed, each stream's in the order its recogniser emits them) and the refused frames as
    (stream, :class:`FrameError`), in the order of the frames."""

    detections: tuple[Detection, ...]
    errors: tuple[tuple[str, FrameError], ...]


class RecognizerBank:
    """Recognisers of many streams, advanced together: :meth:`add` a stream (channels of a skeleton,
    or joint positions in a named order, at its native rate), :meth:`push` one frame of each of any
    number of streams, :meth:`remove` a stream (its last detections). Equal, stream by stream, to one
    :class:`~daemon.recognizer.Recognizer` per stream with the same settings and session."""

    def __init__(
        self,
        library: Library,
        *,
        max_gap_s: float = DEFAULT_MAX_GAP_S,
        classes: Collection[str] | None = None,
        compete: bool = True,
        hold_s: float = DEFAULT_HOLD_S,
    ) -> None:
        self.library = library
        self._hold_s = hold_s
        self._classes = None if classes is None else tuple(classes)
        self._max_gap_s = max_gap_s
        self._compete = compete
        self._plans: tuple[ClassPlan, ...] = plans(library, classes, max_gap_s=max_gap_s)
        self._streams: dict[str, Recognizer] = {}

    @property
    def streams(self) -> tuple[str, ...]:
        """The streams in the bank, in the order they were added."""
        return tuple(self._streams)

    @property
    def plans(self) -> tuple[ClassPlan, ...]:
        return self._plans

    def add(
        self,
        stream: str,
        native_rate: float,
        *,
        skeleton: Skeleton | None = None,
        joint_names: Sequence[str] | None = None,
        session: str | None = None,
    ) -> None:
        """Add ``stream``: frames of AMC-style channels of ``skeleton`` (as
        :meth:`Recognizer.for_skeleton`) or of joint positions in the order ``joint_names`` (as
        :meth:`Recognizer.for_positions`); ``session`` as :class:`Recognizer`'s (None: a new one).
        ValueError for a stream already in the bank, both or neither input, or a bad rate."""
        if stream in self._streams:
            raise ValueError(f"stream {stream!r} is already in the bank")
        self._streams[stream] = self.recognizer(
            stream, native_rate, skeleton=skeleton, joint_names=joint_names, session=session
        )

    def recognizer(
        self,
        stream: str,
        native_rate: float,
        *,
        skeleton: Skeleton | None = None,
        joint_names: Sequence[str] | None = None,
        session: str | None = None,
    ) -> Recognizer:
        """The recogniser :meth:`add` would add, not added (ValueError as :meth:`add`'s, but for a
        stream already in the bank): made before an old one is removed, nothing is lost when it
        cannot be made. :meth:`put` adds it."""
        if (skeleton is None) == (joint_names is None):
            raise ValueError("give a skeleton (channels) or the joint names (positions), not both")
        check_native_rate(native_rate)
        return Recognizer(
            self.library,
            float(native_rate),
            stream=stream,
            session=session,
            classes=self._classes,
            max_gap_s=self._max_gap_s,
            compete=self._compete,
            hold_s=self._hold_s,
            model=None if skeleton is None else skeleton_model(skeleton),
            joint_names=joint_names,
        )

    def put(self, stream: str, recognizer: Recognizer) -> None:
        """Add ``stream`` with a recogniser from :meth:`recognizer`; ValueError if it is in the bank."""
        if stream in self._streams:
            raise ValueError(f"stream {stream!r} is already in the bank")
        self._streams[stream] = recognizer

    def remove(self, stream: str) -> list[Detection]:
        """Take ``stream`` out of the bank: its remaining detections (as :meth:`Recognizer.flush`).
        KeyError if it is not in the bank."""
        return self._streams.pop(stream).flush()

    def push(self, frames: Sequence[Frame]) -> BankResult:
        """Advance each stream named in ``frames`` by its frame: the detections and the refused frames
        (a refused frame changes nothing). ValueError (nothing done) if a stream is not in the bank or
        has more than one frame."""
        names = [f[0] for f in frames]
        if len(set(names)) != len(names):
            raise ValueError("at most one frame per stream in one push")
        unknown = [n for n in names if n not in self._streams]
        if unknown:
            raise ValueError(f"streams not in the bank: {', '.join(map(repr, unknown))}")
        errors: list[tuple[int, str, FrameError]] = []
        checked: list[tuple[int, Recognizer, int, FloatArray]] = []
        for i, (name, number, frame) in enumerate(frames):
            r = self._streams[name]
            try:
                n, values = r._check(number, frame)
            except FrameError as e:
                errors.append((i, name, e))
            else:
                checked.append((i, r, n, values))
        codes: dict[int, int] = {}
        channels = [(i, r, n, values) for i, r, n, values in checked if r.model is not None]
        if channels:  # every channel frame's finiteness, trigonometry and frame step in one pass each
            flat = np.concatenate([values for _, _, _, values in channels])
            starts = list(accumulate((len(values) for _, _, _, values in channels[:-1]), initial=0))
            sums: list[float] = np.add.reduceat(flat, starts).tolist()
            if not all(map(math.isfinite, sums)):
                kept = []
                for item, total in zip(channels, sums, strict=True):
                    i, r, n, values = item
                    if math.isfinite(total) or np.isfinite(values).all():
                        kept.append(item)
                    else:
                        errors.append((i, r.stream, non_finite_channels(n, r.stream)))
                channels = kept
                flat = np.concatenate([values for _, _, _, values in channels]) if channels else flat[:0]
            half = 0.5 * flat
            found = push_channels_many([r._live for _, r, _, _ in channels], flat, np.cos(half), np.sin(half))
            codes = {i: code for (i, _, _, _), code in zip(channels, found, strict=True)}
        detections: list[Detection] = []
        for i, r, n, values in checked:
            code = codes.get(i) if r.model is not None else r._live.push_positions(values.reshape(-1))
            if code is None:
                continue  # refused above
            try:
                detections += r._after(n, code)
            except FrameError as e:
                errors.append((i, r.stream, e))
        errors.sort(key=lambda e: e[0])
        return BankResult(tuple(detections), tuple((name, e) for _, name, e in errors))
