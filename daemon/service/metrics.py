"""The service's Prometheus metrics and the tiny HTTP server of ``/healthz`` and ``/metrics``.

The live path counts in plain Python ints and fixed-bucket histograms (a bisect and an add per
observation: prometheus-client's own counters take a lock per increment, too much at 12,000 poses
a second); prometheus-client turns them into its exposition format when ``/metrics`` is scraped
(:class:`Metrics` is a registry collector).

Series (prefix ``mocapd_``): ``frames_in``, ``messages_in{type}``, ``detections_out``,
``boundaries_out``, ``progress_out``, ``rejects{reason}``, ``drops{reason}``,
``stream_events{event}`` (gaps, poses missing in them, evictions, skeleton changes), ``streams``,
``queued_poses``, ``outbox``, ``transport_up{transport}``, ``stage_seconds{stage}`` (decode,
recognise, publish; buckets from 25 µs to 50 ms with one at the 2 ms budget) and
``end_to_end_seconds`` (the arrival of the pose that completed a detection to the detection's
publish, on this process's monotonic clock: never the pose's source timestamp, since a source's
clock may be anywhere).
``frames_in`` and ``detections_out`` have a ``stream`` label only with ``metrics.stream_labels``,
which config allows only for a bounded stream table. Every incoming message is counted once: in
``messages_in`` when taken in (a pose queued, a skeleton taken or repeated, an empty skeleton: a
retained one cleared), in ``rejects`` when refused, in ``drops{reason="mqtt_incoming_full"}`` when
dropped before it was looked at.
"""

from __future__ import annotations

import asyncio
import contextlib
from bisect import bisect_left
from collections import Counter
from collections.abc import Awaitable, Callable, Container, Iterable, Mapping
from dataclasses import dataclass, field

from prometheus_client import CollectorRegistry, generate_latest
from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily, HistogramMetricFamily, Metric
from prometheus_client.exposition import CONTENT_TYPE_LATEST
from prometheus_client.registry import Collector

STAGE_BUCKETS = (25e-6, 50e-6, 100e-6, 250e-6, 500e-6, 1e-3, 2e-3, 5e-3, 10e-3, 20e-3, 50e-3)
END_TO_END_BUCKETS = (1e-3, 2e-3, 5e-3, 10e-3, 20e-3, 50e-3, 0.1, 0.2, 0.5, 1.0, 2.0, 5.0)


@dataclass
class Histogram:
    """Observations in fixed buckets (upper bounds, inclusive), their count per bucket and sum."""

    bounds: tuple[float, ...]
    counts: list[int] = field(default_factory=list)
    total: float = 0.0

    def __post_init__(self) -> None:
        self.counts = [0] * (len(self.bounds) + 1)

    def observe(self, value: float) -> None:
        self.counts[bisect_left(self.bounds, value)] += 1
        self.total += value

    def buckets(self) -> list[tuple[str, float]]:
        """Cumulative (le, count) pairs, ``+Inf`` last."""
        out, running = [], 0
        for bound, n in zip((*self.bounds, float("inf")), self.counts, strict=True):
            running += n
            out.append(("+Inf" if bound == float("inf") else repr(bound), float(running)))
        return out


class Metrics(Collector):
    """The series of one service; ``tallies()`` gives the rejects, drops and stream events (by
    reason) and ``gauges()`` the current gauge values when scraped."""

    def __init__(
        self,
        stream_labels: bool,
        tallies: Callable[[], tuple[Mapping[str, int], Mapping[str, int], Mapping[str, int]]],
        gauges: Callable[[], tuple[int, int, int, Mapping[str, bool]]],
    ) -> None:
        self.stream_labels = stream_labels
        self.frames: Counter[str] = Counter()
        """Poses received by stream ("" for all when streams are not labelled)."""
        self.messages: Counter[str] = Counter()
        self.detections: Counter[str] = Counter()
        self.boundaries = 0
        """Behaviour boundaries published."""
        self.progress = 0
        """Progress events published."""
        self.stage = {s: Histogram(STAGE_BUCKETS) for s in ("decode", "recognise", "publish")}
        self.end_to_end = Histogram(END_TO_END_BUCKETS)
        self._tallies = tallies
        self._gauges = gauges
        self.cluster: Callable[[], list[tuple[str, str, str, float]]] | None = None
        """Cluster mode's series as (name, help, "gauge" or "counter", value), when scraped."""
        self.registry = CollectorRegistry()
        self.registry.register(self)

    def frame_in(self, stream: str) -> None:
        self.frames[stream if self.stream_labels else ""] += 1

    def frames_in(self, count: int) -> None:
        """``count`` poses taken in, of streams not labelled (``metrics.stream_labels`` off)."""
        self.frames[""] += count

    def detection_out(self, stream: str) -> None:
        self.detections[stream if self.stream_labels else ""] += 1

    def keep(self, live: Container[str]) -> None:
        """Drop the per-stream series of streams no longer ``live``, so the label set is bounded by
        what is live (a stream that comes back starts its series from 0: a counter reset)."""
        if self.stream_labels:
            for per_stream in (self.frames, self.detections):
                for stream in [s for s in per_stream if s not in live]:
                    del per_stream[stream]

    def exposition(self) -> bytes:
        out: bytes = generate_latest(self.registry)
        return out

    def collect(self) -> Iterable[Metric]:
        labels = ["stream"] if self.stream_labels else []
        for name, doc, per_stream in (
            ("mocapd_frames_in", "Poses received and queued", self.frames),
            ("mocapd_detections_out", "Detections published", self.detections),
        ):
            family = CounterMetricFamily(name, doc, labels=labels)
            for stream, n in sorted(per_stream.items()) or [("", 0)]:
                family.add_metric([stream] if labels else [], n)
            yield family
        yield CounterMetricFamily(
            "mocapd_boundaries_out", "Behaviour boundaries published", value=self.boundaries
        )
        yield CounterMetricFamily("mocapd_progress_out", "Progress events published", value=self.progress)
        messages = CounterMetricFamily(
            "mocapd_messages_in", "Messages taken in (pose, skeleton, clear), by type", labels=["type"]
        )
        for kind, n in sorted(self.messages.items()):
            messages.add_metric([kind], n)
        yield messages
        rejects, drops, events = self._tallies()
        for name, doc, label, counts in (
            ("mocapd_rejects", "Messages refused, by reason", "reason", rejects),
            ("mocapd_drops", "Poses or messages dropped, by reason", "reason", drops),
            (
                "mocapd_stream_events",
                "Gaps, poses missing in them, evictions, skeleton changes",
                "event",
                events,
            ),
        ):
            family = CounterMetricFamily(name, doc, labels=[label])
            for key, n in sorted(counts.items()):
                family.add_metric([key], n)
            yield family
        streams, queued, outbox, up = self._gauges()
        yield GaugeMetricFamily("mocapd_streams", "Live streams", value=streams)
        yield GaugeMetricFamily("mocapd_queued_poses", "Poses waiting for recognition", value=queued)
        yield GaugeMetricFamily(
            "mocapd_outbox", "Detections awaiting the broker's acknowledgement", value=outbox
        )
        transports = GaugeMetricFamily(
            "mocapd_transport_up", "1 while a transport serves", labels=["transport"]
        )
        for name, ok in sorted(up.items()):
            transports.add_metric([name], 1.0 if ok else 0.0)
        yield transports
        stage = HistogramMetricFamily("mocapd_stage_seconds", "Time per stage call", labels=["stage"])
        for name, h in self.stage.items():
            stage.add_metric([name], h.buckets(), h.total)
        yield stage
        e2e = HistogramMetricFamily(
            "mocapd_end_to_end_seconds",
            "Arrival of the pose that completed a detection to the detection's publish",
        )
        e2e.add_metric([], self.end_to_end.buckets(), self.end_to_end.total)
        yield e2e
        if self.cluster is not None:
            for name, doc, kind, value in self.cluster():
                if kind == "gauge":
                    yield GaugeMetricFamily(name, doc, value=value)
                else:
                    yield CounterMetricFamily(name, doc, value=value)


async def open_http(
    host: str, port: int, health: Callable[[], str | None], metrics: Metrics | Callable[[], Awaitable[bytes]]
) -> asyncio.Server:
    """A server listening on ``host:port`` (0: a free port) for ``GET /healthz`` (200 ``ok`` while
    ``health()`` is None, else 503 with its reason) and ``GET /metrics`` (``metrics``' exposition,
    or what the coroutine function ``metrics`` gives); serve it with :func:`serve_http`. OSError if
    it cannot listen."""

    async def handle(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        try:
            line = await asyncio.wait_for(reader.readline(), 5)
            while (await asyncio.wait_for(reader.readline(), 5)) not in (b"\r\n", b"\n", b""):
                pass
            words = line.decode("latin-1").split()
            path = words[1] if len(words) >= 2 and words[0] in ("GET", "HEAD") else ""
            kind = "text/plain; charset=utf-8"
            if path == "/healthz":
                problem = health()
                status, body = (200, b"ok\n") if problem is None else (503, f"{problem}\n".encode())
            elif path == "/metrics":
                body = metrics.exposition() if isinstance(metrics, Metrics) else await metrics()
                status, kind = 200, CONTENT_TYPE_LATEST
            else:
                status, body = 404, b"not found\n"
            reason = {200: "OK", 404: "Not Found", 503: "Service Unavailable"}[status]
            head = f"HTTP/1.1 {status} {reason}\r\nContent-Type: {kind}\r\nContent-Length: {len(body)}\r\n"
            writer.write(
                (head + "Connection: close\r\n\r\n").encode() + (b"" if words[:1] == ["HEAD"] else body)
            )
            await writer.drain()
        except (TimeoutError, ConnectionError, UnicodeDecodeError):
            pass
        finally:
            writer.close()
            with contextlib.suppress(ConnectionError):
                await writer.wait_closed()

    return await asyncio.start_server(handle, host, port)


async def serve_http(server: asyncio.Server) -> None:
    """Serve ``server`` (:func:`open_http`) until cancelled, then close it."""
    async with server:
        await server.serve_forever()
