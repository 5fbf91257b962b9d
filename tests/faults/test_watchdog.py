"""The systemd watchdog (issue 16): fed on a silent bus and while frames flow, withheld while a
stage of the pipeline is stuck with work waiting, fed again once it moves.

systemd's side is a datagram socket of the test (``NOTIFY_SOCKET``), the daemon runs in-process
on python-can's ``virtual`` bus with the bank in a thread, so a stage can be stuck on purpose:
the bank's ``update`` or ``ping`` waits on an event, or the reader's sample hand-over does.
``WatchdogSec`` is 1 s (2 s for the healthy run); no assertion depends on a duration:
"withheld" is checked over watchdog periods the daemon counts (``watchdog_withheld``), not over
a time. About 21 s in all.
"""

from __future__ import annotations

import asyncio
import logging
import socket
import sys
import threading
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "daemon"))
from daemon_helpers import demo_frames, make_settings, send_virtual, wait_for

from bmsid.daemon import bank_worker
from bmsid.daemon.core import Daemon
from bmsid.daemon.watchdog import Pipeline, stall

WATCHDOG_S = 1.0


# ---------------------------------------------------------------------- the decision (pure)
def _pipeline(**kw: float) -> Pipeline:
    """Everything idle since long before now (t = 1000 s)."""
    base: dict[str, float] = {
        "now_s": 1000.0,
        "frames_waiting": 0,
        "reader_progress_s": 0.0,
        "samples_waiting": 0,
        "bank_calls": 0,
        "bank_progress_s": 0.0,
    }
    return Pipeline(**(base | kw))  # type: ignore[arg-type]


@pytest.mark.parametrize(
    ("case", "kw"),
    [
        ("silent bus: nothing waits anywhere", {}),
        ("frames flowing", {"frames_waiting": 3, "reader_progress_s": 999.9}),
        (
            "a long call with heartbeats",
            {"bank_calls": 1, "samples_waiting": 640, "bank_progress_s": 999.5},
        ),
        ("the probe answered", {"bank_calls": 1, "bank_progress_s": 999.8}),
    ],
)
def test_idle_or_moving_stages_feed_the_watchdog(case: str, kw: dict[str, float]) -> None:
    assert stall(_pipeline(**kw), 30.0) is None, case


@pytest.mark.parametrize(
    ("kw", "said"),
    [
        ({"frames_waiting": 5, "reader_progress_s": 960.0},
         "the CAN reader has made no progress for 40.0 s (5 frames waiting)"),
        ({"bank_calls": 1, "samples_waiting": 64, "bank_progress_s": 960.0},
         "the bank worker has not answered for 40.0 s (1 call(s) and 64 samples waiting)"),
        ({"samples_waiting": 64, "bank_progress_s": 960.0},  # queued, no call made: stuck too
         "the bank worker has not answered for 40.0 s (0 call(s) and 64 samples waiting)"),
        ({"bank_calls": 1, "bank_progress_s": 960.0},  # the silent bus's probe unanswered
         "the bank worker has not answered for 40.0 s (1 call(s) and 0 samples waiting)"),
    ],
)  # fmt: skip
def test_waiting_work_without_progress_withholds_the_watchdog(
    kw: dict[str, float], said: str
) -> None:
    assert stall(_pipeline(**kw), 30.0) == said
    assert stall(_pipeline(**kw), 45.0) is None  # within the limit: still moving


# ---------------------------------------------------------------------- the daemon
class Systemd:
    """The notify socket's receiving end: what the daemon sent, line by line."""

    def __init__(self, path: Path) -> None:
        self.sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        self.sock.bind(str(path))
        self.sock.setblocking(False)
        self.lines: list[str] = []

    def read(self) -> list[str]:
        """Every line received so far (datagrams are queued in the socket when sent)."""
        while True:
            try:
                self.lines += self.sock.recv(4096).decode().splitlines()
            except BlockingIOError:
                return self.lines

    def pings(self) -> int:
        return self.read().count("WATCHDOG=1")


@pytest.fixture
def systemd(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Iterator[Systemd]:
    path = tmp_path / "notify.sock"
    monkeypatch.setenv("NOTIFY_SOCKET", str(path))
    monkeypatch.setenv("WATCHDOG_USEC", str(int(WATCHDOG_S * 1e6)))
    sd = Systemd(path)
    yield sd
    sd.sock.close()


def _daemon(tmp_path: Path) -> Daemon:
    settings = make_settings(tmp_path, None, systemd_notify=True, estimator={"isolation": "thread"})
    return Daemon(settings)


def _pings_while(sd: Systemd, n: int) -> Callable[[], bool]:
    """True once ``n`` more WATCHDOG=1 than now have come."""
    target = sd.pings() + n
    return lambda: sd.pings() >= target


def test_silent_bus_and_flowing_frames_keep_the_watchdog_fed(
    tmp_path: Path, systemd: Systemd, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A sleeping BMS (no frame at all) is no reason for systemd to restart bmsid: WATCHDOG=1
    keeps coming, and the idle bank worker is probed (it answers); frames flowing after that
    keep it coming too."""
    # a longer WatchdogSec than the stuck cases': no stall of a loaded test machine can pass
    # for a stuck stage here
    monkeypatch.setenv("WATCHDOG_USEC", str(int(2 * WATCHDOG_S * 1e6)))
    pinged: list[int] = []
    ping = bank_worker.BankHost.ping

    def counted(host: bank_worker.BankHost) -> None:
        pinged.append(1)
        ping(host)

    monkeypatch.setattr(bank_worker.BankHost, "ping", counted)
    frames = demo_frames(30.0)

    async def main() -> Daemon:
        daemon = _daemon(tmp_path)
        task = asyncio.create_task(daemon.run())
        await wait_for(lambda: "READY=1" in systemd.read() or task.done(), 20, "READY=1")
        await wait_for(_pings_while(systemd, 4), 20, "4 pings on a silent bus")
        assert daemon.f2s.counters["frames"] == 0 and pinged  # silent, and probed
        await asyncio.to_thread(send_virtual(daemon.settings.can.channel, frames).join)
        await wait_for(
            lambda: daemon.f2s.counters["frames"] == len(frames) or task.done(), 20, "frames"
        )
        await wait_for(lambda: daemon.bank_counters["ticks"] > 0 or task.done(), 20, "ticks")
        await wait_for(_pings_while(systemd, 2), 20, "2 pings after the frames")
        daemon.request_stop()
        assert await asyncio.wait_for(task, 30) == 0
        return daemon

    daemon = asyncio.run(main())
    assert daemon.counters["watchdog_withheld"] == 0
    assert systemd.read()[-1] == "STOPPING=1"


def _stuck_bank_update(monkeypatch: pytest.MonkeyPatch, gate: threading.Event) -> None:
    update = bank_worker.BankHost.update

    def stuck(host: bank_worker.BankHost, block: Any) -> Any:
        gate.wait()
        return update(host, block)

    monkeypatch.setattr(bank_worker.BankHost, "update", stuck)


def _stuck_bank_ping(monkeypatch: pytest.MonkeyPatch, gate: threading.Event) -> None:
    def stuck(host: bank_worker.BankHost) -> None:
        gate.wait()

    monkeypatch.setattr(bank_worker.BankHost, "ping", stuck)


@pytest.mark.parametrize(
    ("stage", "said"),
    [
        ("bank-with-samples", "the bank worker has not answered for"),
        ("bank-on-a-silent-bus", "the bank worker has not answered for"),
        ("reader", "the CAN reader has made no progress for"),
    ],
)
def test_a_stuck_stage_withholds_the_watchdog_until_it_moves_again(
    tmp_path: Path,
    systemd: Systemd,
    monkeypatch: pytest.MonkeyPatch,
    caplog: pytest.LogCaptureFixture,
    stage: str,
    said: str,
) -> None:
    """README row "watchdog: ... WATCHDOG=1 withheld": a bank worker that does not answer (with
    samples waiting, or its probe on a silent bus) or a CAN reader that makes no progress while
    frames wait gets no WATCHDOG=1, with one ERROR line saying which; once it moves, WATCHDOG=1
    comes again with one WARNING line, and nothing was lost."""
    bank_gate = threading.Event()
    if stage == "bank-with-samples":
        _stuck_bank_update(monkeypatch, bank_gate)
    elif stage == "bank-on-a-silent-bus":
        _stuck_bank_ping(monkeypatch, bank_gate)
    frames = [] if stage == "bank-on-a-silent-bus" else demo_frames(30.0)
    seen: dict[str, int] = {}

    async def main() -> Daemon:
        daemon = _daemon(tmp_path)
        reader_gate = asyncio.Event()
        if stage == "reader":
            flush = daemon._flush_samples

            async def stuck_flush() -> None:
                await reader_gate.wait()
                await flush()

            monkeypatch.setattr(daemon, "_flush_samples", stuck_flush)
        task = asyncio.create_task(daemon.run())
        await wait_for(lambda: "READY=1" in systemd.read() or task.done(), 20, "READY=1")
        await wait_for(_pings_while(systemd, 1), 20, "a ping before the fault")
        if frames:
            send_virtual(daemon.settings.can.channel, frames)
        await wait_for(
            lambda: daemon.counters["watchdog_withheld"] > 0 or task.done(), 20, "withheld"
        )
        # from here, three watchdog periods withheld in a row and no WATCHDOG=1 among them
        pings = systemd.pings()
        withheld = daemon.counters["watchdog_withheld"]
        await wait_for(
            lambda: daemon.counters["watchdog_withheld"] >= withheld + 3 or task.done(),
            20,
            "three periods withheld",
        )
        seen["pings_while_stuck"] = systemd.pings() - pings
        bank_gate.set()
        reader_gate.set()
        await wait_for(_pings_while(systemd, 2), 20, "pings once moving again")
        await wait_for(
            lambda: daemon.f2s.counters["frames"] == len(frames) or task.done(), 20, "frames"
        )
        daemon.request_stop()
        assert await asyncio.wait_for(task, 30) == 0
        return daemon

    with caplog.at_level(logging.INFO, logger="bmsid"):
        daemon = asyncio.run(main())
    assert seen["pings_while_stuck"] == 0
    lines = [
        (r.levelno, r.getMessage())
        for r in caplog.records
        if r.getMessage().startswith("watchdog: ")
    ]
    assert len(lines) == 2, lines  # one line at the stall, one when it moves again
    (level0, stuck), (level1, moving) = lines
    assert level0 == logging.ERROR and stuck.startswith(f"watchdog: {said}"), stuck
    assert stuck.endswith(
        "WATCHDOG=1 withheld, systemd restarts bmsid once WatchdogSec has passed since the last one"
    )
    assert level1 == logging.WARNING and "moves again" in moving
    assert daemon.f2s.counters["frames"] == len(frames)  # nothing lost to the stall
