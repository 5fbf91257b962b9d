"""What offline identification writes and says: metrics.json, the plots and the report lines.

``params.csv`` is appended block by block while the bank runs
(:class:`~bmsid.offline.writers.ParamsCsvWriter`); everything here needs the whole run and is
written once at its end. Apart from the files it is given, pure.
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np

from bmsid.config.cell import CellConfig
from bmsid.config.engine import ocv_model
from bmsid.errors import UserError
from bmsid.offline.plots import plot_parameters, plot_voltage
from bmsid.offline.scoring import EvalWindow, IdentifyResult, score

#: Help of the ``--score-soc0`` option (``identify``, ``compare``): what the reference SOC is.
SCORE_SOC0_HELP = (
    "score the --soc-window and the SOC bands on a coulomb count of the measured current "
    "(+ = discharge) from this SOC (fraction) at the first sample, with the cell config's "
    "capacity and coulombic efficiency, instead of on the estimator's SOC; e.g. 1.0 for a test "
    "that starts full"
)

#: Cells plotted one by one; a larger pack shows its first and its worst cell.
MAX_PLOTTED_CELLS = 4

#: ``auto``: every cell up to MAX_PLOTTED_CELLS (``voltage_<cell>.png`` each when there are
#: several), else the first and the worst; ``first``: the first cell only, as ``voltage.png``.
PlotCells = Literal["auto", "first"]


@dataclass(frozen=True)
class OutputSpec:
    """What a run writes into its output directory besides metrics.json.

    Attributes
    ----------
    params_csv : bool
        Write ``params.csv`` (one row per tick and cell).
    plots : {"auto", "first"}
        Which cells get the Fig. 10/11 plots (see ``PlotCells``).
    title : str or None
        Plot title; None: ``"<input file name> - <variant>"``.
    metadata : dict
        Extra keys of metrics.json after the metrics (e.g. ``input``, ``cell_config``).
    """

    params_csv: bool = True
    plots: PlotCells = "auto"
    title: str | None = None
    metadata: Mapping[str, Any] = field(default_factory=dict)


def prepare_out_dir(out: Path) -> None:
    """Create ``out`` (and parents); UserError when it exists as something else."""
    if out.exists() and not out.is_dir():
        raise UserError(f"--out {out} exists and is not a directory")
    out.mkdir(parents=True, exist_ok=True)


def write_metrics_json(doc: Mapping[str, Any], path: Path) -> None:
    """``doc`` as indented JSON (NaN for an empty window, as Python's json writes it)."""
    path.write_text(json.dumps(doc, indent=2) + "\n", encoding="utf-8")


def plotted_cells(result: IdentifyResult, window: EvalWindow) -> list[int]:
    """All cells up to MAX_PLOTTED_CELLS, else the first and the worst (window RMSE)."""
    nc = result.trace.n_cells
    if nc <= MAX_PLOTTED_CELLS:
        return list(range(nc))
    rmse = [m.rmse_V for m in score(result.trace, window).per_cell_window]
    return sorted({0, int(np.argmax(rmse))})


def write_plots(
    result: IdentifyResult, window: EvalWindow, out: Path, title: str, cells: PlotCells = "auto"
) -> None:
    """Fig. 10 (``parameters.png``) and Fig. 11 (``voltage*.png``) of the chosen cells."""
    tr, names = result.trace, result.cell_names
    if tr.n_ticks == 0:
        return  # nothing to draw
    if cells == "first":
        plot_parameters(tr, [0], names, out / "parameters.png", title)
        plot_voltage(tr, 0, names[0], out / "voltage.png", title)
        return
    chosen = plotted_cells(result, window)
    plot_parameters(tr, chosen, names, out / "parameters.png", title)
    for c in chosen:
        file = "voltage.png" if tr.n_cells == 1 else f"voltage_{names[c]}.png"
        plot_voltage(tr, c, names[c], out / file, title)


# ----------------------------------------------------------------------------- report lines
def soc_init_text(result: IdentifyResult) -> str:
    """One line: the initial SOC of the first cells (%) and how it was found."""
    z0 = result.trace["soc"][0] if result.trace.n_ticks else np.array([math.nan])
    socs = ", ".join(f"{100 * z:.1f} %" for z in z0[:4]) + (" ..." if z0.size > 4 else "")
    how = {
        "given": "given by --soc0",
        "ocv_at_rest": "from the first voltage through the OCV curve (the cell was at rest)",
        "ocv_ir_corrected": "from the first voltage plus R0 x current through the OCV curve "
        "(a current flowed; the SOC observer refines it)",
        "config": "the config's soc0 (soc_init.policy fixed)",
        "pending": "none: no cell carried a valid voltage",
    }.get(result.soc_init_method, result.soc_init_method)
    return f"initial SOC {socs}: {how}"


def observer_text(result: IdentifyResult) -> str | None:
    """One line: what the SOC observer found at the end of the record (None when off)."""
    tr = result.trace
    if tr.n_ticks == 0 or not np.isfinite(tr["soc_std"][-1]).any():
        return None
    q, q_sd = tr["capacity_Ah"][-1], tr["capacity_std_Ah"][-1]
    caps = ", ".join(f"{a:.3g} +- {b:.2g} Ah" for a, b in zip(q[:4], q_sd[:4], strict=True))
    return (
        f"SOC observer: current-sensor offset {tr['current_offset_A'][-1][0]:+.3g} A, "
        f"SOC std {100 * float(np.max(tr['soc_std'][-1])):.2f} points, capacity {caps}"
        + (" ..." if q.size > 4 else "")
    )


def ocv_range_warning(result: IdentifyResult, cell: CellConfig) -> str | None:
    """A warning when SOC was read off the OCV curve at one of its ends: the first voltage lies
    outside the curve's range, so SOC is clamped and the OCV model is off by the difference."""
    if result.soc_init_method != "ocv_at_rest" or result.trace.n_ticks == 0:
        return None
    ocv = ocv_model(cell)
    lo, hi = cell.ocv.soc_min, cell.ocv.soc_max
    v_lo, v_hi = float(ocv.ocv(np.array(lo))), float(ocv.ocv(np.array(hi)))
    v0 = result.trace["v_meas_V"][0]
    outside = [
        f"{name} {v:.4f} V"
        for name, v in zip(result.cell_names, v0, strict=True)
        if v > v_hi + 1e-3 or v < v_lo - 1e-3
    ]
    if not outside:
        return None
    return (
        f"warning: first voltage outside the OCV curve ({v_lo:.4f}-{v_hi:.4f} V over SOC "
        f"{100 * lo:g}-{100 * hi:g} %): {', '.join(outside[:4])}; SOC is clamped and the model "
        "starts with that OCV error"
    )


def summary_line(doc: Mapping[str, Any]) -> str:
    """One line of a metrics.json document: the whole record's errors (mV, %), the start-up's and
    the rest's RMSE (mV), the evaluation window's when one was asked for, and the run time (s)."""
    o, s, a = doc["overall"], doc["startup"], doc["after_startup"]
    first = f"{100 * doc['startup_fraction']:g} %"
    text = (
        f"{doc['algorithm']}: RMSE {1e3 * o['rmse_V']:.2f} mV over all {o['n_samples']} ticks "
        f"(max {1e3 * o['max_abs_error_V']:.1f} mV, MAPE {o['mape_pct']:.3f} %); "
        f"first {first} {1e3 * s['rmse_V']:.2f} mV, after it {1e3 * a['rmse_V']:.2f} mV"
    )
    w = doc["evaluation_window"]
    if w["skip_fraction"] or w["soc_lo"] is not None or w["soc_hi"] is not None:
        text += (
            f"; window ({w['description']}) {1e3 * doc['rmse_V']:.2f} mV over "
            f"{doc['n_samples']} ticks (max {1e3 * doc['max_abs_error_V']:.1f} mV)"
        )
    return f"{text}; run time {doc['runtime_s']:.1f} s"
