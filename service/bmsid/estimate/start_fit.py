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
best kept (``tau_grid.py``), re-linearised until dz settles. The relaxation and the load are
explained by the branches; what they cannot explain, a level that follows the OCV slope, is SOC.
Where SOC is known (given by the user) the dz column is left out. Pure numpy.

The engine starts its branches at the fitted ``-c_j`` (``EstimatorBank(branch0_V=...)``), not
empty: a bank that meets a loaded first voltage with empty branches reads their voltage as a
model error and its first updates put it into R0 (the CALCE 25 C BJDST record entered 1,800 s
in: R0 74 -> 121 mOhm in 15 s, 22 mV of error over the first minute).

Measured (``bench/starts_real.py``): the four polarised 25 C starts read 77.6 / 77.9 / 43.4 /
43.9 % from their first voltages for 80 / 80 / 50 / 50 %; fitted over 20 min, 80.5 / 81.8 /
49.8 / 50.2 %. On starts that are at rest and relaxed the first voltage is better (0 C DST
from 50 %: 55.0 % read, 52.0 % fitted, 54.8 % true: the 0 C model's error biases the fit), so
the dz fit is used only where the first voltage is known to mislead.

A rested start's first voltage is OCV(z0) + M(z0) h0 with h0 unknown: -1 after a discharge, +1
after a charge, which the engine's start (h = 0) reads as 1.5-3 SOC points on the paper cell
(M 15 mV), and a discharge without a rest then carries that into R2 (R0 + R1 + R2 -27 % from
45 %). With ``rested`` the extra column is h0 along that voltage's line (z0 follows it,
``dz0/dh0 = -M / OCV'``; h_k = h_free,k + h0 decay_k, Eq. 5-6 being affine in h; the play
law's h is h0 plus the charge's shifts until it clips): after a
discharge starts, h goes to -1 whatever h0 was, so the window shows it. Kept only where it
explains the window clearly better than h = 0 (``H0_GAIN_MIN``): the model's own error (a
cold cell, a small half-gap) is no hysteresis. Where SOC is given (``--soc0``) h stays 0: an
h0 column at a known SOC was tried, and took +1 on a CALCE 45 C start from 50 % after a
discharge.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from bmsid.estimate.cellmodel import CellModel
from bmsid.estimate.rest_anchor import noise_std_A
from bmsid.estimate.tau_grid import Fit, TauGrid, best_fit, refined_fit
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
#: A rested start's fitted h0 is kept only where the window's RMSE with h = 0 is this many
#: times the fit's: the start state explains at least as much of the misfit as the fit
#: leaves (known-truth DST, h0 = +-1: 1.56-7.7, 0: 1.00; CALCE NMC, half-gap 3-5 mV: the 45 C
#: starts from 80 % after the cycler's discharge 1.45-2.05 with h0 = -1, the other rested
#: starts short of it, their h0 anywhere in [-1, 1]).
H0_GAIN_MIN = math.sqrt(2.0)
#: A rested record whose load starts later than this into the window (fraction of it) is fitted
#: from ``LEAD_S`` before the load instead (a car parked, then driven: its first 20 min all rest).
LATE_LOAD = 0.5
#: Rest kept before the load in a window moved to it, s.
LEAD_S = 60.0
#: Longest leading rest read for a window after it, s (a night parked).
MAX_LEADING_REST_S = 12 * 3600.0
#: Cell-samples kept at most for a start window (8 bytes each: 32 MB; 1,200 s of 96 cells at
#: 30 Hz): the daemon's head (``daemon/start_refit.py``), and offline a long leading rest's.
MAX_HEAD_CELL_SAMPLES = 4_000_000
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
    #: per cell, the hysteresis state at the first sample (in [-1, 1]): fitted on a rested
    #: start (``rested``), else 0, as the engine starts it
    h0: FloatArray


def fit_start_soc(
    t_s: FloatArray, current_A: FloatArray, voltages_V: FloatArray, model: CellModel,
    soc_guess: FloatArray, window_s: float = WINDOW_S, tuning: EstimatorTuning | None = None,
    soc_known: bool = False, rested: bool = False, each_cell: Callable[[], None] | None = None,
) -> StartFit:  # fmt: skip
    """The start SOC of each cell fitted over the first ``window_s`` of the record (module
    docstring), from ``soc_guess`` (the first voltage's reading); with ``soc_known`` the
    guess is the SOC (given by the user) and only the branches are fitted (no dz column);
    with ``rested`` (a start at rest and relaxed, SOC not known) h0 is fitted instead of dz,
    z0 following it along the first voltage's line, and ``StartFit.h0`` returns it (no fit
    where it is not worth ``H0_GAIN_MIN``); ``each_cell`` is called between cells.
    Samples (s, A with + = discharge, V (samples, cells)); NaN voltages are left out, and so
    are samples with a NaN
    current (the branches and the count hold the current before through them); a step longer
    than ``tuning.gap_s`` carries no current (a rest, as the engine assumes over a gap); the
    grid keeps tau2 >= ``tuning.tau_ratio_min`` tau1 (None: the defaults). NaN where
    the window is too short, moves SOC too little, or the fit is unphysical (a negative
    resistance). A loaded start's fit starts h at 0, as the engine does: on the paper cell
    entered mid-DST, where h had gone towards -1, it reads ~1 SOC point low (a start-h column
    beside dz was tried: 1.4; under load the two columns are nearly one)."""
    tun = tuning or EstimatorTuning()
    t = np.asarray(t_s, dtype=np.float64)
    guess = np.asarray(soc_guess, dtype=np.float64)
    start = t[0]
    if rested:  # a long rest first: the window from just before the load
        rest_A = float(np.min(model.soc_start.rest_current_C * model.capacity_Ah))
        load = first_load_s(t, np.asarray(current_A, dtype=np.float64), rest_A)
        start = window_start(float(t[0]), load, float(t[-1]), window_s) or float(t[0])
    keep = t <= start + window_s
    i_raw = np.asarray(current_A, dtype=np.float64)[keep]
    t, i = t[keep], _held(i_raw)
    i_read = np.isfinite(i_raw)  # a sample without its current has no R0 term: not fitted
    v = np.asarray(voltages_V, dtype=np.float64).reshape(keep.shape[0], -1)[keep]
    n = v.shape[1]
    # the charge the rest before the window moved (A s; its small currents), which SOC keeps
    dt_all = np.maximum(np.diff(t), 0.0)
    w0 = int(np.searchsorted(t, start))
    before_As = float(np.sum((np.where(dt_all > tun.gap_s, 0.0, i[:-1]) * dt_all)[:w0]))
    t, i, i_read, v = t[w0:], i[w0:], i_read[w0:], v[w0:]
    soc0 = np.full(n, np.nan)
    rmse = np.full(n, np.nan)
    branch = np.full((n, 2), np.nan)
    h_start = np.zeros(n)
    if t.shape[0] < MIN_SAMPLES or t[-1] - t[0] < 0.5 * window_s:
        return StartFit(soc0, rmse, window_s, branch, h_start)
    dt = np.maximum(np.diff(t), 0.0)
    i_held = np.where(dt > tun.gap_s, 0.0, i[:-1])  # the current held over each step (ZOH)
    charge_As = np.concatenate(([0.0], np.cumsum(i_held * dt)))
    grids: dict[tuple[float, ...], TauGrid] = {}
    paths: dict[tuple[float, ...], _HPath] = {}
    for c in range(n):
        if each_cell is not None and c:
            each_cell()
        bounds = tuple(float(b[c]) for name in ("tau1_s", "tau2_s") for b in model.bound(name))
        if bounds not in grids:  # one current for every cell: a pack's cells share a grid
            lo1, hi1, lo2, hi2 = bounds
            grids[bounds] = TauGrid.of(
                np.geomspace(lo1, hi1, GRID_POINTS),
                np.geomspace(lo2, max(min(hi2, 0.5 * window_s), lo2), GRID_POINTS),
                i_held, dt, t, tun.tau_ratio_min,
            )  # fmt: skip
        grid = grids[bounds]
        q_As = float(model.capacity_As[c])
        z0 = float(guess[c]) - before_As / q_As  # at the window's start
        if not np.isfinite(z0):
            continue
        ok = np.isfinite(v[:, c]) & i_read
        if np.count_nonzero(ok) < MIN_SAMPLES or np.ptp(charge_As[ok]) / q_As < MIN_SOC_SWING:
            continue  # a dead tap, a cell that came in late, or too little charge moved
        rate = (float(model.gamma[c]), float(model.capacity_As[c]), float(model.efficiency[c]))
        if rate not in paths:
            paths[rate] = _HPath.of(i_held, dt, model, c)
        cell = _CellWindow(v[:, c], ok, i, charge_As / q_As, paths[rate])
        if rested:
            res = _fit_h0(model, cell, z0, grid)
        else:
            res = _fit_dz(model, cell, z0, grid.at(ok), soc_known)
        if res is not None and abs(res[0] + before_As / q_As - float(guess[c])) <= MAX_DZ:
            soc0[c], h_start[c], fit = res[0] + before_As / q_As, res[1], res[2]
            rmse[c], branch[c] = fit[0], (-fit[2], -fit[3])
    if rested:
        _shared_history(model, guess, soc0, h_start, branch)
    return StartFit(soc0, rmse, window_s, branch, h_start)


def first_load_s(
    t_s: FloatArray, current_A: FloatArray, rest_limit_A: float, noise_sd_A: float = 0.0
) -> float | None:
    """Time (s) of the first sample whose |current| exceeds ``rest_limit_A`` (A; NaN: rest) by
    more than 3 std of the sensor's noise (these samples' ``rest_anchor.noise_std_A``, at least
    ``noise_sd_A``, A, what earlier samples showed: 10 mA of noise on a 2 Ah cell put the load
    at the second sample of a one-hour rest, and the window that shows the start's hysteresis
    state was missed), None if none does."""
    limit = rest_limit_A + 3.0 * max(noise_std_A(current_A, rest_limit_A), noise_sd_A)
    busy = np.flatnonzero(np.abs(np.nan_to_num(current_A)) > limit)
    return float(t_s[busy[0]]) if busy.size else None


def window_start(
    first_s: float, load_s: float | None, last_s: float, window_s: float = WINDOW_S
) -> float | None:
    """Where the fitted window starts (s), for samples from ``first_s`` to ``last_s`` whose load
    starts at ``load_s`` (None: not yet): the first sample, unless the record rests for more
    than ``LATE_LOAD`` of the window first: then ``LEAD_S`` before the load. None while the
    rest so far is longer than that and no load has come."""
    if load_s is not None:
        return first_s if load_s - first_s <= LATE_LOAD * window_s else load_s - LEAD_S
    return first_s if last_s - first_s <= LATE_LOAD * window_s else None


def head_end_s(first_s: float, load_s: float | None, last_s: float) -> float:
    """The time (s) the samples kept for the start fit must reach (``window_start`` + its
    window; after ``MAX_LEADING_REST_S`` of rest without a load, the fit is given up there)."""
    start = window_start(first_s, load_s, last_s)
    return (first_s + MAX_LEADING_REST_S if start is None else start) + WINDOW_S


def _shared_history(
    model: CellModel, guess: FloatArray, soc0: FloatArray, h0: FloatArray, branch: FloatArray
) -> None:
    """Cells in series share one current history, so one h0: where most cells with a first
    voltage fitted theirs, the others take the median along their own first voltage's line;
    where fewer did, none keeps its fit (the start is the engine's). In place."""
    read = np.isfinite(guess)
    fitted = np.isfinite(soc0) & read
    if 2 * np.count_nonzero(fitted) <= np.count_nonzero(read):
        soc0[:], h0[:], branch[:] = np.nan, 0.0, np.nan
        return
    h = float(np.median(h0[fitted]))
    for c in np.flatnonzero(read & ~fitted):
        v_rest = float(model.ocv.ocv(guess[c : c + 1])[0])
        soc0[c], h0[c], branch[c] = _rested_soc(model, v_rest, h, float(guess[c])), h, 0.0


@dataclass(frozen=True)
class _CellWindow:
    """One cell's window: its voltages (V), the samples fitted, the held current (A), the
    charge counted from the start (fraction of its capacity), and h as a function of h0."""

    v_V: FloatArray
    ok: npt.NDArray[np.bool_]
    current_A: FloatArray
    charge: FloatArray
    h: _HPath

    def residual(self, model: CellModel, z0: float, h0: float) -> tuple[FloatArray, ...]:
        """Eq. 9's left side ``v - OCV(z) - M(z) h`` from (z0, h0), M(z), OCV'(z) and
        dh/dh0."""
        zc, _ = model.ocv.clamp(z0 - self.charge)
        m = model.ocv.hysteresis_M(zc)
        h, dh = self.h.at(h0)
        y = self.v_V - model.ocv.ocv(zc) - m * h
        return y, m, model.ocv.docv_dz(zc), dh


@dataclass(frozen=True)
class _HPath:
    """h over the window as a function of its start h0 (Eq. 5-6). Plett's law is affine in h0:
    ``h_free + h0 decay``. The play (``ecm.hysteresis_step``) is not: h0 plus the charge's
    shifts until the path first clips at a branch, the same path for every h0 from there on
    (``moves``: the per-interval shifts, -2 kappa i dt; ``h_free`` and ``decay`` then unused,
    empty)."""

    h_free: FloatArray
    decay: FloatArray
    moves: list[float] | None = None

    @classmethod
    def of(cls, i_held: FloatArray, dt: FloatArray, model: CellModel, c: int) -> _HPath:
        if model.hysteresis_play:
            kappa = hysteresis_kappa(
                model.gamma[c], model.capacity_As[c], model.efficiency[c], i_held
            )
            return cls(np.empty(0), np.empty(0), (-2.0 * kappa * i_held * dt).tolist())
        h_free = _hysteresis(i_held, dt, model, c)
        return cls(h_free, _hysteresis(i_held, dt, model, c, 1.0) - h_free)

    def at(self, h0: float) -> tuple[FloatArray, FloatArray]:
        """(h, dh/dh0) over the window's samples from ``h0``."""
        if self.moves is None:
            return self.h_free + h0 * self.decay, self.decay
        h, dh, hk, free = [h0], [1.0], h0, 1.0  # plain floats: a window is 10^3-10^4 steps
        for mv in self.moves:
            x = hk + mv
            hk = -1.0 if x < -1.0 else 1.0 if x > 1.0 else x
            free = free if hk == x else 0.0  # clipped once: h0 no longer matters
            h.append(hk)
            dh.append(free)
        return np.array(h), np.array(dh)


def _fit_dz(
    model: CellModel, w: _CellWindow, z0: float, grid: TauGrid, soc_known: bool
) -> tuple[float, float, Fit] | None:
    """(z0, 0, fit) of a loaded or relaxing start: dz re-linearised until it settles (none
    where SOC is known: the branches only)."""
    fit = None
    for _ in range(MAX_ITER):
        y, _, slope, _ = w.residual(model, z0, 0.0)
        col = None if soc_known else slope[w.ok]
        fit = best_fit(y[w.ok], -w.current_A[w.ok], col, grid)
        if fit is None or abs(fit[1]) > MAX_DZ:
            return None
        z0 += fit[1]
        if abs(fit[1]) < 1e-4:
            break
    return None if fit is None else (z0, 0.0, fit)


def _fit_h0(
    model: CellModel, w: _CellWindow, z0: float, grid: TauGrid
) -> tuple[float, float, Fit] | None:
    """(z0, h0, fit) of a rested start: h0 along the first voltage's line (module docstring),
    on refined grids (h0 takes up what the coarse grid's step leaves: -0.5 for 0), the branches
    empty (relaxed: no decay columns, fewer to trade with h0). None
    where h0 explains too little: the window's RMSE with h = 0 under ``H0_GAIN_MIN`` x the
    fit's (the model's error, not h), unless h = 0 has no physical fit at all (LFP after a
    discharge, its curve flat)."""
    v_rest = float(model.ocv.ocv(np.array([z0]))[0])  # OCV(z0) + M h0 at the first sample
    h0, fit, plain = 0.0, None, None
    for _ in range(MAX_ITER):
        y, m, slope, dh = w.residual(model, z0, h0)
        if not (math.isfinite(slope[0]) and slope[0] != 0.0):
            return None  # a flat point of the curve (a PCHIP table's extremum): no SOC line
        col = (m * dh - slope * m[0] / slope[0])[w.ok]  # dz0/dh0 = -M / OCV'
        fit = refined_fit(y[w.ok], -w.current_A[w.ok], col, grid, w.ok, decays=False)
        if plain is None:  # h = 0 at the first voltage's reading: what h0 must beat
            base = refined_fit(y[w.ok], -w.current_A[w.ok], None, grid, w.ok, decays=False)
            plain = base or (math.nan,)
        if fit is None:
            return None
        step = float(np.clip(h0 + fit[1], -1.0, 1.0)) - h0
        h0 += step
        z0 = _rested_soc(model, v_rest, h0, z0)
        if abs(step) < 1e-4:
            break
    if fit is None or plain is None or plain[0] < H0_GAIN_MIN * fit[0]:
        return None
    return z0, h0, fit


def _rested_soc(model: CellModel, v_rest_V: float, h0: float, z0: float) -> float:
    """The SOC whose OCV with the hysteresis state ``h0`` is ``v_rest_V`` (V): a few fixed-point
    steps from ``z0`` (M varies slowly with SOC)."""
    z = np.array([z0])
    for _ in range(4):
        zc, _ = model.ocv.clamp(z)
        z = model.ocv.soc_from_ocv(np.array([v_rest_V - float(model.ocv.hysteresis_M(zc)[0]) * h0]))
    return float(z[0])


def _held(current_A: FloatArray) -> FloatArray:
    """NaN currents replaced by the last valid one before them (0 before the first)."""
    valid = np.isfinite(current_A)
    last = np.maximum.accumulate(np.where(valid, np.arange(current_A.shape[0]), -1))
    return np.where(last >= 0, current_A[np.maximum(last, 0)], 0.0)


def _hysteresis(
    i_held: FloatArray, dt: FloatArray, model: CellModel, c: int, h0: float = 0.0
) -> FloatArray:
    """h over the window from ``h0`` (Eq. 5-6; 0: as the engine starts it)."""
    kappa = hysteresis_kappa(model.gamma[c], model.capacity_As[c], model.efficiency[c], i_held)
    h = np.full(dt.shape[0] + 1, h0)
    for k in range(dt.shape[0]):
        h[k + 1] = float(hysteresis_step(h[k], i_held[k], dt[k], kappa[k], model.hysteresis_play))
    return h
