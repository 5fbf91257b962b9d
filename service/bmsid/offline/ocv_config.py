"""``fit-ocv`` as a library: OCV test files (or rest-point tables) in, a cell config out.

The numeric method is :mod:`bmsid.offline.ocv_fit`; this module reads the files, pools them,
runs the fit and builds the :class:`~bmsid.config.cell.CellConfig`, with the lines of the
Table-1-like report. Pure apart from reading the files it is given (the caller saves the config).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np

from bmsid.config.cell import CellConfig, InitialParameters, ParameterBounds, load_cell_config
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

Branch = Literal["discharge", "charge"]


@dataclass(frozen=True)
class OcvFitSpec:
    """How to fit and what to call the result (frozen, picklable).

    Attributes
    ----------
    name : str
        Cell name in the config.
    chemistry : str
        Chemistry label (e.g. ``LFP``).
    points : bool
        The inputs are rest-point tables (``read_ocv_points``), not a low-rate test.
    capacity_Ah : float or None
        Capacity, Ah; None: measured from the test (required with ``points``).
    coulombic_efficiency : float or None
        None: measured from the test (1 for tables).
    charge_positive : bool
        The test files count charge current positive.
    cell : str or None
        Voltage column of a multi-cell test file.
    trim_soc : float
        SOC fraction trimmed at each end of the fit.
    gamma : float
        Hysteresis rate stored in the config (not fitted).
    knots : tuple of float
        SOC knots (fractions) of the piecewise-linear M(z).
    initial : InitialParameters or None
        Start parameter values stored in the config.
    bounds : ParameterBounds or None
        Parameter bounds stored in the config; None: the defaults.
    branch : {"discharge", "charge"} or None
        Branch of tables whose column names do not say it.
    soc_anchor : {"none", "full"}
        ``full``: shift each table's SOC so its highest discharge point is 100 %.
    hysteresis_from : str or None
        Cell config whose M(z) is taken when the tables have one branch only.
    """

    name: str
    chemistry: str = "unknown"
    points: bool = False
    capacity_Ah: float | None = None
    coulombic_efficiency: float | None = None
    charge_positive: bool = False
    cell: str | None = None
    trim_soc: float = 0.02
    gamma: float = 30.0
    knots: tuple[float, ...] = EQ32_KNOTS
    initial: InitialParameters | None = None
    bounds: ParameterBounds | None = None
    branch: Branch | None = None
    soc_anchor: Literal["none", "full"] = "none"
    hysteresis_from: str | None = None


@dataclass(frozen=True)
class OcvFit:
    """A fit, the cell config built from it and the report's information lines."""

    config: CellConfig
    result: OcvFitResult
    info: list[str]

    def report(self) -> str:
        """The Table-1-like report printed by ``bmsid fit-ocv``."""
        return format_report(self.result, self.info)


def fit_test_files(
    paths: Sequence[str | Path], spec: OcvFitSpec
) -> tuple[OcvFitResult, float, float, list[str]]:
    """Fit a low-rate OCV test (one or several tester files in time order).

    Returns
    -------
    result, capacity_Ah, coulombic_efficiency, info
        The fit, the capacity (Ah) and efficiency used, and report lines on them.
    """
    parts: list[OcvTestPart] = []
    for path in paths:
        data = read_tester_csv(path, charge_positive=spec.charge_positive)
        if spec.cell is not None:
            if spec.cell not in data.cell_names:
                raise UserError(f"{path}: no voltage column {spec.cell!r}")
            col = data.cell_names.index(spec.cell)
        elif data.n_cells == 1:
            col = 0
        else:
            raise UserError(f"{path}: {data.n_cells} cell voltage columns; choose one with --cell")
        parts.append(OcvTestPart(data.t_s, data.current_A, data.cell_voltages_V[:, col]))
    br = extract_branches(
        parts, capacity_Ah=spec.capacity_Ah, coulombic_efficiency=spec.coulombic_efficiency
    )
    result = fit_ocv_test(br, trim_soc=spec.trim_soc, knots=spec.knots)
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


def fit_point_files(
    paths: Sequence[str | Path], spec: OcvFitSpec
) -> tuple[OcvFitResult, float, float, list[str]]:
    """Fit rest-point tables (SOC, OCV pairs per branch); returns as :func:`fit_test_files`."""
    if spec.capacity_Ah is None:
        raise UserError("--points needs --capacity-ah (rest tables carry no charge count)")
    pooled: dict[str, tuple[list[FloatArray], list[FloatArray]]] = {
        "discharge": ([], []),
        "charge": ([], []),
    }
    info: list[str] = []
    for path in paths:
        pairs = read_ocv_points(path)
        named = [(pr.branch or spec.branch, pr) for pr in pairs]
        for branch, _ in named:
            if branch is None:
                raise UserError(f"{path}: the columns do not name a branch; give --branch")
        shift = 0.0
        if spec.soc_anchor == "full":
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
    if spec.hysteresis_from is not None:
        other = load_cell_config(spec.hysteresis_from)
        m_table = (
            np.asarray(other.hysteresis.soc, dtype=np.float64),
            np.asarray(other.hysteresis.M_V, dtype=np.float64),
        )
    branches = {b: (np.concatenate(zs), np.concatenate(vs)) for b, (zs, vs) in pooled.items() if zs}
    result = fit_rest_points(
        branches.get("discharge"),
        branches.get("charge"),
        m_table=m_table,
        trim_soc=spec.trim_soc,
        knots=spec.knots,
    )
    eta = 1.0 if spec.coulombic_efficiency is None else spec.coulombic_efficiency
    return result, spec.capacity_Ah, eta, info


def fit_ocv_files(paths: Sequence[str | Path], spec: OcvFitSpec) -> OcvFit:
    """Fit the OCV curve and M(z) of ``paths`` and build the cell config.

    Raises
    ------
    UserError
        Unreadable inputs, a test without usable branches, or a fit that gives no valid config.
    """
    fit = fit_point_files if spec.points else fit_test_files
    result, capacity, eta, info = fit(paths, spec)
    dip = monotonicity_violation_V(result.mean.coeffs, result.soc_min, result.soc_max)
    if dip > 0.005:
        info.append(f"warning: the mean OCV falls by {1e3 * dip:.0f} mV somewhere in its range")
    try:
        cfg = build_cell_config(
            result,
            name=spec.name,
            chemistry=spec.chemistry,
            capacity_Ah=capacity,
            coulombic_efficiency=eta,
            gamma=spec.gamma,
            bounds=spec.bounds,
            initial=spec.initial,
        )
    except ValueError as exc:
        raise UserError(f"the fit gives no valid cell config: {exc}".splitlines()[0]) from None
    return OcvFit(config=cfg, result=result, info=info)


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


def format_report(result: OcvFitResult, info: Sequence[str]) -> str:
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
