"""The motion index on disk: manifests of recordings in, index directories out, and back.

An I/O adapter around :mod:`daemon.index` (the pure inverted lists). A *manifest* is a CSV listing
recordings (columns ``asf`` and ``amc``); :func:`build_index` reads each, computes its 39 features at
the native rate and keeps every k-th frame (the index rate, 30 Hz by default), then indexes the
lower, upper and mix sets. :func:`save_index` writes a directory::

    index.json            format, version, rate, documents, per set its bits and segment count
    <set>.<array>.npy     for set in lower, upper, mix and array in doc, start, length, code,
                          offsets, postings (int64, one dimension)

:func:`load_index` maps the arrays (``mmap_mode="r"``), so loading costs milliseconds at any size;
it checks everything that can be checked without reading the arrays' contents.
"""

from __future__ import annotations

import csv
import io
import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any, get_args

import numpy as np

from daemon.features import SET_SLICES, BoolArray, FeatureSet, decimate, decimation_factor, features
from daemon.index import IntArray, SetIndex, build_set_index
from daemon.storage import JsonChecker, check_target, read_meta, replace_directory, sync, write_json
from replay import JOINT_NAMES, KinematicModel, MocapFormatError, read_amc, read_asf

FORMAT = "mocapd-index"
VERSION = 1
INDEX_JSON = "index.json"
FEATURE_SETS: tuple[FeatureSet, ...] = get_args(FeatureSet)
ARRAYS = ("doc", "start", "length", "code", "offsets", "postings")
DEFAULT_NATIVE_RATE = 120.0

Progress = Callable[[int, int, "Document"], object]


# ------------------------------------------------------------------------------------------ errors


class ManifestError(ValueError):
    """A manifest that cannot be used; ``str``: ``path:line: reason``."""

    def __init__(self, path: str, line: int, reason: str) -> None:
        self.path = path
        self.line = line
        self.reason = reason
        super().__init__(f"{path}:{line}: {reason}")


class IndexFormatError(ValueError):
    """An index directory that cannot be loaded; the message names the offending file (and field)."""


class IndexBuildError(ValueError):
    """A recording that reads but cannot be indexed (e.g. the index rate does not divide its rate);
    the message names the file. Unreadable files raise the reader's :class:`MocapFormatError`."""


# ---------------------------------------------------------------------------------------- manifest


@dataclass(frozen=True)
class ManifestRow:
    """One recording of a manifest: ``asf_text``/``amc_text`` as written, ``asf``/``amc`` resolved
    against the manifest's directory; ``line`` is the row's (last) line in the manifest."""

    line: int
    asf_text: str
    amc_text: str
    asf: Path
    amc: Path
    extra: Mapping[str, str] = field(default_factory=dict)


def read_manifest(path: str | Path, required: Sequence[str] = ()) -> list[ManifestRow]:
    """The rows of a manifest CSV whose header names the columns ``asf`` and ``amc`` and every column
    of ``required`` (in any order, among any others). ``extra`` holds each row's other cells by
    lower-case column name (empty cells of optional columns included). Blank lines are skipped.
    Raises :class:`ManifestError`."""
    path = Path(path)
    source = str(path)
    data = path.read_bytes()
    try:
        text = data.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        line = data[: exc.start].count(b"\n") + 1
        raise ManifestError(source, line, "not UTF-8 text") from None
    reader = csv.reader(io.StringIO(text, newline=""))
    header: list[str] | None = None
    columns: dict[str, int] = {}
    rows: list[ManifestRow] = []
    try:
        for record in reader:
            line = reader.line_num
            cells = [f.strip() for f in record]
            if not any(cells):
                continue
            if header is None:
                header = [f.lower() for f in cells]
                for name in ("asf", "amc", *required):
                    if header.count(name) != 1:
                        how = "lacks" if name not in header else "repeats"
                        raise ManifestError(
                            source, line, f"header {how} the column '{name}': {','.join(record)}"
                        )
                    columns[name] = header.index(name)
                continue
            if len(cells) != len(header):
                raise ManifestError(source, line, f"{len(cells)} fields, the header has {len(header)}")
            texts = {name: cells[i] for name, i in columns.items()}
            for name, value in texts.items():
                if not value:
                    raise ManifestError(source, line, f"the '{name}' field is blank")
            resolved = {name: path.parent / texts[name] for name in ("asf", "amc")}
            for name, file in resolved.items():
                if not file.is_file():
                    raise ManifestError(source, line, f"{name} file not found: {file}")
            others = {name: cells[i] for i, name in enumerate(header) if name not in ("asf", "amc")}
            rows.append(
                ManifestRow(line, texts["asf"], texts["amc"], resolved["asf"], resolved["amc"], others)
            )
    except csv.Error as exc:
        raise ManifestError(source, reader.line_num, f"not valid CSV: {exc}") from None
    if header is None:
        raise ManifestError(source, 1, "empty manifest: no header line (it needs the columns asf, amc)")
    if not rows:
        raise ManifestError(source, max(reader.line_num, 1), "empty manifest: no recordings after the header")
    return rows


# ------------------------------------------------------------------------------------------- index


@dataclass(frozen=True)
class Document:
    """One indexed recording. ``amc``/``asf``: the paths as the manifest writes them; index frame
    ``j`` (0-based, ``0 <= j < frames``) is AMC frame ``first_amc_frame + step * j``; the recording
    has AMC frames ``first_amc_frame .. last_amc_frame`` at ``native_rate`` Hz."""

    amc: str
    asf: str
    first_amc_frame: int
    last_amc_frame: int
    step: int
    frames: int
    native_rate: float


@dataclass(frozen=True)
class MotionIndex:
    """Documents and the index of each feature set (``lower``, ``upper``, ``mix``) at ``rate`` Hz;
    segments' ``start``/``length`` count index-rate frames of their document."""

    rate: float
    documents: tuple[Document, ...]
    sets: Mapping[FeatureSet, SetIndex]

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
        first = d.first_amc_frame + d.step * start
        last = min(d.first_amc_frame + d.step * end + d.step - 1, d.last_amc_frame)
        return first, last


def index_from_matrices(
    matrices: Sequence[BoolArray], documents: Sequence[Document], rate: float
) -> MotionIndex:
    """The index of documents given as feature matrices at the index rate, each shape
    ``(documents[d].frames, 39)``."""
    if len(matrices) != len(documents):
        raise ValueError(f"{len(matrices)} feature matrices for {len(documents)} documents")
    for d, (m, doc) in enumerate(zip(matrices, documents, strict=True)):
        if m.shape != (doc.frames, 39):
            raise ValueError(f"document {d} ({doc.amc}): matrix shape {m.shape}, expected ({doc.frames}, 39)")
        if not math.isclose(doc.native_rate / doc.step, rate, rel_tol=1e-9):
            raise ValueError(
                f"document {d} ({doc.amc}): {doc.native_rate:g} Hz / {doc.step} is not {rate:g} Hz"
            )
    sets = {s: build_set_index(matrices, s) for s in FEATURE_SETS}
    return MotionIndex(float(rate), tuple(documents), sets)


def read_document(
    row: ManifestRow, rate: float = 30.0, default_native_rate: float = DEFAULT_NATIVE_RATE
) -> tuple[Document, BoolArray]:
    """One recording's :class:`Document` and its features at ``rate``, shape ``(frames, 39)``: computed
    at the native rate (the AMC's, else ``default_native_rate``), then every k-th frame from the first
    (as ``mocapd features --fps``)."""
    motion = read_amc(row.amc, read_asf(row.asf))
    native = motion.header.frame_rate or default_native_rate
    try:
        step = decimation_factor(native, rate)
    except ValueError as exc:
        raise IndexBuildError(f"{row.amc}: index rate {exc}") from None
    model = KinematicModel(motion.skeleton)
    joints = model.joints(model.positions(motion.channels, "cm"))
    try:
        matrix = decimate(features(joints, JOINT_NAMES, native), step)
    except MocapFormatError:
        raise
    except ValueError as exc:
        raise IndexBuildError(f"{row.amc}: {exc}") from exc
    frames = motion.frames
    document = Document(
        amc=row.amc_text,
        asf=row.asf_text,
        first_amc_frame=int(frames[0]),
        last_amc_frame=int(frames[-1]),
        step=step,
        frames=int(matrix.shape[0]),
        native_rate=float(native),
    )
    return document, matrix


def build_index(
    rows: Sequence[ManifestRow],
    rate: float = 30.0,
    progress: Progress | None = None,
    default_native_rate: float = DEFAULT_NATIVE_RATE,
) -> MotionIndex:
    """The index of the manifest's recordings at ``rate`` Hz; ``progress(done, total, document)`` is
    called after each recording. Raises :class:`MocapFormatError` (unreadable file) or
    :class:`IndexBuildError` (``rate`` does not divide a recording's rate)."""
    documents: list[Document] = []
    matrices: list[BoolArray] = []
    for i, row in enumerate(rows, start=1):
        document, matrix = read_document(row, rate, default_native_rate)
        documents.append(document)
        matrices.append(matrix)
        if progress is not None:
            progress(i, len(rows), document)
    return index_from_matrices(matrices, documents, rate)


# ------------------------------------------------------------------------------------------ saving


def array_file(feature_set: FeatureSet, array: str) -> str:
    """The file name of one array of one set, e.g. ``lower.postings.npy``."""
    return f"{feature_set}.{array}.npy"


def index_files() -> list[str]:
    """Every file of an index directory."""
    return [INDEX_JSON] + [array_file(s, a) for s in FEATURE_SETS for a in ARRAYS]


def index_bytes(path: str | Path, feature_set: FeatureSet | None = None) -> int:
    """Bytes on disk of the index directory ``path``, or of one feature set's arrays."""
    names = index_files() if feature_set is None else [array_file(feature_set, a) for a in ARRAYS]
    return sum((Path(path) / name).stat().st_size for name in names)


def save_index(index: MotionIndex, path: str | Path) -> None:
    """Write ``index`` as the directory ``path``: built in a temporary sibling and renamed into place,
    so ``path`` never holds half an index. An existing index (or empty directory) at ``path`` is
    replaced; anything else there is left alone and raises :class:`FileExistsError`."""
    meta: dict[str, Any] = {
        "format": FORMAT,
        "version": VERSION,
        "rate": index.rate,
        "documents": [{f.name: getattr(d, f.name) for f in fields(Document)} for d in index.documents],
        "sets": {s: {"bits": index.sets[s].bits, "segments": index.sets[s].n_segments} for s in FEATURE_SETS},
    }

    def fill(temp: Path) -> None:
        for s in FEATURE_SETS:
            for a in ARRAYS:
                with open(temp / array_file(s, a), "wb") as out:
                    np.save(out, np.ascontiguousarray(getattr(index.sets[s], a), dtype=np.int64))
                    sync(out)
        write_json(temp / INDEX_JSON, meta)  # last: a directory with it is complete

    replace_directory(Path(path), INDEX_JSON, "a mocapd index", fill)


def check_index_target(path: str | Path) -> None:
    """Raise :class:`OSError` (naming the path) unless :func:`save_index` may write ``path``: its
    directory exists and ``path`` is absent, an empty directory or an index."""
    check_target(Path(path), INDEX_JSON, "a mocapd index")


# ----------------------------------------------------------------------------------------- loading


def load_index(path: str | Path) -> MotionIndex:
    """The index in directory ``path``, its arrays memory-mapped read-only (numpy memmaps). Raises
    :class:`IndexFormatError` naming the file (and field) if anything is missing or inconsistent."""
    path = Path(path)
    check, meta = read_meta(path, INDEX_JSON, "a mocapd index", IndexFormatError)
    root, rate = check.header(meta, {"format", "version", "rate", "documents", "sets"}, FORMAT, VERSION)
    documents = _documents(check, root["documents"])
    sets_meta = check.mapping(root["sets"], "sets", set(FEATURE_SETS))
    sets: dict[FeatureSet, SetIndex] = {}
    for s in FEATURE_SETS:
        entry = check.mapping(sets_meta[s], f"sets.{s}", {"bits", "segments"})
        bits = check.integer(entry["bits"], f"sets.{s}.bits")
        expected_bits = SET_SLICES[s].stop - SET_SLICES[s].start
        if bits != expected_bits:
            check.fail(f"sets.{s}.bits", f"the {s} set has {expected_bits} bits, got {bits}")
        segments = check.integer(entry["segments"], f"sets.{s}.segments")
        lengths = {"doc": segments, "start": segments, "length": segments, "code": segments}
        lengths |= {"offsets": (1 << bits) + 1, "postings": segments}
        arrays = {a: _load_array(path / array_file(s, a), lengths[a]) for a in ARRAYS}
        if int(arrays["offsets"][-1]) != segments or int(arrays["offsets"][0]) != 0:
            raise IndexFormatError(
                f"{path / array_file(s, 'offsets')}: must run from 0 to the {segments} segments, "
                f"runs from {int(arrays['offsets'][0])} to {int(arrays['offsets'][-1])}"
            )
        sets[s] = SetIndex(s, bits, **arrays)
    return MotionIndex(rate, documents, sets)


def _load_array(file: Path, length: int) -> IntArray:
    if not file.is_file():
        raise IndexFormatError(f"{file}: missing")
    try:
        array = np.load(file, mmap_mode="r", allow_pickle=False)
    except (OSError, ValueError, EOFError) as exc:
        raise IndexFormatError(f"{file}: not a readable .npy array: {exc}") from None
    if not isinstance(array, np.ndarray) or array.dtype != np.int64 or array.ndim != 1:
        raise IndexFormatError(f"{file}: expected a one-dimensional int64 array, got {array!r:.80}")
    if array.shape[0] != length:
        raise IndexFormatError(f"{file}: {array.shape[0]} entries, index.json implies {length}")
    out: IntArray = array
    return out


def _documents(check: JsonChecker, value: object) -> tuple[Document, ...]:
    if not isinstance(value, list) or not value:
        check.fail("documents", "expected a non-empty list")
    out = []
    for i, item in enumerate(value):
        where = f"documents[{i}]"
        d = check.mapping(item, where, {f.name for f in fields(Document)})
        for key in ("amc", "asf"):
            if not isinstance(d[key], str) or not d[key]:
                check.fail(f"{where}.{key}", f"expected a path, got {d[key]!r}")
        first = check.integer(d["first_amc_frame"], f"{where}.first_amc_frame", minimum=None)
        last = check.integer(d["last_amc_frame"], f"{where}.last_amc_frame", minimum=first)
        step = check.integer(d["step"], f"{where}.step", minimum=1)
        frames = check.integer(d["frames"], f"{where}.frames", minimum=1)
        if frames != -(-(last - first + 1) // step):
            check.fail(f"{where}.frames", f"{frames} does not fit AMC frames {first}..{last} every {step}")
        native = check.positive_number(d["native_rate"], f"{where}.native_rate")
        out.append(Document(d["amc"], d["asf"], first, last, step, frames, native))
    return tuple(out)
