"""What the fault tests share: the bundled 8-cell log with a fault put in, and its truth."""

from __future__ import annotations

import functools
import importlib
import sys
from pathlib import Path
from types import ModuleType

import numpy as np
import numpy.typing as npt

from bmsid.canbus.logs import csv_to_messages, write_log
from bmsid.canbus.mapping import default_mapping
from bmsid.config.cell import paper_cell
from bmsid.config.engine import ocv_model
from bmsid.daemon import demo_data as dd
from bmsid.estimate.types import EstimateBlock
from bmsid.model.simulator import simulate
from bmsid.profiles import dst_current

FloatArray = npt.NDArray[np.float64]
#: The issue's targets: every estimate within these of the truth (as on the intact log).
R0_REL_TOL = 0.03
SOC_TOL = 0.02


def daemon_helpers() -> ModuleType:
    """``tests/daemon/daemon_helpers.py`` (tests/ is no package: its folder goes on the path,
    as pytest puts it there when the daemon tests are collected in the same run)."""
    folder = str(Path(__file__).resolve().parents[1] / "daemon")
    if folder not in sys.path:
        sys.path.append(folder)
    return importlib.import_module("daemon_helpers")


@functools.cache
def demo_truth() -> tuple[FloatArray, FloatArray]:
    """(t_s from the log's start, true SOC (n,)) of the demo pack (all cells share the SOC)."""
    cell = paper_cell()
    t = np.arange(0.0, dd.DURATION_S, 1.0 / dd.RATE_HZ)
    i = np.where(t < dd.REST_S, 0.0, dst_current(t - dd.REST_S, dd.PEAK_C * cell.capacity_Ah))
    sim = simulate(
        t, i, ocv_model(cell), capacity_Ah=cell.capacity_Ah, R0_ohm=dd.R0_OHM,
        R1_ohm=dd.R1_OHM, tau1_s=dd.TAU1_S, R2_ohm=dd.R2_OHM, tau2_s=dd.TAU2_S,
        gamma=cell.hysteresis.gamma, soc0=dd.SOC0, n_sets=dd.N_CELLS,
    )  # fmt: skip
    return t, np.asarray(sim.soc, dtype=np.float64)


def write_dropout_log(path: Path, cell: int, level_V: float, start_s: int, n_s: int) -> Path:
    """The demo log with ``cell`` reading ``level_V`` for ``n_s`` samples from ``start_s``."""
    t, i, v = dd.demo_arrays()
    v = v.copy()
    v[start_s : start_s + n_s, cell] = level_V
    write_log(path, csv_to_messages(t, i, v, default_mapping(), t0_s=dd.T0_S))
    return path


def write_log_without_line(path: Path, line: int) -> Path:
    """The demo log with its ``line`` (1-based) deleted: one lost frame."""
    lines = dd.DEMO_LOG.read_text(encoding="ascii").splitlines(keepends=True)
    path.write_text("".join(lines[: line - 1] + lines[line:]), encoding="ascii")
    return path


def assert_within_targets(trace: EstimateBlock) -> None:
    """Final R0 of every cell within 3 % of the truth and SOC within 2 points at every tick
    where a cell publishes one (the issue's targets; the intact log: 0.11 % and 0.11 points)."""
    t, soc = demo_truth()
    k = np.clip(np.searchsorted(t, trace.t_s - dd.T0_S), 0, t.shape[0] - 1)
    err = np.abs(trace["soc"] - soc[k][:, None])
    published = np.isfinite(trace["soc"])
    assert np.all(err[published] <= SOC_TOL), np.nanmax(err, axis=0)
    r0 = trace["R0_ohm"][-1]
    assert np.all(np.abs(r0 / dd.R0_OHM - 1.0) <= R0_REL_TOL), r0 / dd.R0_OHM - 1.0
