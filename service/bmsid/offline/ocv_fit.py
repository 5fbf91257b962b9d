"""OCV fitting (pure numpy): Eq. 4 per branch with Table-1 statistics, hysteresis half-gap M(z).

Eq. 4 is linear in a0..a5, so each fit is ordinary least squares on ``ocv_basis``; the 95 %
bounds use the t-distribution with n - 6 degrees of freedom, as MATLAB's ``fit`` (the paper's
Table 1) does. On a dense OCV test the residuals are model misfit, correlated along SOC, so the
bounds are the conventional figures, not a calibrated uncertainty.

Low-rate OCV test (``extract_branches``), the rules in one place:

- Branches: the discharge branch is the sustained positive-current run carrying the most charge,
  the charge branch the negative one; of each run only samples within 10 % of its median current
  count (drops CV tails). Rest means |I| <= 1 % of the test's largest current.
- SOC reference: z = 1 at the start of the low-rate discharge (the test rests the cell full
  before it), z = 0 at the start of the low-rate charge (rested empty). Capacity Q = net charge
  from the discharge start to the deepest point before the charge (CV/dither parts that finish
  the discharge count), or the reverse for a charge-first test; charge is counted times the
  coulombic efficiency eta = total discharged / total charged Ah (the test ends where it began).
- IR drop: the voltage jump |dV/dI| at every rest <-> low-rate step is the ohmic drop plus the
  fast polarisation within one sample interval plus any OCV slope at that SOC, so every such
  estimate is an upper bound of the resistance and the smallest one is used as R. The branches
  are corrected to ``v_dis + |I_dis| R`` and ``v_chg - |I_chg| R`` before fitting, so the
  half-gap M is the raw half-gap minus (|I_dis| + |I_chg|) R / 2, i.e. gap - 2 I R when both
  rates match.
- Fit range: both branches' overlap, trimmed by ``trim_soc`` at each end (the steep knees load
  the ill-conditioned 1/z and ln(1-z) terms and carry the most polarisation); it becomes the
  config's [soc_min, soc_max]. The mean branch is the average of the two branch curves: Eq. 4 is
  linear, so its coefficients are the average of the branch coefficients (covariance
  (C_dis + C_chg)/4); its SSE/R^2/RMSE are against the average of the two branches' data on a
  common SOC grid.
- M(z): the corrected half-gap on that grid, least-squares fitted by a continuous piecewise-
  linear function with the Eq. 32 knots (2, 12, 88, 98 % clipped to the fit range), then
  clipped to >= 0.
"""

from __future__ import annotations

import itertools
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt
from scipy import stats

from bmsid.config.cell import (
    CellConfig,
    HysteresisTable,
    InitialParameters,
    OcvCurve,
    ParameterBounds,
)
from bmsid.errors import UserError
from bmsid.model.ocv import eval_ocv, ocv_basis

FloatArray = npt.NDArray[np.float64]

N_COEFFS = 6
#: Knots of the paper's piecewise-linear M(z) (Eq. 32): segments 2-12 %, 12-88 %, 88-98 %.
EQ32_KNOTS = (0.02, 0.12, 0.88, 0.98)
#: Highest C-rate accepted as a "low-rate" OCV branch.
MAX_OCV_C_RATE = 0.2
#: Smallest SOC span a branch and the two branches' overlap must cover.
MIN_BRANCH_SPAN = 0.5


@dataclass(frozen=True)
class Eq4Fit:
    """Eq. 4 fitted to (z, v): coefficients a0..a5 with 95 % bounds and the Table-1 statistics.

    ``sse_V2`` in V^2, ``rmse_V`` in V (sqrt(SSE / (n - 6)), MATLAB's definition), ``r2`` and
    ``r2_adj`` dimensionless; ``cov`` the coefficient covariance; ``soc_lo``..``soc_hi`` the SOC
    range of the data.
    """

    coeffs: FloatArray
    ci_low: FloatArray
    ci_high: FloatArray
    cov: FloatArray
    sse_V2: float
    r2: float
    r2_adj: float
    rmse_V: float
    n: int
    soc_lo: float
    soc_hi: float


def _table1_stats(v: FloatArray, v_fit: FloatArray) -> tuple[float, float, float, float]:
    n = v.shape[0]
    resid = v - v_fit
    sse = float(resid @ resid)
    sst = float(np.sum((v - v.mean()) ** 2))
    r2 = 1.0 - sse / sst if sst > 0 else float("nan")
    dof = n - N_COEFFS
    r2_adj = 1.0 - (1.0 - r2) * (n - 1) / dof
    return sse, r2, r2_adj, float(np.sqrt(sse / dof))


def fit_eq4(z: FloatArray, v_V: FloatArray, *, confidence: float = 0.95) -> Eq4Fit:
    """Least-squares fit of Eq. 4 to SOC ``z`` (fraction in (0, 1)) and OCV ``v_V`` (V).

    Columns are scaled to unit norm before the QR solve: the 1/z and ln terms differ by orders of
    magnitude, and on a flat LFP plateau the basis is nearly collinear.
    """
    z = np.asarray(z, dtype=np.float64)
    v = np.asarray(v_V, dtype=np.float64)
    n = z.shape[0]
    if n <= N_COEFFS:
        raise UserError(f"an Eq. 4 fit needs more than {N_COEFFS} points, got {n}")
    if np.any((z <= 0) | (z >= 1)):
        raise UserError("SOC points must lie strictly between 0 and 1 for Eq. 4")
    X = ocv_basis(z)
    scale = np.linalg.norm(X, axis=0)
    Q, R = np.linalg.qr(X / scale)
    if np.min(np.abs(np.diag(R))) < 1e-12 * np.max(np.abs(np.diag(R))):
        raise UserError("the SOC points do not determine Eq. 4 (too narrow or repeated)")
    beta_s = np.linalg.solve(R, Q.T @ v)
    coeffs = beta_s / scale
    sse, r2, r2_adj, rmse = _table1_stats(v, X @ coeffs)
    r_inv = np.linalg.inv(R)
    cov = (r_inv @ r_inv.T) / np.outer(scale, scale) * (sse / (n - N_COEFFS))
    return _with_bounds(
        coeffs,
        cov,
        n=n,
        dof=n - N_COEFFS,
        sse=sse,
        r2=r2,
        r2_adj=r2_adj,
        rmse=rmse,
        z=z,
        confidence=confidence,
    )


def _with_bounds(
    coeffs: FloatArray,
    cov: FloatArray,
    *,
    n: int,
    dof: int,
    sse: float,
    r2: float,
    r2_adj: float,
    rmse: float,
    z: FloatArray,
    confidence: float,
) -> Eq4Fit:
    half = float(stats.t.ppf(0.5 + confidence / 2.0, dof)) * np.sqrt(np.diag(cov))
    return Eq4Fit(
        coeffs=coeffs,
        ci_low=coeffs - half,
        ci_high=coeffs + half,
        cov=cov,
        sse_V2=sse,
        r2=r2,
        r2_adj=r2_adj,
        rmse_V=rmse,
        n=n,
        soc_lo=float(np.min(z)),
        soc_hi=float(np.max(z)),
    )


def _interp_sorted(z_new: FloatArray, z: FloatArray, v: FloatArray) -> FloatArray:
    order = np.argsort(z, kind="stable")
    return np.asarray(np.interp(z_new, z[order], v[order]), dtype=np.float64)


def mean_branch(
    dis: Eq4Fit,
    chg: Eq4Fit,
    *,
    z_dis: FloatArray,
    v_dis_V: FloatArray,
    z_chg: FloatArray,
    v_chg_V: FloatArray,
    confidence: float = 0.95,
) -> Eq4Fit:
    """The mean of two branch fits, scored against the averaged branch data (see module doc)."""
    coeffs = 0.5 * (dis.coeffs + chg.coeffs)
    cov = 0.25 * (dis.cov + chg.cov)
    lo = max(dis.soc_lo, chg.soc_lo)
    hi = min(dis.soc_hi, chg.soc_hi)
    n = min(dis.n, chg.n)
    grid = np.linspace(lo, hi, n)
    v_mean = 0.5 * (_interp_sorted(grid, z_dis, v_dis_V) + _interp_sorted(grid, z_chg, v_chg_V))
    sse, r2, r2_adj, rmse = _table1_stats(v_mean, eval_ocv(coeffs, grid))
    return _with_bounds(
        coeffs,
        cov,
        n=n,
        dof=n - N_COEFFS,
        sse=sse,
        r2=r2,
        r2_adj=r2_adj,
        rmse=rmse,
        z=grid,
        confidence=confidence,
    )


def fit_piecewise_linear(
    z: FloatArray, y: FloatArray, knots: Sequence[float]
) -> tuple[FloatArray, FloatArray]:
    """Continuous piecewise-linear least-squares fit of y(z) with the given knots.

    Knots outside the data range are clipped to it (duplicates dropped). Returns (knots, values).
    """
    k = np.unique(np.clip(np.asarray(knots, dtype=np.float64), np.min(z), np.max(z)))
    if k.shape[0] < 2:
        k = np.array([np.min(z), np.max(z)])
    hats = np.column_stack([np.interp(z, k, np.eye(k.shape[0])[j]) for j in range(k.shape[0])])
    vals, *_ = np.linalg.lstsq(hats, y, rcond=None)
    return k, np.asarray(vals, dtype=np.float64)


@dataclass(frozen=True)
class Branch:
    """One OCV branch: SOC (fraction), terminal voltage (V) and its current magnitude (A)."""

    z: FloatArray
    v_V: FloatArray
    current_A: float


@dataclass(frozen=True)
class OcvTestBranches:
    """Both branches of a low-rate OCV test with the SOC scale and the IR-drop estimate."""

    discharge: Branch
    charge: Branch
    capacity_Ah: float  #: capacity used for the SOC scale
    measured_capacity_Ah: float  #: capacity measured from the test (see the module doc)
    coulombic_efficiency: float
    resistance_ohm: float  #: smallest step estimate, 0 when the test has no usable step
    step_resistances_ohm: tuple[float, ...]
    notes: tuple[str, ...] = ()


@dataclass(frozen=True)
class OcvTestPart:
    """One file of an OCV test: time (s), current (A, + = discharge), cell voltage (V)."""

    t_s: FloatArray
    current_A: FloatArray
    v_V: FloatArray


def _runs(mask: npt.NDArray[np.bool_]) -> list[tuple[int, int]]:
    """Contiguous True runs as (start, stop) index pairs, stop exclusive."""
    m = np.concatenate([[False], mask, [False]]).astype(np.int8)
    edges = np.flatnonzero(np.diff(m))
    return [(int(a), int(b)) for a, b in zip(edges[::2], edges[1::2], strict=True)]


def extract_branches(
    parts: Sequence[OcvTestPart],
    *,
    capacity_Ah: float | None = None,
    coulombic_efficiency: float | None = None,
) -> OcvTestBranches:
    """Split a low-rate OCV test (one or several files, in time order) into its two branches."""
    if not parts:
        raise UserError("no OCV test data")
    notes: list[str] = []
    i_all = np.concatenate([p.current_A for p in parts])
    i_max = float(np.max(np.abs(i_all)))
    if i_max <= 0:
        raise UserError("the OCV test has no current at all")
    i_rest = 0.01 * i_max

    # Forward-held current over each sample interval; Ah per interval (dis, chg), chained.
    dis_ah, chg_ah, n_off = [], [], []
    offset = 0
    for p in parts:
        dt = np.diff(p.t_s)
        i = p.current_A[:-1]
        dis_ah.append(np.concatenate([[0.0], np.clip(i, 0, None) * dt / 3600.0]))
        chg_ah.append(np.concatenate([[0.0], np.clip(-i, 0, None) * dt / 3600.0]))
        n_off.append(offset)
        offset += p.t_s.shape[0]
    d_inc = np.concatenate(dis_ah)
    c_inc = np.concatenate(chg_ah)
    tot_dis, tot_chg = float(d_inc.sum()), float(c_inc.sum())
    if coulombic_efficiency is None:
        eta = tot_dis / tot_chg if tot_chg > 0 else 1.0
        if not 0.95 <= eta <= 1.0:
            notes.append(
                f"discharged/charged Ah = {eta:.4f} is no plausible efficiency (the test does not "
                "end where it began); eta = 1 used"
            )
            eta = 1.0
    else:
        eta = coulombic_efficiency
    q = np.cumsum(d_inc - eta * c_inc)  # net Ah removed, at each sample
    v_all = np.concatenate([p.v_V for p in parts])

    # Sign runs (never across file boundaries: a boundary is a break in the record).
    sign = np.where(i_all > i_rest, 1, np.where(i_all < -i_rest, -1, 0))
    boundary = np.zeros(i_all.shape[0], dtype=bool)
    boundary[np.asarray(n_off[1:], dtype=np.int64)] = True
    best: dict[int, tuple[float, int, int]] = {}
    for s in (1, -1):
        for a, b in _runs(sign == s):
            cuts = [a, *[int(k) for k in np.flatnonzero(boundary[a + 1 : b]) + a + 1], b]
            for aa, bb in itertools.pairwise(cuts):
                ah = abs(float(q[bb - 1] - q[aa]))
                if ah > best.get(s, (0.0, 0, 0))[0]:
                    best[s] = (ah, aa, bb)
    for s, name in ((1, "discharge"), (-1, "charge")):
        if s not in best:
            hint = (
                " (does the tester count charge positive? use --charge-positive)" if s == 1 else ""
            )
            raise UserError(
                f"the OCV test has no {name} branch: no sustained "
                f"{'positive' if s == 1 else 'negative'} current{hint}; give both branches"
            )
    _, da, db = best[1]
    _, ca, cb = best[-1]
    # Discharge first: the deepest point between the discharge start and the charge start.
    measured_q = float(np.max(q[da:ca]) - q[da]) if da < ca else float(q[ca] - np.min(q[ca:da]))
    if measured_q <= 0:
        raise UserError("cannot measure the capacity from the OCV test")
    cap = capacity_Ah if capacity_Ah is not None else measured_q

    def branch(a: int, b: int, s: int, name: str) -> Branch:
        i_run = np.abs(i_all[a:b])
        i_med = float(np.median(i_run))
        keep = np.flatnonzero(np.abs(i_run - i_med) <= 0.1 * i_med) + a
        z = 1.0 - (q[keep] - q[a]) / cap if s == 1 else (q[a] - q[keep]) / cap
        rate = i_med / cap
        if rate > MAX_OCV_C_RATE:
            raise UserError(
                f"the {name} branch runs at {i_med:g} A = C/{1 / rate:.1f} for {cap:.4g} Ah: too "
                "fast for an OCV test (want C/20-C/30); current in mA or wrong capacity?"
            )
        span = float(np.ptp(z))
        if span < MIN_BRANCH_SPAN:
            raise UserError(
                f"the {name} branch covers only {100 * span:.0f} % of {cap:.4g} Ah; an OCV test "
                f"needs a full {name}"
            )
        return Branch(z=z, v_V=v_all[keep], current_A=i_med)

    dis = branch(da, db, 1, "discharge")
    chg = branch(ca, cb, -1, "charge")

    # IR steps: the rest <-> low-rate transitions at both ends of both branch runs.
    steps: list[float] = []
    for a, b in ((da, db), (ca, cb)):
        for k0, k1 in ((a - 1, a), (b - 1, b)):
            same_file = k0 >= 0 and k1 < i_all.shape[0] and not boundary[k1]
            if same_file and min(abs(i_all[k0]), abs(i_all[k1])) <= i_rest:
                di = float(i_all[k1] - i_all[k0])
                steps.append(abs(float(v_all[k1] - v_all[k0]) / di))
    if steps:
        r_ohm = min(steps)
    else:
        r_ohm = 0.0
        notes.append("no rest <-> current step in the test: M is not corrected for the IR drop")
    return OcvTestBranches(
        discharge=dis,
        charge=chg,
        capacity_Ah=cap,
        measured_capacity_Ah=measured_q,
        coulombic_efficiency=eta,
        resistance_ohm=r_ohm,
        step_resistances_ohm=tuple(steps),
        notes=tuple(notes),
    )


@dataclass(frozen=True)
class OcvFitResult:
    """Everything ``fit-ocv`` reports and stores.

    ``m_soc``/``m_V``: the M(z) table (fraction, V). ``half_gap_raw_V`` / ``half_gap_V``: the raw
    and IR-corrected half-gaps on ``gap_soc`` (both None with a single branch).
    """

    mean: Eq4Fit
    discharge: Eq4Fit | None
    charge: Eq4Fit | None
    soc_min: float
    soc_max: float
    m_soc: FloatArray
    m_V: FloatArray
    gap_soc: FloatArray | None = None
    half_gap_raw_V: FloatArray | None = None
    half_gap_V: FloatArray | None = None
    notes: tuple[str, ...] = field(default_factory=tuple)


def _in_range(z: FloatArray, v: FloatArray, lo: float, hi: float) -> tuple[FloatArray, FloatArray]:
    k = (z >= lo) & (z <= hi)
    return z[k], v[k]


def fit_two_branches(
    z_dis: FloatArray,
    v_dis_V: FloatArray,
    z_chg: FloatArray,
    v_chg_V: FloatArray,
    *,
    trim_soc: float = 0.02,
    knots: Sequence[float] = EQ32_KNOTS,
    raw_offset_V: float = 0.0,
    notes: Sequence[str] = (),
) -> OcvFitResult:
    """Fit discharge, charge and mean branches and M(z) from (IR-corrected) branch data.

    ``raw_offset_V`` is the IR correction already applied to the half-gap (reported only: the raw
    half-gap is the corrected one plus it).
    """
    lo = max(float(np.min(z_dis)), float(np.min(z_chg)), trim_soc)
    hi = min(float(np.max(z_dis)), float(np.max(z_chg)), 1.0 - trim_soc)
    if hi - lo < MIN_BRANCH_SPAN:
        raise UserError(
            f"the charge and discharge branches overlap only on SOC {100 * lo:.0f}-{100 * hi:.0f} %"
        )
    zd, vd = _in_range(z_dis, v_dis_V, lo, hi)
    zc, vc = _in_range(z_chg, v_chg_V, lo, hi)
    dis = fit_eq4(zd, vd)
    chg = fit_eq4(zc, vc)
    mean = mean_branch(dis, chg, z_dis=zd, v_dis_V=vd, z_chg=zc, v_chg_V=vc)
    grid = np.linspace(lo, hi, 201)
    half = 0.5 * (_interp_sorted(grid, zc, vc) - _interp_sorted(grid, zd, vd))
    m_soc, m_vals = fit_piecewise_linear(grid, half, knots)
    m_vals = np.clip(m_vals, 0.0, 0.5)
    return OcvFitResult(
        mean=mean,
        discharge=dis,
        charge=chg,
        soc_min=lo,
        soc_max=hi,
        m_soc=m_soc,
        m_V=m_vals,
        gap_soc=grid,
        half_gap_raw_V=half + raw_offset_V,
        half_gap_V=half,
        notes=tuple(notes),
    )


def fit_ocv_test(
    branches: OcvTestBranches, *, trim_soc: float = 0.02, knots: Sequence[float] = EQ32_KNOTS
) -> OcvFitResult:
    """Fit an OCV test's branches after the IR correction of the module doc."""
    r = branches.resistance_ohm
    dis, chg = branches.discharge, branches.charge
    return fit_two_branches(
        dis.z,
        dis.v_V + dis.current_A * r,
        chg.z,
        chg.v_V - chg.current_A * r,
        trim_soc=trim_soc,
        knots=knots,
        raw_offset_V=0.5 * (dis.current_A + chg.current_A) * r,
        notes=branches.notes,
    )


def fit_rest_points(
    discharge: tuple[FloatArray, FloatArray] | None,
    charge: tuple[FloatArray, FloatArray] | None,
    *,
    m_table: tuple[FloatArray, FloatArray] | None = None,
    trim_soc: float = 0.02,
    knots: Sequence[float] = EQ32_KNOTS,
) -> OcvFitResult:
    """Fit rest-point tables (SOC fraction, OCV V) with one or both branches.

    Rest voltages carry no IR drop, so no correction is applied. Points at or beyond
    [trim_soc, 1 - trim_soc] are moved onto it (tables start and end at 0 % and 100 %, where
    Eq. 4 is singular; with ~10 points a narrower trim lets the 1/z term bend the curve
    upwards below the lowest interior point). With both branches M(z) is the piecewise-linear
    fit of the half-gap on their overlap (ends held beyond it); with one, ``m_table`` (soc, M_V)
    is used, or M = 0 with a note. The mean is Eq. 4 fitted to all points shifted onto the
    mean: discharge points + M(z), charge points - M(z) (Plett's convention: discharge lies M
    below the mean), over the union of the branches' SOC ranges, which becomes the config's
    [soc_min, soc_max].
    """
    notes: list[str] = []
    branches: dict[str, tuple[FloatArray, FloatArray]] = {}
    for name, pts in (("discharge", discharge), ("charge", charge)):
        if pts is None:
            continue
        z, n_moved = clamp_soc_points(np.asarray(pts[0], dtype=np.float64), trim_soc)
        if n_moved:
            notes.append(f"{n_moved} {name} point(s) moved onto SOC [{trim_soc}, {1 - trim_soc}]")
        branches[name] = (z, np.asarray(pts[1], dtype=np.float64))
    if not branches:
        raise UserError("no rest points given")
    fits = {name: fit_eq4(z, v) for name, (z, v) in branches.items()}
    gap_soc = half = None
    if len(branches) == 2:
        (zd, vd), (zc, vc) = branches["discharge"], branches["charge"]
        lo, hi = max(zd.min(), zc.min()), min(zd.max(), zc.max())
        if hi - lo < MIN_BRANCH_SPAN:
            raise UserError(f"the branches overlap only on SOC {100 * lo:.0f}-{100 * hi:.0f} %")
        gap_soc = np.linspace(lo, hi, 201)
        half = 0.5 * (_interp_sorted(gap_soc, zc, vc) - _interp_sorted(gap_soc, zd, vd))
        m_soc, m_vals = fit_piecewise_linear(gap_soc, half, knots)
        m_vals = np.clip(m_vals, 0.0, 0.5)
    elif m_table is not None:
        m_soc, m_vals = (np.asarray(a, dtype=np.float64) for a in m_table)
        notes.append("M(z) taken from the given hysteresis table")
    else:
        m_soc, m_vals = np.array([0.0, 1.0]), np.array([0.0, 0.0])
        notes.append("one branch and no hysteresis table: M = 0 and the mean is that branch")
    z_all, v_all = [], []
    for name, (z, v) in branches.items():
        sign = 1.0 if name == "discharge" else -1.0
        z_all.append(z)
        v_all.append(v + sign * np.interp(z, m_soc, m_vals))
    mean = fit_eq4(np.concatenate(z_all), np.concatenate(v_all))
    return OcvFitResult(
        mean=mean,
        discharge=fits.get("discharge"),
        charge=fits.get("charge"),
        soc_min=mean.soc_lo,
        soc_max=mean.soc_hi,
        m_soc=m_soc,
        m_V=m_vals,
        gap_soc=gap_soc,
        half_gap_raw_V=half,
        half_gap_V=half,
        notes=tuple(notes),
    )


def clamp_soc_points(z: FloatArray, trim_soc: float) -> tuple[FloatArray, int]:
    """SOC points moved into [trim_soc, 1 - trim_soc], and how many had to move."""
    zc = np.clip(z, trim_soc, 1.0 - trim_soc)
    return zc, int(np.count_nonzero(zc != z))


def monotonicity_violation_V(coeffs: FloatArray, soc_lo: float, soc_hi: float) -> float:
    """Largest drop (V) of Eq. 4 below its running maximum on [soc_lo, soc_hi]; 0 if monotone."""
    v = eval_ocv(coeffs, np.linspace(soc_lo, soc_hi, 1001))
    return float(np.max(np.maximum.accumulate(v) - v))


def build_cell_config(
    result: OcvFitResult,
    *,
    name: str,
    capacity_Ah: float,
    coulombic_efficiency: float,
    chemistry: str = "unknown",
    gamma: float = 30.0,
    bounds: ParameterBounds | None = None,
    initial: InitialParameters | None = None,
) -> CellConfig:
    """The cell config for a fit: Eq. 4 branches, valid SOC range and M table."""

    def lst(a: FloatArray) -> list[float]:
        return [float(x) for x in a]

    return CellConfig(
        name=name,
        chemistry=chemistry,
        capacity_Ah=capacity_Ah,
        coulombic_efficiency=coulombic_efficiency,
        ocv=OcvCurve(
            mean=lst(result.mean.coeffs),
            charge=lst(result.charge.coeffs) if result.charge is not None else None,
            discharge=lst(result.discharge.coeffs) if result.discharge is not None else None,
            soc_min=result.soc_min,
            soc_max=result.soc_max,
        ),
        hysteresis=HysteresisTable(soc=lst(result.m_soc), M_V=lst(result.m_V), gamma=gamma),
        bounds=bounds if bounds is not None else ParameterBounds(),
        initial=initial,
    )
