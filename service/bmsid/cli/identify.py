"""``bmsid identify INPUT --out DIR``: identify a recording offline, write parameters, metrics
and plots.

INPUT is a tester CSV (``t_s,current_A,voltage_V`` or ``v_cell_01,...``, optional
``temperature_C``, ``.csv`` or ``.csv.gz``) or a candump log (``.log``, decoded with ``--mapping``
exactly as the daemon decodes the bus). Writes ``DIR/params.csv`` (one row per identification
tick and cell; with the default 1 s tick that is one row per sample of a 1 s recording),
``DIR/metrics.json`` (Eq. 31 over the evaluation window, and over all ticks under ``overall``)
and PNG plots (parameters over time as the paper's Fig. 10, voltage and error as Fig. 11).

Evaluation window: by default the first 10 % of the ticks (convergence from the start values)
are not scored; ``--soc-window 0.15,0.95`` scores only ticks whose SOC lies in that range instead.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np
from pydantic import ValidationError
from tqdm import tqdm

from bmsid.canbus.logs import samples_from_log
from bmsid.canbus.mapping import default_mapping, load_mapping
from bmsid.config.cell import CellConfig, OcvCurve, load_cell_config, paper_cell
from bmsid.errors import UserError
from bmsid.estimate.tuning import EstimatorTuning, Variant
from bmsid.estimate.types import VARIANTS
from bmsid.model.ocv import OcvModel
from bmsid.offline.csvio import read_tester_csv
from bmsid.offline.identify import (
    EvalWindow,
    FloatArray,
    IdentifyResult,
    Progress,
    metrics_document,
    run_arrays,
    samples_to_arrays,
    score,
)
from bmsid.offline.plots import plot_parameters, plot_voltage

#: params.csv columns after ``t_s,cell`` and the trace field each comes from.
PARAM_COLUMNS = (
    ("R0_ohm", "R0_ohm", "%.6g"),
    ("R1_ohm", "R1_ohm", "%.6g"),
    ("C1_F", "C1_F", "%.6g"),
    ("R2_ohm", "R2_ohm", "%.6g"),
    ("C2_F", "C2_F", "%.6g"),
    ("tau1_s", "tau1_s", "%.6g"),
    ("tau2_s", "tau2_s", "%.6g"),
    ("lambda", "lambda_", "%.6f"),
    ("h", "h", "%.5f"),
    ("soc", "soc", "%.6f"),
    ("v_model_V", "v_model_V", "%.6f"),
    ("v_meas_V", "v_meas_V", "%.6f"),
)
MAX_PLOTTED_CELLS = 4


# ----------------------------------------------------------------------------- shared options
def add_model_options(p: argparse.ArgumentParser) -> None:
    """Options ``identify`` and ``compare`` share: tuning, window, current sign."""
    p.add_argument(
        "--tuning",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="override an EstimatorTuning field, repeatable (e.g. identify_ocv_offset=true)",
    )
    p.add_argument(
        "--soc-window",
        default=None,
        metavar="LO,HI",
        help="score only ticks with SOC in [LO, HI] (fractions, e.g. 0.15,0.95)",
    )
    p.add_argument(
        "--skip-fraction",
        type=float,
        default=None,
        help="fraction of the first ticks not scored (default 0.1, or 0 with --soc-window)",
    )
    p.add_argument(
        "--charge-positive", action="store_true", help="the input counts charge current positive"
    )


def parse_tuning(items: list[str]) -> EstimatorTuning:
    values: dict[str, str] = {}
    for item in items:
        key, sep, val = item.partition("=")
        if not sep or not key.strip():
            raise UserError(f"--tuning: {item!r} is not KEY=VALUE")
        if key.strip() not in EstimatorTuning.model_fields:
            raise UserError(f"--tuning: unknown field {key.strip()!r} of EstimatorTuning")
        values[key.strip()] = val.strip()
    try:
        return EstimatorTuning.model_validate(values)
    except ValidationError as exc:
        err = exc.errors()[0]
        where = ".".join(str(x) for x in err["loc"]) or "tuning"
        raise UserError(f"--tuning {where}: {err['msg']}") from None


def parse_window(soc_window: str | None, skip_fraction: float | None) -> EvalWindow:
    lo = hi = None
    if soc_window is not None:
        parts = soc_window.split(",")
        try:
            lo, hi = (float(x) for x in parts)
        except ValueError:
            raise UserError(f"--soc-window: expected LO,HI fractions, got {soc_window!r}") from None
        if lo > 1.0 or hi > 1.0:
            raise UserError("--soc-window takes fractions (0.15,0.95), not percent")
    skip = skip_fraction if skip_fraction is not None else (0.1 if soc_window is None else 0.0)
    try:
        return EvalWindow(skip_fraction=skip, soc_lo=lo, soc_hi=hi)
    except ValueError as exc:
        raise UserError(str(exc)) from None


def load_config(path: str | Path) -> CellConfig:
    try:
        return load_cell_config(path)
    except FileNotFoundError:
        raise UserError(f"cell config not found: {path}") from None
    except ValidationError as exc:
        err = exc.errors()[0]
        where = ".".join(str(x) for x in err["loc"])
        raise UserError(f"{path}: invalid cell config at {where}: {err['msg']}") from None
    except (OSError, ValueError) as exc:
        raise UserError(f"{path}: cannot read the cell config: {exc}".splitlines()[0]) from None


@contextmanager
def progress_bar(total: int, desc: str) -> Iterator[Progress]:
    """A tqdm bar on stderr when it is a terminal, silent when piped (``disable=None``)."""
    bar = tqdm(total=total, desc=desc, unit="sample", disable=None, leave=False, file=sys.stderr)

    def update(n: int) -> None:
        bar.update(n)

    try:
        yield update
    finally:
        bar.close()


# ----------------------------------------------------------------------------- identify
def register(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = subparsers.add_parser(
        "identify",
        help="identify a tester CSV or candump log offline; write params, metrics, plots",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("input", metavar="INPUT", help="tester CSV (.csv/.csv.gz) or candump .log")
    p.add_argument("--out", required=True, metavar="DIR", help="output directory")
    p.add_argument("--algorithm", choices=VARIANTS, default="hy-affrls-lpso")
    p.add_argument("--cell-config", default=None, metavar="FILE", help="cell config .toml/.json")
    p.add_argument("--capacity-ah", type=float, default=None, help="override the capacity, Ah")
    p.add_argument("--soc0", type=float, default=None, help="initial SOC, fraction (0..1)")
    p.add_argument(
        "--ocv-coeffs",
        default=None,
        metavar="a0,a1,a2,a3,a4,a5",
        help="override the mean OCV curve (Eq. 4 coefficients, V)",
    )
    p.add_argument("--mapping", default=None, help="bus mapping TOML for .log input")
    p.add_argument("--n-cells", type=int, default=1, help="cells in a .log input (default 1)")
    add_model_options(p)
    p.set_defaults(func=run)


def build_cell(args: argparse.Namespace) -> tuple[CellConfig, str]:
    """The cell config and a note on where it came from."""
    if args.cell_config is not None:
        cell = load_config(args.cell_config)
        note = f"cell config {args.cell_config}"
    else:
        cell = paper_cell()
        note = "no --cell-config: the paper's cell (Table 1 OCV, 15 mV hysteresis)"
        if args.capacity_ah is not None:
            cell = cell.model_copy(update={"initial": None})  # capacity-scaled start values
    update: dict[str, Any] = {}
    if args.capacity_ah is not None:
        if not (math.isfinite(args.capacity_ah) and 0 < args.capacity_ah <= 10_000):
            raise UserError(f"--capacity-ah must lie in (0, 10000], got {args.capacity_ah:g}")
        update["capacity_Ah"] = float(args.capacity_ah)
        note += f", capacity {args.capacity_ah:g} Ah"
    if args.ocv_coeffs is not None:
        try:
            coeffs = [float(x) for x in args.ocv_coeffs.split(",")]
        except ValueError:
            raise UserError(f"--ocv-coeffs: not numbers: {args.ocv_coeffs!r}") from None
        if len(coeffs) != 6 or not all(math.isfinite(c) for c in coeffs):
            raise UserError("--ocv-coeffs needs six finite numbers a0,a1,a2,a3,a4,a5")
        update["ocv"] = OcvCurve(mean=coeffs, soc_min=cell.ocv.soc_min, soc_max=cell.ocv.soc_max)
        note += ", OCV from --ocv-coeffs"
    if update:
        cell = CellConfig.model_validate({**cell.model_dump(), **update})
    return cell, note


def load_input(
    path: str, args: argparse.Namespace
) -> tuple[FloatArray, FloatArray, FloatArray, list[str]]:
    """(t_s, current_A, voltages (n, n_cells), cell names) of a tester CSV or a candump log."""
    if path.lower().endswith(".log"):
        if args.n_cells < 1:
            raise UserError(f"--n-cells must be >= 1, got {args.n_cells}")
        if not Path(path).is_file():
            raise UserError(f"{path}: no such file")
        mapping = load_mapping(args.mapping) if args.mapping else default_mapping()
        samples = samples_from_log(path, mapping, args.n_cells)
        t, i, v = samples_to_arrays(samples)
        if args.charge_positive:
            i = -i
        names = [f"v_cell_{c + 1:02d}" for c in range(v.shape[1])]
        return t, i, v, names
    if args.mapping is not None:
        raise UserError("--mapping applies to candump .log inputs only")
    data = read_tester_csv(path, charge_positive=args.charge_positive)
    return data.t_s, data.current_A, data.cell_voltages_V, list(data.cell_names)


def check_soc0(soc0: float | None) -> None:
    if soc0 is not None and not (math.isfinite(soc0) and 0.0 <= soc0 <= 1.0):
        raise UserError(f"--soc0 is a fraction in [0, 1], got {soc0:g}")


def identify_one(
    t: FloatArray,
    i: FloatArray,
    v: FloatArray,
    names: list[str],
    cell: CellConfig,
    variant: Variant,
    tuning: EstimatorTuning,
    soc0: float | None,
    desc: str,
) -> IdentifyResult:
    with progress_bar(int(t.shape[0]), desc) as bar:
        return run_arrays(t, i, v, cell, variant, tuning, soc0, bar, names)


def soc_init_text(result: IdentifyResult) -> str:
    z0 = result.trace["soc"][0] if result.trace.n_ticks else np.array([math.nan])
    socs = ", ".join(f"{100 * z:.1f} %" for z in z0[:4]) + (" ..." if z0.size > 4 else "")
    how = {
        "given": "given by --soc0",
        "ocv_at_rest": "from the first voltage through the OCV curve (the cell was at rest)",
        "config": "the config's soc0 (the first current was not a rest current)",
        "default_0.5": "a default of 50 %: the first current was not a rest current and the "
        "config gives no soc0; pass --soc0",
    }.get(result.soc_init_method, result.soc_init_method)
    return f"initial SOC {socs}: {how}"


def ocv_range_warning(result: IdentifyResult, cell: CellConfig) -> str | None:
    """A warning when SOC was read off the OCV curve at one of its ends: the first voltage lies
    outside the curve's range, so SOC is clamped and the OCV model is off by the difference."""
    if result.soc_init_method != "ocv_at_rest" or result.trace.n_ticks == 0:
        return None
    ocv = OcvModel.from_cell(cell)
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


def write_params_csv(result: IdentifyResult, path: Path) -> None:
    tr = result.trace
    n, nc = tr.n_ticks, tr.n_cells
    cols = [np.char.mod("%.6f", tr.t_s)]
    per_cell: list[list[str]] = []
    for c in range(nc):
        fields = [np.char.mod(fmt, tr[key][:, c]) for _, key, fmt in PARAM_COLUMNS]
        fields.append(tr.quality[:, c].astype(str))
        joined = fields[0]
        for f in fields[1:]:
            joined = np.char.add(np.char.add(joined, ","), f)
        per_cell.append(joined.tolist())
    header = "t_s,cell," + ",".join(name for name, _, _ in PARAM_COLUMNS) + ",quality\n"
    t_str = cols[0].tolist()
    with path.open("w", encoding="utf-8") as fh:
        fh.write(header)
        for k in range(n):
            for c in range(nc):
                fh.write(f"{t_str[k]},{result.cell_names[c]},{per_cell[c][k]}\n")


def plotted_cells(result: IdentifyResult, window: EvalWindow) -> list[int]:
    """All cells up to MAX_PLOTTED_CELLS, else the first and the worst (window RMSE)."""
    nc = result.trace.n_cells
    if nc <= MAX_PLOTTED_CELLS:
        return list(range(nc))
    rmse = [m.rmse_V for m in score(result.trace, window).per_cell_window]
    return sorted({0, int(np.argmax(rmse))})


def write_outputs(
    result: IdentifyResult, window: EvalWindow, out: Path, title: str, extra: dict[str, Any]
) -> dict[str, Any]:
    out.mkdir(parents=True, exist_ok=True)
    write_params_csv(result, out / "params.csv")
    doc = {**metrics_document(result, window), **extra}
    (out / "metrics.json").write_text(json.dumps(doc, indent=2) + "\n", encoding="utf-8")
    cells = plotted_cells(result, window)
    if result.trace.n_ticks:
        plot_parameters(result.trace, cells, result.cell_names, out / "parameters.png", title)
        for c in cells:
            name = result.cell_names[c]
            file = "voltage.png" if result.trace.n_cells == 1 else f"voltage_{name}.png"
            plot_voltage(result.trace, c, name, out / file, title)
    return doc


def summary_line(doc: dict[str, Any]) -> str:
    return (
        f"{doc['algorithm']}: RMSE {1e3 * doc['rmse_V']:.2f} mV, "
        f"max {1e3 * doc['max_abs_error_V']:.1f} mV, MAPE {doc['mape_pct']:.3f} % "
        f"over {doc['n_samples']} ticks "
        f"({doc['evaluation_window']['description']}); run time {doc['runtime_s']:.1f} s"
    )


def run(args: argparse.Namespace) -> int:
    tuning = parse_tuning(args.tuning)
    window = parse_window(args.soc_window, args.skip_fraction)
    check_soc0(args.soc0)
    cell, note = build_cell(args)
    t, i, v, names = load_input(args.input, args)
    out = Path(args.out)
    if out.exists() and not out.is_dir():
        raise UserError(f"--out {out} exists and is not a directory")
    print(f"{args.input}: {t.shape[0]} samples, {v.shape[1]} cell(s); {note}")
    result = identify_one(t, i, v, names, cell, args.algorithm, tuning, args.soc0, args.algorithm)
    print(soc_init_text(result))
    warning = ocv_range_warning(result, cell)
    if warning:
        print(warning)
    if result.trace.n_ticks == 0:
        raise UserError(f"{args.input}: no identification tick (too short or no valid time)")
    extra = {
        "input": str(args.input),
        "cell_config": note,
        "tuning_overrides": dict(item.partition("=")[::2] for item in args.tuning),
    }
    doc = write_outputs(result, window, out, f"{Path(args.input).name} - {args.algorithm}", extra)
    print(summary_line(doc))
    print(f"wrote {out}/params.csv, metrics.json and plots")
    return 0
