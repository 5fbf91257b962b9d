"""A bounded FIFO of MQTT messages that drops the oldest when full (and counts what it drops).

The CAN and estimator path only ever appends (never waits); the publisher peeks a batch, publishes
it and removes the messages that the broker acknowledged, so an outage delays but does not reorder
or lose messages until the outbox overflows.

A broker outage of minutes leaves tens of thousands of messages here. Held as objects, each is
one more object that every full garbage collection walks on the event loop (~1 ms per 3k);
held as exact tuples of strings, bytes and numbers, the collector stops tracking them after
its first pass, so a long backlog costs a full collection nothing.
"""

from __future__ import annotations

import asyncio
import time
from collections import deque
from dataclasses import dataclass, field


@dataclass(frozen=True, slots=True)
class OutMessage:
    topic: str
    payload: bytes
    qos: int = 1
    retain: bool = False
    #: monotonic time (s) the sample behind it was complete; for latency figures, else None
    t_sample_mono: float | None = None
    t_enqueued_mono: float = field(default_factory=time.monotonic)


#: an :class:`OutMessage` as the outbox holds it: its fields, in order
_Row = tuple[str, bytes, int, bool, float | None, float]


def _row(m: OutMessage) -> _Row:
    return (m.topic, m.payload, m.qos, m.retain, m.t_sample_mono, m.t_enqueued_mono)


class Outbox:
    def __init__(self, maxsize: int) -> None:
        if maxsize < 1:
            raise ValueError("outbox maxsize must be >= 1")
        self.maxsize = maxsize
        self.dropped = 0
        self._q: deque[_Row] = deque()
        self._nonempty = asyncio.Event()

    def __len__(self) -> int:
        return len(self._q)

    def put(self, msg: OutMessage) -> None:
        if len(self._q) >= self.maxsize:
            self._q.popleft()
            self.dropped += 1
        self._q.append(_row(msg))
        self._nonempty.set()

    def peek(self, n: int) -> list[OutMessage]:
        """Up to ``n`` oldest messages, left in the outbox."""
        return [OutMessage(*self._q[i]) for i in range(min(n, len(self._q)))]

    def pop(self, n: int) -> None:
        """Remove the ``n`` oldest messages (those just delivered)."""
        for _ in range(min(n, len(self._q))):
            self._q.popleft()
        if not self._q:
            self._nonempty.clear()

    def remove_delivered(self, delivered: list[OutMessage]) -> int:
        """Remove the delivered prefix, unless an overflow already dropped it; returns count."""
        n = 0
        for msg in delivered:
            if self._q and self._q[0] == _row(msg):
                self._q.popleft()
                n += 1
        if not self._q:
            self._nonempty.clear()
        return n

    async def wait(self) -> None:
        """Return once the outbox holds a message."""
        await self._nonempty.wait()
