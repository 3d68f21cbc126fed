"""A recogniser's state (:meth:`Recognizer.state`), the form in which a stream moves between
cluster workers: a recogniser restored from it anywhere in a stream goes on exactly as the one it
was taken from (on random code streams through the compiled competition, automata included, and on
real recordings with the shipped library); a damaged or foreign state is refused, naming it."""

from __future__ import annotations

import dataclasses
import zlib
from functools import cache
from pathlib import Path
from typing import Any

import msgpack
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from daemon._dtw import Competition
from daemon.dtw import SCALE
from daemon.keyframes import KeyframeQuery
from daemon.library import Library, default_library_path, load_library
from daemon.recognizer import (
    CodeRecognizer,
    Detection,
    Recognizer,
    StateError,
    detect,
    detect_positions,
    plans,
)
from daemon.recordings import native_rate, read_recording
from daemon.types import FeatureSet, RecognitionSettings
from replay import JOINT_NAMES, Motion
from replay.kinematics import joint_positions
from tests.helpers import recording_pairs
from tests.synth import queries, random_class, stream_codes, streams

SESSION = "state"
PAIRS = recording_pairs()[:40:5]


@cache
def shipped() -> Library:
    return load_library(default_library_path())


@cache
def motion(pair: tuple[Path, Path]) -> Motion:
    return read_recording(*pair)


def moved(core: Competition | None) -> list[Any]:
    """A competition's state through the wire's encoding and back."""
    assert core is not None
    state: list[Any] = msgpack.unpackb(msgpack.packb(core.state()))
    return state


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    streams(shortest=20, longest=160),
    queries(tolerant=True),
    queries(),
    st.integers(0, 2**32 - 1),
    st.sampled_from([0.2, 0.5]),
    st.integers(1, 8),
    st.booleans(),
    st.integers(0, 6),
    st.sampled_from(["keyframes", "dtw"]),
    st.lists(st.floats(0, 1), max_size=4),
)
def test_a_competition_restored_anywhere_goes_on_as_the_uninterrupted_one(
    codes: dict[FeatureSet, list[int]],
    q1: KeyframeQuery,
    q2: KeyframeQuery,
    seed: int,
    tau: float,
    max_gap: int,
    compete: bool,
    hold: int,
    mode: str,
    cuts: list[float],
) -> None:
    """Random code streams, a keyframes-first class and one in ``mode``: moved to a fresh
    competition at each cut (through msgpack), the confirmations and the progress after each push
    are those of the stream pushed to one, and the fresh one's state equals the state it was given
    (runs shared as before)."""
    rng = np.random.default_rng(seed)
    classes = [
        dataclasses.replace(random_class("a", q1, rng, tau), mode="keyframes"),
        dataclasses.replace(random_class("b", q2, rng, tau), mode=mode),
    ]
    config = RecognitionSettings(max_gap_s=max_gap / 30.0, compete=compete, hold_s=hold / 30.0)
    class_plans = plans(Library(30.0, {c.name: c for c in classes}), config)
    stream = stream_codes(codes)
    at = {round(c * len(stream)) for c in cuts}

    def run(cut: set[int]) -> list[Any]:
        r = CodeRecognizer(class_plans, 30.0, config)
        out: list[Any] = []
        for j, c in enumerate([*stream, None]):
            if j in cut:
                state = moved(r.core)
                r = CodeRecognizer(class_plans, 30.0, config)
                assert r.core is not None
                r.core.restore(state)
                assert moved(r.core) == state
            found = r.flush() if c is None else r.push(c)
            out += [(p.name, m.start, m.end, round(m.cost * SCALE), j) for p, m, _ in found]
            if c is not None and r.core is not None:
                out.append(r.core.progress(1e-12))
        return out

    assert run(at) == run(set())


def pushed(r: Recognizer, frames: list[int], values: np.ndarray, cuts: set[int]) -> list[Detection]:
    """Each frame pushed, the recogniser moved to a fresh one (its bytes) before each frame of
    ``cuts`` (an index: ``len(frames)`` before the flush), then flushed."""
    out: list[Detection] = []
    for k, (number, v) in enumerate(zip(frames, values, strict=True)):
        if k in cuts:
            r = r.fresh("another").restored(r.state())
        out += r.push(number, v)
    if len(frames) in cuts:
        r = r.fresh("another").restored(r.state())
    return out + r.flush()


@settings(max_examples=12, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    st.sampled_from(PAIRS),
    st.sampled_from(["library", "keyframes", "dtw"]),
    st.lists(st.floats(0, 1), min_size=1, max_size=3),
)
def test_a_recogniser_restored_mid_recording_gives_detects_detections(
    pair: tuple[Path, Path], mode: str, cuts: list[float]
) -> None:
    """Real recordings, the shipped library: a stream moved at random frames to a recogniser of
    another session gives ``mocapd detect``'s detections, ids included (the state carries the
    session)."""
    m = motion(pair)
    rate = native_rate(m)
    config = RecognitionSettings(mode=mode)  # type: ignore[arg-type]
    want = detect(m, shipped(), rate, stream="s", session=SESSION, settings=config)
    r = Recognizer.for_skeleton(shipped(), m.skeleton, rate, stream="s", session=SESSION, settings=config)
    at = {round(c * len(m.frames)) for c in cuts}
    assert pushed(r, m.frames.tolist(), m.channels, at) == want


@pytest.mark.parametrize("rate", [None, 100.0], ids=["native", "100 Hz"])
def test_a_positions_recogniser_restored_mid_recording_gives_detects_detections(rate: float | None) -> None:
    """Also as a 100 Hz stream, moved before each of four frames in a row: one of them follows the
    frame whose pose the next index frame's instant is blended from (the state carries it)."""
    m = motion(PAIRS[0])
    rate = native_rate(m) if rate is None else rate
    positions = joint_positions(m)
    want = detect_positions(positions, m.frames, shipped(), rate, stream="s", session=SESSION)
    assert want
    r = Recognizer.for_positions(shipped(), JOINT_NAMES, rate, stream="s", session=SESSION)
    frames = m.frames.tolist()
    third = len(frames) // 3
    assert pushed(r, frames, positions, {third, third + 1, third + 2, third + 3, len(frames) // 2}) == want


def test_a_damaged_or_foreign_state_is_refused_and_changes_nothing() -> None:
    m = motion(PAIRS[0])
    rate = native_rate(m)
    library = shipped()
    r = Recognizer.for_skeleton(library, m.skeleton, rate, stream="s", session=SESSION)
    half = len(m.frames) // 2
    for number, v in zip(m.frames.tolist()[:half], m.channels[:half], strict=True):
        r.push(number, v)
    state = r.state()
    unpacked = msgpack.unpackb(zlib.decompress(state))
    codes = unpacked["codes"]
    foreign = {
        "a hold": Recognizer.for_skeleton(
            library, m.skeleton, rate, settings=RecognitionSettings(hold_s=1.0)
        ),
        "a rate": Recognizer.for_skeleton(library, m.skeleton, rate / 2),
        "positions": Recognizer.for_positions(library, JOINT_NAMES, rate),
    }
    for what, other in foreign.items():
        with pytest.raises(StateError, match="another library, settings, rate or input") as e:
            other.restored(state)
        assert e.value.field == "state.shape", what
    damaged = {
        "truncated": state[: len(state) // 2],
        "not compressed": b"\x00" * 40,
        "not a dict": zlib.compress(msgpack.packb([1, 2])),
        "another version": zlib.compress(msgpack.packb({**unpacked, "version": 99})),
        "a short ring": zlib.compress(
            msgpack.packb({**unpacked, "features": [*unpacked["features"][:4], unpacked["features"][4][:-8]]})
        ),
        "candidates cut": zlib.compress(
            msgpack.packb({**unpacked, "codes": [*codes[:7], b"\x01" * 12, *codes[8:]]})
        ),
        "no first frame": zlib.compress(msgpack.packb({k: v for k, v in unpacked.items() if k != "first"})),
    }
    for what, data in damaged.items():
        with pytest.raises(StateError) as e:
            r.restored(data)
        assert e.value.field.startswith("state"), what
    rest = list(zip(m.frames.tolist()[half:], m.channels[half:], strict=True))
    got = [d for number, v in rest for d in r.push(number, v)] + r.flush()
    want = detect(m, library, rate, stream="s", session=SESSION)
    assert [d for d in want if d.emitted_at_frame >= m.frames[half]] == got
