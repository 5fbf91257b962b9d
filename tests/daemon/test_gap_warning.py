"""A gap in the samples that resumes under load (data lost mid-drive, a clock that jumped):
the daemon says so in one WARNING line and counts it in its status (``gaps_under_load``,
``reanchors``), as ``bmsid identify`` says it offline (sweep G: it said nothing)."""

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

CELL = Path(__file__).resolve().parents[2] / "configs" / "cells" / "calce_inr18650_20r_25C.toml"
N_CELLS = 4
T0_S = 1_700_000_000.0
SAID = "a gap in the samples resumed under load"


def _log(path: Path, gap: tuple[float, float] | None) -> None:
    """A 2 Ah pack at 1 Hz: 60 s of rest, then 1.5 A steps down and up every 10 s; the samples
    within ``gap`` (s) left out (the pack drives on through it)."""
    t = np.arange(0.0, 600.0)
    i = np.where(t < 60, 0.0, 1.0 + 0.5 * np.sign(np.sin(2 * np.pi * t / 20.0)))
    soc = 0.8 - np.cumsum(i) / 7200.0
    v = 3.3 + 0.9 * soc - 0.07 * i
    keep = np.ones(t.shape, dtype=bool) if gap is None else ~((t >= gap[0]) & (t < gap[1]))
    volts = np.repeat(v[keep, None], N_CELLS, axis=1)
    write_log(path, csv_to_messages(t[keep], i[keep], volts, default_mapping(), t0_s=T0_S))


def _run(tmp_path: Path, gap: tuple[float, float] | None) -> dict[str, float]:
    log = tmp_path / "pack.log"
    _log(log, gap)
    settings = make_settings(
        tmp_path, None, can={"n_cells": N_CELLS, "replay": {"log": str(log), "speed": 1000.0}},
        estimator={"cell": str(CELL), "soc0": 0.8},
    )  # fmt: skip

    async def main() -> dict[str, float]:
        daemon = Daemon(settings)
        await run_replay(daemon)
        return daemon.snapshot()

    return asyncio.run(main())


@pytest.mark.parametrize("gap", [None, (300.0, 400.0)])
def test_a_gap_that_resumes_under_load_is_said_and_counted(
    tmp_path: Path, caplog: pytest.LogCaptureFixture, gap: tuple[float, float] | None
) -> None:
    with caplog.at_level(logging.WARNING):
        counters = _run(tmp_path, gap)
    said = sum(SAID in r.getMessage() for r in caplog.records)
    if gap is None:
        assert said == 0 and counters["gaps_under_load"] == 0, counters
        return
    assert said == 1 and counters["gaps_under_load"] == 1 and counters["reanchors"] == 1, (
        said, counters,
    )  # fmt: skip
