"""The service's Prometheus metrics (prometheus-client, one registry per service) and the tiny HTTP
server of ``/healthz`` and ``/metrics``.

Series: frames in, messages by type, detections out, live streams, queued poses, the outbox,
transports up, per-stage latency (decode, recognise, publish; buckets from 25 µs to 50 ms
with one at the 2 ms budget) and end to end (a pose's source timestamp to the publish of the
detection it completed). No series has a stream label unless ``metrics.stream_labels`` is set, which
config allows only for a bounded stream table. Rejects and drops by reason and the streams' gaps
are read from the service's tallies when scraped (:mod:`daemon.service.app`).
"""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import Callable

from prometheus_client import CollectorRegistry, Counter, Gauge, Histogram, generate_latest
from prometheus_client.exposition import CONTENT_TYPE_LATEST

STAGE_BUCKETS = (25e-6, 50e-6, 100e-6, 250e-6, 500e-6, 1e-3, 2e-3, 5e-3, 10e-3, 20e-3, 50e-3)
END_TO_END_BUCKETS = (1e-3, 2e-3, 5e-3, 10e-3, 20e-3, 50e-3, 0.1, 0.2, 0.5, 1.0, 2.0, 5.0)


class Metrics:
    """The series of one service (names prefixed ``mocapd_``)."""

    def __init__(self, stream_labels: bool = False) -> None:
        self.registry = CollectorRegistry()
        r = self.registry
        self.stream_labels = stream_labels
        extra = ("stream",) if stream_labels else ()
        self.frames = Counter("mocapd_frames_in", "Poses received and queued", extra, registry=r)
        self.messages = Counter("mocapd_messages_in", "Messages received, by type", ("type",), registry=r)
        self.detections = Counter("mocapd_detections_out", "Detections published", extra, registry=r)
        self.streams = Gauge("mocapd_streams", "Live streams", registry=r)
        self.queued = Gauge("mocapd_queued_poses", "Poses waiting for recognition", registry=r)
        self.pending = Gauge("mocapd_outbox", "Detections awaiting the broker's acknowledgement", registry=r)
        self.connected = Gauge(
            "mocapd_transport_up", "1 while a transport serves", ("transport",), registry=r
        )
        self.stage = Histogram(
            "mocapd_stage_seconds", "Time per stage call", ("stage",), buckets=STAGE_BUCKETS, registry=r
        )
        self.end_to_end = Histogram(
            "mocapd_end_to_end_seconds",
            "Source timestamp of the pose that completed a detection to the detection's publish",
            buckets=END_TO_END_BUCKETS,
            registry=r,
        )

    def exposition(self) -> bytes:
        out: bytes = generate_latest(self.registry)
        return out


async def serve_http(
    host: str, port: int, health: Callable[[], str | None], metrics: Metrics, started: asyncio.Event
) -> None:
    """``GET /healthz`` (200 ``ok`` while ``health()`` is None, else 503 with its reason) and
    ``GET /metrics`` on ``host:port`` until cancelled; ``started`` is set once listening."""

    async def handle(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        try:
            line = await asyncio.wait_for(reader.readline(), 5)
            while (await asyncio.wait_for(reader.readline(), 5)) not in (b"\r\n", b"\n", b""):
                pass
            words = line.decode("latin-1").split()
            path = words[1] if len(words) >= 2 and words[0] in ("GET", "HEAD") else ""
            if path == "/healthz":
                problem = health()
                status, body, kind = (
                    (200, b"ok\n", "text/plain")
                    if problem is None
                    else (
                        503,
                        f"{problem}\n".encode(),
                        "text/plain",
                    )
                )
            elif path == "/metrics":
                status, body, kind = 200, metrics.exposition(), CONTENT_TYPE_LATEST
            else:
                status, body, kind = 404, b"not found\n", "text/plain"
            reason = {200: "OK", 404: "Not Found", 503: "Service Unavailable"}[status]
            head = f"HTTP/1.1 {status} {reason}\r\nContent-Type: {kind}\r\nContent-Length: {len(body)}\r\n"
            writer.write(
                (head + "Connection: close\r\n\r\n").encode() + (body if words[:1] != ["HEAD"] else b"")
            )
            await writer.drain()
        except (TimeoutError, ConnectionError, UnicodeDecodeError):
            pass
        finally:
            writer.close()
            with contextlib.suppress(ConnectionError):
                await writer.wait_closed()

    server = await asyncio.start_server(handle, host, port)
    started.set()
    async with server:
        await server.serve_forever()
