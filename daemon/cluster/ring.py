"""Which live member owns which partition: rendezvous (highest random weight) hashing.

Each partition ``p`` of ``0 .. partitions-1`` belongs to the member with the highest
:func:`score` ``(member, p)``, ties (64-bit collisions) to the smallest name. Every member computes
the same answer from the same set of live members, with no coordination beyond agreeing on that set,
and a change of the set moves the fewest partitions possible: when a member leaves only its own
partitions move (each to the member ranked next for it), and when one joins only the partitions it
now ranks highest for move, all to it. Grafana Mimir's hash ring gives the same guarantees with
tokens on a circle; with a few members and tens of partitions the direct ranking is as cheap
(``partitions * members`` hashes) and needs no tokens.

Balance is that of throwing each partition to a uniformly random member: the loads follow a
multinomial distribution. With 16 partitions and 3 members a member owns 5.3 on average, and the
busiest owns 9 or more for about one set of three names in seven (15 %) and 10 or more for one in
twenty (``tests/test_cluster_ring.py`` checks these figures); more partitions even the loads out.

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


def owner(partition: int, members: Iterable[str]) -> str | None:
    """The member ranked highest for ``partition`` (equal scores: the smallest name); None if there
    are no members."""
    best: str | None = None
    best_score = -1
    for member in members:
        s = score(member, partition)
        if s > best_score or (s == best_score and best is not None and member < best):
            best, best_score = member, s
    return best


def _check(partitions: int) -> None:
    if partitions < 0:
        raise InputError(f"partitions must be 0 or more, got {partitions}")


def assignment(members: Iterable[str], partitions: int) -> dict[str, frozenset[int]]:
    """Every member (duplicates once) with the partitions of ``0 .. partitions-1`` it owns, maybe
    none."""
    _check(partitions)
    live = sorted(set(members))
    owned: dict[str, set[int]] = {m: set() for m in live}
    for p in range(partitions):
        best = owner(p, live)
        if best is not None:
            owned[best].add(p)
    return {m: frozenset(ps) for m, ps in owned.items()}


def owned(member: str, members: Iterable[str], partitions: int) -> frozenset[int]:
    """The partitions ``member`` owns among ``members``: none if it is not one of them (a member
    that is not live owns nothing)."""
    _check(partitions)
    live = set(members)
    if member not in live:
        return frozenset()
    return frozenset(p for p in range(partitions) if owner(p, live) == member)
