"""OCV fitting (pure numpy/scipy): Eq. 4 per branch with Table-1 statistics, hysteresis M(z)
(Eq. 10/32) with confidence intervals, the test's polarisation, and the ends of the SOC range.

Eq. 4 is linear in a0..a5, so each fit is ordinary least squares on ``ocv_basis``; the 95 %
bounds use the t-distribution with n - 6 degrees of freedom, as MATLAB's ``fit`` (the paper's
Table 1) does. On a dense OCV test the residuals are model misfit, correlated along SOC, so the
bounds are the conventional figures, not a calibrated uncertainty.

Low-rate OCV test (``extract_branches``, ``fit_ocv_test``), the rules in one place:

- Branches: the discharge branch is the sustained positive-current run carrying the most charge,
  the charge branch the negative one; of each run only samples within 10 % of its median current
  count (drops CV tails). Rest means |I| <= 1 % of the test's largest current. Several files are
  one test in time order; nothing is counted across a file boundary (unknown pause).
- SOC: z = 1 at the fullest point before the low-rate discharge (the test rests the cell full
  before it; a pulse or top-up between that rest and the branch counts), z = 0 at the deepest
  point before the charge (CV/dither parts that finish the discharge count), Q = the charge
  between them (or the reverse for a charge-first test). The throughput counts from there too.
- Throughput (``Throughput``): the Ah out of the first branch's side and back in on the second's
  are compared. More back in than out: their ratio is the measured coulombic efficiency and each
  branch spans its own throughput (normalised: Plett's method). Less back in than out (the
  issue case: 2.61 of 3.00 Ah): the rested voltage where the test ends is compared with the one
  it started from. If it closes (the SOC the voltage difference means at the second branch's
  end slope is under half the SOC the Ah say is missing) the mismatch is counting, not charge:
  normalised, eta = out/in > 1 stored as the charge-counting factor. Otherwise the second
  branch really ended short: counted with eta = 1 and it ends where it ends. Forcing eta = 1 on
  a closed test would shift the charge branch by the whole mismatch and fake a hysteresis.
- Polarisation (``Polarisation``): at C/20 the RC branches run in steady state, so each branch
  sits I (R0 + R1 + R2) off its OCV and the gap is ``2 M + (I_dis + I_chg)(R0 + R1 + R2)``: one
  IR drop (R0) for the polarisation overstates M, the whole DC resistance must come out. It is
  measured on the test's own rests, never taken from the gap: a 2RC model (Eq. 7-8) fitted to
  the relaxation of each rest that follows a branch (the hysteresis state is frozen at rest, so
  the relaxation is the RC branches only; R0 is the jump, R1/R2 the amplitudes over the run's
  current). The relaxation at a knee or with solid diffusion at an end of the SOC range is
  larger than mid-SOC, and only ever larger, so the smallest fit is used, and the M knot at the
  end where a larger one was measured carries the difference in its CI. A polarisation larger
  than the mid-SOC raw half-gap allows with M >= 0 is reported, not scaled to fit the gap (the
  corrected gap then comes out negative, and M is decided from its CI below), unless it is
  more than ``KNEE_FACTOR`` times that: then it measured the OCV relaxing at a knee and is left
  out (so one export of a test gives what its split into files gives), as is a one-sample step
  that large; a fit that does not settle within its rest is none. Without a rest
  long enough (>= 300 s) R0 is the one-sample step |dV/dI| (R0 plus what relaxes within one
  sample) with the lowest upper bound |dV/dI| + 2 se (a coarse sample's step holds more
  relaxation; its noise counts) and the RC part, which the test does not measure, is taken as
  ``UNMEASURED_RC_SHARE`` times it with a standard error as large (the CI says so). The model
  runs over the whole test with its own current and corrects every sample:
  ``v + R0 i + R1 x1 + R2 x2`` (x the unit-gain branch states), the polarisation as it builds
  up after each step, instead of one IR drop.
- Hysteresis: h is run along the test with the one-state model (Eq. 5-6, rate ``gamma``,
  starting at +1 when the test starts full after a charge); the corrected branches are
  ``OCV(z) + M(z) h``, so the gap v_chg - v_dis = M(z) (h_chg - h_dis) is fitted for the
  Eq. 32 knots (clipped to the fit range) by least squares (``fit_hysteresis``): the branch
  starts, where h is still turning, count with their smaller weight instead of biasing M. The
  95 % CI of each knot combines the residual scatter (inflated for its autocorrelation along
  SOC) with the polarisation's standard error, and in quadrature the knot's sensitivity to
  gamma (not fitted: the largest change of the knot over gamma / ``GAMMA_SPAN`` .. gamma *
  ``GAMMA_SPAN``; it matters at the branch starts) and to a larger polarisation measured at
  that end. The evidence for hysteresis is a constant M fitted to mid-SOC, where h is
  saturated even at the slow gamma (``pooled``): present when its 95 % CI excludes 0.
  ``decide_hysteresis`` turns the knots into the stored table: a knot whose CI excludes 0 is
  kept; one whose CI includes 0 or whose estimate is negative keeps max(estimate, the pooled
  lower bound) when hysteresis is present (never 0), and 0 when it is not; every such knot is
  named in a note, and its stored CI covers the knot's own interval.
- Mean and fit range: the mean is Eq. 4 fitted to both branches' corrected data less M(z) h,
  on both branches' overlap trimmed by ``trim_soc`` at each end; that range becomes the
  config's [soc_min, soc_max]. Eq. 4 per branch is fitted for reporting.
- Ends: the last 5 % of the longest rest (>= 600 s) within 0.5 % SOC of 0 and of 1 is the
  rested voltage there; the mean continues to it by the monotone C1 segment of
  ``model.ocv.end_segment`` (the join moves inwards in 0.5 % steps until one exists), and M is
  0 at that end (one rested voltage: the branches meet).
- Correction table (``ocv_correction``): what Eq. 4 misses of the mean data (each branch's
  data less M(z) h, less Eq. 4), binned along SOC and averaged over the branches, written when
  it exceeds the test's voltage noise; the ends then join Eq. 4 plus it.
- Residuals: each branch against the whole model (extended mean + M h) per SOC band.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from typing import Literal

import numpy as np
import numpy.typing as npt
from scipy import optimize, stats

from bmsid.config.cell import (
    CellConfig,
    HysteresisTable,
    InitialParameters,
    OcvCurve,
    ParameterBounds,
)
from bmsid.errors import UserError
from bmsid.model.ecm import rc_decay
from bmsid.model.ocv import (
    OcvModel,
    end_segment,
    eval_ocv,
    ocv_basis,
    table_join,
    table_slopes,
)
from bmsid.offline.ocv_correction import OcvCorrection, fit_correction

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


#: Rest: |I| at most this fraction of the test's largest current.
REST_FRACTION = 0.01
#: A branch carries at least this share of the other branch's charge (less is current noise
#: across the rest threshold, or a pulse).
MIN_BRANCH_SHARE = 0.2
#: Shortest rest (s) after a branch whose relaxation is fitted for the polarisation.
MIN_RELAX_S = 300.0
#: Shortest rest (s) whose voltage counts as a rested end voltage (empty or full).
MIN_END_REST_S = 600.0
#: A rest within this SOC of 0 or 1 gives that end's rested voltage.
END_SOC_TOL = 0.005
#: SOC bands (fractions) of the residual report: the ends, then 10 % bands.
SOC_BANDS = (0.0, 0.02, 0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 0.7, 0.8, 0.9, 0.98, 1.0)
#: The loaded voltage at the switch into a rest: a quadratic through the run's last this many
#: samples, extrapolated. A line is biased where the branch ends in a knee (the voltage bends
#: there: on the synthetic LFP test it put R 25 % low); one sample carries its full noise.
LOAD_FIT_SAMPLES = 20
LOAD_FIT_DEGREE = 2
#: Shortest constant-current run (s) whose ends count as current steps for R0.
MIN_STEP_RUN_S = 30.0
#: Floor of the voltage noise estimate (V): a quantised logger's rests can show no spread.
MIN_VOLTAGE_NOISE_V = 1e-4
#: Without a relaxation fit, the RC part R1 + R2 (not measured by the test) is taken as this
#: times the chosen one-sample step, with a standard error as large (an assumption the CI
#: carries): a Li-ion cell's DC resistance at low rate is typically one to three times R0 (the
#: DFN cell's relaxation at 99 % SOC: 3.6 times its jump), and the step already holds one
#: sample's worth of relaxation.
UNMEASURED_RC_SHARE = 1.0
#: Time constant (s) given to that unmeasured RC part: where it matters (the first minutes of a
#: branch) the M fit weighs little.
UNMEASURED_RC_TAU_S = 300.0
#: A polarisation candidate (relaxation fit or step) whose R0 + R1 + R2 exceeds this times what
#: the mid-SOC raw half-gap allows with M >= 0 (beyond 2 se) would reverse the gap by more than
#: the whole measured gap: it measured a knee (the OCV's own relaxation at an end of the SOC
#: range, or a step taken there), not the polarisation mid-SOC, and is not used. A 1.4x excess
#: (the DFN cell's 99 % relaxation) is within the polarisation's variation along SOC.
KNEE_FACTOR = 2.0
#: gamma is not fitted: each M knot's CI carries its change over gamma / GAMMA_SPAN .. gamma *
#: GAMMA_SPAN (an order of magnitude; published one-state fits range over more).
GAMMA_SPAN = 3.0
#: Mid-SOC for the pooled (constant-M) evidence: where the branches' weight h_chg - h_dis is at
#: least this even at the slow gamma (h saturated on both branches).
POOLED_MIN_WEIGHT = 1.8


@dataclass(frozen=True)
class OcvTestPart:
    """One file of an OCV test: time (s), current (A, + = discharge), cell voltage (V)."""

    t_s: FloatArray
    current_A: FloatArray
    v_V: FloatArray


@dataclass(frozen=True)
class RelaxationFit:
    """A 2RC fit to the rest after a low-rate branch: ``v(t) = v_inf - A1 e^(-t/tau1) -
    A2 e^(-t/tau2)`` (Eq. 7-8 with i = 0), t from the first rest sample.

    R0 (ohm) is the jump at the step, R1/R2 (ohm) the branch amplitudes over the run's current
    (steady state corrected for the run's length); ``r_total_se_ohm`` the standard error of
    R0 + R1 + R2 from the fit's covariance of v_inf plus the noise of the last loaded sample.
    """

    after: str
    soc: float
    duration_s: float
    current_A: float
    R0_ohm: float
    R1_ohm: float
    tau1_s: float
    R2_ohm: float
    tau2_s: float
    r_total_se_ohm: float
    rmse_V: float

    @property
    def r_total_ohm(self) -> float:
        """DC polarisation resistance R0 + R1 + R2 (ohm) at the test's rate."""
        return self.R0_ohm + self.R1_ohm + self.R2_ohm


@dataclass(frozen=True)
class Polarisation:
    """The test's polarisation model (2RC, Eq. 7-9 without OCV and hysteresis) and where it
    comes from. ``r_total_se_ohm`` None: not corrected, no error estimate. ``steps``: the
    test's one-sample current steps (``current_steps``)."""

    R0_ohm: float
    R1_ohm: float
    tau1_s: float
    R2_ohm: float
    tau2_s: float
    r_total_se_ohm: float | None
    source: str
    relaxations: tuple[RelaxationFit, ...] = ()
    steps: tuple[CurrentStep, ...] = ()
    knee: tuple[RelaxationFit, ...] = ()  #: relaxations not used: they measured a knee

    @property
    def step_resistances_ohm(self) -> tuple[float, ...]:
        """|dV/dI| of each current step (ohm)."""
        return tuple(st.r_ohm for st in self.steps)

    @property
    def r_total_ohm(self) -> float:
        """DC polarisation resistance R0 + R1 + R2 (ohm)."""
        return self.R0_ohm + self.R1_ohm + self.R2_ohm


@dataclass(frozen=True)
class Throughput:
    """Charge counted on each side of the test (Ah, eta = 1) and how SOC was scaled.

    ``method``: ``normalised`` (each branch spans its own throughput: eta = discharged / charged
    Ah over the closed cycle), ``counted`` (charge counted with eta = 1: the second branch ends
    where it ends) or ``given`` (the user's eta).
    """

    discharge_Ah: float
    charge_Ah: float
    method: Literal["normalised", "counted", "given"]
    eta: float
    reason: str

    @property
    def mismatch_Ah(self) -> float:
        """Charge minus discharge throughput, Ah."""
        return self.charge_Ah - self.discharge_Ah

    @property
    def mismatch_pct(self) -> float:
        """``mismatch_Ah`` in % of the discharge throughput."""
        return 100.0 * self.mismatch_Ah / self.discharge_Ah


@dataclass(frozen=True)
class Branch:
    """One OCV branch: SOC (fraction), polarisation-corrected and measured terminal voltage (V),
    the one-state hysteresis state h along the test (Eq. 5-6) and the branch current (A).
    ``h_span``: h run with gamma / ``GAMMA_SPAN`` and gamma * ``GAMMA_SPAN`` (the knots' gamma
    sensitivity; None: not computed)."""

    z: FloatArray
    v_V: FloatArray
    v_raw_V: FloatArray
    h: FloatArray
    current_A: float
    h_span: tuple[FloatArray, FloatArray] | None = None


@dataclass(frozen=True)
class OcvTestBranches:
    """Both branches of a low-rate OCV test with the SOC scale, the polarisation model, the
    hysteresis rate used for h, and the rested voltages at empty/full (None: not measured)."""

    discharge: Branch
    charge: Branch
    capacity_Ah: float  #: capacity used for the SOC scale
    measured_capacity_Ah: float  #: capacity measured from the test (see the module doc)
    coulombic_efficiency: float
    throughput: Throughput
    polarisation: Polarisation
    gamma: float
    v_empty_V: float | None = None
    v_full_V: float | None = None
    notes: tuple[str, ...] = ()


def c_rate_text(rate: float) -> str:
    """A C-rate (1/h) as a tester writes it: ``C/20`` below 1C, ``2C`` or ``15.3C`` above."""
    if rate <= 0:
        return "0C"
    return f"{rate:.3g}C" if rate >= 1.0 else f"C/{1.0 / rate:.3g}"


def _runs(mask: npt.NDArray[np.bool_]) -> list[tuple[int, int]]:
    """Contiguous True runs as (start, stop) index pairs, stop exclusive."""
    m = np.concatenate([[False], mask, [False]]).astype(np.int8)
    edges = np.flatnonzero(np.diff(m))
    return [(int(a), int(b)) for a, b in zip(edges[::2], edges[1::2], strict=True)]


def fit_relaxation(
    t_s: FloatArray,
    v_V: FloatArray,
    *,
    current_A: float,
    v_load_V: float,
    run_s: float,
    v_load_se_V: float = 0.0,
) -> RelaxationFit | None:
    """Fit the rest after a constant-current run of ``current_A`` (A, + = discharge) lasting
    ``run_s`` (s) that ended at ``v_load_V`` (V, standard error ``v_load_se_V``) at the switch;
    ``t_s``/``v_V`` are the rest's samples, the first one at the switch. None when the rest is
    too short or the fit fails.

    Two exponentials with tau2 > tau1 (scipy ``curve_fit``; one if two do not converge): the
    relaxation of the two RC branches with the hysteresis state frozen at rest (Plett).
    """
    t = np.asarray(t_s, dtype=np.float64) - float(t_s[0])
    v = np.asarray(v_V, dtype=np.float64)
    if t.shape[0] < 8 or t[-1] < MIN_RELAX_S or current_A == 0:
        return None
    sgn = 1.0 if current_A > 0 else -1.0  # a rest after discharge relaxes upwards
    span = abs(float(v[-1] - v[0])) + 1e-6
    dt = float(np.median(np.diff(t)))
    lt_lo, lt_hi = np.log(max(dt / 2.0, 1e-3)), np.log(t[-1])

    def two(
        tt: FloatArray, v_inf: float, a1: float, lt1: float, a2: float, ld: float
    ) -> FloatArray:
        return np.asarray(
            v_inf - sgn * (a1 * np.exp(-tt / np.exp(lt1)) + a2 * np.exp(-tt / np.exp(lt1 + ld))),
            dtype=np.float64,
        )

    def one(tt: FloatArray, v_inf: float, a1: float, lt1: float) -> FloatArray:
        return np.asarray(v_inf - sgn * a1 * np.exp(-tt / np.exp(lt1)), dtype=np.float64)

    p0_lt = float(np.clip(np.log(t[-1] / 20.0), lt_lo, lt_hi))
    try:
        p, cov = optimize.curve_fit(
            two, t, v, p0=[float(v[-1]), span / 2, p0_lt, span / 2, np.log(10.0)],
            bounds=([-np.inf, 0, lt_lo, 0, 0], [np.inf, np.inf, lt_hi, np.inf, np.log(100.0)]),
            max_nfev=5000,
        )  # fmt: skip
        fit = two(t, *p)
        a1, tau1, a2, tau2 = (
            float(p[1]),
            float(np.exp(p[2])),
            float(p[3]),
            float(np.exp(p[2] + p[4])),
        )
    except (RuntimeError, ValueError):
        try:
            p, cov = optimize.curve_fit(
                one, t, v, p0=[float(v[-1]), span, p0_lt],
                bounds=([-np.inf, 0, lt_lo], [np.inf, np.inf, lt_hi]), max_nfev=5000,
            )  # fmt: skip
        except (RuntimeError, ValueError):
            return None
        fit = one(t, *p)
        a1, tau1, a2, tau2 = float(p[1]), float(np.exp(p[2])), 0.0, 10.0 * float(np.exp(p[2]))
    resid = v - fit
    s2 = float(resid @ resid) / max(t.shape[0] - p.shape[0], 1)
    # More left to relax after the rest than it showed: v_inf and the amplitudes extrapolate.
    left = a1 * math.exp(-t[-1] / tau1) + a2 * math.exp(-t[-1] / tau2)
    if not np.all(np.isfinite(p)) or left > max(span, 3.0 * math.sqrt(s2)):
        return None
    i_abs = abs(current_A)
    se = float(np.sqrt(max(float(cov[0, 0]), 0.0) + v_load_se_V**2)) / i_abs
    if not np.isfinite(se):
        return None

    def steady(a: float, tau: float) -> float:  # the branch had run_s to charge up
        return a / (i_abs * -math.expm1(-run_s / tau))

    r1, r2 = steady(a1, tau1), steady(a2, tau2)
    if not (r1 >= 0 and r2 >= 0 and math.isfinite(r1 + r2)):
        return None
    return RelaxationFit(
        after="discharge" if current_A > 0 else "charge",
        soc=float("nan"),
        duration_s=float(t[-1]),
        current_A=current_A,
        R0_ohm=max(sgn * float(fit[0] - v_load_V) / i_abs, 0.0),
        R1_ohm=r1,
        tau1_s=tau1,
        R2_ohm=r2,
        tau2_s=tau2,
        r_total_se_ohm=se,
        rmse_V=float(np.sqrt(s2)),
    )


def branch_states(
    t_s: FloatArray,
    current_A: FloatArray,
    file_start: npt.NDArray[np.bool_],
    *,
    tau1_s: float,
    tau2_s: float,
    kappa_dis: float,
    kappa_chg: float,
    h0: float,
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Unit-gain RC states x1, x2 (A; branch voltage U_j = R_j x_j) and hysteresis h along the
    test (Eq. 5-8, ``model.ecm``), each at its sample before that sample's current acts.

    The current is held forward over each interval; the RC states restart at 0 at every file
    start (a file begins after a rest of unknown length), h carries on (it does not relax at
    rest). ``kappa_dis``/``kappa_chg``: Eq. 6's kappa (1/(A s)) on discharge / charge.
    """
    n = t_s.shape[0]
    dt = held_intervals(t_s, file_start)
    a1 = rc_decay(dt, tau1_s)
    a2 = rc_decay(dt, tau2_s)
    kappa = np.where(current_A < 0, kappa_chg, kappa_dis)
    x1, x2, h = np.zeros(n), np.zeros(n), np.zeros(n)
    u1 = u2 = 0.0
    hk = h0
    for k, (i, s1, s2, d, kp, first) in enumerate(
        zip(current_A.tolist(), a1.tolist(), a2.tolist(), dt.tolist(), kappa.tolist(),
            file_start.tolist(), strict=True)
    ):  # fmt: skip
        if first:
            u1 = u2 = 0.0
        x1[k], x2[k], h[k] = u1, u2, hk
        u1 = s1 * u1 + (1.0 - s1) * i
        u2 = s2 * u2 + (1.0 - s2) * i
        decay = math.exp(-abs(kp * i) * d)
        hk = decay * hk - (1.0 - decay) * (1.0 if i > 0 else -1.0 if i < 0 else 0.0)
    return x1, x2, h


@dataclass(frozen=True)
class CurrentStep:
    """A one-sample step between rest and a constant current: |dV/dI| (ohm) with its standard
    error from the voltage noise (``sqrt(2) sigma_v / |dI|``), at sample ``index``. ``onset``:
    from rest into the current (the rested voltage before it is not yet moved by the run; at
    a run's end the last loaded interval's OCV drift is in the step too)."""

    r_ohm: float
    se_ohm: float
    index: int
    onset: bool


def voltage_noise_V(v_V: FloatArray, rests: Sequence[tuple[int, int]]) -> float:
    """Sample-to-sample voltage noise (V, one sample's sigma): the median over rests of >= 10
    samples of the robust spread (MAD) of their first differences over sqrt(2); at least
    0.1 mV (a quantised logger's MAD can be 0)."""
    sig = [
        1.4826 * float(np.median(np.abs(d - np.median(d)))) / math.sqrt(2.0)
        for a, b in rests
        if b - a >= 10
        for d in (np.diff(v_V[a:b]),)
    ]
    return max(float(np.median(sig)) if sig else 0.0, MIN_VOLTAGE_NOISE_V)


def current_steps(
    t_s: FloatArray,
    current_A: FloatArray,
    v_V: FloatArray,
    file_start: npt.NDArray[np.bool_],
    *,
    i_rest: float,
    rests: Sequence[tuple[int, int]],
) -> list[CurrentStep]:
    """The steps at the ends of every constant-current run (>= ``MIN_STEP_RUN_S``, its first or
    last 3 samples within 10 % of each other) that meet a rest sample (|I| <= ``i_rest``) in
    the same file: R0 plus what relaxes within one sample, each with its noise error."""
    sigma = voltage_noise_V(v_V, rests)
    sign = np.where(current_A > i_rest, 1, np.where(current_A < -i_rest, -1, 0))
    n = current_A.shape[0]
    out: list[CurrentStep] = []
    for s in (1, -1):
        for a, b in _runs(sign == s):
            if b - a < 4 or t_s[b - 1] - t_s[a] < MIN_STEP_RUN_S or file_start[a + 1 : b].any():
                continue
            for k0, k1, edge, onset in (
                (a - 1, a, current_A[a : a + 3], True),
                (b - 1, b, current_A[b - 3 : b], False),
            ):
                if k0 < 0 or k1 >= n or file_start[k1]:
                    continue
                if np.ptp(edge) > 0.1 * float(np.min(np.abs(edge))):
                    continue
                if min(abs(current_A[k0]), abs(current_A[k1])) > i_rest:
                    continue
                di = abs(float(current_A[k1] - current_A[k0]))
                dv = abs(float(v_V[k1] - v_V[k0]))
                out.append(CurrentStep(dv / di, math.sqrt(2.0) * sigma / di, k1, onset))
    return sorted(out, key=lambda st: st.index)


def relaxation_after(
    t_s: FloatArray, current_A: FloatArray, v_V: FloatArray, run: tuple[int, int],
    rests: Sequence[tuple[int, int]],
) -> tuple[RelaxationFit, int] | None:  # fmt: skip
    """The relaxation fit (``fit_relaxation``) of the rest that starts at the end of the
    constant-current ``run`` [a, b) (noise at rest may blur the end by a sample), from the
    loaded voltage at the switch extrapolated from the run's last samples, and the rest's first
    sample; None without a rest there or a fit."""
    a, b = run
    rest = next(((ra, rb) for ra, rb in rests if abs(ra - b) <= 3 and ra > a), None)
    if rest is None:
        return None
    ra, rb = rest
    k0 = max(a, ra - LOAD_FIT_SAMPLES)
    tt, vv = t_s[k0:ra] - t_s[ra], v_V[k0:ra]
    if tt.shape[0] >= 4 + LOAD_FIT_DEGREE:
        coef, cov_l = np.polyfit(tt, vv, LOAD_FIT_DEGREE, cov=True)
        v_sw = float(coef[-1])
        v_sw_se = float(np.sqrt(max(float(cov_l[-1, -1]), 0.0)))
    else:
        v_sw, v_sw_se = float(v_V[ra - 1]), 0.0
    fit = fit_relaxation(
        t_s[ra:rb], v_V[ra:rb], current_A=float(np.median(current_A[a:b])),
        v_load_V=float(v_sw), run_s=float(t_s[ra] - t_s[a]), v_load_se_V=v_sw_se,
    )  # fmt: skip
    return None if fit is None else (fit, ra)


def _end_voltage(v: FloatArray, a: int, b: int) -> float:
    """Rested voltage of the rest [a, b): the mean of its last 5 % (at least one sample)."""
    k = max(1, (b - a) // 20)
    return float(np.mean(v[b - k : b]))


def joined(
    parts: Sequence[OcvTestPart],
) -> tuple[FloatArray, FloatArray, FloatArray, npt.NDArray[np.bool_]]:
    """The parts' time (s), current (A), voltage (V) in one, and where each file starts."""
    t = np.concatenate([p.t_s for p in parts])
    file_start = np.zeros(t.shape[0], dtype=bool)
    file_start[np.cumsum([0, *[p.t_s.shape[0] for p in parts[:-1]]])] = True
    i = np.concatenate([p.current_A for p in parts])
    return t, i, np.concatenate([p.v_V for p in parts]), file_start


def held_intervals(t_s: FloatArray, file_start: npt.NDArray[np.bool_]) -> FloatArray:
    """The interval (s) over which each sample's current is held forward: to the next sample,
    0 at the last one and across a file boundary (no time passes between files)."""
    dt = np.diff(t_s, append=t_s[-1])
    dt[np.flatnonzero(file_start)[1:] - 1] = 0.0
    return dt


def charge_counts(
    t_s: FloatArray, current_A: FloatArray, file_start: npt.NDArray[np.bool_]
) -> tuple[FloatArray, FloatArray]:
    """Ah discharged and Ah charged before each sample, and after the last (n + 1 entries):
    each sample's current held forward over its interval (``held_intervals``)."""
    dt = held_intervals(t_s, file_start)
    d = np.concatenate([[0.0], np.cumsum(np.clip(current_A, 0, None) * dt / 3600.0)])
    c = np.concatenate([[0.0], np.cumsum(np.clip(-current_A, 0, None) * dt / 3600.0)])
    return d, c


def file_runs(
    mask: npt.NDArray[np.bool_], file_start: npt.NDArray[np.bool_]
) -> list[tuple[int, int]]:
    """``_runs`` of ``mask`` cut where a file starts (a file begins after a pause of unknown
    length, and its clock may start again)."""
    return [
        (aa, bb)
        for a, b in _runs(mask)
        for aa, bb in itertools.pairwise(
            [a, *[int(k) for k in np.flatnonzero(file_start[a + 1 : b]) + a + 1], b]
        )
    ]


def branch_runs(
    sign: npt.NDArray[np.int64], q_Ah: FloatArray, file_start: npt.NDArray[np.bool_]
) -> dict[int, tuple[float, int, int]]:
    """Per current sign (+1 discharge, -1 charge) the run [a, b) carrying the most charge (Ah,
    never across a file boundary) by the count ``q_Ah`` before each sample; a sign whose run
    carries less than ``MIN_BRANCH_SHARE`` of the other's is left out: a few samples of a
    tester's current noise across the rest threshold (it crashed the split), or a top-up."""
    best: dict[int, tuple[float, int, int]] = {}
    for s in (1, -1):
        for a, b in file_runs(sign == s, file_start):
            ah = abs(float(q_Ah[b - 1] - q_Ah[a]))
            if ah > best.get(s, (0.0, 0, 0))[0]:
                best[s] = (ah, a, b)
    longest = max((ah for ah, _, _ in best.values()), default=0.0)
    return {s: r for s, r in best.items() if r[0] >= MIN_BRANCH_SHARE * longest}


def extract_branches(
    parts: Sequence[OcvTestPart],
    *,
    capacity_Ah: float | None = None,
    coulombic_efficiency: float | None = None,
    gamma: float = 30.0,
) -> OcvTestBranches:
    """Split a low-rate OCV test (one or several files, in time order) into its two branches,
    scale SOC, estimate the test's polarisation and correct the branches with it (module doc)."""
    if not parts:
        raise UserError("no OCV test data")
    notes: list[str] = []
    t_all, i_all, v_all, file_start = joined(parts)
    i_max = float(np.max(np.abs(i_all)))
    if i_max <= 0:
        raise UserError("the OCV test has no current at all")
    i_rest = REST_FRACTION * i_max

    d_cum, c_cum = (x[:-1] for x in charge_counts(t_all, i_all, file_start))
    dt = held_intervals(t_all, file_start)
    q1 = d_cum - c_cum  # net Ah removed, eta = 1

    # The two branches: the sign runs carrying the most charge (never across a file boundary).
    sign = np.where(i_all > i_rest, 1, np.where(i_all < -i_rest, -1, 0))
    best = branch_runs(sign, q1, file_start)
    for s, name in ((1, "discharge"), (-1, "charge")):
        if s not in best:
            hint = (
                " (does the tester count charge positive? use --charge-positive)"
                if s == 1
                else " (do all the files count current with one sign? --charge-positive applies "
                "to every file)"
            )
            raise UserError(
                f"the OCV test has no {name} branch: no sustained "
                f"{'positive' if s == 1 else 'negative'} current{hint}; give both branches"
            )
    _, da, db = best[1]
    _, ca, cb = best[-1]
    s1 = 1.0 if da < ca else -1.0  # +1: discharge first (the test starts full)
    f0, s0 = (da, ca) if s1 > 0 else (ca, da)
    # SOC anchor: the fullest (emptiest for a charge-first test) point up to the first branch's
    # start, so a pulse or top-up between the rest and the branch counts. Within half a branch
    # sample's charge of the extreme, the last such point (a tester's current noise at rest
    # moves the count by less).
    fa, fb = (da, db) if s1 > 0 else (ca, cb)
    tol = 0.5 * float(np.median(np.abs(i_all[fa:fb]))) * float(np.median(dt[fa:fb])) / 3600.0
    before_first = -s1 * q1[: f0 + 1]
    f0 = int(np.flatnonzero(before_first >= np.max(before_first) - tol)[-1])
    # Extreme points: the far end of the first branch (before the second starts), then the
    # end of the second branch's side (to the end of the test).
    deep = f0 + int(np.argmax(s1 * (q1[f0 : s0 + 1] - q1[f0])))
    top = deep + int(np.argmax(-s1 * (q1[deep:] - q1[deep])))
    first_Ah = abs(float(q1[deep] - q1[f0]))
    second_Ah = abs(float(q1[top] - q1[deep]))
    if first_Ah <= 0:
        raise UserError("cannot measure the capacity from the OCV test")
    dis_Ah, chg_Ah = (first_Ah, second_Ah) if s1 > 0 else (second_Ah, first_Ah)
    tot_d = float(d_cum[top] - d_cum[f0])
    tot_c = float(c_cum[top] - c_cum[f0])
    eta_meas = tot_d / tot_c if tot_c > 0 else 1.0

    # Rests for the relaxations and end voltages: a tester's current noise at rest can exceed
    # 1 % of the largest current, so up to 10 % of the smaller branch current counts as rest.
    i_quiet = max(
        i_rest, 0.1 * min(float(np.median(np.abs(i_all[a:b]))) for a, b in ((da, db), (ca, cb)))
    )
    rests = file_runs(np.abs(i_all) <= i_quiet, file_start)
    throughput = _scale_charge(
        eta_meas=eta_meas, given=coulombic_efficiency, dis_Ah=dis_Ah, chg_Ah=chg_Ah,
        s1=s1, f0=f0, top=top, second=(s0, cb if s1 > 0 else db), rests=rests,
        t=t_all, v=v_all, q1=q1, first_Ah=first_Ah,
    )  # fmt: skip
    eta = throughput.eta
    q = d_cum - eta * c_cum
    measured_q = abs(float(q[deep] - q[f0]))
    cap = capacity_Ah if capacity_Ah is not None else measured_q
    z_all = (1.0 if s1 > 0 else 0.0) - s1 * (q - q[f0]) / cap

    cap_src = (
        "given by --capacity-ah; the test measures "
        f"{measured_q:.4g} Ah{': Ah, not mAh?' if cap > 10 * measured_q else ''}"
        if capacity_Ah is not None
        else "measured: the charge from full to the deepest point before the other branch"
    )

    def keep(a: int, b: int, name: str) -> tuple[npt.NDArray[np.intp], float]:
        i_run = np.abs(i_all[a:b])
        i_med = float(np.median(i_run))
        idx = np.flatnonzero(np.abs(i_run - i_med) <= 0.1 * i_med) + a
        rate = i_med / cap
        if rate > MAX_OCV_C_RATE:
            raise UserError(
                f"the {name} branch runs at {i_med:g} A = {c_rate_text(rate)} for {cap:.4g} Ah "
                f"({cap_src}): too fast for an OCV test (want C/20-C/30); current in mA or "
                "wrong capacity?"
            )
        span = float(np.ptp(z_all[idx]))
        if span < MIN_BRANCH_SPAN:
            raise UserError(
                f"the {name} branch (the sustained {'positive' if a == da else 'negative'} "
                f"current with the most charge: {i_med:.4g} A for {t_all[b - 1] - t_all[a]:.0f} "
                f"s, {abs(float(q1[b - 1] - q1[a])):.4g} Ah) covers only {100 * span:.0f} % of the "
                f"capacity, {cap:.4g} Ah ({cap_src}); an OCV test needs a full {name}"
            )
        return idx, i_med

    k_dis, i_dis = keep(da, db, "discharge")
    k_chg, i_chg = keep(ca, cb, "charge")

    # One-sample steps between rest and constant current (for the report, and the fallback).
    steps = current_steps(t_all, i_all, v_all, file_start, i_rest=i_rest, rests=rests)
    relax: list[RelaxationFit] = []
    for a, b in ((da, db), (ca, cb)):
        found = relaxation_after(t_all, i_all, v_all, (a, b), rests)
        if found is not None:
            relax.append(replace(found[0], soc=float(z_all[found[1]])))
    # What M >= 0 allows: the polarisation cannot exceed the raw half-gap at mid SOC (a check
    # that is reported, never used to set the polarisation).
    mid = np.linspace(0.2, 0.8, 61)
    raw_half = 0.5 * (
        _interp_sorted(mid, z_all[k_chg], v_all[k_chg])
        - _interp_sorted(mid, z_all[k_dis], v_all[k_dis])
    )
    r_max = float(np.median(raw_half)) / (0.5 * (i_dis + i_chg))
    pol = _choose_polarisation(relax, steps, r_max, notes)

    kap = gamma / (cap * 3600.0)
    h0 = 1.0 if s1 > 0 else -1.0
    x1, x2, h = branch_states(
        t_all, i_all, file_start, tau1_s=pol.tau1_s, tau2_s=pol.tau2_s,
        kappa_dis=kap, kappa_chg=kap * eta, h0=h0,
    )  # fmt: skip
    h_span = tuple(
        branch_states(
            t_all, i_all, file_start, tau1_s=1.0, tau2_s=1.0, kappa_dis=kap * f,
            kappa_chg=kap * f * eta, h0=h0,
        )[2]
        for f in (1.0 / GAMMA_SPAN, GAMMA_SPAN)
    )  # fmt: skip
    v_corr = v_all + pol.R0_ohm * i_all + pol.R1_ohm * x1 + pol.R2_ohm * x2

    def branch(idx: npt.NDArray[np.intp], i_med: float) -> Branch:
        return Branch(
            z=z_all[idx], v_V=v_corr[idx], v_raw_V=v_all[idx], h=h[idx], current_A=i_med,
            h_span=(h_span[0][idx], h_span[1][idx]),
        )  # fmt: skip

    ends: dict[float, float] = {}
    for anchor in (0.0, 1.0):
        cands = [
            (abs(float(z_all[b - 1]) - anchor), -(t_all[b - 1] - t_all[a]), a, b)
            for a, b in rests
            if t_all[b - 1] - t_all[a] >= MIN_END_REST_S
            and abs(float(z_all[b - 1]) - anchor) <= END_SOC_TOL
        ]
        if cands:
            _, _, a, b = min(cands)
            ends[anchor] = _end_voltage(v_all, a, b)
        else:
            notes.append(
                f"no rest of >= {MIN_END_REST_S:.0f} s at SOC {100 * anchor:.0f} %: the OCV "
                f"is not extended to {'empty' if anchor == 0 else 'full'}"
            )
    return OcvTestBranches(
        discharge=branch(k_dis, i_dis),
        charge=branch(k_chg, i_chg),
        capacity_Ah=cap,
        measured_capacity_Ah=measured_q,
        coulombic_efficiency=eta,
        throughput=throughput,
        polarisation=pol,
        gamma=gamma,
        v_empty_V=ends.get(0.0),
        v_full_V=ends.get(1.0),
        notes=tuple(notes),
    )


def _scale_charge(
    *,
    eta_meas: float,
    given: float | None,
    dis_Ah: float,
    chg_Ah: float,
    s1: float,
    f0: int,
    top: int,
    second: tuple[int, int],
    rests: Sequence[tuple[int, int]],
    t: FloatArray,
    v: FloatArray,
    q1: FloatArray,
    first_Ah: float,
) -> Throughput:
    """Normalise or count (module doc): decides eta from the throughput and the rested voltages."""
    if given is not None:
        return Throughput(dis_Ah, chg_Ah, "given", given, "given by the user")
    if eta_meas <= 1.0:
        why = "more Ah back in than out: the measured coulombic efficiency (Plett's method)"
        return Throughput(dis_Ah, chg_Ah, "normalised", eta_meas, why)
    # Less charge back than out: did the test close (the counting is off) or end short?
    before = next(((a, b) for a, b in rests if abs(b - f0) <= 3), None)
    after = next(((a, b) for a, b in rests if a - 3 <= top < b), None)
    if before is None:
        if eta_meas <= 1.02:
            why = "within 2 % and no rest before the first branch to judge closure by"
            return Throughput(dis_Ah, chg_Ah, "normalised", eta_meas, why)
        why = "no rest before the first branch to judge closure by: charge counted as measured"
        return Throughput(dis_Ah, chg_Ah, "counted", 1.0, why)
    v_start = _end_voltage(v, *before)
    v_end = _end_voltage(v, *after) if after is not None else float(v[top])
    sa, sb = second
    z = -s1 * (q1[sa:sb] - q1[sa]) / first_Ah  # SOC moved along the second branch, eta = 1
    tail = np.abs(z) >= np.max(np.abs(z)) - 0.02
    slope = abs(float(np.polyfit(z[tail], v[sa:sb][tail], 1)[0])) if tail.sum() > 2 else 0.0
    short_q = 1.0 - 1.0 / eta_meas  # SOC the second branch misses if counted with eta = 1
    # The end visited twice: short means below the start's voltage at full, above it at empty.
    dv = (v_start - v_end) * (1.0 if s1 > 0 else -1.0)
    short_v = max(dv, 0.0) / slope if slope > 0 else float("inf")
    if short_v < 0.5 * short_q:
        why = (
            f"the test ends {1e3 * dv:+.1f} mV from its starting rested voltage (SOC "
            f"{100 * short_v:.2f} % at the end's slope) while the Ah say {100 * short_q:.1f} % "
            "short: a counting mismatch, each branch normalised to its own throughput"
        )
        return Throughput(dis_Ah, chg_Ah, "normalised", eta_meas, why)
    # A slope taken below a knee the branch never reached turns the mV into more than all SOC.
    soc_v = (
        f"SOC {100 * short_v:.2f} % at the end's slope"
        if short_v <= 1.0
        else "more than the whole SOC range at the end's slope: the knee was not reached"
    )
    why = (
        f"the test ends {1e3 * dv:+.1f} mV below its starting rested voltage ({soc_v}), as the "
        f"Ah say ({100 * short_q:.2f} % short): the second branch ends short; charge counted "
        "with eta = 1"
    )
    return Throughput(dis_Ah, chg_Ah, "counted", 1.0, why)


def _knee_bound_ohm(r_max: float) -> float:
    """The largest R0 + R1 + R2 (ohm) a polarisation candidate may have (``KNEE_FACTOR``)."""
    return KNEE_FACTOR * r_max if r_max > 0 else math.inf


def _drop_knees(
    relax: Sequence[RelaxationFit], r_max: float, notes: list[str]
) -> tuple[list[RelaxationFit], list[RelaxationFit]]:
    """(used, knee) relaxation fits: a knee one reverses the mid-SOC gap by more than the gap."""
    bound = _knee_bound_ohm(r_max)
    knee = [f for f in relax if f.r_total_ohm - 2.0 * f.r_total_se_ohm > bound]
    if knee:
        notes.append(
            "not used for the polarisation: the relaxation"
            + ("s" if len(knee) > 1 else "")
            + " after the "
            + " and ".join(
                f"{f.after} at SOC {100 * f.soc:.1f} % ({1e3 * f.r_total_ohm:.1f} mOhm)"
                for f in knee
            )
            + f", more than {KNEE_FACTOR:g}x what the mid-SOC half-gap allows with M >= 0 "
            f"({1e3 * r_max:.1f} mOhm): the OCV relaxing at a knee, not the polarisation mid-SOC"
        )
    return [f for f in relax if f not in knee], knee


def _usable_steps(
    steps: Sequence[CurrentStep], r_max: float, notes: list[str]
) -> list[CurrentStep]:
    """The steps whose R0 with the assumed RC part is within ``KNEE_FACTOR`` of ``r_max``."""
    bound = _knee_bound_ohm(r_max) / (1.0 + UNMEASURED_RC_SHARE)
    ok = [st for st in steps if st.r_ohm - 2.0 * st.se_ohm <= bound]
    if len(ok) < len(steps):
        notes.append(
            "not used for R0: the one-sample step(s) of "
            + ", ".join(f"{1e3 * st.r_ohm:.1f}" for st in steps if st not in ok)
            + f" mOhm (with the RC part, more than {KNEE_FACTOR:g}x what the mid-SOC half-gap "
            f"allows with M >= 0, {1e3 * r_max:.1f} mOhm): steps at a knee or sampled too "
            "coarsely to separate R0 from the relaxation"
        )
    return ok


def _choose_polarisation(
    relax: Sequence[RelaxationFit], steps: Sequence[CurrentStep], r_max: float, notes: list[str]
) -> Polarisation:
    """The relaxation fits (knees and diffusion at the test's ends only inflate them): the
    smallest, combined (inverse-variance) with those that agree with it within two standard
    errors. Else the current step with the lowest upper bound |dV/dI| + 2 se (onsets first)
    with the unmeasured RC part
    assumed (``UNMEASURED_RC_SHARE``, in the standard error). ``r_max`` (ohm: the most the
    median mid-SOC half-gap allows with M >= 0) is only compared with, beyond two standard
    errors, never imposed (module doc); a candidate beyond ``KNEE_FACTOR`` times it measured a
    knee and is left out (noted)."""
    relax, knee = _drop_knees(relax, r_max, notes)
    steps_ok = _usable_steps(steps, r_max, notes) if not relax else []
    if relax:
        r = min(relax, key=lambda f: f.r_total_ohm)
        agree = [
            f
            for f in relax
            if f.r_total_ohm - r.r_total_ohm <= 2.0 * math.hypot(f.r_total_se_ohm, r.r_total_se_ohm)
        ]
        w = np.array([1.0 / max(f.r_total_se_ohm, 1e-9) ** 2 for f in agree])
        total = float(np.sum(w * np.array([f.r_total_ohm for f in agree])) / np.sum(w))
        shape = min(agree, key=lambda f: f.r_total_se_ohm)  # R0/R1/R2 split and taus
        k = total / shape.r_total_ohm if shape.r_total_ohm > 0 else 1.0
        where = " and ".join(
            f"the {f.duration_s:.0f} s rest after the {f.after} (SOC {100 * f.soc:.1f} %)"
            for f in agree
        )
        pol = Polarisation(
            k * shape.R0_ohm, k * shape.R1_ohm, shape.tau1_s, k * shape.R2_ohm, shape.tau2_s,
            float(1.0 / np.sqrt(np.sum(w))),
            f"2RC relaxation fit{'s' if len(agree) > 1 else ''} of {where}"
            + (" (inverse-variance mean)" if len(agree) > 1 else ""),
            tuple(relax), tuple(steps), tuple(knee),
        )  # fmt: skip
    elif steps_ok:
        # Each step is R0 plus what relaxes within its sample: the one whose upper bound is
        # lowest bounds R0 best (a coarse sample's resolved step holds more relaxation).
        onsets = [st for st in steps_ok if st.onset] or steps_ok
        st = min(onsets, key=lambda x: x.r_ohm + 2.0 * x.se_ohm)
        which = "the one-sample step |dV/dI| with the lowest upper bound (|dV/dI| + 2 se)"
        r0 = st.r_ohm
        rc = UNMEASURED_RC_SHARE * r0
        se = math.hypot(st.se_ohm, rc)
        why = (
            "the relaxations measured a knee"
            if knee
            else f"no rest after a branch long enough (>= {MIN_RELAX_S:.0f} s) to fit its "
            "relaxation"
        )
        notes.append(
            f"{why}: R0 = {which} ({1e3 * r0:.1f} +- {1e3 * st.se_ohm:.1f} mOhm); the test "
            f"does not measure the RC part, taken as {1e3 * rc:.1f} +- {1e3 * rc:.1f} mOhm (1 se); "
            "both errors are in the CI of M"
        )
        pol = Polarisation(
            r0, 0.0, 1.0, rc, UNMEASURED_RC_TAU_S, se,
            "one-sample current step for R0, RC part assumed", (), tuple(steps), tuple(knee),
        )  # fmt: skip
    else:
        notes.append("no rest or step in the test: the branches are not corrected")
        return Polarisation(0.0, 0.0, 1.0, 0.0, 1.0, None, "none", (), tuple(steps), tuple(knee))
    if pol.r_total_ohm - 2.0 * (pol.r_total_se_ohm or 0.0) > r_max > 0:
        notes.append(
            f"the {pol.source} gives {1e3 * pol.r_total_ohm:.1f} mOhm, more than the mid-SOC "
            f"median half-gap allows with M >= 0 ({1e3 * r_max:.1f} mOhm): the polarisation is "
            "smaller mid-SOC than where it was measured; the corrected half-gap comes out "
            "negative (the polarisation is not scaled to fit the gap)"
        )
    return pol


@dataclass(frozen=True)
class BandResidual:
    """Residual of one branch against the fitted model in one SOC band (V)."""

    branch: str
    soc_lo: float
    soc_hi: float
    n: int
    rmse_V: float
    bias_V: float


#: How a stored M knot came about: ``fit`` (its CI excludes 0); with its CI including 0 and
#: hysteresis present: ``wide`` (the fit kept, above the pooled lower bound) or ``conservative``
#: (raised to the pooled lower bound); ``zero`` (CI includes 0, no hysteresis resolved);
#: ``pinned`` (0 at an end with one rested voltage: not a measurement).
KnotStatus = Literal["fit", "wide", "conservative", "zero", "pinned"]


@dataclass(frozen=True)
class HysteresisEvidence:
    """The pooled (constant) M fitted to mid-SOC SOC ``soc_lo``..``soc_hi`` (V) with its 95 % CI
    half-width, whether that says hysteresis is present (CI excludes 0), and each stored knot's
    ``KnotStatus``."""

    pooled_V: float
    pooled_ci95_V: float
    soc_lo: float
    soc_hi: float
    status: tuple[KnotStatus, ...]
    unresolved: str | None = None  #: why the test cannot tell hysteresis from polarisation

    @property
    def present(self) -> bool:
        """True when the pooled M's 95 % CI lies above 0 and the test can tell it."""
        return self.unresolved is None and self.pooled_V - self.pooled_ci95_V > 0


def decide_hysteresis(
    m_soc: FloatArray,
    m_fit: FloatArray,
    m_ci: FloatArray,
    pooled: tuple[float, float, float, float],
    notes: list[str],
    *,
    m_raw: FloatArray | None = None,
    unresolved: str | None = None,
) -> tuple[FloatArray, FloatArray, HysteresisEvidence]:
    """The stored M table (V, in [0, 0.5]) and its CI half-widths from the fitted knots ``m_fit``
    (V) with CI half-widths ``m_ci`` and the ``pooled`` (M, CI, SOC lo, SOC hi) evidence.

    A knot whose CI excludes 0 is kept. Otherwise, with hysteresis present (the pooled CI
    excludes 0), the knot keeps max(fit, pooled lower bound): the test says there is
    hysteresis, so a wide or negative knot is not written as 0; without it the knot is 0. Each
    such knot is named in ``notes``; its stored CI covers the knot's own interval (clipped at 0)
    and, when raised to the pooled bound, the pooled CI. A pooled M below 0 beyond its CI means
    the polarisation over-corrects (M < 0 is not physical): the test cannot tell whether there
    is hysteresis, so a zeroed knot's CI reaches up to ``m_raw`` (the knots fitted to the raw,
    uncorrected gap: the most M can be, with no polarisation at all) and the note says so;
    so does ``unresolved`` (the reason the test cannot separate them: then no knot is kept).
    """
    m_pool, ci_pool, lo, hi = pooled
    m = np.array(m_fit, dtype=np.float64)
    ci = np.array(m_ci, dtype=np.float64)
    status: list[KnotStatus] = []
    ev = HysteresisEvidence(m_pool, ci_pool, lo, hi, (), unresolved)
    floor = m_pool - ci_pool
    over = m_pool + ci_pool < 0 or unresolved is not None
    wide, raised, zeroed = [], [], []
    for k in range(m.shape[0]):
        f, c = float(m_fit[k]), float(m_ci[k])
        if f - c > 0 and unresolved is None:
            status.append("fit")
            continue
        k_lo, k_hi = max(f - c, 0.0), max(f + c, 0.0)
        if ev.present and f >= floor:
            status.append("wide")
            wide.append(k)
        elif ev.present:
            m[k] = floor
            ci[k] = max(k_hi - floor, floor - k_lo, ci_pool)
            status.append("conservative")
            raised.append(k)
        else:
            m[k] = 0.0
            ci[k] = max(k_hi, c, float(m_raw[k]) if over and m_raw is not None else 0.0)
            status.append("zero")
            zeroed.append(k)
    pooled_txt = (
        f"{1e3 * m_pool:.1f} +- {1e3 * ci_pool:.1f} mV at SOC {100 * lo:.0f}-{100 * hi:.0f} %"
    )

    def knots(ks: list[int]) -> str:
        return ", ".join(
            f"{100 * m_soc[k]:.0f} % ({1e3 * m_fit[k]:+.1f} +- {1e3 * m_ci[k]:.1f})" for k in ks
        )

    if wide:
        notes.append(
            f"the CI of the knot(s) at {knots(wide)} mV includes 0; kept, as hysteresis is "
            f"present (pooled M {pooled_txt}) and they lie above its lower bound"
        )
    if raised:
        notes.append(
            f"hysteresis present (pooled M {pooled_txt}), but the knot(s) at {knots(raised)} mV "
            f"are negative or below the pooled lower bound with a CI that includes 0: stored at "
            f"that bound, {1e3 * floor:.1f} mV (conservative), not 0"
        )
    if zeroed and unresolved is not None:
        notes.append(
            f"hysteresis not resolved (pooled M {pooled_txt}): {unresolved}; M = 0 at "
            f"{knots(zeroed)} mV, with the raw half-gap as the upper end of its CI"
        )
    elif zeroed and over:
        notes.append(
            f"the corrected half-gap is negative (pooled M {pooled_txt}): the polarisation "
            "over-corrects mid-SOC (it varies along SOC), so the test cannot tell a hysteresis "
            "of that size from it; "
            f"M = 0 at {knots(zeroed)} mV, with the raw (uncorrected) half-gap as the upper end "
            "of its CI"
        )
    elif zeroed:
        notes.append(
            f"no hysteresis resolved (pooled M {pooled_txt}, CI includes 0): M = 0 at "
            f"{knots(zeroed)} mV, with the knot's upper bound as its CI"
        )
    return np.clip(m, 0.0, 0.5), ci, replace(ev, status=tuple(status))


def pooled_hysteresis(
    z: FloatArray,
    gap_V: FloatArray,
    weight: FloatArray,
    *,
    gap_per_ohm: FloatArray | None = None,
    r_se_ohm: float | None = None,
) -> tuple[float, float, float, float]:
    """A constant M fitted to ``gap = M weight`` on the SOC points ``z`` (the mid-SOC the caller
    chose): (M, 95 % CI half-width, SOC lo, SOC hi), V and fractions."""
    _, m, ci = fit_hysteresis(
        z, gap_V, weight, [float(np.median(z))], gap_per_ohm=gap_per_ohm, r_se_ohm=r_se_ohm
    )
    return float(m[0]), float(ci[0]), float(np.min(z)), float(np.max(z))


@dataclass(frozen=True)
class OcvFitResult:
    """Everything ``fit-ocv`` reports and stores.

    ``m_soc``/``m_V``: the M(z) table (fraction, V; >= 0) and ``m_ci95_V`` the half-widths of its
    95 % confidence intervals (None for rest-point tables with one branch), as stored in the
    config (``decide_hysteresis``). ``m_fit_V`` / ``m_fit_ci95_V``: the fitted knot values (may
    be negative) and their CIs; ``hysteresis``: the pooled evidence and each knot's status.
    ``half_gap_raw_V`` / ``half_gap_V``: the measured and polarisation-corrected half-gaps on
    ``gap_soc``. ``v_empty_V``/``v_full_V``: the rested end voltages the mean curve reaches
    (None: not measured). ``residuals``: per branch and SOC band, against the whole model
    (extended mean + M h). ``test``: the branches (OCV tests). ``correction``: the correction
    table beyond Eq. 4 (``ocv_correction``; None: not fitted).
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
    m_ci95_V: FloatArray | None = None
    m_fit_V: FloatArray | None = None
    v_empty_V: float | None = None
    v_full_V: float | None = None
    residuals: tuple[BandResidual, ...] = ()
    test: OcvTestBranches | None = None
    m_fit_ci95_V: FloatArray | None = None
    hysteresis: HysteresisEvidence | None = None
    correction: OcvCorrection | None = None

    @property
    def table(self) -> tuple[FloatArray, FloatArray] | None:
        """The correction table written to the config (knots, V), None without one."""
        return self.correction.table if self.correction is not None else None

    def ocv_model(self) -> OcvModel:
        """The fitted mean curve with its correction table, its end segments and the M table, as
        the engine uses it."""
        t = self.table
        return OcvModel.from_coeffs(
            self.mean.coeffs, self.soc_min, self.soc_max, self.m_soc, self.m_V,
            v_empty_V=self.v_empty_V, v_full_V=self.v_full_V,
            corr_soc=None if t is None else t[0], corr_V=None if t is None else t[1],
        )  # fmt: skip


def _in_range(z: FloatArray, v: FloatArray, lo: float, hi: float) -> tuple[FloatArray, FloatArray]:
    k = (z >= lo) & (z <= hi)
    return z[k], v[k]


def _hats(z: FloatArray, knots: FloatArray) -> FloatArray:
    """Design matrix of a continuous piecewise-linear function: one hat per knot."""
    return np.column_stack(
        [np.interp(z, knots, np.eye(knots.shape[0])[j]) for j in range(knots.shape[0])]
    )


def fit_hysteresis(
    z: FloatArray,
    gap_V: FloatArray,
    weight: FloatArray,
    knots: Sequence[float],
    *,
    gap_per_ohm: FloatArray | None = None,
    r_se_ohm: float | None = None,
    confidence: float = 0.95,
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """M(z) knots from a branch gap: least squares of ``gap = M(z) weight`` (Eq. 10 on both
    branches: v_chg - v_dis = M (h_chg - h_dis); ``weight`` = h_chg - h_dis, 2 on the major loop).

    Returns (knots, M, ci95 half-widths). The covariance is the residual variance inflated by
    the residuals' lag-1 autocorrelation ((1 + rho) / (1 - rho): a dense test's residuals are
    correlated along SOC), plus, when given, the polarisation's: ``gap_per_ohm`` is d gap / d R
    (V/ohm) and ``r_se_ohm`` the standard error of R.
    """
    k = np.unique(np.clip(np.asarray(knots, dtype=np.float64), np.min(z), np.max(z)))
    a = _hats(z, k) * weight[:, None]
    m, *_ = np.linalg.lstsq(a, gap_V, rcond=None)
    resid = gap_V - a @ m
    dof = max(z.shape[0] - k.shape[0], 1)
    s2 = float(resid @ resid) / dof
    rho = float(np.clip(np.corrcoef(resid[:-1], resid[1:])[0, 1], 0.0, 0.99)) if dof > 2 else 0.0
    cov = np.linalg.pinv(a.T @ a) * s2 * (1.0 + rho) / (1.0 - rho)
    if gap_per_ohm is not None and r_se_ohm is not None:
        j, *_ = np.linalg.lstsq(a, gap_per_ohm, rcond=None)
        cov = cov + np.outer(j, j) * r_se_ohm**2
    half = float(stats.t.ppf(0.5 + confidence / 2.0, dof)) * np.sqrt(np.maximum(np.diag(cov), 0))
    return k, np.asarray(m, dtype=np.float64), np.asarray(half, dtype=np.float64)


def band_residuals(
    name: str, z: FloatArray, resid_V: FloatArray, bands: Sequence[float] = SOC_BANDS
) -> list[BandResidual]:
    """RMSE and mean of ``resid_V`` per SOC band [lo, hi) (the last band closed)."""
    out = []
    for lo, hi in itertools.pairwise(bands):
        k = (z >= lo) & ((z < hi) | ((hi == bands[-1]) & (z <= hi)))
        if k.any():
            r = resid_V[k]
            out.append(
                BandResidual(
                    name, lo, hi, int(k.sum()), float(np.sqrt(np.mean(r * r))), float(np.mean(r))
                )
            )
    return out


def _join_ends(
    coeffs: FloatArray,
    lo: float,
    hi: float,
    v_empty: float | None,
    v_full: float | None,
    notes: list[str],
    table: tuple[FloatArray, FloatArray] | None = None,
) -> tuple[float, float, float | None, float | None]:
    """Move each join inwards (0.5 % steps, up to 10 %) until a monotone C1 end segment exists
    (joining Eq. 4 plus the correction ``table`` when given); drop that end with a note when
    none does."""
    for which in ("empty", "full"):
        v_end = v_empty if which == "empty" else v_full
        if v_end is None:
            continue
        join = lo if which == "empty" else hi
        step = 0.005 if which == "empty" else -0.005
        for _ in range(40):
            try:
                rng = (join, hi) if which == "empty" else (lo, join)  # the curve's range then
                slopes = None if table is None else (*table, table_slopes(coeffs, *table, *rng))
                end_segment(coeffs, join, 0.0 if which == "empty" else 1.0, v_end,
                            join=table_join(coeffs, slopes, join))  # fmt: skip
                break
            except ValueError as exc:
                last = str(exc)
                join = round(join + step, 6)
                if not 0.0 < join < 1.0 or (join > 0.1 if which == "empty" else join < 0.9):
                    join = float("nan")
                    break
        if np.isnan(join):
            notes.append(f"the OCV is not extended to {which}: {last}")
            if which == "empty":
                v_empty = None
            else:
                v_full = None
        elif which == "empty" and join != lo:
            notes.append(f"Eq. 4 joins the empty-end segment at SOC {100 * join:.1f} % (monotone)")
            lo = join
        elif which == "full" and join != hi:
            notes.append(f"Eq. 4 joins the full-end segment at SOC {100 * join:.1f} % (monotone)")
            hi = join
    return lo, hi, v_empty, v_full


def _overlap_error(lo: float, hi: float) -> str:
    """Why the branches do not overlap, with the two usual causes."""
    overlap = (
        f"overlap only on SOC {100 * lo:.0f}-{100 * hi:.0f} %" if hi > lo else "do not overlap"
    )
    return (
        f"the charge and discharge branches {overlap} (SOC counted along the files in the order "
        "given): give the files in the order they were recorded, and --charge-positive if the "
        "tester counts charge positive"
    )


def check_physical(mean: Eq4Fit, v_raw_V: FloatArray, pol: Polarisation) -> None:
    """Refuse a mean OCV that leaves the branches' measured voltage range by more than its span
    over the fit range: no polarisation a cell can have puts the OCV there (a fit that failed).
    """
    z = np.linspace(mean.soc_lo, mean.soc_hi, 201)
    u = eval_ocv(mean.coeffs, z)
    v_lo, v_hi = float(np.min(v_raw_V)), float(np.max(v_raw_V))
    margin = v_hi - v_lo
    if float(np.min(u)) < v_lo - margin or float(np.max(u)) > v_hi + margin:
        raise UserError(
            f"the fit is not physical: the mean OCV reaches {float(np.min(u)):.3f}.."
            f"{float(np.max(u)):.3f} V, the branches measure {v_lo:.3f}..{v_hi:.3f} V "
            f"(polarisation {1e3 * pol.r_total_ohm:.1f} mOhm from the {pol.source}); no config "
            "written"
        )


def fit_ocv_test(
    branches: OcvTestBranches,
    *,
    trim_soc: float = 0.02,
    knots: Sequence[float] = EQ32_KNOTS,
    correction: bool = True,
) -> OcvFitResult:
    """Fit an OCV test's polarisation-corrected branches: Eq. 4 per branch, M(z) with its CI
    from the one-state hysteresis model, the mean, its correction table (``ocv_correction``;
    not with ``correction`` False) and its end segments (module doc)."""
    notes = list(branches.notes)
    dis, chg = branches.discharge, branches.charge
    lo = max(float(np.min(dis.z)), float(np.min(chg.z)), trim_soc)
    hi = min(float(np.max(dis.z)), float(np.max(chg.z)), 1.0 - trim_soc)
    if hi - lo < MIN_BRANCH_SPAN:
        raise UserError(_overlap_error(lo, hi))
    grid = np.linspace(lo, hi, 401)

    def on_grid(b: Branch, y: FloatArray) -> FloatArray:
        return _interp_sorted(grid, b.z, y)

    gap = on_grid(chg, chg.v_V) - on_grid(dis, dis.v_V)
    weight = on_grid(chg, chg.h) - on_grid(dis, dis.h)
    pol = branches.polarisation
    # d gap / d R_total at steady state: the charge branch falls, the discharge branch rises.
    per_ohm = np.full_like(grid, -(chg.current_A + dis.current_A))
    m_soc, m_fit, ci_stat = fit_hysteresis(
        grid, gap, weight, knots, gap_per_ohm=per_ohm, r_se_ohm=pol.r_total_se_ohm
    )
    # gamma is not fitted: each knot's change over gamma / GAMMA_SPAN .. gamma * GAMMA_SPAN.
    ci_gamma = np.zeros_like(m_fit)
    w_slow = weight
    if chg.h_span is not None and dis.h_span is not None:
        for j in (0, 1):
            w_alt = on_grid(chg, chg.h_span[j]) - on_grid(dis, dis.h_span[j])
            _, m_alt, _ = fit_hysteresis(grid, gap, w_alt, knots)
            ci_gamma = np.maximum(ci_gamma, np.abs(m_alt - m_fit))
            w_slow = np.minimum(w_slow, w_alt)
    # A larger polarisation measured at one end of the test may hold at the knot there.
    ci_end = np.zeros_like(m_fit)
    for r in (*pol.relaxations, *pol.knee):  # a knee's relaxation too: it is at that end
        if r.r_total_ohm > pol.r_total_ohm and np.isfinite(r.soc):
            at = _hats(np.array([np.clip(r.soc, m_soc[0], m_soc[-1])]), m_soc)[0]
            extra = 0.5 * (chg.current_A + dis.current_A) * (r.r_total_ohm - pol.r_total_ohm)
            ci_end = np.maximum(ci_end, at * extra)
    m_ci = np.sqrt(ci_stat**2 + ci_gamma**2 + ci_end**2)
    mid = w_slow >= POOLED_MIN_WEIGHT
    if np.count_nonzero(mid) < 20:
        mid = np.ones_like(grid, dtype=bool)
    pooled = pooled_hysteresis(
        grid[mid], gap[mid], weight[mid], gap_per_ohm=per_ohm[mid], r_se_ohm=pol.r_total_se_ohm
    )
    raw_gap = on_grid(chg, chg.v_raw_V) - on_grid(dis, dis.v_raw_V)
    _, m_raw, _ = fit_hysteresis(grid, raw_gap, weight, knots)
    unresolved = (
        None
        if pol.r_total_se_ohm is not None
        else "the test has no rest or current step, so its IR drop and polarisation, which "
        "open the gap like a hysteresis does, are not measured"
    )
    m_vals, m_ci_store, evidence = decide_hysteresis(
        m_soc, m_fit, m_ci, pooled, notes, m_raw=m_raw, unresolved=unresolved
    )
    half_raw = 0.5 * (on_grid(chg, chg.v_raw_V) - on_grid(dis, dis.v_raw_V))

    def mean_data(b: Branch) -> tuple[FloatArray, FloatArray]:
        k = (b.z >= lo) & (b.z <= hi)
        return b.z[k], b.v_V[k] - np.interp(b.z[k], m_soc, m_vals) * b.h[k]

    zd, vd = _in_range(dis.z, dis.v_V, lo, hi)
    zc, vc = _in_range(chg.z, chg.v_V, lo, hi)
    fit_d, fit_c = fit_eq4(zd, vd), fit_eq4(zc, vc)
    (zmd, vmd), (zmc, vmc) = mean_data(dis), mean_data(chg)
    mean = fit_eq4(np.concatenate([zmd, zmc]), np.concatenate([vmd, vmc]))
    check_physical(mean, np.concatenate([dis.v_raw_V, chg.v_raw_V]), branches.polarisation)
    corr = None
    if correction:  # what Eq. 4 misses of the same (hysteresis-free) mean data
        # The noise from each branch's own first differences: at C/20 the OCV moves far less
        # per sample than the noise, and the MAD ignores the branch's few steps.
        noise = float(
            np.median([voltage_noise_V(b.v_V, [(0, b.v_V.shape[0])]) for b in (dis, chg)])
        )
        parts = [(zmd, vmd - eval_ocv(mean.coeffs, zmd)), (zmc, vmc - eval_ocv(mean.coeffs, zmc))]
        corr = fit_correction(mean.coeffs, parts, lo, hi, noise)

    lo_j, hi_j, v_empty, v_full = _join_ends(
        mean.coeffs, lo, hi, branches.v_empty_V, branches.v_full_V, notes,
        None if corr is None else corr.table,
    )  # fmt: skip
    status = list(evidence.status)
    pinned = []
    if v_empty is not None:  # one rested voltage at the end: the branches meet there
        m_soc, m_vals, m_fit, m_ci_store, m_ci = (
            np.concatenate([[0.0], x]) for x in (m_soc, m_vals, m_fit, m_ci_store, m_ci)
        )
        status.insert(0, "pinned")
        pinned.append("0 %")
    if v_full is not None:
        m_soc, m_vals, m_fit, m_ci_store, m_ci = (
            np.concatenate([x, [v]])
            for x, v in ((m_soc, 1.0), (m_vals, 0.0), (m_fit, 0.0), (m_ci_store, 0.0),
                         (m_ci, 0.0))
        )  # fmt: skip
        status.append("pinned")
        pinned.append("100 %")
    if pinned:
        notes.append(
            f"M = 0 at SOC {' and '.join(pinned)}: the test has one rested voltage there, which "
            "the mean curve reaches (pinned, not a measured M)"
        )
    result = OcvFitResult(
        mean=mean, discharge=fit_d, charge=fit_c, soc_min=lo_j, soc_max=hi_j,
        m_soc=m_soc, m_V=m_vals, gap_soc=grid, half_gap_raw_V=half_raw,
        half_gap_V=0.5 * gap, notes=tuple(notes), m_ci95_V=m_ci_store, m_fit_V=m_fit,
        v_empty_V=v_empty, v_full_V=v_full, test=branches, m_fit_ci95_V=m_ci,
        hysteresis=replace(evidence, status=tuple(status)), correction=corr,
    )  # fmt: skip
    result, model = _model_or_eq4(result)
    bands: list[BandResidual] = []
    for name, b in (("discharge", dis), ("charge", chg)):
        v_model = model.ocv(b.z) + model.hysteresis_M(b.z) * b.h
        bands += band_residuals(name, b.z, b.v_V - v_model)
    return replace(result, residuals=tuple(bands))


def _model_or_eq4(result: OcvFitResult) -> tuple[OcvFitResult, OcvModel]:
    """The fit's OCV model; where its written correction table is refused with the end segments
    as joined, the result without it (Eq. 4 alone, the reason in the correction's report)."""
    try:
        return result, result.ocv_model()
    except ValueError as exc:
        corr = result.correction
        if corr is None or not corr.written:
            raise
        corr = replace(corr, written=False, reason=f"refused with the end segments: {exc}")
        result = replace(result, correction=corr)
        return result, result.ocv_model()


@dataclass(frozen=True)
class DenseBranch:
    """A low-rate test's one branch as measured, polarisation-corrected: SOC (fraction),
    voltage (V), which branch, and its one-sample voltage noise (V)."""

    branch: str
    z: FloatArray
    v_V: FloatArray
    noise_V: float


def fit_rest_points(
    discharge: tuple[FloatArray, FloatArray] | None,
    charge: tuple[FloatArray, FloatArray] | None,
    *,
    m_table: tuple[FloatArray, FloatArray] | None = None,
    trim_soc: float = 0.02,
    knots: Sequence[float] = EQ32_KNOTS,
    ends: bool = True,
    dense: DenseBranch | None = None,
) -> OcvFitResult:
    """Fit rest-point tables (SOC fraction, OCV V) with one or both branches.

    Rest voltages carry no IR drop, so no correction is applied. Points within
    ``END_SOC_TOL`` of 0 % or 100 % are the rested end voltages (their mean; with ``ends``) and
    stay out of Eq. 4; other points at or beyond [trim_soc, 1 - trim_soc] are moved onto it
    (Eq. 4 is singular at 0 and 1; with ~10 points a narrower trim lets the 1/z term bend the
    curve upwards below the lowest interior point). With both branches M(z) is the
    piecewise-linear fit of the half-gap on their overlap (ends held beyond it) with its 95 %
    CI, stored by ``decide_hysteresis`` (the pooled evidence over the whole overlap); with one,
    ``m_table`` (soc, M_V) is used, or M = 0 with a note. The mean is Eq. 4
    fitted to all points shifted onto the mean: discharge points + M(z), charge points - M(z)
    (Plett's convention: discharge lies M below the mean), over the union of the branches' SOC
    ranges, which becomes the config's [soc_min, soc_max]. ``dense``: the whole branch the
    points were thinned from (a low-rate test's one branch, ``ocv_one_branch``), whose misfit
    to Eq. 4 gives the correction table as a two-branch test's does (``ocv_correction``).
    """
    notes: list[str] = []
    branches: dict[str, tuple[FloatArray, FloatArray]] = {}
    end_pts: dict[float, list[tuple[float, float]]] = {0.0: [], 1.0: []}  # (V, branch sign)
    for name, pts in (("discharge", discharge), ("charge", charge)):
        if pts is None:
            continue
        z0 = np.asarray(pts[0], dtype=np.float64)
        v0 = np.asarray(pts[1], dtype=np.float64)
        if ends:
            for anchor in (0.0, 1.0):
                at = np.abs(z0 - anchor) <= END_SOC_TOL
                sgn = 1.0 if name == "discharge" else -1.0
                end_pts[anchor] += [(float(x), sgn) for x in v0[at]]
                z0, v0 = z0[~at], v0[~at]
        z, n_moved = clamp_soc_points(z0, trim_soc)
        if n_moved:
            notes.append(f"{n_moved} {name} point(s) moved onto SOC [{trim_soc}, {1 - trim_soc}]")
        branches[name] = (z, v0)
    if not branches:
        raise UserError("no rest points given")
    fits = {name: fit_eq4(z, v) for name, (z, v) in branches.items()}
    gap_soc = half = m_ci = m_fit = m_fit_ci = evidence = None
    if len(branches) == 2:
        (zd, vd), (zc, vc) = branches["discharge"], branches["charge"]
        lo, hi = max(zd.min(), zc.min()), min(zd.max(), zc.max())
        if hi - lo < MIN_BRANCH_SPAN:
            raise UserError(f"the branches overlap only on SOC {100 * lo:.0f}-{100 * hi:.0f} %")
        gap_soc = np.linspace(lo, hi, 201)
        half = 0.5 * (_interp_sorted(gap_soc, zc, vc) - _interp_sorted(gap_soc, zd, vd))
        two = np.full_like(gap_soc, 2.0)
        m_soc, m_fit, m_fit_ci = fit_hysteresis(gap_soc, 2.0 * half, two, knots)
        pooled = pooled_hysteresis(gap_soc, 2.0 * half, two)
        m_vals, m_ci, evidence = decide_hysteresis(m_soc, m_fit, m_fit_ci, pooled, notes)
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
    # An end point of a branch lies M off the mean, as every other point (Plett's sign).
    v_ends = {
        a: float(np.mean([v + sgn * float(np.interp(a, m_soc, m_vals)) for v, sgn in pts]))
        if pts
        else None
        for a, pts in end_pts.items()
    }
    corr = None
    if dense is not None:  # what Eq. 4 misses of the whole branch, shifted onto the mean
        sign = 1.0 if dense.branch == "discharge" else -1.0
        zd, vd = _in_range(dense.z, dense.v_V, mean.soc_lo, mean.soc_hi)
        vm = vd + sign * np.interp(zd, m_soc, m_vals) - eval_ocv(mean.coeffs, zd)
        corr = fit_correction(mean.coeffs, [(zd, vm)], mean.soc_lo, mean.soc_hi, dense.noise_V)
    lo_j, hi_j, v_empty, v_full = _join_ends(
        mean.coeffs, mean.soc_lo, mean.soc_hi, v_ends[0.0], v_ends[1.0], notes,
        None if corr is None else corr.table,
    )  # fmt: skip
    result = OcvFitResult(
        mean=mean, discharge=fits.get("discharge"), charge=fits.get("charge"),
        soc_min=lo_j, soc_max=hi_j, m_soc=m_soc, m_V=m_vals, gap_soc=gap_soc,
        half_gap_raw_V=half, half_gap_V=half, notes=tuple(notes), m_ci95_V=m_ci, m_fit_V=m_fit,
        v_empty_V=v_empty, v_full_V=v_full, m_fit_ci95_V=m_fit_ci, hysteresis=evidence,
        correction=corr,
    )  # fmt: skip
    result, model = _model_or_eq4(result)
    bands: list[BandResidual] = []
    for name, pts in (("discharge", discharge), ("charge", charge)):
        if pts is not None:
            z = np.clip(np.asarray(pts[0], dtype=np.float64), 0.0, 1.0)
            h = -1.0 if name == "discharge" else 1.0
            v_model = model.ocv(z) + h * model.hysteresis_M(z)
            bands += band_residuals(name, z, np.asarray(pts[1], dtype=np.float64) - v_model)
    return replace(result, residuals=tuple(bands))


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
    temperature_C: float | None = None,
) -> CellConfig:
    """The cell config for a fit: Eq. 4 branches, valid SOC range, end voltages and M table,
    and the test's temperature (degC) when known."""

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
            v_empty_V=result.v_empty_V,
            v_full_V=result.v_full_V,
            correction_soc=None if result.table is None else lst(result.table[0]),
            correction_V=None if result.table is None else lst(result.table[1]),
            temperature_C=temperature_C,
        ),
        hysteresis=HysteresisTable(
            soc=lst(result.m_soc),
            M_V=lst(result.m_V),
            gamma=gamma,
            M_ci95_V=lst(result.m_ci95_V) if result.m_ci95_V is not None else None,
        ),
        bounds=bounds,
        initial=initial,
    )
