"""The contract every streaming stage follows, so that the recogniser can chain them uniformly.

A stage takes one item at a time and returns the items that became final (none, one or several);
at the end of a stream :meth:`Stage.flush` returns what is still pending and starts a new stream.
Its state is bounded whatever the stream's length, and it has a batch twin (a function over the
whole sequence) that gives the same output. :class:`~daemon.features.FeatureStream`,
:class:`~daemon.features.Decimator`, :class:`~daemon.search.segments.Segmenter` and
:class:`~daemon.dtw.SubsequenceStream` are stages.
"""

from __future__ import annotations

from collections.abc import Iterable
from typing import Generic, Protocol, TypeVar

In = TypeVar("In")
Mid = TypeVar("Mid")
Out = TypeVar("Out")
In_contra = TypeVar("In_contra", contravariant=True)


class Stage(Protocol[In_contra, Out]):
    """``push(item) -> list`` of the outputs that became final; ``flush() -> list`` of the rest, then
    a fresh state."""

    def push(self, item: In_contra, /) -> list[Out]: ...

    def flush(self) -> list[Out]: ...


class Chain(Generic[In, Mid, Out]):
    """Two stages in series, itself a stage: every output of ``first`` is pushed into ``second``;
    ``flush`` flushes ``first``, pushes what it gave, then flushes ``second``."""

    def __init__(self, first: Stage[In, Mid], second: Stage[Mid, Out]) -> None:
        self.first = first
        self.second = second

    def push(self, item: In, /) -> list[Out]:
        return [y for x in self.first.push(item) for y in self.second.push(x)]

    def flush(self) -> list[Out]:
        out = [y for x in self.first.flush() for y in self.second.push(x)]
        return out + self.second.flush()


def run(stage: Stage[In, Out], items: Iterable[In]) -> list[Out]:
    """Every output of ``stage`` for ``items`` followed by its flush (a whole stream)."""
    out = [y for x in items for y in stage.push(x)]
    return out + stage.flush()
