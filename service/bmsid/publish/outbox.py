"""A bounded FIFO of MQTT messages that drops the oldest when full (and counts what it drops).

The CAN and estimator path only ever appends (never waits); the publisher peeks a batch, publishes
it and removes the messages that the broker acknowledged, so an outage delays but does not reorder
or lose messages until the outbox overflows.

A broker outage of minutes leaves tens of thousands of messages here. Held as objects, each is
one more object that every full garbage collection walks on the event loop (~1 ms per 3k);
held as exact tuples of strings, bytes and numbers, the collector stops tracking them after
its first pass, so a long backlog costs a full collection nothing.

What a shutdown cannot deliver is spooled (:func:`save_spool`): one file in the state
directory, written atomically and fsync'd, holding at most the outbox's ``maxsize`` messages
(``mqtt.outbox_size``; ~0.5 kB each). The next start puts them in the outbox before any new
message (:func:`load_spool`), so a subscriber sees every ``seq`` in order, or a gap that
``mqtt_drops`` counts. A spool too large for what the directory still takes (full, over
quota) is replaced by one that holds only the count of the lost messages (a few bytes, in the
same file: one file says what the last stop left, and the ``.seq`` file stays one number
written by the worker alone); the next start adds it to its ``mqtt_drops``, so the gap those
messages leave is counted after the restart too.
"""

from __future__ import annotations

import asyncio
import json
import logging
import time
from collections import deque
from dataclasses import dataclass, field
from pathlib import Path

from bmsid.daemon.statedir import atomic_write, quarantine

log = logging.getLogger(__name__)
#: Version of the spool file's first line.
SPOOL_FORMAT = 1


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
        #: messages that ever left the head of the outbox (delivered or dropped)
        self.taken = 0
        self._q: deque[_Row] = deque()
        self._nonempty = asyncio.Event()

    def __len__(self) -> int:
        return len(self._q)

    def put(self, msg: OutMessage) -> None:
        if len(self._q) >= self.maxsize:
            self._q.popleft()
            self.dropped += 1
            self.taken += 1
        self._q.append(_row(msg))
        self._nonempty.set()

    def peek(self, n: int) -> list[OutMessage]:
        """Up to ``n`` oldest messages, left in the outbox."""
        return [OutMessage(*self._q[i]) for i in range(min(n, len(self._q)))]

    def pop(self, n: int) -> None:
        """Remove the ``n`` oldest messages (those just delivered)."""
        for _ in range(min(n, len(self._q))):
            self._q.popleft()
            self.taken += 1
        if not self._q:
            self._nonempty.clear()

    def remove_delivered(self, delivered: list[OutMessage]) -> int:
        """Remove the delivered prefix, unless an overflow already dropped it; returns count."""
        n = 0
        for msg in delivered:
            if self._q and self._q[0] == _row(msg):
                self._q.popleft()
                n += 1
        self.taken += n
        if not self._q:
            self._nonempty.clear()
        return n

    async def wait(self) -> None:
        """Return once the outbox holds a message."""
        await self._nonempty.wait()


def encode_spool(pack_id: str, messages: list[OutMessage], dropped: int = 0) -> bytes:
    """The spool file: a JSON header line, then one JSON array per message (topic, qos, retain,
    payload as Latin-1 text: any bytes round-trip). Sample times are not kept: monotonic
    clocks do not survive a restart. ``dropped``: messages of the stop that are not in the
    file (lost: a ``seq`` gap the next start counts)."""
    head = {
        "bmsid_spool": SPOOL_FORMAT,
        "pack_id": pack_id,
        "messages": len(messages),
        "dropped": dropped,
    }
    lines = [json.dumps(head)]
    lines += [json.dumps([m.topic, m.qos, m.retain, m.payload.decode("latin-1")]) for m in messages]
    return ("\n".join(lines) + "\n").encode("utf-8")


def decode_spool(data: bytes, pack_id: str) -> tuple[list[OutMessage], int, str | None]:
    """(messages, lost, problem): the valid prefix of a spool file, how many messages of the
    stop that wrote it are not in that prefix (the header's ``dropped`` and its announced
    messages that cannot be read; 0 without a usable header), and what is wrong (None)."""
    lines = data.decode("utf-8", errors="replace").splitlines()
    try:
        head = json.loads(lines[0]) if lines else None
    except json.JSONDecodeError:
        head = None
    if not isinstance(head, dict) or head.get("bmsid_spool") != SPOOL_FORMAT:
        return [], 0, "no spool header"
    if head.get("pack_id") != pack_id:
        return [], 0, f"spooled for pack {head.get('pack_id')!r}"
    announced, dropped = head.get("messages"), head.get("dropped", 0)  # no "dropped": older
    if not isinstance(announced, int) or announced < 0:
        return [], 0, "bad message count in the header"
    if not isinstance(dropped, int) or dropped < 0:
        return [], announced, "bad dropped count in the header"
    out: list[OutMessage] = []
    for k, line in enumerate(lines[1:], 2):
        try:
            topic, qos, retain, payload = json.loads(line)
            if not (
                isinstance(topic, str)
                and qos in (0, 1, 2)
                and isinstance(retain, bool)
                and isinstance(payload, str)
            ):
                raise ValueError("bad field")
            out.append(OutMessage(topic, payload.encode("latin-1"), qos, retain))
        except (ValueError, UnicodeEncodeError):
            return out, dropped + announced - len(out), f"line {k} is damaged"
    if len(out) != announced:
        return out, dropped + announced - len(out), f"{len(out)} of {announced} messages"
    return out, dropped, None


def save_spool(path: Path, pack_id: str, messages: list[OutMessage], dropped: int = 0) -> None:
    """Write ``messages`` (and the count of the ``dropped`` ones) to the spool file at ``path``
    atomically (raises OSError)."""
    data = encode_spool(pack_id, messages, dropped)
    atomic_write(path, lambda fh: fh.write(data))


def load_spool(path: Path, pack_id: str) -> tuple[list[OutMessage], int]:
    """(messages, lost): the spooled messages (none without a file) and how many messages of
    the stop that wrote it are lost (its count of dropped ones, and those that cannot be read
    back). One WARNING line when some are lost.

    A damaged file is quarantined after its readable prefix is taken, and that prefix is
    spooled again (with the lost count): the file stays until its messages are delivered, so
    a crash before then loses nothing more.
    """
    try:
        data = path.read_bytes()
    except FileNotFoundError:
        return [], 0
    except OSError as exc:
        quarantine(path, "MQTT spool", f"unreadable: {exc.strerror or exc}")
        return [], 0
    messages, lost, problem = decode_spool(data, pack_id)
    if problem is None:
        if lost:
            log.warning(
                "MQTT: %d messages the last stop could neither deliver nor spool are lost (%s): "
                "a seq gap, counted in mqtt_drops",
                lost,
                path,
            )
        return messages, lost
    why = f"{problem}; {len(messages)} messages recovered, {lost} lost (counted in mqtt_drops)"
    quarantine(path, "MQTT spool", why)
    if messages:
        try:
            save_spool(path, pack_id, messages, lost)
        except OSError as exc:
            log.warning(
                "MQTT spool %s: the %d recovered messages cannot be spooled again (%s): a crash "
                "before they are delivered loses them",
                path,
                len(messages),
                exc.strerror or exc,
            )
    return messages, lost
