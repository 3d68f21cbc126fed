"""One partition's two deliveries merged into one (``docs/cluster.md``, "NATS: three servers").

A cluster worker on a NATS cluster reads each owned partition twice: through its JetStream buffer's
consumer (the *buffered* copy: stored, numbered, replayed to a new owner, but lost while the buffer
elects a new leader after a server died) and through a plain subscription of the partition's
subject (the *live* copy: routed by whichever servers are up, whatever JetStream's state, but never
replayed and lost while the worker's own connection moves). :class:`Merge` passes each message on
once:

* a live copy is held until its buffered copy comes, which is then passed and the live one dropped;
  once the buffer is live (not replaying), a live copy held for ``hold_s``, and for ``hold_s``
  since the buffer went live, is passed itself (the buffer lost it, or is slow);
* a buffered copy that matches a held live copy first passes every live copy held before that one:
  they came first on the live path, and the buffer lost them (or has them later in another order
  of streams), so they go first;
* a buffered copy whose live copy was passed already is dropped as a *marker*: its buffer sequence
  alone, the position up to which the partition has been taken in;
* a buffered copy with no live copy yet is passed, and its live copy dropped when it comes.

Copies are told apart by a key (a digest of subject and payload) counted as a multiset. A message
that a publisher repeats identically (a skeleton announced every second) has no key: matched, the
replayed copy of one could be taken for the live copy of a later one and pass the messages held
between them too early. Both its copies are passed, each in its path's order (the live one held
like any other), and the stream table takes the second for the repeat it is. What was passed on
one path is remembered for ``remember_s`` so that its copy on the other is dropped.

The live path itself is two: a plain subscription on the server the worker talks to and another on
a second server (:class:`Twice` passes the first copy of each message on to the merge), so that the
server the worker talks to, killed, costs no message while the worker's connections move (its
buffers' leaders may be electing meanwhile: the buffer has lost them too).

Exact (each message once, every stream's messages in the order they were published) when only the
buffer loses messages and the live copy of a message comes before its buffered copy (a live copy
is routed while the buffered one is still being replicated), or when only the live path loses and
the buffer brings each message within ``hold_s`` of the live path's next one or of the buffer
going live (:meth:`Merge.went_live`). When both lose
messages of one stream within ``hold_s`` of each other, two of its messages can be passed out of
order (the stream table then refuses the later one as ``out_of_order``); a copy that comes more
than ``remember_s`` after the other is passed again (the stream table refuses it as a
``duplicate``). ``tests/test_merge.py`` checks these against a reference on random deliveries.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Generic, TypeVar

T = TypeVar("T")

Passed = tuple[int, "T | None"]
"""What :meth:`Merge.push` and :meth:`Merge.release` give: a message's buffer sequence (-1: a live
copy passed without its buffered one) and the message (None: a marker, the buffer sequence only)."""


@dataclass(slots=True)
class _Held(Generic[T]):
    key: int | None
    item: T
    at: float
    n: int  # the live copy's ordinal among the partition's live copies


@dataclass(slots=True)
class _Entry:
    key: int
    at: float
    n: int
    alive: bool = True


class _Remembered:
    """Keys with when they were added and an ordinal, counted, forgotten after ``seconds``."""

    def __init__(self, seconds: float) -> None:
        self.seconds = seconds
        self._order: deque[_Entry] = deque()
        self._of: dict[int, deque[_Entry]] = {}

    def add(self, key: int, now: float, n: int = 0) -> None:
        entry = _Entry(key, now, n)
        self._order.append(entry)
        self._of.setdefault(key, deque()).append(entry)

    def take(self, key: int) -> int | None:
        """Remove the oldest ``key``: its ordinal, None if there is none."""
        same = self._of.get(key)
        if not same:
            return None
        entry = same.popleft()
        if not same:
            del self._of[key]
        entry.alive = False
        return entry.n

    def forget(self, now: float) -> None:
        order = self._order
        while order and order[0].at < now - self.seconds:
            entry = order.popleft()
            if entry.alive:  # the oldest of its key still there
                self.take(entry.key)


class Merge(Generic[T]):
    """The merge of one partition's buffered and live copies (module docstring). ``hold_s``: the
    longest a live copy waits for its buffered copy once the buffer is live; ``remember_s``: how
    long a copy passed on one path is remembered; ``most``: live copies held at most (the oldest
    is dropped past that, counted in :attr:`dropped`: the buffer has it, if it works)."""

    def __init__(self, hold_s: float, remember_s: float, most: int) -> None:
        self.hold_s = hold_s
        self.most = most
        self.replaying = True
        """Whether the buffer is still replaying what it held when its consumer started (its live
        copies are held however long it takes: passed before the buffered messages before them,
        they would come out of order). The owner sets it, and clears it by :meth:`went_live`."""
        self._live_at = -math.inf
        self.dropped = 0
        self._fifo: deque[_Held[T]] = deque()
        self._held: dict[int, deque[_Held[T]]] = {}
        self._live_passed = _Remembered(remember_s)  # live copies passed, their buffered ones due
        self._buffered_passed = _Remembered(remember_s)  # buffered copies passed, their live ones due
        self._n = 0
        self._released = (0, -math.inf)  # the newest live copy passed alone: its ordinal, when
        self._confirmed = 0  # the newest live copy whose buffered copy came: its ordinal
        self._stall_since = math.inf  # the first live copy passed alone since the buffer last matched one

    def push(self, key: int | None, item: T, now: float, seq: int | None = None) -> list[Passed[T]]:
        """Take a message: a buffered copy with its buffer sequence ``seq``, or a live one
        (``seq`` None); ``key`` None: a message repeated identically, passed from both paths. What
        is passed on now, in order."""
        if seq is None:
            if key is not None and self._buffered_passed.take(key) is not None:
                return []
            self._n += 1
            held = _Held(key, item, now, self._n)
            self._fifo.append(held)
            if key is not None:
                self._held.setdefault(key, deque()).append(held)
            if len(self._fifo) > self.most:
                self._unhold()
                self.dropped += 1
            return []
        if key is None:
            return [(seq, item)]
        same = self._held.get(key)
        if same:
            match = same[0]
            out: list[Passed[T]] = []
            while self._fifo[0] is not match:
                out.append(self._release(now))
            self._unhold()
            self._confirmed = max(self._confirmed, match.n)
            self._stall_since = math.inf
            out.append((seq, item))
            return out
        n = self._live_passed.take(key)
        if n is not None:
            self._confirmed = max(self._confirmed, n)
            self._stall_since = math.inf
            return [(seq, None)]
        self._buffered_passed.add(key, now)
        return [(seq, item)]

    def went_live(self, now: float) -> None:
        """The buffer has replayed what it held when its consumer started (or no replay comes):
        from ``now`` a held live copy is passed alone once it has waited ``hold_s``, counted from
        ``now`` for those held during the replay. From when each came instead, a long replay (a
        loaded worker reading a long buffer) ended with every copy held during it passed at once,
        before the buffered copies of messages published just before them, which the replay's
        snapshot of the buffer did not include and the live path never brought (published before
        the subscription): a stream's poses came out of order, and one was refused. Live
        already: nothing changes (a consumer that cannot be made, tried again and again)."""
        if self.replaying:
            self.replaying = False
            self._live_at = now

    def release(self, now: float) -> list[Passed[T]]:
        """The live copies held for ``hold_s`` since they came and since the buffer went live (none
        while :attr:`replaying`); forgets what is older than ``remember_s``."""
        self._live_passed.forget(now)
        self._buffered_passed.forget(now)
        out: list[Passed[T]] = []
        if not self.replaying and self._live_at <= now - self.hold_s:
            while self._fifo and self._fifo[0].at <= now - self.hold_s:
                out.append(self._release(now))
        return out

    def stalled(self, now: float, seconds: float) -> bool:
        """Whether live copies have been passed alone for ``seconds`` (since :meth:`rewatch`)
        without the buffer bringing the copy of any live one: it has lost them all, or delivers
        nothing (a consumer lost with a server)."""
        return now - self._stall_since > seconds

    def rewatch(self) -> None:
        """Start :meth:`stalled` afresh (a consumer made again)."""
        self._stall_since = math.inf

    def awaiting(self, now: float) -> bool:
        """Whether a live copy was passed alone after the newest one whose buffered copy came,
        within ``remember_s``: a position taken now would precede a message already taken in."""
        n, at = self._released
        return n > self._confirmed and at >= now - self._live_passed.seconds

    @property
    def held(self) -> int:
        """Live copies held now."""
        return len(self._fifo)

    def holding(self) -> Iterator[T]:
        """The live copies held now, oldest first."""
        return (h.item for h in self._fifo)

    def _unhold(self) -> _Held[T]:
        """Remove the oldest held live copy (the first of its key's too)."""
        first = self._fifo.popleft()
        if first.key is not None:
            same = self._held[first.key]
            same.popleft()
            if not same:
                del self._held[first.key]
        return first

    def _release(self, now: float) -> Passed[T]:
        first = self._unhold()
        if first.key is not None:
            self._live_passed.add(first.key, now, first.n)
            self._stall_since = min(self._stall_since, now)
            self._released = (first.n, now)
        return (-1, first.item)


class Twice:
    """The live copies of one partition's messages from two plain subscriptions on two servers
    (``path`` 0 and 1) made one: :meth:`first` says whether a copy is the first of its message
    (pass it on) or the other path's copy of one passed already (drop it). Copies are matched by
    key as a multiset, as :class:`Merge` matches, and a copy is remembered for ``remember_s`` for
    its twin (a path whose server is away delivers none). Each message once whenever the paths
    between them deliver it within ``remember_s``; in the order published when neither path lost
    messages (a message's first copy comes after the first copy of every message before it)."""

    def __init__(self, remember_s: float) -> None:
        self._passed = (_Remembered(remember_s), _Remembered(remember_s))
        self.twins = 0
        """Copies dropped: their twin from the other path was passed."""

    def first(self, key: int | None, path: int, now: float) -> bool:
        """Whether the copy of ``key`` (None: a message repeated identically, both passed) from
        ``path`` is the first of its message."""
        if key is None:
            return True
        mine, other = self._passed[path], self._passed[1 - path]
        mine.forget(now)
        other.forget(now)
        if other.take(key) is not None:
            self.twins += 1
            return False
        mine.add(key, now)
        return True
