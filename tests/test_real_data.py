"""Every real recording in ../shared/data/mocap: both readers, forward kinematics, rigid bones."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from replay import KinematicModel, iter_amc, read_amc, read_asf
from tests.helpers import pair_id, recording_pairs


def test_every_subject_and_actor_is_covered() -> None:
    names = [amc.name for _, amc in recording_pairs()]
    assert len(recording_pairs()) >= 200
    assert any(n.startswith("14_") for n in names)
    for actor in ("bd", "bk", "dg"):
        assert any(n.startswith(f"HDM_{actor}_") for n in names)
    assert all(asf.is_file() for asf, _ in recording_pairs())


@pytest.mark.slow
@pytest.mark.parametrize("pair", recording_pairs(), ids=pair_id)
def test_recording(pair: tuple[Path, Path]) -> None:
    asf, amc = pair
    skeleton = read_asf(asf)
    motion = read_amc(amc, skeleton)
    n = len(motion)
    assert n > 0
    assert np.array_equal(motion.frames, np.arange(1, n + 1))

    streamed = list(iter_amc(amc, skeleton))
    assert [f.frame for f in streamed] == motion.frames.tolist()
    assert np.array_equal(np.stack([f.channels for f in streamed]), motion.channels)

    model = KinematicModel(skeleton)
    for unit, scale in (("asf", 1.0), ("cm", 2.54 / skeleton.length_unit)):
        pos = model.positions(motion.channels, unit)  # type: ignore[arg-type]
        assert pos.shape == (n, len(skeleton.bones) + 1, 3)

        # The root is the AMC root translation (plus the ASF root position, zero here), scaled alike.
        root = np.zeros((n, 3))
        for axis, name in enumerate(("tx", "ty", "tz")):
            root[:, axis] = motion.channels[:, skeleton.channel_names.index(f"root.{name}")]
        expected_root = (root + np.array(skeleton.root.position)) * scale
        assert np.allclose(pos[:, 0], expected_root, rtol=1e-12, atol=1e-12 * scale)

        # Rigid bones: every node keeps its ASF bone length from its parent node in every frame.
        parents = np.array(skeleton.parents[1:])
        lengths = np.array([b.length for b in skeleton.bones]) * scale
        dist = np.linalg.norm(pos[:, 1:] - pos[:, parents], axis=2)
        assert np.all(np.abs(dist - lengths) <= 1e-9 * np.maximum(lengths, 1e-300))

    # One frame at a time gives the batch values bit for bit (every 10th frame and the last).
    batch = model.positions(motion.channels)
    for i in [*range(0, n, 10), n - 1]:
        assert np.array_equal(model.positions_frame(motion.channels[i]), batch[i])
    local = model.local_rotations(motion.channels)
    for i in [*range(0, n, 10), n - 1]:
        assert np.array_equal(model.local_rotations_frame(motion.channels[i]), local[i])
