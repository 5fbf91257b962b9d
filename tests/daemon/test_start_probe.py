"""A cell config without [initial]/[bounds]: the bank worker holds the first samples until
their current steps measure the start values. Measured on a 100 Hz log (sweep): nothing was
published for the whole 300 s and nothing said why; at shutdown the held samples were lost
(ticks=0, and the restart replayed the log from its start)."""

from __future__ import annotations

import asyncio
import logging
from pathlib import Path

import numpy as np
import pytest
from daemon_helpers import make_settings, run_replay

from bmsid.canbus.logs import csv_to_messages, write_log
from bmsid.canbus.mapping import default_mapping
from bmsid.config.settings import Settings
from bmsid.daemon.checkpoint import CheckpointKey, load_checkpoint
from bmsid.daemon.core import Daemon
from bmsid.estimate.types import Estimates

CELL = Path(__file__).resolve().parents[2] / "configs" / "cells" / "calce_inr18650_20r_25C.toml"
N_CELLS = 4
T0_S = 1_700_000_000.0
HOLDING = "holding samples until 3 current steps measure the start values (at most 1800 s"


def _log(path: Path, rate_hz: float, duration_s: float, steps: bool) -> float:
    """A 2 Ah pack's candump log; ``steps``: a staircase from 1.5 A down and up in 0.5 A steps
    every 10 s, each ramped over 50 ms, so that no sample-to-sample change reaches a tenth of
    the current's 95th percentile (else a constant 1 A). Returns the last sample time, s."""
    t = np.arange(0.0, duration_s, 1.0 / rate_hz)
    if steps:
        levels = 0.5 * np.array([3.0, 2.0, 1.0, 0.0, -1.0, -2.0, -3.0, -2.0, -1.0, 0.0])
        jumps = levels[(t // 10.0).astype(int) % levels.shape[0]]
        n = max(round(0.05 * rate_hz), 1)  # a moving average: each jump a 50 ms ramp
        i = np.convolve(np.concatenate([np.full(n - 1, jumps[0]), jumps]), np.ones(n) / n, "valid")
    else:
        i = np.full(t.shape[0], 1.0)
    soc = 0.8 - np.cumsum(i) / rate_hz / 7200.0
    v = 3.3 + 0.9 * soc - 0.07 * i  # OCV slope and R0 = 70 mOhm: enough for the plumbing
    volts = np.repeat(v[:, None], N_CELLS, axis=1)
    write_log(path, csv_to_messages(t, i, volts, default_mapping(), t0_s=T0_S))
    return T0_S + float(t[-1])


def _settings(tmp_path: Path, log: Path) -> Settings:
    return make_settings(
        tmp_path,
        None,
        can={"n_cells": N_CELLS, "replay": {"log": str(log), "speed": 1000.0}},
        estimator={"cell": str(CELL), "soc0": 0.8},
    )


def _run(settings: Settings) -> tuple[list[float], list[float]]:
    """Sample times of the ticks seen before the stop was asked for, and of all of them."""
    seen: list[float] = []
    before_stop: list[float] = []

    def on_estimates(e: Estimates) -> None:
        seen.append(e.t_s)

    async def main() -> None:
        daemon = Daemon(settings, on_estimates=on_estimates)
        stop = daemon.request_stop

        def stop_and_note() -> None:
            before_stop.extend(seen)
            stop()

        daemon.request_stop = stop_and_note  # type: ignore[method-assign]
        await run_replay(daemon)

    asyncio.run(main())
    return before_stop, seen


def test_100_hz_replay_measures_start_values_and_publishes_before_the_stop(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    log = tmp_path / "r100.log"
    _log(log, 100.0, 90.0, steps=True)
    with caplog.at_level(logging.INFO):
        before_stop, _ = _run(_settings(tmp_path, log))
    # ticks from the measured start values, long before 1800 s of samples were held
    assert before_stop and min(before_stop) < T0_S + 90.0
    said = [r.getMessage() for r in caplog.records]
    assert sum(HOLDING in m for m in said) == 1
    assert any(m.startswith("start values from the first") for m in said)


def test_samples_held_at_stop_go_through_the_bank_not_lost(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """No current step in the log: the stop releases the held samples with the fallback start
    values, and the checkpoint resumes after the last of them."""
    log = tmp_path / "flat.log"
    t_last = _log(log, 1.0, 60.0, steps=False)
    settings = _settings(tmp_path, log)
    with caplog.at_level(logging.INFO):
        before_stop, seen = _run(settings)
    assert not before_stop  # held while the replay ran: too few steps
    assert seen and max(seen) == pytest.approx(t_last, abs=1.0)
    assert any(HOLDING in r.getMessage() for r in caplog.records)
    ck = load_checkpoint(settings.state.directory / "testpack.ckpt.npz", _key(settings))
    assert ck is not None and ck.extra["t_s"] == pytest.approx(t_last)


def _key(settings: Settings) -> CheckpointKey:
    return Daemon(settings).ckpt_key  # the key the daemon saved under
