"""Frame sources of the daemon: SocketCAN through an ``add_reader`` reader, python-can's
``virtual`` bus through a thread, and a candump-log replayer onto the virtual bus (demo, tests).

Both sources hand the daemon batches of frames through a bounded queue. SocketCAN drops (and
counts) when the queue is full, as the kernel would; the virtual-bus thread blocks instead, which
pushes back into python-can's unbounded in-process queue (nothing is lost, the sender is slowed).
"""

from __future__ import annotations

import asyncio
import logging
import threading
import time
from pathlib import Path
from typing import Protocol

import can

from bmsid.canbus.bus import AsyncFrameReader, open_socketcan
from bmsid.canbus.logs import choose_channel, read_log, summarize_log
from bmsid.canbus.mapping import BusMapping
from bmsid.config.settings import ReplaySettings
from bmsid.errors import UserError

log = logging.getLogger(__name__)

BATCH_FRAMES = 256


class FrameSource(Protocol):
    @property
    def bus(self) -> can.BusABC: ...

    @property
    def dropped(self) -> int:
        """Frames lost because the queue was full."""
        ...

    @property
    def waiting(self) -> int:
        """Frames (or batches of frames) received and not yet taken: 0 when the reader is idle."""
        ...

    async def get_batch(self) -> list[can.Message]:
        """Frames received since the last call (at least one); raises on a bus error."""
        ...

    async def aclose(self) -> None:
        """Release the bus without blocking the event loop."""
        ...


IFF_UP = 0x1


def link_problem(channel: str) -> str | None:
    """Why ``channel`` cannot carry frames now (missing or administratively down), or None.

    A CAN socket binds to a down interface without complaint and then simply receives nothing,
    so the daemon checks the link before it reports the bus as up.
    """
    flags = Path("/sys/class/net") / channel / "flags"
    try:
        value = int(flags.read_text().strip(), 16)
    except FileNotFoundError:
        return f"no network interface {channel!r}"
    except (OSError, ValueError):
        return None  # no sysfs here: let the socket tell
    return None if value & IFF_UP else f"interface {channel} is down"


class SocketCanSource:
    def __init__(self, channel: str, fd: bool, maxsize: int) -> None:
        if (problem := link_problem(channel)) is not None:
            raise OSError(problem)
        self.bus = open_socketcan(channel, fd=fd)
        self._reader = AsyncFrameReader(self.bus, maxsize=maxsize)

    @property
    def dropped(self) -> int:
        return self._reader.dropped

    @property
    def waiting(self) -> int:
        return self._reader._queue.qsize()

    async def get_batch(self) -> list[can.Message]:
        batch = [await self._reader.get()]
        q = self._reader._queue  # drain what is already there: one hop per batch, not per frame
        while len(batch) < BATCH_FRAMES and not q.empty():
            item = q.get_nowait()
            if isinstance(item, BaseException):
                raise item
            batch.append(item)
        return batch

    async def aclose(self) -> None:
        # on the loop: the reader is registered with it (add_reader); both calls are quick
        self._reader.close()
        self.bus.shutdown()


class VirtualSource:
    """python-can ``virtual`` bus read by a thread (the bus has no file descriptor)."""

    def __init__(self, channel: str, maxsize_frames: int) -> None:
        self.bus = can.Bus(interface="virtual", channel=channel, receive_own_messages=False)
        self.dropped = 0
        self._loop = asyncio.get_running_loop()
        self._queue: asyncio.Queue[list[can.Message]] = asyncio.Queue(
            max(2, maxsize_frames // BATCH_FRAMES)
        )
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="bmsid-virtual-reader", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            msg = self.bus.recv(0.05)
            if msg is None:
                continue
            batch = [msg]
            while len(batch) < BATCH_FRAMES and (m := self.bus.recv(0)) is not None:
                batch.append(m)
            fut = asyncio.run_coroutine_threadsafe(self._queue.put(batch), self._loop)
            while not self._stop.is_set():
                try:
                    fut.result(timeout=0.1)
                    break
                except TimeoutError:
                    continue
            else:
                fut.cancel()

    @property
    def waiting(self) -> int:
        return self._queue.qsize()

    async def get_batch(self) -> list[can.Message]:
        return await self._queue.get()

    async def aclose(self) -> None:
        self._stop.set()
        # the reader thread notices within its 50 ms receive timeout: wait for it off the loop
        await asyncio.to_thread(self._thread.join, 2.0)
        self.bus.shutdown()


def open_source(interface: str, channel: str, fd: bool, maxsize_frames: int) -> FrameSource:
    if interface == "socketcan":
        return SocketCanSource(channel, fd, maxsize_frames)
    return VirtualSource(channel, maxsize_frames)


class LogReplayer:
    """Replays a candump log onto a ``virtual`` channel at ``speed`` x real time, in a thread.

    Frames keep their log timestamps (``preserve_timestamps``), so the estimator sees the log's
    time axis whatever the speed. Frames that others send on the channel (bmsid's own output)
    are discarded as they arrive so the in-process queue cannot grow. ``resume_after_s`` skips
    the frames up to that log time: a daemon restored from a checkpoint resumes the replay
    where its state left off, as a live bus would have moved on. ``log_channel`` replays only
    the frames the log recorded on that interface (None: all, see :func:`replay_channel`).

    Raises:
        UserError: the log cannot be opened (checked here, before the thread starts: a
            missing log must stop the daemon with one line, not leave it on a silent bus).
    """

    def __init__(
        self,
        log_path: Path,
        channel: str,
        speed: float,
        start_delay_s: float,
        resume_after_s: float | None = None,
        log_channel: str | None = None,
    ) -> None:
        try:
            with log_path.open("rb"):
                pass
        except OSError as exc:
            raise UserError(
                f"can.replay.log: cannot read {log_path}: {exc.strerror or exc}"
            ) from None
        self.log_path = log_path
        self.speed = speed
        self.start_delay_s = start_delay_s
        self.resume_after_s = resume_after_s
        self.log_channel = log_channel
        self.skipped = 0
        self.sent = 0
        self.done = threading.Event()
        self._stop = threading.Event()
        self._bus = can.Bus(
            interface="virtual",
            channel=channel,
            preserve_timestamps=True,
            receive_own_messages=False,
        )
        self._thread = threading.Thread(target=self._run, name="bmsid-replay", daemon=True)

    def start(self) -> None:
        self._thread.start()

    def _run(self) -> None:
        try:
            if self._stop.wait(self.start_delay_s):
                return
            t0_wall = time.monotonic()
            t0_log: float | None = None
            for msg in read_log(self.log_path):
                if self.log_channel is not None and str(msg.channel) != self.log_channel:
                    continue
                if self.resume_after_s is not None and msg.timestamp <= self.resume_after_s:
                    self.skipped += 1
                    continue
                if t0_log is None:
                    t0_log = msg.timestamp
                due = t0_wall + (msg.timestamp - t0_log) / self.speed
                delay = due - time.monotonic()
                if delay > 0.001 and self._stop.wait(delay):
                    return
                if self._stop.is_set():
                    return
                self._bus.send(msg)
                self.sent += 1
                if self.sent % 512 == 0:
                    while self._bus.recv(0) is not None:
                        pass
            if self.sent == 0 and self.skipped:
                log.warning(
                    "replay of %s: all %d frames are older than the restored checkpoint, none "
                    "sent (state.restore = false, or another state.directory, replays it again)",
                    self.log_path,
                    self.skipped,
                )
            else:
                log.info(
                    "replay of %s finished: %d frames (%d skipped: before the checkpoint)",
                    self.log_path,
                    self.sent,
                    self.skipped,
                )
        except (UserError, OSError) as exc:  # the file went away or became unreadable
            log.error("replay of %s stopped after %d frames: %s", self.log_path, self.sent, exc)
        except Exception:
            log.exception("replay of %s failed", self.log_path)
        finally:
            self.done.set()

    def stop(self) -> None:
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(timeout=2.0)
        self._bus.shutdown()


def replay_channel(replay: ReplaySettings, mapping: BusMapping) -> str | None:
    """The log interface to replay (``replay.channel``, checked against the log), or None when
    the log carries the mapping's frames on at most one, as ``bmsid identify`` decides.

    Raises:
        UserError: naming ``can.replay.channel``: the mapping's frames on several interfaces
            and no channel set, or the set one carries none of them.
    """
    summary = summarize_log(replay.log, mapping, cells=False)  # channels only: a fast pass
    try:
        choose_channel(summary, replay.channel, 'set can.replay.channel = "NAME"')
    except UserError as exc:
        raise UserError(f"can.replay.channel: {exc}") from None
    return replay.channel
