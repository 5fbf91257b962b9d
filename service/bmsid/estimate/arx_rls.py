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

from bmsid.estimate.affrls import reset_covariance
from bmsid.estimate.cellmodel import CellModel
from bmsid.estimate.rls_kernel import ARX_TICK
from bmsid.estimate.stage import (
    BoolArray,
    FloatArray,
    Forgetting,
    TickContext,
    innovation_constants,
    innovation_gain,
    per_cell_limit,
)
from bmsid.estimate.statedict import load_arrays
from bmsid.estimate.tuning import EstimatorTuning
from bmsid.model.arx import params_to_theta


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
        # the kernel's constant arguments: contiguous float arrays, one tuple
        self._bounds = np.ascontiguousarray(np.stack([model.lo[:, rows].T, model.hi[:, rows].T]))
        self._rest_A = np.full(self.n, per_cell_limit(tuning.rest_current_C, model))
        self._consts = innovation_constants(tuning)

    def _start_values(self) -> None:
        """Every per-cell array at its start value (start values clamped to the bounds)."""
        m, n = self.model, self.n
        self.x1 = np.zeros(n)
        self.x2 = np.zeros(n)
        # contiguous (a column of the model's table is not): what the compiled kernel was built for
        self.R0 = np.ascontiguousarray(m.start("R0_ohm"))
        self.R1 = np.ascontiguousarray(m.start("R1_ohm"))
        self.R2 = np.ascontiguousarray(m.start("R2_ohm"))
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
        """One tick: a single call of ``rls_kernel.ARX_TICK`` (compiled or its numpy reference,
        ``rls_reference.arx_tick_numpy``); it updates the branch states, lambda, the innovation
        RMS, theta, P and the histories in place."""
        tick, tun = ctx.tick, self.tuning
        if tick.new_segment:
            self.hist_n = 0
        dt = tick.dt_s
        forget = Forgetting.for_tick(tick, tun)
        self.lam_exp = forget.per_second_exp
        self._m_table = ctx.m_table_V
        if self.T_arx == 0.0 and dt > 0:
            self.T_arx = dt
            self.theta_arx = self._seed_theta()
        out, rejected = ARX_TICK.impl(
            self.x1, self.x2, self.tau1, self.tau2, self.R0, self.R1, self.R2, self.lam,
            self.sig_e, self.theta_arx, self.P_arx, self.ue_hist, self.arx_scale, self.i_hist,
            self._bounds, self._rest_A, ctx.v_safe_V, ctx.ocv_V, ctx.hm_V, tick.ok, ctx.learn,
            self.clamped, self.arx_ok, tick.current_A, tick.i_prev_A, dt, self.T_arx,
            forget.lam_lo, forget.lam_hi, innovation_gain(dt, tun), self._consts,
            tun.trace_max, self.hysteresis, self.hist_n >= 2 and self.T_arx > 0,
        )  # fmt: skip
        # published as they are: rows of an array new every tick
        self.R0, self.R1, self.R2, self.tau1, self.tau2, self.arx_err, self.v_model = out
        if rejected:
            self.counters["arx_rejected"] += rejected
        self.hist_n += 1

    def outputs(self) -> dict[str, FloatArray]:
        # Every array here is rebound by each step (rows of the tick kernel's result), never
        # written in place: the estimates may hold them without a copy.
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

    def seed_branches(self, branch_V: FloatArray) -> bool:
        """Kept empty: the ARX's first updates move R1 and R2 far (CALCE US06 25 C: R1 36.7
        -> 0.9 mOhm in two minutes, on its bound), and a seeded unit-gain state moves its
        branch's voltage with them (that record, ``non-hy-affrls``: 3.75 -> 8.74 mV seeded)."""
        return False

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
