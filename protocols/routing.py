"""Which worker of ``mocapd run --workers N`` takes a stream: a stable hash of the stream id, so
one stream always lands on the same worker (in every run, on every machine: BLAKE2b, not Python's
per-process salted ``hash``; not CRC-32 either, whose linearity can send a family of ids that differ
in a few bits all to one worker), and the router finds the stream in the topic without decoding the
payload. Pure: no sockets."""

from __future__ import annotations

import hashlib
from collections.abc import Callable, Sequence

from protocols.messages import is_id

TOPIC_PREFIX = "mocap/"
TOPICS_PER_STREAM = 4
"""A stream's topics a cache of routes makes room for (its poses, skeleton, end and frames)."""


def routes_cached(streams: int) -> int:
    """The most topics whose worker the front remembers when the workers hold ``streams`` streams
    in all: room for their topics and no more, so that a flood of new stream ids, which clears the
    cache again and again, holds no more memory than the streams the daemon may take (a cache of
    100,000 topics grew the front by 2.5 MiB for every 10,000 new ids until it was full)."""
    return TOPICS_PER_STREAM * max(1, streams)


def stream_of(topic: str) -> str:
    """The stream id of a ``mocap/<stream>/<word>`` topic; the whole topic for any other (so that
    whatever it is, one worker takes it and refuses it as the single daemon would)."""
    if topic.startswith(TOPIC_PREFIX):
        end = topic.find("/", len(TOPIC_PREFIX))
        if end > 0:
            return topic[len(TOPIC_PREFIX) : end]
    return topic


def worker_of(stream: str, workers: int) -> int:
    """The worker, in ``0 .. workers - 1``, that takes ``stream``; ValueError for ``workers`` < 1."""
    if workers < 1:
        raise ValueError(f"workers must be at least 1, got {workers}")
    digest = hashlib.blake2b(stream.encode("utf-8", "surrogateescape"), digest_size=8).digest()
    return int.from_bytes(digest, "little") % workers


FRAME_SUFFIX = b"/frame"
"""A frame message's topic ends so (``mocap/<source>/frame``): its subjects are any workers'."""


def choose(workers: int) -> Callable[[bytes], int]:
    """The worker of a topic (UTF-8 bytes, undecodable bytes replaced) of ``workers``; ``workers``
    itself for a frame message's topic (``mocap/<source>/frame``, the source an id), which every
    worker takes (each its own subjects: :func:`mine`; a frame message refused whole is counted by
    the source's worker alone)."""

    def worker(topic: bytes) -> int:
        text = topic.decode("utf-8", "replace")
        if topic.endswith(FRAME_SUFFIX) and text.count("/") == 2 and is_id(stream_of(text)):
            return workers
        return worker_of(stream_of(text), workers)

    return worker


def mine(index: int, workers: int, cached: int) -> Callable[[str], bool]:
    """Whether a stream is worker ``index``'s of ``workers`` (:func:`worker_of`, remembered for at
    most ``cached`` streams, then all forgotten at once)."""
    known: dict[str, bool] = {}

    def owned(stream: str) -> bool:
        found = known.get(stream)
        if found is None:
            if len(known) >= cached:
                known.clear()
            found = known[stream] = worker_of(stream, workers) == index
        return found

    return owned


class Routes:
    """:func:`choose` remembered per topic, at most ``cached`` topics (then all forgotten at once:
    a flood of new ids must not grow it): a lookup per message, not a hash."""

    def __init__(self, workers: int, cached: int) -> None:
        self.workers = workers
        self.cached = max(1, cached)
        self._choose = choose(workers)
        self._routes: dict[bytes, int] = {}

    def __call__(self, topic: bytes) -> int:
        k = self._routes.get(topic)
        if k is None:
            if len(self._routes) >= self.cached:
                self._routes.clear()
            k = self._routes[topic] = self._choose(topic)
        return k


def split(
    messages: Sequence[Sequence[bytes]], worker: Callable[[bytes], int], workers: int
) -> list[list[bytes]]:
    """Per worker the frames ``[topic, payload, topic, payload, ...]`` of ``messages`` (each a
    message's frames, in order) that ``worker`` sends it (``workers``: to every worker); a message
    that is not two frames becomes ``b"", b""`` (refused by the worker as undecodable) for the
    worker of its first frame."""
    out: list[list[bytes]] = [[] for _ in range(workers)]
    for frames in messages:
        k = worker(frames[0])
        pair = frames if len(frames) == 2 else (b"", b"")
        for to in out if k == workers else (out[k],):
            to += pair
    return out
