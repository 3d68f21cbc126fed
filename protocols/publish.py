"""A recording as a live stream's messages (``mocapd replay``; :mod:`protocols.replay` sends them):
the skeleton announced (the ASF text), then every frame's channels as a pose, and when each is due.

Pacing: frame i (counted from the first frame's number, so a frame missing from the recording
leaves its time empty) is due at t0 + i / (rate * speed), t0 the time the first frame went out;
each frame waits for its own due time, so sleeping late never accumulates into drift over a long
file (``speed`` None: as fast as the transport takes them). Sequence numbers are the AMC frame
numbers (a recording's missing frames are missing from the stream too), continued across passes
with ``loop``; each pose carries the time it was sent and the replay's epoch (one run of the source,
``protocols/README.md``, "A stream's life"). Pure: no sockets.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from daemon.types import FloatArray, IntArray
from protocols.messages import EndMessage, FrameMessage, PoseMessage, SkeletonMessage, Units, Up, frame_of
from replay.amc import Motion


@dataclass(frozen=True)
class Positions:
    """A recording of joint positions (a BVH take through its rig map, :mod:`replay.rigs`):
    ``frames`` ``(N,)``, ``joints`` ``(N, J, 3)`` named ``names``, ``up`` axis, length ``units``."""

    frames: IntArray
    joints: FloatArray
    names: tuple[str, ...]
    up: Up = "y"
    units: Units = "cm"

    def __len__(self) -> int:
        return len(self.frames)


@dataclass(frozen=True)
class BvhChannels:
    """A BVH take as it is (a bridge forwarding a BVH broadcast): its ``hierarchy`` (the
    ``HIERARCHY`` text), ``frames`` ``(N,)``, ``channels`` ``(N, C)`` as its ``MOTION`` rows hold
    them, the ``up`` axis it stands along and its length ``units``."""

    hierarchy: str
    frames: IntArray
    channels: FloatArray
    up: Up = "y"
    units: Units = "cm"

    def __len__(self) -> int:
        return len(self.frames)


Recording = Motion | Positions | BvhChannels
"""What a replay sends: AMC channels, joint positions, or a BVH take's channels."""

Items = Iterator[SkeletonMessage | PoseMessage | FrameMessage | EndMessage]
"""A replay's messages in the order they go out."""


def due(start: float, i: int, rate: float, speed: float | None) -> float:
    """When frame ``i`` of a replay begun at ``start`` goes out (``speed`` None: at once)."""
    return start if speed is None else start + i / (rate * speed)


def messages(
    motion: Recording,
    asf_text: str,
    stream: str,
    rate: float,
    passes: int | None,
    epoch: str | None = None,
) -> Items:
    """The skeleton (``asf_text``'s channels, ``motion``'s joint names if it is :class:`Positions`,
    its hierarchy if it is :class:`BvhChannels`), then one pose per frame (``passes`` times through
    the recording; None: for ever), sequence numbers the frame numbers, each pass's after the
    last's, all of run ``epoch``; ``time`` is filled when sent; then the run's end."""
    if isinstance(motion, Positions):
        yield SkeletonMessage(
            stream, rate, joints=motion.names, up=motion.up, units=motion.units, epoch=epoch
        )
        rows: npt.NDArray[Any] = motion.joints.astype(np.float32)
    elif isinstance(motion, BvhChannels):
        yield SkeletonMessage(
            stream, rate, up=motion.up, units=motion.units, bvh=motion.hierarchy, epoch=epoch
        )
        rows = motion.channels
    else:
        yield SkeletonMessage(stream, rate, asf=asf_text, angle_unit="rad", epoch=epoch)
        rows = motion.channels
    if not len(motion):
        return
    span = int(motion.frames[-1]) - int(motion.frames[0]) + 1
    done = 0
    seq = 0
    positions = isinstance(motion, Positions)
    while passes is None or done < passes:
        for number, row in zip(motion.frames.tolist(), rows, strict=True):
            seq = number + done * span
            values = np.ascontiguousarray(row)
            if positions:
                yield PoseMessage(stream, seq, 0.0, positions=values, epoch=epoch)
            else:
                yield PoseMessage(stream, seq, 0.0, channels=values, epoch=epoch)
        done += 1
    yield EndMessage(stream, seq, epoch)


def framed(streams: list[Items], source: str) -> Items:
    """Several streams' messages (each :func:`messages`) as one source sends them (``protocols/
    README.md``, ``frame``): every skeleton first, then per step the next pose of every stream that
    has one in one frame message from ``source`` (a second one if the streams carry both channels
    and positions), each stream's end once its poses are over. Time stamps are filled when sent."""
    live: list[Items] = []
    ends: list[EndMessage] = []
    for items in streams:
        first = next(items)
        assert isinstance(first, SkeletonMessage)
        yield first
        live.append(items)
    while live:
        poses: list[PoseMessage] = []
        going: list[Items] = []
        for items in live:
            m = next(items)
            if isinstance(m, EndMessage):
                ends.append(m)
                continue
            assert isinstance(m, PoseMessage)
            poses.append(m)
            going.append(items)
        live = going
        for kind in ("channels", "positions"):
            mine = [p for p in poses if (p.channels is not None) == (kind == "channels")]
            if mine:
                yield frame_of(mine, source, mine[0].epoch)
        yield from ends
        ends = []
