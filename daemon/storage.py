"""Writing and checking the directories mocapd stores (indexes, template libraries): a directory is
built in a temporary sibling and renamed into place, and its JSON is checked field by field with
errors that name the file and the field."""

from __future__ import annotations

import errno
import json
import math
import os
import secrets
import shutil
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import IO, Any, NoReturn


def sync(file: IO[Any]) -> None:
    file.flush()
    os.fsync(file.fileno())


def write_json(path: Path, value: object) -> None:
    with open(path, "w", encoding="utf-8") as out:
        json.dump(value, out, indent=1)
        out.write("\n")
        sync(out)


def check_target(path: Path, marker: str, what: str) -> None:
    """Raise :class:`OSError` (naming the path) unless ``path`` may be written: its directory exists
    and ``path`` is absent, an empty directory or a directory holding ``marker`` (``what``)."""
    parent = path.parent
    if not parent.is_dir():
        raise FileNotFoundError(errno.ENOENT, os.strerror(errno.ENOENT), str(parent))
    if path.exists() and not (path.is_dir() and (not any(path.iterdir()) or (path / marker).is_file())):
        raise FileExistsError(errno.EEXIST, f"exists and is not {what}, not replaced", str(path))


def replace_directory(path: Path, marker: str, what: str, fill: Callable[[Path], None]) -> None:
    """Write the directory ``path`` with ``fill(temp)`` in a temporary sibling, then rename it into
    place (replacing an earlier one, see :func:`check_target`), so ``path`` is never half written."""
    check_target(path, marker, what)
    temp = path.parent / f".{path.name}.{os.getpid()}.{secrets.token_hex(4)}.tmp"
    temp.mkdir()  # unlike mkdtemp's 0o700, the umask's permissions, which the directory keeps
    try:
        fill(temp)
        if path.exists():
            old = Path(tempfile.mkdtemp(prefix=f".{path.name}.", suffix=".old", dir=path.parent))
            os.replace(path, old / path.name)
            os.replace(temp, path)
            shutil.rmtree(old)
        else:
            os.replace(temp, path)
    except BaseException:
        shutil.rmtree(temp, ignore_errors=True)
        raise


def read_meta(path: Path, marker: str, what: str, error: type[Exception]) -> tuple[JsonChecker, Any]:
    """The parsed JSON file ``marker`` of the directory ``path`` (``what``, e.g. "a mocapd index")
    and a checker naming it; ``error`` names the path if it cannot be read."""
    meta_path = path / marker
    if not path.is_dir():
        raise error(f"{path}: not {what} (not a directory)")
    try:
        text = meta_path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise error(f"{path}: not {what} (no {marker})") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise error(f"{meta_path}: cannot read: {exc}") from None
    try:
        meta = json.loads(text)
    except json.JSONDecodeError as exc:
        raise error(f"{meta_path}: not valid JSON: {exc}") from None
    return JsonChecker(str(meta_path), error), meta


class JsonChecker:
    """Type checks of parsed JSON that raise ``error`` naming file and field."""

    def __init__(self, source: str, error: type[Exception]) -> None:
        self.source = source
        self.error = error

    def fail(self, field: str, reason: str) -> NoReturn:
        raise self.error(f"{self.source}: {field or 'top level'}: {reason}")

    def header(self, value: object, keys: set[str], fmt: str, version: int) -> tuple[dict[str, Any], float]:
        """The top-level object with exactly ``keys``, its ``format`` and ``version`` checked; and its
        positive ``rate``."""
        root = self.mapping(value, "", keys)
        if root["format"] != fmt:
            self.fail("format", f"expected '{fmt}', got {root['format']!r}")
        if root["version"] != version or isinstance(root["version"], bool):
            self.fail("version", f"this mocapd reads version {version}, got {root['version']!r}")
        return root, self.positive_number(root["rate"], "rate")

    def mapping(self, value: object, field: str, keys: set[str]) -> dict[str, Any]:
        if not isinstance(value, dict):
            self.fail(field, f"expected an object, got {type(value).__name__}")
        missing, extra = keys - value.keys(), value.keys() - keys
        if missing:
            self.fail(field, f"missing {', '.join(sorted(missing))}")
        if extra:
            self.fail(field, f"unknown {', '.join(sorted(extra))}")
        return value

    def integer(self, value: object, field: str, minimum: int | None = 0) -> int:
        if not isinstance(value, int) or isinstance(value, bool):
            self.fail(field, f"expected an integer, got {value!r}")
        if minimum is not None and value < minimum:
            self.fail(field, f"must be at least {minimum}, got {value}")
        return value

    def positive_number(self, value: object, field: str) -> float:
        if (
            not isinstance(value, int | float)
            or isinstance(value, bool)
            or not (math.isfinite(value) and value > 0)
        ):
            self.fail(field, f"expected a positive number, got {value!r}")
        return float(value)
