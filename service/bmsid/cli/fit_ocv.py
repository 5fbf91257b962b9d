"""``bmsid fit-ocv``: fit OCV (Eq. 4) and hysteresis M(z) from a test; write a cell config.

Two inputs:

- a low-rate (C/20-C/30) discharge-then-charge test as tester CSV files (one file, or several
  in time order, e.g. the discharge and the charge files, or all four parts of Plett's test);
- ``--points``: rest-point tables (SOC, OCV) with one or both branches (``read_ocv_points``).

The method and its conventions are documented in ``bmsid.offline.ocv_fit``.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from bmsid.config.cell import (
    InitialParameters,
    ParameterBounds,
    Range,
    load_cell_config,
    save_cell_config,
)
from bmsid.errors import UserError
from bmsid.offline.csvio import read_ocv_points, read_tester_csv
from bmsid.offline.ocv_fit import (
    EQ32_KNOTS,
    Eq4Fit,
    FloatArray,
    OcvFitResult,
    OcvTestPart,
    build_cell_config,
    extract_branches,
    fit_ocv_test,
    fit_rest_points,
    monotonicity_violation_V,
)

_INITIAL_KEYS = ("R0_ohm", "R1_ohm", "tau1_s", "R2_ohm", "tau2_s")
_BOUND_KEYS = ("R0_ohm", "R1_ohm", "R2_ohm", "tau1_s", "tau2_s", "M_scale", "ocv_offset_V")


def register(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = subparsers.add_parser(
        "fit-ocv",
        help="fit OCV (Eq. 4) and hysteresis M(z) from an OCV test; write a cell config",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("inputs", nargs="+", metavar="FILE", help="test CSV(s) in time order, or tables")
    p.add_argument("--out", required=True, help="cell config to write (.toml or .json)")
    p.add_argument("--name", default=None, help="cell name (default: the output file's stem)")
    p.add_argument("--chemistry", default="unknown", help="chemistry label, e.g. LFP, NMC")
    p.add_argument(
        "--capacity-ah", type=float, default=None, help="capacity, Ah (default: measured)"
    )
    p.add_argument(
        "--coulombic-efficiency", type=float, default=None, help="default: measured from the test"
    )
    p.add_argument("--charge-positive", action="store_true", help="the files count charge positive")
    p.add_argument("--cell", default=None, help="voltage column to use when a file has several")
    p.add_argument(
        "--trim-soc",
        type=float,
        default=0.02,
        help="SOC trimmed at each end of the fit (default 0.02)",
    )
    p.add_argument("--gamma", type=float, default=30.0, help="hysteresis rate gamma (not fitted)")
    p.add_argument(
        "--m-knots",
        default=",".join(str(k) for k in EQ32_KNOTS),
        help="SOC knots of the piecewise-linear M(z) table (default: Eq. 32's)",
    )
    p.add_argument(
        "--initial",
        default=None,
        metavar="R0_ohm=X,R1_ohm=X,tau1_s=X,R2_ohm=X,tau2_s=X",
        help="starting parameter values stored in the config",
    )
    p.add_argument(
        "--bound",
        action="append",
        default=[],
        metavar="NAME=LO:HI",
        help=f"parameter bound, repeatable; NAME in {', '.join(_BOUND_KEYS)}",
    )
    g = p.add_argument_group("rest-point tables")
    g.add_argument("--points", action="store_true", help="inputs are rest-point tables")
    g.add_argument(
        "--branch",
        choices=("discharge", "charge"),
        default=None,
        help="branch of tables whose column names do not say it",
    )
    g.add_argument(
        "--soc-anchor",
        choices=("none", "full"),
        default="none",
        help="full: shift each table's SOC so its highest discharge point is 100 %%",
    )
    g.add_argument(
        "--hysteresis-from",
        default=None,
        metavar="CONFIG",
        help="take M(z) from this cell config when the tables have one branch only",
    )
    p.set_defaults(func=run)


def _float_list(text: str, what: str) -> list[float]:
    try:
        return [float(x) for x in text.split(",") if x.strip()]
    except ValueError:
        raise UserError(f"{what}: expected comma-separated numbers, got {text!r}") from None


def _initial(text: str | None) -> InitialParameters | None:
    if text is None:
        return None
    values: dict[str, float] = {}
    for item in text.split(","):
        key, _, val = item.partition("=")
        if key.strip() not in _INITIAL_KEYS:
            raise UserError(
                f"--initial: unknown key {key.strip()!r}; use {', '.join(_INITIAL_KEYS)}"
            )
        try:
            values[key.strip()] = float(val)
        except ValueError:
            raise UserError(f"--initial: {item!r} is not KEY=NUMBER") from None
    if set(values) != set(_INITIAL_KEYS):
        raise UserError(f"--initial needs all of {', '.join(_INITIAL_KEYS)}")
    try:
        return InitialParameters(**values)
    except ValueError as exc:
        raise UserError(f"--initial: {exc}".splitlines()[0]) from None


def _bounds(items: list[str]) -> ParameterBounds:
    ranges: dict[str, Range] = {}
    for item in items:
        key, _, span = item.partition("=")
        lo, _, hi = span.partition(":")
        if key.strip() not in _BOUND_KEYS:
            raise UserError(f"--bound: unknown name {key.strip()!r}; use {', '.join(_BOUND_KEYS)}")
        try:
            ranges[key.strip()] = Range(lo=float(lo), hi=float(hi))
        except ValueError:
            raise UserError(f"--bound: {item!r} is not NAME=LO:HI with LO < HI") from None
    try:
        return ParameterBounds(**ranges)
    except ValueError as exc:
        raise UserError(f"--bound: {exc}".splitlines()[0]) from None


def _fit_test(
    args: argparse.Namespace, trim: float, knots: list[float]
) -> tuple[OcvFitResult, float, float, list[str]]:
    parts: list[OcvTestPart] = []
    for path in args.inputs:
        data = read_tester_csv(path, charge_positive=args.charge_positive)
        if args.cell is not None:
            if args.cell not in data.cell_names:
                raise UserError(f"{path}: no voltage column {args.cell!r}")
            col = data.cell_names.index(args.cell)
        elif data.n_cells == 1:
            col = 0
        else:
            raise UserError(f"{path}: {data.n_cells} cell voltage columns; choose one with --cell")
        parts.append(OcvTestPart(data.t_s, data.current_A, data.cell_voltages_V[:, col]))
    br = extract_branches(
        parts, capacity_Ah=args.capacity_ah, coulombic_efficiency=args.coulombic_efficiency
    )
    result = fit_ocv_test(br, trim_soc=trim, knots=knots)
    steps = ", ".join(f"{1e3 * r:.1f}" for r in br.step_resistances_ohm)
    info = [
        f"capacity measured from the test: {br.measured_capacity_Ah:.4f} Ah "
        f"(used: {br.capacity_Ah:.4f} Ah); coulombic efficiency {br.coulombic_efficiency:.4f}",
        f"branch currents: discharge {br.discharge.current_A:.4g} A "
        f"(C/{br.capacity_Ah / br.discharge.current_A:.0f}), charge {br.charge.current_A:.4g} A "
        f"(C/{br.capacity_Ah / br.charge.current_A:.0f})",
        f"IR steps |dV/dI| [mOhm]: {steps or 'none'}; R used = {1e3 * br.resistance_ohm:.1f} mOhm",
    ]
    return result, br.capacity_Ah, br.coulombic_efficiency, info


def _fit_points(
    args: argparse.Namespace, trim: float, knots: list[float]
) -> tuple[OcvFitResult, float, float, list[str]]:
    if args.capacity_ah is None:
        raise UserError("--points needs --capacity-ah (rest tables carry no charge count)")
    pooled: dict[str, tuple[list[FloatArray], list[FloatArray]]] = {
        "discharge": ([], []),
        "charge": ([], []),
    }
    info: list[str] = []
    for path in args.inputs:
        pairs = read_ocv_points(path)
        named = [(pr.branch or args.branch, pr) for pr in pairs]
        for branch, _ in named:
            if branch is None:
                raise UserError(f"{path}: the columns do not name a branch; give --branch")
        shift = 0.0
        if args.soc_anchor == "full":
            dis = [pr.soc for b, pr in named if b == "discharge"] or [pr.soc for _, pr in named]
            shift = 1.0 - float(max(np.max(s) for s in dis))
            info.append(
                f"{path}: SOC shifted by {100 * shift:+.2f} % (top discharge point = 100 %)"
            )
        for branch, pr in named:
            assert branch is not None
            pooled[branch][0].append(pr.soc + shift)
            pooled[branch][1].append(pr.ocv_V)
    m_table = None
    if args.hysteresis_from is not None:
        other = load_cell_config(args.hysteresis_from)
        m_table = (
            np.asarray(other.hysteresis.soc, dtype=np.float64),
            np.asarray(other.hysteresis.M_V, dtype=np.float64),
        )
    branches = {b: (np.concatenate(zs), np.concatenate(vs)) for b, (zs, vs) in pooled.items() if zs}
    result = fit_rest_points(
        branches.get("discharge"),
        branches.get("charge"),
        m_table=m_table,
        trim_soc=trim,
        knots=knots,
    )
    eta = 1.0 if args.coulombic_efficiency is None else args.coulombic_efficiency
    return result, args.capacity_ah, eta, info


def _fit_lines(name: str, f: Eq4Fit) -> list[str]:
    out = [
        f"{name:<10} n={f.n:<6d} SSE={f.sse_V2:.4g} V^2  R^2={f.r2:.5f}  adj R^2={f.r2_adj:.5f}  "
        f"RMSE={1e3 * f.rmse_V:.2f} mV  SOC {100 * f.soc_lo:.1f}-{100 * f.soc_hi:.1f} %"
    ]
    for k in range(6):
        out.append(
            f"    a{k} = {f.coeffs[k]: .6g}  (95 % CI {f.ci_low[k]: .6g} .. {f.ci_high[k]: .6g})"
        )
    return out


def format_report(result: OcvFitResult, info: list[str]) -> str:
    """The Table-1-like report: per-branch coefficients with bounds and fit statistics, M table."""
    lines = ["OCV fit, Eq. 4: U(z) = a0 + a1 z + a2 z^2 + a3/z + a4 ln z + a5 ln(1-z)", *info]
    for name in ("discharge", "charge", "mean"):
        f = getattr(result, name)
        if f is not None:
            lines += _fit_lines(name, f)
    lines.append(
        f"valid SOC range: {result.soc_min:.4f} .. {result.soc_max:.4f}; hysteresis M(z) "
        "(SOC %: mV): "
        + ", ".join(
            f"{100 * z:.0f}: {1e3 * m:.1f}" for z, m in zip(result.m_soc, result.m_V, strict=True)
        )
    )
    if result.half_gap_raw_V is not None and result.half_gap_V is not None:
        lines.append(
            f"half-gap (max over SOC): raw {1e3 * np.max(result.half_gap_raw_V):.1f} mV, "
            f"IR-corrected {1e3 * np.max(result.half_gap_V):.1f} mV; median raw "
            f"{1e3 * np.median(result.half_gap_raw_V):.1f} mV, corrected "
            f"{1e3 * np.median(result.half_gap_V):.1f} mV"
        )
    lines += [f"note: {n}" for n in result.notes]
    return "\n".join(lines)


def run(args: argparse.Namespace) -> int:
    out = Path(args.out)
    if out.suffix.lower() not in (".toml", ".json"):
        raise UserError(f"--out {out}: use a .toml or .json file name")
    knots = _float_list(args.m_knots, "--m-knots")
    initial = _initial(args.initial)
    bounds = _bounds(args.bound)
    if args.points:
        result, capacity, eta, info = _fit_points(args, args.trim_soc, knots)
    else:
        result, capacity, eta, info = _fit_test(args, args.trim_soc, knots)
    dip = monotonicity_violation_V(result.mean.coeffs, result.soc_min, result.soc_max)
    if dip > 0.005:
        info.append(f"warning: the mean OCV falls by {1e3 * dip:.0f} mV somewhere in its range")
    try:
        cfg = build_cell_config(
            result,
            name=args.name or out.stem,
            chemistry=args.chemistry,
            capacity_Ah=capacity,
            coulombic_efficiency=eta,
            gamma=args.gamma,
            bounds=bounds,
            initial=initial,
        )
    except ValueError as exc:
        raise UserError(f"the fit gives no valid cell config: {exc}".splitlines()[0]) from None
    print(format_report(result, info))
    save_cell_config(cfg, out)
    print(f"wrote {out}")
    return 0
