"""Cluster mode's transport: NATS with JetStream (``docs/cluster.md``; nats-py's documented API).

Subjects. A publisher's ``mocap/<stream>/pose`` (MQTT, through the server's MQTT listener) is NATS
subject ``mocap.<stream>.pose``, which the server maps (``deploy/nats/nats.conf``) to
``mocap.p.<partition>.<stream>.pose``, the partition a hash of the stream id; skeletons likewise.
Each partition's messages are captured by its own JetStream stream ``MOCAPD_BUF_<p>`` (memory,
``cluster.buffer_s`` long): the buffer a new owner rebuilds the partition's streams from. A worker
owns some partitions (:meth:`NatsTransport.own`, told by the membership) and reads each owned one
with a push consumer (no acknowledgements, flow control) that starts at the first buffered message:
the buffer replayed, then live, one sequence without a seam. Messages of a partition given up are
dropped, even those already queued.

The deliveries are read on a connection of the worker's own (:mod:`protocols.deliveries`), not
through nats-py, whose reader stops for good on one delivered message whose subject or header block
it cannot decode (any publisher can send one). Each delivery is then taken for what it is: a message
the partition's buffer delivered (its reply is this consumer's acknowledgement subject) goes to the
service whatever its subject or contents, which counts it (a subject that is not
``mocap.p.<p>.<stream>.<word>`` with ``p`` the stream's partition, :func:`partition_of`, is refused
as a ``topic``: a publisher may write to a partition's subject directly); the server's flow control
and heartbeats (status 100, not from the buffer) are answered and not counted; anything else was
published on the delivery subject directly and is counted as ``drops{reason="nats_foreign"}``.

Detections and boundaries are stored first in ``MOCAPD_OUT`` (subjects ``mocap.d.<stream>.<word>``)
with header ``Nats-Msg-Id`` = their id: within the stream's duplicate window the server keeps only the
first copy and acknowledges a repeat as a duplicate. Only a first copy is then published on
``mocap.<stream>.<word>``, where NATS and MQTT subscribers (``mocap/+/detections``) receive it, so a
detection that two workers compute across a takeover reaches clients once; a store that does not
answer is asked again with the same id for :data:`STORE_FOR_S` (an answer that timed out may have
stored it: publishing then could deliver it twice), and only then is the detection published
without it, at least once. (The stream's RePublish
would deliver stored messages to ``mocap.<stream>.<word>`` by itself, but nats-server 2.9.10 does
not deliver republished messages to MQTT subscribers: verified, ``docs/cluster.md``.) A worker
killed between the store and the publish loses that detection. The window runs from the server
storing it to the publish leaving the worker: the answer's way back and the worker's event loop,
which under load is tens to hundreds of milliseconds, and a worker storing its detections one at a
time is inside one much of the time (``tests/test_cluster_e2e.py`` kills a worker while 30 streams
play: with a CPU-bound process more beside it, 2 runs in 5 lost one detection so; the test excuses
exactly those, each proven by the logs). Closing it needs the store to publish (JetStream's
RePublish), which MQTT subscribers do not get from nats-server 2.9.10.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import os
import time
from collections.abc import AsyncIterator, Awaitable, Callable, Mapping
from dataclasses import dataclass
from types import TracebackType
from typing import TYPE_CHECKING

import msgpack
from nats.aio.client import Client as NATS
from nats.aio.msg import Msg
from nats.errors import Error as NatsError
from nats.js.api import (
    AckPolicy,
    ConsumerConfig,
    DeliverPolicy,
    DiscardPolicy,
    KeyValueConfig,
    RetentionPolicy,
    StorageType,
    StreamConfig,
)
from nats.js.errors import Error as JetStreamError
from nats.js.errors import KeyNotFoundError, ServiceUnavailableError

from protocols.deliveries import Delivery, ProtocolError, Reader
from protocols.merge import Merge, Passed, Twice
from protocols.transport import STATE_TOPIC, Incoming, Outgoing, StartupError, Throttle
from protocols.urls import parse_nats_urls

if TYPE_CHECKING:
    from nats.js.client import JetStreamContext
    from nats.js.kv import KeyValue

    from daemon.config import ClusterConfig

log = logging.getLogger("mocapd.cluster")

BUFFER = "MOCAPD_BUF_{}"
"""The JetStream stream buffering partition ``p``'s skeletons and poses."""
OUT = "MOCAPD_OUT"
"""The JetStream stream of published detections and boundaries (de-duplicated by id)."""
QUEUE = 1 << 20
"""Messages received and not yet taken in, at most (then the consumers wait: JetStream's flow
control holds the rest on the server)."""
PUBLISH_TIMEOUT_S = 2.0
STORE_FOR_S = 30.0
"""How long a detection's store into ``MOCAPD_OUT`` is tried again (with its id: the server keeps one
copy) before it is published without it, at least once."""
STARTUP_S = 3.0
"""Entering fails when the server has not answered within this many seconds."""
ENSURE_AT_ONCE = 16
"""Streams made (or checked) at once at start: a clustered JetStream takes 0.2-0.5 s for each, one
after the other."""
ENSURE_FOR_S = 30.0
"""How long a worker starting tries to make the buffers while JetStream times out or is unavailable."""
CATCH_UP_S = 2.0
"""The longest recognition waits for a taken partition's buffer to be read."""
HEARTBEAT_S = 2.0
"""A partition's consumer, idle, says so this often (JetStream's idle heartbeat)."""
SILENT_S = 3 * HEARTBEAT_S
"""A consumer that delivers nothing, not even a heartbeat, for this long is made again (from the
last message read): one lost with a server, or deleted; so is one that delivers none of the
messages its partition's plain subscription brings for this long (its buffer's election lasts
4-5 s)."""
RETRY_S = 0.5
"""How soon a partition's consumer that could not be made is tried again."""
STOP_S = 2.0
"""The longest giving partitions up waits for their consumers to be deleted."""
STRAYS = ("mocap.*.*.pose", "mocap.*.*.skeleton")
"""Pose and skeleton subjects of four tokens, which no mapping partitions and no buffer stores (a
native NATS publisher's stream id with a dot, a partition's subject cut short): the owner of
partition 0 reads them, so that they are counted as refused instead of vanishing. Longer subjects
outside ``mocap.p.`` cannot be told from the partitions' by a subscription, and are not."""
CHECKPOINTS = "MOCAPD_CHECKPOINTS"
"""The key-value bucket of the partitions' checkpoints (key: the partition's number; value: the
buffer sequence after which its new owner starts reading, and the states of the partition's streams
then, :meth:`NatsTransport.checkpoint`)."""
ROOM = 4096
"""Bytes of a server's largest message kept free for a checkpoint's key and headers."""
HOLD_S = 1.0
"""How long a partition's live copy of a message waits for its buffered copy before it is passed
without it (:mod:`protocols.merge`): the longest the poses of a buffer that elects a new leader are
late."""
REMEMBER_S = 30.0
"""How long a copy passed on one path is remembered, so that its copy on the other is dropped."""
TWIN_S = 2.0
"""How long a live copy from one plain subscription waits to be matched by its twin from the other
(:class:`protocols.merge.Twice`; they come milliseconds apart, or not at all while a server is
away: a twin later still goes to the merge, which takes it for a new live copy, and the stream table
refuses it as a repeat). Short, because every message is remembered this long."""
HELD_MOST = 1 << 16
"""Live copies held per partition at most (while its buffer replays, or its consumer is made again)."""
RELEASE_EVERY_S = 0.1


@dataclass(frozen=True, slots=True)
class Ack:
    """What a JetStream delivery's acknowledgement subject says: the stream and the consumer that
    delivered it, its sequence in the stream and its delivery sequence on the consumer."""

    stream: str
    consumer: str
    stream_seq: int
    consumer_seq: int


def acknowledgement(reply: bytes) -> Ack | None:
    """The :class:`Ack` in a JetStream message's reply subject (NATS ADR-15: ``$JS.ACK.<stream>.
    <consumer>.<delivered>.<stream seq>.<consumer seq>.<time>.<pending>``, or the form with
    ``<domain>.<account hash>`` after ``ACK`` and a token at the end); None for any other reply (a
    message JetStream did not deliver). Read here rather than by nats-py's ``msg.metadata``: three
    times faster, and from bytes."""
    tokens = reply.split(b".")
    if len(tokens) == 9 and tokens[0] == b"$JS" and tokens[1] == b"ACK":
        stream, consumer, stream_seq, consumer_seq = tokens[2], tokens[3], tokens[5], tokens[6]
    elif len(tokens) >= 12 and tokens[0] == b"$JS" and tokens[1] == b"ACK":
        stream, consumer, stream_seq, consumer_seq = tokens[4], tokens[5], tokens[7], tokens[8]
    else:
        return None
    if not (stream_seq.isdigit() and consumer_seq.isdigit() and stream.isascii() and consumer.isascii()):
        return None
    return Ack(stream.decode(), consumer.decode(), int(stream_seq), int(consumer_seq))


def partition_of(stream: str, partitions: int) -> int:
    """The partition nats-server's ``partition(P, 1)`` mapping gives ``stream``'s subjects: the
    32-bit FNV-1a hash of the id's bytes, modulo P."""
    h = 0x811C9DC5
    for byte in stream.encode():
        h = ((h ^ byte) * 0x01000193) & 0xFFFFFFFF
    return h % partitions


PROBE = "mocapd.probe"
"""Subjects a worker publishes at start (``mocapd.probe.<token>``) to read the partition the server's
mapping gives ``<token>`` (``mocapd.probe.<p>.<token>``), so that a server partitioning by another
count than ``cluster.partitions`` is refused at once."""
PROBES = 8
PROBE_S = 2.0


def mappings(partitions: int) -> str:
    """The NATS server's subject mappings for ``partitions`` partitions: the text of
    ``deploy/nats/partitions.conf``, which ``deploy/nats/nats.conf`` includes (``mocapd cluster
    mappings`` prints it from ``cluster.partitions``)."""
    rule = f"{{{{partition({partitions},1)}}}}.{{{{wildcard(1)}}}}"
    return (
        f"# The partitioning of mocapd's streams: {partitions} partitions (cluster.partitions of\n"
        "# config.yaml). Made by `mocapd cluster mappings`: change the count there and make this file\n"
        '# again, never by hand (docs/cluster.md, "Partitions").\n'
        "mappings {\n"
        f'  "mocap.*.pose": "mocap.p.{rule}.pose"\n'
        f'  "mocap.*.skeleton": "mocap.p.{rule}.skeleton"\n'
        f'  "{PROBE}.*": "{PROBE}.{rule}"\n'
        "}\n"
    )


def counts_matching(found: dict[str, int], most: int = 4096) -> list[int]:
    """The partition counts of 1 .. ``most`` under which every token of ``found`` falls in the
    partition given with it."""
    return [n for n in range(1, most + 1) if all(partition_of(t, n) == p for t, p in found.items())]


def buffer_subject(partition: int) -> str:
    return f"mocap.p.{partition}.>"


def out_window(buffer_s: float) -> float:
    """Seconds ``MOCAPD_OUT`` keeps ids (its duplicate window): longer than any detection a new
    owner recomputes from the buffer can be old."""
    return max(60.0, 2 * buffer_s)


class NatsTransport:
    """Poses and skeletons of the owned partitions in, detections out (module docstring);
    ``settings``: :class:`daemon.config.ClusterConfig`, ``buffer_s`` the buffers' length in seconds
    (computed by the service when the config says 0)."""

    name = "cluster"

    def __init__(self, settings: ClusterConfig, *, instance: str, source: bool, sink: bool) -> None:
        self.settings = settings
        self.instance = instance
        self.buffer_s = settings.buffer_s or 60.0
        self._source = source
        self._sink = sink
        self._nc: NATS | None = None
        self._js: JetStreamContext | None = None
        self._checkpoints: KeyValue | None = None
        self._status: tuple[Outgoing, Outgoing] | None = None
        # (partition, buffer sequence (-1: none), stream, the message (None: a position only))
        self._queue: asyncio.Queue[tuple[int, int, str | None, Incoming | None]] = asyncio.Queue(QUEUE)
        # per stream, its messages in the queue: the service has not seen them, so forget() keeps it
        self._queued: dict[str, int] = {}
        self._consumers: dict[int, asyncio.Task[None]] = {}
        self._given_up: dict[int, asyncio.Event] = {}
        # consumers given up that have not finished yet: held, so that none is destroyed pending
        self._stopping: set[asyncio.Task[None]] = set()
        self._streams: dict[int, set[str]] = {}
        self._partial: set[int] = set()  # partitions taken from a buffer that had lost messages
        # streams first seen in the replay of such a buffer, or whose checkpoint's state was refused
        self._truncated: set[str] = set()
        self._partition_of: dict[str, int] = {}
        self._position: dict[int, int] = {}  # the last buffer sequence read, per partition
        self._taken: dict[int, int] = {}  # the last buffer sequence the service took in, per partition
        self._stopped = False
        self._consumer_names: dict[int, str] = {}
        self._behind: dict[int, float] = {}  # partitions still reading their buffer: since when
        self._drain_s = 1.0
        self._connected = False
        self.replayed = 0
        """Messages read from a buffer that were there before its consumer started."""
        self.checkpoints = 0
        """Checkpoints stored."""
        self.resumed = 0
        """Partitions taken whose buffer was read from a checkpoint rather than from its start."""
        self.unbuffered = 0
        """Messages passed from a partition's plain subscription alone (:attr:`both_paths`): its
        buffer lost them (electing a leader) or had not delivered them within :data:`HOLD_S`."""
        self.duplicates = 0
        """Detections and boundaries not published because a worker had published them already."""
        self.publish_errors = 0
        self.gaps = 0
        """Buffered messages a consumer skipped (none on a healthy server)."""
        self.foreign = 0
        """Messages on a delivery subject that no buffer delivered (published there directly)."""
        self._foreign_log = Throttle()
        self._reader: Reader | None = None
        self._strays: list[int] = []  # the reader's subscriptions to STRAYS
        self._partition_tokens = frozenset(str(p).encode() for p in range(settings.partitions))
        self._last_error: str | None = None
        self._error_log = Throttle()
        self._servers = parse_nats_urls(settings.nats)
        self.both_paths = len(self._servers) > 1 or settings.replicas > 1
        """Whether each owned partition is read through a plain subscription of its subject too
        (:mod:`protocols.merge`): on a NATS cluster, whose servers route a partition's messages
        while its buffer elects a new leader (set before entering)."""
        # detections and boundaries waiting to be stored and published, in order, with when each came
        self._outgoing: asyncio.Queue[tuple[Outgoing, float]] = asyncio.Queue()
        self._storing = 0
        self._publisher: asyncio.Task[None] | None = None
        self._merges: dict[int, Merge[Delivery]] = {}
        self._twice: dict[int, Twice] = {}
        self._held_dropped = 0  # live copies the merges of partitions given up dropped past HELD_MOST
        self._second: Reader | None = None  # the second plain subscriptions', on another server
        self._live: dict[int, tuple[int, int | None]] = {}  # per partition, its plain subscriptions
        self._releasing: asyncio.Task[None] | None = None

    # ------------------------------------------------------------------------------ the connection

    def announce(self, online: Outgoing, offline: Outgoing) -> None:
        self._status = (online, offline)

    async def __aenter__(self) -> NatsTransport:
        url, servers = self.settings.nats, self._servers
        nc = NATS()
        try:
            async with asyncio.timeout(STARTUP_S):  # the client itself would try for ever
                await nc.connect(
                    servers,
                    dont_randomize=True,  # in the order given, as the deliveries' reader
                    name=self.instance,
                    connect_timeout=2,
                    max_reconnect_attempts=-1,
                    reconnect_time_wait=0.25,  # type: ignore[arg-type]  # seconds, a float (the stub says int)
                    disconnected_cb=self._disconnected,
                    reconnected_cb=self._reconnected,
                    error_cb=self._error,
                )
        except (OSError, NatsError, TimeoutError) as e:
            with contextlib.suppress(NatsError, TimeoutError, OSError):
                await nc.close()
            why = "no answer in time" if isinstance(e, TimeoutError) else str(e) or type(e).__name__
            if self._last_error is not None:
                why += f" (the last error: {self._last_error})"
            raise StartupError("cluster.nats", f"cannot connect to NATS at {url}: {why}") from None
        self._nc = nc
        self._connected = True
        self._js = nc.jetstream()
        try:
            await self._check_partitions()
        except StartupError:
            await nc.close()
            raise
        give_up = time.monotonic() + ENSURE_FOR_S
        while True:
            try:
                await self._ensure_streams()
                break
            except (NatsError, TimeoutError) as e:
                # a clustered JetStream answers slowly while it makes many replicated streams (other
                # workers starting at once), or not while its servers elect a leader: tried again;
                # a refusal is final
                again = isinstance(e, (TimeoutError, ServiceUnavailableError))
                if not again or time.monotonic() >= give_up:
                    await nc.close()
                    why = f"{url}: JetStream unavailable or refused: {e}"
                    raise StartupError("cluster.nats", why) from None
                log.warning("JetStream not ready", extra={"fields": {"error": repr(e)}})
                await asyncio.sleep(RETRY_S)
        self._reader = Reader(servers, name=f"{self.instance} deliveries")
        try:
            await self._reader.start(STARTUP_S)
        except (OSError, ValueError, ProtocolError) as e:
            await nc.close()
            why = str(e) or type(e).__name__
            raise StartupError("cluster.nats", f"{url}: cannot read deliveries: {why}") from None
        if self.both_paths and len(servers) > 1:
            # on another server from the first: whichever of the two is killed, the other carries
            # the live copies while the reader of the killed one moves (protocols.merge.Twice)
            self._second = Reader([*servers[1:], servers[0]], name=f"{self.instance} second copies")
            try:
                await self._second.start(STARTUP_S)
            except (OSError, ValueError, ProtocolError) as e:
                await self._reader.close()
                await nc.close()
                why = str(e) or type(e).__name__
                raise StartupError("cluster.nats", f"{url}: cannot read deliveries: {why}") from None
        if self._status is not None:
            await self._plain(self._status[0])
        if self.both_paths:
            self._releasing = asyncio.create_task(self._release(), name="cluster live copies")
        return self

    async def _check_partitions(self) -> None:
        """StartupError naming ``cluster.partitions`` unless the server maps :data:`PROBES` probe
        tokens to the partitions :func:`partition_of` gives them with ``cluster.partitions``."""
        nc = self._nc
        assert nc is not None
        want = self.settings.partitions
        tokens = {os.urandom(6).hex() for _ in range(PROBES)}
        found: dict[str, int] = {}
        done = asyncio.Event()

        async def got(msg: Msg) -> None:
            *_, p, token = msg.subject.split(".")
            if token in tokens and p.isdigit():
                found[token] = int(p)
                if len(found) == len(tokens):
                    done.set()

        sub = await nc.subscribe(f"{PROBE}.*.*", cb=got)
        try:
            for token in tokens:
                await nc.publish(f"{PROBE}.{token}", b"")
            with contextlib.suppress(TimeoutError):
                async with asyncio.timeout(PROBE_S):
                    await done.wait()
        finally:
            with contextlib.suppress(NatsError, TimeoutError, OSError):
                await sub.unsubscribe()
        url = self.settings.nats
        if len(found) < len(tokens):
            raise StartupError(
                "cluster.partitions",
                f"the NATS server at {url} does not map {PROBE}.*: its config lacks the mappings "
                f"`mocapd cluster mappings` makes (deploy/nats/partitions.conf)",
            )
        if any(partition_of(t, want) != p for t, p in found.items()):
            theirs = counts_matching(found)
            said = f"by {theirs[0]}" if len(theirs) == 1 else "by another count"
            raise StartupError(
                "cluster.partitions",
                f"{want} here, but the NATS server at {url} partitions {said}: make its mappings "
                f"with `mocapd cluster mappings` from the same cluster.partitions",
            )

    async def __aexit__(
        self, kind: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        await self.own(frozenset())
        for task in (self._releasing, self._publisher):
            if task is not None:
                task.cancel()
        for reader in (self._reader, self._second):
            if reader is not None:
                await reader.close()
        nc = self._nc
        if nc is None:
            return
        with contextlib.suppress(NatsError, TimeoutError, OSError):
            async with asyncio.timeout(self._drain_s):
                if self._status is not None:
                    await self._plain(self._status[1])
                await nc.flush()
        with contextlib.suppress(NatsError, TimeoutError, OSError):
            await nc.close()
        self._nc = None

    async def _disconnected(self) -> None:
        self._connected = False

    async def _reconnected(self) -> None:
        """Back after a disconnection. A server that restarted lost its memory streams and their
        consumers: make the streams again and every owned partition's consumer anew (what the table
        already took is refused again by its sequence numbers)."""
        self._connected = True
        js = self._js
        if js is None:
            return
        with contextlib.suppress(NatsError, TimeoutError, OSError):
            await self._ensure_streams()
        for p in list(self._consumers):
            name = self._consumer_names.get(p)
            if name is not None:
                try:
                    await js.consumer_info(BUFFER.format(p), name)
                    continue  # still there: it goes on where it was
                except (NatsError, TimeoutError, OSError):
                    pass
            self._give_up(p)
            self._take(p)

    async def _error(self, e: Exception) -> None:
        """nats-py's errors: before the first connection, kept for the startup error's one line
        (the client retries every quarter second); after it, logged at most one every 10 s, with
        how many were not."""
        self._last_error = f"{type(e).__name__}: {e}"[:300]
        if self._nc is not None and (quiet := self._error_log.due()) is not None:
            log.warning("nats error", extra={"fields": {"error": self._last_error, "since_last": quiet}})

    async def _ensure_streams(self) -> None:
        """The partitions' buffers and the detections' stream, made or brought to these settings."""
        assert self._js is not None
        configs = [
            StreamConfig(
                name=BUFFER.format(p),
                subjects=[buffer_subject(p)],
                retention=RetentionPolicy.LIMITS,
                storage=StorageType.MEMORY,
                discard=DiscardPolicy.OLD,
                max_age=self.buffer_s,
                num_replicas=self.settings.replicas,
            )
            for p in range(self.settings.partitions)
        ]
        window = out_window(self.buffer_s)
        configs.append(
            StreamConfig(
                name=OUT,
                subjects=["mocap.d.>"],
                retention=RetentionPolicy.LIMITS,
                storage=StorageType.MEMORY,
                discard=DiscardPolicy.OLD,
                max_age=window,
                duplicate_window=window,
                num_replicas=self.settings.replicas,
            )
        )
        js = self._js
        room = asyncio.Semaphore(ENSURE_AT_ONCE)

        async def ensure(config: StreamConfig) -> None:
            async with room:
                try:
                    await js.add_stream(config)
                except JetStreamError:  # there already, made by another worker with other settings
                    await js.update_stream(config)

        async def checkpoints() -> None:
            async with room:
                config = KeyValueConfig(
                    bucket=CHECKPOINTS,
                    storage=StorageType.MEMORY,
                    ttl=self.buffer_s,  # older, it names messages the buffer no longer holds
                    replicas=self.settings.replicas,
                )
                try:
                    self._checkpoints = await js.create_key_value(config)
                except JetStreamError:  # there already, made by another worker with other settings
                    self._checkpoints = await js.key_value(CHECKPOINTS)

        ensured = [*map(ensure, configs), checkpoints()]
        failed = [e for e in await asyncio.gather(*ensured, return_exceptions=True) if e]
        if failed:
            raise failed[0]

    @property
    def problem(self) -> str | None:
        if self._nc is None:
            return "not connected"
        if not self._connected:
            return f"disconnected from {self.settings.nats}"
        reader = self._reader
        return None if reader is None or reader.problem is None else f"deliveries: {reader.problem}"

    @property
    def pending(self) -> int:
        """Detections and boundaries not yet stored and published (:meth:`publish`)."""
        return self._outgoing.qsize() + self._storing

    def dropped(self) -> dict[str, int]:
        """Messages on a delivery subject that no buffer delivered (``nats_foreign``), deliveries
        whose handling raised (``nats_internal``, a defect: that message lost, the reading goes on)
        and live copies held past :data:`HELD_MOST` (``nats_held``: the buffer has them, if it
        works)."""
        failures = sum(r.failures for r in (self._reader, self._second) if r is not None)
        held = self._held_dropped + sum(m.dropped for m in self._merges.values())
        return {"nats_foreign": self.foreign, "nats_internal": failures, "nats_held": held}

    def drain_within(self, seconds: float) -> None:
        self._drain_s = seconds

    def ask_skeleton(self, stream: str) -> None:
        """Nothing: publishers announce their skeletons at least once a second, and the buffer holds
        the last ones."""

    # ------------------------------------------------------------------------------- ownership

    @property
    def owned(self) -> frozenset[int]:
        return frozenset(self._consumers)

    def partial(self, stream: str) -> bool:
        """Whether ``stream`` was first seen in the replay of a buffer that had already lost
        messages (to its age limit, no checkpoint to start from), or its checkpoint's state was
        refused (:meth:`refused`), so that its history here may begin mid-motion (the service then
        suppresses what a truncated history could get wrong). A stream first seen live, in a buffer
        that holds the partition's whole history, or resumed from a checkpoint, is whole."""
        return stream in self._truncated

    def refused(self, stream: str) -> None:
        """``stream``'s state could not be resumed: it is taken as a truncated history
        (:meth:`partial`)."""
        self._truncated.add(stream)

    async def own(self, partitions: frozenset[int]) -> list[str]:
        """Consume exactly ``partitions`` from now on; the streams seen in the partitions given up."""
        lost: list[str] = []
        gone = sorted(set(self._consumers) - partitions)
        tasks = [self._give_up(p) for p in gone]
        if tasks:
            # their consumers are deleted on the way out; a server that does not answer must not
            # hold up the membership (the consumers then lapse by their inactivity threshold)
            _, late = await asyncio.wait(tasks, timeout=STOP_S)
            if late:
                log.warning("partition consumers slow to stop", extra={"fields": {"count": len(late)}})
        for p in gone:
            merge = self._merges.pop(p, None)
            if merge is not None:
                self._held_dropped += merge.dropped
            self._twice.pop(p, None)
            sids = self._live.pop(p, None)
            for sid, reader in zip(sids or (), (self._reader, self._second), strict=False):
                if sid is not None and reader is not None:
                    await reader.unsubscribe(sid)
            self._partial.discard(p)
            self._behind.pop(p, None)
            self._position.pop(p, None)
            self._taken.pop(p, None)
            self._consumer_names.pop(p, None)
            for stream in self._streams.pop(p, set()):
                self._partition_of.pop(stream, None)
                self._truncated.discard(stream)
                lost.append(stream)
        for p in sorted(partitions - set(self._consumers)):
            if self.both_paths and self._reader is not None:
                # subscribed before the consumer starts: what the plain subscription misses at the
                # start, the buffer has
                self._merges[p] = Merge(HOLD_S, REMEMBER_S, HELD_MOST)
                second = None
                if self._second is not None:
                    self._twice[p] = Twice(TWIN_S)
                    second = self._second.register(buffer_subject(p), self._live_copy(p, 1))
                self._live[p] = (self._reader.register(buffer_subject(p), self._live_copy(p, 0)), second)
            self._take(p)
        await self._watch_strays(0 in partitions)
        return lost

    async def _watch_strays(self, watch: bool) -> None:
        """Subscribe to :data:`STRAYS` while this worker owns partition 0 (one worker counts them),
        unsubscribe otherwise (not waiting for the server: a reader not connected subscribes when
        it is again)."""
        reader = self._reader
        if reader is None or watch == bool(self._strays):
            return
        if not watch:
            for sid in self._strays:
                await reader.unsubscribe(sid)
            self._strays = []
            return
        self._strays = [reader.register(subject, self._stray) for subject in STRAYS]

    async def _stray(self, d: Delivery) -> None:
        """A pose or skeleton on a subject no buffer stores: taken in as the topic it is, which the
        service refuses and counts (``topic``). ``mocap.p.<p>.pose`` with ``p`` a partition is a
        buffer's (its consumer delivers it), and passed over here."""
        tokens = d.subject.split(b".")
        if tokens[1] == b"p" and tokens[2] in self._partition_tokens:
            return
        incoming = Incoming(f"nats:{d.subject.decode('utf-8', 'replace')[:200]}", d.data, time.time())
        try:
            self._queue.put_nowait((0, -1, None, incoming))
        except asyncio.QueueFull:
            await self._queue.put((0, -1, None, incoming))

    def _live_copy(self, p: int, path: int) -> Callable[[Delivery], Awaitable[None]]:
        """The handler of partition ``p``'s plain subscription on reader ``path`` (0: the first, 1:
        the second): each message's first copy to the merge."""

        async def got(d: Delivery) -> None:
            merge = self._merges.get(p)
            if merge is None:
                return
            key, now, twice = merge_key(d), time.monotonic(), self._twice.get(p)
            if twice is None or twice.first(key, path, now):
                await self._pass(p, merge.push(key, d, now), replayed=False)

        return got

    async def _release(self) -> None:
        """Pass, every :data:`RELEASE_EVERY_S`, the live copies held for :data:`HOLD_S` whose
        buffered copies have not come."""
        while True:
            await asyncio.sleep(RELEASE_EVERY_S)
            now = time.monotonic()
            for p, merge in list(self._merges.items()):
                await self._pass(p, merge.release(now), replayed=False)

    async def _pass(self, p: int, passed: list[Passed[Delivery]], *, replayed: bool) -> None:
        """Queue what the merge passed (a marker: the buffer sequence alone)."""
        for seq, d in passed:
            if seq < 0:
                self.unbuffered += 1
            if d is None:
                item: tuple[int, int, str | None, Incoming | None] = (p, seq, None, None)
            else:
                stream, incoming = self._incoming(d, self._streams.setdefault(p, set()), p, replayed=replayed)
                if stream is not None:
                    self._queued[stream] = self._queued.get(stream, 0) + 1
                item = (p, seq, stream, incoming)
            try:
                self._queue.put_nowait(item)
            except asyncio.QueueFull:
                await self._queue.put(item)

    def _take(self, p: int) -> None:
        given_up = self._given_up[p] = asyncio.Event()
        self._consumers[p] = asyncio.create_task(self._consume(p, given_up), name=f"partition {p}")

    def _give_up(self, p: int) -> asyncio.Task[None]:
        """Stop reading partition ``p``: its consumer's task, told to stop. Cancelling alone is not
        enough: nats-py swallows a cancellation that arrives while it flushes (``_flush_pending``),
        and a consumer that outlived it would go on reading a partition given up."""
        task = self._consumers.pop(p)
        self._given_up.pop(p).set()
        task.cancel()
        self._stopping.add(task)
        task.add_done_callback(self._stopping.discard)
        return task

    @property
    def catching_up(self) -> bool:
        """Whether a partition taken less than :data:`CATCH_UP_S` ago is still reading what its
        buffer held (the service recognises after it: the partition is live sooner)."""
        now = time.monotonic()
        return any(now - since < CATCH_UP_S for since in self._behind.values())

    def partition(self, stream: str) -> int | None:
        """The owned partition ``stream`` came in on (None: none seen)."""
        return self._partition_of.get(stream)

    def streams_of(self, p: int) -> frozenset[str]:
        """The streams seen in owned partition ``p``."""
        return frozenset(self._streams.get(p, ()))

    def stop_taking(self) -> None:
        """Give the service no more messages (a worker handing its partitions over): what was read
        and not taken in is the new owners' to read."""
        self._stopped = True

    def taken_up_to(self, p: int) -> int | None:
        """The sequence of the last message of owned partition ``p``'s buffer that the service has
        taken in (None: none yet, or a message taken in after it came on the plain subscription
        alone and may yet come from the buffer): the position of a checkpoint taken now."""
        merge = self._merges.get(p)
        if merge is not None and merge.awaiting(time.monotonic()):
            return None
        return self._taken.get(p) if p in self._consumers else None

    async def checkpoint(self, p: int, position: int, states: Mapping[str, bytes]) -> bool:
        """Store partition ``p``'s checkpoint: its next owner reads its buffer from after
        ``position`` and resumes its streams from ``states`` (each stream's
        :meth:`daemon.service.streams.StreamTable.state` when the message at ``position`` had been
        taken in). Whether it was stored: one that fails, or is larger than the server's largest
        message, is logged and skipped (the older checkpoint, or none, costs a longer read only)."""
        kv, nc = self._checkpoints, self._nc
        if kv is None or nc is None:
            return False
        value = msgpack.packb({"after": position, "streams": dict(states)})
        try:
            if len(value) > nc.max_payload - ROOM:
                raise ValueError(f"{len(value)} bytes, more than the server's messages hold")
            await kv.put(str(p), value)
        except (NatsError, TimeoutError, ValueError) as e:
            if (quiet := self._error_log.due()) is not None:
                log.warning(
                    "checkpoint not stored",
                    extra={"fields": {"partition": p, "error": repr(e), "since_last": quiet}},
                )
            return False
        self.checkpoints += 1
        return True

    async def _checkpoint_of(self, p: int) -> tuple[int, dict[str, bytes]] | None:
        """Partition ``p``'s stored checkpoint (:meth:`checkpoint`'s position and states; None:
        none, or unreadable)."""
        kv = self._checkpoints
        if kv is None:
            return None
        try:
            entry = await kv.get(str(p))
        except KeyNotFoundError:
            return None
        except (NatsError, TimeoutError) as e:
            log.warning("checkpoint not read", extra={"fields": {"partition": p, "error": repr(e)}})
            return None
        try:
            value = msgpack.unpackb(entry.value or b"")
            after, states = value["after"], value["streams"]
            if not isinstance(after, int) or not isinstance(states, dict):
                raise TypeError("after, streams")
            if not all(isinstance(k, str) and isinstance(v, bytes) for k, v in states.items()):
                raise TypeError("a stream's state")
        except (ValueError, TypeError, KeyError, AttributeError, msgpack.UnpackException) as e:
            log.warning(
                "checkpoint not read", extra={"fields": {"partition": p, "error": f"malformed: {e!r}"}}
            )
            return None
        return after, states

    def waiting(self) -> frozenset[str]:
        """The streams with a message waiting to be taken in: queued, or a live copy held for its
        buffered copy (:mod:`protocols.merge`; held while a buffer replays, however long that takes,
        and a stream whose poses are held is not silent)."""
        held = {
            d.subject.split(b".")[3].decode("utf-8", "replace")
            for merge in self._merges.values()
            for d in merge.holding()
            if d.subject.count(b".") == 4
        }
        return frozenset(self._queued).union(held)

    def forget(self, keep: set[str]) -> None:
        """Forget the streams not in ``keep`` (those the service no longer holds) that have no
        message waiting to be taken in: a stream read from a buffer but not yet taken in keeps what
        is known of it (a truncated history's mark above all, :meth:`partial`)."""
        for streams in self._streams.values():
            gone = {s for s in streams - keep if not self._queued.get(s)}
            streams -= gone
            for s in gone:
                self._partition_of.pop(s, None)
                self._truncated.discard(s)

    async def _resume(self, p: int, position: int, states: Mapping[str, bytes]) -> None:
        """Partition ``p`` taken from a checkpoint at ``position``: its streams' ``states`` go to
        the service first (:data:`STATE_TOPIC`), and reading goes on after ``position`` (also when
        the consumer is made again)."""
        self._position[p] = position
        streams = self._streams.setdefault(p, set())
        now = time.time()
        for stream, state in states.items():
            streams.add(stream)
            self._partition_of[stream] = p
            self._queued[stream] = self._queued.get(stream, 0) + 1
            await self._queue.put((p, -1, stream, Incoming(STATE_TOPIC + stream, state, now)))

    async def _consume(self, p: int, given_up: asyncio.Event) -> None:
        """Read partition ``p`` until it is given up; a consumer that cannot be made (the server
        away) is tried again every :data:`RETRY_S`."""
        while not given_up.is_set():
            try:
                await self._read(p, given_up)
            except (NatsError, TimeoutError, OSError) as e:
                log.warning("partition not read", extra={"fields": {"partition": p, "error": repr(e)}})
                merge = self._merges.get(p)
                if merge is not None:  # no replay comes until a consumer is made: the live path goes on
                    merge.went_live(time.monotonic())
                with contextlib.suppress(TimeoutError):
                    async with asyncio.timeout(RETRY_S):
                        await given_up.wait()

    async def _read(self, p: int, given_up: asyncio.Event) -> None:
        assert self._js is not None
        js = self._js
        taken = time.time()
        merge = self._merges.get(p)
        info = await js.stream_info(BUFFER.format(p))
        if given_up.is_set():
            return
        state = info.state
        last = state.last_seq
        position = self._position.get(p)
        if position is not None and position > last:
            position = None  # the server lost the buffer (a restart): from its start again
        states: dict[str, bytes] | None = None  # read from a checkpoint: its streams' states
        if position is None:
            checkpoint = await self._checkpoint_of(p)
            if given_up.is_set():
                return
            # from after the checkpoint, if the buffer holds what follows it (else from its start)
            if checkpoint is not None and state.first_seq <= checkpoint[0] + 1 and checkpoint[0] <= last:
                position, states = checkpoint
                self.resumed += 1
                await self._resume(p, position, states)
        if state.first_seq > 1 and states is None:  # its streams' histories may begin mid-way
            self._partial.add(p)
        replay = bool(state.messages) and (position is None or position < last)
        if replay:
            self._behind[p] = time.monotonic()
            if merge is not None:  # the live copies wait until the buffer has replayed what precedes them
                merge.replaying = True
        log.info(
            "partition taken",
            extra={
                "fields": {
                    "partition": p,
                    "buffered": state.messages,
                    "partial": p in self._partial,
                    "from": 1 if position is None else position + 1,
                }
            },
        )
        nc, reader = self._nc, self._reader
        assert nc is not None and reader is not None
        live = False
        expected = 1  # the consumer's next delivery sequence
        heard = time.monotonic()  # the consumer's last delivery or heartbeat
        buffer = BUFFER.format(p)
        inbox = nc.new_inbox()
        name = f"mocapd-{p}-{inbox.rsplit('.', 1)[-1]}"  # known before the first delivery comes

        async def got(d: Delivery) -> None:
            nonlocal live, expected, heard
            if given_up.is_set():
                return
            ack = acknowledgement(d.reply)
            if ack is None or ack.stream != buffer or ack.consumer != name or ack.consumer_seq < expected:
                if d.status() == b"100":  # the server's flow control, or a heartbeat
                    heard = time.monotonic()
                    reply = d.reply if d.reply.startswith(b"$JS.FC.") else d.header(b"Nats-Consumer-Stalled")
                    if reply is not None and reply.startswith(b"$JS.FC."):
                        reader.publish(reply)
                    return
                self.foreign += 1  # published on the delivery subject, not delivered by the buffer
                self._note_foreign(p, d)
                return
            heard = time.monotonic()
            seq, delivered = ack.stream_seq, ack.consumer_seq
            if delivered != expected:  # lost on the way (a connection that moved): read them again
                self.gaps += delivered - expected
                again = self._position.get(p, 0) + 1
                log.warning(
                    "buffer gap", extra={"fields": {"partition": p, "expected": expected, "again": again}}
                )
                self._give_up(p)
                self._take(p)
                return
            expected = delivered + 1
            self._position[p] = seq
            if not live:
                if seq >= last:
                    self._behind.pop(p, None)
                if seq > last:
                    live = True
                    log.info(
                        "partition live",
                        extra={"fields": {"partition": p, "since_taken": round(time.time() - taken, 4)}},
                    )
                else:
                    self.replayed += 1
            if merge is None:
                await self._pass(p, [(seq, d)], replayed=not live)
                return
            now = time.monotonic()
            passed = merge.push(merge_key(d), d, now, seq)
            if merge.replaying and seq >= last:
                merge.went_live(now)
                passed += merge.release(now)
            await self._pass(p, passed, replayed=not live)

        # A push consumer read by a subscription of the worker's own reader, flow control answered
        # here: nats-py's ordered consumer does the same with its own checks per message, at a fifth
        # of the rate (a taken partition's buffer is read this much sooner).
        sid = await reader.subscribe(inbox, got)
        consumer = None
        try:
            consumer = await js.add_consumer(
                buffer,
                ConsumerConfig(
                    name=name,
                    deliver_subject=inbox,
                    # from the first buffered message, or after the last read (a consumer made anew)
                    deliver_policy=DeliverPolicy.ALL if position is None else DeliverPolicy.BY_START_SEQUENCE,
                    opt_start_seq=None if position is None else position + 1,
                    ack_policy=AckPolicy.NONE,
                    filter_subject=buffer_subject(p),
                    flow_control=True,
                    idle_heartbeat=HEARTBEAT_S,
                    inactive_threshold=30.0,
                ),
            )
            if not given_up.is_set():
                self._consumer_names[p] = consumer.name
                if merge is not None and not replay:
                    merge.went_live(time.monotonic())
            heard = time.monotonic()
            if merge is not None:
                merge.rewatch()
            while not given_up.is_set():
                with contextlib.suppress(TimeoutError):
                    async with asyncio.timeout(HEARTBEAT_S):
                        await given_up.wait()
                # a full queue holds the reader (and the heartbeats) back: that is no silence
                now = time.monotonic()
                if now - heard > SILENT_S and self._queue.qsize() < QUEUE // 2:
                    raise TimeoutError(f"no delivery nor heartbeat for {SILENT_S:.0f} s")
                if merge is not None and merge.stalled(now, SILENT_S):
                    raise TimeoutError(f"nothing of the live messages delivered for {SILENT_S:.0f} s")
        finally:
            await reader.unsubscribe(sid)
            # by its name: given up while the server made it, the consumer exists without an answer
            # here, and would push to an inbox nobody reads until its inactivity threshold
            with contextlib.suppress(NatsError, TimeoutError, OSError):
                await js.delete_consumer(buffer, name if consumer is None else consumer.name)

    def _note_foreign(self, p: int, d: Delivery) -> None:
        """Log a message published on a delivery subject: the first, then at most one every 10 s
        with the count of those not logged."""
        if self._foreign_log.due() is None:
            return
        log.warning(
            "not a delivery",
            extra={
                "fields": {
                    "partition": p,
                    "reply": d.reply[:80].decode("utf-8", "replace"),
                    "count": self.foreign,
                }
            },
        )

    def _incoming(
        self,
        d: Delivery,
        streams: set[str],
        p: int,
        *,
        replayed: bool,
    ) -> tuple[str | None, Incoming]:
        """The message as the service takes it in, whatever its subject: ``mocap.p.<p>.<stream>.
        <word>`` as topic ``mocap/<stream>/<word>`` (a stream seen for the first time is noted, and
        noted as truncated, :meth:`partial`, if its first message was ``replayed`` from a buffer that
        had lost messages); any
        other subject (a publisher's, straight into the buffer: another number of tokens, another
        partition than the stream's, bytes that are not UTF-8) as a topic the service refuses and
        counts (``topic``). With the stream (None: no
        stream's)."""
        now = time.time()
        try:
            subject = d.subject.decode()
        except UnicodeDecodeError:
            return None, Incoming(f"nats:{d.subject.decode('utf-8', 'replace')[:200]}", d.data, now)
        tokens = subject.split(".")
        if (
            len(tokens) != 5
            or tokens[:3] != ["mocap", "p", str(p)]
            or not all(tokens[3:])
            or partition_of(tokens[3], self.settings.partitions) != p  # published past the mapping
        ):
            return None, Incoming(f"nats:{subject[:200]}", d.data, now)
        stream = tokens[3]
        if stream not in streams:
            streams.add(stream)
            self._partition_of[stream] = p
            if replayed and p in self._partial:
                self._truncated.add(stream)
        return stream, Incoming(f"mocap/{stream}/{tokens[-1]}", d.data, now)

    # --------------------------------------------------------------------------- source and sink

    def source(self) -> NatsTransport | None:
        return self if self._source else None

    def __aiter__(self) -> AsyncIterator[Incoming]:
        return self._messages()

    async def _messages(self) -> AsyncIterator[Incoming]:
        while True:
            p, seq, stream, incoming = await self._queue.get()
            if stream is not None:
                left = self._queued.pop(stream, 1) - 1
                if left:
                    self._queued[stream] = left
            if self._stopped:
                continue
            if p in self._consumers:  # not of a partition given up since
                if seq >= 0:  # the service takes it in before it asks for the next: no await between
                    self._taken[p] = seq
                if incoming is not None:
                    yield incoming

    def sink(self) -> NatsTransport | None:
        return self if self._sink else None

    async def publish(self, message: Outgoing) -> None:
        """Publish ``message``: one with an id (a detection, a boundary) is queued, stored and
        published in turn by a task of its own, so that a store that does not answer (its leader
        electing) holds up no recognition (:attr:`pending` counts what waits); others at once."""
        if message.relay or message.reminder:  # poses are on the bus already; etcd says who lives
            return
        if message.key is None:
            await self._plain(message)
            return
        self._outgoing.put_nowait((message, time.monotonic()))
        if self._publisher is None:
            self._publisher = asyncio.create_task(self._publish_stored(), name="cluster detections")

    async def _publish_stored(self) -> None:
        while True:
            message, queued = await self._outgoing.get()
            self._storing = 1
            try:
                await self._store(message, queued + STORE_FOR_S)
            except Exception as e:  # a defect of mocapd's: it costs this detection, not the others
                log.error("detection not published", extra={"fields": {"id": message.key, "error": repr(e)}})
            finally:
                self._storing = 0

    async def _store(self, message: Outgoing, given_up: float) -> None:
        """Store ``message`` in ``MOCAPD_OUT`` under its id, then publish it if it is the first
        copy; asked again until ``given_up`` (monotonic), then published without the store."""
        assert self._js is not None and message.key is not None
        parts = message.topic.split("/")
        while True:
            try:
                ack = await self._js.publish(
                    f"mocap.d.{parts[1]}.{parts[2]}",
                    message.payload,
                    timeout=PUBLISH_TIMEOUT_S,
                    headers={"Nats-Msg-Id": message.key},
                )
            except (NatsError, TimeoutError) as e:
                # unknown whether it was stored (perhaps by another worker before): asking again
                # with the same id tells, where publishing now could deliver it twice
                self.publish_errors += 1
                late = time.monotonic() >= given_up
                log.warning(
                    "detection not stored: published without the store"
                    if late
                    else "detection not stored yet",
                    extra={"fields": {"id": message.key, "error": repr(e)}},
                )
                if late:
                    break
                await asyncio.sleep(RETRY_S)
                continue
            if ack.duplicate:
                self.duplicates += 1
                log.debug("duplicate", extra={"fields": {"id": message.key}})
                return
            break
        await self._plain(message)

    async def _plain(self, message: Outgoing) -> None:
        if self._nc is None:
            return
        with contextlib.suppress(NatsError):
            await self._nc.publish(message.topic.replace("/", "."), message.payload)


def merge_key(d: Delivery) -> int | None:
    """A delivered message's key in its partition's merge (None: a skeleton, which publishers
    announce again identically, :mod:`protocols.merge`)."""
    return None if d.subject.endswith(b".skeleton") else hash((d.subject, d.data))


def transport(settings: ClusterConfig, *, instance: str, source: bool, sink: bool) -> NatsTransport:
    return NatsTransport(settings, instance=instance, source=source, sink=sink)
