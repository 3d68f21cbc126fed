"""``mocapd run --replay``: a recording replayed into the service's own first source, and the stop
once every pose sent has been received and recognised."""

from __future__ import annotations

import asyncio
import time
from collections.abc import Callable, Coroutine
from typing import TYPE_CHECKING, Any

from protocols.replay import replay_to
from replay.amc import Motion

if TYPE_CHECKING:
    from daemon.service.app import Service

Task = tuple[str, Callable[[], Coroutine[Any, Any, None]]]
Tasks = Callable[["Service", asyncio.Event], list[Task]]


def replay_then_stop(
    url: str, motion: Motion, asf_text: str, *, stream: str, rate: float, speed: float | None
) -> Tasks:
    """The service's extra task: once it serves, ``motion`` replayed to ``url`` as ``stream``; after
    0.3 s with nothing queued, the stop event set."""

    def tasks(service: Service, stop: asyncio.Event) -> list[Task]:
        async def run() -> None:
            while service.health() is not None:
                await asyncio.sleep(0.01)
            await replay_to(url, motion, asf_text, stream=stream, rate=rate, speed=speed)
            quiet = time.monotonic()
            while time.monotonic() - quiet < 0.3:  # the last poses received, nothing queued
                await asyncio.sleep(0.02)
                if service.table.queued:
                    quiet = time.monotonic()
            stop.set()

        return [("replay", run)]

    return tasks
