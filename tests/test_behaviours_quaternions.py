"""The frame vectors of behaviour segmentation (daemon.behaviours.quaternions; Barbič et al. 2004,
§3): each joint's rotation relative to its parent as a quaternion, signs consistent over time, the
stream equal to the batch bit for bit; root angles past ±180° and input that is not finite."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from daemon.behaviours.quaternions import PAPER_BONES, JointRotations, RotationStream
from daemon.types import FloatArray
from replay.asf import ROTATION_DOFS
from replay.kinematics import KinematicModel, quaternion_matrix
from tests.behaviour_data import REAL, SETTINGS, frames, motion


def test_cmu_frames_are_the_quaternions_of_the_papers_fourteen_joints() -> None:
    skeleton = motion("86_01").skeleton
    rotations = JointRotations(skeleton)
    assert set(rotations.bones) == set(PAPER_BONES) and rotations.dims == 56  # the paper's R^56
    rotating = [b.name for b in skeleton.bones if set(b.dofs) & set(ROTATION_DOFS)]
    every = JointRotations(skeleton, rotating)
    assert len(every.bones) == 28 and every.dims == 112
    assert "root" not in every.bones
    assert not {"lhipjoint", "rhipjoint"} & set(every.bones)  # bones without dofs
    assert {"lfemur", "rtibia", "thorax", "head", "lhumerus", "rfingers"} <= set(every.bones)
    with pytest.raises(ValueError, match="no rotating bone nose"):
        JointRotations(skeleton, ["lfemur", "nose"])


def test_each_quaternion_is_the_bones_rotation_relative_to_its_parent() -> None:
    """The rotation matrix of bone k's quaternion is ``G_parent^T G_k`` of forward kinematics."""
    m = motion("86_01")
    rotations = JointRotations(m.skeleton)
    channels = m.channels[::500]
    q = frames("86_01")[::500].reshape(len(channels), -1, 4)
    glob = KinematicModel(m.skeleton).rotations(channels)
    parents = m.skeleton.parents
    for j, node in enumerate(rotations.nodes):
        local = np.einsum("nji,njk->nik", glob[:, parents[node]], glob[:, node])
        assert np.allclose(quaternion_matrix(q[:, j].T), local, atol=1e-12)


def check_sign_consistency(x: FloatArray, raw: FloatArray) -> None:
    q = x.reshape(raw.shape[0], -1, 4)
    assert np.allclose(np.linalg.norm(q, axis=2), 1.0)
    assert np.all((q == raw) | (q == -raw))
    assert np.all((q[1:] * q[:-1]).sum(axis=2) >= 0.0)
    first = q[0][np.arange(raw.shape[1]), np.argmax(q[0] != 0, axis=1)]
    assert np.all(first > 0)


@pytest.mark.parametrize("trial", REAL)
def test_the_stream_gives_the_batch_frames_bit_for_bit_on_real_recordings(trial: str) -> None:
    m = motion(trial)
    rotations = JointRotations(m.skeleton)
    batch = frames(trial)
    stream = rotations.stream()
    assert np.array_equal(np.array([stream.frame(c) for c in m.channels]), batch)
    raw = rotations.raw(m.channels)
    check_sign_consistency(batch, raw)


@SETTINGS
@given(st.integers(0, 2**32 - 1), st.integers(1, 60), st.integers(0, 40))
def test_the_stream_gives_the_batch_frames_for_random_channels(seed: int, n: int, split: int) -> None:
    """Angles anywhere in ±720° (sign flips galore), a flush in the middle starts a new stream."""
    m = motion("86_01")
    rotations = JointRotations(m.skeleton)
    rng = np.random.default_rng(seed)
    channels = rng.uniform(-4 * np.pi, 4 * np.pi, size=(n, rotations.width))
    channels[rng.random(n) < 0.3] = 0.0  # T-poses: every bone at the identity
    stream: RotationStream = rotations.stream()
    split = min(split, n)
    for piece in (channels[:split], channels[split:]):
        got = [v for c in piece for v in stream.push(c)] + stream.flush()
        expected = rotations(piece)
        assert np.array_equal(np.array(got).reshape(expected.shape), expected)
        if len(piece):
            raw = rotations.raw(piece)
            check_sign_consistency(expected, raw)
            if len(piece) >= 10:  # the raw quaternions do flip, so the rule is exercised
                assert np.any((raw[1:] * raw[:-1]).sum(axis=2) < 0)


@pytest.mark.parametrize("trial", ["86_01", "135_06"])
def test_root_angles_past_180_degrees_change_nothing(trial: str) -> None:
    m = motion(trial)
    names = m.skeleton.channel_names
    root = [i for i, name in enumerate(names) if name in ("root.rx", "root.ry", "root.rz")]
    assert np.abs(m.channels[:, root]).max() > np.pi  # the case is real
    wrapped = m.channels.copy()
    wrapped[:, root] = np.angle(np.exp(1j * wrapped[:, root]))
    wrapped[:, [names.index(f"root.t{a}") for a in "xyz"]] = 0.0
    rotations = JointRotations(m.skeleton)
    assert np.array_equal(rotations(wrapped), frames(trial))
    assert np.all(np.isfinite(frames(trial)))


def test_channels_that_are_not_finite_are_refused() -> None:
    m = motion("86_01")
    rotations = JointRotations(m.skeleton)
    channels = m.channels[:50].copy()
    channels[17, 9] = np.nan
    with pytest.raises(ValueError, match="frame 17"):
        rotations(channels)
    stream = rotations.stream()
    for c in channels[:17]:
        stream.frame(c)
    with pytest.raises(ValueError, match=r"frame 17.*not finite"):
        stream.frame(channels[17])
    with pytest.raises(ValueError, match="shape"):
        stream.frame(channels[18, :-1])
    # The refused frames left the stream as it was.
    rest = np.array([stream.frame(c) for c in channels[18:]])
    good = np.delete(channels, 17, axis=0)
    assert np.array_equal(rest, rotations(good)[17:])
