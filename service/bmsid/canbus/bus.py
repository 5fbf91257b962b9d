"""SocketCAN at the edge: open a bus, read frames into a bounded asyncio queue, send with retry.

The reader drains ``bus.recv(0)`` from ``loop.add_reader`` itself instead of using python-can's
``Notifier``: the queue is bounded (drops are counted, not buffered without limit) and interface
errors (ENETDOWN, ENODEV) reach the consumer as exceptions instead of the loop's handler.
"""

from __future__ import annotations

import asyncio
import errno
import logging
import socket
from collections.abc import Iterable

import can

log = logging.getLogger(__name__)

#: Receive buffer asked for (capped by net.core.rmem_max): about 550 frames fit by default.
DEFAULT_RCVBUF_BYTES = 4 * 1024 * 1024


def open_socketcan(
    channel: str,
    *,
    fd: bool = False,
    rcvbuf_bytes: int | None = DEFAULT_RCVBUF_BYTES,
    receive_own_messages: bool = False,
) -> can.BusABC:
    """A SocketCAN bus on ``channel`` (error frames are delivered; the decoder counts them)."""
    bus = can.Bus(
        interface="socketcan",
        channel=channel,
        fd=fd,
        receive_own_messages=receive_own_messages,
    )
    if rcvbuf_bytes:
        sock = getattr(bus, "socket", None)
        if isinstance(sock, socket.socket):
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, rcvbuf_bytes)
    return bus


class AsyncFrameReader:
    """Frames of ``bus`` as an async iterator, through a queue of at most ``maxsize`` frames."""

    def __init__(self, bus: can.BusABC, maxsize: int = 10_000) -> None:
        self.bus = bus
        self.dropped = 0
        self._queue: asyncio.Queue[can.Message | BaseException] = asyncio.Queue(maxsize)
        self._loop = asyncio.get_running_loop()
        self._fd = bus.fileno()
        self._loop.add_reader(self._fd, self._drain)

    def _drain(self) -> None:
        try:
            while (msg := self.bus.recv(0)) is not None:
                if self._queue.full():
                    self.dropped += 1
                    if self.dropped == 10 ** (len(str(self.dropped)) - 1):
                        log.warning("reader queue full: %d frames dropped", self.dropped)
                    continue
                self._queue.put_nowait(msg)
        except (can.CanError, OSError) as exc:
            self._loop.remove_reader(self._fd)
            while self._queue.full():  # make room: the error must reach the consumer
                self._queue.get_nowait()
                self.dropped += 1
            self._queue.put_nowait(exc)

    async def get(self) -> can.Message:
        """The next frame; raises the bus error that stopped the reader."""
        item = await self._queue.get()
        if isinstance(item, BaseException):
            raise item
        return item

    def __aiter__(self) -> AsyncFrameReader:
        return self

    async def __anext__(self) -> can.Message:
        return await self.get()

    def close(self) -> None:
        self._loop.remove_reader(self._fd)


async def send_frames(
    bus: can.BusABC,
    frames: Iterable[can.Message],
    *,
    retries: int = 50,
    backoff_s: float = 0.002,
) -> int:
    """Send ``frames`` in order; retry ENOBUFS (full tx queue) with backoff. Returns frames sent.

    Raises ``can.CanOperationError`` for any other error or when retries run out.
    """
    sent = 0
    for frame in frames:
        for attempt in range(retries + 1):
            try:
                bus.send(frame)
                break
            except can.CanOperationError as exc:
                if exc.error_code != errno.ENOBUFS or attempt == retries:
                    raise
                await asyncio.sleep(backoff_s * (attempt + 1))
        sent += 1
    return sent
