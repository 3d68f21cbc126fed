""":func:`protocols.endpoints.each_in_turn` against its definition on random outcomes: each endpoint
tried in turn for its share of the time; the first that answers wins; a listed error or the timeout
moves on, any other error stops at once; all failing raises the last failure."""

from __future__ import annotations

import asyncio

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from protocols.endpoints import each_in_turn

OUTCOMES = st.sampled_from(["answer", "refused", "silent", "broken"])


class Broken(Exception):
    """An error not in the list: not a reason to try the next endpoint."""


@settings(max_examples=60, deadline=None)
@given(st.lists(OUTCOMES, min_size=1, max_size=4))
def test_each_endpoint_in_turn_until_one_answers(outcomes: list[str]) -> None:
    tried: list[int] = []

    async def attempt(k: int, endpoint: str) -> str:
        tried.append(k)
        if endpoint == "refused":
            raise ConnectionRefusedError(k)
        if endpoint == "silent":
            await asyncio.sleep(10)
        if endpoint == "broken":
            raise Broken(k)
        return f"answered by {k}"

    stop = next((k for k, o in enumerate(outcomes) if o in ("answer", "broken")), None)
    run = each_in_turn(outcomes, attempt, 0.02 * len(outcomes), (OSError,))
    if stop is not None and outcomes[stop] == "answer":
        assert asyncio.run(run) == f"answered by {stop}"
    else:
        last = outcomes[-1] if stop is None else "broken"
        expected = {"refused": ConnectionRefusedError, "silent": TimeoutError, "broken": Broken}[last]
        with pytest.raises(expected):
            asyncio.run(run)
    assert tried == list(range(len(outcomes) if stop is None else stop + 1))


def test_no_endpoints_is_an_error() -> None:
    async def attempt(k: int, endpoint: str) -> str:
        return endpoint

    with pytest.raises(ValueError, match="no endpoints"):
        asyncio.run(each_in_turn([], attempt, 1.0, (OSError,)))
