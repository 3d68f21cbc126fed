"""The one error root: every error a user can cause derives from :class:`MocapdError`, which says
where it happened (a file or an option, a line, a field), so the command line and the service catch
one type and print one line."""

from __future__ import annotations

import os


def printable(text: str, *, ascii_only: bool = False) -> str:
    """``text`` with control characters (and, with ``ascii_only``, everything outside printable ASCII)
    written as Python escapes, so that bytes from a damaged file cannot garble a terminal or a log
    line."""
    return "".join(
        c if c.isprintable() and (not ascii_only or c.isascii()) else c.encode("unicode_escape").decode()
        for c in text
    )


class MocapdError(Exception):
    """Bad input: ``reason`` and where it was found: ``path`` (a file, or an option such as ``--fps``),
    ``line`` (1-based) and ``field`` (e.g. ``classes.squat[0].values``). ``str``:
    ``path:line: field: reason``, the parts that are known."""

    def __init__(
        self,
        reason: str,
        *,
        path: str | os.PathLike[str] | None = None,
        line: int | None = None,
        field: str = "",
    ) -> None:
        self.reason = reason
        self.path = None if path is None else os.fspath(path)
        self.line = line
        self.field = field
        super().__init__(reason)

    @property
    def where(self) -> str:
        """``path:line: field`` of the parts that are known ("" if none)."""
        place = "" if self.path is None else self.path if self.line is None else f"{self.path}:{self.line}"
        return ": ".join(p for p in (place, self.field) if p)

    def _reason(self) -> str:
        return printable(self.reason)

    def __str__(self) -> str:
        where = printable(self.where)
        return f"{where}: {self._reason()}" if where else self._reason()


class InputError(MocapdError, ValueError):
    """A value an algorithm cannot work with (a rate, a window, a skeleton, a setting, an address),
    raised by the pure modules; the caller names where it came from."""


class UsageError(MocapdError, ValueError):
    """Options that do not fit each other or the input; ``path`` names the option."""


class FileAccessError(MocapdError, OSError):
    """A file that cannot be opened, read or written (an :class:`OSError` with the file named)."""

    @classmethod
    def from_os_error(cls, exc: OSError, path: str | os.PathLike[str] | None = None) -> FileAccessError:
        """``exc`` naming its own file name if it has one, else ``path``."""
        name = exc.filename if exc.filename is not None else path
        error = cls(exc.strerror or str(exc) or type(exc).__name__, path=name)
        error.errno = exc.errno
        return error
