"""Opening recordings: plain or gzip (told by the magic bytes, not the name), CRLF or LF.

Whole files are inflated by ISA-L (``isal``), faster than zlib (docs/layout.md, Dependencies).
"""

from __future__ import annotations

import gzip
import zlib
from pathlib import Path
from typing import BinaryIO, cast

from isal import igzip, isal_zlib

from daemon.errors import FileAccessError
from replay.errors import MocapFormatError

GZIP_MAGIC = b"\x1f\x8b"
GZIP_ERRORS: tuple[type[BaseException], ...] = (
    EOFError,
    OSError,
    zlib.error,
    cast(type[BaseException], isal_zlib.error),
)


def is_gzip(path: str | Path) -> bool:
    try:
        with open(path, "rb") as probe:
            return probe.read(2) == GZIP_MAGIC
    except OSError as exc:
        raise FileAccessError.from_os_error(exc, path) from None


def open_binary(path: str | Path) -> BinaryIO:
    """Open ``path`` for reading bytes, decompressing transparently if it is gzip.

    The stream uses the standard library's gzip: on a truncated stream it hands out everything that
    was recoverable before raising, where ISA-L's reader stops several blocks early."""
    gzipped = is_gzip(path)
    try:
        return cast(BinaryIO, gzip.open(path, "rb")) if gzipped else open(path, "rb")
    except OSError as exc:
        raise FileAccessError.from_os_error(exc, path) from None


def read_bytes(path: str | Path) -> bytes:
    """The whole (decompressed) content of ``path``; a damaged gzip stream is a format error."""
    try:
        with open(path, "rb") as f:
            raw = f.read()
    except OSError as exc:
        raise FileAccessError.from_os_error(exc, path) from None
    if raw[:2] != GZIP_MAGIC:
        return raw
    try:
        return cast(bytes, igzip.decompress(raw))  # type: ignore[no-untyped-call]
    except GZIP_ERRORS as exc:
        raise MocapFormatError(str(path), None, f"damaged or truncated gzip data ({exc})") from None


def read_text_lines(path: str | Path) -> list[str]:
    """Lines of a small text file (an ASF), without line terminators. Latin-1, so no byte fails."""
    return read_bytes(path).decode("latin-1").replace("\r\n", "\n").replace("\r", "\n").split("\n")
