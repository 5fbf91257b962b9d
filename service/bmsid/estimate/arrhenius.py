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

A swarm's window fit (30 min) gives R0 at the window's temperature, which lags a moving one:
at a drive's end, cooling 0.5 K in half an hour at 50 kJ/mol, 3 % low, and the evening's
constant-current charge kept it. ``window_factor`` takes the fit's R0 to the last tick's
temperature, from the window's temperature as the fit weighs it (its current steps).

B is the cell's activation temperature, identified from those window fits' (ln R0, 1 / T) pairs
by a scalar Kalman filter on the differences of consecutive pairs (used when the temperature
moved at least ``MIN_DT_K`` and SOC at most ``MAX_PAIR_DSOC`` between them: a drive's first fit
against the last one of the drive before, a rest between; R0 depends on SOC as well), starting
from the prior ``B_PRIOR_K`` (30 kJ/mol: ohmic and charge-transfer resistances of Li-ion cells
near room temperature, 15-60 kJ/mol in the literature) with std ``B_PRIOR_STD_K``, within
``B_MIN_K``-``B_MAX_K``. A window fit's R0 is the data's alone; R0 learnt tick by tick, which
fed B before, is the value the law carried (with the B in force) plus the data's first
corrections, so a pair early in a drive taught B back towards itself: on ``temp-ea50`` (3 days,
truth 6,014 K) B reached 6,135 K but the window fits' temperature lag held R0 4 % low under the
charges; with the lag corrected, B learnt tick by tick reached 5,600 K (R0 2-3 % low); from the
window fits 5,956 K, R0 median under load 0.2 / 0.2 / 0.4 % on days 1-3 (6.7 / 4.1 / 4.0 %
before). Without the SOC condition a DFN cell's fits 2 K and many SOC points apart took B to 0.
Without a temperature (NaN) nothing changes,
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
#: The gas constant, J/(mol K).
R_GAS = 8.314
#: Prior activation temperature Ea / R_gas, K (30 kJ/mol).
B_PRIOR_K = 30_000.0 / R_GAS
#: Its std, K: Ea from 15 to 60 kJ/mol is within 2 sigma.
B_PRIOR_STD_K = 1800.0
#: Pairs closer than this in temperature say nothing about B, K.
MIN_DT_K = 1.0
#: Std of a fit's ln R0 beyond the temperature's share: the fit's noise, the SOC moving within
#: and between windows, ageing between pairs (each pair takes the difference of two).
LN_R_STD = 0.03
#: Pairs further apart in SOC than this (fraction) are not used: R0 depends on SOC as well (a
#: DFN cell's R0 16 -> 26 mOhm over one discharge while it warmed).
MAX_PAIR_DSOC = 0.1
#: B's bounds, K: activation energies 10-90 kJ/mol (reported ones for Li-ion resistances lie in
#: 15-60); never 0, a resistance with no temperature dependence.
B_MIN_K, B_MAX_K = 10_000.0 / R_GAS, 90_000.0 / R_GAS


class ArrheniusCarry:
    """Per-cell activation temperature B and the last tick's temperature (module docstring)."""

    name = "arrhenius"
    _ARRAYS = ("b_K", "b_var", "t_prev_K", "pair_ln_r0", "pair_inv_t", "pair_soc")

    def __init__(self, n_cells: int) -> None:
        self.n = n_cells
        self.b_K = np.full(n_cells, B_PRIOR_K)
        self.b_var = np.full(n_cells, B_PRIOR_STD_K**2)
        self.t_prev_K = np.full(n_cells, np.nan)
        self.pair_ln_r0 = np.full(n_cells, np.nan)
        self.pair_inv_t = np.full(n_cells, np.nan)
        self.pair_soc = np.full(n_cells, np.nan)
        self.counters: dict[str, int] = {"arrhenius_pairs": 0, "arrhenius_carried": 0}

    def step(self, temperature_C: float, carry: BoolArray, r0_ohm: FloatArray) -> FloatArray | None:
        """One tick. ``carry``: cells whose R0 (ohm) moves by the law's factor from the previous
        tick's temperature to this one's (every identified cell: a learning one takes it as its
        prediction). Per-tick factors telescope, so a temperature that comes back brings R0
        back exactly, and a constant one changes nothing. Returns the carried R0, or None when
        nothing is carried."""
        if not math.isfinite(temperature_C):
            return None
        t_k = temperature_C + KELVIN
        prev = self.t_prev_K
        self.t_prev_K = np.full(self.n, t_k)
        go = carry & np.isfinite(prev) & (prev != t_k)
        if not go.any():
            return None
        factor = np.exp(self.b_K * (1.0 / t_k - 1.0 / np.where(go, prev, t_k)))
        self.counters["arrhenius_carried"] += int(go.sum())
        return np.asarray(np.where(go, r0_ohm * factor, r0_ohm), dtype=np.float64)

    def learn_fit(self, c: int, r0_ohm: float, soc: float) -> None:
        """Cell ``c``'s R0 (ohm) from a window fit, taken to the last tick's temperature
        (:meth:`window_factor`), at SOC ``soc`` (fraction), as its next (ln R0, 1 / T) pair: a
        scalar Kalman update of B from the change of ln R0 against the change of 1 / T since
        its previous pair, where the temperature moved at least ``MIN_DT_K`` and SOC at most
        ``MAX_PAIR_DSOC`` (a drive's first fit and the last of the drive before, a rest
        between). A window fit's R0 is the data's alone (the fit does not start from the
        carried value); R0 learnt tick by tick is the carried value plus the data's first
        corrections, and a pair early in a drive after a rest 7 K warmer taught the prior's B
        back (30 -> 40 kJ/mol on ``temp-ea50``, truth 50)."""
        inv_t = 1.0 / float(self.t_prev_K[c])
        if not (math.isfinite(inv_t) and r0_ohm > 0 and math.isfinite(soc)):
            return
        ln_r0 = math.log(r0_ohm)
        dx, dy = inv_t - float(self.pair_inv_t[c]), ln_r0 - float(self.pair_ln_r0[c])
        near = abs(soc - float(self.pair_soc[c])) <= MAX_PAIR_DSOC  # False against NaN
        if near and abs(dx) / inv_t**2 >= MIN_DT_K:  # |d(1/T)| T^2 ~ |dT|
            var, b = float(self.b_var[c]), float(self.b_K[c])
            gain = var * dx / (dx * dx * var + 2.0 * LN_R_STD**2)  # two noisy logs
            self.b_K[c] = min(max(b + gain * (dy - b * dx), B_MIN_K), B_MAX_K)
            self.b_var[c] = (1.0 - gain * dx) * var
            self.counters["arrhenius_pairs"] += 1
        # every fit becomes the next reference (one kept until the temperature moved 1 K took
        # ageing and SOC effects between distant pairs for temperature)
        self.pair_ln_r0[c], self.pair_inv_t[c], self.pair_soc[c] = ln_r0, inv_t, soc

    def window_factor(
        self, c: int, inv_t_K: FloatArray, current_A: FloatArray, weights: FloatArray
    ) -> float:
        """The factor that takes cell ``c``'s R0 fitted over a window (a swarm's) to the last
        tick's temperature. A fit of R0 over a window whose temperature moved is R0 at the
        window's temperature as the fit weighs it: its current steps (R0 is what a step shows
        at once; the branches take the rest), ``weights`` x (delta I)^2, by their 1 / T
        (``inv_t_K``, NaN where unknown). 1 when the window's temperature is the last tick's
        or unknown. (A 30 min window at a drive's end lags a cooling pack by ~0.5 K: R0 3 %
        low at 50 kJ/mol, kept through the evening's constant-current charge.)"""
        inv_now = 1.0 / self.t_prev_K[c]
        di = np.diff(current_A, prepend=current_A[:1])
        w = weights * di * di
        ok = np.isfinite(inv_t_K) & (w > 0)
        if not math.isfinite(inv_now) or not ok.any() or np.all(inv_t_K[ok] == inv_now):
            return 1.0
        inv_fit = float(np.sum(w[ok] * inv_t_K[ok]) / np.sum(w[ok]))
        return math.exp(float(self.b_K[c]) * (inv_now - inv_fit))

    def activation_energy_J_mol(self) -> FloatArray:
        """Per cell, the law's activation energy Ea = B R_gas, J/mol (the prior until a pair)."""
        return np.asarray(self.b_K * R_GAS, dtype=np.float64)

    # ------------------------------------------------------------------ protocol
    def reset(self, mask: BoolArray) -> None:
        """The masked cells forget their pairs (B, a property of the cell, is kept)."""
        m = np.asarray(mask, dtype=bool)
        for k in ("pair_ln_r0", "pair_inv_t", "pair_soc"):
            setattr(self, k, np.where(m, np.nan, getattr(self, k)))

    def state_dict(self) -> dict[str, Any]:
        return {k: np.array(getattr(self, k)) for k in self._ARRAYS}

    def load_state_dict(self, st: dict[str, Any]) -> None:
        st = {"pair_soc": np.full(self.n, np.nan), **st}  # (checkpoints before: no SOC)
        load_arrays(self, st, self._ARRAYS, self.name)
