"""``kill -9`` mid-run, restart: SOC and parameters continue from the checkpoint."""

from __future__ import annotations

import itertools
import signal
import subprocess
import time
from pathlib import Path
from typing import Any

import pytest
from daemon_helpers import (
    FAST_TUNING,
    MqttCapture,
    demo_frames,
    make_settings,
    offline_estimates,
    start_daemon,
)

from bmsid.config.cell import paper_cell
from bmsid.daemon.demo_data import DEMO_LOG, T0_S, WEAK_CELL

REPO = Path(__file__).resolve().parents[2]
SPEED = 60.0


def _config(tmp_path: Path, port: int) -> Path:
    tuning = "\n".join(f"{k} = {v}" for k, v in FAST_TUNING.items())
    path = tmp_path / "bmsid.toml"
    path.write_text(
        f"""pack_id = "testpack"
systemd_notify = false
status_period_s = 1.0
[can]
interface = "virtual"
channel = "restart-test"
n_cells = 8
[can.replay]
log = "{DEMO_LOG}"
speed = {SPEED}
start_delay_s = 0.2
[estimator.tuning]
{tuning}
[mqtt]
url = "mqtt://127.0.0.1:{port}"
publish_period_s = 0.0
[state]
directory = "{tmp_path / "state"}"
checkpoint_period_s = 1.0
""",
        encoding="utf-8",
    )
    return path


def _cell0(cap: MqttCapture, skip: int = 0) -> list[dict[str, Any]]:
    return [p for t, p in cap.messages()[skip:] if t.endswith("/cell/0")]


def _children(pid: int) -> list[int]:
    """Live child processes of ``pid`` (from /proc)."""
    out = []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        if int(fields[1]) == pid:
            out.append(int(stat.parent.name))
    return out


def _wait(cond: Any, timeout_s: float, what: str, proc: subprocess.Popen[bytes], log: Path) -> None:
    deadline = time.monotonic() + timeout_s
    while not cond():
        if proc.poll() is not None:
            raise AssertionError(f"daemon exited with {proc.returncode}:\n{log.read_text()}")
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out waiting for {what}:\n{log.read_text()[-3000:]}")
        time.sleep(0.05)


def test_kill_9_then_restart_continues(
    tmp_path: Path, mosquitto_broker: Any, require_tool: Any, request: pytest.FixtureRequest
) -> None:
    cap = MqttCapture(require_tool("mosquitto_sub"), mosquitto_broker.port, tmp_path / "sub.txt")
    request.addfinalizer(cap.stop)
    cap.wait_ready(require_tool("mosquitto_pub"), mosquitto_broker.port)
    config = _config(tmp_path, mosquitto_broker.port)
    log = tmp_path / "daemon.log"
    ckpt = tmp_path / "state" / "testpack.ckpt.npz"
    first = start_daemon(config, log)
    try:
        _wait(
            lambda: any(p["t_s"] - T0_S >= 480 for p in _cell0(cap)) and ckpt.exists(),
            60,
            "480 s of data and a checkpoint",
            first,
            log,
        )
        workers = _children(first.pid)
        assert workers, "the bank worker process is missing"
    finally:
        first.send_signal(signal.SIGKILL)
        first.wait(10)
    # the bank worker does not outlive a killed daemon (no orphan computing and checkpointing)
    deadline = time.monotonic() + 5.0
    while any(Path(f"/proc/{pid}").exists() for pid in workers) and time.monotonic() < deadline:
        time.sleep(0.05)
    assert not [pid for pid in workers if Path(f"/proc/{pid}").exists()]
    # what the broker still had in flight reaches the subscriber: it belongs to the first run
    settled = -1
    while settled != len(cap.messages()):
        settled = len(cap.messages())
        time.sleep(0.3)
    first_run = _cell0(cap)
    seq_before = max(p["seq"] for _, p in cap.messages() if "seq" in p)
    n_before = len(cap.messages())
    second = start_daemon(config, log)
    try:
        _wait(
            lambda: len(_cell0(cap, n_before)) >= 3, 90, "messages after the restart", second, log
        )
        second.send_signal(signal.SIGTERM)
        assert second.wait(30) == 0
    finally:
        if second.poll() is None:
            second.kill()
        cap.stop()
    assert "restored" in log.read_text()
    after = _cell0(cap, n_before)[0]
    # sequence numbers never repeat across a crash (a gap marks it): consumers may dedupe by seq
    assert min(p["seq"] for _, p in cap.messages()[n_before:] if "seq" in p) > seq_before
    assert after["t_s"] > T0_S + 300  # continued, not restarted from the log's beginning
    settings = make_settings(tmp_path, None)
    ref = offline_estimates(demo_frames(after["t_s"] - T0_S + 0.5), settings)[after["t_s"]]
    # SOC continues: equal to the uninterrupted run, and close to the first run's value nearest
    # in sample time, by at most what SOC moved at its steepest in the first run (past its
    # first 300 s of convergence) over the time between them. The checkpoint may be older than
    # the last message before the kill (the restart then repeats a stretch) or newer (messages
    # not yet delivered at the kill): the distance is absolute, the tolerance never negative.
    assert after["soc"] == pytest.approx(float(ref.soc[0]), abs=0.005)
    nearest = min(first_run, key=lambda p: abs(p["t_s"] - after["t_s"]))
    steepest = max(
        abs(b["soc"] - a["soc"]) / (b["t_s"] - a["t_s"])
        for a, b in itertools.pairwise(first_run)
        if b["t_s"] > a["t_s"] >= T0_S + 300
    )  # 1/s
    gap_s = abs(after["t_s"] - nearest["t_s"])
    assert abs(after["soc"] - nearest["soc"]) <= 0.005 + steepest * gap_s, (nearest, after)
    # parameters carry on: the identified values, not the cell config's start values
    init = paper_cell().initial_parameters()
    assert after["R0_ohm"] == pytest.approx(float(ref.R0_ohm[0]), rel=0.02)
    assert after["tau2_s"] != init.tau2_s
    weak = next(p for t, p in cap.messages()[n_before:] if t.endswith(f"/cell/{WEAK_CELL}"))
    assert weak["R0_ohm"] > 1.3 * init.R0_ohm  # the weak cell's 3.2 mOhm, not the 2 mOhm start
    assert weak["quality"] == 1
