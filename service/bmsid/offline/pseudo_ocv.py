"""An OCV curve read off the record itself, for a run with no cell config whose record does not
fit the assumed cell's chemistry (an LFP record against the paper's NMC curve: 80 mV of RMSE on
the A123 DYN50 test).

Without an OCV test the best the record offers is a *pseudo-OCV*: over its widest discharge
(the one the capacity was read off, ``plausibility.derive_capacity``), the voltage with the
ohmic drop put back, ``v + R0 i`` (R0 the median -dV/dI of the record's current steps, as the
start values measure it), against the SOC the coulomb count gives from the discharge's start
(Eq. 2 with the capacity read off), fitted by Eq. 4 (``ocv_fit.fit_eq4``). It carries the
record's mean polarisation (R1 + R2 times the mean current: the curve sits that much below the
true OCV, which the identified branches then partly re-learn) and no hysteresis (one
direction), so the run says so and points at ``fit-ocv``.

The curve is used over the SOC range the discharge covered (within ``[SOC_EDGE, 1 -
SOC_EDGE]``), and only if Eq. 4 rises monotonically there: an OCV that falls with SOC would
make the SOC read from a voltage ambiguous.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from bmsid.config.cell import OcvCurve
from bmsid.errors import UserError
from bmsid.estimate.startvalues import median_step_resistance
from bmsid.model.ocv import eval_docv_dz
from bmsid.offline.plausibility import (
    FloatArray,
    cell_mean_min,
    coulomb_Ah,
    held,
    max_excursion,
)

#: The pseudo-OCV's SOC range keeps this far from 0 and 1: Eq. 4's 1/z and ln terms diverge.
SOC_EDGE = 0.05
#: The discharge must cover at least this SOC span for its curve to be worth more than a guess.
MIN_SPAN = 0.5


@dataclass(frozen=True)
class PseudoOcv:
    """Eq. 4 read off the record: the curve (SOC range the data covered), the fit's residual
    RMS (V: the polarisation the dynamic record scatters about the curve) and the R0 (ohm) the
    voltage was corrected with."""

    curve: OcvCurve
    rmse_V: float
    r0_ohm: float

    def text(self) -> str:
        c = self.curve
        return (
            f"OCV read off the record (Eq. 4 fitted to v + R0 i, R0 {1e3 * self.r0_ohm:.1f} mOhm, "
            f"against the count over SOC {100 * c.soc_min:.0f}-{100 * c.soc_max:.0f} %: a "
            f"pseudo-OCV, {1e3 * self.rmse_V:.1f} mV RMS about it, no hysteresis)"
        )


def pseudo_ocv(
    t_s: FloatArray,
    current_A: FloatArray,
    voltages_V: FloatArray,
    capacity_Ah: float,
    start_soc: float,
    gap_s: float,
    v_ends_V: tuple[float | None, float | None] = (None, None),
) -> PseudoOcv | None:
    """The pseudo-OCV of the record's widest discharge (see the module docstring), which starts
    at ``start_soc`` (fraction) of ``capacity_Ah``; None when the discharge covers less than
    ``MIN_SPAN`` of SOC, no current step gives R0, or Eq. 4 does not rise monotonically.

    ``v_ends_V``: the voltages (V) the record shows at empty (its cut-off) and full (a rest
    from full), or None: the curve's end segments run to them (``OcvCurve``), so the rested
    range the input gates and the start check use spans the cell's, not only the fitted part."""
    t = np.asarray(t_s, dtype=np.float64)
    i = held(np.asarray(current_A, dtype=np.float64), 0.0)
    v, _ = cell_mean_min(voltages_V)  # refused readings (NaN) left out
    if not (capacity_Ah > 0 and np.isfinite(start_soc)) or t.shape[0] < 10:
        return None
    q = coulomb_Ah(t, i, gap_s)
    ex = max_excursion(q)
    if ex.direction != "discharge":
        return None
    seg = slice(ex.start, ex.end + 1)
    r0_ohm = median_step_resistance(t[seg], i[seg], v[seg])
    if r0_ohm is None:
        return None
    z = start_soc - (q[seg] - q[ex.start]) / capacity_Ah
    v_eq = v[seg] + r0_ohm * i[seg]
    lo = max(float(np.min(z)), SOC_EDGE)
    hi = min(float(np.max(z)), 1.0 - SOC_EDGE)
    if hi - lo < MIN_SPAN:
        return None
    use = (z >= lo) & (z <= hi) & np.isfinite(v_eq)
    try:
        # imported here: ocv_fit brings scipy.optimize and stats (~50 MB resident), which a run
        # that reads no pseudo-OCV (an NMC record, or any with a config) never needs
        from bmsid.offline.ocv_fit import fit_eq4  # noqa: PLC0415

        fit = fit_eq4(z[use], v_eq[use])
    except UserError:
        return None
    grid = np.linspace(lo, hi, 201)
    if not np.all(eval_docv_dz(fit.coeffs, grid) > 0):
        return None
    coeffs = [float(c) for c in fit.coeffs]
    v_empty, v_full = v_ends_V
    try:
        curve = OcvCurve(mean=coeffs, soc_min=lo, soc_max=hi, v_empty_V=v_empty, v_full_V=v_full)
    except ValueError:  # an end no monotone segment reaches: the fitted range alone
        curve = OcvCurve(mean=coeffs, soc_min=lo, soc_max=hi)
    return PseudoOcv(curve, fit.rmse_V, r0_ohm)
