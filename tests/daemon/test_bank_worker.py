"""The bank worker: process and thread isolation agree; sequence numbers never repeat."""

from __future__ import annotations

import ast
import asyncio
import itertools
import json
import logging
import multiprocessing
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from daemon_helpers import drive_samples

from bmsid.config.cell import paper_cell
from bmsid.config.engine import build_bank
from bmsid.daemon import bank_worker
from bmsid.daemon.bank_worker import (
    HEARTBEAT,
    SEQ_BLOCK,
    BankHost,
    BankSpec,
    BankWorker,
    Isolation,
    samples_per_tick,
    tick_samples,
)
from bmsid.daemon.checkpoint import CheckpointKey
from bmsid.estimate.tuning import EstimatorTuning
from bmsid.samples import Sample, SampleBlock

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
    return drive_samples(t0, n, N_CELLS)


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


def _block_10hz(seconds: int) -> SampleBlock:
    """``seconds`` of 10 Hz samples, twice: the time base jumps back (beyond ``gap_s``) to its
    start halfway, so tick times repeat within the block; every sample has its own mono time."""
    rng = np.random.default_rng(3)
    n = 10 * seconds
    t = np.tile(1000.0 + 0.1 * np.arange(n), 2)
    i = 60.0 * np.sin(t / 9.0) + 30.0 * np.sign(np.sin(t / 37.0))
    v = 3.7 - 0.002 * i[:, None] + rng.normal(0.0, 5e-4, (2 * n, N_CELLS))
    return SampleBlock(
        t, i, v, t_complete_mono=np.asarray(5000.0 + 1e-3 * np.arange(t.size), np.float64)
    )


def test_each_tick_publishes_with_the_completion_time_of_its_own_sample(tmp_path: Path) -> None:
    seconds = 45  # > gap_s (30 s): the jump back is one, not a run of rejected samples
    block = _block_10hz(seconds)
    mono = block.t_complete_mono
    assert mono is not None
    # Reference: the sample at which a bank fed one sample at a time returns each tick.
    ref = build_bank(paper_cell(), N_CELLS, "hy-affrls-lpso", TUNING, soc0=0.8)
    completing = [
        k
        for k in range(len(block))
        if ref.update(float(block.t_s[k]), float(block.current_A[k]), block.cell_voltages_V[k])
        is not None
    ]
    assert len(completing) > 2 * seconds - 5  # about one tick per 10 samples
    spec = _spec(tmp_path, restore=False, keep_all_estimates=True)
    assert samples_per_tick(block.t_s, spec.tuning.id_period_s) == 10  # fed in many chunks
    host = BankHost(spec)
    host.start()
    result = host.update(block)
    assert result.counters["time_jumps_back"] == 1
    times = [e.t_s for e in result.estimates]
    assert len(set(times)) < len(times)  # tick times do repeat
    assert times == [float(block.t_s[k]) for k in completing]
    want = [float(mono[k]) for k in completing for _ in range(N_CELLS + 1)]
    assert [m.t_sample_mono for m in result.messages] == want
    # How the daemon happens to batch the samples changes nothing.
    other = BankHost(_spec(tmp_path / "b", restore=False, keep_all_estimates=True))
    other.start()
    cuts = [*range(0, len(block), 37), len(block)]
    msgs = [
        m for a, b in itertools.pairwise(cuts) for m in other.update(block.slice(a, b)).messages
    ]
    want_msgs = [(m.payload, m.t_sample_mono) for m in result.messages]
    assert [(m.payload, m.t_sample_mono) for m in msgs] == want_msgs
    # Nor does a host alone in its process, which feeds the bank many ticks per call.
    alone = BankHost(_spec(tmp_path / "c", restore=False, keep_all_estimates=True))
    alone.shares_gil = False
    alone.start()
    got = alone.update(block)
    assert [e.t_s for e in got.estimates] == times
    assert [(m.payload, m.t_sample_mono) for m in got.messages] == want_msgs


@pytest.mark.parametrize(("r_ohm", "warned"), [(0.002, False), (0.07, True)])
def test_a_cell_config_that_does_not_fit_the_pack_is_said_once(
    tmp_path: Path, caplog: pytest.LogCaptureFixture, r_ohm: float, warned: bool
) -> None:
    """A 2 Ah pack run with the default 70 Ah cell published wrong SOC and parameters for hours
    and nothing said why (a sweep). The first samples' current steps measure R0: 10x or more
    from the cell config's start R0, one WARNING names estimator.cell; near it, nothing."""
    host = BankHost(_spec(tmp_path, restore=False))
    host.start()
    with caplog.at_level(logging.WARNING, logger="bmsid.daemon.bank_worker"):
        for t0 in range(0, 1200, 100):
            block = _samples(float(t0), 100)
            v = 3.7 - r_ohm * block.current_A[:, None] + 0.0 * block.cell_voltages_V
            host.update(SampleBlock.from_arrays(block.t_s, block.current_A, v))
    said = [r.getMessage() for r in caplog.records if r.getMessage().startswith("estimator.cell")]
    assert len(said) == (1 if warned else 0), said
    if warned:
        assert (
            "the cells measure R0 70 mOhm" in said[0]
            and "is the cell config this pack's" in said[0]
        )


def test_only_the_newest_estimate_returns_unless_all_are_kept(tmp_path: Path) -> None:
    host = BankHost(_spec(tmp_path, restore=False))
    host.start()
    result = host.update(_samples(0.0, 20))
    assert [e.t_s for e in result.estimates] == [19.0]
    assert len(result.messages) == 20 * (N_CELLS + 1)


@pytest.mark.parametrize(("period_s", "beats"), [(0.0, 20), (float("inf"), 0)])
def test_a_long_update_beats_between_ticks(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, period_s: float, beats: int
) -> None:
    """The heartbeat that tells the daemon's watchdog a long call from a stuck one: between the
    ticks of an update, at most every HEARTBEAT_S (0: after each of the 20 one-sample ticks)."""
    monkeypatch.setattr(bank_worker, "HEARTBEAT_S", period_s)
    host = BankHost(_spec(tmp_path, restore=False))
    got: list[int] = []
    host.beat = lambda: got.append(1)
    host.start()
    host.update(_samples(0.0, 20))
    assert len(got) == beats


def test_heartbeats_cross_the_log_pipe_beside_the_records(caplog: pytest.LogCaptureFixture) -> None:
    """The worker process's heartbeat travels on its log pipe: the daemon's side calls
    ``on_beat`` for it and re-emits the log records around it."""
    recv, send = multiprocessing.Pipe(duplex=False)
    pipe = bank_worker._PipeQueue(send)
    record = logging.LogRecord(
        "bmsid.test", logging.WARNING, __file__, 1, "from the worker", (), None
    )
    pipe.put_nowait(record)
    pipe.put_nowait(HEARTBEAT)
    pipe.put_nowait(HEARTBEAT)
    send.close()
    beats: list[int] = []
    with caplog.at_level(logging.WARNING):
        bank_worker._forward_logs(recv, lambda: beats.append(1))  # returns at EOF
    assert beats == [1, 1]
    assert [r.getMessage() for r in caplog.records] == ["from the worker"]


@pytest.mark.parametrize("isolation", ["process", "thread"])
def test_ping_is_answered_and_counted_as_progress(tmp_path: Path, isolation: Isolation) -> None:
    """The watchdog's probe on a silent bus: an idle worker answers it; while it is out it is a
    call owed (``calls``), and its answer moves ``progress_mono``."""

    async def main() -> None:
        worker = BankWorker(_spec(tmp_path), isolation)
        try:
            await worker.start()
            before = worker.progress_mono
            probe = asyncio.create_task(worker.ping())
            await asyncio.sleep(0)
            assert worker.calls == 1
            await probe
            assert worker.calls == 0 and worker.progress_mono > before
        finally:
            worker.close()

    asyncio.run(main())


def test_tick_samples_walks_forward_over_repeated_times() -> None:
    t = np.array([0.0, 1.0, 2.0, 0.0, 1.0, 2.0, np.nan])
    assert tick_samples(t, np.array([1.0, 2.0, 0.0, 2.0])).tolist() == [1, 2, 3, 5]
    assert tick_samples(t, np.zeros(0)).tolist() == []
    with pytest.raises(ValueError, match="matches no sample"):
        tick_samples(t, np.array([2.0, 1.5]))


def test_chunks_span_one_tick() -> None:
    assert samples_per_tick(np.asarray(1.7e9 + 0.1 * np.arange(50), np.float64), 1.0) == 10
    assert samples_per_tick(np.arange(50.0), 1.0) == 1
    assert samples_per_tick(np.arange(50.0), 2.0) == 2
    assert samples_per_tick(np.array([5.0]), 1.0) == 1
    # gaps, a jump back and a missing time do not move the median sample period
    t = np.r_[0.1 * np.arange(30), 100.0 + 0.1 * np.arange(30), 0.1 * np.arange(30), np.nan]
    assert samples_per_tick(t, 1.0) == 10


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
    assert info.t_s == 19.0  # the newest sample: where a restarted replay resumes
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


def test_unwritable_state_directory_withholds_unreserved_messages(tmp_path: Path) -> None:
    blocker = tmp_path / "file"
    blocker.write_text("x")
    host = BankHost(_spec(tmp_path, ckpt_path=blocker / "sub" / "p.ckpt.npz"))
    host.start()
    result = host.update(_samples(0.0, 5))
    # no seq can be reserved: nothing is published (a restart could not know the numbers)
    assert result.messages == []
    counters = host.checkpoint(clean=True)
    assert counters["mqtt_withheld"] == 5 * (N_CELLS + 1)
    assert counters["checkpoint_errors"] == 1
    assert counters["seq_file_errors"] >= 1
    assert host.seq == 0


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


def test_bmsid_run_leaves_scipy_to_the_bank_worker() -> None:
    # `bmsid run`'s own BLAS limit (cli/main.py) must not load scipy's BLAS (~28 MB resident):
    # up to the config it reads, the daemon's process has none of scipy.
    code = """
import sys
from bmsid.cli.main import main
assert main(["run", "--config", "/nonexistent/bmsid.toml"]) == 2
print(sorted(m for m in sys.modules if m.split(".")[0] == "scipy"))
"""
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, check=True, timeout=60
    )
    assert out.stdout.strip() == "[]", out.stdout[:300]


@pytest.mark.parametrize("isolation", ["process", "thread"])
def test_the_bank_runs_every_blas_library_on_one_thread(
    tmp_path: Path, isolation: Isolation, caplog: pytest.LogCaptureFixture
) -> None:
    # A worker process starts without the daemon's limit; scipy's BLAS (the compiled kernels')
    # on two threads made a 96-cell observer update 100x slower on a busy 2-core machine.
    async def start() -> None:
        worker = BankWorker(_spec(tmp_path), isolation)
        try:
            await worker.start()
        finally:
            worker.close()

    with caplog.at_level("DEBUG"):  # the root's level: what the worker process logs at
        asyncio.run(start())
    lines = [r.getMessage() for r in caplog.records if r.getMessage().startswith("bank: BLAS")]
    assert len(lines) == 1, caplog.text[-2000:]
    threads = ast.literal_eval(lines[0].removeprefix("bank: BLAS threads "))
    assert any("scipy" in lib for lib in threads), threads
    assert set(threads.values()) == {1}, threads


def test_a_config_without_start_values_measures_them_on_the_first_samples(
    tmp_path: Path,
) -> None:
    """No [initial] and no [bounds]: the worker holds the first samples until their current
    steps give R0 (-dV/dI), then starts the bank from it and feeds what it held; a restart
    from the checkpoint rebuilds the same bank (its normalisation depends on them)."""
    cell = paper_cell().model_copy(update={"initial": None, "bounds": None})
    spec = _spec(tmp_path, cell=cell, keep_all_estimates=True)
    host = BankHost(spec)
    host.start()
    first = host.update(SampleBlock.from_samples([_sample_at(0.0, 0.0)]))
    assert first.estimates == [] and host.start_values is None  # one sample: no step yet
    pulses = [_sample_at(float(t), 40.0 * ((t // 10) % 2)) for t in range(1, 61)]
    result = host.update(SampleBlock.from_samples(pulses))  # 5 steps of 40 A
    assert host.start_values is not None
    assert host.start_values.R0_ohm == pytest.approx(2e-3, rel=0.05)  # the -0.002 V/A above
    assert result.estimates and result.estimates[0].t_s == 0.0  # the held sample fed too
    r0 = host.bank.model.start("R0_ohm")
    np.testing.assert_allclose(r0, host.start_values.R0_ohm)
    host.checkpoint(clean=True)
    again = BankHost(spec)
    assert again.start().restored
    assert again.start_values == host.start_values
    a, b = host.update(_samples(61.0, 20)), again.update(_samples(61.0, 20))
    np.testing.assert_array_equal(a.estimates[-1].R0_ohm, b.estimates[-1].R0_ohm)


def _sample_at(t: float, i: float) -> Sample:
    return Sample(t_s=t, current_A=i, cell_voltages_V=np.full(N_CELLS, 3.7 - 0.002 * i))
