"""Fault injection, cells without data (issue 16, items 1-2, measured cases 1 and 6): a cell's
state starts from its own first valid reading, never a fallback; until then it publishes "no
data" (quality ``no_data``, every field null), and configured cells that never appear on the
bus are reported as missing, not published. Time: ~25 s (one offline run, two short daemon
runs on the virtual bus with a real Mosquitto)."""

from __future__ import annotations

import asyncio
import json
import logging
from pathlib import Path
from typing import Any

import jsonschema
import numpy as np
import pytest
from gate_fault_helpers import (
    SOC_TOL,
    assert_within_targets,
    daemon_helpers,
    demo_truth,
    write_log_without_line,
)

from bmsid.config.cell import paper_cell
from bmsid.config.engine import build_bank
from bmsid.daemon import demo_data as dd
from bmsid.daemon.core import Daemon
from bmsid.estimate import jit
from bmsid.estimate.types import Quality
from bmsid.offline.identify import IdentifySpec, identify_file
from bmsid.samples import SampleBlock

NO_DATA = int(Quality.NO_DATA)
dh = daemon_helpers()


def test_cell_starts_at_its_own_first_valid_voltage() -> None:
    bank = build_bank(paper_cell(), 2)
    ocv = bank.model.ocv
    first = bank.update(0.0, 0.0, [3.9, np.nan])
    assert first is not None
    assert first.quality.tolist()[1] == NO_DATA
    assert all(np.isnan(first.cells[k][1]) for k in first.cells)  # nothing invented
    assert first.quality[0] != NO_DATA and np.isfinite(first.soc[0])
    bank.update(1.0, 35.0, [3.88, np.nan])  # the pack current flows: counted for cell 0 only
    z0_before = float(bank.state.z[0])
    second = bank.update(2.0, 0.0, [3.89, 3.95])
    assert second is not None and second.quality[1] != NO_DATA
    # from its own voltage at rest (not 0.5, not a count from t = 0)
    assert second.soc[1] == pytest.approx(float(ocv.soc_from_ocv(np.array([3.95]))[0]))
    assert bank.state.z[0] < z0_before + 1e-12  # cell 0 kept its count
    assert bank.soc_init_method == "ocv_at_rest"


@pytest.mark.parametrize("kernels", ["numpy", "compiled"])
@pytest.mark.parametrize("how", ["soc0", "config"])
def test_a_dead_voltage_tap_publishes_no_data_when_the_start_soc_is_given(
    kernels: str, how: str
) -> None:
    """Found by a sweep: with --soc0 (or a fixed start in the config) every cell started at
    once, a tap reading 0 V for the whole record too, which was then published as a normal
    cell (quality converging, start values, a counted SOC). A cell publishes only once it has
    read a valid voltage, however its SOC starts; until then (here never) ``no_data``."""
    cell = paper_cell()
    if how == "config":
        cell = cell.model_copy(
            update={"soc_init": cell.soc_init.model_copy(update={"policy": "fixed", "soc0": 0.8})}
        )
    before = jit.MODE
    try:
        jit.select(kernels)
        bank = build_bank(cell, 3, soc0=0.8 if how == "soc0" else None)
        t = np.arange(0.0, 1200.0)
        i = np.where((t // 60) % 2 == 0, 35.0, 0.0)
        # the input gate refuses a 0 V tap: the bank sees no reading (NaN) from it
        v = np.stack([3.9 - 0.002 * i, np.full_like(t, np.nan), 3.9 - 0.0021 * i], axis=1)
        out = bank.update_block(SampleBlock.from_arrays(t, i, v))
    finally:
        jit.restore(before)
    assert out.n_ticks > 1000
    assert np.all(out.quality[:, 1] == NO_DATA)
    assert all(np.all(np.isnan(col[:, 1])) for col in out.cells.values())
    assert not np.any(out.quality[:, [0, 2]] == NO_DATA)
    assert np.all(np.isfinite(out.cells["soc"][:, [0, 2]]))


def test_lost_frame_at_start_up_defaults_no_cell(tmp_path: Path) -> None:
    """Measured case 1: line 3 of the bundled log deleted (cells 4-7 of the first cycle).
    Before: cells 4-7 started at SOC 0.5 and stayed there (39 points off, tau2 on its 8,000 s
    bound, ``converged``). Now: no data for one tick, then from their own first voltage."""
    res = identify_file(
        write_log_without_line(tmp_path / "lost.log", 3), IdentifySpec(paper_cell())
    )
    tr = res.trace
    assert res.soc_init_method == "ocv_at_rest"
    assert tr.quality[0].tolist() == [
        NO_DATA if c >= 4 else int(tr.quality[0][c]) for c in range(8)
    ]
    assert all(np.all(np.isnan(tr.cells[k][0, 4:])) for k in tr.cells)
    assert not np.any(tr.quality[1:] == NO_DATA)
    assert_within_targets(tr)
    _, soc = demo_truth()
    assert np.all(np.abs(tr["soc"][1, 4:] - soc[1]) <= SOC_TOL)  # from data at the first chance
    assert np.all(np.abs(tr["tau2_s"][-1] / dd.TAU2_S - 1.0) <= 0.25)


def _kind(topic: str) -> str:
    return "cell" if "/cell/" in topic else topic.rsplit("/", 1)[-1]


@pytest.fixture
def capture(tmp_path: Path, mosquitto_broker: Any, require_tool: Any) -> Any:
    cap = dh.MqttCapture(require_tool("mosquitto_sub"), mosquitto_broker.port, tmp_path / "sub.txt")
    cap.wait_ready(require_tool("mosquitto_pub"), mosquitto_broker.port)
    yield cap
    cap.stop()


def _run(settings: Any, frames: list[Any]) -> Daemon:
    async def main() -> Daemon:
        daemon = Daemon(settings)
        await dh.run_with_frames(daemon, frames)
        return daemon

    return asyncio.run(main())


def _validated(capture: Any) -> list[tuple[str, dict[str, Any]]]:
    capture.stop()
    msgs: list[tuple[str, dict[str, Any]]] = capture.messages()
    for topic, payload in msgs:
        schema = json.loads((dh.SCHEMA_DIR / f"{_kind(topic)}.json").read_text())
        jsonschema.Draft202012Validator(schema).validate(payload)
    return msgs


def test_phantom_cells_are_missing_not_invented(
    tmp_path: Path, mosquitto_broker: Any, capture: Any, caplog: pytest.LogCaptureFixture
) -> None:
    """Measured case 6: ``n_cells`` 10 on the 8-cell log. Before: cells 8-9 published as SOC
    0.5 drifting with the current, and the pack's soc_min taken from one of them."""
    settings = dh.make_settings(
        tmp_path, mosquitto_broker.port, can={"n_cells": 10}, estimator={"isolation": "thread"}
    )
    with caplog.at_level(logging.WARNING):
        daemon = _run(settings, dh.demo_frames(90.0))
    msgs = _validated(capture)
    cells = [p for t, p in msgs if _kind(t) == "cell"]
    packs = [p for t, p in msgs if _kind(t) == "pack"]
    assert cells and packs
    assert {p["cell"] for p in cells} == set(range(8))  # never a message for cells 8, 9
    soc_at = {(p["t_s"], p["cell"]): p["soc"] for p in cells}
    for p in packs:
        assert p["missing_cells"] == [8, 9]
        assert p["quality_counts"]["no_data"] == 2
        assert p["health"] & 8  # input missing
        assert p["soc_min"] == min(soc_at[(p["t_s"], c)] for c in range(8))
    status = json.loads(daemon._online_payload())  # what the next status would carry
    jsonschema.validate(status, json.loads((dh.SCHEMA_DIR / "status.json").read_text()))
    assert status["inputs"]["missing_cells"] == [8, 9]
    assert status["inputs"]["no_data_cells"] == [8, 9]
    assert status["counters"]["gated_v_window"] == 0
    told = [r.getMessage() for r in caplog.records if "never on the bus" in r.getMessage()]
    assert told == [
        "cells 8, 9 (0-based) configured but never on the bus: reported as missing_cells, "
        "not published as cells (check can.n_cells)"
    ]
    assert daemon.latest is not None and daemon.latest.quality[8:].tolist() == [NO_DATA] * 2


def test_lost_frame_at_start_up_publishes_no_data_then_truth(
    tmp_path: Path, mosquitto_broker: Any, capture: Any
) -> None:
    """Measured case 1 live: the daemon publishes cells 4-7 of the first tick as no data
    (every field null), then their SOC from their own first voltage; never a default."""
    frames = dh.demo_frames(60.0)
    del frames[2]  # line 3 of the log: cells 4-7 of the first cycle
    settings = dh.make_settings(tmp_path, mosquitto_broker.port, estimator={"isolation": "thread"})
    _run(settings, frames)
    cells = [p for t, p in _validated(capture) if _kind(t) == "cell"]
    t_first = min(p["t_s"] for p in cells)
    first = {p["cell"]: p for p in cells if p["t_s"] == t_first}
    for c in range(4, 8):
        assert first[c]["quality_name"] == "no_data"
        assert first[c]["soc"] is None and first[c]["R0_ohm"] is None
    assert all(first[c]["quality_name"] != "no_data" for c in range(4))
    t, soc = demo_truth()
    later = [p for p in cells if p["t_s"] > t_first]
    assert later and all(p["quality_name"] != "no_data" for p in later)
    k = np.clip(np.searchsorted(t, np.array([p["t_s"] for p in later]) - dd.T0_S), 0, len(t) - 1)
    err = np.abs(np.array([p["soc"] for p in later]) - soc[k])
    assert np.all(err <= SOC_TOL), err.max()
