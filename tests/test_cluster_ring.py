"""The partition ring (rendezvous hashing with bounded loads): against its definition, the
ownership invariants, the balance it promises, and the moves of joins and leaves."""

from __future__ import annotations

import hashlib
import itertools
import random
from collections import Counter

import pytest
from hypothesis import given
from hypothesis import strategies as st

from daemon.cluster.ring import assignment, loads, orphaned, owned, room, score, spread
from protocols.nats import partition_of
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


weight_maps = st.dictionaries(st.integers(0, 39), st.integers(0, 6), max_size=40)


def _no_better_move_or_swap(got: dict[str, frozenset[int]], weights: dict[int, int]) -> bool:
    """The slow check of :func:`even_out`'s stopping rule: no partition with streams, nor pair of
    them, moves from a member to one with fewer streams such that the sum of squared loads drops."""
    load = loads(got, weights)
    for a, b in itertools.permutations(got, 2):
        gap = load[a] - load[b]
        for p in got[a]:
            wp = weights.get(p, 0)
            if 0 < wp < gap:
                return False
            if wp > 0 and any(weights.get(q, 0) > 0 and 0 < wp - weights.get(q, 0) < gap for q in got[b]):
                return False
    return True


@given(member_sets, partition_counts, weight_maps)
def test_evened_out_every_partition_has_one_owner_and_no_move_would_even_the_loads_more(
    members: set[str], partitions: int, weights: dict[int, int]
) -> None:
    weights = {p: n for p, n in weights.items() if p < partitions}
    got = assignment(members, partitions, weights)
    ring = assignment(members, partitions)
    assert set(got) == members
    assert sorted(p for ps in got.values() for p in ps) == (list(range(partitions)) if members else [])
    assert _no_better_move_or_swap(got, weights)
    squares = sum(n * n for n in loads(got, weights).values())
    assert squares <= sum(n * n for n in loads(ring, weights).values())
    assert assignment(sorted(members, reverse=True), partitions, dict(reversed(weights.items()))) == got
    for m in members:
        assert owned(m, members, partitions, weights) == got[m]


@given(member_sets, member_sets, partition_counts, weight_maps)
def test_orphaned_partitions_are_those_whose_owner_by_the_balance_before_is_gone(
    before: set[str], after: set[str], partitions: int, weights: dict[int, int]
) -> None:
    ring = assignment(before, partitions, weights)
    gone = {p for m, ps in ring.items() if m not in after for p in ps}
    unowned = set(range(partitions)) - {p for ps in ring.values() for p in ps}
    assert orphaned(range(partitions), before, after, partitions, weights) == gone | unowned


def test_streams_evened_out_are_within_a_fifth_of_the_mean_at_3_to_10_members() -> None:
    """The issue's bound on streams per worker, which the ring alone misses (streams hashed to 256
    partitions as nats-server hashes them), for 3 to 30 streams per member over 10 random sets of
    names and stream ids each; the partitions per member stay as even as the ring made them."""
    rng = random.Random(3410)
    ring_fails = 0
    for n in range(3, 11):
        for per in (3, 10, 30):
            for _ in range(10):
                members = [f"worker-{rng.getrandbits(40):010x}" for _ in range(n)]
                ids = [f"s{rng.getrandbits(40):010x}" for _ in range(per * n)]
                weights = dict(Counter(partition_of(s, 256) for s in ids))
                got = assignment(members, 256, weights)
                assert spread(loads(got, weights)) <= 0.2, (n, per, loads(got, weights))
                assert {len(ps) for ps in got.values()} <= {
                    len(ps) for ps in assignment(members, 256).values()
                }
                ring_fails += spread(loads(assignment(members, 256), weights)) > 0.2
    assert ring_fails > 200  # of 240 (206 with this seed)
