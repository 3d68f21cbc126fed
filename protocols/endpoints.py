"""Several servers of one service (NATS servers, etcd members) tried in turn at start-up."""

from __future__ import annotations

import asyncio
from collections.abc import Awaitable, Callable, Sequence
from typing import TypeVar

E = TypeVar("E")
R = TypeVar("R")


async def each_in_turn(
    endpoints: Sequence[E],
    attempt: Callable[[int, E], Awaitable[R]],
    seconds: float,
    errors: tuple[type[BaseException], ...],
) -> R:
    """``attempt(k, endpoint)`` for each of ``endpoints`` in turn, each for its share of
    ``seconds`` (TimeoutError past it), until one returns: what it returned. An error of ``errors``
    (or the timeout) moves on to the next endpoint; any other is raised at once. When every one
    failed, the last failure is raised. ``attempt`` cleans up after itself."""
    if not endpoints:
        raise ValueError("no endpoints to try")
    failure: BaseException | None = None
    caught: tuple[type[BaseException], ...] = (TimeoutError, *errors)
    for k, endpoint in enumerate(endpoints):
        try:
            async with asyncio.timeout(seconds / len(endpoints)):
                return await attempt(k, endpoint)
        except caught as e:
            failure = e
    assert failure is not None
    raise failure
