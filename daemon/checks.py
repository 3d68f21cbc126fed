"""The one structure checker for what mocapd reads as JSON or YAML (index and library metadata,
keyframe files, ``config.yaml``) and for option values: every error names the file (or option) and
the field, as ``path: field: reason``."""

from __future__ import annotations

import csv
import io
import json
import math
from collections.abc import Collection, Iterator
from pathlib import Path
from typing import Any, Literal, NoReturn

import yaml

from daemon.errors import FileAccessError, MocapdError


def read_text(path: str | Path, error: type[MocapdError]) -> str:
    """The text of the UTF-8 file ``path`` (a byte-order mark dropped). Unreadable files raise
    :class:`FileAccessError`; bytes that are not UTF-8 raise ``error`` naming the file and line."""
    try:
        data = Path(path).read_bytes()
    except OSError as exc:
        raise FileAccessError.from_os_error(exc, path) from None
    try:
        return data.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        line = data[: exc.start].count(b"\n") + 1
        raise error(f"not UTF-8 text (byte {exc.start})", path=path, line=line) from None


def csv_records(
    path: str | Path, error: type[MocapdError], required: Collection[str]
) -> Iterator[tuple[int, dict[str, str]]]:
    """The records of the UTF-8 CSV file ``path`` as (line, cells by lower-case column name, stripped),
    blank lines skipped. The header must name every column of ``required`` once; a record with
    another number of fields, a blank required field or damaged CSV raises ``error`` naming the
    file and line."""
    reader = csv.reader(io.StringIO(read_text(path, error), newline=""))
    header: list[str] | None = None
    try:
        for record in reader:
            cells = [c.strip() for c in record]
            if not any(cells):
                continue
            line = reader.line_num
            if header is None:
                header = [c.lower() for c in cells]
                for name in required:
                    if header.count(name) != 1:
                        how = "lacks" if name not in header else "repeats"
                        raise error(f"header {how} the column '{name}'", path=path, line=line)
                continue
            if len(cells) != len(header):
                raise error(f"{len(cells)} fields, the header has {len(header)}", path=path, line=line)
            value = dict(zip(header, cells, strict=True))
            for name in required:
                if not value[name]:
                    raise error(f"the '{name}' field is blank", path=path, line=line)
            yield line, value
    except csv.Error as exc:
        raise error(f"not valid CSV: {exc}", path=path, line=reader.line_num) from None
    if header is None:
        raise error(f"empty file: no header (it needs the columns {','.join(required)})", path=path, line=1)


def read_structured(path: str | Path, kind: Literal["json", "yaml"], error: type[MocapdError]) -> Any:
    """The parsed content of the UTF-8 JSON or YAML file ``path``; errors as :func:`read_text`, and
    text that is not valid ``kind`` raises ``error`` naming the file and the line."""
    text = read_text(path, error)
    if kind == "json":
        try:
            return json.loads(text)
        except json.JSONDecodeError as exc:
            raise error(f"not valid JSON: {exc.msg}", path=path, line=exc.lineno) from None
        except RecursionError:
            raise error("not valid JSON: nested too deeply", path=path) from None
    try:
        return yaml.safe_load(text)
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        problem = getattr(exc, "problem", None) or type(exc).__name__
        where: int | None = None if mark is None else mark.line + 1
        if isinstance(exc, yaml.reader.ReaderError):  # a character YAML refuses (no mark, no problem)
            code = exc.character if isinstance(exc.character, int) else ord(exc.character)
            problem = f"character U+{code:04X}: {exc.reason}"
            where = text[: exc.position].count("\n") + 1
        raise error(f"not valid YAML: {problem}", path=path, line=where) from None
    except RecursionError:
        raise error("not valid YAML: nested too deeply", path=path) from None


def number_reason(
    value: object,
    *,
    low: float | None = None,
    high: float | None = None,
    low_open: bool = False,
    high_open: bool = False,
    integer: bool = False,
) -> str | None:
    """Why ``value`` is not a finite number (an int with ``integer``; never a bool) in the given
    range, or None if it is."""
    kind = "an integer" if integer else "a number"
    if low == 0 and low_open and high is None:
        wanted = "a positive integer" if integer else "a positive number"
    elif low is not None and high is not None:
        wanted = f"{kind} in {'(' if low_open else '['}{low:g}, {high:g}{')' if high_open else ']'}"
    elif low is not None:
        wanted = f"{kind} {'>' if low_open else '>='} {low:g}"
    elif high is not None:
        wanted = f"{kind} {'<' if high_open else '<='} {high:g}"
    else:
        wanted = kind
    bad = f"must be {wanted}, got {value!r:.60}"
    types = int if integer else int | float
    if isinstance(value, bool) or not isinstance(value, types):
        return bad
    try:
        number = float(value)
    except OverflowError:  # an int too large for a float
        return bad
    if not math.isfinite(number):
        return bad
    if low is not None and (number <= low if low_open else number < low):
        return bad
    if high is not None and (number >= high if high_open else number > high):
        return bad
    return None


def join(field: str, key: str | int) -> str:
    """The field ``key`` (a name, or a list position) inside ``field``."""
    if isinstance(key, int):
        return f"{field}[{key}]"
    return f"{field}.{key}" if field else key


class Checker:
    """Checks of parsed JSON or YAML from ``source`` that raise ``error`` naming the source and the
    field (a dotted path below ``prefix``)."""

    def __init__(self, source: str | Path, error: type[MocapdError] = MocapdError, prefix: str = "") -> None:
        self.source = str(source)
        self.error = error
        self.prefix = prefix

    def fail(self, field: str, reason: str) -> NoReturn:
        whole = self.prefix + field if not field or field.startswith("[") else join(self.prefix, field)
        raise self.error(reason, path=self.source, field=whole or "top level")

    def mapping(
        self,
        value: object,
        field: str,
        required: Collection[str] = (),
        optional: Collection[str] = (),
        *,
        others: bool = False,
    ) -> dict[str, Any]:
        """``value`` as an object with string keys: every key of ``required``, any of ``optional``,
        and others only if ``others``."""
        if not isinstance(value, dict):
            self.fail(field, f"must be a mapping, got {_kind(value)}")
        for key in value:
            if not isinstance(key, str):
                self.fail(field, f"keys must be strings, got {key!r:.60}")
        missing = [k for k in required if k not in value]
        if missing:
            self.fail(field, f"missing {', '.join(missing)}")
        if not others:
            allowed = [*required, *optional]
            for key in value:
                if key not in allowed:
                    self.fail(join(field, key), f"unknown field (allowed: {', '.join(sorted(allowed))})")
        return value

    def listing(self, value: object, field: str, *, nonempty: bool = False) -> list[Any]:
        if not isinstance(value, list):
            self.fail(field, f"must be a list, got {_kind(value)}")
        if nonempty and not value:
            self.fail(field, "must not be empty")
        return value

    def string(self, value: object, field: str) -> str:
        """A non-empty string."""
        if not isinstance(value, str) or not value:
            self.fail(field, f"must be a non-empty string, got {value!r:.60}")
        return value

    def choice(self, value: object, field: str, options: Collection[str]) -> str:
        if not isinstance(value, str) or value not in options:
            self.fail(field, f"must be one of {', '.join(options)}, got {value!r:.60}")
        return value

    def integer(self, value: object, field: str, minimum: int | None = 0, maximum: int | None = None) -> int:
        reason = number_reason(value, low=minimum, high=maximum, integer=True)
        if reason is not None:
            self.fail(field, reason)
        assert isinstance(value, int)
        return value

    def number(
        self,
        value: object,
        field: str,
        *,
        low: float | None = None,
        high: float | None = None,
        low_open: bool = False,
        high_open: bool = False,
    ) -> float:
        reason = number_reason(value, low=low, high=high, low_open=low_open, high_open=high_open)
        if reason is not None:
            self.fail(field, reason)
        assert isinstance(value, int | float)
        return float(value)

    def positive_number(self, value: object, field: str) -> float:
        return self.number(value, field, low=0, low_open=True)

    def header(
        self, value: object, required: Collection[str], fmt: str, versions: Collection[int], rebuild: str
    ) -> dict[str, Any]:
        """The top level of a stored mocapd format: exactly ``required``, ``format`` equal to ``fmt``
        and ``version`` among ``versions`` (else: how to get a readable one, ``rebuild``)."""
        root = self.mapping(value, "", required)
        if root["format"] != fmt:
            self.fail("format", f"must be '{fmt}', got {root['format']!r:.60}")
        version = root["version"]
        if isinstance(version, bool) or version not in versions:
            known = ", ".join(map(str, versions))
            self.fail("version", f"this mocapd reads version {known}, got {version!r:.60}; {rebuild}")
        return root


def _kind(value: object) -> str:
    return {dict: "a mapping", list: "a list", str: "a string", type(None): "nothing"}.get(
        type(value), type(value).__name__
    )
