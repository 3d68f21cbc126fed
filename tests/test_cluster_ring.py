"""The partition ring (rendezvous hashing): against its definition, the ownership invariants, the
fewest moves on joins and leaves, and its balance against the multinomial it should follow."""

from __future__ import annotations

import hashlib
import random
from math import comb

import pytest
from hypothesis import given
from hypothesis import strategies as st

from daemon.cluster.ring import assignment, owned, owner, score
from tests.naive import slow_rendezvous

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
    reference = slow_rendezvous(sorted(members), partitions)
    assert assignment(members, partitions) == {m: frozenset(ps) for m, ps in reference.items()}
    for p in range(partitions):
        expected = next((m for m, ps in reference.items() if p in ps), None)
        assert owner(p, members) == expected
    for m in members:
        assert owned(m, members, partitions) == frozenset(reference[m])


@given(member_sets, partition_counts)
def test_every_partition_has_exactly_one_live_owner(members: set[str], partitions: int) -> None:
    got = assignment(members, partitions)
    assert set(got) == members
    counted = sorted(p for ps in got.values() for p in ps)
    assert counted == (list(range(partitions)) if members else [])


@given(member_sets, names, partition_counts)
def test_a_member_that_is_not_live_owns_nothing(members: set[str], other: str, partitions: int) -> None:
    if other not in members:
        assert owned(other, members, partitions) == frozenset()


@given(member_sets.filter(bool), st.data(), partition_counts)
def test_a_leaving_member_moves_only_its_own_partitions(
    members: set[str], data: st.DataObject, partitions: int
) -> None:
    leaving = data.draw(st.sampled_from(sorted(members)))
    before = assignment(members, partitions)
    after = assignment(members - {leaving}, partitions)
    for m in members - {leaving}:
        assert before[m] <= after[m]  # nobody loses a partition
        assert after[m] - before[m] <= before[leaving]  # and gains only the leaver's


@given(member_sets, names, partition_counts)
def test_a_joining_member_takes_partitions_and_nobody_else_gets_any(
    members: set[str], joining: str, partitions: int
) -> None:
    if joining in members:
        return
    before = assignment(members, partitions)
    after = assignment(members | {joining}, partitions)
    for m in members:
        assert after[m] <= before[m]  # others only lose, and what they lose goes to the newcomer
        assert before[m] - after[m] <= after[joining]


def test_duplicates_count_once_and_order_does_not_matter() -> None:
    members = ["c", "a", "b", "a"]
    assert assignment(members, 16) == assignment(["a", "b", "c"], 16)
    assert assignment(reversed(members), 16) == assignment(members, 16)
    assert assignment([], 16) == {}
    assert owner(3, []) is None


def test_a_negative_partition_count_is_refused() -> None:
    with pytest.raises(ValueError, match="partitions"):
        assignment(["a"], -1)
    with pytest.raises(ValueError, match="partitions"):
        owned("a", ["a"], -1)


def multinomial_at_least(n: int, k: int, threshold: int) -> float:
    """P(the largest of k equal-chance counts of n throws is ≥ threshold), for k = 3 exactly."""
    assert k == 3
    return float(
        sum(
            comb(n, a) * comb(n - a, b) / 3**n
            for a in range(n + 1)
            for b in range(n + 1 - a)
            if max(a, b, n - a - b) >= threshold
        )
    )


def test_16_partitions_over_3_members_are_balanced_as_random_throws_are() -> None:
    """Over 3000 sets of three random names (a fixed seed), the busiest member's load is distributed
    as the multinomial's maximum (within four standard errors), and each name's share is a third."""
    rng = random.Random(23)
    draws = 3000
    busiest: list[int] = []
    first_share = 0
    for _ in range(draws):
        members = [f"worker-{rng.getrandbits(40):010x}" for _ in range(3)]
        loads = assignment(members, 16)
        busiest.append(max(len(ps) for ps in loads.values()))
        first_share += len(loads[members[0]])
    for threshold in (8, 9, 10):
        expected = multinomial_at_least(16, 3, threshold)
        seen = sum(b >= threshold for b in busiest) / draws
        error = (expected * (1 - expected) / draws) ** 0.5
        assert abs(seen - expected) < 4 * error, (threshold, seen, expected)
    assert abs(first_share / (16 * draws) - 1 / 3) < 0.01
    assert multinomial_at_least(16, 3, 9) == pytest.approx(0.15, abs=0.005)  # the figure ring.py states
    assert multinomial_at_least(16, 3, 10) == pytest.approx(0.048, abs=0.005)
