"""Where a partition's new owner can start reading its buffer (docs/cluster.md, "Checkpoints").

A worker takes a :class:`Sample` of a partition whenever the partition is *settled*: every message
its buffer delivered up to sequence :attr:`Sample.position` has been recognised and every detection
that came of it stored. A recogniser's detections depend on the poses of a bounded reach only
(:attr:`daemon.recognizer.Recognizer.reach`), so a new owner that reads the buffer from after such
a position, with the detections of each stream's warm-up suppressed, computes every detection the
old owner had not yet stored, provided each stream has been fed enough frames since the sample:
twice its warm-up (the warm-up whose detections are suppressed, then the reach of a detection not
yet stored) and a second for its skeleton's next announcement and a margin. :func:`resume_after`
picks the newest such sample; its position, with the runs its streams were in, is the checkpoint a
worker stores: the new owner suppresses the warm-up of those runs only (a stream not fed before the
position is read from its start).

Why positions and not the recognisers' whole state: the state is a function of the last warm-up's
poses but for one thing, the body lengths the features' thresholds are multiples of, measured on the
stretch's first pose (a recogniser started elsewhere gave another cost to 1 detection in 37 of a
looped recording, ``tests/test_cluster_table.py``). So a checkpoint stores those lengths with
each run, and rebuilding the rest costs the replay of two warm-ups per stream, whatever the buffer's
length, with no serialised form of the compiled recognisers that could drift from the running ones.

Pure: no I/O, no clock.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass


@dataclass(frozen=True, slots=True)
class Fed:
    """A stream's progress in a worker's table: its run (the table's generation of the stream and
    the source's epoch: either changes when the stream starts anew), the sequence number of the
    last pose fed to its recogniser (-1: none yet), and the body lengths its features' thresholds
    are multiples of (:class:`daemon.features.language.BodyLengths`, measured on the first pose of
    the stretch it is in: the one state of a recogniser that outlasts its warm-up, which a new
    owner must take over)."""

    run: tuple[int, str | None]
    seq: int
    lengths: tuple[float, ...] | None = None


@dataclass(frozen=True, slots=True)
class Sample:
    """A partition settled: every buffered message up to ``position`` recognised and what came of
    it stored; ``fed``: each of the partition's streams' progress then."""

    position: int
    fed: Mapping[str, Fed]


def far_enough(then: Fed | None, now: Fed, need: int) -> bool:
    """Whether a stream fed ``now`` (``seq`` -1: nothing yet) lies far enough after a sample that
    had it at ``then``: the stream was made (its skeleton taken) after the sample (``then`` None, or
    another generation), so that all of it lies after; or it has been fed at least ``need`` frames
    of the same run since. A run or a numbering that began anew without a new skeleton is not far
    enough: the new owner would lack its skeleton until the next announcement (a later sample
    serves once it is)."""
    if then is None or then.run[0] != now.run[0]:
        return True
    return then.run == now.run and then.seq <= now.seq and now.seq - then.seq >= need


def resume_after(samples: Sequence[Sample], now: Mapping[str, Fed], need: Mapping[str, int]) -> Sample | None:
    """The newest of ``samples`` (oldest first) after which each stream of ``now`` (its progress at
    the latest settled moment) lies :func:`far_enough`; None if none is such a sample."""
    for sample in reversed(samples):
        if all(far_enough(sample.fed.get(s), fed, need[s]) for s, fed in now.items()):
            return sample
    return None
