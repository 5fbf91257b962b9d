"""A low-rate OCV test with one branch only (a C/20 discharge from full, or a charge from empty).

Many labs run only the discharge (a "pseudo-OCV"): ``ocv_fit.extract_branches`` needs both
branches (the gap between them is the hysteresis, and its mid-SOC size bounds the
polarisation) and refused it. Here the branch's voltage is corrected for the test's
polarisation from the onset's one-sample step with the RC part assumed
(``ocv_fit._choose_polarisation``: the rest after a whole branch lies at the end of the SOC
range, where the OCV relaxes too, and no branch gap tells that knee apart), and the corrected
branch, thinned to ``MAX_POINTS``, with the rested voltages at full and empty, is fitted as a
rest-point table (``ocv_fit.fit_rest_points``), the whole branch giving the correction table
beyond Eq. 4 as a two-branch test's does: M(z) from ``--hysteresis-from``, else 0 (the mean is
then the branch, M off it). SOC is counted over the branch from its start (full for a
discharge) on the measured capacity (the branch's charge) or the given one. Pure numpy.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt

from bmsid.errors import UserError
from bmsid.offline.ocv_fit import (
    END_SOC_TOL,
    MAX_OCV_C_RATE,
    MIN_BRANCH_SPAN,
    MIN_END_REST_S,
    REST_FRACTION,
    DenseBranch,
    OcvTestPart,
    _choose_polarisation,
    _end_voltage,
    branch_runs,
    branch_states,
    c_rate_text,
    current_steps,
    file_runs,
    held_intervals,
    joined,
    relaxation_after,
    voltage_noise_V,
)

FloatArray = npt.NDArray[np.float64]
Points = tuple[FloatArray, FloatArray]

#: The corrected branch is thinned to at most this many points (Eq. 4 has six terms).
MAX_POINTS = 400


@dataclass(frozen=True)
class OneBranch:
    """The corrected branch as points (SOC fraction, V) on its side, the capacity (Ah) used
    and measured, and report lines."""

    discharge: Points | None
    charge: Points | None
    capacity_Ah: float
    measured_capacity_Ah: float
    #: the whole corrected branch, for the correction table beyond Eq. 4
    dense: DenseBranch
    info: list[str] = field(default_factory=list)


def one_branch_points(
    parts: Sequence[OcvTestPart], capacity_Ah: float | None = None, gamma: float = 30.0
) -> OneBranch | None:
    """The points of ``parts`` (in time order) if they hold one low-rate branch and nothing of
    the other (module doc); None where both are there (the two-branch path)."""
    t, i, v, file_start = joined(parts)
    i_max = float(np.max(np.abs(i))) if i.size else 0.0
    if i_max <= 0:
        return None
    dt = held_intervals(t, file_start)
    q = np.concatenate([[0.0], np.cumsum(i * dt / 3600.0)[:-1]])  # Ah out before each sample
    sign = np.where(i > REST_FRACTION * i_max, 1, np.where(i < -REST_FRACTION * i_max, -1, 0))
    best = branch_runs(sign, q, file_start)
    if len(best) != 1:
        return None
    s, (_, a, b) = next(iter(best.items()))
    name = "discharge" if s > 0 else "charge"
    i_med = float(np.median(np.abs(i[a:b])))
    measured = abs(float(q[b - 1] - q[a]))
    cap = capacity_Ah if capacity_Ah is not None else measured
    if i_med / cap > MAX_OCV_C_RATE:  # a drive, or pulses without the rests of an OCV test
        rate = "" if capacity_Ah is None else f", {c_rate_text(i_med / cap)} of {cap:.4g} Ah"
        raise UserError(
            f"no OCV test: its longest {name} run is {i_med:.4g} A for {t[b - 1] - t[a]:.0f} s "
            f"({measured:.4g} Ah{rate}); an OCV test runs a whole branch at C/20-C/30, or "
            "pulses with rests of >= 10 min between them (an incremental test); a drive goes "
            "to bmsid identify"
        )
    z = (1.0 if s > 0 else 0.0) - (q - q[a]) / cap  # from full (discharge) or empty (charge)
    idx = np.flatnonzero(np.abs(np.abs(i[a:b]) - i_med) <= 0.1 * i_med) + a
    span = float(np.ptp(z[idx])) if idx.size else 0.0
    if span < MIN_BRANCH_SPAN:
        raise UserError(
            f"the {name} branch ({i_med:.4g} A for {t[b - 1] - t[a]:.0f} s) covers only "
            f"{100 * span:.0f} % of the capacity, {cap:.4g} Ah; an OCV test needs a full {name}"
        )

    i_quiet = max(REST_FRACTION * i_max, 0.1 * i_med)
    rests = file_runs(np.abs(i) <= i_quiet, file_start)
    notes: list[str] = []
    # The rest after a whole branch lies at its end, where the OCV itself relaxes (solid
    # diffusion at a knee: the five PyBaMM cells' rests after a C/20 discharge read 251-2,808
    # mOhm, 2.6-19x their onset steps with the RC part assumed), and no gap tells such a knee
    # apart here: the onset's step, RC part assumed.
    found = relaxation_after(t, i, v, (a, b), rests)
    steps = current_steps(t, i, v, file_start, i_rest=REST_FRACTION * i_max, rests=rests)
    pol = _choose_polarisation([], steps, 0.0, notes)
    if found is not None:
        notes.append(
            f"not used for the polarisation: the relaxation after the {name} at SOC "
            f"{100 * abs(float(z[found[1]])):.1f} % ({1e3 * found[0].r_total_ohm:.1f} mOhm), "
            "at the end of the SOC range, where the OCV relaxes too"
        )
    kap = gamma / (cap * 3600.0)
    x1, x2, _ = branch_states(
        t, i, file_start, tau1_s=pol.tau1_s, tau2_s=pol.tau2_s, kappa_dis=kap, kappa_chg=kap,
        h0=-float(s),
    )  # fmt: skip
    v_corr = v + pol.R0_ohm * i + pol.R1_ohm * x1 + pol.R2_ohm * x2
    keep = idx[np.unique(np.linspace(0, idx.size - 1, min(MAX_POINTS, idx.size)).astype(int))]
    zs, vs = list(z[keep]), list(v_corr[keep])
    ends = []
    for anchor in (0.0, 1.0):
        for ra, rb in rests:
            rested = t[rb - 1] - t[ra] >= MIN_END_REST_S
            if rested and abs(float(z[rb - 1]) - anchor) <= END_SOC_TOL:
                zs.append(anchor)
                vs.append(_end_voltage(v, ra, rb))
                ends.append(f"{'full' if anchor else 'empty'} {vs[-1]:.4f} V")
                break
    pts = (np.array(zs), np.array(vs))
    info = [
        f"one branch: a {name} at {i_med:.4g} A ({c_rate_text(i_med / cap)}) and no "
        f"{'charge' if s > 0 else 'discharge'}: the {name} corrected for the polarisation is "
        f"fitted as rest points ({keep.size} of it); rested ends: {', '.join(ends) or 'none'}",
        f"capacity measured from the test: {measured:.4f} Ah, the {name}'s charge (used: "
        f"{cap:.4f} Ah)",
        f"polarisation: {pol.source}: R0 {1e3 * pol.R0_ohm:.1f} mOhm, R1 {1e3 * pol.R1_ohm:.1f} "
        f"mOhm, R2 {1e3 * pol.R2_ohm:.1f} mOhm, total {1e3 * pol.r_total_ohm:.1f}"
        + (
            f" +- {1e3 * pol.r_total_se_ohm:.1f} (1 se)"
            if pol.r_total_se_ohm is not None and math.isfinite(pol.r_total_se_ohm)
            else ""
        )
        + f" mOhm: {1e3 * i_med * pol.r_total_ohm:.2f} mV at the branch current",
        *notes,
    ]
    noise = voltage_noise_V(v_corr[idx], [(0, idx.size)])  # its own first differences
    dense = DenseBranch(name, z[idx], v_corr[idx], noise)
    return OneBranch(pts if s > 0 else None, None if s > 0 else pts, cap, measured, dense, info)
