"""Writing what mocapd stores (indexes, template libraries, CSV and PNG outputs) so that a target is
never half written: every output is written beside its target and renamed into place, and SIGINT or
SIGTERM during the swap or the clean-up takes effect only after it, so the previous file is intact or
the new one complete and nothing temporary is left behind. Targets are checked before the work (by
creating and removing a probe beside them) and errors name the target, not a temporary file."""

from __future__ import annotations

import errno
import hashlib
import json
import os
import secrets
import shutil
import signal
import stat
import threading
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from types import FrameType
from typing import IO, Any, Literal, NamedTuple

import numpy as np
import numpy.typing as npt

from daemon.checks import Checker, read_structured
from daemon.errors import FileAccessError, MocapdError

STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM)


@contextmanager
def uninterrupted() -> Iterator[None]:
    """Run the block to its end even if SIGINT or SIGTERM arrive meanwhile; the first of them is then
    handled as it would have been (e.g. ``KeyboardInterrupt`` raised) once the block is done. Outside
    the main thread, where Python handles no signals, the block simply runs."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    caught: list[tuple[int, FrameType | None]] = []

    def record(number: int, frame: FrameType | None) -> None:
        caught.append((number, frame))

    previous = {s: signal.signal(s, record) for s in STOP_SIGNALS}
    try:
        yield
    finally:
        for s, handler in previous.items():
            signal.signal(s, handler)
        if caught:
            number, frame = caught[0]
            handler = previous[signal.Signals(number)]
            if callable(handler):
                handler(number, frame)
            elif handler == signal.SIG_DFL:
                os.kill(os.getpid(), number)


class _Pending(NamedTuple):
    put: Callable[[], None]
    """Rename the written output into place."""
    discard: Callable[[], None]
    """Remove what was written instead."""
    target: Path


_batches: list[list[_Pending]] = []
"""The outputs waiting for the end of the enclosing :func:`together` block (one at most)."""
_placed: list[bool] = [False]
"""Whether outputs were put into place since :func:`forget_placed` (see :func:`placed`)."""


def placed() -> bool:
    """Whether outputs were put into place since :func:`forget_placed`: the command line then takes a
    stop signal as too late (the new outputs are its result, and what is left of it is short), so
    that a status of 130 or 143 always means the previous outputs are intact."""
    return _placed[0]


def forget_placed() -> None:
    """A new command begins (:func:`placed` is false again)."""
    _placed[0] = False


@contextmanager
def together() -> Iterator[None]:
    """Put the outputs written in the block (:func:`output_file`, :func:`replace_directory`) into
    place together when it ends, their renames in one uninterrupted step, so a command writing several
    outputs that is stopped before that step leaves every previous one intact, not some replaced. If
    the block ends by an exception, signals included, none is put into place and what was written is
    removed. Inside another ``together`` block, the outputs wait for that one."""
    if _batches:
        yield
        return
    pending: list[_Pending] = []
    _batches.append(pending)
    try:
        yield
    except BaseException:
        with uninterrupted():
            for output in pending:
                output.discard()
        raise
    finally:
        _batches.pop()
    with uninterrupted():
        for i, output in enumerate(pending):
            try:
                output.put()
            except OSError as exc:
                for rest in pending[i:]:
                    rest.discard()
                raise _named(exc, output.target) from None
        _placed[0] = bool(pending) or _placed[0]


def _put_in_place(put: Callable[[], None], discard: Callable[[], None], target: Path) -> None:
    """``put()`` an output into place now, uninterrupted, or at the end of a :func:`together` block."""
    if _batches:
        _batches[-1].append(_Pending(put, discard, target))
        return
    with uninterrupted():
        put()
        _placed[0] = True


def _beside(target: Path, kind: str) -> Path:
    """A fresh hidden name in the directory of ``target`` (so a rename into place is atomic)."""
    return target.parent / f".{target.name}.{os.getpid()}.{secrets.token_hex(4)}.{kind}"


def _named(exc: OSError, target: Path) -> FileAccessError:
    error = FileAccessError(exc.strerror or str(exc), path=target)
    error.errno = exc.errno
    return error


def _probe(directory: Path, named: Path) -> None:
    """Create and remove a directory in ``directory``: the real test that it can be written there
    (permission bits alone say nothing to root or on a read-only file system). Errors name
    ``named``, the output the user asked for."""
    probe = _beside(directory / "mocapd", "probe")
    with uninterrupted():
        try:
            probe.mkdir()
        except OSError as exc:
            raise _named(exc, named) from None
        probe.rmdir()


# ------------------------------------------------------------------------------------------ files


def _direct(target: Path) -> bool:
    """Whether ``target`` is written in place: an existing device, pipe or socket (``/dev/stdout``,
    a FIFO) cannot be replaced, and must not be."""
    try:
        mode = target.stat().st_mode
    except OSError:
        return False
    return not stat.S_ISREG(mode) and not stat.S_ISDIR(mode)


def check_output_file(path: str | Path) -> None:
    """Raise :class:`FileAccessError` naming ``path`` unless :func:`output_file` can write it."""
    target = Path(path)
    if target.is_dir():
        raise FileAccessError("is a directory", path=target)
    if _direct(target):
        if not os.access(target, os.W_OK):
            raise FileAccessError(os.strerror(errno.EACCES), path=target)
        return
    real = Path(os.path.realpath(target))
    if not real.parent.is_dir():
        raise FileAccessError(os.strerror(errno.ENOENT), path=target)
    _probe(real.parent, target)


def check_directory(path: str | Path) -> None:
    """Raise :class:`FileAccessError` naming ``path`` unless files can be created in the directory
    ``path``, or, if it does not exist yet, it can be created (its nearest existing ancestor is a
    directory that can be written)."""
    target = Path(path)
    existing = next(p for p in (target, *target.parents) if p.exists())
    if not existing.is_dir():
        raise FileAccessError("not a directory", path=existing)
    _probe(existing, target)


@contextmanager
def output_file(path: str | Path, mode: Literal["w", "wb"] = "w") -> Iterator[IO[Any]]:
    """A file to write ``path`` through: text (UTF-8, ``\\n`` line ends) or binary. On a clean exit it
    is synced and renamed onto ``path`` (a symbolic link is followed; an existing file keeps its
    permissions), inside a :func:`together` block when that ends; on any exception, signals
    included, it is removed and ``path`` is untouched. Devices and pipes are written in place.
    :class:`OSError` from writing becomes :class:`FileAccessError` naming ``path``."""
    target = Path(path)
    check_output_file(target)
    text: dict[str, Any] = {"encoding": "utf-8", "newline": ""} if mode == "w" else {}
    if _direct(target):
        try:
            with open(target, mode, **text) as out:
                yield out
        except OSError as exc:
            raise _named(exc, target) from None
        return
    real = Path(os.path.realpath(target))
    with uninterrupted():
        temp = _beside(real, "tmp")
        try:
            fd = os.open(temp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666)
        except OSError as exc:
            raise _named(exc, target) from None
    try:
        with os.fdopen(fd, mode, **text) as out:
            yield out
            out.flush()
            os.fsync(out.fileno())
        if real.exists():
            os.chmod(temp, stat.S_IMODE(real.stat().st_mode))
        _put_in_place(lambda: os.replace(temp, real), lambda: temp.unlink(missing_ok=True), target)
    except BaseException as exc:
        with uninterrupted():
            temp.unlink(missing_ok=True)
        if isinstance(exc, OSError):
            raise _named(exc, target) from None
        raise


# ------------------------------------------------------------------------------------ directories


def sync(file: IO[Any]) -> None:
    file.flush()
    os.fsync(file.fileno())


def write_json(path: Path, value: object) -> None:
    with open(path, "w", encoding="utf-8") as out:
        json.dump(value, out, indent=1)
        out.write("\n")
        sync(out)


def check_target(path: str | Path, marker: str, what: str) -> None:
    """Raise :class:`FileAccessError` (naming ``path``) unless :func:`replace_directory` may write
    ``path``: its directory exists and can be written, and ``path`` is absent, an empty directory or
    a directory holding ``marker`` (``what``)."""
    target = Path(path)
    if not target.parent.is_dir():
        raise FileAccessError(os.strerror(errno.ENOENT), path=target)
    if target.exists() and not (
        target.is_dir() and (not any(target.iterdir()) or (target / marker).is_file())
    ):
        raise FileAccessError(f"exists and is not {what}, not replaced", path=target)
    _probe(target.parent, target)


def replace_directory(path: str | Path, marker: str, what: str, fill: Callable[[Path], None]) -> None:
    """Write the directory ``path`` with ``fill(temp)`` in a temporary sibling, then rename it into
    place (replacing an earlier one, see :func:`check_target`; inside a :func:`together` block when
    that ends), so ``path`` is never half written."""
    target = Path(path)
    check_target(target, marker, what)
    with uninterrupted():
        temp = _beside(target, "tmp")
        try:
            temp.mkdir()  # unlike mkdtemp's 0o700, the umask's permissions, which the directory keeps
        except OSError as exc:
            raise _named(exc, target) from None

    def swap() -> None:
        if target.exists():
            old = _beside(target, "old")
            os.replace(target, old)
            os.replace(temp, target)
            shutil.rmtree(old)
        else:
            os.replace(temp, target)

    try:
        fill(temp)
        _put_in_place(swap, lambda: shutil.rmtree(temp, ignore_errors=True), target)
    except BaseException as exc:
        with uninterrupted():
            shutil.rmtree(temp, ignore_errors=True)
        if isinstance(exc, OSError):
            raise _named(exc, target) from None
        raise


def read_meta(path: Path, marker: str, what: str, error: type[MocapdError]) -> tuple[Checker, Any]:
    """The parsed JSON file ``marker`` of the directory ``path`` (``what``, e.g. "a mocapd index")
    and a checker naming it."""
    if not path.is_dir():
        raise error(f"not {what} (not a directory)", path=path)
    if not (path / marker).is_file():
        raise error(f"not {what} (no {marker})", path=path)
    return Checker(path / marker, error), read_structured(path / marker, "json", error)


def checksum(array: npt.NDArray[Any]) -> str:
    """SHA-256 (hex) of an array's values in C order, the check that a stored array is the one
    written."""
    return hashlib.sha256(np.ascontiguousarray(array).data).hexdigest()
