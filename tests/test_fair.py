"""The MQTT intake's fair queue (issue 21): against a literal reading on random puts and takes, and
a flood of one stream's topic that crowds out that stream only."""

from __future__ import annotations

from hypothesis import given, settings
from hypothesis import strategies as st

from protocols.fair import FairQueue, key_of
from protocols.transport import Incoming
from tests.naive import slow_fair_queue

ops = st.lists(st.none() | st.tuples(st.sampled_from(list("abcdef")), st.integers(0, 99)), max_size=200)


@settings(max_examples=500, deadline=None)
@given(ops, st.integers(1, 12))
def test_the_queue_reads_its_definition(steps: list[tuple[str, int] | None], size: int) -> None:
    queue = FairQueue(size)
    taken, dropped = [], 0
    labelled: list[tuple[str, str] | None] = []
    for i, op in enumerate(steps):
        if op is None:
            got = queue.take()
            if got is not None:
                taken.append(got.payload.decode())
            labelled.append(None)
        else:
            key, _ = op
            label = f"{key}{i}"
            dropped += queue.put(Incoming(f"mocap/{key}/pose", label.encode(), 0.0))
            labelled.append((key, label))
        assert len(queue) <= size
    assert (taken, dropped) == slow_fair_queue(labelled, size)


def test_a_flood_of_one_stream_crowds_out_that_stream_only() -> None:
    """A hundred garbage messages on one stream's topic for every good pose, the consumer taking ten
    messages for each: every good message comes through, in order; the drops are the flood's."""
    queue = FairQueue(100)
    queue.put(Incoming("mocap/good/skeleton", b"s", 0.0))
    good, dropped, taken = [], 0, 0
    for i in range(100):
        for _ in range(100):
            dropped += queue.put(Incoming("mocap/bad/pose", b"x", 0.0))
        dropped += queue.put(Incoming("mocap/good/pose", str(i).encode(), 0.0))
        for _ in range(10):
            m = queue.take()
            taken += m is not None
            if m is not None and key_of(m.topic) == "good":
                good.append(m.payload)
    while (m := queue.take()) is not None:
        taken += 1
        if key_of(m.topic) == "good":
            good.append(m.payload)
    assert good == [b"s"] + [str(i).encode() for i in range(100)]
    assert dropped + taken == 1 + 100 * 101 and dropped > 8000
    assert key_of("mocapd/i/status") == "mocapd/i/status"
