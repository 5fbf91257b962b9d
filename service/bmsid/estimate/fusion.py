"""The AFFRLS-LPSO fusion stage (the paper's hysteresis AFFRLS-LPSO, redesigned; see bank.py).

Every tick, the AFFRLS (Eq. 17-21) tracks the parameters the voltage is linear in, with the
time constants in force: ``v = OCV(z) + phi . theta`` with ``phi = [-i, -x1, -x2, M(z) h, 1]``
and theta = (R0, R1, R2, M scale, OCV offset) in normalised units. Every ``swarm_period_s`` per
cell, an LPSO swarm (Eq. 24-30) searches ln tau1, ln tau2 over the buffered window, each
particle's fitness the window RMSE with the linear parameters solved exactly (variable
projection); a finished swarm sets the poles and re-seeds theta, P and x1, x2 from the weighted
window solution, i.e. what the AFFRLS would hold had it run with those poles.

LPSO owns the poles, where recursive ARX identification is ill-conditioned (it divides by
1 - th1 - th2 ~ 5e-5: the paper's "filter saturation"); AFFRLS owns what is linear.
"""

from __future__ import annotations

import math
from dataclasses import replace
from typing import Any

import numpy as np
import numpy.typing as npt

from bmsid.estimate import lpso, swarm_kernel
from bmsid.estimate.affrls import fusion_covariance, reset_covariance, swarm_covariance
from bmsid.estimate.arrhenius import KELVIN, ArrheniusCarry
from bmsid.estimate.cellmodel import BOUNDED, CellModel
from bmsid.estimate.rls_kernel import FUSION_TICK
from bmsid.estimate.rls_reference import clamp_linear
from bmsid.estimate.stage import (
    BoolArray,
    FloatArray,
    Forgetting,
    TickContext,
    innovation_constants,
    innovation_gain,
    is_excited,
    per_cell_limit,
    unit_branch_states,
)
from bmsid.estimate.statedict import load_arrays
from bmsid.estimate.swarms import RunningSwarms, SwarmSchedule, WindowBuffer
from bmsid.estimate.tuning import EstimatorTuning
from bmsid.estimate.varpro import Window, column_layout, fit_linear, fixed_rmse

#: Linear parameters, in theta's order, and their columns in ``CellModel.lo``/``hi``.
_LINEAR_BOUNDS = ("R0_ohm", "R1_ohm", "R2_ohm", "M_scale", "ocv_offset_V")


class FusionStage:
    """AFFRLS-LPSO over every cell (see the module docstring).

    Args:
        model: per-cell start values, bounds and capacity.
        tuning: estimator constants.
        cell_ids: global index of each cell (seeds its swarm, staggers its schedule).
        n_stagger: the number of cells the swarm schedule is spread over.
    """

    name = "params"

    def __init__(
        self, model: CellModel, tuning: EstimatorTuning, cell_ids: npt.NDArray[np.int64],
        n_stagger: int,
    ) -> None:  # fmt: skip
        self.model, self.tuning = model, tuning
        self.n = n = model.n_cells
        self.cell_ids = cell_ids
        self.counters: dict[str, int] = {"swarms": 0, "clamped": 0, "swarms_rejected": 0}
        cols = [BOUNDED.index(name) for name in _LINEAR_BOUNDS]
        # C-contiguous (a column selection is not): each cell's row goes to a compiled kernel
        self._lin_lo = np.ascontiguousarray(model.lo[:, cols])
        self._lin_hi = np.ascontiguousarray(model.hi[:, cols])
        r0, r1, r2 = model.start("R0_ohm"), model.start("R1_ohm"), model.start("R2_ohm")
        # Normalisation of the linear parameters (R0, R1, R2, M scale, offset).
        self.scale = np.stack([r0, r1, r2, np.ones(n), np.full(n, 0.05)], axis=1)
        self._theta0 = np.stack([r0, r1, r2, np.ones(n), np.zeros(n)], axis=1) / self.scale
        self._abs_scale = np.abs(self.scale)
        self._clamp_tol = 1e-12 * self._abs_scale  # a clamp that moves less is no clamp
        size = int(np.ceil(tuning.window_s / tuning.id_period_s)) + 1
        self.buffer = WindowBuffer(size=size, n_cells=n)
        n_iter_max = max(tuning.n_iter, tuning.n_iter_first)
        self.swarms = RunningSwarms(n, tuning.n_particles, n_iter_max, size)
        self.schedule = SwarmSchedule(
            n, (cell_ids % n_stagger) / n_stagger, tuning.swarm_period_s, tuning.min_window_s,
            self.swarms,
        )  # fmt: skip
        self.fused = np.zeros(n, dtype=bool)
        self.clamped = np.zeros(n, dtype=bool)
        self.arrhenius = ArrheniusCarry(n)
        self.counters |= self.arrhenius.counters
        self.arrhenius.counters = self.counters  # one dict: the bank reports and restores it
        self.lam_exp = 1.0
        self.v_model = np.zeros(n)
        self._no_hysteresis = not bool(np.any(model.ocv.m_V))
        self._fit_scale = tuning.fits_hysteresis_scale
        # The RLS regressor's scale: the OCV offset's column zeroed (see fusion_covariance).
        phi_scale = self.scale * np.array([1.0, 1.0, 1.0, float(self._fit_scale), 0.0])
        # the tick kernel's constants: per cell the scale, the regressor's scale, the bounds
        # and the clamp tolerance (5, n, 5), and the innovation step's tuning
        self._lin = np.stack([self.scale, phi_scale, self._lin_lo, self._lin_hi, self._clamp_tol])
        self._consts = innovation_constants(tuning)
        self._m_table = np.zeros(n)
        self._excited: bool | BoolArray = False
        self._period_s = tuning.id_period_s
        self._rest_A = np.full(n, per_cell_limit(tuning.rest_current_C, model))
        self._excitation_limit_A = per_cell_limit(tuning.excitation_C, model)
        self._step_A = float(np.min(self._excitation_limit_A))  # a current step, A
        self._swarm_params = lpso.SwarmParams(
            c1=tuning.c1, c2=tuning.c2, w_max=tuning.w_max, w_min=tuning.w_min,
            shape=tuning.inertia_shape, vmax_frac=tuning.velocity_max_frac,
        )  # fmt: skip
        # the window fits' constants: the active columns' scales per cell, their indices, the
        # offset's column (as varpro.fit_columns lays them out); and the swarm kernel's
        fit_s, self._fit_idx, self._fit_j_off = column_layout(
            bool(self._fit_scale), tuning.identify_ocv_offset, self.scale
        )
        self._fit_s = np.ascontiguousarray(fit_s)
        self._swarm_consts = swarm_kernel.consts(self._swarm_params, tuning.tau_ratio_min)
        #: run a swarm to its end at its start (``block_run``: the fused loop then runs the ticks
        #: it takes); only without the offset, whose ridge follows sig_e tick by tick
        self.ahead = False
        self._start_values()

    def _start_values(self) -> None:
        m, n = self.model, self.n
        self.x1, self.x2 = np.zeros(n), np.zeros(n)  # empty branches (seed_branches: loaded)
        self.tau1 = np.clip(m.start("tau1_s"), *m.bound("tau1_s"))
        self.tau2 = np.clip(m.start("tau2_s"), *m.bound("tau2_s"))
        self.theta = self._theta0.copy()
        self.P = fusion_covariance(reset_covariance(n, 5, self.tuning.p0))
        self.lam = np.ones(n)
        self.sig_e = np.full(n, self.tuning.e_floor_V)
        self.arx_err = np.zeros(n)
        self._publish_linear()

    @property
    def converged(self) -> BoolArray:
        return self.fused

    # ------------------------------------------------------------------ every tick
    def step(self, ctx: TickContext) -> None:
        tick, tun = ctx.tick, self.tuning
        if tick.new_segment:
            self.buffer.clear()
            self.schedule.new_segment(tick.t_s)
        dt, i = tick.dt_s, tick.current_A
        forget = Forgetting.for_tick(tick, tun)
        self.lam_exp = forget.per_second_exp
        self._period_s = tick.period_s
        self._excited = is_excited(tick, self._excitation_limit_A)  # one bool for a uniform pack
        self._m_table, self._soc = ctx.m_table_V, ctx.soc_clamped
        hm, learn = ctx.hm_V, ctx.learn
        # the AFFRLS and the bounds: one call of the kernel (compiled, or the numpy reference
        # rls_reference.fusion_tick_numpy); x1, x2, theta, P, lambda and sig_e move in place
        out, n_moved = FUSION_TICK.impl(
            self.x1, self.x2, self.tau1, self.tau2, self.theta, self.P, self.sig_e, self.lam,
            self._lin, self._rest_A, ctx.v_safe_V, ctx.ocv_V, hm, tick.ok, learn, self.clamped,
            i, tick.i_prev_A, dt, forget.lam_lo, forget.lam_hi, innovation_gain(dt, tun),
            self._consts, tun.trace_max, self._fit_scale, tun.identify_ocv_offset,
        )  # fmt: skip
        self.arx_err, self.v_model, y = out  # rows of an array new every tick
        if n_moved:
            self.counters["clamped"] += n_moved
        self._carry_temperature(tick.temperature_C)
        self.buffer.push(i, y, hm, learn, 1.0 / (tick.temperature_C + KELVIN), tick.t_s)
        self._run_swarms(tick.t_s)
        self._publish_linear()

    def _carry_temperature(self, temperature_C: float) -> None:
        """R0 follows the temperature, also while learning (``estimate/arrhenius.py``)."""
        if math.isnan(temperature_C):
            return
        sc, lo, hi = self.scale[:, 0], self._lin_lo[:, 0], self._lin_hi[:, 0]
        th0 = self.theta[:, 0] * sc
        r0 = self.arrhenius.step(temperature_C, self.fused, th0)
        if r0 is not None:
            self.theta[:, 0] = np.clip(r0, lo, hi) / sc

    def _clamp_linear(self, theta_n: FloatArray, rows: slice) -> FloatArray:
        """theta_n (normalised) of the cells ``rows`` clipped; flags the moved."""
        sc, lo, hi = self.scale[rows], self._lin_lo[rows], self._lin_hi[rows]
        tol, offset = self._clamp_tol[rows], self.tuning.identify_ocv_offset
        cl, moved = clamp_linear(theta_n, theta_n * sc, sc, lo, hi, tol, self._fit_scale, offset)
        n_moved = int(np.count_nonzero(moved))  # usually 0: flags and count stay as they are
        if n_moved:
            self.clamped[rows] |= moved
            self.counters["clamped"] += n_moved
        return cl

    def _publish_linear(self) -> None:
        # one copy, transposed: each field is a row of it (contiguous, fresh every tick)
        self.R0, self.R1, self.R2, self.Ms, self.off = (self.theta * self.scale).T.copy()

    # ------------------------------------------------------------------ swarms
    def _run_swarms(self, t: float) -> None:
        sched, self._t_s = self.schedule, t
        due = sched.due(t)
        if due:
            for c in due if self._window_has_steps() else ():
                excited = self._excited if isinstance(self._excited, bool) else self._excited[c]
                if excited and sched.has_data(c, t, self.buffer, self._period_s):
                    self._start_swarm(c)
        if sched.n_running():
            self._step_swarms()

    def _step_swarms(self) -> None:
        """The running swarms' fits of this tick and their moves (one kernel call); a swarm
        that has run all its iterations is applied and ends (one run ahead: at the tick its
        last move would have come)."""
        rs, tun = self.swarms, self.tuning
        ahead = rs.active & (rs.left > 0)
        done: list[int] = []
        if ahead.any():
            rs.left[ahead] -= 1
            done = np.flatnonzero(ahead & (rs.left == 0)).tolist()
        stepped = rs.active & ~ahead
        if stepped.any():
            prior = np.zeros(self.n)
            if tun.identify_ocv_offset:  # the ridge of the offset, with sig_e as it is now
                for c in np.flatnonzero(stepped).tolist():
                    prior[c] = self._offset_prior(c)
            cells = np.flatnonzero(self._kernel_step(stepped, prior, tun.fits_per_update))
            if cells.size:
                rs.refresh_poles(cells)
                done += cells[rs.iteration[cells] >= rs.n_iter[cells]].tolist()
        for c in sorted(done):
            self._apply_swarm(c)
            rs.active[c] = False

    def _kernel_step(self, active: BoolArray, prior: FloatArray, budget: int) -> BoolArray:
        """One call of the swarm kernel over the ``active`` cells; the cells that moved."""
        rs, tun = self.swarms, self.tuning
        return swarm_kernel.STEP.impl(
            active, rs.x, rs.v, rs.pbest, rs.pbest_f, rs.gbest, rs.gbest_f, rs.iteration,
            rs.lo, rs.hi, rs.fitness, rs.done_fits, rs.rand, rs.inertia, rs.a1, rs.a2, rs.t_lo,
            rs.t_hi, rs.win, rs.win_len, self._fit_s, self._fit_idx, bool(self._fit_scale),
            tun.identify_ocv_offset, prior, self._fit_j_off, self._lin_lo, self._lin_hi,
            self._abs_scale, budget, self._swarm_consts,
        )  # fmt: skip

    def _run_ahead(self, c: int) -> None:
        """Cell ``c``'s new swarm to its end now: every particle of an iteration in one call,
        each the same fit as tick by tick (no ridge: the same prior 0); ``left`` counts the
        ticks its fits would have taken."""
        rs, tun, only = self.swarms, self.tuning, np.zeros(self.n, dtype=bool)
        only[c] = True
        cell = np.array([c])
        while rs.iteration[c] < rs.n_iter[c]:
            self._kernel_step(only, np.zeros(self.n), tun.n_particles)
            rs.refresh_poles(cell)
        rs.left[c] = rs.n_iter[c] * -(-tun.n_particles // tun.fits_per_update)

    def _window_has_steps(self) -> bool:
        """The window holds ``swarm_min_steps`` current steps: one (a charge starting) ties the
        taus to the hysteresis swing and OCV slope after it, a rest to nothing (variances ~1e9)."""
        t = self.tuning
        return self.buffer.n_steps(t.window_s, self._period_s, self._step_A) >= t.swarm_min_steps

    def _window(self, c: int) -> tuple[Window, FloatArray]:
        tun = self.tuning
        w, valid = self.buffer.window(
            c, self._period_s, tun.window_s, self._fit_scale, tun.identify_ocv_offset
        )
        if not self._fit_scale:  # h M(z) known (scale 1): part of the OCV side
            w = replace(w, y_V=w.y_V - w.hm_V * (valid > 0))
        return w, valid

    def _tau_box(self, c: int) -> tuple[FloatArray, FloatArray]:
        """(lo, hi) of (tau1, tau2) of cell ``c``, s."""
        (lo1, hi1), (lo2, hi2) = self.model.bound("tau1_s"), self.model.bound("tau2_s")
        return np.array([lo1[c], lo2[c]]), np.array([hi1[c], hi2[c]])

    def _start_swarm(self, c: int) -> None:
        tun, sched = self.tuning, self.schedule
        rng = np.random.default_rng([tun.seed, int(self.cell_ids[c]), int(sched.swarm_count[c])])
        lo, hi = (np.log(b) for b in self._tau_box(c))
        first = not self.fused[c]
        seed = np.clip(np.log([[self.tau1[c], self.tau2[c]]]), lo, hi)
        sw = lpso.swarm_init(
            lo, hi, tun.n_particles, tun.n_iter_first if first else tun.n_iter, rng,
            seeds=seed, spread=tun.init_spread_log,
        )  # fmt: skip
        window, weights = self._window(c)
        self.swarms.start(c, sw, rng, self._swarm_params, window, weights)
        if self.ahead and not tun.identify_ocv_offset:
            self._run_ahead(c)
        sched.swarm_count[c] += 1
        self.counters["swarms"] += 1

    def _offset_prior(self, c: int) -> float:
        """Ridge for the offset in normalised units: (noise std / prior std)^2."""
        sig = max(float(self.sig_e[c]), self.tuning.e_floor_V)
        return float((sig * self.scale[c, 4] / self.tuning.ocv_offset_prior_V) ** 2)

    def _apply_swarm(self, c: int) -> None:
        """Feed the swarm optimum back: poles, then theta/P/x as the AFFRLS would hold them."""
        tun = self.tuning
        # exp(log) may miss the box
        taus = np.clip(np.sort(np.exp(self.swarms.gbest[c])), *self._tau_box(c))
        if not np.isfinite(self.swarms.gbest_f[c]):
            return
        # judged on the data up to now: a swarm started as a drive ended can end on a rest
        if not self._window_has_steps():
            self.counters["swarms_rejected"] += 1
            return
        window, valid = self._window(c)
        n_w = window.current_A.shape[0]
        age = (n_w - 1 - np.arange(n_w)) * window.dt_s
        weights = valid * tun.lambda_max**age
        sc = self.scale[c]
        fit = fit_linear(
            window, taus[:1], taus[1:], sc, weights, self._offset_prior(c), with_cov=True
        )
        # A result far worse on the window (as applied, clipped) than what is in force: kept out.
        if self.fused[c]:
            cand = np.clip(fit.theta[0], self._lin_lo[c], self._lin_hi[c])
            new_rmse = fixed_rmse(window, float(taus[0]), float(taus[1]), cand, weights)
            now = self.theta[c] * sc
            old_rmse = fixed_rmse(window, float(self.tau1[c]), float(self.tau2[c]), now, weights)
            if not new_rmse <= tun.swarm_reject_ratio * old_rmse:
                self.counters["swarms_rejected"] += 1
                return
        self.tau1[c], self.tau2[c] = taus
        th = fit.theta[0].copy()
        inv_t = self.buffer.inv_temperature(self._period_s, tun.window_s, self._t_s)
        th[0] *= self.arrhenius.window_factor(c, inv_t, window.current_A, weights)
        # Columns the fit does not estimate come back 0: held, not clamped (the M scale's 0 -> 1
        # flagged every swarm's cell out_of_bounds for a tick: quality and health flickered)
        if not self._fit_scale:
            th[3] = 1.0
        if not tun.identify_ocv_offset:
            th[4] = 0.0
        if math.isfinite(inv_t[-1]) and self._lin_lo[c, 0] < th[0] < self._lin_hi[c, 0]:
            self.arrhenius.learn_fit(c, float(th[0]), float(self._soc[c]))  # (not on a bound)
        self.theta[c] = self._clamp_linear((th / sc)[None, :], rows=slice(c, c + 1))[0]
        restart, keep_r0 = self._no_hysteresis or tun.swarm_rls_restart, not self._no_hysteresis
        P = swarm_covariance(fit.cov[0], tun, self._fit_scale, restart=restart, keep_r0=keep_r0)
        self.P[c] = fusion_covariance(P)
        # The fit's x = x_unit - (c / R) a^k: with R1 or R2 in (0, lower bound) the clipped R
        # multiplies c / R (CALCE US06 45 C, 60 s observer updates: 284 mV), so R x is kept.
        r_fit, r_lo = fit.theta[0, 1:3], self._lin_lo[c, 1:3]
        amplified = (r_fit > 0) & (r_fit < r_lo)
        self.x1[c], self.x2[c] = np.where(amplified, fit.x_last[0] * r_fit / r_lo, fit.x_last[0])
        self.fused[c] = True

    # ------------------------------------------------------------------ protocol
    def outputs(self) -> dict[str, FloatArray]:
        return {
            # R*, Ms, off are fresh each tick (_publish_linear), arx_err and v_model rebound;
            # the taus are written in place by a finished swarm: copied.
            "R0_ohm": self.R0,
            "R1_ohm": self.R1,
            "C1_F": self.tau1 / self.R1,
            "R2_ohm": self.R2,
            "C2_F": self.tau2 / self.R2,
            "tau1_s": self.tau1.copy(),
            "tau2_s": self.tau2.copy(),
            "lambda_": self.lam**self.lam_exp,  # per second: in [lambda_min, 1]
            "M_V": np.asarray(self.Ms * self._m_table * 1.0),
            "ocv_offset_V": self.off,
            "arx_error_V": self.arx_err,
            "v_model_V": self.v_model,
        }

    _PER_CELL = ("x1", "x2", "tau1", "tau2", "theta", "P", "lam", "sig_e", "arx_err")

    def seed_branches(self, branch_V: FloatArray) -> bool:  # the start R1, R2 hold branch_V
        self.x1, self.x2 = unit_branch_states(branch_V, self.R1, self.R2)
        return True

    def reset(self, mask: BoolArray) -> None:
        """The masked cells restart from their start values; their running swarm ends."""
        mask = np.asarray(mask, dtype=bool)
        old = {k: getattr(self, k) for k in self._PER_CELL}
        self._start_values()
        for k, cur in old.items():
            new = getattr(self, k)
            setattr(self, k, np.where(mask.reshape((-1,) + (1,) * (new.ndim - 1)), new, cur))
        self.fused &= ~mask
        self.arrhenius.reset(mask)
        self.schedule.reset(mask)
        self._publish_linear()

    def state_dict(self) -> dict[str, Any]:
        st: dict[str, Any] = {k: np.array(getattr(self, k)) for k in self._PER_CELL}
        st["fused"] = self.fused.copy()
        st["schedule"] = self.schedule.state_dict()
        st["arrhenius"] = self.arrhenius.state_dict()
        st["buffer"] = self.buffer.state_dict()
        return st

    def load_state_dict(self, st: dict[str, Any]) -> None:
        load_arrays(self, st, (*self._PER_CELL, "fused"), self.name)
        self.schedule.load_state_dict(st["schedule"])
        if "arrhenius" in st:  # checkpoints from before it start it fresh
            self.arrhenius.load_state_dict(st["arrhenius"])
        self.buffer.load_state_dict(st["buffer"])
        self._publish_linear()
