"""The SOC observer: SOC of every cell and the pack's current-sensor offset corrected from the
measured voltages through the identified model, capacity from rest anchors.

An extended Kalman filter over ``x = [z_1 .. z_n, b]`` (SOC of each cell, fraction; the offset of
the one current sensor the cells share, A), following Plett's bias-state EKF (Plett, "Battery
Management Systems Vol. II", ch. 3-4):

* prediction (Eq. 2 with the offset removed): ``z_c+ = z_c - eta dt (i_meas - b) / Q_c``, so
  ``dz_c/db = eta dt / Q_c``; SOC random-walks with the current gain error and what the model
  cannot know (``soc_walk_per_sqrt_h``), the offset with sensor drift;
* measurement (Eq. 9): ``v_c = OCV(z_c) + M h - R0 (i - b) - R1 x1 - R2 x2``; the innovation is
  the parameter stage's a-priori model error, ``H = [dOCV/dz, R0 + R1 + R2]``;
* with ``learn_hysteresis``, ``x`` also holds a correction d_k of the half-gap M at each knot
  of a SOC grid, one for the pack (``M(z) = M_table(z) + sum_k w_k(z) d_k``,
  ``hysteresis_map.py``; ``dv_c/dd_k = s h_c w_k(z_c)`` with s the parameter stage's scale):
  M per SOC region from the data, the table its prior; the cells that do not teach it take it
  as consider states (in S and P, gain 0: ``hysteresis_map.map_rows``);
* the error of h, one for the pack (``hysteresis_error.py``); h moves at rest with the pack's
  draw only; what a rest is and what its reading says of the offset: ``rest_anchor.py``;

Dual estimation, kept apart by time scale and by gates: the parameters learn every tick but only
while the SOC uncertainty is worth less than ``learn_ocv_sigma_V`` of OCV (an unremoved SOC error
would be learnt as R2); the observer updates every ``update_period_s`` with a model error of
``v_sigma_V``, so it corrects drifts over minutes to hours, not the dynamics the parameters
describe. Under load the offset is confounded with the parameters' errors (young start values pulled
it the wrong way): there it is a consider state (Schmidt-Kalman: in P, not updated); rests teach it.
A rest long enough for the identified branches to relax is an *anchor*: an update with a rested
cell's small error, counted, which also measures capacity (``capacity.py``). A gap longer than
``restart_gap_s`` (a restart after downtime), or one that resumes under load (data lost mid-drive),
re-anchors from the first voltage after it. The state (SOC, h) is the coulomb-count stage's,
corrected in place; covariance predictions accumulate between updates (a few scalar operations).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from bmsid.estimate import observer_checkpoint, state_jit
from bmsid.estimate import rest_anchor as rest
from bmsid.estimate.capacity import CapacityTracker
from bmsid.estimate.cellmodel import CellModel
from bmsid.estimate.hysteresis_error import fold, target_variance
from bmsid.estimate.hysteresis_error import predict as predict_h
from bmsid.estimate.hysteresis_map import hat_matrix, map_knots, map_rows
from bmsid.estimate.observer_ekf import IndexArray, joint_update
from bmsid.estimate.observer_kernel import lone_cells
from bmsid.estimate.observer_tuning import ObserverTuning
from bmsid.estimate.stage import BoolArray, FloatArray, TickContext
from bmsid.estimate.start_relaxation import StartRelaxation, relaxation_tau_s, widened_variance
from bmsid.estimate.state import CoulombState, _uniform, mean_abs_current, start_soc_sigma
from bmsid.estimate.ticks import Tick
from bmsid.model.ecm import hysteresis_kappa


class ObserverState(CoulombState):
    """SOC, hysteresis and current offset with covariance (see the module docstring).

    Args:
        model: per-cell capacity, efficiency, hysteresis rate, OCV curve, start values.
        soc0: start SOC (fraction) the caller knows; None: from the first voltage.
        knee_slope_factor: see ``EstimatorTuning.knee_slope_factor``.
        tuning: the observer's constants.
        rest_current_C: below this |I| (C-rate) the pack rests.
    """

    def __init__(
        self, model: CellModel, soc0: float | FloatArray | None, knee_slope_factor: float,
        tuning: ObserverTuning, rest_current_C: float,
    ) -> None:  # fmt: skip
        super().__init__(model, soc0, knee_slope_factor)
        n = self.n
        self.tun = tuning
        q_mean_Ah = float(np.mean(model.capacity_Ah))
        self.b = 0.0
        ocv = model.ocv
        self._knots = map_knots(ocv.m_soc) if tuning.learn_hysteresis else np.zeros(0)
        self._m_knots = np.interp(self._knots, ocv.m_soc, ocv.m_V)  # the table, V
        m_sd = tuning.hysteresis_prior_rel * self._m_knots + tuning.hysteresis_prior_floor_V
        self._d_walk = (tuning.hysteresis_walk_rel_per_sqrt_day * m_sd) ** 2 / 86400.0  # V^2/s
        self.d = np.zeros(self._knots.shape[0])  # M correction at each knot, V
        self.P = np.zeros((n + 2 + self.d.shape[0],) * 2)  # z, b, d, the hysteresis error
        self.P[n, n] = (tuning.offset_prior_C * q_mean_Ah) ** 2
        self.P[n + 1 : -1, n + 1 : -1] = np.diag(m_sd**2)
        self._h_floor = tuning.play_error_variance if model.hysteresis_play else 0.0
        self.P[-1, -1] = self._h_target()
        self._b_max = tuning.offset_max_C * q_mean_Ah
        base = self._rest_base_A = rest_current_C * float(np.min(model.capacity_Ah))
        self._rest_limit_A = self._h_rest_A = base  # a rest's current moves no h
        self._noise_sd_A, self._i_prev_A = 0.0, math.nan  # the sensor's (rest.rest_limit)
        self.capacity = CapacityTracker(
            model.capacity_Ah, tuning.capacity_prior_rel, tuning.capacity_min_dsoc,
            tuning.capacity_fade_rel_per_sqrt_day,
        )  # fmt: skip
        self._q_As = np.asarray(model.capacity_As, dtype=np.float64).copy()
        self._eff = np.broadcast_to(np.asarray(model.efficiency, dtype=np.float64), (n,)).copy()
        # Accumulated since the last update: dz/db, SOC and offset process noise, data time.
        self._g, self._qz, self._lh = np.zeros(n), np.zeros(n), np.zeros(n)  # lh: h's log decay
        self._qb = self._since_s = self._rest_s = self._seen_s = 0.0  # seen: since the start
        self._rest_i_A = rest.NO_REST_A  # the rests' reading, A (rest_anchor.py)
        self._i_load_A, self._tau_load_s = np.zeros(n), np.array(model.start("tau2_s"), float)
        self._anchored, self._reanchor, self._widen = np.zeros(n, dtype=bool), False, False
        self._learn_gate, self._start_var = np.ones(n, dtype=bool), np.zeros(n)
        tau_relax_s = relaxation_tau_s(model.start("tau1_s"), model.start("tau2_s"))
        self._relax = StartRelaxation(n, tau_relax_s, tuning.anchor_min_rest_s)
        self.counters |= dict.fromkeys(self._COUNTERS, 0)
        self.counters |= self.capacity.counters  # one dict: the bank reports and restores it
        self.capacity.counters = self.counters

    # ------------------------------------------------------------------ per tick
    def step(self, ctx: TickContext) -> None:
        tick, reading, base = ctx.tick, self._rest_i_A, self._rest_base_A
        self._noise_sd_A = rest.next_noise(
            self._noise_sd_A, tick.current_A, self._i_prev_A, base, tick.dt_s)  # fmt: skip
        self._i_prev_A, limit = tick.current_A, rest.rest_limit(base, self._noise_sd_A)
        self._rest_limit_A = self._h_rest_A = limit
        if rest.at_rest_reading(tick.current_A, reading, limit):
            self.b = rest.offset_within_rest(self.b, reading, base)  # a draw, not noise
        if state_jit.step(self, ctx, observer=True):  # the compiled kernel (jit.select)
            return
        self._h_hold = mean_abs_current([(i - reading, dt) for i, dt in tick.coulomb_steps]) < limit
        tick.remove_offset(self.b)
        self._accumulate(tick)
        super().step(ctx)
        i_abs = abs(tick.current_A)
        a = np.exp(-tick.dt_s / self._tau_load_s)  # |I| the branches still carry: over tau2
        self._i_load_A = np.maximum(i_abs, a * self._i_load_A + (1 - a) * i_abs)
        # Until a SOC is known (learn gate), |I| within 2 std of the offset rests too (a 1 % C
        # offset is the rest limit); not later: on LFP that moved SOC far (A123 3.48 -> 3.67 mV)
        cont = rest.at_rest_reading(tick.current_A + self.b, reading, limit)
        if not np.count_nonzero(self._learn_gate):
            limit += 2.0 * math.sqrt(max(float(self.P[self.n, self.n]), 0.0))
        self._after_step(tick, i_abs < limit or cont)

    def _after_step(self, tick: Tick, resting: bool) -> None:
        """The start's first rest watched, the rest timed, a restart after downtime or data lost
        under load (the charge moved in the gap unknown; one that resumes at rest was a rest)."""
        extra_V = self._relax.feed(tick.t_s, tick.v_V, tick.ok, resting)
        if extra_V is not None and np.count_nonzero(extra_V):
            self._widen_start(extra_V)
        if resting:
            self._rest_s += tick.dt_s
            i_meas, lim = tick.current_A + self.b, self._rest_limit_A
            if abs(tick.current_A) < lim or rest.at_rest_reading(i_meas, self._rest_i_A, lim):
                self._rest_i_A = rest.next_rest_reading(self._rest_i_A, i_meas, tick.dt_s)
        elif self._rest_s:
            self._rest_s = 0.0
            self._anchored = np.zeros(self.n, dtype=bool)
        long_gap = tick.dt_s >= self.tun.restart_gap_s
        gap = tick.new_segment and not tick.first and (long_gap or not resting)
        self.counters["gaps_under_load"] += int(gap and not resting)
        if gap or self._widen:  # _widen: a checkpoint from before the observer, SOC unchecked
            self._restart(tick)

    def _h_decayed(self, log_decay: FloatArray) -> None:  # (state.py's hooks)
        self._lh = self._lh + log_decay

    def _rest_draw_A(self) -> float:
        p_bb = float(self.P[self.n, self.n])
        return rest.rest_draw(self._rest_i_A, self.b, p_bb) if self.tun.rest_draw else 0.0

    def _h_target(self) -> float:
        """The hysteresis error's variance once the current moved h (``hysteresis_error``)."""
        return target_variance(self.h, self._h_floor) if self.tun.hysteresis_error else 0.0

    def hysteresis_m(self, zc: FloatArray) -> FloatArray:
        """The table's M (V) at ``zc`` plus the learnt correction, never below 0."""
        m = self.model.ocv.hysteresis_M(zc)
        if not self.d.any():
            return m
        return np.maximum(m + hat_matrix(self._knots, zc) @ self.d, 0.0)

    def _restart(self, tick: Tick) -> None:
        """After downtime the count missed what the pack did: SOC is as uncertain as the first
        voltage makes it (not correlated with the offset), h as a current that moved it leaves
        it; the next update re-anchors, and no capacity is measured across the gap."""
        n, P = self.n, self.P
        self.start_variance(tick, "restart", self.z)
        P[:n, :n] = np.diag(np.diag(P)[:n] + self._start_var)
        P[:n, n:] = P[n:, :n] = 0.0
        P[-1, -1] = max(P[-1, -1], self._h_target())
        self.capacity.forget_anchors()
        self._reanchor, self._widen = True, False

    def _accumulate(self, tick: Tick) -> None:
        """dz/db, process noise and charge throughput of this tick's coulomb steps (Eq. 2)."""
        tun = self.tun
        for i, dt in tick.coulomb_steps:
            eta = self._eff if i < 0 else 1.0
            dz = eta * dt / self._q_As
            self._g = self._g + dz
            self._qz = self._qz + tun.current_gain_sigma**2 * abs(i) * dz
            self.capacity.count(eta * i * dt / 3600.0)
        dt_s = tick.dt_s
        self._qz = self._qz + tun.soc_walk_per_sqrt_h**2 * dt_s / 3600.0
        q_Ah = self.capacity.q_Ah
        q_mean_Ah = float(q_Ah.sum() / q_Ah.size)  # np.mean's sum and division, a third the cost
        self._qb += (tun.offset_walk_C_per_sqrt_day * q_mean_Ah) ** 2 * dt_s / 86400.0
        self._since_s += dt_s
        self._seen_s += dt_s

    @property
    def learn_gate(self) -> BoolArray:
        """Cells whose SOC is certain enough for their parameters to learn (the bank applies
        it to converged cells: start values learn from any SOC, they are worse)."""
        return self._learn_gate

    # ------------------------------------------------------------------ correction
    def correct(
        self, ctx: TickContext, params: dict[str, FloatArray], converged: BoolArray
    ) -> None:
        """The measurement update, when one is due (period, anchor or restart), from the
        parameter stage's a-priori model voltage and parameters of this tick. Cells whose
        parameters have not converged once update only at anchors and restarts (their model
        error is the start values', not SOC's) for ``unconverged_wait_s`` of data."""
        tun, n = self.tun, self.n
        converged = converged | (self._seen_s >= tun.unconverged_wait_s)
        if self._rest_s <= 0.0:  # a rest is timed by the tau2 identified under load before it
            self._tau_load_s = params["tau2_s"]
        anchor = rest.anchors_due(self._rest_s, self._anchored, self._tau_load_s, tun)
        any_anchor = anchor is not None and np.count_nonzero(anchor) > 0
        if not (any_anchor or self._reanchor or self._since_s >= tun.update_period_s):
            return
        anchor = np.zeros(n, dtype=bool) if anchor is None else anchor
        if any_anchor and not self._anchored.any() and self._rest_i_A < rest.NO_REST_A:
            self._predict()  # the rest's first anchor: its reading measures the offset now
            dx, self.P = rest.draw_update(self.P, n, self.b, self._rest_i_A, self._rest_base_A)
            self._apply(dx)
            ctx.h = self.h
        if state_jit.update(self, ctx, params, converged, anchor):  # compiled (jit.select)
            return
        self._predict()
        tick, zc = ctx.tick, ctx.soc_clamped
        hz = self.model.ocv.docv_dz(zc)
        hb = params["R0_ohm"] + params["R1_ohm"] + params["R2_ohm"]
        e = tick.v_V - params["v_model_V"]
        jump = anchor | self._reanchor  # SOC may move far: the OCV's secant, not its tangent
        if np.count_nonzero(jump):
            secant, z_ocv = self.model.ocv.secant_slope(zc, ctx.ocv_V + e)
            hz = np.where(jump & np.isfinite(secant), secant, hz)
        if self._reanchor:  # the branches' state after downtime is unknown
            r_rc = abs(tick.current_A) * (params["R1_ohm"] + params["R2_ohm"])
            r = tun.v_sigma_V**2 + r_rc**2
        else:
            r_load = self._i_load_A * tun.r_dc_rel_sigma * hb
            r = tun.v_sigma_V**2 + r_load**2
        if self.d.shape[0]:  # M learnt: its uncertainty is in P, not in the anchor's error
            r_anchor = np.full(n, tun.v_sigma_floor_V**2)
            G, teach = map_rows(
                self._knots, zc, ctx.h, params["M_V"], ctx.m_table_V, self.P, hz, anchor
            )
        else:
            r_anchor = tun.v_sigma_floor_V**2 + (0.25 * ctx.m_table_V) ** 2
            G, teach = np.zeros((n, 0)), np.zeros(n, dtype=bool)
        G = np.column_stack([G, params["M_V"]])  # dv / d dh (hysteresis_error.py)
        r = np.where(anchor, r_anchor, r)
        valid = tick.ok & np.isfinite(e) & np.isfinite(hz) & np.isfinite(hb) & np.isfinite(G[:, -1])
        forced = anchor | self._reanchor
        valid &= converged | forced
        lone = lone_cells(e, tun.v_sigma_floor_V**2, valid, tun.agree_sigmas**2)
        self._update(np.flatnonzero(valid), hz, hb, G, e, r, forced, lone, teach)
        anchored = anchor & valid
        if anchored.any():
            z_var = r / np.maximum(hz**2, 1e-12)
            self.capacity.anchor(tick.t_s, z_ocv, z_var, float(self.P[n, n]), anchored)
            self._use_capacity()
            self._anchored = self._anchored | anchored
            self.counters["anchors"] += int(anchored.sum())
        self.counters["reanchors"] += int(self._reanchor)
        self._reanchor = False
        self._gate_learning()

    def _predict(self) -> None:
        """Apply the accumulated prediction: P <- F P F' + Q with F = I + g e_b' (Eq. 2)."""
        n, g, P = self.n, self._g, self.P
        pb = P[:n, n].copy()
        pbb = P[n, n]
        P[:n, :n] += np.outer(g, pb) + np.outer(pb, g) + pbb * np.outer(g, g)
        P[:n, n] = P[n, :n] = pb + g * pbb
        P[np.arange(n), np.arange(n)] += self._qz
        P[n, n] += self._qb
        k = np.arange(n + 1, P.shape[0] - 1)
        P[k, k] += self._d_walk * self._since_s
        predict_h(P, self._lh, self._h_target())
        self._g, self._qz = np.zeros(n), np.zeros(n)
        self._qb = self._since_s = 0.0

    def _update(
        self, idx: IndexArray, hz: FloatArray, hb: FloatArray, G: FloatArray, e: FloatArray,
        r: FloatArray, forced: BoolArray | bool, lone: BoolArray | None = None,
        teach: BoolArray | None = None,
    ) -> None:  # fmt: skip
        """Joint EKF update of the cells ``idx`` (``observer_ekf.joint_update``); the offset
        is a consider state under load (module docstring)."""
        n = self.n
        step = joint_update(
            self.P, n, idx, hz, hb, G, e, r, np.broadcast_to(forced, (n,)),
            self.tun.gate_sigmas, consider_offset=self._rest_s <= 0.0, lone=lone, teach=teach,
            n_map=self.d.shape[0],
        )  # fmt: skip
        self.counters["observer_gated"] += step.n_gated
        if step.dx is None or step.P is None:
            return
        self.P = step.P
        self._apply(step.dx)
        self.counters["observer_updates"] += 1

    def _apply(self, dx: FloatArray) -> None:
        """The state's correction ``dx``: SOC within [0, 1], the offset within its bound, M >= 0
        at the knots, the hysteresis error folded into h (``hysteresis_error.py``)."""
        n = self.n
        self.z = np.clip(self.z + dx[:n], 0.0, 1.0)
        self.b = float(np.clip(self.b + dx[n], -self._b_max, self._b_max))
        if self.d.shape[0]:
            self.d = np.maximum(self.d + dx[n + 1 : -1], -self._m_knots)  # M >= 0 at the knots
        self.h = fold(self.h, float(dx[-1]))

    def _use_capacity(self) -> None:
        """The coulomb count and the hysteresis rate (Eq. 6) follow the measured capacity."""
        self._q_As = self.capacity.q_Ah * 3600.0
        self._capacity_As = _uniform(self._q_As)
        gamma = _uniform(self.model.gamma)
        self._kappa_discharge = hysteresis_kappa(gamma, self._capacity_As, self._efficiency, 1.0)
        self._kappa_charge = hysteresis_kappa(gamma, self._capacity_As, self._efficiency, -1.0)

    # ------------------------------------------------------------------ start
    def _start(self, tick: Tick, cells: BoolArray) -> BoolArray:
        cells = super()._start(tick, cells)
        if not cells.any():
            return cells
        n, self._seen_s = self.n, 0.0  # a (re)started cell's start values wait an hour too
        # what the count accumulated for a deferred cell before its start is not its own
        self._g, self._qz = np.where(cells, 0.0, self._g), np.where(cells, 0.0, self._qz)
        sigma = np.where(cells, np.sqrt(self._start_var), np.sqrt(np.diag(self.P)[:n]))
        keep = ~cells
        self.P[:n, :n] *= np.outer(keep, keep)  # a restarted cell forgets its correlations
        self.P[:n, n:] *= keep[:, None]
        self.P[n:, :n] *= keep
        self.P[np.arange(n), np.arange(n)] = sigma**2
        if cells.all():  # the start's h (0, or a start fit's): its error's variance
            self.P[-1, :], self.P[:, -1] = 0.0, 0.0
            self.P[-1, -1] = self._h_target()
        if self.soc_init_method == "ocv_at_rest":
            self._relax.begin(tick.t_s, cells)
        self._gate_learning()
        return cells

    def _widen_start(self, extra_V: FloatArray) -> None:
        """The first rest showed a start still relaxing (``start_relaxation.py``): SOC is as
        much less certain as ``extra_V`` (V) of OCV; its learning waits for the observer."""
        ocv, d = self.model.ocv, np.arange(self.n)
        slope = ocv.docv_dz(np.clip(self.z, ocv.soc_min, ocv.soc_max))
        self.P[d, d] = widened_variance(self.P[d, d], extra_V, slope, self.tun.start_soc_sigma_max)
        self.counters["start_relaxations"] += int(np.count_nonzero(extra_V))
        self._gate_learning()

    def _gate_learning(self) -> None:
        """Cells whose SOC uncertainty is worth less than ``learn_ocv_sigma_V`` of OCV."""
        n, ocv = self.n, self.model.ocv
        slope = np.abs(ocv.docv_dz(np.clip(self.z, ocv.soc_min, ocv.soc_max)))
        sd = np.sqrt(np.maximum(np.diag(self.P)[:n], 0.0))
        self._learn_gate = slope * sd <= self.tun.learn_ocv_sigma_V

    def start_variance(self, tick: Tick, method: str, z: FloatArray) -> None:
        """Variance of the start SOC (fraction^2): from the voltage's uncertainty (hysteresis,
        unknown relaxation, IR drop) through the OCV slope, or that of a given value."""
        tun = self.tun
        if method in ("given", "config"):  # config: a value the user fixed, not a measurement
            sigma0 = tun.given_soc_sigma if method == "given" else tun.start_soc_sigma_max
            self._start_var = np.full(self.n, sigma0**2)
            return
        sigma = start_soc_sigma(self.model, z, abs(tick.current_A), tun.start_soc_sigma_max)
        self._start_var = np.maximum(sigma, tun.given_soc_sigma) ** 2

    # ------------------------------------------------------------------ outputs, checkpoints
    def outputs(self) -> dict[str, FloatArray]:
        sd = np.sqrt(np.maximum(self.P.diagonal()[: self.n], 0.0))
        return {"soc": self.z, "h": self.h, "soc_std": sd, "capacity_Ah": self.capacity.q_Ah,
                "capacity_std_Ah": self.capacity.std_Ah,  # never written: shared between ticks
                "current_offset_A": np.full(self.n, self.b)}  # fmt: skip

    _COUNTERS = ("observer_updates", "observer_gated", "anchors", "reanchors", "gaps_under_load",
                 "start_relaxations")  # fmt: skip

    def state_dict(self) -> dict[str, Any]:
        st = super().state_dict()
        st["observer"] = observer_checkpoint.save(self)
        return st

    def load_state_dict(self, st: dict[str, Any]) -> None:
        super().load_state_dict(st)
        observer_checkpoint.load(self, st.get("observer"))
