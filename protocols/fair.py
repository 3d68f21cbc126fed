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
        # a key holding one message holds it bare: a flood of distinct stream ids (one message
        # each) would otherwise cost a deque (~600 B) each, a peak the allocator keeps
        self._queues: dict[str, Incoming | deque[Incoming]] = {}
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
            self._popleft(largest)
            dropped = True
            if largest not in self._queues:
                del self._turns[largest]
        key = key_of(message.topic)
        held = self._queues.get(key)
        if held is None:
            self._queues[key] = message
            self._turns[key] = None
            n = 1
        elif isinstance(held, deque):
            held.append(message)
            n = len(held)
        else:
            self._queues[key] = deque((held, message))
            n = 2
        self._held += 1
        self._move(key, n - 1, n)
        self._most = max(self._most, n)
        return dropped

    def take(self) -> Incoming | None:
        """The next message in turn (None: empty)."""
        if not self._turns:
            return None
        key, _ = self._turns.popitem(last=False)
        message = self._popleft(key)
        if key in self._queues:
            self._turns[key] = None
        return message

    def _popleft(self, key: str) -> Incoming:
        """``key``'s oldest message, taken and accounted for (the key forgotten if it holds no more)."""
        held = self._queues[key]
        if isinstance(held, deque):
            message, n = held.popleft(), len(held)
        else:
            message, n = held, 0
        if n == 0:
            del self._queues[key]
        self._held -= 1
        self._move(key, n + 1, n)
        if n + 1 == self._most and (n + 1) not in self._holding:
            self._most = n  # the key was the last holding the most, and now holds one fewer
        return message

    def _move(self, key: str, before: int, after: int) -> None:
        if before:
            keys = self._holding[before]
            del keys[key]
            if not keys:
                del self._holding[before]
        if after:
            self._holding.setdefault(after, OrderedDict())[key] = None
