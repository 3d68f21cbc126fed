"""The one error type of the readers: bad input, located by file and line."""

from __future__ import annotations


class MocapFormatError(ValueError):
    """A recording that cannot be read as it stands.

    ``path`` names the file, ``line`` the 1-based line the problem was found on (``None`` when it
    concerns the file as a whole), ``reason`` what is wrong with it.
    """

    def __init__(self, path: str, line: int | None, reason: str) -> None:
        self.path = path
        self.line = line
        self.reason = reason
        where = f"{path}:{line}" if line is not None else path
        super().__init__(f"{where}: {reason}")
