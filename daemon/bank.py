"""Many streams' recognisers in one: each :meth:`RecognizerBank.push` advances any number of streams
by one frame each (DESIGN.md, "Scale").

A stream is a :class:`~daemon.recognizer.Recognizer`; a push is one compiled call,
:func:`daemon._live.push_many` (:meth:`~daemon.recognizer.Recognizer.push_many` of the frames),
that steps all the frames in passes over contiguous arrays: the frames looked up and checked (the
usual frame, the next number with contiguous doubles of the stream's shape, in C; anything else
through the recogniser's Python checks); the channel frames side by side for one numpy cosine and
one sine of their half angles; forward kinematics by blocks of up to 32 streams of one skeleton,
every step over the block (:meth:`replay._kinematics.FrameKinematics.joints_many`); each pose into
its features' ring; the feature program by blocks of up to 32 frames, every instruction over the
block (:meth:`daemon._features.Bytecode.run_many`); then per stream the hysteresis, the decimation
to the library's rate and, for an index-rate code, the compiled competition
(:class:`daemon._dtw.Competition`: every template's stream-wide DTW column, the keyframe automata,
the candidates, their hold and publication on C arrays). Python runs per frame only to hand out a
detection, to refuse a bad frame (reported as ``(stream, FrameError)``, changing nothing) and at a
stream's first frame. A single recogniser's push is the same call over its one frame, so the
detections equal those of one :class:`~daemon.recognizer.Recognizer` per stream bit for bit, and
those of the batch twin :func:`~daemon.recognizer.detect` (tests): every frame's operations are
the same in the same order whatever block it is stepped in.

Bounded state: per stream the recogniser's rings (poses, codes), three DTW columns per template, its
automata's partial matches and the candidates of the last :func:`~daemon.recognizer.reach` frames,
none growing with the frames pushed; the blocks' registers are one buffer shared by all streams.

Pure: numpy in, dataclasses out; no I/O.
"""

from __future__ import annotations

import dataclasses
from collections import OrderedDict
from collections.abc import Sequence
from dataclasses import dataclass

import numpy.typing as npt

from daemon._live import push_many
from daemon.library import Library
from daemon.recognizer import (
    DEFAULT_SETTINGS,
    ClassPlan,
    Detection,
    FrameError,
    Recognizer,
    plans,
    skeleton_model,
)
from daemon.types import RecognitionSettings
from replay import KinematicModel, Skeleton

MODELS_KEPT = 64
"""How many skeletons' forward kinematics a bank keeps for new streams."""

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
    :class:`~daemon.recognizer.Recognizer` per stream with the same ``settings`` and session."""

    def __init__(self, library: Library, settings: RecognitionSettings = DEFAULT_SETTINGS) -> None:
        self.library = library
        self.settings = settings
        self._plans: tuple[ClassPlan, ...] = plans(library, settings)
        self._streams: dict[str, Recognizer] = {}
        self._models: OrderedDict[Skeleton, KinematicModel] = OrderedDict()  # least recently used first

    @property
    def streams(self) -> tuple[str, ...]:
        """The streams in the bank, in the order they were added."""
        return tuple(self._streams)

    def __getitem__(self, stream: str) -> Recognizer:
        """The recogniser of ``stream``; KeyError if it is not in the bank."""
        return self._streams[stream]

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
        rate, settings = float(native_rate), self.settings
        if skeleton is not None:
            return Recognizer(
                self.library,
                rate,
                settings=settings,
                stream=stream,
                session=session,
                model=self._model(skeleton),
            )
        assert joint_names is not None
        return Recognizer.for_positions(
            self.library, joint_names, rate, settings=settings, stream=stream, session=session
        )

    def _model(self, skeleton: Skeleton) -> KinematicModel:
        """The forward kinematics of ``skeleton`` (:func:`~daemon.recognizer.skeleton_model`), made
        once for the bank's streams of skeletons equal but for their source (the last
        :data:`MODELS_KEPT`): the streams of one studio share a handful of skeletons, and the tables
        take milliseconds to make."""
        key = dataclasses.replace(skeleton, source="")
        model = self._models.pop(key, None) or skeleton_model(skeleton)
        self._models[key] = model
        if len(self._models) > MODELS_KEPT:
            self._models.popitem(last=False)
        return model

    def put(self, stream: str, recognizer: Recognizer) -> None:
        """Add ``stream`` with a recogniser from :meth:`recognizer`; ValueError if it is in the bank."""
        if stream in self._streams:
            raise ValueError(f"stream {stream!r} is already in the bank")
        self._streams[stream] = recognizer

    def remove(self, stream: str) -> list[Detection]:
        """Take ``stream`` out of the bank: its remaining detections (as :meth:`Recognizer.flush`).
        KeyError if it is not in the bank."""
        return self._streams.pop(stream).flush()

    def restart(self, stream: str, session: str | None = None) -> list[Detection]:
        """End ``stream``'s motion: its remaining detections (as :meth:`remove`), and a fresh
        recogniser of it under ``session`` (:meth:`Recognizer.fresh`). KeyError if it is not in the
        bank."""
        old = self._streams[stream]
        out = old.flush()
        self._streams[stream] = old.fresh(session)
        return out

    def restore(self, stream: str, state: bytes) -> None:
        """Put ``stream``'s recogniser in ``state`` (:meth:`Recognizer.state`, here or on another
        worker): :class:`~daemon.recognizer.StateError`, the recogniser unchanged, if it does not
        fit it. KeyError if it is not in the bank."""
        self._streams[stream] = self._streams[stream].restored(state)

    def push(self, frames: Sequence[Frame]) -> BankResult:
        """Advance each stream named in ``frames`` by its frame: the detections and the refused frames
        (a refused frame changes nothing). ValueError (nothing done) if a stream is not in the bank or
        has more than one frame."""
        detections, errors = push_many(
            frames if isinstance(frames, list) else list(frames), FrameError, self._streams
        )
        return BankResult(tuple(detections), tuple((frames[i][0], e) for i, e in errors))
