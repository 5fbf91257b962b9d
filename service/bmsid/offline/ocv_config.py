"""``fit-ocv`` as a library: OCV test files (or rest-point tables) in, a cell config out.

The numeric method is :mod:`bmsid.offline.ocv_fit`; this module reads the files, pools them,
runs the fit and builds the :class:`~bmsid.config.cell.CellConfig`, with the lines of the
Table-1-like report. Pure apart from reading the files it is given (the caller saves the config).
"""

from __future__ import annotations

import importlib
import json
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any, Literal

import numpy as np

from bmsid.config.cell import CellConfig, InitialParameters, ParameterBounds, load_cell_config
from bmsid.errors import UserError
from bmsid.offline import plausibility
from bmsid.offline.csvio import (
    ColumnMap,
    OcvPoints,
    TesterData,
    read_ocv_points,
    read_tester_csv,
)
from bmsid.offline.ocv_fit import (
    EQ32_KNOTS,
    Eq4Fit,
    FloatArray,
    OcvFitResult,
    OcvTestPart,
    Throughput,
    build_cell_config,
    extract_branches,
    fit_ocv_test,
    fit_rest_points,
    monotonicity_violation_V,
)
from bmsid.offline.ocv_incremental import incremental_points
from bmsid.offline.ocv_one_branch import one_branch_points

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
    columns : mapping of canonical name to ColumnMap, or None
        Where the test files' columns are (``--columns``, as ``bmsid identify`` reads them).
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
    soc_anchor : {"auto", "none", "full"}
        ``auto`` (default): a table whose SOC runs above 100 % is shifted so that its highest
        discharge point is 100 % (a rest above full is the full rest on another SOC
        reference); one within 0-100 % keeps its axis. ``full``: every table shifted so.
        ``none``: as given (points beyond the fit's range are moved onto it).
    hysteresis_from : str or None
        Cell config whose M(z) is taken when the tables have one branch only.
    ends : bool
        Extend the mean OCV to the rested voltages measured at empty/full (when the test has
        them); False keeps it clamped to [soc_min, soc_max].
    correction : bool
        Fit the correction table beyond Eq. 4 (``ocv_correction``; low-rate tests only) and
        write it when the test resolves it; False: Eq. 4 alone.
    temperature_C : float or None
        The test's temperature (degC) written to the config; None: the median of the test
        files' temperature column where they all have one (rest-point tables: not known).
    """

    name: str
    chemistry: str = "unknown"
    points: bool = False
    capacity_Ah: float | None = None
    coulombic_efficiency: float | None = None
    charge_positive: bool = False
    columns: Mapping[str, ColumnMap] | None = None
    cell: str | None = None
    trim_soc: float = 0.02
    gamma: float = 30.0
    knots: tuple[float, ...] = EQ32_KNOTS
    initial: InitialParameters | None = None
    bounds: ParameterBounds | None = None
    branch: Branch | None = None
    soc_anchor: Literal["auto", "none", "full"] = "auto"
    hysteresis_from: str | None = None
    ends: bool = True
    correction: bool = True
    temperature_C: float | None = None


@dataclass(frozen=True)
class OcvFit:
    """A fit, the cell config built from it and the report's information lines."""

    config: CellConfig
    result: OcvFitResult
    info: list[str]

    def report(self) -> str:
        """The Table-1-like report printed by ``bmsid fit-ocv``."""
        return format_report(self.result, self.info)


#: A capacity given with --capacity-ah this many times above or below the charge the test
#: measures is warned about: a full low-rate discharge counts it to about 1 %, so beyond 10 %
#: the SOC axis is stretched (a branch runs past 0 or 100 % and only its overlap is fitted) or
#: the given figure is a nominal one the cell no longer has. ``bmsid identify``'s
#: ``capacity_mismatch`` allows 3x: its records only imply a capacity roughly.
OCV_CAPACITY_MISMATCH = 1.1


def capacity_warning(given_Ah: float | None, measured_Ah: float) -> list[str]:
    """A report line when ``given_Ah`` is ``OCV_CAPACITY_MISMATCH`` off ``measured_Ah``."""
    if given_Ah is None:
        return []
    ratio = plausibility.mismatch_ratio(given_Ah, measured_Ah, OCV_CAPACITY_MISMATCH)
    if ratio is None:
        return []
    return [
        f"warning: capacity_mismatch: --capacity-ah {given_Ah:g} Ah is {ratio:.3g}x the "
        f"{measured_Ah:.4g} Ah the test measures (full to empty): the SOC axis and every "
        "curve on it are scaled by that; leave --capacity-ah out to use the measured capacity"
    ]


#: A measured coulombic efficiency below this is not a Li-ion cell's (above 0.99 at C/20) but
#: a charge count that is off: pulses sampled too coarsely (the A123 test resampled to 60 s
#: measured 0.942, and identify then gave 9.5 mV on DYN50 instead of 4.9 with 0.995).
MIN_PLAUSIBLE_EFFICIENCY = 0.98


def efficiency_warning(tp: Throughput) -> list[str]:
    """A report line when the measured coulombic efficiency is implausibly low."""
    if tp.method != "normalised" or tp.eta >= MIN_PLAUSIBLE_EFFICIENCY:
        return []
    return [
        f"warning: the measured coulombic efficiency {tp.eta:.4f} ({tp.charge_Ah:.4g} Ah in for "
        f"{tp.discharge_Ah:.4g} Ah out) is below {MIN_PLAUSIBLE_EFFICIENCY:g}, which no Li-ion "
        "cell has: the charge count is off (pulses sampled too coarsely, a current offset); "
        "give --coulombic-efficiency (e.g. 0.995) or a finer-sampled export"
    ]


#: The branches' overlap may stop this much (SOC) short of the trimmed range before the config
#: is called partial: a test's branches reach both ends, only a cut-short one does not.
PARTIAL_SOC = 0.02


def partial_range_warning(result: OcvFitResult, trim_soc: float) -> list[str]:
    """A report line when the fit range stops short of an end: the OCV is not measured beyond
    it (a charge stopped early gave SOC 2-60 % and 11.7 mV on DYN50)."""
    lo, hi = result.mean.soc_lo, result.mean.soc_hi
    short = []
    if hi < 1.0 - trim_soc - PARTIAL_SOC:
        short.append(f"above {100 * hi:.1f} %")
    if lo > trim_soc + PARTIAL_SOC:
        short.append(f"below {100 * lo:.1f} %")
    if not short:
        return []
    return [
        f"warning: partial test: the branches overlap only on SOC {100 * lo:.1f}-{100 * hi:.1f} "
        f"%, so the config's OCV {' and '.join(short)} is not measured (clamped, or bridged to a "
        "rested end voltage): a charge or discharge that stopped early (fit the whole test) or "
        "a charge count that is off"
    ]


def _read_test_file(path: str | Path, spec: OcvFitSpec) -> TesterData:
    """A test file; one that fails as one but reads as a rest-point table says --points."""
    try:
        return read_tester_csv(path, charge_positive=spec.charge_positive, columns=spec.columns)
    except UserError as exc:
        try:
            read_ocv_points(path)
        except UserError:
            raise exc from None
        raise UserError(
            f"{path}: a rest-point table (SOC and OCV columns), not a test: pass --points "
            "(with --capacity-ah)"
        ) from None


def fit_test_files(
    paths: Sequence[str | Path], spec: OcvFitSpec
) -> tuple[OcvFitResult, float, float, list[str], float | None]:
    """Fit a low-rate OCV test (one or several tester files in time order).

    Returns
    -------
    result, capacity_Ah, coulombic_efficiency, info, temperature_C
        The fit, the capacity (Ah) and efficiency used, report lines on them and the test's
        temperature (degC, ``_test_temperature``).
    """
    parts: list[OcvTestPart] = []
    input_notes: list[str] = []
    temps: list[FloatArray | None] = []
    for path in paths:
        data = _read_test_file(path, spec)
        temps.append(data.temperature_C)
        if data.merged_repeats or data.time_restarts:
            input_notes.append(
                f"{path}: merged {data.merged_repeats} rows with repeated timestamps (the last "
                f"row of each time is kept); {len(data.time_restarts)} clock restart(s) stitched"
            )
        if spec.cell is not None:
            if spec.cell not in data.cell_names:
                raise UserError(f"{path}: no voltage column {spec.cell!r}")
            col = data.cell_names.index(spec.cell)
        elif data.n_cells == 1:
            col = 0
        else:
            raise UserError(f"{path}: {data.n_cells} cell voltage columns; choose one with --cell")
        parts.append(OcvTestPart(data.t_s, data.current_A, data.cell_voltages_V[:, col]))
    temp_C = _test_temperature(temps, spec)
    inc = incremental_points(parts, spec.capacity_Ah, spec.coulombic_efficiency)
    if inc is not None:  # pulses and rests: the rests' voltages are the points
        result = fit_rest_points(
            inc.discharge, inc.charge, trim_soc=spec.trim_soc, knots=spec.knots, ends=spec.ends
        )
        warn = capacity_warning(spec.capacity_Ah, inc.measured_capacity_Ah)
        return result, inc.capacity_Ah, inc.eta, [*input_notes, *inc.info, *warn], temp_C
    one = one_branch_points(parts, spec.capacity_Ah, spec.gamma)
    if one is not None:  # a discharge (or charge) alone: its corrected voltage as the points
        result = fit_rest_points(
            one.discharge, one.charge, m_table=_hysteresis_table(spec.hysteresis_from),
            trim_soc=spec.trim_soc, knots=spec.knots, ends=spec.ends,
            dense=one.dense if spec.correction else None,
        )  # fmt: skip
        warn = capacity_warning(spec.capacity_Ah, one.measured_capacity_Ah)
        eta = 1.0 if spec.coulombic_efficiency is None else spec.coulombic_efficiency
        return result, one.capacity_Ah, eta, [*input_notes, *one.info, *warn], temp_C
    br = extract_branches(
        parts,
        capacity_Ah=spec.capacity_Ah,
        coulombic_efficiency=spec.coulombic_efficiency,
        gamma=spec.gamma,
    )
    if not spec.ends:
        br = replace(br, v_empty_V=None, v_full_V=None)
    result = fit_ocv_test(br, trim_soc=spec.trim_soc, knots=spec.knots, correction=spec.correction)
    tp, pol = br.throughput, br.polarisation
    steps = ", ".join(f"{1e3 * st.r_ohm:.1f} +- {1e3 * st.se_ohm:.1f}" for st in pol.steps)
    info = [
        *input_notes,
        f"capacity measured from the test: {br.measured_capacity_Ah:.4f} Ah "
        f"(used: {br.capacity_Ah:.4f} Ah)",
        *capacity_warning(spec.capacity_Ah, br.measured_capacity_Ah),
        *efficiency_warning(tp),
        f"throughput: discharge {tp.discharge_Ah:.4f} Ah, charge {tp.charge_Ah:.4f} Ah, "
        f"mismatch {tp.mismatch_Ah:+.4f} Ah ({tp.mismatch_pct:+.2f} %); SOC {tp.method}, "
        f"coulombic efficiency (charge-counting factor) {tp.eta:.4f}: {tp.reason}",
        f"branch currents: discharge {br.discharge.current_A:.4g} A "
        f"(C/{br.capacity_Ah / br.discharge.current_A:.0f}), charge {br.charge.current_A:.4g} A "
        f"(C/{br.capacity_Ah / br.charge.current_A:.0f})",
        f"polarisation: {pol.source}: R0 {1e3 * pol.R0_ohm:.1f} mOhm, R1 {1e3 * pol.R1_ohm:.1f} "
        f"mOhm (tau1 {pol.tau1_s:.0f} s), R2 {1e3 * pol.R2_ohm:.1f} mOhm (tau2 {pol.tau2_s:.0f} "
        f"s), total {1e3 * pol.r_total_ohm:.1f}"
        + (f" +- {1e3 * pol.r_total_se_ohm:.1f} (1 se)" if pol.r_total_se_ohm is not None else "")
        + " mOhm; at the branch currents (steady state) "
        f"{1e3 * br.discharge.current_A * pol.r_total_ohm:.2f} mV (discharge) + "
        f"{1e3 * br.charge.current_A * pol.r_total_ohm:.2f} mV (charge) of the gap",
        *[
            f"  rest after the {r.after} at SOC {100 * r.soc:.1f} % ({r.duration_s:.0f} s): "
            f"{1e3 * r.r_total_ohm:.1f} +- {1e3 * r.r_total_se_ohm:.1f} mOhm, tau "
            f"{r.tau1_s:.0f} / {r.tau2_s:.0f} s, fit RMSE {1e3 * r.rmse_V:.2f} mV"
            + (" (a knee: not used)" if r in pol.knee else "")
            for r in (*pol.relaxations, *pol.knee)
        ],
        f"  one-sample current steps |dV/dI| [mOhm, +- noise 1 se]: {steps or 'none'}",
        f"hysteresis state h run along the test with gamma = {br.gamma:g}",
        *partial_range_warning(result, spec.trim_soc),
    ]
    return result, br.capacity_Ah, br.coulombic_efficiency, info, temp_C


def _test_temperature(temps: Sequence[FloatArray | None], spec: OcvFitSpec) -> float | None:
    """The test's temperature, degC: ``spec.temperature_C``, else the median of the files'
    temperature column (rounded to 0.1 degC) where every file has one, else None."""
    if spec.temperature_C is not None:
        return spec.temperature_C
    if not temps or any(t is None for t in temps):
        return None
    vals = np.concatenate([t for t in temps if t is not None])
    vals = vals[np.isfinite(vals)]
    return round(float(np.median(vals)), 1) if vals.size else None


def _anchor_shift(
    path: str | Path, named: Sequence[tuple[str | None, OcvPoints]],
    anchor: Literal["auto", "none", "full"], info: list[str],
) -> float:  # fmt: skip
    """The SOC shift (fraction) of one table (``OcvFitSpec.soc_anchor``), said in ``info``.

    A table's SOC axis is its own count: the CALCE sibling cells' tables run to 100.7-108.9 %.
    Taken as given, the points above full were moved onto the fit's range and a user's 0 C
    config read the 0 C DST record's 81.9 % start as 88.5 % (README, Model and conventions)."""
    dis = [pr.soc for b, pr in named if b == "discharge"] or [pr.soc for _, pr in named]
    top = float(max(np.max(s) for s in dis))
    if anchor == "none" or (anchor == "auto" and top <= 1.0):
        return 0.0
    why = "" if anchor == "full" else f": its top point, {100 * top:.2f} %, lies above full"
    shift = 1.0 - top
    info.append(f"{path}: SOC shifted by {100 * shift:+.2f} % (top discharge point = 100 %{why})")
    return shift


def _hysteresis_table(path: str | None) -> tuple[FloatArray, FloatArray] | None:
    """(SOC, M V) of the cell config at ``path`` (``--hysteresis-from``), or None."""
    if path is None:
        return None
    other = load_cell_config(path)
    return (
        np.asarray(other.hysteresis.soc, dtype=np.float64),
        np.asarray(other.hysteresis.M_V, dtype=np.float64),
    )


def fit_point_files(
    paths: Sequence[str | Path], spec: OcvFitSpec
) -> tuple[OcvFitResult, float, float, list[str], float | None]:
    """Fit rest-point tables (SOC, OCV pairs per branch); returns as :func:`fit_test_files`
    (the temperature: ``--temperature-c`` only, tables carry none)."""
    if spec.capacity_Ah is None:
        raise UserError("--points needs --capacity-ah (rest tables carry no charge count)")
    if spec.columns:
        raise UserError(
            "--columns maps test files' columns; rest-point tables (--points) do not take it"
        )
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
        shift = _anchor_shift(path, named, spec.soc_anchor, info)
        for branch, pr in named:
            assert branch is not None
            pooled[branch][0].append(pr.soc + shift)
            pooled[branch][1].append(pr.ocv_V)
    m_table = _hysteresis_table(spec.hysteresis_from)
    branches = {b: (np.concatenate(zs), np.concatenate(vs)) for b, (zs, vs) in pooled.items() if zs}
    result = fit_rest_points(
        branches.get("discharge"),
        branches.get("charge"),
        m_table=m_table,
        trim_soc=spec.trim_soc,
        knots=spec.knots,
        ends=spec.ends,
    )
    eta = 1.0 if spec.coulombic_efficiency is None else spec.coulombic_efficiency
    return result, spec.capacity_Ah, eta, info, spec.temperature_C


def fit_ocv_files(paths: Sequence[str | Path], spec: OcvFitSpec) -> OcvFit:
    """Fit the OCV curve and M(z) of ``paths`` and build the cell config.

    Raises
    ------
    UserError
        Unreadable inputs, a test without usable branches, or a fit that gives no valid config.
    """
    fit = fit_point_files if spec.points else fit_test_files
    result, capacity, eta, info, temp_C = fit(paths, spec)
    # A correction table keeps the curve increasing (checked when it is fitted): Eq. 4 alone here.
    dip = 0.0 if result.table is not None else monotonicity_violation_V(
        result.mean.coeffs, result.soc_min, result.soc_max)  # fmt: skip
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
            temperature_C=temp_C,
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


def _hysteresis_lines(r: OcvFitResult) -> list[str]:
    """M(z) as stored (with each knot's status), as fitted, and the pooled evidence."""
    ci, ev = r.m_ci95_V, r.hysteresis
    status = ev.status if ev is not None else ("fit",) * r.m_soc.shape[0]
    out = [
        "hysteresis M(z) stored (SOC %: mV"
        + (" +- 95 % CI" if ci is not None else "")
        + "): "
        + ", ".join(
            f"{100 * z:.0f}: {1e3 * m:.1f}"
            + (f" +- {1e3 * ci[k]:.1f}" if ci is not None and ci[k] > 0 else "")
            + (f" ({status[k]})" if status[k] != "fit" else "")
            for k, (z, m) in enumerate(zip(r.m_soc, r.m_V, strict=True))
        )
    ]
    if r.m_fit_V is not None and r.m_fit_ci95_V is not None:
        out.append(
            "hysteresis M(z) fitted (SOC %: mV +- 95 % CI, before the decision): "
            + ", ".join(
                f"{100 * z:.0f}: {1e3 * m:+.1f} +- {1e3 * c:.1f}"
                for z, m, c, st in zip(r.m_soc, r.m_fit_V, r.m_fit_ci95_V, status, strict=True)
                if st != "pinned"
            )
        )
    if ev is not None:
        verdict = (
            f"not resolved: {ev.unresolved}"
            if ev.unresolved is not None
            else "hysteresis present"
            if ev.present
            else "negative: the polarisation over-corrects"
            if ev.pooled_V + ev.pooled_ci95_V < 0
            else "no hysteresis resolved"
        )
        out.append(
            f"hysteresis evidence: pooled M {1e3 * ev.pooled_V:.1f} +- {1e3 * ev.pooled_ci95_V:.1f}"
            f" mV (95 % CI) at SOC {100 * ev.soc_lo:.0f}-{100 * ev.soc_hi:.0f} %: {verdict}"
        )
    return out


def format_report(result: OcvFitResult, info: Sequence[str]) -> str:
    """The Table-1-like report: per-branch coefficients with bounds and fit statistics, the
    ends, M(z) with its 95 % CI, and the residuals per branch and SOC band."""
    lines = ["OCV fit, Eq. 4: U(z) = a0 + a1 z + a2 z^2 + a3/z + a4 ln z + a5 ln(1-z)", *info]
    for name in ("discharge", "charge", "mean"):
        f = getattr(result, name)
        if f is not None:
            lines += _fit_lines(name, f)
    ends = ", ".join(
        f"{name} {v:.4f} V" if v is not None else f"{name} not measured (clamped)"
        for name, v in (("empty", result.v_empty_V), ("full", result.v_full_V))
    )
    lines.append(
        f"Eq. 4 range: SOC {result.soc_min:.4f} .. {result.soc_max:.4f}; "
        f"rested end voltages: {ends}"
    )
    if result.correction is not None:
        lines.append(result.correction.summary())
    elif result.test is None:
        lines.append(
            "OCV correction table: not fitted (rest-point tables: too few points to resolve a "
            "residual beyond Eq. 4's six terms)"
        )
    else:
        lines.append("OCV correction table: not fitted (--no-ocv-correction)")
    lines += _hysteresis_lines(result)
    if result.half_gap_raw_V is not None and result.half_gap_V is not None:
        lines.append(
            f"half-gap median over SOC: measured {1e3 * np.median(result.half_gap_raw_V):.1f} mV, "
            f"polarisation-corrected {1e3 * np.median(result.half_gap_V):.1f} mV"
        )
    if result.residuals:
        lines.append("residuals vs the model (mean OCV + M h), per branch [SOC %: RMSE / bias mV]:")
        for name in ("discharge", "charge"):
            rows = [b for b in result.residuals if b.branch == name]
            if rows:
                lines.append(
                    f"  {name}: "
                    + ", ".join(
                        f"{100 * b.soc_lo:.0f}-{100 * b.soc_hi:.0f}: {1e3 * b.rmse_V:.1f}/"
                        f"{1e3 * b.bias_V:+.1f}"
                        for b in rows
                    )
                )
    lines += [f"note: {n}" for n in result.notes]
    return "\n".join(lines)


def report_json(fit: OcvFit) -> dict[str, Any]:
    """The report as plain data (what ``--report`` writes as ``ocv_fit.json``)."""
    r = fit.result

    def arr(a: FloatArray | None) -> list[float] | None:
        return None if a is None else [float(x) for x in a]

    doc: dict[str, Any] = {
        "info": list(fit.info),
        "notes": list(r.notes),
        "soc_min": r.soc_min,
        "soc_max": r.soc_max,
        "v_empty_V": r.v_empty_V,
        "v_full_V": r.v_full_V,
        "hysteresis": {"soc": arr(r.m_soc), "M_V": arr(r.m_V), "M_fit_V": arr(r.m_fit_V),
                       "M_ci95_V": arr(r.m_ci95_V), "M_fit_ci95_V": arr(r.m_fit_ci95_V),
                       "status": list(r.hysteresis.status) if r.hysteresis else None,
                       "pooled_V": r.hysteresis.pooled_V if r.hysteresis else None,
                       "pooled_ci95_V": r.hysteresis.pooled_ci95_V if r.hysteresis else None,
                       "pooled_soc": [r.hysteresis.soc_lo, r.hysteresis.soc_hi]
                       if r.hysteresis else None,
                       "present": r.hysteresis.present if r.hysteresis else None,
                       "unresolved": r.hysteresis.unresolved if r.hysteresis else None},
        "fits": {
            name: {"coeffs": arr(f.coeffs), "ci_low": arr(f.ci_low), "ci_high": arr(f.ci_high),
                   "sse_V2": f.sse_V2, "r2": f.r2, "r2_adj": f.r2_adj, "rmse_V": f.rmse_V,
                   "n": f.n}
            for name in ("discharge", "charge", "mean")
            if (f := getattr(r, name)) is not None
        },
        "residuals": [asdict(b) for b in r.residuals],
        "ocv_correction": None if (c := r.correction) is None else {
            "written": c.written, "reason": c.reason, "soc": arr(c.soc), "dU_V": arr(c.dU_V),
            "eq4_rmse_V": c.eq4_rmse_V, "rmse_V": c.rmse_V, "table_rms_V": c.table_rms_V,
            "noise_V": c.noise_V, "pooled": c.pooled, "n_knots": int(c.soc.shape[0]),
        },
    }  # fmt: skip
    if r.test is not None:
        tp, pol = r.test.throughput, r.test.polarisation
        doc["throughput"] = {**asdict(tp), "mismatch_Ah": tp.mismatch_Ah,
                             "mismatch_pct": tp.mismatch_pct}  # fmt: skip
        doc["polarisation"] = {
            "R0_ohm": pol.R0_ohm, "R1_ohm": pol.R1_ohm, "tau1_s": pol.tau1_s,
            "R2_ohm": pol.R2_ohm, "tau2_s": pol.tau2_s, "r_total_ohm": pol.r_total_ohm,
            "r_total_se_ohm": pol.r_total_se_ohm, "source": pol.source,
            "relaxations": [asdict(x) for x in pol.relaxations],
            "knee_relaxations": [asdict(x) for x in pol.knee],
            "step_resistances_ohm": list(pol.step_resistances_ohm),
            "step_se_ohm": [st.se_ohm for st in pol.steps],
        }  # fmt: skip
        doc["gamma"] = r.test.gamma
    return doc


def write_report(fit: OcvFit, out_dir: str | Path) -> list[Path]:
    """Write ``ocv_fit.txt``, ``ocv_fit.json`` and ``ocv_fit.png`` (branches, mean, M(z) with its
    CI, residuals) into ``out_dir``; returns the paths."""
    d = Path(out_dir)
    d.mkdir(parents=True, exist_ok=True)
    txt, js, png = d / "ocv_fit.txt", d / "ocv_fit.json", d / "ocv_fit.png"
    txt.write_text(fit.report() + "\n", encoding="utf-8")
    js.write_text(json.dumps(report_json(fit), indent=2) + "\n", encoding="utf-8")
    _plot(fit.result, png)
    return [txt, js, png]


def _plot(r: OcvFitResult, path: Path) -> None:
    # matplotlib only here: every other command would pay for importing it.
    matplotlib = importlib.import_module("matplotlib")
    matplotlib.use("Agg")
    plt = importlib.import_module("matplotlib.pyplot")
    model = r.ocv_model()
    z = np.linspace(0.0, 1.0, 1001)
    fig, ax = plt.subplots(3, 1, figsize=(9, 10), sharex=True,
                           gridspec_kw={"height_ratios": [3, 1.4, 1.4]})  # fmt: skip
    a0, a1, a2 = ax
    if r.test is not None:
        for b, name, col in ((r.test.discharge, "discharge", "tab:red"),
                             (r.test.charge, "charge", "tab:blue")):  # fmt: skip
            k = slice(None, None, max(1, b.z.shape[0] // 3000))
            a0.plot(100 * b.z[k], b.v_raw_V[k], ",", color=col, alpha=0.3)
            a0.plot(100 * b.z[k], b.v_V[k], lw=0.8, color=col, label=f"{name} (corrected)")
            res = b.v_V - (model.ocv(b.z) + model.hysteresis_M(b.z) * b.h)
            a2.plot(100 * b.z[k], 1e3 * res[k], lw=0.6, color=col, label=name)
    label = "mean OCV (Eq. 4 + table + ends)" if r.table is not None else "mean OCV (Eq. 4 + ends)"
    a0.plot(100 * z, model.ocv(z), "k", lw=1.2, label=label)
    for zz in (r.soc_min, r.soc_max):
        a0.axvline(100 * zz, color="0.6", ls=":", lw=0.8)
    a0.set_ylabel("voltage / V")
    a0.legend(fontsize=8)
    a0.grid(alpha=0.3)
    if r.gap_soc is not None and r.half_gap_raw_V is not None and r.half_gap_V is not None:
        a1.plot(
            100 * r.gap_soc, 1e3 * r.half_gap_raw_V, color="0.6", lw=0.8, label="half-gap measured"
        )
        a1.plot(
            100 * r.gap_soc,
            1e3 * r.half_gap_V,
            color="tab:green",
            lw=0.8,
            label="half-gap corrected",
        )
    a1.plot(100 * r.m_soc, 1e3 * r.m_V, "ko-", ms=3, label="M(z) table (stored)")
    if r.m_fit_ci95_V is not None and r.m_fit_V is not None:
        a1.errorbar(100 * r.m_soc, 1e3 * r.m_fit_V, yerr=1e3 * r.m_fit_ci95_V, fmt="s",
                    ms=3, color="tab:orange", capsize=3, label="knots fitted, 95 % CI")  # fmt: skip
    a1.axhline(0.0, color="0.6", lw=0.6)
    a1.set_ylabel("M / mV")
    a1.legend(fontsize=8)
    a1.grid(alpha=0.3)
    a2.set_ylabel("residual / mV")
    a2.set_xlabel("SOC / %")
    a2.grid(alpha=0.3)
    if r.test is not None:
        a2.set_ylim(-50, 50)
        a2.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
