"""Where the real dashboards live (installed by scripts/install-dashboard-tools) and what the
tests need of them: the pins, a free port, an MQTT publisher, a process that is always stopped.

A missing tool fails the test when real parts are required (CI) and skips it otherwise, by the
rule of tests/conftest.py.
"""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import time
from collections.abc import Iterable
from pathlib import Path
from typing import IO

import paho.mqtt.client as paho

from conftest import missing_real_part, port_accepts

REPO = Path(__file__).resolve().parents[2]
INSTALLER = REPO / "scripts" / "install-dashboard-tools"
TOOLS_DIR = Path(
    os.environ.get("BMSID_TOOLS_DIR")
    or Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "bmsid-tools"
)
HOW = f"run {INSTALLER.relative_to(REPO)} (./scripts/test does)"


def pin(name: str) -> str:
    """A version pinned in scripts/install-dashboard-tools (the one place the pins live)."""
    match = re.search(rf"^{name}=(\S+)", INSTALLER.read_text(encoding="utf-8"), re.MULTILINE)
    assert match, name
    return match.group(1)


def require_path(path: Path, what: str) -> Path:
    if not path.exists():
        missing_real_part(f"{what} not installed at {path}; {HOW}")
    return path


def publish(port: int, messages: Iterable[tuple[str, bytes, bool]]) -> None:
    """Publish (topic, payload, retain) at QoS 1 and wait until the broker has each."""
    client = paho.Client(paho.CallbackAPIVersion.VERSION2)
    client.connect("127.0.0.1", port)
    client.loop_start()
    try:
        for topic, payload, retain in messages:
            client.publish(topic, payload, qos=1, retain=retain).wait_for_publish(10)
    finally:
        client.disconnect()
        client.loop_stop()


class Process:
    """A child process with its output in a log file; ``stop()`` terminates it (then kills)."""

    def __init__(self, args: list[str], log: Path, cwd: Path, env: dict[str, str]) -> None:
        self.log_path = log
        self._log: IO[bytes] = log.open("wb")
        self.proc = subprocess.Popen(
            args, stdout=self._log, stderr=subprocess.STDOUT, cwd=cwd, env=env,
            start_new_session=True,
        )  # fmt: skip

    def log(self) -> str:
        return self.log_path.read_text(encoding="utf-8", errors="replace")

    def wait_port(self, port: int, timeout_s: float, what: str) -> float:
        """Seconds until ``port`` accepts; AssertionError with the log if it dies or times out."""
        t0 = time.monotonic()
        while not port_accepts("127.0.0.1", port):
            if self.proc.poll() is not None:
                raise AssertionError(f"{what} exited with {self.proc.returncode}:\n{self.log()}")
            if time.monotonic() - t0 > timeout_s:
                raise AssertionError(f"{what} not listening after {timeout_s} s:\n{self.log()}")
            time.sleep(0.1)
        return time.monotonic() - t0

    def stop(self) -> None:
        if self.proc.poll() is None:
            os.killpg(self.proc.pid, signal.SIGTERM)
            try:
                self.proc.wait(20)
            except subprocess.TimeoutExpired:
                os.killpg(self.proc.pid, signal.SIGKILL)
                self.proc.wait()
        self._log.close()


def wait_until(cond: object, timeout_s: float, what: str, log: Process | None = None) -> None:
    deadline = time.monotonic() + timeout_s
    while not callable(cond) or not cond():
        if time.monotonic() > deadline:
            extra = f"\n{log.log()[-4000:]}" if log is not None else ""
            raise AssertionError(f"timed out after {timeout_s} s waiting for {what}{extra}")
        time.sleep(0.1)


def read_jsonl(path: Path) -> list[dict[str, object]]:
    if not path.exists():
        return []
    return [json.loads(line) for line in path.read_text(encoding="utf-8").splitlines() if line]
