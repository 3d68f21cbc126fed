"""Standard output as a sink: every published message as one JSON line (``{"topic": ..., **fields}``,
bytes fields as hex) or, with ``format: text``, a readable line per detection, boundary and
progress event. Lines are flushed at once, so a pipe sees each detection when it is published."""

from __future__ import annotations

import json
import sys
from types import TracebackType
from typing import TYPE_CHECKING, Any, TextIO

import msgpack

from protocols.transport import Outgoing

if TYPE_CHECKING:
    from daemon.config import StdoutConfig


def _plain(value: Any) -> Any:
    return value.hex() if isinstance(value, bytes) else value


class StdoutTransport:
    """A sink writing to ``stream`` (None: ``sys.stdout``) in the ``format`` of ``settings``
    (``daemon.config.StdoutConfig``: ``json`` or ``text``)."""

    name = "stdout"

    def __init__(self, settings: StdoutConfig, stream: TextIO | None = None) -> None:
        self.format = settings.format
        self.stream = stream
        self._status: tuple[Outgoing, Outgoing] | None = None

    def announce(self, online: Outgoing, offline: Outgoing) -> None:
        """Print ``online`` on entering and ``offline`` on leaving."""
        self._status = (online, offline)

    async def __aenter__(self) -> StdoutTransport:
        if self._status is not None:
            await self.publish(self._status[0])
        return self

    async def __aexit__(
        self, kind: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        if self._status is not None:
            await self.publish(self._status[1])
        (self.stream or sys.stdout).flush()

    def source(self) -> None:
        return None

    def ask_skeleton(self, stream: str) -> None:
        """Nothing: stdout takes nothing in."""

    def sink(self) -> StdoutTransport:
        return self

    def drain_within(self, seconds: float) -> None:
        """Nothing: every line is written when it is published."""

    @property
    def pending(self) -> int:
        return 0

    async def publish(self, message: Outgoing) -> None:
        if message.relay or message.reminder:  # for viewers and watchers, not the daemon's output
            return
        body = msgpack.unpackb(message.payload, raw=False)
        out = self.stream or sys.stdout
        if self.format == "json":
            line = json.dumps({"topic": message.topic, **{k: _plain(v) for k, v in body.items()}})
        elif body.get("type") == "detection":
            line = (
                f"{body['stream']}: {body['class']:30s} frames {body['start_frame']}-{body['end_frame']}  "
                f"cost {body['cost']:.3f} (tau {body['tau']:.3f})"
            )
        elif body.get("type") == "boundary":
            line = (
                f"{body['stream']}: boundary at frame {body['frame']} ({body['method']}, {body['score']:.3g})"
            )
        elif body.get("type") == "progress":
            line = f"{body['stream']}: progress at frame {body['frame']}: " + (
                ", ".join(
                    f"{c['class']} {c['position']:.0%} (cost {c['cost']:.3f}"
                    + (f", keyframes {len(c['matched'])}/{c['keyframes']})" if c["keyframes"] else ")")
                    for c in body["classes"]
                )
                or "nothing under way"
            )
        elif body.get("type") == "status":
            line = f"mocapd {body['instance']} {body['state']} ({body['streams']} streams)"
        else:
            return
        out.write(line + "\n")
        out.flush()

    @property
    def problem(self) -> str | None:
        return None

    def dropped(self) -> dict[str, int]:
        return {}


def transport(settings: StdoutConfig, *, instance: str, source: bool, sink: bool) -> StdoutTransport:
    """The daemon's stdout sink (:class:`protocols.transport.Factory`; never a source)."""
    return StdoutTransport(settings)
