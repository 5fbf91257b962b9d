"""The AFFRLS parameter stage on the bilinear ARX model (the paper's non-fusion variants).

``U_E = V - OCV(z) [- M(z) h]`` is regressed on its own two past values and the current's
present and two past values (Eq. 15-17), by recursive least squares with the adaptive
forgetting factor of Eq. 21; theta is mapped back to R0, R1, tau1, R2, tau2 by the corrected
Eq. 22-23 every tick. A map that is physically valid but outside the bounds is clamped and
flagged; an invalid one (complex poles, negative R, unstable) holds the last accepted values.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from bmsid.estimate.affrls import reset_covariance, rls_update
from bmsid.estimate.cellmodel import CellModel
from bmsid.estimate.stage import (
    BoolArray,
    FloatArray,
    Forgetting,
    TickContext,
    adapt_innovation,
    is_quiet,
    per_cell_limit,
)
from bmsid.estimate.statedict import load_arrays
from bmsid.estimate.tuning import EstimatorTuning
from bmsid.model.arx import MapStatus, params_to_theta, theta_to_rows
from bmsid.model.ecm import branches_step

_MAP_OK = int(MapStatus.OK)  # numpy compares an array with an IntEnum member ~5x slower


class ArxRlsStage:
    """AFFRLS on the ARX model of every cell; ``hysteresis`` removes M(z) h from U_E first."""

    name = "params"

    def __init__(self, model: CellModel, tuning: EstimatorTuning, *, hysteresis: bool) -> None:
        self.model = model
        self.tuning = tuning
        self.hysteresis = hysteresis
        self.n = model.n_cells
        self.counters: dict[str, int] = {"arx_rejected": 0, "clamped": 0}
        self._start_values()
        self.T_arx = 0.0  # the ARX sample period, s: the first tick step (Eq. 11-15 need one)
        self.i_hist = np.zeros(2)
        self.hist_n = 0
        self.arx_ok = np.zeros(self.n, dtype=bool)
        self.clamped = np.zeros(self.n, dtype=bool)
        self.lam_exp = 1.0  # 1 / (forgetting time step): reports lambda per second
        self.v_model = np.zeros(self.n)
        self._m_table = np.zeros(self.n)
        rows = [0, 1, 2, 4, 3]  # model columns R0, R1, R2, tau1, tau2 as theta_to_rows' rows
        self._bounds = (model.lo[:, rows].T, model.hi[:, rows].T)
        self._rest_limit_A = per_cell_limit(tuning.rest_current_C, model)

    def _start_values(self) -> None:
        """Every per-cell array at its start value (start values clamped to the bounds)."""
        m, n = self.model, self.n
        self.x1 = np.zeros(n)
        self.x2 = np.zeros(n)
        self.R0 = m.start("R0_ohm")
        self.R1 = m.start("R1_ohm")
        self.R2 = m.start("R2_ohm")
        self.tau1 = np.clip(m.start("tau1_s"), *m.bound("tau1_s"))
        self.tau2 = np.clip(m.start("tau2_s"), *m.bound("tau2_s"))
        self.lam = np.ones(n)
        self.sig_e = np.full(n, self.tuning.e_floor_V)
        self.arx_err = np.zeros(n)
        # theta in units of its start magnitude: [1, 1, R0, R0, R0] (Eq. 17's a1, a2, b0..b2)
        self.arx_scale = np.stack([np.ones(n), np.ones(n), self.R0, self.R0, self.R0], axis=1)
        self.theta_arx = np.zeros((n, 5))
        self.P_arx = reset_covariance(n, 5, self.tuning.p0)
        self.ue_hist = np.zeros((n, 2))

    def _seed_theta(self) -> FloatArray:
        """theta (normalised) that the present circuit parameters give at ``T_arx`` (Eq. 12, 14)."""
        th = params_to_theta(self.R0, self.R1, self.tau1, self.R2, self.tau2, self.T_arx)
        return np.asarray(th / self.arx_scale, dtype=np.float64)

    @property
    def converged(self) -> BoolArray:
        return self.arx_ok

    def step(self, ctx: TickContext) -> None:
        tick, tun = ctx.tick, self.tuning
        if tick.new_segment:
            self.hist_n = 0
        dt, ip, i = tick.dt_s, tick.i_prev_A, tick.current_A
        self.x1, self.x2 = branches_step(self.x1, self.x2, self.tau1, self.tau2, ip, dt)
        forget = Forgetting.for_tick(tick, tun)
        self.lam_exp = forget.per_second_exp
        quiet = is_quiet(tick, self._rest_limit_A)
        self.clamped[:] = False
        self._m_table = ctx.m_table_V
        ok, v, ocv_v = tick.ok, ctx.v_safe_V, ctx.ocv_V
        h_term = ctx.hm_V if self.hysteresis else np.zeros(self.n)
        v_model = ocv_v + h_term - self.R0 * i - self.R1 * self.x1 - self.R2 * self.x2
        ue = v - ocv_v - h_term
        if self.T_arx == 0.0 and dt > 0:
            self.T_arx = dt
            self.theta_arx = self._seed_theta()
        if self.hist_n >= 2 and self.T_arx > 0:
            phi = np.empty((self.n, 5))
            phi[:, :2] = self.ue_hist
            phi[:, 2] = i
            phi[:, 3:] = self.i_hist
            e = ue - np.einsum("nk,nk->n", phi, self.theta_arx * self.arx_scale)
            self.arx_err = np.where(ok, e, 0.0)
            learn = ctx.learn
            e_c, self.sig_e, self.lam = adapt_innovation(
                e, self.sig_e, learn, quiet, dt, forget, tun
            )
            self.theta_arx, self.P_arx = rls_update(
                self.theta_arx, self.P_arx, phi * self.arx_scale, e_c, self.lam, learn,
                tun.trace_max,
            )  # fmt: skip
            self._accept(learn)
        else:
            self.arx_err = np.where(ok, v - v_model, 0.0)
        ue_hist = np.empty((self.n, 2))
        ue_hist[:, 0] = ue
        ue_hist[:, 1] = self.ue_hist[:, 0]
        self.ue_hist = ue_hist
        self.i_hist = np.array([i, self.i_hist[0]])
        self.hist_n += 1
        self.v_model = np.asarray(v_model, dtype=np.float64)

    def _accept(self, ok: BoolArray) -> None:
        raw, status = theta_to_rows(self.theta_arx * self.arx_scale, self.T_arx)
        good = ok & (status == _MAP_OK)
        lo, hi = self._bounds
        clipped = np.minimum(np.maximum(raw, lo), hi)  # rows R0, R1, R2, tau2, tau1
        inside = np.logical_and.reduce(clipped == raw)  # ufunc reduce: no .all() dispatch
        if np.count_nonzero(good) == good.size:  # the usual tick: every row taken
            self.clamped |= ~inside
            self.R0, self.R1, self.R2, self.tau2, self.tau1 = clipped
            self.arx_ok |= good
            return
        self.counters["arx_rejected"] += int(np.count_nonzero(ok & ~good))
        self.clamped |= good & ~inside
        held = np.array([self.R0, self.R1, self.R2, self.tau2, self.tau1])
        self.R0, self.R1, self.R2, self.tau2, self.tau1 = np.where(good, clipped, held)
        self.arx_ok |= good

    def outputs(self) -> dict[str, FloatArray]:
        # Every array here is rebound by each step (np.where), never written in place: the
        # estimates may hold them without a copy.
        zeros = np.zeros(self.n)
        out = {
            "R0_ohm": self.R0,
            "R1_ohm": self.R1,
            "C1_F": self.tau1 / self.R1,
            "R2_ohm": self.R2,
            "C2_F": self.tau2 / self.R2,
            "tau1_s": self.tau1,
            "tau2_s": self.tau2,
            "lambda_": self.lam**self.lam_exp,  # per second: in [lambda_min, 1]
            "M_V": self._m_table if self.hysteresis else zeros,
            "ocv_offset_V": zeros,
            "arx_error_V": self.arx_err,
            "v_model_V": self.v_model,
        }
        if not self.hysteresis:
            out["h"] = zeros  # the model has no hysteresis: report none
        return out

    def reset(self, mask: BoolArray) -> None:
        mask = np.asarray(mask, dtype=bool)
        old = {k: getattr(self, k) for k in self._PER_CELL}
        self._start_values()
        if self.T_arx > 0:
            self.theta_arx = self._seed_theta()
        for k, cur in old.items():
            new = getattr(self, k)
            setattr(self, k, np.where(mask.reshape((-1,) + (1,) * (new.ndim - 1)), new, cur))
        self.arx_ok &= ~mask

    _PER_CELL = (
        "x1", "x2", "R0", "R1", "R2", "tau1", "tau2", "lam", "sig_e", "arx_err", "arx_scale",
        "theta_arx", "P_arx", "ue_hist",
    )  # fmt: skip

    _ARRAYS = (
        "x1", "x2", "R0", "R1", "R2", "tau1", "tau2", "lam", "sig_e", "arx_err", "theta_arx",
        "P_arx", "ue_hist", "i_hist", "arx_ok",
    )  # fmt: skip

    def state_dict(self) -> dict[str, Any]:
        st: dict[str, Any] = {k: np.array(getattr(self, k)) for k in self._ARRAYS}
        st.update(T_arx=self.T_arx, hist_n=self.hist_n)
        return st

    def load_state_dict(self, st: dict[str, Any]) -> None:
        load_arrays(self, st, self._ARRAYS, self.name)
        self.T_arx = float(st["T_arx"])
        self.hist_n = int(st["hist_n"])
