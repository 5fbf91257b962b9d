"""The bank worker: process and thread isolation agree; sequence numbers never repeat."""

from __future__ import annotations

import asyncio
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from bmsid.config.cell import paper_cell
from bmsid.daemon.bank_worker import SEQ_BLOCK, BankHost, BankSpec, BankWorker, Isolation
from bmsid.daemon.checkpoint import CheckpointKey
from bmsid.daemon.sample_queue import SampleBlock
from bmsid.estimate.tuning import EstimatorTuning
from bmsid.samples import Sample

N_CELLS = 4
TUNING = EstimatorTuning(min_window_s=60.0, window_s=120.0, swarm_period_s=40.0)


def _spec(tmp_path: Path, **kw: object) -> BankSpec:
    base: dict[str, object] = {
        "cell": paper_cell(),
        "n_cells": N_CELLS,
        "variant": "hy-affrls-lpso",
        "tuning": TUNING,
        "soc0": 0.8,
        "restore": True,
        "ckpt_path": tmp_path / "p.ckpt.npz",
        "ckpt_key": CheckpointKey("p", N_CELLS, "h"),
        "pack_id": "p",
        "topic_prefix": "bmsid",
        "mqtt_enabled": True,
        "qos": 1,
        "publish_period_s": 0.0,
    }
    return BankSpec(**(base | kw))  # type: ignore[arg-type]


def _samples(t0: float, n: int) -> SampleBlock:
    rng = np.random.default_rng(int(t0))
    out = []
    for k in range(n):
        t = t0 + k
        i = 60.0 * np.sin(t / 9.0) + 30.0 * np.sign(np.sin(t / 37.0))
        v = 3.7 - 0.002 * i + rng.normal(0.0, 5e-4, N_CELLS)
        out.append(Sample(t_s=t, current_A=float(i), cell_voltages_V=v))
    return SampleBlock.from_samples(out, [0.0] * n)


async def _run(spec: BankSpec, isolation: Isolation, batches: int) -> list[bytes]:
    worker = BankWorker(spec, isolation)
    try:
        await worker.start()
        payloads: list[bytes] = []
        for b in range(batches):
            result = await worker.update(_samples(1000.0 + 50 * b, 50))
            payloads += [m.payload for m in result.messages]
        await worker.checkpoint(clean=True)
        return payloads
    finally:
        worker.close()


def test_process_and_thread_isolation_publish_identical_messages(tmp_path: Path) -> None:
    a = asyncio.run(_run(_spec(tmp_path / "a"), "process", 6))
    b = asyncio.run(_run(_spec(tmp_path / "b"), "thread", 6))
    assert len(a) == 6 * 50 * (N_CELLS + 1)  # every tick: each cell and the pack
    assert a == b
    assert json.loads(a[-1])["seq"] == len(a) - 1


def test_sequence_continues_after_clean_stop_and_jumps_after_crash(tmp_path: Path) -> None:
    spec = _spec(tmp_path)
    host = BankHost(spec)
    assert host.start().seq == 0
    host.update(_samples(0.0, 20))
    used = host.seq
    assert used > 0
    host.checkpoint(clean=True)
    # graceful restart: contiguous
    again = BankHost(spec)
    info = again.start()
    assert info.restored and info.seq == used
    again.update(_samples(20.0, 10))
    crashed_at = again.seq
    again.checkpoint(clean=False)  # periodic checkpoint, then "kill -9"
    after_crash = BankHost(spec).start().seq
    assert after_crash > crashed_at  # never reuses a number consumers may have seen
    assert after_crash <= used + SEQ_BLOCK


def test_sequence_survives_a_fresh_estimator_state(tmp_path: Path) -> None:
    host = BankHost(_spec(tmp_path, restore=False))
    host.start()
    host.update(_samples(0.0, 20))
    host.checkpoint(clean=True)
    other = BankHost(_spec(tmp_path, restore=False, ckpt_key=CheckpointKey("p", N_CELLS, "new")))
    # a config change discards the estimator state but not the numbering
    assert other.start().seq == host.seq


def test_unwritable_state_directory_is_counted_not_fatal(tmp_path: Path) -> None:
    blocker = tmp_path / "file"
    blocker.write_text("x")
    host = BankHost(_spec(tmp_path, ckpt_path=blocker / "sub" / "p.ckpt.npz"))
    host.start()
    result = host.update(_samples(0.0, 5))
    assert result.messages  # publishing goes on
    counters = host.checkpoint(clean=True)
    assert counters["checkpoint_errors"] == 1
    assert counters["seq_file_errors"] >= 1


@pytest.mark.parametrize("isolation", ["process", "thread"])
def test_worker_logs_reach_the_parent(
    tmp_path: Path, isolation: Isolation, caplog: pytest.LogCaptureFixture
) -> None:
    spec = _spec(tmp_path)
    spec.ckpt_path.write_bytes(b"not a checkpoint")

    async def start() -> None:
        worker = BankWorker(spec, isolation)
        try:
            assert not (await worker.start()).restored
        finally:
            worker.close()

    with caplog.at_level("WARNING"):
        asyncio.run(start())
    assert "unreadable" in caplog.text


def test_daemon_process_does_not_load_the_estimator_stack() -> None:
    # With process isolation only the worker needs the bank (scipy.signal: ~65 MB resident);
    # a gateway pays for it once, not twice. `bmsid run` must not load the other commands either.
    code = """
import sys
from bmsid.cli.main import _requested_command, build_parser
from bmsid.config.settings import Settings
from bmsid.daemon.core import Daemon
build_parser(_requested_command(["-v", "run", "--config", "x.toml"]))  # as `bmsid -v run` does
Daemon(Settings(pack_id="p", can={"interface": "virtual", "channel": "x", "n_cells": 96}))
print(sorted(m for m in sys.modules if m.split(".")[0] == "scipy" or m == "bmsid.estimate.bank"))
"""
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, check=True, timeout=60
    )
    assert out.stdout.strip() == "[]", out.stdout[:300]
