"""The start SOC of a record that opens under load or still relaxing, fitted over its first window.

A SOC read from the first voltage through the OCV curve is only as good as that voltage is an
OCV. A record that opens under load (IR-corrected with R0 only: the RC branches' voltage is not
known) or moments after a current step (the relaxation still to come) reads it wrong by the
branches' voltage: the CALCE 25 C US06 and BJDST tests opened 2-6 SOC points low. In the flat
middle of an NMC curve the observer then moves SOC slowly, and the parameter fits take the OCV
error into R2 (an OCV error looks like R2 under a steady mean current): R1 and R2 ran to their
lower bounds for the whole record.

The window holds what one voltage does not: with the start SOC z0 + dz, Eq. 9 over the window
linearised in dz is

    v_k - OCV(z_k) - M(z_k) h_k = -R0 i_k - R1 x1_k - R2 x2_k + dOCV/dz(z_k) dz
                                  + c1 a1^k + c2 a2^k

(z_k coulomb-counted from z0 (Eq. 2), h_k by Eq. 5-6 from 0, x_j the unit-gain ZOH branch
states of Eq. 8, c_j the branch voltages at the window start), linear in (R0, R1, R2, dz, c1,
c2) for fixed time constants: a grid over (tau1, tau2) and a least-squares solve for each, the
best kept, re-linearised until dz settles. The relaxation and the load are explained by the
branches; what they cannot explain, a level that follows the OCV slope, is SOC. Where SOC is
known (given by the user) the dz column is left out. Pure numpy.

The engine starts its branches at the fitted ``-c_j`` (``EstimatorBank(branch0_V=...)``), not
empty: a bank that meets a loaded first voltage with empty branches reads their voltage as a
model error and its first updates put it into R0 (the CALCE 25 C BJDST record entered 1,800 s
in: R0 74 -> 121 mOhm in 15 s, 22 mV of error over the first minute).

Measured (``bench/starts_real.py``): the four polarised 25 C starts read 77.6 / 77.9 / 43.4 /
43.9 % from their first voltages for 80 / 80 / 50 / 50 %; fitted over 20 min, 80.5 / 81.8 /
49.8 / 50.2 %. On starts that are at rest and relaxed the first voltage is better (0 C DST
from 50 %: 55.0 % read, 52.0 % fitted, 54.8 % true: the 0 C model's error biases the fit), so
the fit is used only where the first voltage is known to mislead.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from bmsid.estimate.cellmodel import CellModel
from bmsid.estimate.tuning import EstimatorTuning
from bmsid.model.ecm import hysteresis_kappa, hysteresis_step

FloatArray = npt.NDArray[np.float64]

#: The window fitted, s: a few slow time constants, and little SOC swing for the OCV curve's
#: own error to act on (README: 10 and 20 min alike on the CALCE starts, 30 min one record
#: 1.2 mV worse than its known start, 60 min reads 80 % starts at 85 %).
WINDOW_S = 1200.0
#: Points of each time constant's grid, log-spaced over the cell's bounds (the fit's error is
#: flat in log tau); the slow branch at most half the window: a slower one is a level there,
#: which the SOC column is too (at 45 C BJDST it took tau2 = 2,151 s and 2.4 SOC points).
GRID_POINTS = 10
#: Re-linearisations at most (dz settles to 1e-4 in two or three).
MAX_ITER = 5
#: Valid voltages a cell needs in the window (ten per column fitted).
MIN_SAMPLES = 60
#: The window must move SOC by this much for the slope column to be more than an offset.
MIN_SOC_SWING = 0.02
#: A fit whose dz needs more than this is no correction of a first voltage but a different
#: cell or curve: kept out.
MAX_DZ = 0.3


@dataclass(frozen=True)
class StartFit:
    """Per cell: the fitted start SOC (NaN where no fit), the fit's RMSE (V) and the two
    branches' voltages at the first sample (V, (cells, 2), NaN where no fit): the drops
    ``u_j = R_j x_j`` of Eq. 9 (``v = OCV + M h - R0 i - u1 - u2``), ``-c_j`` of the fit."""

    soc0: FloatArray
    rmse_V: FloatArray
    window_s: float
    branch_V: FloatArray


def fit_start_soc(
    t_s: FloatArray, current_A: FloatArray, voltages_V: FloatArray, model: CellModel,
    soc_guess: FloatArray, window_s: float = WINDOW_S, tuning: EstimatorTuning | None = None,
    soc_known: bool = False,
) -> StartFit:  # fmt: skip
    """The start SOC of each cell fitted over the first ``window_s`` of the record (module
    docstring), from ``soc_guess`` (the first voltage's reading); with ``soc_known`` the
    guess is the SOC (given by the user) and only the branches are fitted (no dz column).
    Samples (s, A with + = discharge, V (samples, cells)); NaN voltages are left out, and so
    are samples with a NaN
    current (the branches and the count hold the current before through them); a step longer
    than ``tuning.gap_s`` carries no current (a rest, as the engine assumes over a gap); the
    grid keeps tau2 >= ``tuning.tau_ratio_min`` tau1 (None: the defaults). NaN where
    the window is too short, moves SOC too little, or the fit is unphysical (a negative
    resistance). The fit starts h at 0, as the engine does: on the paper cell entered mid-DST,
    where h had gone towards -1, it reads ~1 SOC point low (a start-h column was tried: 1.4)."""
    tun = tuning or EstimatorTuning()
    t = np.asarray(t_s, dtype=np.float64)
    keep = t <= t[0] + window_s
    i_raw = np.asarray(current_A, dtype=np.float64)[keep]
    t, i = t[keep], _held(i_raw)
    i_read = np.isfinite(i_raw)  # a sample without its current has no R0 term: not fitted
    v = np.asarray(voltages_V, dtype=np.float64).reshape(keep.shape[0], -1)[keep]
    n = v.shape[1]
    soc0 = np.full(n, np.nan)
    rmse = np.full(n, np.nan)
    branch = np.full((n, 2), np.nan)
    if t.shape[0] < MIN_SAMPLES or t[-1] - t[0] < 0.5 * window_s:
        return StartFit(soc0, rmse, window_s, branch)
    dt = np.maximum(np.diff(t), 0.0)
    i_held = np.where(dt > tun.gap_s, 0.0, i[:-1])  # the current held over each step (ZOH)
    charge_As = np.concatenate(([0.0], np.cumsum(i_held * dt)))
    for c in range(n):
        lo1, hi1 = (float(b[c]) for b in model.bound("tau1_s"))
        lo2, hi2 = (float(b[c]) for b in model.bound("tau2_s"))
        tau1 = np.geomspace(lo1, hi1, GRID_POINTS)
        tau2 = np.geomspace(lo2, max(min(hi2, 0.5 * window_s), lo2), GRID_POINTS)
        x1, x2 = _branch_states(i_held, dt, tau1), _branch_states(i_held, dt, tau2)
        d1 = np.exp(-(t - t[0])[None, :] / tau1[:, None])
        d2 = np.exp(-(t - t[0])[None, :] / tau2[:, None])
        pairs = tau2[None, :] >= tun.tau_ratio_min * tau1[:, None]
        z0 = float(soc_guess[c])
        if not np.isfinite(z0):
            continue
        ok = np.isfinite(v[:, c]) & i_read
        q_As = float(model.capacity_As[c])
        if np.count_nonzero(ok) < MIN_SAMPLES or np.ptp(charge_As[ok]) / q_As < MIN_SOC_SWING:
            continue  # a dead tap, a cell that came in late, or too little charge moved
        h = _hysteresis(i_held, dt, model, c)
        fit = None
        for _ in range(MAX_ITER):
            z = z0 - charge_As / q_As
            zc, _ = model.ocv.clamp(z)
            y = v[:, c] - model.ocv.ocv(zc) - model.ocv.hysteresis_M(zc) * h
            slope = None if soc_known else model.ocv.docv_dz(zc)[ok]
            fit = _best_fit(y[ok], -i[ok], x1[:, ok], x2[:, ok], slope, d1[:, ok], d2[:, ok],
                            pairs)  # fmt: skip
            if fit is None or abs(fit[1]) > MAX_DZ:
                fit = None
                break
            z0 += fit[1]
            if abs(fit[1]) < 1e-4:
                break
        if fit is not None and abs(z0 - float(soc_guess[c])) <= MAX_DZ:
            soc0[c], rmse[c] = z0, fit[0]
            branch[c] = -fit[2], -fit[3]
    return StartFit(soc0, rmse, window_s, branch)


def _held(current_A: FloatArray) -> FloatArray:
    """NaN currents replaced by the last valid one before them (0 before the first)."""
    valid = np.isfinite(current_A)
    last = np.maximum.accumulate(np.where(valid, np.arange(current_A.shape[0]), -1))
    return np.where(last >= 0, current_A[np.maximum(last, 0)], 0.0)


def _branch_states(i_held: FloatArray, dt: FloatArray, taus: FloatArray) -> FloatArray:
    """Unit-gain ZOH branch states (Eq. 8) for each time constant: (taus, samples), from 0."""
    a = np.exp(-dt[None, :] / taus[:, None])
    x = np.zeros((taus.shape[0], dt.shape[0] + 1))
    for k in range(dt.shape[0]):
        x[:, k + 1] = a[:, k] * x[:, k] + (1.0 - a[:, k]) * i_held[k]
    return x


def _hysteresis(i_held: FloatArray, dt: FloatArray, model: CellModel, c: int) -> FloatArray:
    """h over the window from 0 (Eq. 5-6), as the engine starts it."""
    kappa = hysteresis_kappa(model.gamma[c], model.capacity_As[c], model.efficiency[c], i_held)
    h = np.zeros(dt.shape[0] + 1)
    for k in range(dt.shape[0]):
        h[k + 1] = float(hysteresis_step(h[k], i_held[k], dt[k], kappa[k]))
    return h


def _best_fit(
    y: FloatArray, minus_i: FloatArray, x1: FloatArray, x2: FloatArray,
    slope: FloatArray | None, d1: FloatArray, d2: FloatArray, pairs: npt.NDArray[np.bool_],
) -> tuple[float, float, float, float] | None:  # fmt: skip
    """(RMSE V, dz, c1 V, c2 V) of the best physical (R0, R1, R2 > 0) solve over the
    time-constant grid's ``pairs``; without ``slope`` SOC is known (dz 0, not fitted)."""
    best: tuple[float, float, float, float] | None = None
    for j1, j2 in zip(*np.nonzero(pairs), strict=True):
        cols = [minus_i, -x1[j1], -x2[j2]] + ([] if slope is None else [slope])
        A = np.column_stack([*cols, d1[j1], d2[j2]])
        th, *_ = np.linalg.lstsq(A, y, rcond=None)
        if not (th[0] > 0 and th[1] > 0 and th[2] > 0 and np.all(np.isfinite(th))):
            continue
        rmse = float(np.sqrt(np.mean((y - A @ th) ** 2)))
        if best is None or rmse < best[0]:
            dz = 0.0 if slope is None else float(th[3])
            best = (rmse, dz, float(th[-2]), float(th[-1]))
    return best
