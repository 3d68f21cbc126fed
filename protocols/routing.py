"""Which worker of ``mocapd run --workers N`` takes a stream: a stable hash of the stream id, so
one stream always lands on the same worker (in every run, on every machine: BLAKE2b, not Python's
per-process salted ``hash``; not CRC-32 either, whose linearity can send a family of ids that differ
in a few bits all to one worker), and the router finds the stream in the topic without decoding the
payload. Pure: no sockets."""

from __future__ import annotations

import hashlib

TOPIC_PREFIX = "mocap/"


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
