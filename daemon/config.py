"""``config.yaml``, parsed once at the edge into frozen dataclasses; errors name the file and field."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal, cast, get_args

from daemon.checks import Checker, read_structured
from daemon.errors import MocapdError
from daemon.types import DEFAULT_MAX_GAP_S, DEFAULT_NATIVE_RATE, MAX_NATIVE_RATE

Units = Literal["asf", "cm"]


class ConfigError(MocapdError, ValueError):
    """A configuration value that cannot be used; the message names the file and the field."""


@dataclass(frozen=True)
class ReplayConfig:
    """How recordings are read: the frame rate assumed when an AMC file does not state one, and the
    units of joint positions."""

    frame_rate_hz: float = DEFAULT_NATIVE_RATE
    units: Units = "asf"


@dataclass(frozen=True)
class RecognizerConfig:
    """The live recogniser (:mod:`daemon.recognizer`): how far an unbounded keyframe gap (stiffness
    0) may reach, in seconds."""

    max_gap_s: float = DEFAULT_MAX_GAP_S


@dataclass(frozen=True)
class Config:
    replay: ReplayConfig = field(default_factory=ReplayConfig)
    recognizer: RecognizerConfig = field(default_factory=RecognizerConfig)


def load_config(path: str | Path | None) -> Config:
    """Read ``path`` (``None``: the built-in defaults)."""
    if path is None:
        return Config()
    data = read_structured(path, "yaml", ConfigError)
    return parse_config({} if data is None else data, str(path))


def parse_config(data: object, source: str = "<config>") -> Config:
    """Build a :class:`Config` from parsed YAML; unknown or ill-typed fields are errors."""
    check = Checker(source, ConfigError)
    root = check.mapping(data, "", optional=("replay", "recognizer"))
    section = root.get("replay")
    replay = check.mapping({} if section is None else section, "replay", optional=("frame_rate_hz", "units"))
    defaults = ReplayConfig()
    rate = check.number(
        replay.get("frame_rate_hz", defaults.frame_rate_hz),
        "replay.frame_rate_hz",
        low=0,
        low_open=True,
        high=MAX_NATIVE_RATE,
    )
    units = check.choice(replay.get("units", defaults.units), "replay.units", get_args(Units))
    section = root.get("recognizer")
    live = check.mapping({} if section is None else section, "recognizer", optional=("max_gap_s",))
    gap = check.number(
        live.get("max_gap_s", DEFAULT_MAX_GAP_S), "recognizer.max_gap_s", low=0, low_open=True, high=3600
    )
    return Config(
        replay=ReplayConfig(frame_rate_hz=rate, units=cast(Units, units)),
        recognizer=RecognizerConfig(max_gap_s=gap),
    )
