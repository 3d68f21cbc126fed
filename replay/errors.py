"""The reader's error: bad input, located by file and line (a :class:`daemon.errors.MocapdError`)."""

from __future__ import annotations

from daemon.errors import MocapdError, printable


class MocapFormatError(MocapdError, ValueError):
    """A recording that cannot be read as it stands.

    ``path`` names the file, ``line`` the 1-based line the problem was found on (``None`` when it
    concerns the file as a whole), ``reason`` what is wrong with it. ASF and AMC files are ASCII, so
    anything else the reason quotes from the file is escaped.
    """

    def __init__(self, path: str, line: int | None, reason: str) -> None:
        super().__init__(reason, path=path, line=line)

    def _reason(self) -> str:
        return printable(self.reason, ascii_only=True)
