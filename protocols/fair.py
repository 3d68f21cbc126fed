"""A bounded queue of incoming messages that one flooding stream cannot take over (issue 21).

Messages are queued per *key*, the stream of a ``mocap/<stream>/...`` topic (any other topic is its
own key), and taken key by key in turn, each key's in the order they came (a stream's skeleton stays
before its poses). At most ``size`` are held in all; when full, the oldest message of the key that
holds the most goes: garbage flooding one stream's topics crowds out that stream, not the others.

Pure: no sockets.
"""

from __future__ import annotations

from collections import deque

from protocols.transport import Incoming


def key_of(topic: str) -> str:
    """The stream of a ``mocap/<stream>/...`` topic, else the topic."""
    if topic.startswith("mocap/"):
        return topic.split("/", 2)[1]
    return topic


class FairQueue:
    """See the module docstring. :meth:`put` returns whether a message was dropped to make room."""

    def __init__(self, size: int) -> None:
        if size < 1:
            raise ValueError(f"a queue holds at least one message, got {size}")
        self.size = size
        self._queues: dict[str, deque[Incoming]] = {}
        self._turns: deque[str] = deque()  # the keys with messages, in the order they are taken
        self._held = 0

    def __len__(self) -> int:
        return self._held

    def put(self, message: Incoming) -> bool:
        dropped = False
        if self._held >= self.size:
            largest = max(self._queues, key=lambda k: len(self._queues[k]))
            self._queues[largest].popleft()
            self._held -= 1
            dropped = True
            if not self._queues[largest]:
                del self._queues[largest]
                self._turns.remove(largest)
        key = key_of(message.topic)
        queue = self._queues.get(key)
        if queue is None:
            queue = self._queues[key] = deque()
            self._turns.append(key)
        queue.append(message)
        self._held += 1
        return dropped

    def take(self) -> Incoming | None:
        """The next message in turn (None: empty)."""
        if not self._turns:
            return None
        key = self._turns.popleft()
        queue = self._queues[key]
        message = queue.popleft()
        self._held -= 1
        if queue:
            self._turns.append(key)
        else:
            del self._queues[key]
        return message
