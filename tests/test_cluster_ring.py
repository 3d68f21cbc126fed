"""The partition ring (rendezvous hashing with bounded loads): against its definition, the
ownership invariants, the balance it promises, and the moves of joins and leaves."""

from __future__ import annotations

import hashlib
import random

import pytest
from hypothesis import given
from hypothesis import strategies as st

from daemon.cluster.ring import assignment, orphaned, owned, room, score
from tests.naive import slow_bounded_rendezvous

names = st.text(min_size=1, max_size=12)
member_sets = st.sets(names, max_size=7)
partition_counts = st.integers(min_value=0, max_value=40)


def test_the_score_is_blake2b_of_the_name_and_the_partition() -> None:
    """A fixed value: every process, on every machine and Python, ranks alike (no salted hash)."""
    expected = hashlib.blake2b(b"worker-a\xff" + (7).to_bytes(8, "big"), digest_size=8).digest()
    assert score("worker-a", 7) == int.from_bytes(expected, "big")
    assert 0 <= score("", 0) < 2**64
    assert score("ab", 1) != score("a", 1)


@given(member_sets, partition_counts)
def test_the_ring_is_its_definition(members: set[str], partitions: int) -> None:
    reference = slow_bounded_rendezvous(sorted(members), partitions)
    assert assignment(members, partitions) == {m: frozenset(ps) for m, ps in reference.items()}
    for m in members:
        assert owned(m, members, partitions) == frozenset(reference[m])


@given(member_sets, partition_counts)
def test_every_partition_has_exactly_one_live_owner_and_none_more_than_its_room(
    members: set[str], partitions: int
) -> None:
    got = assignment(members, partitions)
    assert set(got) == members
    counted = sorted(p for ps in got.values() for p in ps)
    assert counted == (list(range(partitions)) if members else [])
    assert all(len(ps) <= room(len(members), partitions) for ps in got.values())


@given(member_sets, names, partition_counts)
def test_a_member_that_is_not_live_owns_nothing(members: set[str], other: str, partitions: int) -> None:
    if other not in members:
        assert owned(other, members, partitions) == frozenset()


@given(member_sets.filter(bool), st.data(), partition_counts)
def test_a_leaving_member_hands_over_all_it_owned(
    members: set[str], data: st.DataObject, partitions: int
) -> None:
    leaving = data.draw(st.sampled_from(sorted(members)))
    before = assignment(members, partitions)
    after = assignment(members - {leaving}, partitions)
    assert set(after) == members - {leaving}
    if len(members) > 1:
        assert before[leaving] <= frozenset().union(*after.values())


@given(member_sets, member_sets, partition_counts)
def test_orphaned_partitions_are_those_whose_owner_before_is_gone(
    before: set[str], after: set[str], partitions: int
) -> None:
    reference = slow_bounded_rendezvous(sorted(before), partitions)
    gone = {p for m, ps in reference.items() if m not in after for p in ps}
    unowned = set(range(partitions)) - {p for ps in reference.values() for p in ps}
    assert orphaned(range(partitions), before, after, partitions) == gone | unowned
    assert orphaned([], before, after, partitions) == frozenset()


def test_duplicates_count_once_and_order_does_not_matter() -> None:
    members = ["c", "a", "b", "a"]
    assert assignment(members, 16) == assignment(["a", "b", "c"], 16)
    assert assignment(reversed(members), 16) == assignment(members, 16)
    assert assignment([], 16) == {}


def test_a_negative_partition_count_is_refused() -> None:
    with pytest.raises(ValueError, match="partitions"):
        assignment(["a"], -1)
    with pytest.raises(ValueError, match="partitions"):
        owned("a", ["a"], -1)


def test_256_partitions_are_balanced_within_a_fifth_at_3_to_10_members_and_moves_stay_few() -> None:
    """The issue's bound (±20 % of the mean) on every set of 30 random names per size, and what
    ring.py states: within 16 %, and extra moves (partitions moving between members that neither
    left nor joined) at most 60 % of the leaver's or joiner's partitions, a fifth on average at
    most at 3 members. Plain rendezvous hashing fails the bound (the reason for the bounded loads)."""
    rng = random.Random(34)
    plain_fails = 0
    for n in range(3, 11):
        extra: list[float] = []
        for _ in range(30):
            members = [f"worker-{rng.getrandbits(40):010x}" for _ in range(n)]
            ring = assignment(members, 256)
            loads = [len(ps) for ps in ring.values()]
            assert all(abs(load - 256 / n) <= 0.16 * 256 / n for load in loads), (n, loads)
            plain = [sum(max(members, key=lambda m: score(m, p)) == m for p in range(256)) for m in members]
            plain_fails += any(abs(load - 256 / n) > 0.2 * 256 / n for load in plain)
            after = assignment(members[1:], 256)
            extra.append(sum(len(ring[m] - after[m]) for m in members[1:]) / len(ring[members[0]]))
            joiner = f"worker-{rng.getrandbits(40):010x}"
            joined = assignment([*members, joiner], 256)
            extra.append(
                (sum(len(ring[m] - joined[m]) for m in members) - len(joined[joiner])) / len(joined[joiner])
            )
        assert max(extra) <= 0.6, (n, max(extra))
        if n == 3:
            assert sum(extra) / len(extra) <= 0.2
    assert plain_fails > 120  # of 240 sets of names
