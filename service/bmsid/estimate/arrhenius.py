"""Temperature: R0 carried along an Arrhenius law (pure numpy, per cell).

R0 is identified from current changes. Under a constant current (a charge, a cruise) there are
none: R0 I is a constant offset, nothing in the voltage tells R0 from an OCV error, and the
fusion does not learn (``POORLY_EXCITED``). The pack's temperature still moves and R0 with it (a
7 degC cooling over an evening charge raises an NMC cell's R0 by ~30 %). When the pack reports a
temperature, R0 follows it there:

    R(T) = R(T_ref) exp(B (1 / T - 1 / T_ref)),   T in kelvin, B = Ea / R_gas

applied tick by tick (R x exp(B (1/T - 1/T_prev))): the factors telescope, so from the last
identified values R follows the law exactly, a temperature that comes back brings R back, and
a constant temperature changes nothing (a swarm's result is kept). The law applies while R0 is
learnt too: to the RLS it is the prediction step of a parameter with a known drift, so the
estimate does not lag a moving temperature by the forgetting factor's memory, and the data
correct only what the law gets wrong. (Carried only between drives before: on the 3-day
``temp-ea50`` record of ``bench/multiday.py``, R0 median error under load on days 2/3 4.8/4.9
-> 1.3/1.4 %, 95th percentile 7.3/7.7 -> 2.5/2.7 %; ``temp-ageing`` 2.1/2.4 -> 0.9/1.2 %.)

B is the cell's activation temperature, identified from its own learnt (ln R0, 1 / T) pairs by a
scalar Kalman filter on the differences of consecutive pairs (one per ``PAIR_S`` of learning,
used when the temperature moved at least ``MIN_DT_K`` between them), starting from the prior
``B_PRIOR_K`` (30 kJ/mol: ohmic and charge-transfer resistances of Li-ion cells near room
temperature, 15-60 kJ/mol in the literature) with std ``B_PRIOR_STD_K``. A slow daily swing
moves the temperature a fraction of a kelvin between pairs, so there B stays near its prior
(keeping a pair's reference until the temperature moved 1 K, weighted by the time between, took
B from 3,600 to 5,600 K on ``temp-ea50``, truth 6,000, but R0 lags the temperature by the RLS's
memory and the learnt pairs carry it: measured before that prediction, R0 came out worse,
6.4/6.8 % there and 3.7/4.4 % on ``temp-ageing``). Without a temperature (NaN) nothing changes,
and a constant one changes nothing either: records without a varying temperature give what they
gave before. Only R0 is carried: carrying R1 too (the multi-day truth scales both) was measured
worse for R0+R1+R2 (3-day `all` scenario, day 2: 15.6 % against 4.3 %), the estimator's R1 being
confounded with the slow branch under a constant current.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import numpy.typing as npt

from bmsid.estimate.statedict import load_arrays

FloatArray = npt.NDArray[np.float64]
BoolArray = npt.NDArray[np.bool_]

KELVIN = 273.15
#: Prior activation temperature Ea / R_gas, K (30 kJ/mol / 8.314 J/(mol K)).
B_PRIOR_K = 30_000.0 / 8.314
#: Its std, K: Ea from 15 to 60 kJ/mol is within 2 sigma.
B_PRIOR_STD_K = 1800.0
#: One (ln R0, 1/T) pair per this much learning, s: consecutive ticks carry the same estimate.
PAIR_S = 300.0
#: Pairs closer than this in temperature say nothing about B, K.
MIN_DT_K = 1.0
#: Relative std of one learnt R0 (its estimate's noise between two pairs).
LN_R_STD = 0.01


class ArrheniusCarry:
    """Per-cell activation temperature B and the last tick's temperature (module docstring)."""

    name = "arrhenius"
    _ARRAYS = ("b_K", "b_var", "t_prev_K", "pair_ln_r0", "pair_inv_t", "pair_s")

    def __init__(self, n_cells: int) -> None:
        self.n = n_cells
        self.b_K = np.full(n_cells, B_PRIOR_K)
        self.b_var = np.full(n_cells, B_PRIOR_STD_K**2)
        self.t_prev_K = np.full(n_cells, np.nan)
        self.pair_ln_r0 = np.full(n_cells, np.nan)
        self.pair_inv_t = np.full(n_cells, np.nan)
        self.pair_s = np.zeros(n_cells)
        self.counters: dict[str, int] = {"arrhenius_pairs": 0, "arrhenius_carried": 0}

    def step(
        self,
        temperature_C: float,
        dt_s: float,
        learnt: BoolArray,
        carry: BoolArray,
        r0_ohm: FloatArray,
    ) -> FloatArray | None:
        """One tick. ``learnt``: cells whose R0 (ohm) was identified this tick (it feeds B);
        ``carry``: cells whose R0 moves by the law's factor from the previous tick's temperature to
        this one's (every identified cell: a learning one takes it as its prediction). Per-tick
        factors telescope, so a temperature that comes back brings R0 back exactly, and a constant
        one changes nothing. Returns the carried R0, or None when nothing is carried."""
        if not math.isfinite(temperature_C):
            return None
        t_k = temperature_C + KELVIN
        inv_t = 1.0 / t_k
        ok = learnt & (r0_ohm > 0)
        if ok.any():
            self._learn_b(ok, inv_t, r0_ohm, dt_s)
        prev = self.t_prev_K
        self.t_prev_K = np.full(self.n, t_k)
        go = carry & np.isfinite(prev) & (prev != t_k)
        if not go.any():
            return None
        factor = np.exp(self.b_K * (inv_t - 1.0 / np.where(go, prev, t_k)))
        self.counters["arrhenius_carried"] += int(go.sum())
        return np.asarray(np.where(go, r0_ohm * factor, r0_ohm), dtype=np.float64)

    def _learn_b(self, ok: BoolArray, inv_t: float, r0_ohm: FloatArray, dt_s: float) -> None:
        """Every ``PAIR_S`` of learning, a scalar Kalman update of B from the change of ln R0
        against the change of 1/T since the cell's previous pair."""
        self.pair_s = np.where(ok, self.pair_s + max(dt_s, 0.0), self.pair_s)
        due = ok & ((self.pair_s >= PAIR_S) | ~np.isfinite(self.pair_inv_t))
        if not due.any():
            return
        ln_r0 = np.log(np.where(due, r0_ohm, 1.0))
        dx = inv_t - self.pair_inv_t
        dy = ln_r0 - self.pair_ln_r0
        dt_k = np.abs(dx) * (1.0 / inv_t) ** 2  # |d(1/T)| T^2 ~ |dT|
        use = due & np.isfinite(dx) & (dt_k >= MIN_DT_K)
        if use.any():
            r = 2.0 * LN_R_STD**2  # the difference of two noisy logs
            s = dx * dx * self.b_var + r
            gain = np.where(use, self.b_var * dx / np.where(use, s, 1.0), 0.0)
            self.b_K = np.where(use, self.b_K + gain * (dy - self.b_K * dx), self.b_K)
            self.b_var = np.where(use, (1.0 - gain * dx) * self.b_var, self.b_var)
            self.b_K = np.clip(self.b_K, 0.0, 4.0 * B_PRIOR_K)
            self.counters["arrhenius_pairs"] += int(use.sum())
        # every candidate becomes the next reference (keeping an old one until the temperature
        # moved 1 K was tried: day-2 R0 error 4.3 % instead of 3.0 %, ageing and SOC effects
        # between distant pairs were taught as temperature)
        self.pair_ln_r0 = np.where(due, ln_r0, self.pair_ln_r0)
        self.pair_inv_t = np.where(due, inv_t, self.pair_inv_t)
        self.pair_s = np.where(due, 0.0, self.pair_s)

    # ------------------------------------------------------------------ protocol
    def reset(self, mask: BoolArray) -> None:
        """The masked cells forget their pairs (B, a property of the cell, is kept)."""
        m = np.asarray(mask, dtype=bool)
        for k in ("pair_ln_r0", "pair_inv_t"):
            setattr(self, k, np.where(m, np.nan, getattr(self, k)))
        self.pair_s = np.where(m, 0.0, self.pair_s)

    def state_dict(self) -> dict[str, Any]:
        return {k: np.array(getattr(self, k)) for k in self._ARRAYS}

    def load_state_dict(self, st: dict[str, Any]) -> None:
        load_arrays(self, st, self._ARRAYS, self.name)
