"""``bmsid run`` under the systemd notify protocol, as the unit's ``Type=notify`` and
``WatchdogSec=`` expect: READY=1 once the bus is open, WATCHDOG=1 every WATCHDOG_USEC/2,
STOPPING=1 on SIGTERM, exit 0. systemd's side is played by a datagram socket of the test."""

from __future__ import annotations

import itertools
import os
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

from bmsid.daemon.demo_data import DEMO_LOG

REPO = Path(__file__).resolve().parents[2]
WATCHDOG_S = 1.0


def _config(tmp_path: Path) -> Path:
    path = tmp_path / "bmsid.toml"
    path.write_text(
        f"""pack_id = "notify"
systemd_notify = true
[can]
interface = "virtual"
channel = "notify-test"
n_cells = 8
[can.replay]
log = "{DEMO_LOG}"
speed = 20.0
[mqtt]
enabled = false
[state]
directory = "{tmp_path / "state"}"
""",
        encoding="utf-8",
    )
    return path


def _enough(got: list[tuple[float, str]]) -> bool:
    ready = [t for t, line in got if line == "READY=1"]
    return bool(ready) and sum(line == "WATCHDOG=1" and t > ready[0] for t, line in got) >= 4


def _receive(
    sock: socket.socket, until: float, done: Callable[[list[tuple[float, str]]], bool]
) -> list[tuple[float, str]]:
    out: list[tuple[float, str]] = []
    while time.monotonic() < until and not done(out):
        sock.settimeout(max(0.01, until - time.monotonic()))
        try:
            data = sock.recv(4096)
        except TimeoutError:
            break
        out += [(time.monotonic(), line) for line in data.decode().splitlines()]
    return out


def test_ready_watchdog_and_stopping_reach_the_notify_socket(tmp_path: Path) -> None:
    addr = str(tmp_path / "notify.sock")
    with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM) as sock:
        sock.bind(addr)
        env = {
            **os.environ,
            "PYTHONPATH": str(REPO / "service"),
            "NOTIFY_SOCKET": addr,
            "WATCHDOG_USEC": str(int(WATCHDOG_S * 1e6)),
        }
        log = tmp_path / "daemon.log"
        with log.open("wb") as fh:
            proc = subprocess.Popen(
                [sys.executable, "-m", "bmsid.cli.main", "run", "--config", str(_config(tmp_path))],
                stdout=fh,
                stderr=subprocess.STDOUT,
                env=env,
            )
        try:
            got = _receive(sock, time.monotonic() + 60.0, _enough)
            lines = [line for _, line in got]
            assert "READY=1" in lines, log.read_text()
            ready_at = next(t for t, line in got if line == "READY=1")
            pings = [t for t, line in got if line == "WATCHDOG=1" and t > ready_at]
            assert len(pings) >= 4, lines  # pinged every WATCHDOG_USEC/2
            assert max(b - a for a, b in itertools.pairwise(pings)) < WATCHDOG_S
            proc.send_signal(signal.SIGTERM)
            assert proc.wait(30) == 0, log.read_text()
            after = [line for _, line in _receive(sock, time.monotonic() + 0.5, lambda _: False)]
            assert "STOPPING=1" in after, after
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.wait()
