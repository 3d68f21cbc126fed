"""The multi-stream bank equals one :class:`Recognizer` per stream (and the batch twin ``detect``), bit
for bit: real recordings (CMU and HDM05; channels of two skeleton topologies, joint positions in
another joint order, a stream at 60 Hz) joining and leaving at random ticks, pushed in random
interleavings with bad frames among them; detections (every field) and refused frames (problem and
message) agree push by push. Streams join after others and leave at any time, and ids can come
back."""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from functools import cache
from pathlib import Path

import numpy as np
import numpy.typing as npt
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from daemon.bank import RecognizerBank
from daemon.library import Library
from daemon.recognizer import Detection, FrameError, Recognizer, detect, detect_positions
from daemon.recordings import read_recording
from daemon.types import FloatArray
from replay import JOINT_NAMES, Bone, Motion, Skeleton
from replay.kinematics import joint_positions
from tests.helpers import DATA, hdm05_clip, small_library, takes

SESSION = "bank-test"


@pytest.fixture(scope="module")
def library(tmp_path_factory: pytest.TempPathFactory) -> Library:
    return small_library(tmp_path_factory.mktemp("lib"))


# ------------------------------------------------------------------------------------- streams


@dataclass
class Source:
    """A stream's input: frames ``(number, values)`` at ``rate`` Hz, channels of ``skeleton`` or
    joint positions named ``joint_names``."""

    rate: float
    frames: list[tuple[int, FloatArray]]
    skeleton: Skeleton | None = None
    joint_names: tuple[str, ...] | None = None

    def recognizer(self, library: Library, stream: str, session: str) -> Recognizer:
        if self.skeleton is not None:
            return Recognizer.for_skeleton(library, self.skeleton, self.rate, stream=stream, session=session)
        assert self.joint_names is not None
        return Recognizer.for_positions(library, self.joint_names, self.rate, stream=stream, session=session)

    def add_to(self, bank: RecognizerBank, stream: str, session: str) -> None:
        bank.add(stream, self.rate, skeleton=self.skeleton, joint_names=self.joint_names, session=session)


@cache
def motion(asf: Path, amc: Path) -> Motion:
    return read_recording(asf, amc)


def channels(asf: Path, amc: Path, limit: int) -> Source:
    m = motion(asf, amc)
    return Source(120.0, list(zip(m.frames[:limit].tolist(), m.channels[:limit], strict=True)), m.skeleton)


def with_prop(asf: Path, amc: Path, limit: int) -> Source:
    """Channels of the recording's skeleton with an extra one-dof leaf bone under the head (another
    topology: 63 channels, 32 nodes), the prop's angle swinging."""
    m = motion(asf, amc)
    s = m.skeleton
    prop = Bone(
        "prop", None, (0.0, 1.0, 0.0), 3.0, (0.0, 0.0, 0.3), "XYZ", ("rx",), ((-math.pi, math.pi),), 0
    )
    skeleton = dataclasses.replace(
        s, bones=(*s.bones, prop), parents=(*s.parents, s.node_names.index("head"))
    )
    angle = np.sin(np.arange(len(m)) / 10.0)[:, None]
    values = np.concatenate([m.channels, angle], axis=1)[:limit]
    return Source(120.0, list(zip(m.frames[:limit].tolist(), values, strict=True)), skeleton)


def positions(asf: Path, amc: Path, limit: int, every: int = 1) -> Source:
    """Joint positions in a shuffled order with an extra joint, every ``every``-th frame (at 120 /
    ``every`` Hz), numbered from 1."""
    p = joint_positions(motion(asf, amc))[::every][:limit]
    order = np.random.default_rng(7).permutation(len(JOINT_NAMES))
    names = (*(JOINT_NAMES[i] for i in order), "prop")
    values = np.concatenate([p[:, order], np.full((len(p), 1, 3), 5.0)], axis=1)
    return Source(120.0 / every, list(enumerate(values, 1)), joint_names=names)


@cache
def sources() -> dict[str, Source]:
    cmu_02 = (DATA / "cmu" / "02" / "02.asf", DATA / "cmu" / "02" / "02_01.amc.gz")
    cmu_13 = (DATA / "cmu" / "13" / "13.asf", DATA / "cmu" / "13" / "13_29.amc.gz")
    return {
        "cmu02": channels(*cmu_02, 260),
        "bd-squat": channels(*hdm05_clip("bd", "squat1Reps", takes("squat1Reps", "bd")[3]), 400),
        "bk-hop-prop": with_prop(
            *hdm05_clip("bk", "hopBothLegs1hops", takes("hopBothLegs1hops", "bk")[4]), 400
        ),
        "cmu13-positions": positions(*cmu_13, 220),
        "dg-squat-60hz": positions(*hdm05_clip("dg", "squat1Reps", takes("squat1Reps", "dg")[0]), 400, 2),
    }


# ------------------------------------------------------------------------------- the simulation


BAD = ("short", "long", "nan", "inf", "repeat", "back", "jump", "float", "text", "huge")


def damaged(kind: str, source: Source, i: int) -> tuple[object, object] | None:
    """Frame ``i`` of ``source`` made bad by ``kind`` as (number, values); None where ``kind`` makes
    no bad frame there."""
    number, values = source.frames[i]
    bad = values.copy()
    if kind == "short":
        return number, values[:-1]
    if kind == "long":
        return number, np.concatenate([values, values[:1]])
    if kind in ("nan", "inf", "huge"):
        if source.skeleton is not None:
            if kind == "huge":  # a root translation that overflows in forward kinematics
                bad[source.skeleton.channel_names.index("root.tx")] = 1e308
            else:
                bad[i % len(bad)] = np.nan if kind == "nan" else -np.inf
        elif kind == "huge":
            return None  # huge positions are finite
        else:
            assert source.joint_names is not None  # a used joint, not the prop
            bad[source.joint_names.index(JOINT_NAMES[i % len(JOINT_NAMES)]), i % 3] = np.nan
        return number, bad
    if kind == "float":
        return float(number), values
    if kind == "text":
        return str(number), values
    if kind == "jump":  # any number starts a stream
        return (number + 1 + i % 3, values) if i > 0 else None
    if kind == "repeat":
        return (number - 1, values) if i > 0 else None
    return (number - 2 - i % 3, values) if i > 1 else None  # back


@dataclass
class Plan:
    """When a stream joins (tick), how far it gets before it leaves (frames), how often it gets a
    frame in a tick, and the bad frames pushed before its frame ``i``."""

    source: str
    join: int
    leave: int
    chance: float
    bad: dict[int, list[str]] = field(default_factory=dict)


def simulate(library: Library, plans: dict[str, Plan], seed: int) -> RecognizerBank:
    """Runs the plans through one bank and through one recogniser per stream, checking every push;
    returns the (emptied) bank."""
    rng = np.random.default_rng(seed)
    bank = RecognizerBank(library)
    recognizers: dict[str, Recognizer] = {}
    at: dict[str, int] = {}
    pending_bad: dict[str, dict[int, list[str]]] = {}
    tick = 0
    done: set[str] = set()
    while len(done) < len(plans):
        for name, plan in plans.items():
            if plan.join == tick:
                session = f"{SESSION}-{name}"
                sources()[plan.source].add_to(bank, name, session)
                recognizers[name] = sources()[plan.source].recognizer(library, name, session)
                at[name] = 0
                pending_bad[name] = {i: list(kinds) for i, kinds in plan.bad.items()}
        frames: list[tuple[str, int, npt.ArrayLike]] = []
        expected: dict[str, list[Detection]] = {}
        expected_errors: list[tuple[str, str, str]] = []
        leaving = []
        names = list(at)
        rng.shuffle(names)
        for name in names:
            plan, source = plans[name], sources()[plans[name].source]
            if rng.random() >= plan.chance:
                continue
            i = at[name]
            kinds = pending_bad[name].get(i, [])
            bad = None
            while kinds and bad is None:
                bad = damaged(kinds.pop(), source, i)
            if bad is not None:
                number, values = bad
                with pytest.raises(FrameError) as caught:
                    recognizers[name].push(number, values)  # type: ignore[arg-type]
                expected_errors.append((name, caught.value.problem, str(caught.value)))
                frames.append((name, number, values))  # type: ignore[arg-type]
                continue
            number, values = source.frames[i]
            expected[name] = recognizers[name].push(number, values)
            frames.append((name, number, values))
            at[name] = i + 1
            if at[name] == min(plan.leave, len(source.frames)):
                leaving.append(name)
        result = bank.push(frames)
        assert [(s, e.problem, str(e)) for s, e in result.errors] == expected_errors
        for name, dets in expected.items():
            assert [d for d in result.detections if d.stream == name] == dets, (name, tick)
        assert {d.stream for d in result.detections} <= set(expected)
        for name in leaving:
            assert bank.remove(name) == recognizers[name].flush(), name
            del at[name]
            done.add(name)
        tick += 1
    assert bank.streams == ()
    return bank


@settings(max_examples=15, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    st.integers(0, 2**32 - 1),
    st.lists(
        st.tuples(st.sampled_from(sorted(sources())), st.integers(0, 200), st.sampled_from(BAD)), max_size=6
    ),
)
def test_bank_equals_one_recognizer_per_stream(
    library: Library, seed: int, bad: list[tuple[str, int, str]]
) -> None:
    rng = np.random.default_rng(seed)
    plans = {}
    for name, source in sources().items():
        n = len(source.frames)
        leave = n if rng.random() < 0.5 else int(rng.integers(1, n))  # else mid-stream
        plans[name] = Plan(name, int(rng.integers(0, 60)), leave, float(rng.uniform(0.6, 1.0)))
    for name, i, kind in bad:
        plans[name].bad.setdefault(i, []).append(kind)
    simulate(library, plans, seed)


def test_join_leave_any_time(library: Library) -> None:
    """Streams join after others and leave at any time (one id comes back with a new session), and
    the detections still equal the recognisers'. Misuse changes nothing."""
    plans = {
        "long": Plan("bd-squat", 0, 400, 1.0),
        "early-leaver": Plan("cmu02", 5, 90, 1.0),
        "late": Plan("bk-hop-prop", 150, 400, 0.9),
        "positions": Plan("cmu13-positions", 20, 220, 0.95),
        "slow": Plan("dg-squat-60hz", 40, 200, 0.5),
    }
    # a sequence of short-lived streams, one after another
    plans |= {f"brief{k}": Plan("cmu02", 10 + 25 * k, 25 + 2 * k, 1.0) for k in range(12)}
    simulate(library, plans, 3)

    source = sources()["bd-squat"]
    bank = RecognizerBank(library)
    source.add_to(bank, "a", SESSION)
    with pytest.raises(ValueError, match="already in the bank"):
        source.add_to(bank, "a", SESSION)
    number, values = source.frames[0]
    with pytest.raises(ValueError, match="at most one frame"):
        bank.push([("a", number, values), ("a", number + 1, values)])
    with pytest.raises(ValueError, match="not in the bank"):
        bank.push([("a", number, values), ("b", number, values)])
    reference = source.recognizer(library, "a", SESSION)
    got: list[Detection] = []
    want: list[Detection] = []
    for k, (_, values) in enumerate(source.frames * 6):  # a squat six times, renumbered
        got += bank.push([("a", k + 1, values)]).detections
        want += reference.push(k + 1, values)
    got += bank.remove("a")
    assert got == want + reference.flush()
    assert len([d for d in got if d.class_name == "squat1Reps"]) >= 4
    m = motion(*hdm05_clip("bd", "squat1Reps", takes("squat1Reps", "bd")[3]))
    six = np.array([values for _, values in source.frames * 6])
    renumbered = Motion(m.source, m.skeleton, m.header, np.arange(1, len(six) + 1), six)
    assert got == detect(renumbered, library, 120.0, stream="a", session=SESSION)  # and its batch twin
    with pytest.raises(KeyError):
        bank.remove("a")
    # the id comes back as a new stream, frame numbers from 1 again
    source.add_to(bank, "a", "another")
    assert bank.push([("a", 1, source.frames[0][1])]).errors == ()


@pytest.mark.parametrize("name", ["bd-squat", "cmu13-positions"])
def test_a_restart_is_a_flush_then_a_fresh_recogniser(library: Library, name: str) -> None:
    """``restart`` gives what ``remove`` gives, then the stream goes on as one added anew under the
    new session would, on the same kinematic model (not made again)."""
    source = sources()[name]
    half = len(source.frames) // 2
    bank, reference = RecognizerBank(library), RecognizerBank(library)
    source.add_to(bank, "a", SESSION)
    source.add_to(reference, "a", SESSION)
    for number, values in source.frames[:half]:
        assert bank.push([("a", number, values)]) == reference.push([("a", number, values)])
    model = bank["a"].model
    assert bank.restart("a", "again") == reference.remove("a")
    assert bank["a"].model is model
    source.add_to(reference, "a", "again")
    seen: list[Detection] = []
    for number, (_, values) in enumerate(source.frames[half:] + source.frames, start=source.frames[half][0]):
        got = bank.push([("a", number, values)])
        assert got == reference.push([("a", number, values)])
        seen += got.detections
    last = bank.remove("a")
    assert last == reference.remove("a")
    if name == "bd-squat":  # the squat is found again after the restart
        assert [d.class_name for d in seen + last].count("squat1Reps") >= 1


# ------------------------------------------------------------------ many streams, the batch twin


def as_given(values: FloatArray, k: int) -> npt.ArrayLike:
    """A frame in one of the forms a caller may send: an array, a list, a strided view, Fortran
    order (the last three through the recogniser's own checks, not the compiled fast path)."""
    form = k % 4
    if form == 1:
        listed: npt.ArrayLike = values.tolist()
        return listed
    if form == 2:
        return np.repeat(values, 2, axis=0)[::2]
    if form == 3:
        return np.asfortranarray(values)
    return values


def batch_twin(
    library: Library, source: Source, frames: list[tuple[int, FloatArray]], name: str
) -> list[Detection]:
    """:func:`detect` (or :func:`detect_positions`) of ``frames`` of ``source``."""
    numbers = np.array([n for n, _ in frames])
    values = np.array([v for _, v in frames])
    if source.skeleton is not None:
        m = motion(DATA / "cmu" / "02" / "02.asf", DATA / "cmu" / "02" / "02_01.amc.gz")
        played = Motion(m.source, source.skeleton, m.header, numbers, values)
        return detect(played, library, source.rate, stream=name, session=SESSION)
    assert source.joint_names is not None
    standard = values[:, [source.joint_names.index(j) for j in JOINT_NAMES]]
    return detect_positions(standard, numbers, library, source.rate, stream=name, session=SESSION)


def test_blocks_of_streams_equal_the_batch_twin(library: Library) -> None:
    """More streams of one skeleton than one block of the compiled step holds (32), streams of another
    skeleton, positions at 120 Hz and at 60 Hz (another feature program), joining at different
    ticks, each from another frame of its recording, frames in the forms a caller may send: each
    stream's detections (and what leaving gives) equal :func:`detect` on its frames, bit for bit."""
    plan = (
        [("bd-squat", k) for k in range(40)]
        + [("bk-hop-prop", k) for k in range(3)]
        + [("cmu13-positions", k) for k in range(3)]
        + [("dg-squat-60hz", k) for k in range(3)]
    )
    bank = RecognizerBank(library)
    played: dict[str, list[tuple[int, FloatArray]]] = {}
    for k, (name, _) in enumerate(plan):
        frames = sources()[name].frames
        shift = (37 * k) % len(frames)
        played[f"{name}/{k}"] = [(j + 1, v) for j, (_, v) in enumerate(frames[shift:] + frames[:shift])]
    got: dict[str, list[Detection]] = {s: [] for s in played}
    left: set[str] = set()
    tick = 0
    while len(left) < len(plan):
        frames_now: list[tuple[str, int, npt.ArrayLike]] = []
        for k, (name, _) in enumerate(plan):
            stream = f"{name}/{k}"
            at = tick - k % 7
            if at == 0:
                sources()[name].add_to(bank, stream, SESSION)
            if 0 <= at < len(played[stream]):
                number, values = played[stream][at]
                frames_now.append((stream, number, as_given(values, k)))
            elif at == len(played[stream]):
                got[stream] += bank.remove(stream)
                left.add(stream)
        result = bank.push(frames_now)
        assert result.errors == ()
        for d in result.detections:
            got[d.stream].append(d)
        tick += 1
    for k, (name, _) in enumerate(plan):
        stream = f"{name}/{k}"
        assert got[stream] == batch_twin(library, sources()[name], played[stream], stream), stream
    assert sum(len(d) for d in got.values()) >= 30  # squats were found


def test_push_many_takes_a_recogniser_once(library: Library) -> None:
    """Two frames of one recogniser in one step are refused before anything is done."""
    source = sources()["bd-squat"]
    r = source.recognizer(library, "a", SESSION)
    reference = source.recognizer(library, "a", SESSION)
    (n1, v1), (n2, v2) = source.frames[:2]
    with pytest.raises(ValueError, match="at most one frame"):
        Recognizer.push_many([(r, n1, v1), (r, n2, v2)])
    for number, values in source.frames:
        assert r.push(number, values) == reference.push(number, values)
    assert r.flush() == reference.flush()


def test_a_frame_number_beyond_int64_is_refused(library: Library) -> None:
    source = sources()["cmu13-positions"]
    r = source.recognizer(library, "a", SESSION)
    _, values = source.frames[0]
    with pytest.raises(FrameError, match="out of range") as caught:
        r.push(2**70, values)
    assert caught.value.problem == "type"
    r.push(1, values)  # nothing changed: the stream starts at the next good frame
    with pytest.raises(FrameError) as jumped:
        r.push(2**64, values)
    assert jumped.value.problem == "jump"


def test_the_class_stage_state_is_bounded(library: Library) -> None:
    """A squat played twelve times: the compiled competition's candidates, detections and keyframe
    ranges remembered are the same after the eighth and the twelfth (what is older than its reach is
    forgotten), and its DTW keeps three columns whatever the length."""
    source = sources()["bd-squat"]
    r = source.recognizer(library, "a", SESSION)
    core = r._stage.codes.core
    assert core is not None
    sizes = []
    for rep in range(12):
        for j, (_, values) in enumerate(source.frames):
            r.push(rep * len(source.frames) + j + 1, values)
        sizes.append(core.state_size)
    assert sizes[7] == sizes[11] and max(sizes) > 0
    assert core.dtw.n == core.n  # every index frame a column, none kept beyond three
