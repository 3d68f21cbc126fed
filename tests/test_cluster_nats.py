"""The facts about nats-server that cluster mode is built on (docs/cluster.md, "What was verified"),
on the shipped config: the partitioning mappings apply to what is published over MQTT and over
NATS; MQTT subscribers get what workers publish on ``mocap.<s>.detections``; JetStream answers a
repeated ``Nats-Msg-Id`` as a duplicate. And the two limits of 2.9 the design works around: an MQTT
topic with ``.`` in a level is refused, and a stream's RePublish does not reach MQTT subscribers (if
a newer server delivers it, this test says so: the workers could then leave publishing to it)."""

from __future__ import annotations

import asyncio
import contextlib
import random
import signal
import threading
import time
from functools import partial
from pathlib import Path
from typing import Any, cast

import nats
import paho.mqtt.client as paho
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from nats.aio.msg import Msg
from paho.mqtt.enums import CallbackAPIVersion

from daemon.config import ClusterConfig
from protocols.nats import (
    HEARTBEAT_S,
    HOLD_S,
    PUBLISH_TIMEOUT_S,
    RETRY_S,
    SILENT_S,
    STORE_FOR_S,
    Ack,
    NatsTransport,
    acknowledgement,
    partition_of,
)
from protocols.transport import STATE_TOPIC, Outgoing
from tests.helpers import freeze, wait_for
from tests.nats_server import NatsServer, partitions


class Mqtt:
    def __init__(self, port: int, name: str, topics: list[str]) -> None:
        self.got: list[tuple[str, bytes]] = []
        self.subscribed = threading.Event()
        self.client = paho.Client(CallbackAPIVersion.VERSION2, client_id=name)
        self.client.on_message = lambda c, u, m: self.got.append((m.topic, bytes(m.payload)))
        self.client.on_subscribe = lambda *a: self.subscribed.set()
        self.client.connect("127.0.0.1", port)
        self.client.loop_start()
        if topics:
            self.client.subscribe([(t, 1) for t in topics])
            assert self.subscribed.wait(10)

    def close(self) -> None:
        self.client.loop_stop()
        self.client.disconnect()


@pytest.mark.slow
def test_what_cluster_mode_relies_on(tmp_path: Path) -> None:
    import nats
    from nats.js.api import RePublish, StorageType, StreamConfig

    server = NatsServer(tmp_path).start()
    seen: list[tuple[str, bytes]] = []
    results: dict[str, Any] = {}
    sub = pub = None
    try:
        sub = Mqtt(server.mqtt_port, "facts-sub", ["mocap/+/detections", "mocap/+/republished"])
        pub = Mqtt(server.mqtt_port, "facts-pub", [])

        async def main() -> None:
            nc = await nats.connect(server.url)
            js = nc.jetstream()

            async def got(msg: Any) -> None:
                seen.append((msg.subject, msg.data))

            await nc.subscribe("mocap.p.>", cb=got)
            await nc.subscribe("mocap.*.republished", cb=got)
            await nc.flush()
            pub.client.publish("mocap/s1/pose", b"over mqtt", qos=0)
            await nc.publish("mocap.s2.pose", b"over nats")
            await js.add_stream(StreamConfig(name="DEDUP", subjects=["dedup.>"], storage=StorageType.MEMORY))
            acks = [await js.publish("dedup.x", b"d", headers={"Nats-Msg-Id": "same"}) for _ in range(2)]
            results["duplicate"] = [a.duplicate for a in acks]
            await js.add_stream(
                StreamConfig(
                    name="REPUB",
                    subjects=["repub.*"],
                    storage=StorageType.MEMORY,
                    republish=RePublish(src="repub.*", dest="mocap.{{wildcard(1)}}.republished"),
                )
            )
            await js.publish("repub.s3", b"stored")
            await nc.publish("mocap.s4.detections", b"plain", headers={"Nats-Msg-Id": "x"})
            await nc.flush()
            await asyncio.sleep(1.0)
            await nc.close()

        asyncio.run(main())
        wait_for(lambda: len(seen) >= 3, 5, "the mapped poses and the republished message")
        by_payload = {data: subject for subject, data in seen}
        assert by_payload[b"stored"] == "mocap.s3.republished"  # RePublish works, for NATS subscribers
        for payload, stream in ((b"over mqtt", "s1"), (b"over nats", "s2")):  # mapped to a partition
            p, name, word = by_payload[payload].split(".")[2:]
            assert (name, word) == (stream, "pose") and 0 <= int(p) < partitions()
        assert results["duplicate"] == [None, True]
        wait_for(lambda: ("mocap/s4/detections", b"plain") in sub.got, 5, "a worker's detection over MQTT")
        time.sleep(0.5)
        assert not [t for t, _ in sub.got if t.endswith("/republished")], "RePublish reaches MQTT now"
        # a topic level with '.': the server closes the publisher's connection
        pub.client.publish("mocap/a.b/pose", b"x", qos=0)
        wait_for(
            lambda: (
                "not supported for MQTT topics" in server.log.read_text(encoding="utf-8", errors="replace")
            ),
            5,
            "the refusal",
        )
    finally:
        for client in (sub, pub):
            if client is not None:
                client.close()
        server.stop()


@settings(max_examples=200, deadline=None)
@given(
    stream_seq=st.integers(1, 2**63 - 1),
    consumer_seq=st.integers(1, 2**63 - 1),
    delivered=st.integers(1, 1000),
    domain=st.booleans(),
)
def test_acknowledgements_are_read_as_nats_py_reads_them(
    stream_seq: int, consumer_seq: int, delivered: int, domain: bool
) -> None:
    """The reading of a JetStream message's acknowledgement subject equals nats-py's
    ``Msg.metadata``, in both forms of the subject (ADR-15)."""
    head = "$JS.ACK.hub.ACCHASH." if domain else "$JS.ACK."
    tail = ".tok" if domain else ""
    reply = (
        f"{head}MOCAPD_BUF_3.c0nsumer.{delivered}.{stream_seq}.{consumer_seq}.1701234567890123456.42{tail}"
    )
    slow = _message(reply).metadata
    ack = acknowledgement(reply.encode())
    assert ack == Ack(slow.stream, slow.consumer, slow.sequence.stream, slow.sequence.consumer)


@pytest.mark.parametrize(
    "reply",
    [
        b"",
        b"_INBOX.abc",
        b"$JS.FC.MOCAPD_BUF_3.x.y",
        b"$JS.ACK.MOCAPD_BUF_3.c.1.x.2.3.4",  # a sequence that is no number
        b"$JS.ACK.MOCAPD_BUF_3.c.1.-2.2.3.4",
        b"$JS.ACK.MOCAPD_BUF_\xff.c.1.2.2.3.4",  # a stream name that is not ASCII
        b"$JS.ACK.MOCAPD_BUF_3.c.1.2.2.3",  # a token short
        b"$js.ack.MOCAPD_BUF_3.c.1.2.2.3.4",
    ],
)
def test_what_is_no_acknowledgement_subject_is_none(reply: bytes) -> None:
    """A reply that is not JetStream's acknowledgement subject (a message published on a delivery
    subject directly, the server's flow control) says nothing: None, never an exception."""
    assert acknowledgement(reply) is None


def _message(reply: str) -> Msg:
    """A message as nats-py delivers it, with no client (the metadata needs none)."""
    return Msg(_client=cast(Any, None), subject="mocap.p.3.s.pose", reply=reply)


def test_a_partition_taken_from_a_checkpoint_gives_every_streams_state_first(tmp_path: Path) -> None:
    """A partition taken from a checkpoint: the state of each of its streams comes to the service
    before any message of the buffer, a silent stream's too (so that the new owner holds it, evicts
    it when idle and carries it into its own checkpoints); the buffer is read from after the
    checkpoint, and a stream's state waiting in the queue keeps the stream known."""
    server = NatsServer(tmp_path).start()
    try:

        async def main() -> None:
            settings = ClusterConfig(nats=server.url, partitions=partitions(), buffer_s=60.0)
            talking, silent = [f"s{i}" for i in range(10_000) if partition_of(f"s{i}", partitions()) == 0][:2]
            transport = NatsTransport(settings, instance="t", source=True, sink=False)
            async with transport:
                nc = await nats.connect(server.url)
                for seq in range(3):
                    await nc.publish(f"mocap.{talking}.pose", f"{seq}".encode())
                await nc.flush()
                await nc.close()
                states = {talking: b"state of the talking one", silent: b"state of the silent one"}
                assert await transport.checkpoint(0, 1, states)
                await transport.own(frozenset({0}))
                wait = time.monotonic() + 10
                while transport.partition(silent) is None and time.monotonic() < wait:
                    await asyncio.sleep(0.01)
                transport.forget(set())  # their states not taken in yet: both are still known
                assert transport.partition(silent) == transport.partition(talking) == 0
                incoming = aiter(transport)
                first = [await anext(incoming) for _ in range(2)]
                assert sorted((m.topic, m.payload) for m in first) == sorted(
                    (STATE_TOPIC + s, state) for s, state in states.items()
                )
                rest = [await anext(incoming) for _ in range(2)]  # from after the checkpoint
                assert [(m.topic, m.payload) for m in rest] == [
                    (f"mocap/{talking}/pose", b"%d" % q) for q in (1, 2)
                ]
                assert transport.resumed == 1 and transport.taken_up_to(0) == 3

        asyncio.run(main())
    finally:
        server.stop()


async def _payloads(transport: NatsTransport, n: int, within: float = 10.0) -> list[bytes]:
    """The payloads of the next ``n`` messages ``transport`` gives, TimeoutError after ``within``."""
    incoming = aiter(transport)  # a fresh iterator: one whose wait timed out is closed
    async with asyncio.timeout(within):
        return [(await anext(incoming)).payload for _ in range(n)]


def _source(url: str) -> NatsTransport:
    """A worker's transport reading from the server at ``url`` (a 60 s buffer)."""
    settings = ClusterConfig(nats=url, partitions=partitions(), buffer_s=60.0)
    return NatsTransport(settings, instance="t", source=True, sink=False)


def _of_partition_0() -> str:
    """A stream id the partitions' mapping puts in partition 0."""
    return next(f"s{i}" for i in range(1000) if partition_of(f"s{i}", partitions()) == 0)


@pytest.mark.slow
def test_read_on_both_paths_each_message_comes_once_and_what_the_buffer_lost_comes_live(
    tmp_path: Path,
) -> None:
    """A partition read through its buffer and a plain subscription (as on a NATS cluster,
    :mod:`protocols.merge`): what the buffer held before the take is replayed, each message after
    it comes once, in order, at the buffer's positions; when the buffer stores nothing more (here
    deleted; on a cluster, a buffer electing a new leader after its server died) the messages still
    come, through the plain subscription, once each, and no checkpoint position claims them."""
    server = NatsServer(tmp_path).start()
    try:

        async def main() -> None:
            stream, transport = _of_partition_0(), _source(server.url)
            transport.both_paths = True  # one server: a cluster's servers would set it
            async with transport:
                nc = await nats.connect(server.url)

                async def publish(seqs: range) -> None:
                    for seq in seqs:
                        await nc.publish(f"mocap.{stream}.pose", b"%d" % seq)
                    await nc.flush()

                read = partial(_payloads, transport)

                await publish(range(3))
                await transport.own(frozenset({0}))
                assert await read(3) == [b"0", b"1", b"2"]  # replayed
                await publish(range(3, 8))
                assert await read(5) == [b"%d" % q for q in range(3, 8)]
                with pytest.raises(TimeoutError):  # nothing twice
                    await read(1, 2 * HOLD_S)
                assert transport.taken_up_to(0) == 8

                await nc.jetstream().delete_stream("MOCAPD_BUF_0")
                await publish(range(8, 13))
                assert await read(5) == [b"%d" % q for q in range(8, 13)]
                with pytest.raises(TimeoutError):
                    await read(1, 2 * HOLD_S)
                assert transport.taken_up_to(0) is None  # a checkpoint now would claim too little
                # the buffer still delivers nothing: its consumer is made again, which fails while
                # the buffer is gone, and the plain subscription goes on meanwhile
                await asyncio.sleep(SILENT_S + HEARTBEAT_S)
                await publish(range(13, 15))
                assert await read(2, 2 * HOLD_S + 1) == [b"13", b"14"]
                await nc.close()

        asyncio.run(main())
    finally:
        server.stop()


def test_a_stream_whose_live_copies_are_held_is_waiting_and_they_come_though_no_buffer_can_be_read(
    tmp_path: Path,
) -> None:
    """A live copy held for its buffered copy keeps its stream from being taken for silent (the
    service would flush and forget it, and take its later poses for a new stream); and when the
    buffer cannot be read at all (here deleted before the take; on a cluster, no leader elected
    yet), the live copies are not held for a replay that cannot come."""
    server = NatsServer(tmp_path).start()
    try:

        async def main() -> None:
            stream, transport = _of_partition_0(), _source(server.url)
            transport.both_paths = True
            async with transport:
                nc = await nats.connect(server.url)
                await nc.jetstream().delete_stream("MOCAPD_BUF_0")
                await transport.own(frozenset({0}))
                async with asyncio.timeout(10):  # the plain subscription in place: nothing lost
                    while not await asyncio.to_thread(server.subscribed, "mocap.p.0.>"):
                        await asyncio.sleep(0.01)
                await nc.publish(f"mocap.{stream}.pose", b"0")
                await nc.flush()
                async with asyncio.timeout(HOLD_S):
                    while stream not in transport.waiting():
                        await asyncio.sleep(0.01)
                assert await _payloads(transport, 1, RETRY_S + 2 * HOLD_S + 1) == [b"0"]
                assert stream not in transport.waiting()
                await nc.close()

        asyncio.run(main())
    finally:
        server.stop()


@pytest.mark.slow
def test_a_partitions_consumer_that_falls_silent_is_made_again_from_the_last_message_read(
    tmp_path: Path,
) -> None:
    """A consumer that delivers nothing, not even its idle heartbeat, for ``SILENT_S`` (here deleted
    behind the worker's back; on a cluster, lost with a server) is made again from after the last
    message read: what was published meanwhile comes, once, in order."""
    server = NatsServer(tmp_path).start()
    try:

        async def main() -> None:
            stream, transport = _of_partition_0(), _source(server.url)
            async with transport:
                nc = await nats.connect(server.url)
                js = nc.jetstream()
                read = partial(_payloads, transport)
                await transport.own(frozenset({0}))
                for seq in range(2):
                    await nc.publish(f"mocap.{stream}.pose", b"%d" % seq)
                assert await read(2, 10) == [b"0", b"1"]
                for consumer in await js.consumers_info("MOCAPD_BUF_0"):
                    await js.delete_consumer("MOCAPD_BUF_0", consumer.name)
                for seq in range(2, 5):
                    await nc.publish(f"mocap.{stream}.pose", b"%d" % seq)
                await nc.flush()
                assert await read(3, SILENT_S + 3 * HEARTBEAT_S) == [b"2", b"3", b"4"]
                with pytest.raises(TimeoutError):
                    await read(1, HEARTBEAT_S)
                assert transport.taken_up_to(0) == 5
                await nc.close()

        asyncio.run(main())
    finally:
        server.stop()


def test_a_stream_read_from_a_partial_buffer_keeps_its_mark_until_it_is_taken_in(tmp_path: Path) -> None:
    """The service forgets every second the streams its table does not hold; a stream read from a
    buffer that lost its start but still waiting in the queue must not lose its truncated-history
    mark then (the cause of extra detections after a takeover)."""
    server = NatsServer(tmp_path).start()
    try:

        async def main() -> None:
            settings = ClusterConfig(nats=server.url, partitions=partitions(), buffer_s=60.0)
            stream = _of_partition_0()
            elsewhere = next(f"s{i}" for i in range(1000) if partition_of(f"s{i}", partitions()) != 0)
            transport = NatsTransport(settings, instance="t", source=True, sink=False)
            async with transport:
                nc = await nats.connect(server.url)
                await nc.publish("mocap.p.0.gone.pose", b"x")
                for word in ("skeleton", "pose", "pose"):
                    await nc.publish(f"mocap.{stream}.{word}", b"x")
                await nc.publish(f"mocap.p.0.{elsewhere}.pose", b"x")  # past the mapping: refused
                await nc.flush()
                await nc.jetstream().purge_stream("MOCAPD_BUF_0", seq=2)  # as if aged out
                await nc.close()
                await transport.own(frozenset({0}))
                wait = time.monotonic() + 10
                while transport.replayed < 4 and time.monotonic() < wait:
                    await asyncio.sleep(0.01)
                assert transport.replayed == 4
                transport.forget(set())  # the table has not taken the stream in yet
                incoming = aiter(transport)
                first = await anext(incoming)
                assert first.topic == f"mocap/{stream}/skeleton"
                assert transport.partial(stream)  # so the service warms it up
                assert transport.partition(stream) == 0
                for _ in range(2):
                    await anext(incoming)
                assert (await anext(incoming)).topic == f"nats:mocap.p.0.{elsewhere}.pose"
                transport.forget(set())  # nothing of it waits: forgotten now
                assert not transport.partial(stream) and transport.partition(stream) is None

        asyncio.run(main())
    finally:
        server.stop()


def test_partition_of_is_the_servers_mapping(tmp_path: Path) -> None:
    """Each stream's subjects land in the buffer :func:`partition_of` names (the shipped mapping,
    on a real nats-server), for ids of every allowed character and length."""
    rng = random.Random(7)
    chars = "ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789_:@-"
    ids = ["a", "s1", "HDM_bd_squat1Reps_001_120", "x" * 128] + [
        "".join(rng.choice(chars) for _ in range(rng.randint(1, 40))) for _ in range(200)
    ]
    server = NatsServer(tmp_path).start()
    try:

        async def main() -> dict[str, str]:
            nc = await nats.connect(server.url)
            landed: dict[str, str] = {}

            async def got(msg: Msg) -> None:
                landed[msg.subject.split(".")[3]] = msg.subject.split(".")[2]

            await nc.subscribe("mocap.p.*.*.pose", cb=got)
            for stream in ids:
                await nc.publish(f"mocap.{stream}.pose", b"x")
            await nc.flush()
            deadline = time.monotonic() + 10
            while len(landed) < len(ids) and time.monotonic() < deadline:
                await asyncio.sleep(0.01)
            await nc.close()
            return landed

        landed = asyncio.run(main())
    finally:
        server.stop()
    p = partitions()
    assert landed == {s: str(partition_of(s, p)) for s in ids}


def test_a_detection_whose_store_times_out_is_not_published_twice(tmp_path: Path) -> None:
    """A worker recomputes a detection another one published (a takeover) while the server is too
    slow to answer the store in time (frozen here): it asks the store again with the same id and
    publishes nothing, where publishing after the timeout delivered the detection twice. Meanwhile
    publishing holds nothing up (recognition goes on; a stalled intake had its streams evicted as
    idle while a buffer elected a leader): the detection waits, counted as pending."""
    server = NatsServer(tmp_path).start()
    assert server.process is not None
    try:

        async def main() -> list[bytes]:
            settings = ClusterConfig(nats=server.url, partitions=partitions())
            first = NatsTransport(settings, instance="w1", source=False, sink=True)
            second = NatsTransport(settings, instance="w2", source=False, sink=True)
            nc = await nats.connect(server.url)
            seen: list[bytes] = []

            async def got(msg: Msg) -> None:
                seen.append(msg.data)

            await nc.subscribe("mocap.s.detections", cb=got)
            detection = Outgoing("mocap/s/detections", b"d1", reliable=True, key="id-1")

            async def stored(t: NatsTransport) -> None:
                async with asyncio.timeout(STORE_FOR_S):
                    while t.pending:
                        await asyncio.sleep(0.01)

            async with first, second:
                await first.publish(detection)
                await stored(first)
                await nc.flush()
                assert server.process is not None
                freeze(server.process)
                try:
                    async with asyncio.timeout(0.5):  # at once, whatever the store does
                        await second.publish(detection)
                    assert second.pending == 1
                    deadline = time.monotonic() + 10 * PUBLISH_TIMEOUT_S
                    while not second.publish_errors and time.monotonic() < deadline:
                        await asyncio.sleep(0.05)  # until its store has timed out
                finally:
                    server.process.send_signal(signal.SIGCONT)
                await stored(second)
                assert second.publish_errors >= 1 and second.duplicates == 1
                await asyncio.sleep(0.3)
            await nc.close()
            return seen

        assert asyncio.run(main()) == [b"d1"]
    finally:
        server.process.send_signal(signal.SIGCONT)
        server.stop()


def test_partitions_given_up_while_their_consumers_are_made_leave_no_consumer(tmp_path: Path) -> None:
    """A worker that takes partitions and gives them up again at once (members sharing them out
    at startup) leaves no consumer on the server, even one the server made while the worker had
    stopped waiting for it: such a consumer pushed to an inbox nobody read, for 30 s."""
    server = NatsServer(tmp_path).start()
    try:

        async def main() -> list[int]:
            settings = ClusterConfig(nats=server.url, partitions=partitions())
            transport = NatsTransport(settings, instance="w", source=True, sink=False)
            nc = await nats.connect(server.url)
            js = nc.jetstream()
            left = []
            async with transport:
                everything = frozenset(range(partitions()))
                for delay in (0.0, 0.002, 0.005, 0.01, 0.02, 0.05):
                    await transport.own(everything)
                    await asyncio.sleep(delay)
                    await transport.own(frozenset())
                    await asyncio.sleep(0.5)
                    consumers = 0
                    for p in range(partitions()):
                        consumers += len(await js.consumers_info(f"MOCAPD_BUF_{p}"))
                    left.append(consumers)
            await nc.close()
            return left

        assert asyncio.run(main()) == [0] * 6
    finally:
        server.stop()


def test_poses_no_buffer_stores_are_read_by_the_owner_of_partition_0(tmp_path: Path) -> None:
    """A native NATS publisher's ``mocap.a.b.pose`` (a stream id with a dot) or ``mocap.p.999.pose``
    (a partition's subject cut short, of no partition) is neither mapped nor stored: the owner of
    partition 0 takes it in as the topic it is (the service refuses and counts it), and only while
    it owns 0. ``mocap.p.3.pose`` is partition 3's buffer's, and not taken a second time."""
    server = NatsServer(tmp_path).start()
    try:

        async def main() -> tuple[list[str], list[str]]:
            settings = ClusterConfig(nats=server.url, partitions=partitions())
            transport = NatsTransport(settings, instance="t", source=True, sink=False)
            async with transport:
                nc = await nats.connect(server.url)
                incoming = aiter(transport)

                async def publish_and_read() -> list[str]:
                    await asyncio.sleep(0.3)  # the subscriptions made (or given up)
                    for subject in (
                        "mocap.a.b.pose",
                        "mocap.p.3.pose",
                        "mocap.p.999.pose",
                        "mocap.a.b.skeleton",
                    ):
                        await nc.publish(subject, b"x")
                    await nc.flush()
                    got: list[str] = []
                    with contextlib.suppress(TimeoutError):
                        async with asyncio.timeout(1.0):
                            while len(got) < 3:
                                got.append((await anext(incoming)).topic)
                    return got

                await transport.own(frozenset({0}))
                owning = await publish_and_read()
                await transport.own(frozenset({1}))
                not_owning = await publish_and_read()
                await nc.close()
            return owning, not_owning

        owning, not_owning = asyncio.run(main())
        assert owning == ["nats:mocap.a.b.pose", "nats:mocap.p.999.pose", "nats:mocap.a.b.skeleton"]
        assert not_owning == []
    finally:
        server.stop()
