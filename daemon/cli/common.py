"""What several commands share: option types, the recording and rate options, and outputs that are
checked before the work and written beside their target."""

from __future__ import annotations

import argparse
import math
import sys
from collections.abc import Callable
from pathlib import Path
from typing import IO, Any

from daemon.checks import number_reason
from daemon.config import Config
from daemon.errors import FileAccessError, UsageError
from daemon.plots import check_plotting
from daemon.recordings import read_rig_maps
from daemon.storage import check_directory, check_output_file, output_file
from daemon.types import MAX_NATIVE_RATE
from replay.rigs import RigMap

STDOUT = "-"


def positive_float(text: str) -> float:
    """An option value that must be a positive number."""
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if number_reason(value, low=0, low_open=True) is not None:
        raise argparse.ArgumentTypeError(f"must be a positive number, got '{text}'")
    return value


def non_negative_int(text: str) -> int:
    """An option value that must be a whole number, 0 or more."""
    try:
        value = int(text)
    except ValueError:
        value = -1
    if value < 0:
        raise argparse.ArgumentTypeError(f"must be a whole number, 0 or more, got '{text}'")
    return value


def native_rate(text: str) -> float:
    """An option value that must be a capture rate: a positive number up to the highest rate
    features are computed at."""
    value = positive_float(text)
    if value > MAX_NATIVE_RATE:
        raise argparse.ArgumentTypeError(f"must be at most {MAX_NATIVE_RATE:g} Hz, got '{text}'")
    return value


def rate_option(command: argparse.ArgumentParser, default: float | None, purpose: str) -> None:
    """``--fps HZ``: a rate the command works at, every k-th frame of each recording's native rate."""
    command.add_argument(
        "--fps",
        type=positive_float,
        default=default,
        metavar="HZ",
        help=f"{purpose}: every k-th frame of the native rate, which it must divide",
    )


def recording_options(command: argparse.ArgumentParser, *, bvh: bool = False) -> None:
    """``--asf`` and ``--amc``; with ``bvh``, or ``--bvh`` instead (:func:`bvh_or_asf` checks)."""
    command.add_argument("--asf", type=Path, required=not bvh, help="ASF skeleton file")
    command.add_argument("--amc", type=Path, required=not bvh, help="AMC motion file, plain or gzip")
    if bvh:
        command.add_argument(
            "--bvh",
            type=Path,
            default=None,
            help="a BVH recording, plain or gzip, instead of --asf and --amc",
        )
        rig_option(command)
    native_rate_option(command)


def rig_option(command: argparse.ArgumentParser) -> None:
    """``--rig YAML``: a user's rig map for BVH recordings (:func:`rig_maps`)."""
    command.add_argument(
        "--rig",
        type=Path,
        default=None,
        metavar="YAML",
        help="a rig map for BVH recordings (docs/recordings-and-features.md), tried before the built-in ones",
    )


def stream_name(recording: Path) -> str:
    """A recording's stream id by default: its file name without ``.amc``/``.bvh`` and ``.gz``."""
    return recording.name.removesuffix(".gz").removesuffix(".amc").removesuffix(".bvh")


def rig_maps(args: argparse.Namespace, config: Config) -> tuple[RigMap, ...]:
    """``--rig``'s map (if given), the configuration's (``replay.rig_maps``), then the built-in
    ones."""
    return read_rig_maps([*([] if args.rig is None else [args.rig]), *config.replay.rig_maps])


def bvh_or_asf(args: argparse.Namespace) -> Path | None:
    """The ``--bvh`` given (None: ``--asf`` and ``--amc`` are); UsageError for neither or both."""
    bvh: Path | None = args.bvh
    if bvh is not None and (args.asf is not None or args.amc is not None):
        raise UsageError("give --bvh, or --asf and --amc, not both", field="--bvh")
    if bvh is None and (args.asf is None or args.amc is None):
        raise UsageError(
            "give --asf and --amc (or --bvh)", field="--amc" if args.asf is not None else "--asf"
        )
    return bvh


def native_rate_option(command: argparse.ArgumentParser) -> None:
    command.add_argument(
        "--native-fps",
        type=native_rate,
        default=None,
        metavar="HZ",
        help="the rate recordings were captured at when their AMC file states none "
        "(default: config replay.frame_rate_hz, 120)",
    )


def default_native_rate(args: argparse.Namespace, config: Config) -> float:
    """The rate assumed for recordings whose AMC states none: ``--native-fps``, else the config's."""
    given: float | None = args.native_fps
    return config.replay.frame_rate_hz if given is None else given


# ------------------------------------------------------------------------------------------ outputs


def check_csv_output(path: Path) -> None:
    """Before the work: ``path`` can be written (``-`` is stdout)."""
    if str(path) != STDOUT:
        check_output_file(path)


def write_csv(path: Path, write: Callable[[IO[str]], None]) -> None:
    """``write`` the CSV to stdout (``-``) or into ``path``, which is replaced only when complete."""
    if str(path) == STDOUT:
        write(sys.stdout)
        return
    with output_file(path) as out:
        write(out)


def check_png_output(path: Path, *, directory: bool = False) -> None:
    """Before the work: PNGs can be drawn (matplotlib is there) and ``path`` is a ``.png`` file that
    can be written, or with ``directory`` a directory PNGs can be written in (created when the first
    is written)."""
    if directory:
        check_directory(path)
    else:
        if path.is_dir():
            raise FileAccessError("is a directory; --png names the PNG file to write", path=path)
        if path.suffix.lower() != ".png":
            raise UsageError(f"'{path}' does not end in .png (only PNG is written)", field="--png")
        check_output_file(path)
    check_plotting()


def write_png(path: Path, draw: Callable[[IO[bytes]], Any]) -> None:
    """``draw`` a PNG into ``path`` (its directory created if missing), which is replaced only when
    complete."""
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise FileAccessError.from_os_error(exc, path.parent) from None
    with output_file(path, "wb") as out:
        draw(out)
