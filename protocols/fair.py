"""A bounded queue of incoming messages that one flooding stream cannot take over (issue 21).
Messages are queued per *key*, the stream of a ``mocap/<stream>/...`` topic (any other topic is its
own key), and taken key by key in turn, each key's in the order they came (a stream's skeleton stays
before its poses). At most ``size`` are held in all; when full, the oldest message of the key that
holds the most goes (of several, the one that came to hold that many first): garbage flooding one
stream's topics crowds out that stream, not the others. Every operation is O(1), so a flood of
distinct stream ids costs no more per message than a flood of one. Pure: no sockets.
"""

from __future__ import annotations

from collections import OrderedDict, deque

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
        self._turns: OrderedDict[str, None] = OrderedDict()  # the keys with messages, in turn order
        self._holding: dict[int, OrderedDict[str, None]] = {}  # n: the keys holding n, as they came to
        self._most = 0
        self._held = 0

    def __len__(self) -> int:
        return self._held

    def put(self, message: Incoming) -> bool:
        dropped = False
        if self._held >= self.size:
            largest = next(iter(self._holding[self._most]))
            self._queues[largest].popleft()
            self._held -= 1
            dropped = True
            if not self._shrunk(largest):
                del self._turns[largest]
        key = key_of(message.topic)
        queue = self._queues.get(key)
        if queue is None:
            queue = self._queues[key] = deque()
            self._turns[key] = None
        queue.append(message)
        self._held += 1
        self._move(key, len(queue) - 1, len(queue))
        self._most = max(self._most, len(queue))
        return dropped

    def take(self) -> Incoming | None:
        """The next message in turn (None: empty)."""
        if not self._turns:
            return None
        key, _ = self._turns.popitem(last=False)
        message = self._queues[key].popleft()
        self._held -= 1
        if self._shrunk(key):
            self._turns[key] = None
        return message

    def _shrunk(self, key: str) -> bool:
        """Account for ``key`` having lost a message; False (and the key forgotten) if it holds none."""
        n = len(self._queues[key])
        self._move(key, n + 1, n)
        if n + 1 == self._most and (n + 1) not in self._holding:
            self._most = n  # the key was the last holding the most, and now holds one fewer
        if n == 0:
            del self._queues[key]
        return n > 0

    def _move(self, key: str, before: int, after: int) -> None:
        if before:
            keys = self._holding[before]
            del keys[key]
            if not keys:
                del self._holding[before]
        if after:
            self._holding.setdefault(after, OrderedDict())[key] = None
