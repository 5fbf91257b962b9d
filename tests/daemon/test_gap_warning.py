"""A gap in the samples that resumes under load (data lost mid-drive, a clock that jumped):
the daemon says so in one WARNING line and counts it in its status (``gaps_under_load``,
``reanchors``), as ``bmsid identify`` says it offline (sweep G: it said nothing). A cell whose
readings stop is said once too (``readings_lost``) and published ``no_data`` while they are
missing (sweep G: 10 min of refused readings published as ``converged``)."""

from __future__ import annotations

import asyncio
import logging
from pathlib import Path

import numpy as np
import pytest
from daemon_helpers import make_settings, run_replay

from bmsid.canbus.logs import csv_to_messages, write_log
from bmsid.canbus.mapping import default_mapping
from bmsid.daemon.core import Daemon
from bmsid.estimate.types import Quality

CELL = Path(__file__).resolve().parents[2] / "configs" / "cells" / "calce_inr18650_20r_25C.toml"
N_CELLS = 4
T0_S = 1_700_000_000.0
SAID = "a gap in the samples (over 30 s) resumed under load"


def _log(path: Path, gap: tuple[float, float] | None, cell_lost: bool = False) -> None:
    """A 2 Ah pack at 1 Hz: 60 s of rest, then 1.5 A steps down and up every 10 s; the samples
    within ``gap`` (s) left out (the pack drives on through it), or with ``cell_lost`` cell 2's
    readings sent as not-available within it."""
    t = np.arange(0.0, 600.0)
    i = np.where(t < 60, 0.0, 1.0 + 0.5 * np.sign(np.sin(2 * np.pi * t / 20.0)))
    soc = 0.8 - np.cumsum(i) / 7200.0
    v = 3.3 + 0.9 * soc - 0.07 * i
    keep = np.ones(t.shape, dtype=bool) if gap is None else ~((t >= gap[0]) & (t < gap[1]))
    volts = np.repeat(v[:, None], N_CELLS, axis=1)
    if cell_lost and gap is not None:
        volts[~keep, 2] = np.nan
        keep[:] = True
    volts = volts[keep]
    write_log(path, csv_to_messages(t[keep], i[keep], volts, default_mapping(), t0_s=T0_S))


def _run(
    tmp_path: Path, gap: tuple[float, float] | None, cell_lost: bool = False
) -> tuple[dict[str, float], list[tuple[float, int]]]:
    log = tmp_path / "pack.log"
    _log(log, gap, cell_lost)
    settings = make_settings(
        tmp_path, None, can={"n_cells": N_CELLS, "replay": {"log": str(log), "speed": 1000.0}},
        estimator={"cell": str(CELL), "soc0": 0.8},
    )  # fmt: skip

    async def main() -> tuple[dict[str, float], list[tuple[float, int]]]:
        daemon = Daemon(settings)
        quality: list[tuple[float, int]] = []  # cell 2's published (time s, quality)
        daemon.on_estimates = lambda est: quality.append((est.t_s - T0_S, int(est.quality[2])))
        await run_replay(daemon)
        return daemon.snapshot(), quality

    return asyncio.run(main())


@pytest.mark.parametrize("gap", [None, (300.0, 400.0)])
def test_a_gap_that_resumes_under_load_is_said_and_counted(
    tmp_path: Path, caplog: pytest.LogCaptureFixture, gap: tuple[float, float] | None
) -> None:
    with caplog.at_level(logging.WARNING):
        counters, _ = _run(tmp_path, gap)
    said = sum(SAID in r.getMessage() for r in caplog.records)
    if gap is None:
        assert said == 0 and counters["gaps_under_load"] == 0, counters
        return
    assert said == 1 and counters["gaps_under_load"] == 1 and counters["reanchors"] == 1, (
        said, counters,
    )  # fmt: skip


def test_a_cell_whose_readings_stop_is_said_and_published_no_data(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    with caplog.at_level(logging.WARNING):
        counters, quality = _run(tmp_path, (300.0, 400.0), cell_lost=True)
    said = [r.getMessage() for r in caplog.records if "no valid voltage for 30 s" in r.getMessage()]
    assert len(said) == 1 and counters["readings_lost"] == 1, (said, counters)
    t, q = np.array(quality).T
    # 300..399 s without cell 2's reading: no_data from 30 s on, live again after
    lost = (t > 331.0) & (t < 400.0)
    # (the daemon publishes the newest estimate of each batch: how many fall there depends on
    # the machine's speed)
    assert lost.sum() >= 1 and np.all(q[lost] == Quality.NO_DATA), quality
    assert not np.any(q[(t < 329.0) | (t > 401.0)] == Quality.NO_DATA), quality
