"""What offline identification writes and says: metrics.json, the plots and the report lines.

``params.csv`` (or ``params.parquet``) is appended block by block while the bank runs
(:mod:`bmsid.offline.writers`), every tick or one row per ``every_s`` interval
(:func:`auto_every_s` picks one for long records); everything here is written once at the run's
end from what the run accumulated (:class:`~bmsid.offline.scoring.RunScorer`: running sums and
the plots' min-max decimation). Apart from the files it is given, pure.
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np
import numpy.typing as npt

from bmsid.config.cell import CellConfig
from bmsid.config.engine import ocv_model
from bmsid.errors import UserError
from bmsid.estimate.arrhenius import B_PRIOR_K, MAX_PAIR_DSOC, MIN_DT_K, R_GAS
from bmsid.estimate.start_fit import WINDOW_S as START_WINDOW_S
from bmsid.model.ocv import OcvModel
from bmsid.offline.accumulate import PLOT_SERIES
from bmsid.offline.scoring import (
    EvalWindow,
    IdentifyResult,
    current_dependence_warnings,
    held_warnings,
    lone_cell_warnings,
    past_empty_warnings,
)
from bmsid.offline.writers import EveryMode, ParamsFormat

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
FloatArray = npt.NDArray[np.float64]

#: Records with more ticks than this get a decimated parameter table by default: one day of
#: 1 s ticks, which a spreadsheet or a pandas session still opens whole (86,400 rows per cell).
AUTO_EVERY_MAX_ROWS = 86_400
#: The intervals the default decimation picks from, s.
AUTO_EVERY_STEPS_S = (2.0, 5.0, 10.0, 20.0, 30.0, 60.0, 120.0, 300.0, 600.0, 900.0, 1800.0, 3600.0)


def auto_every_s(n_ticks: int, duration_s: float) -> float | None:
    """The default ``--every`` of a record: None (every tick) up to ``AUTO_EVERY_MAX_ROWS``
    ticks, else the shortest of ``AUTO_EVERY_STEPS_S`` that leaves at most that many rows per
    cell over ``duration_s`` (s). The estimates move over tens of seconds and more (tau1 ~30 s,
    tau2 ~10 min, forgetting windows of minutes), so 5-30 s rows keep their course; a 3-day
    1 s record gets 5 s, a 30-day one 30 s."""
    if n_ticks <= AUTO_EVERY_MAX_ROWS:
        return None
    need = duration_s / AUTO_EVERY_MAX_ROWS
    return next((s for s in AUTO_EVERY_STEPS_S if s >= need), AUTO_EVERY_STEPS_S[-1])


@dataclass(frozen=True)
class OutputSpec:
    """What a run writes into its output directory besides metrics.json.

    Attributes
    ----------
    params_csv : bool
        Write the parameter table (one row per tick, or per ``every_s``, and cell).
    params_format : {"csv", "parquet"}
        ``params.csv`` or ``params.parquet`` (same columns and units).
    every_s : float or None
        One row per interval of this many seconds; 0: every tick; None: the default
        (:func:`auto_every_s`, announced; every tick when the run is not streamed).
    every_mode : {"last", "mean"}
        Per interval the last tick's values or the mean of its ticks.
    plots : {"auto", "first"}
        Which cells get the Fig. 10/11 plots (see ``PlotCells``).
    title : str or None
        Plot title; None: ``"<input file name> - <variant>"``.
    metadata : dict
        Extra keys of metrics.json after the metrics (e.g. ``input``, ``cell_config``).
    """

    params_csv: bool = True
    params_format: ParamsFormat = "csv"
    every_s: float | None = None
    every_mode: EveryMode = "last"
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
    nc = len(result.cell_names)
    if nc <= MAX_PLOTTED_CELLS:
        return list(range(nc))
    rmse = [m.rmse_V for m in result.scorer(window).scores().per_cell_window]
    return sorted({0, int(np.argmax(rmse))})


def write_plots(
    result: IdentifyResult, window: EvalWindow, out: Path, title: str, cells: PlotCells = "auto"
) -> None:
    """Fig. 10 (``parameters.png``) and Fig. 11 (``voltage*.png``) of the chosen cells, drawn
    from the run's min-max decimation (every tick of a record up to ``PLOT_BINS`` ticks)."""
    # matplotlib only now: pyplot is ~40 MB of resident memory a run's estimation never needs
    from bmsid.offline.plots import plot_parameters, plot_voltage  # noqa: PLC0415

    names = result.cell_names
    if result.n_ticks == 0:
        return  # nothing to draw
    plot = result.scorer(window).acc.plot

    def series(name: str, cell: int) -> tuple[FloatArray, FloatArray]:
        return plot.series(PLOT_SERIES.index(name), cell)

    if cells == "first":
        plot_parameters(series, [0], names, out / "parameters.png", title)
        plot_voltage(series, 0, names[0], out / "voltage.png", title)
        return
    chosen = plotted_cells(result, window)
    plot_parameters(series, chosen, names, out / "parameters.png", title)
    for c in chosen:
        file = "voltage.png" if len(names) == 1 else f"voltage_{names[c]}.png"
        plot_voltage(series, c, names[c], out / file, title)


# ----------------------------------------------------------------------------- report lines
def soc_init_text(result: IdentifyResult, rest_limit_A: float | None = None) -> str:
    """One line: the initial SOC of the first cells (%) and how it was found; ``rest_limit_A``
    (the cell's ``soc_init.rest_current_C`` x capacity, A) is named when given: "at rest" means
    within it, which an assumed capacity far too large makes true of a real load."""
    first = result.first_tick()
    z0 = first["soc"][0] if first is not None else np.array([math.nan])
    socs = ", ".join(f"{100 * z:.1f} %" if math.isfinite(z) else "no data" for z in z0[:4])
    socs += " ..." if z0.size > 4 else ""
    rest = (
        "the cell was at rest"
        if rest_limit_A is None
        else f"the first current within the rest limit, |I| <= {rest_limit_A:.3g} A"
    )
    how = {
        "given": "given by --soc0",
        "ocv_at_rest": f"from the first voltage through the OCV curve ({rest})",
        "ocv_ir_corrected": "from the first voltage plus R0 x current through the OCV curve "
        "(a current flowed; the SOC observer refines it)",
        "config": "the config's soc0 (soc_init.policy fixed)",
        "window_fit": f"fitted with the model over the record's first {START_WINDOW_S / 60:.0f} "
        "min (it opens under load or still relaxing, which the first voltage misreads, or at "
        "rest after a charge or discharge whose hysteresis state the window shows; the SOC "
        "observer refines it)",
        "pending": "none: no cell carried a valid voltage",
    }.get(result.soc_init_method, result.soc_init_method)
    b = result.start_branch_V
    if b is not None and np.any(b):  # under load or relaxing: what the RC branches held
        volts = ", ".join(f"{1e3 * u:.1f} mV" for u in b[:4]) + (" ..." if b.size > 4 else "")
        also = (
            ""
            if result.soc_init_method == "window_fit"
            else f" (fitted over the first {START_WINDOW_S / 60:.0f} min)"
        )
        how += f"; RC branches from {volts}{also}"
    if (h := result.start_h) is not None:  # at rest after a charge or discharge
        states = ", ".join(f"{x:+.2f}" for x in h[:4]) + (" ..." if h.size > 4 else "")
        how += f"; hysteresis state {states} (-1 after a discharge, +1 after a charge)"
    return f"initial SOC {socs}: {how}"


#: A start fit that misses its window by more than this (V RMS) is warned about: the fitted
#: voltages' noise is ~1 mV; 5 mV is a model that does not follow the cell there.
START_FIT_MISFIT_V = 0.005


def start_fit_warning(result: IdentifyResult, ocv: OcvModel) -> str | None:
    """A line when the start SOC was fitted over the first minutes (``window_fit``) and the
    fit missed them by more than ``START_FIT_MISFIT_V``: that start is as uncertain as the
    misfit through the OCV's slope, which the published ``soc_std`` (the start taken as a
    given value) does not carry. A PyBaMM cell entered mid-drive at -10 degC: 13.7 mV, the
    start 13 points low for two hours at a std of 1 point."""
    rmse = result.start_fit_rmse_V
    first = result.first_tick()
    if result.soc_init_method != "window_fit" or rmse is None or first is None:
        return None
    worst = int(np.nanargmax(np.where(np.isfinite(rmse), rmse, -1.0)))
    if not rmse[worst] > START_FIT_MISFIT_V:
        return None
    z0 = float(first["soc"][0][worst])
    slope = float(np.abs(ocv.docv_dz(np.array([z0])))[0])
    off = round(100 * float(rmse[worst]) / slope) if slope > 0 else 0
    pts = f"about {off} point{'' if off == 1 else 's'}" if off else "points"
    return (
        f"WARNING: {result.cell_names[worst]}: the start SOC fitted over the first "
        f"{START_WINDOW_S / 60:.0f} min misses them by {1e3 * float(rmse[worst]):.1f} mV RMS (the "
        f"model does not follow the cell there: a cold cell, a start far from rest): the start "
        f"may be {pts} off, more than its published soc_std says; give --soc0 when the start "
        "is known"
    )


#: A start SOC read off a voltage with a std above this (fraction) is warned about.
START_STD_WARN = 0.05


def start_std_warning(result: IdentifyResult) -> str | None:
    """A line when the start SOC read off the first voltage is uncertain by more than
    ``START_STD_WARN`` (its published ``soc_std``): on a flat OCV (an LFP plateau) the unknown
    hysteresis state and relaxation move that SOC by points, and whatever the observer has not
    corrected the slow branch takes (a 280 Ah LFP cell rested after a charge, at 60 %: read
    75.4 %, std 21 points, R2 +141 %, no line)."""
    first = result.first_tick()
    if result.soc_init_method not in ("ocv_at_rest", "ocv_ir_corrected") or first is None:
        return None
    std = np.asarray(first["soc_std"][0], dtype=np.float64)
    if not np.any(std > START_STD_WARN):
        return None
    c = int(np.nanargmax(std))
    return (
        f"WARNING: {result.cell_names[c]}: the start SOC read off the first voltage "
        f"({100 * float(first['soc'][0][c]):.1f} %) is uncertain by +-{100 * float(std[c]):.0f}"
        " points (the OCV is flat there: the unknown hysteresis state, after a charge or a "
        "discharge, and any relaxation move it that far); until a long rest or the curve's "
        "knees settle it, the slow RC branch takes what is left: give --soc0 when the start "
        "is known"
    )


def gaps_under_load_warning(result: IdentifyResult) -> str | None:
    """A line when gaps in the data resumed under load (the observer's ``gaps_under_load``):
    data lost mid-drive, or a clock that jumped, never a rest; the charge moved there is
    unknown and SOC was re-anchored from the voltage after each (a clock set an hour ahead
    mid-drive read as "1 gap(s) > 30 s" and nothing more)."""
    n = result.counters.get("gaps_under_load", 0)
    if not n:
        return None
    return (
        f"WARNING: {n} gap(s) in the data resumed under load (data lost mid-drive, or a clock "
        "that jumped): the charge moved in them is unknown, and SOC was re-anchored from the "
        "voltage after each"
    )


def readings_lost_warning(result: IdentifyResult) -> str | None:
    """A line when a cell went ``gap_s`` without a valid voltage mid-record (the bank's
    ``readings_lost``): its rows are ``no_data`` until a reading returns, not the held
    estimate they were (a blank column in a tester's export, every reading of a cell refused)."""
    n = result.counters.get("readings_lost", 0)
    if not n:
        return None
    return (
        f"WARNING: {n} time(s) a cell went longer than gap_s (30 s by default) without a valid "
        "voltage (blank in the input, or every reading refused by the gates): its rows are "
        "no_data (empty) until a valid reading returned"
    )


#: (code, line) of a run's warning: the code for a fleet's summary.csv, the line for the console
Warned = list[tuple[str, str]]


def start_warnings(result: IdentifyResult, ocv: OcvModel) -> Warned:
    """A finished run's warnings on its start and its gaps (said after the start line)."""
    found = (
        ("start_fit_misfit", start_fit_warning(result, ocv)),
        ("start_uncertain", start_std_warning(result)),
        ("gaps_under_load", gaps_under_load_warning(result)),
        ("readings_lost", readings_lost_warning(result)),
    )
    return [(code, line) for code, line in found if line is not None]


def fit_warnings(result: IdentifyResult, window: EvalWindow) -> Warned:
    """A finished run's warnings on its fit over ``window`` (said after its summary)."""
    return [
        *(("held", line) for line in held_warnings(result, window)),
        *(("lone_cell", line) for line in lone_cell_warnings(result, window)),
        *(("current_dependence", line) for line in current_dependence_warnings(result, window)),
        *(("past_empty", line) for line in past_empty_warnings(result, window)),
    ]


def observer_text(result: IdentifyResult) -> str | None:
    """One line: what the SOC observer found at the end of the record (None when off)."""
    tr = result.last_tick()
    if tr is None or not np.isfinite(tr["soc_std"][-1]).any():
        return None
    q, q_sd = tr["capacity_Ah"][-1], tr["capacity_std_Ah"][-1]
    caps = ", ".join(f"{a:.3g} +- {b:.2g} Ah" if math.isfinite(a) else "no data"
                     for a, b in zip(q[:4], q_sd[:4], strict=True))  # fmt: skip
    offset = tr["current_offset_A"][-1]  # one per pack; NaN in a no_data cell's column
    return (
        f"SOC observer: current-sensor offset {float(np.nanmax(offset)):+.3g} A, "
        f"SOC std {100 * float(np.nanmax(tr['soc_std'][-1])):.2f} points, capacity {caps}"
        + (" ..." if q.size > 4 else "")
    )


def temperature_law_text(result: IdentifyResult) -> str | None:
    """One line: the temperature law's activation energy (None where the temperature did not
    move): learnt from pairs of window fits, or the prior where none was 1 K apart at one SOC."""
    ea = result.activation_energy_J_mol
    if ea is None:
        return None
    pairs = result.counters.get("arrhenius_pairs", 0)
    how = (f"learnt from {pairs} pair(s) of window fits" if pairs else
           f"the prior: no two window fits {MIN_DT_K:g} K apart within "
           f"{100 * MAX_PAIR_DSOC:g} SOC points")  # fmt: skip
    vals = ", ".join(f"{x / 1e3:.1f}" for x in ea[:4]) + (" ..." if ea.size > 4 else "")
    prior = B_PRIOR_K * R_GAS / 1e3
    return f"temperature law (R0): activation energy {vals} kJ/mol, {how} (prior {prior:g})"


def ocv_range_warning(result: IdentifyResult, cell: CellConfig) -> str | None:
    """A warning when SOC was read off the OCV curve at one of its ends: the first voltage lies
    outside the curve's range, so SOC is clamped and the OCV model is off by the difference."""
    first = result.first_tick()
    if result.soc_init_method != "ocv_at_rest" or first is None:
        return None
    ocv = ocv_model(cell)
    # the model's range: with the config's rested empty / full voltages the curve's end segments
    # reach 0 and 100 % (A123 DYN50 opens at 3.575 V, above the Eq. 4 fit's 98 % but on the curve)
    lo, hi = ocv.soc_min, ocv.soc_max
    v_lo, v_hi = float(ocv.ocv(np.array(lo))), float(ocv.ocv(np.array(hi)))
    v0 = first["v_meas_V"][0]
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
    if not o["n_samples"]:
        return (
            f"{doc['algorithm']}: no RMSE: no tick of the {doc['n_ticks']} had a valid cell "
            "voltage and a model voltage to compare (every cell no_data); nothing was "
            f"identified; run time {doc['runtime_s']:.1f} s"
        )
    first = f"{100 * doc['startup_fraction']:g} %"
    text = (
        f"{doc['algorithm']}: RMSE {1e3 * o['rmse_V']:.2f} mV over all {o['n_samples']} ticks "
        f"(max {1e3 * o['max_abs_error_V']:.1f} mV, MAPE {o['mape_pct']:.3f} %); "
        f"first {first} {_rmse_mv(s)}, after it {_rmse_mv(a)}"
    )
    w = doc["evaluation_window"]
    if doc["rmse_V"] is None:
        text += f"; window ({w['description']}): no tick scored"
    elif w["skip_fraction"] or w["soc_lo"] is not None or w["soc_hi"] is not None:
        text += (
            f"; window ({w['description']}) {1e3 * doc['rmse_V']:.2f} mV over "
            f"{doc['n_samples']} ticks (max {1e3 * doc['max_abs_error_V']:.1f} mV)"
        )
    return f"{text}; run time {doc['runtime_s']:.1f} s"


#: A SOC band holding this share of the record's squared model error is named on the console.
BAND_SHARE = 0.5
#: ... when its RMSE is also this many times the other bands'.
BAND_RATIO = 3.0


def error_band_line(doc: Mapping[str, Any]) -> str | None:
    """A line naming the 10 % SOC band (metrics.json ``soc_bands``) that holds ``BAND_SHARE`` of
    the squared model error or more with ``BAND_RATIO`` times the others' RMSE, else None: a
    whole-record RMSE that is mostly a knee or the end of a discharge reads as a poor fit
    throughout (CALCE 25 C DST from 80 %: 13.49 mV over all, 39.5 mV at SOC 0-10 %)."""
    bands = [b for b in doc.get("soc_bands", []) if b["n_samples"] and b["rmse_V"] is not None]
    if len(bands) < 2:
        return None
    sse = [b["n_samples"] * b["rmse_V"] ** 2 for b in bands]
    j = int(np.argmax(sse))
    total, n_rest = sum(sse), sum(b["n_samples"] for b in bands) - bands[j]["n_samples"]
    rest = math.sqrt((total - sse[j]) / n_rest)
    if not (total > 0 and sse[j] >= BAND_SHARE * total and bands[j]["rmse_V"] >= BAND_RATIO * rest):
        return None
    return (
        f"most of the model error lies at SOC {bands[j]['band']}: {1e3 * bands[j]['rmse_V']:.1f} "
        f"mV RMSE over its {bands[j]['n_samples']} ticks, {100 * sse[j] / total:.0f} % of the "
        f"squared error; {1e3 * rest:.2f} mV over the other {n_rest} (metrics.json soc_bands)"
    )


def _rmse_mv(part: Mapping[str, Any]) -> str:
    """A part's RMSE in mV, or why there is none (a part without a scored tick has null)."""
    return "no tick" if part["rmse_V"] is None else f"{1e3 * part['rmse_V']:.2f} mV"
