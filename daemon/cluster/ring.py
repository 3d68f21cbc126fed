"""Which live member owns which partition: rendezvous (highest random weight) hashing with bounded
loads.

Every (member, partition) pair has a :func:`score`, a stable hash of both. :func:`assignment` walks
the pairs from the highest score down and gives each partition to the first member it meets that
has room, a member's room being ``ceil(P / N)`` partitions of the ``P`` among ``N`` members (the
greedy matching of consistent hashing with bounded loads, Mirrokni, Thorup and Zadimoghaddam 2018,
on rendezvous scores). Every member computes the same answer from the same set of live members,
with no coordination beyond agreeing on that set.

Balance: no member owns more than ``ceil(P / N)``, so with the default 256 partitions the loads at 3
to 10 members are within 16 % of the mean (3 members: 84 to 86; 9: 24 to 29; 10: 22 to 26;
``tests/test_cluster_ring.py``).
Plain rendezvous hashing (this module before issue 34) throws each partition to a random member:
with 16 partitions one member of three owned 9 or more for one set of names in seven, and even 256
partitions leave a member of ten 20 % above the mean for most sets of names.

Moves: when a member leaves, its partitions go to the others, and the others' room grows, so some
partitions also move between the others (a partition whose higher-ranked member was full before now
fits there); a member joining takes its partitions from the others, with such moves too. Each move
costs the partition's buffer read again by its new owner. With 256 partitions, over 30 random sets of
names, these extra moves were on average 5 % (3 members) to 27 % (8 to 10 members) of the partitions
of the member that left or joined, at worst 54 % (``python -m bench.bench_ring``). Loosening the room to
``ceil(1.1 P / N)`` halves them but lets a member of ten fall to 14 partitions, 45 % below the mean.

Streams: they are spread over partitions by a hash of their id (``protocols.nats.partition_of``),
so the ring alone balances streams per worker only as their hashes do (within ±20 % from about 100
streams per worker). Given ``weights`` (the streams each partition holds, as the cluster's leader
last measured and wrote them: ``docs/cluster.md``, "Balance"), :func:`assignment` then evens the
members' loads out (:func:`even_out`): it moves a partition with streams from a member with more
to one with fewer (or swaps two), each move or swap strictly lowering the sum of the squared loads,
and gives back a partition without streams for each one moved so that the partition counts stay
as the ring made them; it stops when no such move is left.

Pure: no I/O, no clock, no randomness; the hash is BLAKE2b, never Python's per-process salted
``hash()``, so every process ranks alike.
"""

from __future__ import annotations

import hashlib
from collections.abc import Callable, Iterable, Mapping

from daemon.errors import InputError

_SEPARATOR = b"\xff"  # never in UTF-8: the member's bytes end unambiguously before the partition's


def score(member: str, partition: int) -> int:
    """The rank of ``member`` for ``partition``: a stable unsigned 64-bit hash of both (BLAKE2b)."""
    digest = hashlib.blake2b(
        member.encode("utf-8", "surrogatepass") + _SEPARATOR + partition.to_bytes(8, "big", signed=True),
        digest_size=8,
    ).digest()
    return int.from_bytes(digest, "big")


def _check(partitions: int) -> None:
    if partitions < 0:
        raise InputError(f"partitions must be 0 or more, got {partitions}")


def room(members: int, partitions: int) -> int:
    """The most partitions one of ``members`` live members may own: ``ceil(partitions / members)``."""
    return -(-partitions // members) if members else 0


Weights = Mapping[int, int]
"""Streams per partition (absent: none)."""


def assignment(
    members: Iterable[str], partitions: int, weights: Weights | None = None
) -> dict[str, frozenset[int]]:
    """Every member (duplicates once) with the partitions of ``0 .. partitions-1`` it owns, maybe
    none (module docstring; equal scores: the smaller name first, then the smaller partition); with
    ``weights``, the members' streams evened out (:func:`even_out`)."""
    owned = _ring(members, partitions)
    if weights:
        even_out(owned, weights)
    return {m: frozenset(ps) for m, ps in owned.items()}


def loads(owned: Mapping[str, Iterable[int]], weights: Weights) -> dict[str, int]:
    """Each member's streams: the ``weights`` of the partitions it owns."""
    return {m: sum(weights.get(p, 0) for p in ps) for m, ps in owned.items()}


def spread(counts: Mapping[str, int]) -> float:
    """How far the fullest or emptiest member is from the mean, as a share of the mean (0: no
    streams)."""
    if not counts or not sum(counts.values()):
        return 0.0
    mean = sum(counts.values()) / len(counts)
    return max(max(counts.values()) - mean, mean - min(counts.values())) / mean


def even_out(owned: dict[str, set[int]], weights: Weights) -> None:
    """Move partitions between the members of ``owned`` (in place) until no move of one partition
    with streams, nor swap of two, from a fuller member to an emptier one lowers the sum of the
    squared loads (a move of ``w`` streams across a gap of ``g`` does exactly when ``0 < w < g``;
    the one chosen brings the two loads closest together, ties to the smaller partitions; the
    fullest pair first, ties to the smaller names). For each partition moved, the emptier member
    gives back the partition without streams that the fuller one ranks highest, if it has one."""

    def w(p: int) -> int:
        return weights.get(p, 0)

    load = loads(owned, weights)
    while True:
        order = sorted(load, key=lambda m: (load[m], m))
        step = next(
            (
                (hi, lo, found)
                for hi in reversed(order)
                for lo in order
                if load[hi] - load[lo] > 1 and (found := _best(owned[hi], owned[lo], load[hi] - load[lo], w))
            ),
            None,
        )
        if step is None:
            return
        hi, lo, (p, q) = step
        owned[hi].remove(p)
        owned[lo].add(p)
        if q is None:
            empty = [e for e in owned[lo] if not w(e)]
            if empty:
                q = max(empty, key=lambda e: (score(hi, e), -e))
        if q is not None:
            owned[lo].remove(q)
            owned[hi].add(q)
        moved = w(p) - (0 if q is None else w(q))
        load[hi] -= moved
        load[lo] += moved


def _best(
    fuller: set[int], emptier: set[int], gap: int, w: Callable[[int], int]
) -> tuple[int, int | None] | None:
    """The move (partition, None) or swap (partition, partition) from ``fuller`` to ``emptier``
    whose streams ``0 < d < gap`` bring the two closest together (None: no such)."""
    moves = [(abs(gap - 2 * w(p)), p, -1) for p in fuller if 0 < w(p) < gap]
    if moves:
        _, p, _ = min(moves)
        return p, None
    swaps = [
        (abs(gap - 2 * (w(p) - w(q))), p, q)
        for p in fuller
        if w(p)
        for q in emptier
        if w(q) > 0 and 0 < w(p) - w(q) < gap
    ]
    if not swaps:
        return None
    _, p, q = min(swaps)
    return p, q


def _ring(members: Iterable[str], partitions: int) -> dict[str, set[int]]:
    """The ring alone: bounded-load rendezvous hashing over partition counts."""
    _check(partitions)
    live = sorted(set(members))
    owned: dict[str, set[int]] = {m: set() for m in live}
    most = room(len(live), partitions)
    pairs = sorted((-score(m, p), m, p) for m in live for p in range(partitions))
    taken: set[int] = set()
    for _, m, p in pairs:
        if p not in taken and len(owned[m]) < most:
            taken.add(p)
            owned[m].add(p)
            if len(taken) == partitions:
                break
    return owned


def owned(
    member: str, members: Iterable[str], partitions: int, weights: Weights | None = None
) -> frozenset[int]:
    """The partitions ``member`` owns among ``members`` (with ``weights``, :func:`assignment`):
    none if it is not one of them (a member that is not live owns nothing)."""
    _check(partitions)
    live = set(members)
    if member not in live:
        return frozenset()
    return assignment(live, partitions, weights)[member]


def orphaned(
    partitions: Iterable[int],
    before: Iterable[str],
    after: Iterable[str],
    count: int,
    weights: Weights | None = None,
) -> frozenset[int]:
    """Those of ``partitions`` whose owner among the members ``before`` (with the ``weights`` of
    then) is not among ``after`` (it left or died), or that had no owner: nobody else can be
    reading them, so a new owner may take them at once. ``count``: the number of partitions."""
    _check(count)
    live = set(after)
    ring = assignment(before, count, weights)
    owner = {p: m for m, ps in ring.items() for p in ps}
    return frozenset(p for p in partitions if owner.get(p) not in live)
