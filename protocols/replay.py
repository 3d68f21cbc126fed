"""A recording replayed onto a bus as a live stream (``mocapd replay``): the messages of
:func:`protocols.publish.messages` sent to the daemon's ZeroMQ poses socket or an MQTT broker, each pose
on its due time (:func:`protocols.publish.due`: paced by the clock, no drift over a long file).

ZeroMQ late joiners: a PUB socket sends nothing to a subscriber whose connection is not up yet, so a
replay's first frames would be lost. The replay's socket is an XPUB, which receives the subscriber's
subscription once the connection is up; the replay waits for it before the skeleton goes out, and
its high-water mark is large enough that a replay as fast as possible is not dropped at the sender.
On MQTT the skeleton is retained (QoS 1), so a daemon started later still learns it; with
``retain=False`` (``--no-retain``) the skeletons and the end go at QoS 0, not retained, as a NATS
cluster's MQTT listener needs (``docs/cluster.md``: nats-server 2.9 stores QoS 1 and retained messages
in JetStream while it holds the publisher's connection, whose later poses a killed server then cost).

A stream's life (``protocols/README.md``): every replay is a new run of its stream, with an epoch of
its own in its skeleton and poses; the skeleton is announced again every :data:`ANNOUNCE_S` and at
once when a daemon asks — a subscription reaching the XPUB socket (a daemon that started or
restarted), an "online" status on MQTT — so a restarted daemon, or one that forgot a stream that was
silent too long, learns it again within a second.
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import os
import signal
import threading
import time
import uuid
from collections.abc import Awaitable, Callable, Sequence
from typing import Any
from urllib.parse import urlsplit

import numpy as np
import zmq
import zmq.asyncio

from daemon.errors import MocapdError
from protocols.messages import (
    EndMessage,
    FrameMessage,
    PoseMessage,
    StatusMessage,
    WireError,
    decode,
    encode,
    topic,
)
from protocols.publish import Items, Recording, due, framed, messages
from protocols.transport import Outgoing

SEND_HWM = 10_000_000
ANNOUNCE_S = 1.0
"""The longest a replay goes without announcing its skeleton."""
FINISH_S = 10.0
"""How long a replay that has sent everything waits for it to leave (a peer gone: no longer)."""
STOPPED_S = 0.5
"""How long a replay stopped by a signal still gives what it sent to leave: alone on a machine it
exits within a second of SIGTERM whatever its peer does."""
STOP_SIGNALS = (signal.SIGTERM, signal.SIGINT)


class TargetError(MocapdError, ValueError):
    """A URL a replay cannot send to."""


async def replay_to(
    url: str,
    motion: Recording,
    asf_text: str,
    *,
    stream: str,
    rate: float,
    speed: float | None = 1.0,
    loop: bool = False,
    wait_s: float = 10.0,
    retain: bool = True,
    others: Sequence[tuple[Recording, str, str]] = (),
    source: str = "replay",
) -> int:
    """Replay ``motion`` onto ``url`` (``zmq+tcp://HOST:PORT``: the daemon's poses socket;
    ``mqtt://HOST:PORT`` or ``mqtts://``: a broker) as ``stream``; the poses sent. With ``others``
    (recording, ASF text, stream; at the same ``rate``), every recording's poses of a step go out
    together in frame messages from ``source`` (:func:`protocols.publish.framed`), as a capture
    system sends its subjects. :class:`TargetError` for another URL (a ValueError from
    :func:`protocols.mqtt.parse_url` for a bad MQTT one); TimeoutError when no subscriber or broker
    answers within ``wait_s``."""
    scheme = urlsplit(url).scheme
    epoch, passes = uuid.uuid4().hex[:16], None if loop else 1
    items = messages(motion, asf_text, stream, rate, passes, epoch=epoch)
    if others:
        items = framed(
            [items, *(messages(m, text, name, rate, passes, epoch=epoch) for m, text, name in others)], source
        )
    if scheme.startswith("zmq+"):
        return await _to_zmq(url[len("zmq+") :], items, rate, speed, wait_s)
    if scheme in ("mqtt", "mqtts"):
        return await _to_mqtt(url, items, stream, rate, speed, wait_s, retain)
    raise TargetError(f"must be zmq+tcp://HOST:PORT or mqtt://HOST:PORT, got {url!r}")


async def _send_all(
    send: Callable[[Outgoing], Awaitable[None]],
    items: Items,
    rate: float,
    speed: float | None,
    asked: Callable[[], bool] = lambda: False,
    retain: bool = True,
) -> int:
    """Send every message through ``send(Outgoing)`` (awaited), poses on their due times (a frame
    message's by its step: the k-th is due as frame k); the skeletons again every
    :data:`ANNOUNCE_S` and whenever ``asked()`` says a daemon asks for them; ``retain``: the
    skeletons retained and reliable (QoS 1 on MQTT), the ends reliable (after frame messages, on
    their topic). The poses sent."""
    sent = 0
    start = time.monotonic()
    i = 0
    first: int | None = None
    steps = 0
    skeletons: list[Outgoing] = []
    announced = start
    framing: str | None = None  # the topic of the frame messages sent
    for m in items:
        if isinstance(m, PoseMessage | FrameMessage):
            if isinstance(m, PoseMessage):
                first = m.seq if first is None else first
                step = m.seq - first
            else:
                step, steps = steps, steps + 1
            wait = due(start, step, rate, speed) - time.monotonic()
            if wait > 0:
                await asyncio.sleep(wait)
            elif i % 256 == 0:
                await asyncio.sleep(0)
            if skeletons and (asked() or time.monotonic() - announced >= ANNOUNCE_S):
                for skeleton in skeletons:
                    await send(skeleton)
                announced = time.monotonic()
            now = time.time()
            if isinstance(m, PoseMessage):
                m = PoseMessage(m.stream, m.seq, now, m.positions, m.channels, m.epoch)
                sent += 1
            else:
                m = dataclasses.replace(m, time=np.full(len(m.streams), now))
                sent += len(m.streams)
                framing = topic(m)
            out = Outgoing(topic(m), encode(m))
            i += 1
        elif isinstance(m, EndMessage):
            # after frame messages, on their topic: on its stream's own it could overtake them
            out = Outgoing(framing or topic(m), encode(m), reliable=retain)
        else:
            out = Outgoing(topic(m), encode(m), retain=retain, reliable=retain)
            skeletons = [k for k in skeletons if k.topic != out.topic] + [out]
            announced = time.monotonic()
        await send(out)
    return sent


async def _to_zmq(endpoint: str, items: Items, rate: float, speed: float | None, wait_s: float) -> int:
    ctx = zmq.asyncio.Context()
    sock = ctx.socket(zmq.XPUB)
    sock.setsockopt(zmq.SNDHWM, SEND_HWM)
    sock.setsockopt(zmq.LINGER, round(1000 * FINISH_S))
    linger_s = STOPPED_S
    try:
        sock.connect(endpoint)
        # the daemon's subscription arrives once the connection is up (see the module docstring)
        while True:
            event = await asyncio.wait_for(sock.recv(), wait_s)
            if event[:1] == b"\x01":
                break

        async def send(out: Outgoing) -> None:
            await sock.send_multipart([out.topic.encode(), out.payload])

        sync: zmq.Socket[bytes] = zmq.Socket.shadow(sock.underlying)

        def asked() -> bool:
            """A subscription reached the socket: a daemon (re)connected."""
            found = False
            while True:
                try:
                    event = sync.recv(zmq.NOBLOCK)
                except zmq.Again:
                    return found
                found = found or event[:1] == b"\x01"

        sent = await _send_all(send, items, rate, speed, asked)
        linger_s = FINISH_S  # all sent: give it time to leave (a signal or an error: not)
        return sent
    finally:
        sock.close(linger=round(1000 * linger_s))
        ctx.term()


async def _to_mqtt(
    url: str, items: Items, stream: str, rate: float, speed: float | None, wait_s: float, retain: bool
) -> int:
    from daemon.config import MqttConfig
    from protocols.mqtt import MqttTransport

    client = MqttTransport(
        MqttConfig(url=url, queue=1000),
        client_id=f"mocapd-replay-{stream}-{os.getpid()}",
        subscribe=[("mocapd/+/status", 1)],
        presence=None,
    )
    client.drain_within(60.0)
    async with client:
        await client.wait_connected(wait_s)

        async def send(out: Outgoing) -> None:
            while client.pending > 10_000:  # let the sender catch up rather than drop
                await asyncio.sleep(0.001)
            await client.publish(out)

        online = asyncio.Event()

        async def watch() -> None:
            """A daemon's "online" status (retained ones included) asks for the skeleton."""
            async for incoming in client:
                with contextlib.suppress(WireError):
                    status = decode(incoming.payload)
                    if isinstance(status, StatusMessage) and status.state == "online":
                        online.set()

        def asked() -> bool:
            found = online.is_set()
            online.clear()
            return found

        watcher = asyncio.create_task(watch(), name="replay status watch")
        try:
            sent = await _send_all(send, items, rate, speed, asked, retain)
        except asyncio.CancelledError:
            client.drain_within(STOPPED_S)
            raise
        finally:
            watcher.cancel()
        with contextlib.suppress(TimeoutError):
            async with asyncio.timeout(60):
                while client.pending:
                    await asyncio.sleep(0.005)
        return sent


def replay(
    url: str,
    motion: Recording,
    asf_text: str,
    *,
    stream: str,
    rate: float,
    speed: float | None,
    loop: bool,
    retain: bool = True,
    others: Sequence[tuple[Recording, str, str]] = (),
    source: str = "replay",
) -> int:
    """:func:`replay_to` run to its end on a fresh event loop (for callers outside asyncio).

    SIGTERM and SIGINT (unless ignored) stop it through the loop (``loop.add_signal_handler``):
    the replay is cancelled, gives what it sent :data:`STOPPED_S` to leave, and the signal is then
    raised again under the handler the caller had, which decides what it means. A signal's
    handler raising inside the event loop's callbacks would be swallowed by asyncio (it catches what
    a callback raises, bar KeyboardInterrupt and SystemExit), and the replay would go on."""
    received: list[int] = []

    async def main() -> int:
        task = asyncio.current_task()
        assert task is not None
        running = asyncio.get_running_loop()
        previous: dict[signal.Signals, Any] = {}

        def stop(signum: int) -> None:
            if not received:
                received.append(signum)
                task.cancel()

        if threading.current_thread() is threading.main_thread():
            for signum in STOP_SIGNALS:
                handler = signal.getsignal(signum)
                if handler != signal.SIG_IGN:
                    previous[signum] = handler
                    running.add_signal_handler(signum, stop, signum)
        try:
            return await replay_to(
                url,
                motion,
                asf_text,
                stream=stream,
                rate=rate,
                speed=speed,
                loop=loop,
                retain=retain,
                others=others,
                source=source,
            )
        except asyncio.CancelledError:
            if not received:
                raise
            return 0
        finally:
            for number, handler in previous.items():
                running.remove_signal_handler(number)
                signal.signal(number, handler)

    sent = asyncio.run(main())
    if received:
        signal.raise_signal(received[0])
    return sent
