"""CAN faults of the README's troubleshooting table, the daemon's side (issue 16, item 7).

A real bus-off and a wrong bit rate need a CAN controller: vcan has neither (tests/faults/
README.md says what covers them). What the daemon does about them is tested here on
python-can's ``virtual`` bus, in-process, ~3 s in all: a bus-off error frame, and a missing
interface under systemd's notify protocol.
"""

from __future__ import annotations

import asyncio
import json
import logging
import socket
import sys
import time
from pathlib import Path

import can
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "daemon"))
from daemon_helpers import demo_frames, make_settings, send_virtual, wait_for

from bmsid.canbus.frames_to_samples import FrameToSamples
from bmsid.canbus.mapping import default_mapping
from bmsid.config.settings import Settings
from bmsid.daemon.core import CAN_ERR_BUSOFF, Daemon


def _state_lines(caplog: pytest.LogCaptureFixture, channel: str) -> list[tuple[int, str]]:
    prefix = f"CAN virtual/{channel} "
    return [
        (r.levelno, r.getMessage()) for r in caplog.records if r.getMessage().startswith(prefix)
    ]


def test_bus_off_is_one_state_change_in_the_status_and_loses_no_frame(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """README row "`can: bus_off`": the controller's bus-off error frames turn the status to
    ``bus_off`` with one WARNING line for the episode (the only line: the error frames are still
    counted, in ``can_bus_off`` and ``decode_errors``), the next data frame back to ``up``;
    every data frame before and after is decoded into the same samples as without them, and
    the error frames make none."""
    settings = make_settings(tmp_path, None, estimator={"isolation": "thread"})
    channel = settings.can.channel
    frames = demo_frames(30.0)
    half = len(frames) // 2
    n_err = 3  # a controller may report the episode more than once
    bus_off = [
        can.Message(
            timestamp=frames[half - 1].timestamp,
            arbitration_id=CAN_ERR_BUSOFF,
            is_extended_id=False,
            is_error_frame=True,
            data=bytes(8),
        )
        for _ in range(n_err)
    ]
    seen: dict[str, str] = {}

    async def main() -> Daemon:
        daemon = Daemon(settings)
        task = asyncio.create_task(daemon.run())
        await wait_for(lambda: daemon.can_state == "up" or task.done(), 20, "the bus")
        await asyncio.to_thread(send_virtual(channel, [*frames[:half], *bus_off]).join)
        await wait_for(lambda: daemon.can_state == "bus_off" or task.done(), 10, "bus_off")
        seen["status"] = json.loads(daemon._online_payload())["can"]
        await asyncio.to_thread(send_virtual(channel, frames[half:]).join)
        await wait_for(
            lambda: daemon.f2s.counters["frames"] == len(frames) + n_err or task.done(),
            10,
            "frames",
        )
        daemon.request_stop()
        assert await asyncio.wait_for(task, 30) == 0
        return daemon

    with caplog.at_level(logging.INFO, logger="bmsid"):
        daemon = asyncio.run(main())
    assert seen["status"] == "bus_off" and daemon.can_state == "up"
    assert daemon.counters["bus_off"] == n_err
    counters = daemon.snapshot()  # users see them in the status
    assert counters["can_bus_off"] == counters["decode_errors"] == n_err
    line = (
        f"CAN virtual/{channel} bus_off (bus-off error frame, 1 so far; up again with the next "
        "data frame)"
    )
    assert _state_lines(caplog, channel) == [
        (logging.INFO, f"CAN virtual/{channel} up"),
        (logging.WARNING, line),
        (logging.INFO, f"CAN virtual/{channel} up"),
    ]
    # the episode's only warning: no second line from the error-frame counter
    warnings = [r.getMessage() for r in caplog.records if r.levelno >= logging.WARNING]
    assert warnings == [line]
    # nothing lost, nothing invented: the samples of the data frames alone
    alone = FrameToSamples(default_mapping(), settings.can.n_cells, settings.can.staleness_s)
    expected = [s for m in frames for s in alone.feed(m)]
    assert daemon.f2s.counters["decoded"] == alone.counters["decoded"] == len(frames)
    assert daemon.f2s.counters["samples"] == len(expected) > 0
    assert daemon.f2s.counters["error_frames"] == n_err


def test_missing_interface_withholds_ready_and_says_down(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """README row "`can: down` in the status; `activating` for 2 min then 'start operation
    timed out'": with can0 missing the daemon keeps retrying, says ``down`` in its status and
    never sends READY=1, so systemd (Type=notify, TimeoutStartSec=2min) holds the unit in
    ``activating`` and restarts it after the timeout; STOPPING=1 still comes at the stop."""
    addr = str(tmp_path / "notify.sock")
    monkeypatch.setenv("NOTIFY_SOCKET", addr)
    monkeypatch.delenv("WATCHDOG_USEC", raising=False)
    settings = Settings(
        pack_id="p",
        systemd_notify=True,
        can={"channel": "bmsidgone0", "n_cells": 2, "reopen_min_s": 0.02, "reopen_max_s": 0.02},
        estimator={"isolation": "thread"},
        mqtt={"enabled": False},
        state={"directory": tmp_path / "state"},
    )
    seen: dict[str, str] = {}

    async def run_until_attempts(n: int) -> Daemon:
        daemon = Daemon(settings)
        task = asyncio.create_task(daemon.run())
        deadline = time.monotonic() + 20
        while daemon.counters["can_open_failures"] < n and time.monotonic() < deadline:
            await asyncio.sleep(0.02)
        seen["status"] = json.loads(daemon._online_payload())["can"]
        daemon.request_stop()
        assert await task == 0
        return daemon

    with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM) as sock:
        sock.bind(addr)
        daemon = asyncio.run(run_until_attempts(5))
        sock.settimeout(0.2)
        sent: list[str] = []
        while True:
            try:
                sent += sock.recv(4096).decode().splitlines()
            except TimeoutError:
                break
    assert daemon.counters["can_open_failures"] >= 5
    assert seen["status"] == "down"
    assert "READY=1" not in sent and "STOPPING=1" in sent, sent
