"""The OCV correction table of a low-rate OCV test: what Eq. 4's six terms miss of the test's
mean OCV, as knots dU(z) that ``model.ocv.OcvModel`` adds to Eq. 4 (``fit-ocv`` writes them to
the config's ``ocv.correction_soc`` / ``ocv.correction_V``).

- Data: each branch's hysteresis-free mean data (polarisation-corrected voltage less M(z) h, the
  data Eq. 4's mean is fitted to) minus Eq. 4, on the fit range [lo, hi].
- Knots (``correction_knots``): from lo to hi, ``KNOT_SPACING`` apart where the test is dense,
  wider where a branch has fewer than ``MIN_SAMPLES_PER_KNOT`` samples in an interval.
- Values: a continuous piecewise-linear least-squares fit of each branch's residual on the
  knots, the two branches averaged: a hysteresis M(z) mis-stated by dM puts +dM on one branch
  and -dM on the other, which cancel, so the table is the branch mean and M(z) (fitted before,
  from the branch gap) stays as it was.
- Monotone: the corrected curve at the knots is made non-decreasing (weighted pool-adjacent-
  violators, weights the knots' sample counts); where the C1 cubic still falls between knots
  (``model.ocv.correction_fall``), the interior knot nearest the fall is dropped and the values
  refitted, until it increases (none left: no table).
- Written (``fit_correction``) when the table's RMS over SOC exceeds the test's
  one-sample voltage noise (the median over both branches of ``ocv_fit.voltage_noise_V``): a
  systematic error larger than a single reading's scatter. With ``MIN_SAMPLES_PER_KNOT`` per
  branch a knot's own noise is at most 1/6 of that, so the table then follows the curve, not
  the noise.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt
from scipy.optimize import isotonic_regression

from bmsid.model.ocv import correction_fall, eval_ocv, hermite_table, table_slopes

FloatArray = npt.NDArray[np.float64]

#: Knot spacing (SOC fraction) where the test is dense: graphite's staging steps and the
#: plateaus between them are 5-15 % SOC wide (the residual of Eq. 4 on the C/20 NMC tests
#: changes sign every 10-20 %), so 2.5 % puts 2-6 knots across each; closer knots would follow
#: the polarisation's transients at the branch starts, which are no part of the OCV.
KNOT_SPACING = 0.025
#: Fewest samples of each branch between two knots: a knot's value then averages >= 40
#: readings, its noise at most 1/6 of one reading's.
MIN_SAMPLES_PER_KNOT = 20


@dataclass(frozen=True)
class OcvCorrection:
    """The correction table fitted to a test and whether it is written.

    ``soc`` / ``dU_V``: knots (fractions) and values (V); ``eq4_rmse_V`` / ``rmse_V``: the RMS
    over SOC of the branches' mean (their hysteresis-free data averaged) against Eq. 4 alone and
    against Eq. 4 + the table (written or not); ``table_rms_V`` the table's RMS over SOC;
    ``noise_V`` the test's one-sample voltage noise; ``pooled``
    the knots the monotone step moved; ``reason``: why it is (not) written.
    """

    soc: FloatArray
    dU_V: FloatArray
    written: bool
    reason: str
    eq4_rmse_V: float
    rmse_V: float
    table_rms_V: float
    noise_V: float
    pooled: int = 0

    @property
    def table(self) -> tuple[FloatArray, FloatArray] | None:
        """(knots, values) when written, else None."""
        return (self.soc, self.dU_V) if self.written else None

    def summary(self) -> str:
        """The report's line."""
        head = (
            f"OCV correction table: Eq. 4 RMSE {1e3 * self.eq4_rmse_V:.2f} mV on the branches' mean"
        )
        if not self.written:
            return f"{head}; no table written: {self.reason}"
        spacing = float(np.median(np.diff(self.soc)))
        return (
            f"{head}; with the correction table {1e3 * self.rmse_V:.2f} mV over "
            f"{self.soc.shape[0]} knots (SOC {100 * self.soc[0]:.1f}-{100 * self.soc[-1]:.1f} %, "
            f"median spacing {100 * spacing:.1f} %, |dU| <= "
            f"{1e3 * float(np.max(np.abs(self.dU_V))):.1f} mV): {self.reason}"
        )


def correction_knots(zs: Sequence[FloatArray], lo: float, hi: float) -> FloatArray:
    """Knots from ``lo`` to ``hi``: ``KNOT_SPACING`` apart, wider until every branch in ``zs``
    has ``MIN_SAMPLES_PER_KNOT`` samples in each interval; a last interval shorter than half a
    spacing is merged into the one before. Interior knots rounded to 1e-6."""
    sorted_z = [np.sort(z[(z >= lo) & (z <= hi)]) for z in zs]
    edges, cur = [lo], lo
    while True:
        nxt = cur + KNOT_SPACING
        for z in sorted_z:
            above = z[np.searchsorted(z, cur, side="right") :]
            nxt = max(nxt, float(above[MIN_SAMPLES_PER_KNOT - 1])) if (
                above.shape[0] >= MIN_SAMPLES_PER_KNOT) else np.inf  # fmt: skip
        if nxt > hi - 0.5 * KNOT_SPACING:
            break
        edges.append(nxt)
        cur = nxt
    inner = np.round(np.asarray(edges[1:], dtype=np.float64), 6)  # 0.17, not 0.16999999999999998
    return np.concatenate([[lo], inner, [hi]])  # the ends exact: they bound the curve's range


def _hats(z: FloatArray, knots: FloatArray) -> FloatArray:
    return np.column_stack(
        [np.interp(z, knots, np.eye(knots.shape[0])[j]) for j in range(knots.shape[0])]
    )


def _fit_values(
    parts: Sequence[tuple[FloatArray, FloatArray]], knots: FloatArray
) -> tuple[FloatArray, FloatArray]:
    """Each branch's piecewise-linear least-squares values on ``knots``, averaged; and each
    knot's weight (its hat's sample sum over the branches)."""
    vals, weight = [], np.zeros_like(knots)
    for z, r in parts:
        a = _hats(z, knots)
        v, *_ = np.linalg.lstsq(a, r, rcond=None)
        vals.append(v)
        weight += a.sum(axis=0)
    return np.asarray(np.mean(vals, axis=0), dtype=np.float64), weight


def _monotone_values(
    coeffs: FloatArray, parts: Sequence[tuple[FloatArray, FloatArray]], knots: FloatArray
) -> tuple[FloatArray, int]:
    du, weight = _fit_values(parts, knots)
    base = eval_ocv(coeffs, knots)
    # weighted isotonic (non-decreasing) regression: pool-adjacent-violators
    total = isotonic_regression(base + du, weights=np.maximum(weight, 1e-12)).x
    return total - base, int(np.count_nonzero(np.abs(total - base - du) > 1e-9))  # not rounding


def fit_correction(
    coeffs: FloatArray,
    parts: Sequence[tuple[FloatArray, FloatArray]],
    lo: float,
    hi: float,
    noise_V: float,
) -> OcvCorrection:
    """The correction table of Eq. 4 (``coeffs``) from each branch's (z, mean data - Eq. 4)
    on [lo, hi], and whether it is written (module doc)."""
    parts = [(z[(z >= lo) & (z <= hi)], r[(z >= lo) & (z <= hi)]) for z, r in parts]
    knots = correction_knots([z for z, _ in parts], lo, hi)
    du, pooled = _monotone_values(coeffs, parts, knots)
    fall = correction_fall(coeffs, knots, du, lo, hi)
    while fall is not None and knots.shape[0] > 3:
        inner = np.arange(1, knots.shape[0] - 1)
        drop = inner[np.argmin(np.abs(knots[inner] - fall[0]))]
        knots = np.delete(knots, drop)
        du, pooled = _monotone_values(coeffs, parts, knots)
        fall = correction_fall(coeffs, knots, du, lo, hi)
    # Scored on the branches' mean (each interpolated onto one SOC grid, then averaged): what is
    # left of a branch's own offset (M(z) h, the polarisation) is no part of the mean curve.
    grid = np.linspace(lo, hi, 1001)
    r_mean = np.mean([np.interp(grid, z[np.argsort(z)], r[np.argsort(z)]) for z, r in parts], 0)
    table = hermite_table(knots, du, table_slopes(coeffs, knots, du, lo, hi), grid, False)
    eq4_rmse = float(np.sqrt(np.mean(r_mean**2)))
    rmse = float(np.sqrt(np.mean((r_mean - table) ** 2)))
    table_rms = float(np.sqrt(np.mean(table**2)))
    if fall is not None:
        written, reason = (
            False,
            (
                f"no table of >= 3 knots keeps the mean curve increasing (it falls at SOC "
                f"{100 * fall[0]:.1f} %)"
            ),
        )
    elif table_rms <= noise_V:
        written, reason = (
            False,
            (
                f"Eq. 4's systematic residual (RMS {1e3 * table_rms:.2f} mV, binned) is within the "
                f"test's voltage noise ({1e3 * noise_V:.2f} mV per sample)"
            ),
        )
    else:
        written, reason = (
            True,
            (
                f"Eq. 4's systematic residual (RMS {1e3 * table_rms:.2f} mV, binned) exceeds the "
                f"test's voltage noise ({1e3 * noise_V:.2f} mV per sample)"
                + (f"; {pooled} knot(s) moved to keep the curve increasing" if pooled else "")
            ),
        )
    return OcvCorrection(
        soc=knots, dU_V=du, written=written, reason=reason, eq4_rmse_V=eq4_rmse,
        rmse_V=rmse, table_rms_V=table_rms, noise_V=noise_V,
        pooled=pooled,
    )  # fmt: skip
