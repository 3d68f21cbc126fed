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

Streams are spread over partitions by a hash of their id (``protocols.nats.partition_of``), so the
streams per worker balance as the streams' hashes do: evenly with many streams per worker, within
±20 % only from about 100 streams per worker (docs/cluster.md, "Partitions").

Pure: no I/O, no clock, no randomness; the hash is BLAKE2b, never Python's per-process salted
``hash()``, so every process ranks alike.
"""

from __future__ import annotations

import hashlib
from collections.abc import Iterable

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


def assignment(members: Iterable[str], partitions: int) -> dict[str, frozenset[int]]:
    """Every member (duplicates once) with the partitions of ``0 .. partitions-1`` it owns, maybe
    none (module docstring; equal scores: the smaller name first, then the smaller partition)."""
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
    return {m: frozenset(ps) for m, ps in owned.items()}


def owned(member: str, members: Iterable[str], partitions: int) -> frozenset[int]:
    """The partitions ``member`` owns among ``members``: none if it is not one of them (a member
    that is not live owns nothing)."""
    _check(partitions)
    live = set(members)
    if member not in live:
        return frozenset()
    return assignment(live, partitions)[member]


def orphaned(
    partitions: Iterable[int], before: Iterable[str], after: Iterable[str], count: int
) -> frozenset[int]:
    """Those of ``partitions`` whose owner among the members ``before`` is not among ``after`` (it
    left or died), or that had no owner: nobody else can be reading them, so a new owner may take
    them at once. ``count``: the number of partitions."""
    _check(count)
    live = set(after)
    ring = assignment(before, count)
    owner = {p: m for m, ps in ring.items() for p in ps}
    return frozenset(p for p in partitions if owner.get(p) not in live)
