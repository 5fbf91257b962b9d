"""Capacity of each cell from the charge moved between two SOC anchors (the capacity side of
state of health).

At an anchor (a rest long enough for the branches to relax) the OCV gives SOC independently of
the coulomb count. Two anchors ``a`` and ``b`` with the charge ``dq`` (Ah, coulombic efficiency
applied, current offset removed) moved between them measure ``Q = dq / (z_a - z_b)`` (Eq. 2
solved for Q). Its variance carries both anchors' SOC variance and the offset's uncertainty
integrated over the interval. Measurements are fused by a scalar Kalman filter per cell whose
state random-walks with age, so the estimate follows fade.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import numpy.typing as npt

from bmsid.estimate.statedict import load_arrays

FloatArray = npt.NDArray[np.float64]
BoolArray = npt.NDArray[np.bool_]

#: A measurement this far (relative) from the estimate is rejected as an anchor error.
REJECT_REL = 0.3


class CapacityTracker:
    """Per-cell capacity (Ah) and its variance from anchor pairs.

    Args:
        capacity_Ah: configured capacity per cell (the prior), shape (n,).
        prior_rel: relative std of the prior.
        min_dsoc: anchors closer than this in SOC (fraction) do not measure.
        fade_rel_per_sqrt_day: relative random walk of the capacity per sqrt(day).
    """

    name = "capacity"

    def __init__(
        self,
        capacity_Ah: FloatArray,
        prior_rel: float,
        min_dsoc: float,
        fade_rel_per_sqrt_day: float,
    ) -> None:
        self.n = capacity_Ah.shape[0]
        self.min_dsoc = min_dsoc
        self.fade = fade_rel_per_sqrt_day
        self.q_Ah = np.asarray(capacity_Ah, dtype=np.float64).copy()
        self.var_Ah2 = (prior_rel * self.q_Ah) ** 2
        self.throughput_Ah = np.zeros(self.n)  # running eta-weighted discharge, Ah
        self.anchor_z = np.full(self.n, np.nan)  # SOC of the last anchor (NaN: none yet)
        self.anchor_var = np.zeros(self.n)
        self.anchor_q_Ah = np.zeros(self.n)  # throughput at the last anchor
        self.anchor_t_s = np.zeros(self.n)
        # time of the last fusion, s (fade is added since then); NaN until the first anchor: a
        # sample clock is Unix time on a gateway, and fade since 1970 would void the prior
        self.t_s = math.nan
        self.counters: dict[str, int] = {"capacity_updates": 0, "capacity_rejected": 0}
        self._std_of: FloatArray | None = None  # the var_Ah2 that _std is the root of
        self._std = np.zeros(0)

    @property
    def std_Ah(self) -> FloatArray:
        """sqrt(var_Ah2), Ah: computed again only when var_Ah2 is rebound (an anchor, a
        restore; it is never written in place), the same array every tick in between."""
        var = self.var_Ah2
        if var is not self._std_of:
            self._std_of, self._std = var, np.sqrt(var)
        return self._std

    def count(self, dq_Ah: float | FloatArray) -> None:
        """Add the charge moved this step (Ah, + = discharge, efficiency applied)."""
        self.throughput_Ah = self.throughput_Ah + dq_Ah

    def anchor(
        self, t_s: float, z: FloatArray, z_var: FloatArray, offset_var_A2: float, cells: BoolArray
    ) -> None:
        """An anchor of ``cells`` at ``t_s`` with OCV-derived SOC ``z`` (variance ``z_var``);
        ``offset_var_A2`` is the current offset's variance (A^2) over the interval."""
        if math.isnan(self.t_s):
            self.t_s = t_s  # the prior stands for the capacity at the first anchor
        prev = cells & np.isfinite(self.anchor_z)
        dz = self.anchor_z - z
        use = prev & (np.abs(np.nan_to_num(dz)) >= self.min_dsoc)
        if use.any():
            dq = self.throughput_Ah - self.anchor_q_Ah
            dt_h = (t_s - self.anchor_t_s) / 3600.0
            # dz < min_dsoc is masked by use; huge meas/var (an extreme test input) become inf
            # and fail the isfinite / gain checks below instead of warning
            with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
                meas = dq / dz
                var = meas**2 * (self.anchor_var + z_var) / dz**2 + offset_var_A2 * (dt_h / dz) ** 2
            ok = use & np.isfinite(meas) & (np.abs(meas / self.q_Ah - 1.0) <= REJECT_REL)
            self.counters["capacity_rejected"] += int((use & ~ok).sum())
            if ok.any():
                days = max(t_s - self.t_s, 0.0) / 86400.0
                prior = self.var_Ah2 + (self.fade * self.q_Ah) ** 2 * days
                gain = np.where(ok, prior / (prior + np.where(ok, var, 1.0)), 0.0)
                self.q_Ah = np.where(
                    ok, self.q_Ah + gain * (np.nan_to_num(meas) - self.q_Ah), self.q_Ah
                )
                self.var_Ah2 = np.where(ok, (1.0 - gain) * prior, self.var_Ah2)
                self.t_s = t_s
                self.counters["capacity_updates"] += int(ok.sum())
        self.anchor_z = np.where(cells, z, self.anchor_z)
        self.anchor_var = np.where(cells, z_var, self.anchor_var)
        self.anchor_q_Ah = np.where(cells, self.throughput_Ah, self.anchor_q_Ah)
        self.anchor_t_s = np.where(cells, t_s, self.anchor_t_s)

    def forget_anchors(self) -> None:
        """Drop the last anchors: the charge moved over a gap in the data is unknown."""
        self.anchor_z = np.full(self.n, np.nan)

    _ARRAYS = ("q_Ah", "var_Ah2", "throughput_Ah", "anchor_z", "anchor_var", "anchor_q_Ah",
               "anchor_t_s")  # fmt: skip

    def state_dict(self) -> dict[str, Any]:
        return {**{k: getattr(self, k).copy() for k in self._ARRAYS}, "t_s": self.t_s}

    def load_state_dict(self, st: dict[str, Any]) -> None:
        load_arrays(self, st, self._ARRAYS, self.name)
        t_s = float(st["t_s"])
        # 0.0 was "no fusion yet" before NaN was (checkpoints older than the fix of the prior's
        # fade on Unix-time clocks): read as NaN, or its first fusion voids the prior
        self.t_s = math.nan if t_s == 0.0 else t_s
