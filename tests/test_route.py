"""The front's compiled router (:class:`protocols._route.Router`) against its Python twin
(:func:`protocols.routing.split` over :func:`protocols.zeromq.receive`): on real ZeroMQ sockets,
for any sequence of messages (of one, two or more frames, empty or large, of any topic), every worker
gets the same frames in the same order; a worker whose queue is full is counted, not waited for;
topics are remembered within a bound."""

from __future__ import annotations

from collections.abc import Iterator

import msgpack
import pytest
import zmq
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from protocols._route import Router
from protocols.routing import Routes, choose, split
from protocols.zeromq import libzmq_functions, receive


@pytest.fixture(scope="module")
def ctx() -> Iterator[zmq.Context[zmq.Socket[bytes]]]:
    context: zmq.Context[zmq.Socket[bytes]] = zmq.Context()
    yield context
    context.destroy(linger=0)


class Rig:
    """A source socket fed by a PUSH, ``workers`` PUSH sinks each drained by a PULL; every socket
    unbounded but where told."""

    count = 0

    def __init__(self, ctx: zmq.Context[zmq.Socket[bytes]], workers: int, sink_hwm: int = 0) -> None:
        Rig.count += 1
        name = f"inproc://route-{Rig.count}"
        self.source = ctx.socket(zmq.PULL)
        self.source.setsockopt(zmq.RCVHWM, 0)
        self.source.bind(name)
        self.feed = ctx.socket(zmq.PUSH)
        self.feed.setsockopt(zmq.SNDHWM, 0)
        self.feed.connect(name)
        self.sinks, self.drains = [], []
        for k in range(workers):
            sink = ctx.socket(zmq.PUSH)
            sink.setsockopt(zmq.SNDHWM, sink_hwm)
            sink.bind(f"{name}-w{k}")
            drain = ctx.socket(zmq.PULL)
            drain.setsockopt(zmq.RCVHWM, sink_hwm)
            drain.connect(f"{name}-w{k}")
            self.sinks.append(sink)
            self.drains.append(drain)

    def router(self, cached: int = 1000) -> Router:
        functions = libzmq_functions()
        assert functions is not None, "the libzmq pyzmq loaded was not found"
        return Router(
            functions,
            self.source.underlying,
            [s.underlying for s in self.sinks],
            choose(len(self.sinks)),
            cached,
        )

    def send(self, messages: list[list[bytes]]) -> None:
        for frames in messages:
            self.feed.send_multipart(frames)

    def received(self) -> list[list[bytes]]:
        """What each worker got, the frames of its messages one after another."""
        out: list[list[bytes]] = []
        for drain in self.drains:
            frames: list[bytes] = []
            while drain.poll(0):
                frames += msgpack.unpackb(drain.recv())
            out.append(frames)
        return out

    def close(self) -> None:
        for sock in [self.source, self.feed, *self.sinks, *self.drains]:
            sock.close(linger=0)


topics = st.one_of(
    st.builds(
        lambda s, w: f"mocap/{s}/{w}".encode(),
        st.text(min_size=0, max_size=20),
        st.sampled_from(["pose", "skeleton", "frame"]),  # a frame message's: every worker's
    ),
    st.binary(max_size=30),
)
frames_after = st.lists(st.binary(max_size=300), max_size=3)
messages = st.lists(st.tuples(topics, frames_after).map(lambda m: [m[0], *m[1]]), max_size=60)


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(batch=messages, workers=st.integers(1, 4), most=st.integers(1, 70))
def test_the_router_gives_each_worker_what_split_gives(
    ctx: zmq.Context[zmq.Socket[bytes]], batch: list[list[bytes]], workers: int, most: int
) -> None:
    rig = Rig(ctx, workers)
    try:
        rig.send(batch)
        router = rig.router()
        taken = 0
        while True:
            got, full = router.drain(most)
            assert full == [0] * workers
            assert got <= most
            taken += got
            if got < most:
                break
        assert taken == len(batch)
        assert router.drain(most) == (0, [0] * workers)
        rig.send(batch)  # the twin: the same messages through receive() and split()
        twin: list[list[bytes]] = []
        while (parts := receive(rig.source)) is not None:
            twin.append(parts)
        assert twin == batch
        assert rig.received() == split(twin, Routes(workers, 1000), workers)
    finally:
        rig.close()


def test_a_large_payload_and_a_full_worker(ctx: zmq.Context[zmq.Socket[bytes]]) -> None:
    """A worker whose queue is full: its messages are counted as not sent, the others' go."""
    rig = Rig(ctx, 2, sink_hwm=1)
    try:
        router = rig.router()
        route = Routes(2, 1000)
        mine = [t for t in (f"mocap/s{k}/pose".encode() for k in range(50)) if route(t) == 0][:3]
        theirs = next(t for t in (f"mocap/t{k}/pose".encode() for k in range(50)) if route(t) == 1)
        big = bytes(range(256)) * 4000  # 1 MB: the frame's buffer grows
        sent = []
        for rounds in range(40):  # worker 0's queue (one message each side) fills up
            rig.send([[mine[rounds % 3], big]])
            sent.append(router.drain(10))
        assert all(taken == 1 for taken, _ in sent)
        assert sum(full[0] for _, full in sent) > 0
        rig.send([[theirs, b"x"]])
        assert router.drain(10) == (1, [0, 0])
        got = rig.received()
        assert got[1] == [theirs, b"x"]
        assert got[0][:2] == [mine[0], big]
    finally:
        rig.close()


def test_routes_are_remembered_within_a_bound() -> None:
    route = Routes(3, cached=10)
    first = [route(f"mocap/s{k}/pose".encode()) for k in range(25)]
    assert len(route._routes) <= 10  # a flood of new ids does not grow it
    assert [route(f"mocap/s{k}/pose".encode()) for k in range(25)] == first
    assert first == [choose(3)(f"mocap/s{k}/pose".encode()) for k in range(25)]


def test_the_router_remembers_within_a_bound(ctx: zmq.Context[zmq.Socket[bytes]]) -> None:
    asked: list[bytes] = []

    def chooser(topic: bytes) -> int:
        asked.append(topic)
        return 0

    rig = Rig(ctx, 1)
    try:
        functions = libzmq_functions()
        assert functions is not None
        router = Router(functions, rig.source.underlying, [rig.sinks[0].underlying], chooser, 4)
        names = [f"mocap/s{k}/pose".encode() for k in range(6)]
        rig.send([[n, b"p"] for n in names + names[:2]])
        assert router.drain(100) == (8, [0])
        assert asked == names + names[:2]  # the cache held 4, then was cleared for the fifth
        rig.send([[names[5], b"p"]])
        router.drain(100)
        assert asked[-1] == names[1]  # remembered: not asked again
    finally:
        rig.close()


def test_a_router_refuses_a_worker_out_of_range(ctx: zmq.Context[zmq.Socket[bytes]]) -> None:
    rig = Rig(ctx, 2)
    try:
        functions = libzmq_functions()
        assert functions is not None
        router = Router(functions, rig.source.underlying, [s.underlying for s in rig.sinks], lambda t: 5, 10)
        rig.send([[b"mocap/a/pose", b"p"]])
        with pytest.raises(ValueError, match="worker 5 of 2"):
            router.drain(10)
        with pytest.raises(ValueError, match="libzmq functions missing: zmq_msg_init"):
            Router({}, 0, [0], lambda t: 0, 10)
    finally:
        rig.close()
