"""``config.yaml``, parsed once at the edge into frozen dataclasses; errors name the file and field."""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal, cast

import yaml

Units = Literal["asf", "cm"]


class ConfigError(ValueError):
    """A configuration value that cannot be used; the message names the file and the field."""


@dataclass(frozen=True)
class ReplayConfig:
    """How recordings are read: the frame rate assumed when an AMC file does not state one, and the
    units of joint positions."""

    frame_rate_hz: float = 120.0
    units: Units = "asf"


@dataclass(frozen=True)
class Config:
    replay: ReplayConfig = field(default_factory=ReplayConfig)


def load_config(path: str | Path | None) -> Config:
    """Read ``path`` (``None``: the built-in defaults)."""
    if path is None:
        return Config()
    source = str(path)
    try:
        text = Path(path).read_text(encoding="utf-8")
    except OSError as exc:
        raise ConfigError(f"{source}: cannot read ({exc.strerror})") from None
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f" at line {mark.line + 1}" if mark is not None else ""
        problem = getattr(exc, "problem", None) or type(exc).__name__
        raise ConfigError(f"{source}: not valid YAML{where}: {problem}") from None
    return parse_config({} if data is None else data, source)


def parse_config(data: object, source: str = "<config>") -> Config:
    """Build a :class:`Config` from parsed YAML; unknown or ill-typed fields are errors."""
    root = _mapping(data, source, "")
    _known(root, {"replay"}, source, "")
    replay = _mapping(root.get("replay") or {}, source, "replay")
    _known(replay, {"frame_rate_hz", "units"}, source, "replay")
    defaults = ReplayConfig()
    rate = replay.get("frame_rate_hz", defaults.frame_rate_hz)
    if not _positive_number(rate):
        raise ConfigError(f"{source}: replay.frame_rate_hz must be a positive number, got {rate!r}")
    units = replay.get("units", defaults.units)
    if units not in ("asf", "cm"):
        raise ConfigError(f"{source}: replay.units must be 'asf' or 'cm', got {units!r}")
    return Config(replay=ReplayConfig(frame_rate_hz=float(rate), units=cast(Units, units)))


def _positive_number(value: object) -> bool:
    if isinstance(value, bool) or not isinstance(value, int | float):
        return False
    try:
        return math.isfinite(value) and value > 0
    except OverflowError:  # an int too large for a float
        return False


def _mapping(value: object, source: str, where: str) -> Mapping[str, Any]:
    if not isinstance(value, Mapping):
        raise ConfigError(
            f"{source}: {where or 'the top level'} must be a mapping, got {type(value).__name__}"
        )
    return cast(Mapping[str, Any], value)


def _known(section: Mapping[str, Any], allowed: set[str], source: str, where: str) -> None:
    for key in section:
        if key not in allowed:
            name = f"{where}.{key}" if where else str(key)
            raise ConfigError(f"{source}: unknown field '{name}' (allowed: {', '.join(sorted(allowed))})")
