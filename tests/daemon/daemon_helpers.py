"""Builders shared by the daemon tests: demo frames, settings, offline reference, MQTT capture."""

from __future__ import annotations

import asyncio
import functools
import json
import os
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

import can
import numpy as np

from bmsid.canbus.encoder import CLASSIC_PAGES, PACK_PAGES
from bmsid.canbus.frames_to_samples import FrameToSamples
from bmsid.canbus.logs import read_log
from bmsid.canbus.mapping import default_mapping
from bmsid.config.engine import build_bank
from bmsid.config.settings import Settings
from bmsid.daemon.core import Daemon
from bmsid.daemon.demo_data import DEMO_LOG, N_CELLS
from bmsid.estimate.types import Estimates
from bmsid.samples import Sample, SampleBlock

SCHEMA_DIR = Path(__file__).resolve().parents[2] / "service" / "bmsid" / "publish" / "schemas"
#: Short swarm windows so the LPSO fusion runs within a few hundred seconds of data.
FAST_TUNING = {"min_window_s": 120.0, "window_s": 300.0, "swarm_period_s": 150.0}


@functools.cache
def _demo_frames() -> tuple[can.Message, ...]:
    return tuple(read_log(DEMO_LOG))


def demo_frames(duration_s: float) -> list[can.Message]:
    """Fresh copies of the bundled demo log's frames of the first ``duration_s`` seconds."""
    frames = _demo_frames()
    t0 = frames[0].timestamp
    return [
        can.Message(
            timestamp=m.timestamp,
            arbitration_id=m.arbitration_id,
            is_extended_id=m.is_extended_id,
            data=bytes(m.data),
        )
        for m in frames
        if m.timestamp - t0 < duration_s
    ]


def start_daemon(config: Path, log: Path, new_session: bool = False) -> subprocess.Popen[bytes]:
    """``bmsid run --config CONFIG`` as a separate process (the way a gateway runs it), its
    output appended to ``log`` (so restarts of one test share a log); ``new_session``: in a
    session of its own, so that signals can go to its whole process group (a terminal's
    hang-up, systemd's cgroup kill)."""
    env = {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[2] / "service")}
    with log.open("ab") as fh:
        return subprocess.Popen(
            [sys.executable, "-m", "bmsid.cli.main", "-v", "run", "--config", str(config)],
            stdout=fh,
            stderr=subprocess.STDOUT,
            env=env,
            cwd=config.parent,
            start_new_session=new_session,
        )


def make_settings(tmp_path: Path, port: int | None, **sections: Any) -> Settings:
    """Settings for a virtual-bus daemon (channel unique per test), MQTT on ``port``."""
    data: dict[str, Any] = {
        "pack_id": "testpack",
        "status_period_s": 0.5,
        "systemd_notify": False,
        "can": {
            "interface": "virtual",
            "channel": f"t{time.monotonic_ns()}",
            "n_cells": N_CELLS,
            "output_period_s": 0.05,
        },
        "estimator": {"tuning": dict(FAST_TUNING)},
        "mqtt": {
            "enabled": port is not None,
            "url": f"mqtt://127.0.0.1:{port or 1883}",
            "publish_period_s": 0.0,
            "reconnect_min_s": 0.1,
            "reconnect_max_s": 0.5,
        },
        "state": {"directory": str(tmp_path / "state"), "checkpoint_period_s": 1.0},
    }
    for name, values in sections.items():
        if isinstance(values, dict) and isinstance(data.get(name), dict):
            data[name] = {**data[name], **values}
        else:
            data[name] = values
    return Settings(**data)


def offline_estimates(frames: list[can.Message], settings: Settings) -> dict[float, Estimates]:
    """What the bank computes from the same frames, offline: tick time -> estimates."""
    f2s = FrameToSamples(default_mapping(), settings.can.n_cells, settings.can.staleness_s)
    est_cfg = settings.estimator
    bank = build_bank(
        est_cfg.load_cell(),
        settings.can.n_cells,
        est_cfg.variant,
        est_cfg.tuning,
        soc0=est_cfg.soc0,
    )
    samples = [s for m in frames for s in f2s.feed(m)]
    if not samples:
        return {}
    return {e.t_s: e for e in bank.update_block(SampleBlock.from_samples(samples)).rows()}


class MqttCapture:
    """``mosquitto_sub`` (the independent peer) writing ``topic payload`` lines to a file."""

    def __init__(
        self,
        exe: str,
        port: int,
        path: Path,
        topic: str = "bmsid/#",
        persistent_id: str | None = None,
    ) -> None:
        self.path = path
        args = [exe, "-h", "127.0.0.1", "-p", str(port), "-t", topic, "-v", "-q", "1"]
        if persistent_id is not None:
            args += ["-c", "-i", persistent_id]
        args += ["-t", "probe/#"]
        self._fh = path.open("wb")
        self.proc = subprocess.Popen(args, stdout=self._fh, stderr=subprocess.STDOUT)

    def wait_ready(self, pub_exe: str, port: int, timeout_s: float = 10.0) -> None:
        """Publish probes until one comes back: the subscription is in place."""
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            subprocess.run(
                [pub_exe, "-h", "127.0.0.1", "-p", str(port), "-t", "probe/x", "-m", "probe"],
                check=False,
                timeout=5,
            )
            time.sleep(0.1)
            if b"probe/x" in self.path.read_bytes():
                return
        raise AssertionError(f"mosquitto_sub did not subscribe: {self.path.read_text()}")

    def messages(self, prefix: str = "bmsid/") -> list[tuple[str, dict[str, Any]]]:
        """Every complete line so far (mosquitto_sub may be half-way through the last one)."""
        out = []
        text = self.path.read_text(encoding="utf-8", errors="replace")
        for line in text[: text.rfind("\n") + 1].splitlines():
            topic, _, payload = line.partition(" ")
            if topic.startswith(prefix):
                out.append((topic, json.loads(payload)))
        return out

    def stop(self) -> None:
        if self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(5)
            except subprocess.TimeoutExpired:
                self.proc.kill()
        self._fh.close()


def send_virtual(channel: str, frames: list[can.Message], pace_s: float = 0.0) -> threading.Thread:
    """Send ``frames`` on a virtual channel (log timestamps kept) from a thread."""

    def run() -> None:
        bus = can.Bus(interface="virtual", channel=channel, preserve_timestamps=True)
        try:
            for k, m in enumerate(frames):
                bus.send(m)
                if pace_s and k % 3 == 2:
                    time.sleep(pace_s)
        finally:
            bus.shutdown()

    th = threading.Thread(target=run, daemon=True)
    th.start()
    return th


async def wait_for(cond: Any, timeout_s: float, what: str) -> None:
    deadline = time.monotonic() + timeout_s
    while not cond():
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out after {timeout_s} s waiting for {what}")
        await asyncio.sleep(0.02)


async def full_can_output_cycle(daemon: Daemon, timeout_s: float = 30.0) -> None:
    """Wait until every cell's parameter frames went out again after this call, plus one round:
    a round already under way may carry the previous tick's estimates."""
    per_round = daemon.cycler.per_round
    rounds = -(-daemon.cycler.n_cells // per_round) + 1
    frames_per_cell = 1 if daemon.settings.can.output_fd else len(CLASSIC_PAGES)
    frames_per_round = len(PACK_PAGES) + per_round * frames_per_cell  # pack frames, then cells'
    target = daemon.counters["can_frames_sent"] + rounds * frames_per_round
    await wait_for(
        lambda: daemon.counters["can_frames_sent"] >= target, timeout_s, "a full CAN output cycle"
    )


def all_published(daemon: Daemon, n_frames: int) -> bool:
    """``daemon`` has read ``n_frames`` frames, estimated every sample and handed every message
    to the broker (safe to call from another thread: it only reads)."""
    q = daemon._samples
    done = (
        daemon.f2s.counters["frames"] >= n_frames
        and q is not None
        and q.empty()
        and daemon.counters["batches_in_flight"] == 0
    )
    if daemon.outbox is not None:
        done = done and len(daemon.outbox) == 0
    return done


async def run_with_frames(
    daemon: Daemon,
    frames: list[can.Message],
    *,
    pace_s: float = 0.0,
    during: Any = None,
    after: Any = None,
    timeout_s: float = 120.0,
) -> None:
    """Run ``daemon``, feed ``frames`` on its virtual channel, wait until all is processed and
    published, stop it. ``during(daemon)`` (async) runs while the frames flow, ``after(daemon)``
    (async) once everything is processed, before the stop."""
    task = asyncio.create_task(daemon.run())
    await wait_for(lambda: daemon.can_state == "up" or task.done(), 20, "the bus")
    if daemon.mqtt is not None:
        await wait_for(lambda: daemon.mqtt is not None and daemon.mqtt.connected, 20, "MQTT")
    sender = send_virtual(daemon.settings.can.channel, frames, pace_s)
    if during is not None:
        await during(daemon)
    n = len(frames)

    def drained() -> bool:
        return (not sender.is_alive() and all_published(daemon, n)) or task.done()

    await wait_for(drained, timeout_s, "the frames to be processed and published")
    if after is not None:
        await after(daemon)
    daemon.request_stop()
    assert await asyncio.wait_for(task, 60) == 0


def assert_matches_offline(payload: dict[str, Any], est: Estimates) -> None:
    """Every published value equals the offline estimate exactly (JSON keeps float repr)."""
    i = payload["cell"]
    for key, attr in (
        ("R0_ohm", "R0_ohm"),
        ("R1_ohm", "R1_ohm"),
        ("R2_ohm", "R2_ohm"),
        ("C1_F", "C1_F"),
        ("C2_F", "C2_F"),
        ("tau1_s", "tau1_s"),
        ("tau2_s", "tau2_s"),
        ("lambda", "lambda_"),
        ("h", "h"),
        ("soc", "soc"),
        ("M_V", "M_V"),
        ("v_model_V", "v_model_V"),
    ):
        want = float(getattr(est, attr)[i])
        assert payload[key] == want, (key, payload["t_s"], i, payload[key], want)
    assert payload["quality"] == int(est.quality[i])


def contiguous(seqs: list[int]) -> bool:
    u = np.unique(seqs)
    return bool(u.size and u[-1] - u[0] + 1 == u.size)


def drive_samples(t0: float, n: int, n_cells: int) -> SampleBlock:
    """``n`` 1 s samples of a drive-like current (A) and a plain ohmic cell response (V) for
    ``n_cells`` cells, reproducible from ``t0``: bank-worker plumbing tests, not accuracy."""
    rng = np.random.default_rng(int(t0))
    out = []
    for k in range(n):
        t = t0 + k
        i = 60.0 * np.sin(t / 9.0) + 30.0 * np.sign(np.sin(t / 37.0))
        v = 3.7 - 0.002 * i + rng.normal(0.0, 5e-4, n_cells)
        out.append(Sample(t_s=t, current_A=float(i), cell_voltages_V=v))
    return SampleBlock.from_samples(out, [0.0] * n)


async def run_replay(daemon: Daemon, timeout_s: float = 120.0) -> None:
    """Run ``daemon`` on its ``can.replay`` log until every frame is processed, then stop it."""
    task = asyncio.create_task(daemon.run())
    await wait_for(lambda: daemon.idle() or task.done(), timeout_s, "the replay to be processed")
    daemon.request_stop()
    assert await asyncio.wait_for(task, 60) == 0
