"""When the daemon may tell systemd it is alive (``WATCHDOG=1``): the decision, without I/O.

Feeding the watchdog only while frames flow would be wrong on a gateway: a parked vehicle's BMS
sleeps and the bus goes silent for hours, and a daemon killed by systemd every ``WatchdogSec``
(then held failed by the start limit) wakes no BMS; the silence is already said by health bit 8
(stale input) and a counters line whose ``frames`` stop growing. What a restart does cure is a
stuck pipeline, and that shows as work that waits without moving:

- the event loop: stuck, it runs no watchdog task, so nothing is sent;
- the CAN reader: frames wait (in its source's queue, or in the batch it holds) and it has
  neither taken frames nor queued samples for ``limit_s`` (a reader held back by a full sample
  queue is the bank's stall, not its own);
- the bank worker: samples or calls wait for it and it has given no sign for ``limit_s``; a
  sign is an answer, or a heartbeat it sends between ticks of a long call (a start-up probe
  releasing half an hour of samples). On a silent bus the daemon probes it with a no-op call,
  so a hung worker is found without data too.

A stage with nothing waiting for it is idle, not stuck.
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True, slots=True)
class Pipeline:
    """The daemon's pipeline as the watchdog sees it; times are ``time.monotonic()``, s."""

    now_s: float
    #: frames (or batches of frames) received by the CAN source and not yet through the reader:
    #: in the source's queue, or in the batch the reader is working through
    frames_waiting: int
    #: when the reader last took frames from its source or queued samples
    reader_progress_s: float
    #: samples queued for the bank worker
    samples_waiting: int
    #: calls to the bank worker not answered yet (queued or running)
    bank_calls: int
    #: when the bank worker last answered or sent a heartbeat, or was handed work while idle
    bank_progress_s: float


def stall(p: Pipeline, limit_s: float) -> str | None:
    """Why the pipeline is stuck (the end of a log line), or None when ``WATCHDOG=1`` is due.

    Args:
        p: the pipeline now.
        limit_s: how long waiting work may go without progress, s (the unit's ``WatchdogSec``:
            systemd restarts the daemon at most another ``WatchdogSec`` later).
    """
    reader_idle = p.now_s - p.reader_progress_s
    if p.frames_waiting > 0 and reader_idle > limit_s:
        return (
            f"the CAN reader has made no progress for {reader_idle:.1f} s "
            f"({p.frames_waiting} frames waiting)"
        )
    bank_idle = p.now_s - p.bank_progress_s
    if (p.samples_waiting > 0 or p.bank_calls > 0) and bank_idle > limit_s:
        return (
            f"the bank worker has not answered for {bank_idle:.1f} s ({p.bank_calls} call(s) "
            f"and {p.samples_waiting} samples waiting)"
        )
    return None
