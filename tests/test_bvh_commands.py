"""BVH everywhere a recording goes (issue 35, item 3): ``info``, ``positions``, ``features``,
``index build``, ``search --example`` and ``segment`` take ``--bvh`` (or a manifest's ``bvh``
column), each giving for a recording converted from ASF/AMC (``mocapd convert``) what it gives for
the AMC; and on Bandai Namco Research's takes (``bandai2``, CC BY-NC-ND 4.0, read unmodified) what
the library functions give."""

from __future__ import annotations

import csv
import dataclasses
import io
import json
from pathlib import Path

import numpy as np
import pytest

from daemon import behaviours as bh
from daemon.features import FEATURE_NAMES
from daemon.features.batch import features
from daemon.features.catalog import CATALOG, features_reading
from daemon.library import load_library
from daemon.recordings import read_bvh_features, read_example_rows, read_recording
from daemon.tools.repetitions import periodic_examples
from replay import JOINT_NAMES
from replay.bvh import read_bvh, write_bvh
from replay.rigs import bvh_standard_joints, read_bvh_take
from tests.helpers import DATA, assert_ok, mocapd, pair_id, recording_pairs

BANDAI = DATA / "bandai2"
WALK = BANDAI / "dataset-2_walk_normal_001.bvh.gz"


@pytest.fixture(scope="module")
def converted(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path, Path]:
    """CMU 86_01 (a long take of several behaviours): its ASF, its AMC, and its BVH."""
    asf, amc = next(p for p in recording_pairs() if pair_id(p) == "86_01")
    out = tmp_path_factory.mktemp("convert") / "86_01.bvh.gz"
    assert_ok(mocapd("convert", "--asf", asf, "--amc", amc, "--out", out))
    return asf, amc, out


def test_features_of_a_converted_recording_are_the_amcs(converted: tuple[Path, Path, Path]) -> None:
    asf, amc, bvh = converted
    from_bvh = mocapd("features", "--bvh", bvh, "--csv", "-", "--fps", "30")
    from_amc = mocapd("features", "--asf", asf, "--amc", amc, "--csv", "-", "--fps", "30")
    assert_ok(from_bvh)
    bvh_rows, amc_rows = from_bvh.stdout.splitlines(), from_amc.stdout.splitlines()
    assert bvh_rows[0] == amc_rows[0] == ",".join(("frame", *FEATURE_NAMES))
    first = int(read_recording(asf, amc).frames[0])
    # the same bits; the BVH numbers its frames from 1, the AMC from its first frame number
    assert len(bvh_rows) == len(amc_rows) > 100
    for b, a in zip(bvh_rows[1:], amc_rows[1:], strict=True):
        fb, bits_b = b.split(",", 1)
        fa, bits_a = a.split(",", 1)
        assert (int(fb) - 1, bits_b) == (int(fa) - first, bits_a)


def test_positions_and_info_of_a_bandai2_take() -> None:
    got = mocapd("positions", "--bvh", WALK, "--csv", "-")
    assert_ok(got)
    rows = list(csv.reader(io.StringIO(got.stdout)))
    take = read_bvh_take(WALK)
    assert rows[0] == ["frame", "joint", "x", "y", "z"]
    assert len(rows) - 1 == len(take.frames) * len(JOINT_NAMES)
    assert rows[1][:2] == ["1", "root"]
    assert np.allclose([float(v) for v in rows[1][2:]], take.joints[0, 0], atol=1e-6)
    info = mocapd("info", "--bvh", WALK, "--json")
    assert_ok(info)
    summary = json.loads(info.stdout)
    assert (summary["frames"], summary["frame_rate_hz"], summary["rig_map"]) == (
        len(take.frames),
        30.0,
        "upperarm",
    )
    assert summary["derived"]["lfingers"] == list(features_reading("lfingers"))
    assert "handLeftHighVel" in summary["derived"]["lfingers"] and summary["derived"]["lthumb"] == []


@pytest.mark.parametrize("joint", ["headtop", "lfingers", "rthumb", "ltoes", "lclavicle"])
def test_features_reading_a_joint_are_the_only_ones_moving_it_changes(joint: str) -> None:
    """Moving one joint of a real take far about (each frame by another offset) changes only the
    features :func:`features_reading` names for it."""
    take = read_bvh_take(WALK)
    base = features(take.joints, JOINT_NAMES, take.rate)
    moved = take.joints.copy()
    rng = np.random.default_rng(1)
    moved[:, JOINT_NAMES.index(joint)] += rng.normal(scale=60.0, size=(len(moved), 3))
    changed = {
        CATALOG[k].name for k in np.flatnonzero((features(moved, JOINT_NAMES, take.rate) != base).any(axis=0))
    }
    assert changed <= set(features_reading(joint))


def test_index_build_takes_a_bvh_manifest_and_search_a_bvh_example(tmp_path: Path) -> None:
    takes = [BANDAI / f"dataset-2_{a}_normal_001.bvh.gz" for a in ("walk", "run", "raise-up-both-hands")]
    manifest = tmp_path / "takes.csv"
    manifest.write_text("bvh,style\n" + "".join(f"{p},normal\n" for p in takes), encoding="utf-8")
    built = mocapd("index", "build", "--manifest", manifest, "--out", tmp_path / "idx")
    assert built.returncode == 0 and "documents:  3" in built.stdout, built.stderr
    wanted = read_bvh_features(takes[2], 30.0)
    assert (
        f"frames:     {sum(len(read_bvh_features(p, 30.0).frames) for p in takes)} at 30 Hz" in built.stdout
    )
    found = mocapd(
        "search",
        "--index",
        tmp_path / "idx",
        "--example",
        takes[2],
        "1",
        str(len(wanted.frames)),
        "--features",
        "handRightRaisedRelSpine,handLeftRaisedRelSpine",
        "--json",
    )
    assert found.returncode == 0, found.stderr
    hits = [json.loads(line) for line in found.stdout.splitlines()]
    assert hits and any(h["document"].endswith(takes[2].name) and h["start_frame"] == 1 for h in hits)
    assert (
        mocapd(
            "search", "--index", tmp_path / "idx", "--example", takes[2], "1", "--features", "x"
        ).returncode
        == 2
    )


def test_segment_cuts_a_converted_recording_where_it_cuts_the_amc(converted: tuple[Path, Path, Path]) -> None:
    """The rig's 13 joints are the paper's bones but ``lowerback`` (at the root, no joint of its
    own): the cuts of the BVH are those of the AMC from the same bones."""
    asf, amc, bvh = converted
    motion = read_recording(asf, amc)
    take = read_bvh(bvh)
    rig = bh.RigRotations(take.hierarchy, bvh_standard_joints(take)[1])
    joints = bh.JointRotations(motion.skeleton, [b for b in bh.PAPER_BONES if b != "lowerback"])
    assert rig.bones == ("upperback", "thorax", "head", "lhumerus", "lradius", "rhumerus", "rradius",
                         "lfemur", "ltibia", "lfoot", "rfemur", "rtibia", "rfoot")  # fmt: skip
    order = [joints.bones.index(b) for b in rig.bones]
    want = joints(motion.channels).reshape(len(motion), -1, 4)[:, order]
    assert np.abs(rig(take.channels).reshape(len(take.channels), -1, 4) - want).max() < 1e-9
    got = mocapd("segment", "--bvh", bvh, "--json")
    assert_ok(got)
    cuts = [json.loads(line)["frame"] for line in got.stdout.splitlines()]
    result = bh.analyse(
        joints(motion.channels)[:, np.ravel([[4 * k + c for c in range(4)] for k in order])], 120.0, "ppca"
    )
    assert cuts == [b.frame + 1 for b in result.boundaries] and cuts


@pytest.mark.parametrize("name", ["walk_normal_001", "wave-both-hands_active_002"])
def test_a_rigs_rotation_stream_gives_the_batch_frames_bit_for_bit(name: str) -> None:
    """A BVH rig's joint rotations one frame at a time (the daemon's segmentation of a BVH stream)
    equal the batch's (``segment --bvh``), a flush in the middle starting a new stream."""
    take = read_bvh(BANDAI / f"dataset-2_{name}.bvh.gz")
    rig = bh.RigRotations(take.hierarchy, bvh_standard_joints(take)[1])
    stream = rig.stream()
    half = len(take.channels) // 2
    for piece in (take.channels[:half], take.channels[half:]):
        got = [v for c in piece for v in stream.push(c)] + stream.flush()
        assert np.array_equal(np.array(got), rig(piece))


def test_a_take_in_metres_is_recognised_as_in_centimetres(tmp_path: Path) -> None:
    """The features are scale-free (every threshold a multiple of a body length), so a studio's
    BVH in metres gives the detections of the same take in centimetres."""
    take = read_bvh(BANDAI / "dataset-2_wave-both-hands_normal_001.bvh.gz")
    metres = np.array(take.channels)
    columns = [k for k, name in enumerate(take.hierarchy.channel_names) if name.endswith("position")]
    metres[:, columns] *= 0.01
    joints = tuple(
        dataclasses.replace(j, offset=(0.01 * j.offset[0], 0.01 * j.offset[1], 0.01 * j.offset[2]))
        for j in take.hierarchy.joints
    )
    hierarchy = dataclasses.replace(take.hierarchy, joints=joints)
    (tmp_path / "m.bvh").write_bytes(
        write_bvh(dataclasses.replace(take, hierarchy=hierarchy, channels=metres))
    )
    in_m = mocapd("detect", "--bvh", tmp_path / "m.bvh", "--json", "--stream", "s")
    in_cm = mocapd(
        "detect", "--bvh", BANDAI / "dataset-2_wave-both-hands_normal_001.bvh.gz", "--json", "--stream", "s"
    )
    assert_ok(in_m)

    def found(output: str) -> list[tuple[str, int, int]]:
        return [(r["class"], r["start_frame"], r["end_frame"]) for r in map(json.loads, output.splitlines())]

    assert found(in_m.stdout) == found(in_cm.stdout) and found(in_cm.stdout)


@pytest.mark.slow  # 11 s: two mocapd learn runs on twelve takes
def test_learn_cuts_takes_of_a_periodic_action_into_single_repetitions(tmp_path: Path) -> None:
    """``mocapd learn`` with its defaults on whole takes: walking (a periodic action) is learned from
    the first 2 single repetitions of each take, each named by its frames and equal to those rows of
    the take's features; the turning walks and the raised hands stay whole takes. With
    ``--repetitions 0`` every class is learned from the whole takes."""
    actions = ("walk", "walk-turn-left", "raise-up-both-hands")
    rows = [
        f"{a},{BANDAI / f'dataset-2_{a}_{s}_00{t}.bvh.gz'},{s}"
        for a in actions
        for s in ("active", "normal")
        for t in (1, 2)
    ]
    manifest = tmp_path / "takes.csv"
    manifest.write_text("\n".join(["class,bvh,actor", *rows]) + "\n", encoding="utf-8")
    result = mocapd("learn", "--manifest", manifest, "--out", tmp_path / "lib")
    assert result.returncode == 0, result.stderr
    cut = [line for line in result.stderr.splitlines() if line.startswith("[repetitions]")]
    assert cut == ["[repetitions] walk: 4 of 4 examples cut into 8 single repetitions"]
    library = load_library(tmp_path / "lib")
    examples = periodic_examples(read_example_rows(manifest), 30.0, 2)
    walks = library.classes["walk"].training
    assert walks == tuple(clip for clip, _ in examples["walk"])
    assert len(walks) == 8 and all(c.amc == walks[2 * (i // 2)].amc for i, c in enumerate(walks))
    for clip, matrix in examples["walk"]:
        whole = read_bvh_features(clip.amc, 30.0).matrix
        assert clip.frames == clip.end_frame - clip.start_frame + 1 and clip.frames < len(whole)
        assert np.array_equal(matrix, whole[clip.start_frame - 1 : clip.end_frame])
        assert 0.5 * 30 <= clip.frames <= 2 * 30  # one step cycle: about a second
    for name in actions[1:]:
        assert [(c.start_frame, c.frames) for c in library.classes[name].training] == [
            (1, len(read_bvh_features(c.amc, 30.0).matrix)) for c in library.classes[name].training
        ]
    plain = mocapd("learn", "--manifest", manifest, "--out", tmp_path / "whole", "--repetitions", "0")
    assert plain.returncode == 0 and "[repetitions]" not in plain.stderr
    assert len(load_library(tmp_path / "whole").classes["walk"].training) == 4
