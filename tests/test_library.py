"""Template libraries and ranked retrieval on real HDM05 clips: the training manifest (errors name file
and line), frame ranges cut from whole-clip features, the library format round trip and its errors
(naming file and field), and template search equal to a per-document subsequence DTW read off the
cost matrix, with and without keyframe pre-selection."""

from __future__ import annotations

import dataclasses
import hashlib
import json
import re
import shutil
from pathlib import Path

import numpy as np
import numpy.typing as npt
import pytest

from daemon.dtw import pack
from daemon.errors import FileAccessError
from daemon.keyframes import KeyframeQuery, parse_keyframe_queries
from daemon.learn.library import learn_class, save_library
from daemon.library import (
    DTW,
    GATED,
    LEARNED,
    PUBLISHED,
    Calibration,
    ClassTemplate,
    Library,
    LibraryFormatError,
    Variant,
    default_library_path,
    load_library,
)
from daemon.recordings import ManifestError, ManifestRow, read_examples, read_training_manifest
from daemon.search.retrieval import TemplateHits, frame_codes, template_search
from daemon.search.store import MotionIndex, index_from_matrices, read_document
from tests.helpers import HDM_AMC, HDM_ASF, KEYFRAMES, TRAINING, hdm05_clip, training_rows, write_training
from tests.naive import template_brute_force

DATABASE = [
    ("hopBothLegs1hops", "dg", 22),
    ("squat1Reps", "dg", 25),
    ("squat1Reps", "dg", 26),
    ("kickLFront1Reps", "dg", 13),
    ("depositFloorR", "dg", 13),
]


@pytest.fixture(scope="module")
def library(tmp_path_factory: pytest.TempPathFactory) -> Library:
    where = tmp_path_factory.mktemp("lib")
    examples = read_examples(write_training(where / "clips.csv", training_rows(TRAINING)))
    classes = {name: learn_class(name, items) for name, items in examples.items()}
    return Library(30.0, classes)


@pytest.fixture(scope="module")
def database() -> tuple[MotionIndex, list[npt.NDArray[np.bool_]]]:
    docs, matrices = [], []
    for c, a, t in DATABASE:
        asf, amc = hdm05_clip(a, c, t)
        row = ManifestRow(0, "asf", str(amc), asf, amc)
        document, matrix = read_document(row)
        docs.append(document)
        matrices.append(matrix)
    return index_from_matrices(matrices, docs, 30.0), matrices


# ----------------------------------------------------------------------------------- training data


def test_manifest_classes_and_ranges(tmp_path: Path) -> None:
    hop = hdm05_clip("bd", "hopBothLegs1hops", 1)[1]
    rows = [f"hop,{HDM_ASF},{hop},,", f"hop.part,{HDM_ASF},{hop},5,40"]
    items = read_training_manifest(write_training(tmp_path / "m.csv", rows))
    assert [(i.name, i.start_frame, i.end_frame) for i in items] == [("hop", None, None), ("hop.part", 5, 40)]
    examples = read_examples(tmp_path / "m.csv")
    (whole_clip, whole), (part_clip, part) = examples["hop"][0], examples["hop.part"][0]
    # features over the whole recording, then the samples (AMC frames 1, 5, 9, ...) inside 5..40
    assert (part_clip.start_frame, part_clip.end_frame) == (5, 40)
    assert part_clip.frames == len(range(5, 41, 4)) == part.shape[0]
    np.testing.assert_array_equal(part, whole[1:10])
    assert whole_clip.frames == whole.shape[0]


@pytest.mark.parametrize(
    ("row", "message"),
    [
        ("bad/name,{asf},{amc},,", "class 'bad/name'"),
        ("hop,{asf},{amc},5,", "give both start_frame and end_frame"),
        ("hop,{asf},{amc},x,9", "start_frame 'x' is not an integer"),
        ("hop,{asf},{amc},9,5", "start_frame 9 is after end_frame 5"),
        ("hop,{asf},{amc},1,100000", "outside the recording's"),
        ("hop,{asf},{amc},2,4", "hold no sample at 30 Hz"),
    ],
)
def test_manifest_errors_name_file_and_line(tmp_path: Path, row: str, message: str) -> None:
    hop = hdm05_clip("bd", "hopBothLegs1hops", 1)[1]
    good = f"hop,{HDM_ASF},{hop},,"
    path = write_training(tmp_path / "m.csv", [good, row.format(asf=HDM_ASF, amc=hop)])
    with pytest.raises(ManifestError, match=f"^{re.escape(str(path))}:3: .*{re.escape(message)}") as err:
        read_examples(path)
    assert str(err.value).startswith(f"{path}:3: ") and message in str(err.value)


def test_manifest_needs_a_class_column(tmp_path: Path) -> None:
    path = write_training(tmp_path / "m.csv", [f"{HDM_ASF},{HDM_AMC}"], "asf,amc")
    with pytest.raises(ManifestError, match=r":1: header lacks the column 'class'"):
        read_training_manifest(path)


# ------------------------------------------------------------------------------------------ format


def assert_same_class(a: ClassTemplate, b: ClassTemplate) -> None:
    for kind in ("soft", "quantised", "hard"):
        np.testing.assert_array_equal(getattr(a, kind).values, getattr(b, kind).values)
        np.testing.assert_array_equal(getattr(a, kind).weights, getattr(b, kind).weights)
    assert (a.name, a.tau, a.delta, a.steps, a.iterations, a.training) == (
        b.name,
        b.tau,
        b.delta,
        b.steps,
        b.iterations,
        b.training,
    )
    assert a.keyframes == b.keyframes


def test_library_round_trip(library: Library, tmp_path: Path) -> None:
    save_library(library, tmp_path / "lib")
    loaded = load_library(tmp_path / "lib")
    assert loaded.rate == library.rate and list(loaded.classes) == list(library.classes)
    for name in library.classes:
        assert_same_class(library.classes[name], loaded.classes[name])
    save_library(loaded, tmp_path / "lib")  # an existing library is replaced
    assert sorted(p.name for p in (tmp_path / "lib").iterdir()) == [
        "hopBothLegs1hops.npz",
        "library.json",
        "squat1Reps.npz",
    ]
    with pytest.raises(KeyError, match=r"no class 'walk' .* \(it has hopBothLegs1hops, squat1Reps\)"):
        loaded.get("walk")


def test_library_keeps_keyframes_and_provenance(library: Library) -> None:
    hop = library.classes["hopBothLegs1hops"]
    assert isinstance(hop.keyframes, KeyframeQuery) and len(hop.keyframes.keyframes) == 3
    assert [c.amc for c in hop.training] == [
        str(hdm05_clip("bd", "hopBothLegs1hops", t)[1]) for t in (1, 2, 3)
    ]
    assert hop.quantised.length == hop.soft.length
    assert set(np.unique(hop.quantised.values)) <= {0.0, 0.5, 1.0}


def test_library_not_written_over_other_files(library: Library, tmp_path: Path) -> None:
    (tmp_path / "lib").mkdir()
    (tmp_path / "lib" / "notes.txt").write_text("mine")
    with pytest.raises(FileAccessError, match=r"is not a mocapd template library, not replaced$"):
        save_library(library, tmp_path / "lib")
    assert (tmp_path / "lib" / "notes.txt").read_text() == "mine"


def test_library_keyframe_source_and_extra_files(library: Library, tmp_path: Path) -> None:
    published = parse_keyframe_queries(json.loads(KEYFRAMES.read_text()), KEYFRAMES)["squat1Reps"]
    squat = dataclasses.replace(library.classes["squat1Reps"], keyframes=published, keyframe_source=PUBLISHED)
    lib = tmp_path / "lib"
    save_library(Library(30.0, {**library.classes, "squat1Reps": squat}), lib, {"notes.csv": "a,b\n"})
    assert (lib / "notes.csv").read_text() == "a,b\n"
    meta = json.loads((lib / "library.json").read_text())
    assert meta["version"] == 4 and meta["classes"]["squat1Reps"]["keyframe_source"] == "published"
    # learned keyframes write no field: a version 3 library as it was before the field loads as learned
    assert "keyframe_source" not in meta["classes"]["hopBothLegs1hops"]
    loaded = load_library(lib)
    assert loaded.classes["squat1Reps"].keyframe_source == PUBLISHED
    assert loaded.classes["hopBothLegs1hops"].keyframe_source == LEARNED
    kf = loaded.classes["squat1Reps"].keyframes
    assert kf is not None and kf.keyframes == published.keyframes
    edit_json(lib, {"classes/squat1Reps/keyframe_source": "guessed"})
    with pytest.raises(LibraryFormatError, match=r"classes\.squat1Reps\.keyframe_source: must be one of"):
        load_library(lib)
    with pytest.raises(ValueError, match="plain name"):
        save_library(library, tmp_path / "other", {"library.json": "{}"})
    with pytest.raises(ValueError, match="keyframe_source"):
        dataclasses.replace(squat, keyframe_source="guessed")


def test_library_keeps_keyframe_mismatches(library: Library, tmp_path: Path) -> None:
    """A keyframe's ``mismatches`` is written only where it is not 0 and loads back; the shipped
    library, whose keyframes are exact, is written byte for byte as it ships."""
    hop = library.classes["hopBothLegs1hops"]
    assert hop.keyframes is not None
    first, *rest = hop.keyframes.keyframes
    tolerant = dataclasses.replace(first, mismatches=first.max_mismatches)
    assert tolerant.mismatches > 0
    query = dataclasses.replace(hop.keyframes, keyframes=(tolerant, *rest))
    lib = tmp_path / "lib"
    save_library(
        Library(30.0, {**library.classes, "hopBothLegs1hops": dataclasses.replace(hop, keyframes=query)}), lib
    )
    meta = json.loads((lib / "library.json").read_text())
    entries = meta["classes"]["hopBothLegs1hops"]["keyframes"]
    assert [e.get("mismatches") for e in entries] == [tolerant.mismatches] + [None] * len(rest)
    assert all("mismatches" not in e for e in meta["classes"]["squat1Reps"]["keyframes"])
    loaded = load_library(lib)
    assert loaded.classes["hopBothLegs1hops"].keyframes == query
    assert_same_class(loaded.classes["squat1Reps"], library.classes["squat1Reps"])
    edit_json(lib, {"classes/hopBothLegs1hops/keyframes/0/mismatches": 99})
    with pytest.raises(
        LibraryFormatError, match=r"classes\.hopBothLegs1hops\.keyframes\[0\]\.mismatches: must be"
    ):
        load_library(lib)
    save_library(load_library(default_library_path()), tmp_path / "shipped")
    for path in sorted(default_library_path().glob("*.*")):
        if path.suffix in (".json", ".npz"):
            assert (tmp_path / "shipped" / path.name).read_bytes() == path.read_bytes(), path.name


def edit_json(lib: Path, change: dict[str, object]) -> None:
    meta = json.loads((lib / "library.json").read_text())
    for path, value in change.items():
        *parents, key = path.split("/")
        node = meta
        for p in parents:
            node = node[int(p)] if isinstance(node, list) else node[p]
        node[key] = value
    (lib / "library.json").write_text(json.dumps(meta))


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ({"version": 1}, "library.json: version: this mocapd reads version 2, 3, 4, got 1; learn it again"),
        ({"format": "x"}, "library.json: format: must be 'mocapd-templates', got 'x'"),
        ({"features": ["a"]}, "library.json: features: not the 39 features"),
        ({"classes/squat1Reps/tau": -1}, "classes.squat1Reps.tau: must be a positive number, got -1"),
        (
            {"classes/squat1Reps/steps": "x"},
            "classes.squat1Reps.steps: must be one of thesis, toolbox, got 'x'",
        ),
        (
            {"classes/squat1Reps/file": "x.npz"},
            "classes.squat1Reps.file: must be 'squat1Reps.npz', got 'x.npz'",
        ),
        ({"classes/squat1Reps/sha256/hard": 3}, "classes.squat1Reps.sha256.hard: must be a non-empty string"),
        ({"classes/squat1Reps/training": [{"asf": "a"}]}, "classes.squat1Reps.training[0]: missing"),
        (
            {"classes/squat1Reps/keyframes": [{"set": "arms", "values": [0], "position": 0}]},
            "classes.squat1Reps.keyframes[0].set: must be one of lower, upper, mix, got 'arms'",
        ),
    ],
)
def test_library_json_errors_name_field(
    library: Library, tmp_path: Path, change: dict[str, object], message: str
) -> None:
    save_library(library, tmp_path / "lib")
    edit_json(tmp_path / "lib", change)
    where = re.escape(str(tmp_path / "lib" / "library.json"))
    reason = re.escape(message.removeprefix("library.json: "))
    with pytest.raises(LibraryFormatError, match=f"^{where}: .*{reason}") as err:
        load_library(tmp_path / "lib")
    assert str(err.value).startswith(str(tmp_path / "lib" / "library.json")) and message in str(err.value)


def test_library_array_errors_name_file(library: Library, tmp_path: Path) -> None:
    lib = tmp_path / "lib"
    save_library(library, lib)
    shutil.copy(lib / "squat1Reps.npz", tmp_path / "good.npz")
    with np.load(tmp_path / "good.npz") as npz:
        arrays = dict(npz)
    # another array of the same shape in its place: refused by its checksum ...
    np.savez(lib / "squat1Reps.npz", **{**arrays, "hard": arrays["quantised"]})
    with pytest.raises(
        LibraryFormatError, match=r"squat1Reps\.npz: hard: SHA-256 differs from library\.json's$"
    ):
        load_library(lib)
    # ... and values that cannot be a hard MT, with a matching checksum: refused by the values check
    bad = arrays["hard"] * 0.3
    np.savez(lib / "squat1Reps.npz", **{**arrays, "hard": bad})
    edit_json(lib, {"classes/squat1Reps/sha256/hard": hashlib.sha256(bad.tobytes()).hexdigest()})
    with pytest.raises(LibraryFormatError, match=r"squat1Reps\.npz: hard: values must be 0, 0\.5 or 1"):
        load_library(lib)
    np.savez(lib / "squat1Reps.npz", **{k: v for k, v in arrays.items() if k != "soft_weights"})
    with pytest.raises(LibraryFormatError, match=r"squat1Reps\.npz: missing arrays soft_weights"):
        load_library(lib)
    (lib / "squat1Reps.npz").unlink()
    with pytest.raises(LibraryFormatError, match=r"squat1Reps\.npz: missing"):
        load_library(lib)
    with pytest.raises(LibraryFormatError, match="not a mocapd template library"):
        load_library(tmp_path)


def test_library_v4_modes_and_member_templates(library: Library, tmp_path: Path) -> None:
    """Version 4 keeps how each class is recognised and why, and a class's other templates with
    their own τ and calibration; damaged, they are refused naming the field or the array."""
    squat, hop = library.classes["squat1Reps"], library.classes["hopBothLegs1hops"]
    variant = Variant(hop.quantised, 0.07, Calibration(0.07, "two styles", 2, 5, 1, 0.8, 1.0), (1,))
    two = dataclasses.replace(squat, mode=DTW, mode_reason="why not", keyframes=None, variants=(variant,))
    assert [
        (t is m, tau) for (t, tau), m in zip(two.members, (squat.quantised, hop.quantised), strict=True)
    ] == [
        (True, squat.tau),
        (True, 0.07),
    ]
    lib = tmp_path / "lib"
    save_library(Library(30.0, {"squat1Reps": two, "hopBothLegs1hops": hop}), lib)
    loaded = load_library(lib)
    got = loaded.classes["squat1Reps"]
    assert (got.mode, got.mode_reason, got.keyframes) == (DTW, "why not", None)
    (v,) = got.variants
    assert (v.tau, v.calibration, v.examples) == (variant.tau, variant.calibration, variant.examples)
    assert np.array_equal(v.quantised.values, hop.quantised.values)
    assert np.array_equal(v.quantised.weights, hop.quantised.weights)
    assert (
        loaded.classes["hopBothLegs1hops"].mode == GATED and loaded.classes["hopBothLegs1hops"].variants == ()
    )
    changes: list[tuple[dict[str, object], str]] = [
        ({"classes/squat1Reps/mode": "fast"}, r"classes\.squat1Reps\.mode: must be one of keyframes, dtw"),
        (
            {"classes/squat1Reps/mode": "keyframes"},
            r"classes\.squat1Reps\.mode: the keyframes mode needs keyframes",
        ),
        ({"classes/squat1Reps/members/0/examples": [0, 99]}, r"members\[0\]\.examples\[1\]: must be"),
        ({"classes/squat1Reps/members/0/tau": -1}, r"members\[0\]\.tau: must be"),
        ({"classes/squat1Reps/members": []}, r"sha256\.member1: unknown field"),
    ]
    for change, message in changes:
        save_library(Library(30.0, {"squat1Reps": two, "hopBothLegs1hops": hop}), lib)
        edit_json(lib, change)
        with pytest.raises(LibraryFormatError, match=message):
            load_library(lib)
    save_library(Library(30.0, {"squat1Reps": two}), lib)
    with np.load(lib / "squat1Reps.npz") as npz:
        arrays = dict(npz)
    np.savez(lib / "squat1Reps.npz", **{**arrays, "member1": arrays["quantised"]})
    with pytest.raises(LibraryFormatError, match=r"squat1Reps\.npz: member1: SHA-256 differs"):
        load_library(lib)
    with pytest.raises(ValueError, match="the keyframes mode needs keyframes"):
        dataclasses.replace(squat, keyframes=None, mode=GATED)


def test_library_v3_loads_as_gated_by_its_keyframes(library: Library, tmp_path: Path) -> None:
    """A version 3 library (no mode, no members) loads with every class gated by its keyframes, as
    it was recognised."""
    lib = tmp_path / "lib"
    save_library(library, lib)
    meta = json.loads((lib / "library.json").read_text())
    meta["version"] = 3
    for entry in meta["classes"].values():
        for key in ("mode", "mode_reason", "members"):
            del entry[key]
    (lib / "library.json").write_text(json.dumps(meta))
    loaded = load_library(lib)
    for name, cls in loaded.classes.items():
        assert cls.mode == GATED and cls.variants == () and cls.keyframes == library.classes[name].keyframes


# --------------------------------------------------------------------------------------- retrieval


def test_frame_codes_are_the_packed_features(
    database: tuple[MotionIndex, list[npt.NDArray[np.bool_]]],
) -> None:
    index, matrices = database
    np.testing.assert_array_equal(frame_codes(index), pack(np.concatenate(matrices)))


def rows(hits: TemplateHits) -> list[tuple[float, int, int, int]]:
    return list(
        zip(hits.cost.tolist(), hits.doc.tolist(), hits.start.tolist(), hits.end.tolist(), strict=True)
    )


@pytest.mark.parametrize("name", ["hopBothLegs1hops", "squat1Reps"])
def test_template_search_equals_per_document_dtw(
    library: Library, database: tuple[MotionIndex, list[npt.NDArray[np.bool_]]], name: str
) -> None:
    index, matrices = database
    cls = library.classes[name]
    hits = template_search(index, cls.quantised, tau=0.3)
    got = list(
        zip(hits.cost.tolist(), hits.doc.tolist(), hits.start.tolist(), hits.end.tolist(), strict=True)
    )
    whole = [(d, 0, m.shape[0] - 1) for d, m in enumerate(matrices)]
    assert got == template_brute_force(cls, matrices, 0.3, whole)
    assert hits.searched == index.n_frames and hits.keyframes is None
    limited = template_search(index, cls.quantised, tau=0.3, limit=2)
    assert len(limited) == min(2, len(hits)) and limited.cost.tolist() == hits.cost[:2].tolist()
    # the class's own clips are found at the thesis' threshold
    relevant = {d for d, (c, _, _) in enumerate(DATABASE) if c == name}
    assert relevant <= set(hits.doc[hits.cost <= 0.1].tolist())


def test_template_search_inside_keyframe_ranges(
    library: Library, database: tuple[MotionIndex, list[npt.NDArray[np.bool_]]]
) -> None:
    index, matrices = database
    cls = library.classes["squat1Reps"]
    published = parse_keyframe_queries(json.loads(KEYFRAMES.read_text()), "k")["squat1Reps"]
    hits = template_search(index, cls.quantised, tau=0.3, keyframes=published, extend=(3, 5))
    assert hits.keyframes is not None and len(hits.keyframes) > 0
    ranges = list(
        zip(
            hits.keyframes.doc.tolist(),
            hits.keyframes.start.tolist(),
            hits.keyframes.end.tolist(),
            strict=True,
        )
    )
    got = list(
        zip(hits.cost.tolist(), hits.doc.tolist(), hits.start.tolist(), hits.end.tolist(), strict=True)
    )
    assert got == template_brute_force(cls, matrices, 0.3, ranges)
    assert hits.searched == sum(e - s + 1 for _, s, e in ranges) < index.n_frames
    for _, d, s, e in got:
        assert any(d == rd and rs <= s <= e <= re for rd, rs, re in ranges)
