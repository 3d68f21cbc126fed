"""The motion index on disk: an I/O adapter around :mod:`daemon.search.index` (the pure inverted lists).

:func:`build_index` turns the recordings of a manifest into an index (each recording's features at
the index rate from :func:`daemon.recordings.read_features`); :func:`save_index` writes a directory::

    index.json            format, version 2, rate, base (the directory relative document paths are
                          relative to), documents, per set its bits, segment count and the SHA-256 of
                          each array
    <set>.<array>.npy     for set in lower, upper, mix and array in doc, start, length, code,
                          offsets, postings (int64, one dimension)

:func:`load_index` maps the arrays (``mmap_mode="r"``), checks each against its SHA-256 and checks
that they form an index of the documents (segments tile each document, codes fit the set, every
list holds exactly the segments of its code), so an index whose arrays were damaged, swapped or
edited is refused rather than answering wrongly.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Any

import numpy as np
from numpy.lib import format as npy_format

from daemon.checks import Checker
from daemon.errors import MocapdError
from daemon.features import SET_SLICES, sample_count
from daemon.frames import FrameClock
from daemon.recordings import ManifestRow, display_path, read_bvh_features, read_features
from daemon.search.index import SetIndex, build_set_index
from daemon.storage import check_target, checksum, read_meta, replace_directory, sync, write_json
from daemon.types import (
    DEFAULT_INDEX_RATE,
    DEFAULT_NATIVE_RATE,
    FEATURE_SETS,
    N_FEATURES,
    BoolArray,
    FeatureSet,
    IntArray,
)
from replay.rigs import BUILT_IN, RigMap

FORMAT = "mocapd-index"
VERSION = 2
INDEX_JSON = "index.json"
WHAT = "a mocapd index"
ARRAYS = ("doc", "start", "length", "code", "offsets", "postings")

Progress = Callable[[int, int, "Document"], object]


class IndexFormatError(MocapdError, ValueError):
    """An index directory that cannot be loaded; the message names the offending file (and field)."""


# ------------------------------------------------------------------------------------------- index


@dataclass(frozen=True)
class Document:
    """One indexed recording. ``amc``/``asf``: the paths as the manifest writes them; ``step`` AMC
    frames hold ``per`` index frames (lowest terms), index frame ``j`` (0-based, ``0 <= j < frames``)
    is AMC frame ``first_amc_frame + ceil(step * j / per)`` (:class:`daemon.frames.FrameClock`;
    every ``step``-th frame when ``per`` = 1); the recording has AMC frames ``first_amc_frame ..
    last_amc_frame`` at ``native_rate`` Hz."""

    amc: str
    asf: str
    first_amc_frame: int
    last_amc_frame: int
    step: int
    frames: int
    native_rate: float
    per: int = 1


@dataclass(frozen=True)
class MotionIndex:
    """Documents and the index of each feature set (``lower``, ``upper``, ``mix``) at ``rate`` Hz;
    segments' ``start``/``length`` count index-rate frames of their document. ``base``: the directory
    relative document paths are relative to (the manifest's; "" if unknown)."""

    rate: float
    documents: tuple[Document, ...]
    sets: Mapping[FeatureSet, SetIndex]
    base: str = ""

    @property
    def n_frames(self) -> int:
        """Index-rate frames over all documents."""
        return sum(d.frames for d in self.documents)

    def amc_frames(self, doc: int, start: int, end: int) -> tuple[int, int]:
        """AMC frame numbers of index-rate frames ``start .. end`` (inclusive, 0-based) of document
        ``doc``: the end reaches to the native frame before the next sample, at most the last."""
        d = self.documents[doc]
        if not 0 <= start <= end < d.frames:
            raise ValueError(f"frames {start}..{end} are outside 0..{d.frames - 1} of document {doc}")
        clock = FrameClock(d.step, 0, d.per)
        first = clock.start(d.first_amc_frame, start)
        return first, min(clock.start(d.first_amc_frame, end + 1) - 1, d.last_amc_frame)

    def document_path(self, doc: int) -> str:
        """Where document ``doc``'s AMC file is, for a reader in the working directory
        (:func:`~daemon.recordings.display_path`)."""
        return display_path(self.base, self.documents[doc].amc)


def index_from_matrices(
    matrices: Sequence[BoolArray], documents: Sequence[Document], rate: float, base: str = ""
) -> MotionIndex:
    """The index of documents given as feature matrices at the index rate, each shape
    ``(documents[d].frames, 39)``."""
    if len(matrices) != len(documents):
        raise ValueError(f"{len(matrices)} feature matrices for {len(documents)} documents")
    for d, (m, doc) in enumerate(zip(matrices, documents, strict=True)):
        if m.shape != (doc.frames, N_FEATURES):
            raise ValueError(
                f"document {d} ({doc.amc}): matrix shape {m.shape}, expected ({doc.frames}, {N_FEATURES})"
            )
        if not math.isclose(doc.native_rate * doc.per / doc.step, rate, rel_tol=1e-9):
            raise ValueError(
                f"document {d} ({doc.amc}): {doc.native_rate:g} Hz every {doc.step / doc.per:g} frames "
                f"is not {rate:g} Hz"
            )
    sets = {s: build_set_index(matrices, s) for s in FEATURE_SETS}
    return MotionIndex(float(rate), tuple(documents), sets, base)


def read_document(
    row: ManifestRow,
    *,
    rate: float = DEFAULT_INDEX_RATE,
    default_native_rate: float = DEFAULT_NATIVE_RATE,
    maps: Sequence[RigMap] = BUILT_IN,
) -> tuple[Document, BoolArray]:
    """One recording's :class:`Document` and its features at ``rate``, shape ``(frames, 39)``
    (:func:`daemon.recordings.read_features`; a BVH row's through the first of ``maps`` that fits,
    its frames from 1)."""
    if row.bvh is not None:
        got = read_bvh_features(row.bvh, rate, maps)
    else:
        got = read_features(row.asf, row.amc, rate, default_native_rate)
    document = Document(
        amc=row.amc_text,
        asf=row.asf_text,
        first_amc_frame=got.first_amc_frame,
        last_amc_frame=got.last_amc_frame,
        step=got.step,
        frames=int(got.matrix.shape[0]),
        native_rate=got.native_rate,
        per=got.per,
    )
    return document, got.matrix


def build_index(
    rows: Sequence[ManifestRow],
    *,
    rate: float = DEFAULT_INDEX_RATE,
    progress: Progress | None = None,
    default_native_rate: float = DEFAULT_NATIVE_RATE,
    base: str | Path = "",
    maps: Sequence[RigMap] = BUILT_IN,
) -> MotionIndex:
    """The index of the manifest's recordings at ``rate`` Hz; ``progress(done, total, document)`` is
    called after each recording; ``base``: the manifest's directory. Raises
    :class:`~replay.MocapFormatError` (unreadable file) or :class:`~daemon.recordings.RecordingError`
    (e.g. ``rate`` does not divide a recording's rate)."""
    documents: list[Document] = []
    matrices: list[BoolArray] = []
    for i, row in enumerate(rows, start=1):
        document, matrix = read_document(row, rate=rate, default_native_rate=default_native_rate, maps=maps)
        documents.append(document)
        matrices.append(matrix)
        if progress is not None:
            progress(i, len(rows), document)
    return index_from_matrices(matrices, documents, rate, str(Path(base).resolve()) if str(base) else "")


# ------------------------------------------------------------------------------------------ saving


def array_file(feature_set: str, array: str) -> str:
    """The file name of one array of one set, e.g. ``lower.postings.npy``."""
    return f"{feature_set}.{array}.npy"


def index_files() -> list[str]:
    """Every file of an index directory."""
    return [INDEX_JSON] + [array_file(s, a) for s in FEATURE_SETS for a in ARRAYS]


def index_bytes(path: str | Path, feature_set: str | None = None) -> int:
    """Bytes on disk of the index directory ``path``, or of one feature set's arrays."""
    names = index_files() if feature_set is None else [array_file(feature_set, a) for a in ARRAYS]
    return sum((Path(path) / name).stat().st_size for name in names)


def save_index(index: MotionIndex, path: str | Path) -> None:
    """Write ``index`` as the directory ``path``: built in a temporary sibling and renamed into place,
    so ``path`` never holds half an index. An existing index (or empty directory) at ``path`` is
    replaced; anything else there is left alone and raises
    :class:`~daemon.errors.FileAccessError`."""
    arrays = {
        s: {a: np.ascontiguousarray(getattr(index.sets[s], a), dtype=np.int64) for a in ARRAYS}
        for s in FEATURE_SETS
    }
    meta: dict[str, Any] = {
        "format": FORMAT,
        "version": VERSION,
        "rate": index.rate,
        "base": index.base,
        "documents": [
            {f.name: getattr(d, f.name) for f in fields(Document) if f.name != "per" or d.per != 1}
            for d in index.documents
        ],
        "sets": {
            s: {
                "bits": index.sets[s].bits,
                "segments": index.sets[s].n_segments,
                "sha256": {a: checksum(v) for a, v in arrays[s].items()},
            }
            for s in FEATURE_SETS
        },
    }

    def fill(temp: Path) -> None:
        for s in FEATURE_SETS:
            for a, values in arrays[s].items():
                with open(temp / array_file(s, a), "wb") as out:
                    np.save(out, values)
                    sync(out)
        write_json(temp / INDEX_JSON, meta)  # last: a directory with it is complete

    replace_directory(path, INDEX_JSON, WHAT, fill)


def check_index_target(path: str | Path) -> None:
    """Raise :class:`~daemon.errors.FileAccessError` (naming the path) unless :func:`save_index` may
    write ``path``: its directory exists and can be written, and ``path`` is absent, an empty
    directory or an index."""
    check_target(path, INDEX_JSON, WHAT)


# ----------------------------------------------------------------------------------------- loading


def load_index(path: str | Path) -> MotionIndex:
    """The index in directory ``path``, its arrays memory-mapped read-only (numpy memmaps). Raises
    :class:`IndexFormatError` naming the file (and field) if anything is missing, damaged or
    inconsistent."""
    path = Path(path)
    check, meta = read_meta(path, INDEX_JSON, WHAT, IndexFormatError)
    keys = {"format", "version", "rate", "base", "documents", "sets"}
    root = check.header(meta, keys, FORMAT, (VERSION,), "rebuild it with mocapd index build")
    rate = check.positive_number(root["rate"], "rate")
    if not isinstance(root["base"], str):
        check.fail("base", f"must be a directory path, got {root['base']!r:.60}")
    documents = _documents(check, root["documents"], rate)
    sets_meta = check.mapping(root["sets"], "sets", FEATURE_SETS)
    sets: dict[FeatureSet, SetIndex] = {}
    for s in FEATURE_SETS:
        entry = check.mapping(sets_meta[s], f"sets.{s}", ("bits", "segments", "sha256"))
        bits = check.integer(entry["bits"], f"sets.{s}.bits")
        expected_bits = SET_SLICES[s].stop - SET_SLICES[s].start
        if bits != expected_bits:
            check.fail(f"sets.{s}.bits", f"the {s} set has {expected_bits} bits, got {bits}")
        segments = check.integer(entry["segments"], f"sets.{s}.segments")
        sums = check.mapping(entry["sha256"], f"sets.{s}.sha256", ARRAYS)
        lengths = dict.fromkeys(("doc", "start", "length", "code", "postings"), segments)
        lengths["offsets"] = (1 << bits) + 1
        arrays = {}
        for a in ARRAYS:
            file = path / array_file(s, a)
            arrays[a] = _load_array(file, lengths[a])
            if checksum(arrays[a]) != sums[a]:
                raise IndexFormatError(f"SHA-256 differs from index.json's sets.{s}.sha256.{a}", path=file)
        _check_set(path, s, bits, arrays, documents)
        sets[s] = SetIndex(s, bits, **arrays)
    return MotionIndex(rate, documents, sets, root["base"])


def _load_array(file: Path, length: int) -> IntArray:
    """The int64 array of ``length`` entries in ``file``, memory-mapped; its header is read and
    checked first, so a file that is not such an array gives one plain reason."""
    if not file.is_file():
        raise IndexFormatError("missing", path=file)
    try:
        with open(file, "rb") as f:
            major, _ = npy_format.read_magic(f)
            read_header = npy_format.read_array_header_1_0 if major == 1 else npy_format.read_array_header_2_0
            shape, _, dtype = read_header(f)
    except OSError as exc:
        raise IndexFormatError(f"cannot read: {exc.strerror}", path=file) from None
    except Exception:  # whatever a damaged header makes numpy's parser raise, the file is not an array
        raise IndexFormatError("not a .npy array file", path=file) from None
    if dtype != np.int64 or len(shape) != 1:
        raise IndexFormatError(
            f"expected a one-dimensional int64 array, got {dtype} of shape {shape}", path=file
        )
    if shape[0] != length:
        raise IndexFormatError(f"{shape[0]} entries, index.json implies {length}", path=file)
    try:
        array = np.load(file, mmap_mode="r", allow_pickle=False)
    except (OSError, ValueError, EOFError) as exc:
        raise IndexFormatError(f"not a readable .npy array: {str(exc).splitlines()[0]}", path=file) from None
    out: IntArray = array
    return out


def _check_set(
    path: Path, feature_set: str, bits: int, arrays: Mapping[str, IntArray], documents: Sequence[Document]
) -> None:
    """Raise :class:`IndexFormatError` naming the array file unless the arrays are an index of the
    documents: segments in document order tile each document, codes fit the set, offsets run from 0
    to the segment count, and list v holds exactly the segments of code v, ascending."""
    doc, start, length, code = (np.asarray(arrays[a]) for a in ("doc", "start", "length", "code"))
    offsets, postings = np.asarray(arrays["offsets"]), np.asarray(arrays["postings"])

    def fail(array: str, reason: str) -> None:
        raise IndexFormatError(reason, path=path / array_file(feature_set, array))

    n_docs = len(documents)
    if len(doc) and (doc.min() < 0 or doc.max() >= n_docs or np.any(np.diff(doc) < 0)):
        fail("doc", f"documents must rise from 0 to {n_docs - 1}, the documents of index.json")
    frames = np.asarray([d.frames for d in documents], dtype=np.int64)
    if np.any(length < 1):
        fail("length", "a segment must have at least one frame")
    ends = start + length
    first = np.ones(len(doc), dtype=bool)
    first[1:] = doc[1:] != doc[:-1]
    last = np.ones(len(doc), dtype=bool)
    last[:-1] = doc[1:] != doc[:-1]
    if (
        np.any(start[first] != 0)
        or np.any(start[1:][~first[1:]] != ends[:-1][~first[1:]])
        or np.any(ends[last] != frames[doc[last]])
        or len(np.unique(doc)) != n_docs
    ):
        together = ", ".join(array_file(feature_set, a) for a in ("doc", "start", "length"))
        fail("start", f"the segments ({together}) do not tile the documents of index.json")
    if len(code) and (code.min() < 0 or code.max() >= 1 << bits):
        fail("code", f"codes must lie in 0..{(1 << bits) - 1}")
    if offsets[0] != 0 or offsets[-1] != len(code) or np.any(np.diff(offsets) < 0):
        fail("offsets", f"must rise from 0 to the {len(code)} segments")
    listed = np.repeat(np.arange(1 << bits, dtype=np.int64), np.diff(offsets))
    if len(postings) and (postings.min() < 0 or postings.max() >= len(code)):
        fail("postings", f"segment numbers must lie in 0..{len(code) - 1}")
    if np.any(code[postings] != listed) or np.any(np.diff(postings)[np.diff(listed) == 0] <= 0):
        fail(
            "postings",
            f"the lists ({array_file(feature_set, 'offsets')}, {array_file(feature_set, 'postings')}) do "
            f"not hold exactly the segments of their codes ({array_file(feature_set, 'code')}), ascending",
        )


def _documents(check: Checker, value: object, rate: float) -> tuple[Document, ...]:
    out = []
    for i, item in enumerate(check.listing(value, "documents", nonempty=True)):
        where = f"documents[{i}]"
        d = check.mapping(item, where, [f.name for f in fields(Document) if f.name != "per"], ["per"])
        amc, asf = check.string(d["amc"], f"{where}.amc"), check.string(d["asf"], f"{where}.asf")
        first = check.integer(d["first_amc_frame"], f"{where}.first_amc_frame", minimum=None)
        last = check.integer(d["last_amc_frame"], f"{where}.last_amc_frame", minimum=first)
        step = check.integer(d["step"], f"{where}.step", minimum=1)
        per = check.integer(d.get("per", 1), f"{where}.per", minimum=1)
        if per > step or math.gcd(step, per) != 1:
            check.fail(
                f"{where}.per",
                f"{per} index frames in {step} AMC frames: not a ratio in lowest terms, at most 1",
            )
        frames = check.integer(d["frames"], f"{where}.frames", minimum=1)
        if frames != sample_count(last - first + 1, step, per):
            check.fail(
                f"{where}.frames", f"{frames} does not fit AMC frames {first}..{last} every {step / per:g}"
            )
        native = check.positive_number(d["native_rate"], f"{where}.native_rate")
        if not math.isclose(native * per / step, rate, rel_tol=1e-9):
            check.fail(
                f"{where}.step", f"{native:g} Hz every {step / per:g} frames is not {rate:g} Hz (rate)"
            )
        out.append(Document(amc, asf, first, last, step, frames, native, per))
    return tuple(out)
