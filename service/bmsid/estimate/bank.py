"""The estimator bank: N cells that share one pack current, identified in one vectorised call.

Variants (the paper's three):

* ``non-hy-affrls`` - AFFRLS on the bilinear ARX model (Eq. 15-21) of ``U_E = V - OCV(z)``,
  mapped back to R0, R1, C1, R2, C2 by the corrected Eq. 22-23.
* ``hy-affrls`` - the same with the hysteresis voltage removed first: ``U_E = V - OCV - M(z) h``.
* ``hy-affrls-lpso`` - the fusion, designed as follows::

        samples --> [decimate to id_period] --> tick k
                                                  |
           +--------------------------------------+------------------------------+
           | every tick (cheap, vectorised over cells)                           |
           |   propagate z, h, x1, x2 with the taus in force                     |
           |   phi = [-i, -x1, -x2, M(z) h, 1]   (linear in R0,R1,R2,s,offset)   |
           |   v_model = OCV(z) + phi . theta(k-1)        (a-priori, Eq. 9)      |
           |   AFFRLS step on theta (Eq. 17-21): R0,R1,R2, M scale, OCV offset   |
           +-----------------------------------+---------------------------------+
                 window buffer (last window_s) |        ^ new taus, theta, P, x1, x2
                                               v        |
           +--------------------------------------------+------------------------+
           | every swarm_period_s per cell (amortised: fits_per_update particle  |
           | swarm iterations per tick, cells staggered across the period)       |
           |   LPSO (Eq. 24-30) over ln tau1, ln tau2, seeded at the taus in use; |
           |   fitness = window RMSE of the full hysteresis model with the linear |
           |   parameters solved exactly (variable projection, estimate/varpro). |
           |   On completion: taus <- swarm optimum; theta, P <- the exponentially|
           |   weighted LS solution and its covariance over the window (what the  |
           |   AFFRLS would hold had it run with those poles); x1, x2 re-filtered.|
           +---------------------------------------------------------------------+

  LPSO owns the poles, where recursive ARX identification is ill-conditioned (it divides by
  1 - th1 - th2 ~ 5e-5: the "filter saturation" of the paper); AFFRLS owns the parameters the
  voltage is linear in and tracks them every tick. Worst-case cost of one ``update``: the tick
  (a few hundred microseconds of numpy call overhead, nearly independent of the cell count) plus
  ``fits_per_update`` window fits (one particle each, ~0.3-1 ms at 1800 samples) for every cell
  whose swarm is running; cells are staggered across ``swarm_period_s`` so few run at once.

Time handling: samples are averaged into ``id_period_s`` bins (SOC is coulomb-counted at the raw
rate); a time step longer than ``gap_s`` is a gap (zero current assumed, histories restart);
non-increasing time is dropped and counted; NaN currents hold the previous current, NaN voltages
skip that cell's update. Every published value is finite and inside the configured bounds.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
import numpy.typing as npt

from bmsid.config.cell import CellConfig
from bmsid.estimate import lpso
from bmsid.estimate.affrls import adaptive_lambda, reset_covariance, rls_update
from bmsid.estimate.tuning import EstimatorTuning, Variant
from bmsid.estimate.types import VARIANTS, Estimates, Quality
from bmsid.estimate.varpro import Window, fit_linear
from bmsid.model.arx import MapStatus, params_to_theta, theta_to_params
from bmsid.model.hysteresis import hysteresis_step
from bmsid.model.ocv import OcvModel

FloatArray = npt.NDArray[np.float64]
BoolArray = npt.NDArray[np.bool_]


@dataclass
class _CellSwarm:
    """A running swarm of one cell and the window snapshot it fits."""

    swarm: lpso.Swarm
    window: Window
    weights: FloatArray
    rng: np.random.Generator
    fitness: FloatArray  # of the current positions, filled a few particles per tick
    done_fits: int = 0


@dataclass
class _Buffer:
    """Ring buffer of identification ticks for the swarm window (shared current, per-cell y)."""

    size: int
    n_cells: int
    current_A: FloatArray = field(init=False)
    y_V: FloatArray = field(init=False)
    hm_V: FloatArray = field(init=False)
    valid: BoolArray = field(init=False)
    head: int = 0
    count: int = 0

    def __post_init__(self) -> None:
        self.current_A = np.zeros(self.size)
        self.y_V = np.zeros((self.n_cells, self.size))
        self.hm_V = np.zeros((self.n_cells, self.size))
        self.valid = np.zeros((self.n_cells, self.size), dtype=bool)

    def push(self, i: float, y: FloatArray, hm: FloatArray, valid: BoolArray) -> None:
        j = self.head
        self.current_A[j] = i
        self.y_V[:, j] = y
        self.hm_V[:, j] = hm
        self.valid[:, j] = valid
        self.head = (j + 1) % self.size
        self.count = min(self.count + 1, self.size)

    def order(self) -> npt.NDArray[np.intp]:
        """Indices of the buffered ticks, oldest first."""
        start = (self.head - self.count) % self.size
        return (start + np.arange(self.count)) % self.size

    def clear(self) -> None:
        self.count = 0


class EstimatorBank:
    """Online identification of ``n_cells`` cells of one cell type (see the module docstring).

    Args:
        cell: the cell configuration (OCV, hysteresis table, bounds, capacity).
        n_cells: cells sharing the pack current.
        variant: ``non-hy-affrls``, ``hy-affrls`` or ``hy-affrls-lpso``.
        tuning: estimator constants (defaults documented in ``EstimatorTuning``).
        soc0: initial SOC (fraction, scalar or per cell); None applies ``cell.soc_init``.
        cell_ids: global index of each cell (seeds its swarm and staggers its schedule), default
            0..n_cells-1; ``n_stagger`` is the number of cells the schedule is spread over.
    """

    def __init__(
        self,
        cell: CellConfig,
        n_cells: int,
        variant: Variant = "hy-affrls-lpso",
        tuning: EstimatorTuning | None = None,
        soc0: float | FloatArray | None = None,
        cell_ids: npt.ArrayLike | None = None,
        n_stagger: int | None = None,
    ) -> None:
        if variant not in VARIANTS:
            raise ValueError(f"unknown variant {variant!r}; choose one of {', '.join(VARIANTS)}")
        if n_cells < 1:
            raise ValueError("n_cells must be >= 1")
        self.cell = cell
        self.n = n_cells
        self.variant: Variant = variant
        self.tuning = tuning or EstimatorTuning()
        self.ocv = OcvModel.from_cell(cell)
        self.cell_ids = (
            np.arange(n_cells) if cell_ids is None else np.asarray(cell_ids, dtype=np.int64)
        )
        n_st = n_stagger or n_cells
        self._phase = (self.cell_ids % n_st) / n_st
        self._soc0_arg = soc0
        self.soc_init_method = "pending"
        self.counters: dict[str, int] = {
            "samples": 0,
            "ticks": 0,
            "non_increasing_time": 0,
            "time_jumps_back": 0,
            "nan_current": 0,
            "nan_voltage": 0,
            "gaps": 0,
            "swarms": 0,
            "arx_rejected": 0,
            "clamped": 0,
        }
        self._init_state()

    # ------------------------------------------------------------------ state
    def _init_state(self) -> None:
        n, tun, b = self.n, self.tuning, self.cell.bounds
        ini = self.cell.initial_parameters()
        self._Q_As = self.cell.capacity_Ah * 3600.0
        self._eta = self.cell.coulombic_efficiency
        self._kappa = self.cell.hysteresis.gamma / self._Q_As
        self.z = np.full(n, 0.5)
        self.h = np.zeros(n)
        self.x1 = np.zeros(n)
        self.x2 = np.zeros(n)
        self.R0 = np.full(n, ini.R0_ohm)
        self.R1 = np.full(n, ini.R1_ohm)
        self.R2 = np.full(n, ini.R2_ohm)
        self.tau1 = np.full(n, min(max(ini.tau1_s, b.tau1_s.lo), b.tau1_s.hi))
        self.tau2 = np.full(n, min(max(ini.tau2_s, b.tau2_s.lo), b.tau2_s.hi))
        self.Ms = np.ones(n)
        self.off = np.zeros(n)
        self.lam = np.ones(n)
        self.sig_e = np.full(n, tun.e_floor_V)
        self.arx_err = np.zeros(n)
        # Normalisation of the linear parameters (R0, R1, R2, M scale, offset).
        self._scale = np.array([ini.R0_ohm, ini.R1_ohm, ini.R2_ohm, 1.0, 0.05])
        self._lin_lo = np.array(
            [b.R0_ohm.lo, b.R1_ohm.lo, b.R2_ohm.lo, b.M_scale.lo, b.ocv_offset_V.lo]
        )
        self._lin_hi = np.array(
            [b.R0_ohm.hi, b.R1_ohm.hi, b.R2_ohm.hi, b.M_scale.hi, b.ocv_offset_V.hi]
        )
        self.theta = np.tile(
            np.array([ini.R0_ohm, ini.R1_ohm, ini.R2_ohm, 1.0, 0.0]) / self._scale, (n, 1)
        )
        self.P = self._fusion_covariance(reset_covariance(n, 5, tun.p0))
        self._phi = np.ones((n, 5))  # regressor of the fusion, refilled every tick
        self._arx_bounds = (
            np.array([[b.R0_ohm.lo], [b.R1_ohm.lo], [b.R2_ohm.lo], [b.tau1_s.lo], [b.tau2_s.lo]]),
            np.array([[b.R0_ohm.hi], [b.R1_ohm.hi], [b.R2_ohm.hi], [b.tau1_s.hi], [b.tau2_s.hi]]),
        )
        # ARX (bilinear) state, used by the non-fusion variants.
        self._arx_scale = np.array([1.0, 1.0, ini.R0_ohm, ini.R0_ohm, ini.R0_ohm])
        self.theta_arx = np.zeros((n, 5))
        self.P_arx = reset_covariance(n, 5, tun.p0)
        self.T_arx = 0.0
        self._ue_hist = np.zeros((n, 2))
        self._i_hist = np.zeros(2)
        self._hist_n = 0
        self.arx_ok = np.zeros(n, dtype=bool)
        # Raw-sample and tick clocks.
        self._t_raw: float | None = None
        self._i_raw = 0.0
        self._t_tick = 0.0
        self._i_tick = 0.0
        self._bin_i = 0.0
        self._bin_n = 0
        self._bin_v = np.zeros(n)
        self._bin_vn = np.zeros(n, dtype=np.int64)
        self._i_mean = 0.0
        self._i_var = 0.0
        self._lam_exp = 1.0  # 1 / (forgetting time step): reports lambda per second
        self._dt_nom = 0.0  # running nominal tick period, s (ticks are id_period_s or slower)
        # Swarm scheduling.
        size = int(np.ceil(tun.window_s / tun.id_period_s)) + 1
        self._buf = _Buffer(size=size, n_cells=n)
        self._next_swarm = np.zeros(n)
        self._swarm_count = np.zeros(n, dtype=np.int64)
        self._swarms: list[_CellSwarm | None] = [None] * n
        self.fused = np.zeros(n, dtype=bool)
        self._clamped = np.zeros(n, dtype=bool)

    # ------------------------------------------------------------------ public API
    def update(self, t_s: float, current_A: float, voltages_V: npt.ArrayLike) -> Estimates | None:
        """Feed one raw sample (time s, pack current A, cell voltages V); returns the estimates
        when an identification tick completes, else None. Never raises on bad numbers."""
        v = np.asarray(voltages_V, dtype=np.float64).reshape(self.n)
        self.counters["samples"] += 1
        if not np.isfinite(t_s):
            self.counters["non_increasing_time"] += 1
            return None
        if not np.isfinite(current_A):
            self.counters["nan_current"] += 1
            current_A = self._i_raw
        bad_v = ~np.isfinite(v)
        n_bad = int(bad_v.sum())
        v_raw = v
        if n_bad:
            self.counters["nan_voltage"] += n_bad
            v = np.where(bad_v, 0.0, v)  # summed into the bin, excluded by the count
        if self._t_raw is None:
            self._start(t_s, current_A, v_raw)
            return self._tick(t_s, current_A, v_raw, ~bad_v, 0.0)
        dt = t_s - self._t_raw
        if dt < -self.tuning.gap_s:
            # The time base restarted (a replay from its beginning, a gateway clock set back
            # after a restart from a checkpoint): start a new segment instead of rejecting every
            # later sample as "non-increasing"; the time in between is unknown, so nothing is
            # propagated across it.
            self.counters["time_jumps_back"] += 1
            return self._gap(t_s, current_A, v_raw, ~bad_v, elapsed_s=0.0)
        if dt <= 0:
            self.counters["non_increasing_time"] += 1
            return None
        if dt > self.tuning.gap_s:
            return self._gap(t_s, current_A, v_raw, ~bad_v)
        eff = self._eta if self._i_raw < 0 else 1.0
        self.z = self.z - eff * self._i_raw * dt / self._Q_As
        self._t_raw = t_s
        self._i_raw = current_A
        self._bin_i += current_A
        self._bin_n += 1
        self._bin_v += v
        self._bin_vn += ~bad_v
        if t_s - self._t_tick < self.tuning.id_period_s - 0.5 * dt:
            return None
        i_avg = self._bin_i / self._bin_n
        has_v = self._bin_vn > 0
        v_avg = np.where(has_v, self._bin_v / np.maximum(self._bin_vn, 1), np.nan)
        dt_tick = t_s - self._t_tick
        self._clear_bin()
        return self._tick(t_s, i_avg, v_avg, has_v, dt_tick)

    # ------------------------------------------------------------------ internals
    def _clear_bin(self) -> None:
        self._bin_i = 0.0
        self._bin_n = 0
        self._bin_v[:] = 0.0
        self._bin_vn[:] = 0

    def _start(self, t_s: float, current_A: float, v: FloatArray) -> None:
        si = self.cell.soc_init
        if self._soc0_arg is not None:
            self.z = np.broadcast_to(np.asarray(self._soc0_arg, dtype=float), (self.n,)).copy()
            self.soc_init_method = "given"
        elif (
            si.policy == "ocv_at_rest"
            and abs(current_A) <= si.rest_current_C * self.cell.capacity_Ah
        ):
            fallback = si.soc0 if si.soc0 is not None else 0.5
            z = self.ocv.soc_from_ocv(np.where(np.isfinite(v), v, np.nan))
            self.z = np.where(np.isfinite(z), z, fallback)
            self.soc_init_method = "ocv_at_rest"
        else:
            self.z = np.full(self.n, si.soc0 if si.soc0 is not None else 0.5)
            self.soc_init_method = "config" if si.soc0 is not None else "default_0.5"
        self._t_raw = t_s
        self._i_raw = current_A
        self._t_tick = t_s
        self._i_tick = current_A
        self._start_segment(t_s)

    def _start_segment(self, t_s: float) -> None:
        tun = self.tuning
        self._buf.clear()
        self._swarms = [None] * self.n
        self._next_swarm = t_s + tun.min_window_s + self._phase * tun.swarm_period_s
        self._hist_n = 0

    def _gap(
        self,
        t_s: float,
        current_A: float,
        v: FloatArray,
        ok: BoolArray,
        elapsed_s: float | None = None,
    ) -> Estimates:
        """New segment after a gap of ``elapsed_s`` (default: the time since the last tick)."""
        self.counters["gaps"] += 1
        dt = t_s - self._t_tick if elapsed_s is None else elapsed_s
        self._clear_bin()
        self._t_raw = t_s
        self._i_raw = current_A
        self._i_tick = 0.0  # unknown current during the gap: assume the pack rested
        self._start_segment(t_s)
        return self._tick(t_s, current_A, v, ok, dt)

    def _tick(self, t: float, i: float, v: FloatArray, ok: BoolArray, dt: float) -> Estimates:
        tun = self.tuning
        self.counters["ticks"] += 1
        ip = self._i_tick
        if 0 < dt <= tun.gap_s:
            self._dt_nom = dt if self._dt_nom == 0.0 else self._dt_nom + 0.05 * (dt - self._dt_nom)
        if dt > 0:
            a1 = np.exp(-dt / self.tau1)
            a2 = np.exp(-dt / self.tau2)
            self.x1 = a1 * self.x1 + (1.0 - a1) * ip
            self.x2 = a2 * self.x2 + (1.0 - a2) * ip
            kap = self._kappa * (self._eta if ip < 0 else 1.0)
            self.h = hysteresis_step(self.h, ip, dt, kap)
        zc = np.minimum(np.maximum(self.z, self.ocv.soc_min), self.ocv.soc_max)
        ocv_v = self.ocv.ocv(zc)
        mtab = self.ocv.hysteresis_M(zc)
        hm = self.h * mtab
        v_safe = np.where(ok, v, ocv_v)
        # Excitation: running variance of the current (time constant excitation_window_s).
        g = 1.0 - np.exp(-max(dt, 0.0) / tun.excitation_window_s) if dt > 0 else 0.0
        self._i_mean += g * (i - self._i_mean)
        self._i_var += g * ((i - self._i_mean) ** 2 - self._i_var)
        quiet = abs(i) < tun.rest_current_C * self.cell.capacity_Ah and abs(i - ip) < (
            tun.rest_current_C * self.cell.capacity_Ah
        )
        # Forgetting is per second of *data*: a gap carries none, so it forgets no more than a tick.
        dt_f = min(dt, self._tick_period()) if dt > 0 else tun.id_period_s
        self._lam_exp = 1.0 / dt_f
        lam_lo = tun.lambda_min**dt_f
        lam_hi = tun.lambda_max**dt_f
        self._clamped[:] = False
        if self.variant == "hy-affrls-lpso":
            v_model = self._tick_fusion(t, i, v_safe, ok, ocv_v, hm, lam_lo, lam_hi, quiet, dt)
        else:
            v_model = self._tick_arx(i, v_safe, ok, ocv_v, hm, mtab, lam_lo, lam_hi, quiet, dt)
        self._t_tick = t
        self._i_tick = i
        return self._estimates(t, i, v, v_model, mtab)

    def _adapt(
        self, e: FloatArray, lam_lo: float, lam_hi: float, quiet: bool, ok: BoolArray, dt: float
    ) -> FloatArray:
        """Innovation scale, forgetting factor (Eq. 21) and spike clipping; returns clipped e."""
        tun = self.tuning
        sig = np.maximum(self.sig_e, tun.e_floor_V)
        lim = tun.innovation_clip_sigmas * sig
        e_c = np.minimum(np.maximum(e, -lim), lim)
        g = 1.0 - np.exp(-max(dt, 1e-9) / tun.innovation_scale_s)
        self.sig_e = np.where(ok, np.sqrt(self.sig_e**2 + g * (e_c**2 - self.sig_e**2)), self.sig_e)
        e_base = np.maximum(tun.e_base_sigmas * sig, tun.e_floor_V)
        lam = adaptive_lambda(e_c, e_base, lam_lo, lam_hi, tun.forgetting_base)
        self.lam = np.where(quiet, 1.0, lam)
        return np.asarray(e_c)

    # -- fusion ----------------------------------------------------------------
    def _tick_fusion(
        self,
        t: float,
        i: float,
        v: FloatArray,
        ok: BoolArray,
        ocv_v: FloatArray,
        hm: FloatArray,
        lam_lo: float,
        lam_hi: float,
        quiet: bool,
        dt: float,
    ) -> FloatArray:
        tun = self.tuning
        use_h = 1.0 if tun.identify_hysteresis_scale else 0.0
        phi = self._phi
        phi[:, 0] = -i
        phi[:, 1] = -self.x1
        phi[:, 2] = -self.x2
        phi[:, 3] = hm
        v_model = ocv_v + (phi * (self.theta * self._scale)).sum(axis=1)
        e = v - v_model
        self.arx_err = np.where(ok, e, 0.0)
        e_c = self._adapt(e, lam_lo, lam_hi, quiet, ok, dt)
        # The OCV offset is not tracked per tick (see _fusion_covariance): column zeroed.
        phi_n = phi * (self._scale * np.array([1.0, 1.0, 1.0, use_h, 0.0]))
        theta, self.P = rls_update(self.theta, self.P, phi_n, e_c, self.lam, ok, tun.trace_max)
        self.theta = self._clamp_linear(self._project_linear(theta, self.P))
        self._buf.push(i, v - ocv_v, hm, ok)
        self._run_swarms(t)
        self._publish_linear()
        return np.asarray(v_model, dtype=np.float64)

    @staticmethod
    def _fusion_covariance(P: FloatArray) -> FloatArray:
        """Zero the OCV offset's rows and columns of P: the AFFRLS leaves the offset alone.

        Under a steady mean current the offset is collinear with R2 x2; tracked per tick it
        drifts along that unobservable direction. It is refit with each swarm window instead,
        under the prior ``ocv_offset_prior_V``.
        """
        P = P.copy()
        P[..., 4, :] = 0.0
        P[..., :, 4] = 0.0
        return P

    def _project_linear(self, theta_n: FloatArray, P: FloatArray) -> FloatArray:
        """Project an estimate that left the bounds back onto them in the metric of P.

        Clipping one coordinate alone leaves the coordinates correlated with it carrying a step
        that assumed it had moved; the error then grows and the next updates push further the
        wrong way. Moving coordinate j onto its bound by d shifts the others by P[:, j] d / P[j, j]
        (the least-squares estimate conditioned on theta_j at the bound). P is kept, so the
        parameter can leave the bound again when the data say so. Coordinates are taken one at a
        time, in a fixed order; the final clip removes what is left.
        """
        th = theta_n * self._scale
        viol = (th < self._lin_lo) | (th > self._lin_hi)
        if not viol.any():
            return theta_n
        theta_n = theta_n.copy()
        for j in range(5):  # fixed order, whatever the other cells do (bank == single)
            th_j = theta_n[:, j] * self._scale[j]
            d_n = (np.minimum(np.maximum(th_j, self._lin_lo[j]), self._lin_hi[j]) - th_j) / (
                self._scale[j]
            )
            pjj = P[:, j, j]
            gain = np.where(
                pjj[:, None] > 0, P[:, :, j] / np.where(pjj > 0, pjj, 1.0)[:, None], 0.0
            )
            theta_n += gain * d_n[:, None]
        return theta_n

    def _clamp_linear(self, theta_n: FloatArray) -> FloatArray:
        th = theta_n * self._scale
        cl = np.minimum(np.maximum(th, self._lin_lo), self._lin_hi)
        if not self.tuning.identify_hysteresis_scale:
            cl[:, 3] = 1.0
        if not self.tuning.identify_ocv_offset:
            cl[:, 4] = 0.0
        moved = np.any(np.abs(cl - th) > 1e-12 * np.abs(self._scale), axis=1)
        self._clamped |= moved
        self.counters["clamped"] += int(moved.sum())
        return np.asarray(cl / self._scale)

    def _publish_linear(self) -> None:
        th = self.theta * self._scale
        self.R0, self.R1, self.R2 = th[:, 0].copy(), th[:, 1].copy(), th[:, 2].copy()
        self.Ms, self.off = th[:, 3].copy(), th[:, 4].copy()

    def _run_swarms(self, t: float) -> None:
        tun = self.tuning
        span = self._buf.count * self._tick_period()
        due = (
            np.flatnonzero((t >= self._next_swarm) & np.array([s is None for s in self._swarms]))
            if t >= self._next_swarm.min()
            else ()
        )
        for cj in due:
            self._next_swarm[cj] += tun.swarm_period_s * max(
                1.0, np.ceil((t - self._next_swarm[cj]) / tun.swarm_period_s)
            )
            if span >= tun.min_window_s and self._excited():
                self._start_swarm(int(cj))
        if self._n_running() == 0:
            return
        for c, cs in enumerate(self._swarms):
            if cs is None:
                continue
            self._swarm_fits(c, cs, tun.fits_per_update)
            if cs.swarm.done:
                self._apply_swarm(c, cs)
                self._swarms[c] = None

    def _tick_period(self) -> float:
        """Nominal time between identification ticks, s."""
        return max(self._dt_nom, self.tuning.id_period_s)

    def _n_running(self) -> int:
        return sum(s is not None for s in self._swarms)

    def _excited(self) -> bool:
        return bool(np.sqrt(self._i_var) >= self.tuning.excitation_C * self.cell.capacity_Ah)

    def _window(self, c: int) -> tuple[Window, FloatArray]:
        buf, tun = self._buf, self.tuning
        dt = self._tick_period()
        idx = buf.order()[-(int(tun.window_s / dt) + 1) :]
        w = Window(
            current_A=buf.current_A[idx].copy(),
            y_V=np.where(buf.valid[c, idx], buf.y_V[c, idx], 0.0),
            hm_V=buf.hm_V[c, idx].copy(),
            dt_s=dt,
            use_hysteresis=tun.identify_hysteresis_scale,
            use_offset=tun.identify_ocv_offset,
        )
        return w, buf.valid[c, idx].astype(np.float64)

    def _start_swarm(self, c: int) -> None:
        tun, b = self.tuning, self.cell.bounds
        rng = np.random.default_rng([tun.seed, int(self.cell_ids[c]), int(self._swarm_count[c])])
        lo = np.log([b.tau1_s.lo, b.tau2_s.lo])
        hi = np.log([b.tau1_s.hi, b.tau2_s.hi])
        first = not self.fused[c]
        seed = np.clip(np.log([[self.tau1[c], self.tau2[c]]]), lo, hi)
        sw = lpso.swarm_init(
            lo, hi, tun.n_particles, tun.n_iter_first if first else tun.n_iter, rng,
            seeds=seed, spread=tun.init_spread_log,
        )  # fmt: skip
        window, weights = self._window(c)
        self._swarms[c] = _CellSwarm(
            swarm=sw, window=window, weights=weights, rng=rng, fitness=np.zeros(tun.n_particles)
        )
        self._swarm_count[c] += 1
        self.counters["swarms"] += 1

    def _offset_prior(self, c: int) -> float:
        """Ridge for the offset in normalised units: (noise std / prior std)^2."""
        sig = max(float(self.sig_e[c]), self.tuning.e_floor_V)
        return float((sig * self._scale[4] / self.tuning.ocv_offset_prior_V) ** 2)

    def _fitness(self, c: int, window: Window, weights: FloatArray, taus: FloatArray) -> FloatArray:
        tun = self.tuning
        t_lo = np.minimum(taus[:, 0], taus[:, 1])
        t_hi = np.maximum(taus[:, 0], taus[:, 1])
        fit = fit_linear(window, t_lo, t_hi, self._scale, weights, self._offset_prior(c))
        th = fit.theta
        viol = (np.maximum(self._lin_lo - th, 0.0) + np.maximum(th - self._lin_hi, 0.0)) / np.abs(
            self._scale
        )
        ratio = t_hi / t_lo
        viol_r = np.maximum(tun.tau_ratio_min / ratio - 1.0, 0.0)
        return np.asarray(fit.rmse_V * (1.0 + 10.0 * (viol.sum(axis=1) + viol_r)))

    def _swarm_fits(self, c: int, cs: _CellSwarm, budget: int) -> None:
        """Evaluate up to ``budget`` particles; when all are evaluated, move the swarm."""
        tun = self.tuning
        n_p = cs.swarm.x.shape[0]
        j0, j1 = cs.done_fits, min(cs.done_fits + budget, n_p)
        cs.fitness[j0:j1] = self._fitness(c, cs.window, cs.weights, np.exp(cs.swarm.x[j0:j1]))
        cs.done_fits = j1
        if j1 < n_p:
            return
        params = lpso.SwarmParams(
            c1=tun.c1, c2=tun.c2, w_max=tun.w_max, w_min=tun.w_min, shape=tun.inertia_shape,
            vmax_frac=tun.velocity_max_frac,
        )  # fmt: skip
        cs.swarm = lpso.swarm_tell(cs.swarm, cs.fitness, cs.rng, params)
        cs.done_fits = 0

    def _apply_swarm(self, c: int, cs: _CellSwarm) -> None:
        """Feed the swarm optimum back: poles, then theta/P/x as the AFFRLS would hold them."""
        tun = self.tuning
        b = self.cell.bounds
        taus = np.clip(  # exp(log(x)) may miss a bound by one ulp
            np.sort(np.exp(cs.swarm.gbest)), [b.tau1_s.lo, b.tau2_s.lo], [b.tau1_s.hi, b.tau2_s.hi]
        )
        if not np.isfinite(cs.swarm.gbest_f):
            return
        window, valid = self._window(c)  # data up to now, not just the snapshot
        n_w = window.current_A.shape[0]
        age = (n_w - 1 - np.arange(n_w)) * window.dt_s
        weights = valid * tun.lambda_max**age
        fit = fit_linear(
            window, taus[:1], taus[1:], self._scale, weights, self._offset_prior(c), with_cov=True
        )
        self.tau1[c], self.tau2[c] = taus
        theta_n = fit.theta[0] / self._scale
        self.theta[c] = self._clamp_linear(theta_n[None, :])[0]
        P = fit.cov[0]
        if not tun.identify_hysteresis_scale:
            P[3, 3] = tun.p0
        if not tun.identify_ocv_offset:
            P[4, 4] = tun.p0
        tr = float(np.trace(P))
        if not np.all(np.isfinite(P)) or tr <= 0:
            P = np.eye(5) * tun.p0
        elif tr > tun.trace_max:
            P = P * (tun.trace_max / tr)
        self.P[c] = self._fusion_covariance(P)
        self.x1[c], self.x2[c] = fit.x_last[0]
        self.fused[c] = True

    # -- ARX variants ------------------------------------------------------------
    def _tick_arx(
        self,
        i: float,
        v: FloatArray,
        ok: BoolArray,
        ocv_v: FloatArray,
        hm: FloatArray,
        mtab: FloatArray,
        lam_lo: float,
        lam_hi: float,
        quiet: bool,
        dt: float,
    ) -> FloatArray:
        tun = self.tuning
        hyst = self.variant == "hy-affrls"
        h_term = hm if hyst else np.zeros(self.n)
        v_model = ocv_v + h_term - self.R0 * i - self.R1 * self.x1 - self.R2 * self.x2
        ue = v - ocv_v - h_term
        if self.T_arx == 0.0 and dt > 0:
            self.T_arx = dt
            self.theta_arx = np.tile(
                params_to_theta(
                    self.R0[0], self.R1[0], self.tau1[0], self.R2[0], self.tau2[0], self.T_arx
                )
                / self._arx_scale,
                (self.n, 1),
            )
        if self._hist_n >= 2 and self.T_arx > 0:
            phi = np.concatenate(
                [self._ue_hist, np.tile([i, self._i_hist[0], self._i_hist[1]], (self.n, 1))],
                axis=1,
            )
            th = self.theta_arx * self._arx_scale
            e = ue - np.einsum("nk,nk->n", phi, th)
            self.arx_err = np.where(ok, e, 0.0)
            e_c = self._adapt(e, lam_lo, lam_hi, quiet, ok, dt)
            self.theta_arx, self.P_arx = rls_update(
                self.theta_arx, self.P_arx, phi * self._arx_scale, e_c, self.lam, ok,
                tun.trace_max,
            )  # fmt: skip
            self._accept_arx(ok)
        else:
            self.arx_err = np.where(ok, v - v_model, 0.0)
        self._ue_hist = np.stack([ue, self._ue_hist[:, 0]], axis=1)
        self._i_hist = np.array([i, self._i_hist[0]])
        self._hist_n += 1
        return v_model

    def _accept_arx(self, ok: BoolArray) -> None:
        p, status = theta_to_params(self.theta_arx * self._arx_scale, self.T_arx)
        good = ok & (status == MapStatus.OK)
        raw = np.stack([p.R0_ohm, p.R1_ohm, p.R2_ohm, p.tau1_s, p.tau2_s])
        lo, hi = self._arx_bounds
        clipped = np.minimum(np.maximum(raw, lo), hi)
        inside = np.all(clipped == raw, axis=0)
        # Physically valid but outside the bounds: clamp and flag; invalid (complex poles,
        # negative R, unstable): hold the last accepted parameters and count the rejection.
        self.counters["arx_rejected"] += int((ok & ~good).sum())
        self._clamped |= good & ~inside
        self.R0 = np.where(good, clipped[0], self.R0)
        self.R1 = np.where(good, clipped[1], self.R1)
        self.R2 = np.where(good, clipped[2], self.R2)
        self.tau1 = np.where(good, clipped[3], self.tau1)
        self.tau2 = np.where(good, clipped[4], self.tau2)
        self.arx_ok |= good

    # -- output ------------------------------------------------------------------
    def _estimates(
        self, t: float, i: float, v: FloatArray, v_model: FloatArray, mtab: FloatArray
    ) -> Estimates:
        converged = self.fused if self.variant == "hy-affrls-lpso" else self.arx_ok
        q = np.full(self.n, int(Quality.CONVERGED), dtype=np.int64)
        if not self._excited():
            q[:] = Quality.POORLY_EXCITED
        q[self._clamped] = Quality.OUT_OF_BOUNDS
        q[~converged] = Quality.CONVERGING
        hyst = self.variant != "non-hy-affrls"
        m_v = (self.Ms if self.variant == "hy-affrls-lpso" else 1.0) * mtab * (1.0 if hyst else 0.0)
        return Estimates(
            t_s=t,
            current_A=i,
            R0_ohm=self.R0.copy(),
            R1_ohm=self.R1.copy(),
            C1_F=self.tau1 / self.R1,
            R2_ohm=self.R2.copy(),
            C2_F=self.tau2 / self.R2,
            tau1_s=self.tau1.copy(),
            tau2_s=self.tau2.copy(),
            M_V=np.asarray(m_v * np.ones(self.n)),
            ocv_offset_V=self.off.copy() if self.variant == "hy-affrls-lpso" else np.zeros(self.n),
            lambda_=self.lam**self._lam_exp,  # reported per second: in [lambda_min, 1]
            h=self.h.copy() if hyst else np.zeros(self.n),
            soc=self.z.copy(),
            v_model_V=np.asarray(v_model),
            v_meas_V=np.asarray(v, dtype=np.float64),
            arx_error_V=self.arx_err.copy(),
            quality=q,
        )

    # ------------------------------------------------------------------ checkpoints
    _ARRAYS = (
        "z", "h", "x1", "x2", "R0", "R1", "R2", "tau1", "tau2", "Ms", "off", "lam", "sig_e",
        "arx_err", "theta", "P", "theta_arx", "P_arx", "_ue_hist", "_i_hist", "arx_ok",
        "_bin_v", "_bin_vn", "_next_swarm", "_swarm_count", "fused",
    )  # fmt: skip
    _SCALARS = (
        "T_arx", "_hist_n", "_t_raw", "_i_raw", "_t_tick", "_i_tick", "_bin_i", "_bin_n",
        "_i_mean", "_i_var", "soc_init_method", "_dt_nom",
    )  # fmt: skip

    def state_dict(self) -> dict[str, Any]:
        """The whole estimator state as plain arrays and numbers (for an atomic checkpoint).

        Running swarms are not saved: after a restore they start again at their next period.
        """
        st: dict[str, Any] = {k: np.array(getattr(self, k)) for k in self._ARRAYS}
        st.update({k: getattr(self, k) for k in self._SCALARS})
        st["counters"] = dict(self.counters)
        b = self._buf
        st["buf"] = {
            "current_A": b.current_A.copy(), "y_V": b.y_V.copy(), "hm_V": b.hm_V.copy(),
            "valid": b.valid.copy(), "head": b.head, "count": b.count,
        }  # fmt: skip
        st["meta"] = {"n_cells": self.n, "variant": self.variant, "cell": self.cell.name}
        return st

    def load_state_dict(self, st: dict[str, Any]) -> None:
        """Restore ``state_dict`` output; raises ValueError when it belongs to another setup."""
        meta = st.get("meta", {})
        if meta.get("n_cells") != self.n or meta.get("variant") != self.variant:
            raise ValueError(
                f"checkpoint is for {meta.get('n_cells')} cells / {meta.get('variant')}, "
                f"not {self.n} / {self.variant}"
            )
        for k in self._ARRAYS:
            cur = getattr(self, k)
            arr = np.asarray(st[k], dtype=np.asarray(cur).dtype)
            if arr.shape != np.shape(cur):
                raise ValueError(
                    f"checkpoint field {k} has shape {arr.shape}, need {np.shape(cur)}"
                )
            setattr(self, k, arr.copy())
        for k in self._SCALARS:
            setattr(self, k, st[k])
        self.counters.update(st.get("counters", {}))
        b = st["buf"]
        if b["y_V"].shape == self._buf.y_V.shape:
            self._buf.current_A[:] = b["current_A"]
            self._buf.y_V[:] = b["y_V"]
            self._buf.hm_V[:] = b["hm_V"]
            self._buf.valid[:] = b["valid"]
            self._buf.head = int(b["head"])
            self._buf.count = int(b["count"])
        self._swarms = [None] * self.n
