"""A start read from a voltage that was still relaxing: how much SOC it may be off by.

A SOC read from the first voltage at rest (``state.start_soc_sigma``) assumes the RC branches
have relaxed. A log that begins seconds after a drive, or a tester's record that starts a few
seconds after its last discharge step, begins with the branches still charged: the voltage is
tens of mV from the OCV and climbs (after a discharge) or sinks (after a charge) while the
record rests. That drift is measurable before the first load step, and it is what this module
measures.

Over the first rest of a start, per cell, the least-squares slope ``s`` (V/s) of the voltage
against time and its standard error (from the fit's own residuals, their std at least a 1 mV
resolution's quantisation). When the rest ends, what is left of a relaxation that moves at
``s`` is ``s tau``; ``tau`` lies between the start values' tau1 and tau2 (Eq. 8: a sum of two
exponentials has remaining / rate between its time constants), and the estimate uses their
geometric mean, the middle of that range on a log scale. Only the slope beyond two standard
errors counts, so a noisy flat rest widens nothing. ``offline/plausibility`` judges the same
slope (``slope_from_sums``) to warn the user (``start_not_relaxed``).

The result widens the SOC uncertainty (the observer's ``P``); it does not move SOC: on CALCE's
records a start after a charge and a chamber still settling in temperature drift too (0 and
45 degC: -0.8 to -1.3 mV in 7 s), and the observer's updates, not this estimate, tell which way
SOC is off.

A rest that lasts ``anchor_min_rest_s`` ends the watch without widening: the rest anchor
(``observer.py``) then reads SOC from a relaxed voltage.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from bmsid.estimate.stage import BoolArray, FloatArray
from bmsid.estimate.statedict import load_arrays

#: Fewest rest samples whose slope is judged (a slope of 2 points has no residuals).
MIN_SAMPLES = 5
#: Least residual std a slope's error is computed with, V: the quantisation of a 1 mV
#: resolution (1 / sqrt(12) mV); a flat quantised rest has residuals of ~0.
NOISE_FLOOR_V = 0.29e-3


class StartRelaxation:
    """The first rest of a start from the voltage, watched per cell (see the module docstring).

    Args:
        n_cells: cells of the bank.
        tau_s: the relaxation time the remaining voltage is estimated with, s, per cell
            (sqrt(tau1 tau2) of the start values).
        max_rest_s: a rest this long ends the watch without a result (the anchor's).
    """

    _SUMS = ("n", "st", "sv", "stt", "stv", "svv", "v0")

    def __init__(self, n_cells: int, tau_s: FloatArray, max_rest_s: float) -> None:
        self.tau_s = np.broadcast_to(np.asarray(tau_s, dtype=np.float64), (n_cells,)).copy()
        self.max_rest_s = max_rest_s
        self.active = False
        self.t0_s = 0.0
        z = np.zeros(n_cells)
        self.n, self.st, self.sv, self.stt, self.stv, self.svv = (z.copy() for _ in range(6))
        self.v0 = z.copy()  # the first voltage, V: sums of v - v0 keep their digits

    def begin(self, t_s: float, cells: BoolArray) -> None:
        """A start from the voltage at rest at ``t_s`` (s): watch ``cells`` from this tick."""
        self.active = True
        self.t0_s = t_s
        for k in self._SUMS:
            setattr(self, k, np.where(cells, 0.0, getattr(self, k)))

    def feed(self, t_s: float, v_V: FloatArray, ok: BoolArray, resting: bool) -> FloatArray | None:
        """One tick. Returns, when the first rest ends under load, the voltage (V, >= 0, per
        cell) the start may be off by beyond what ``start_soc_sigma`` allowed for; else None."""
        if not self.active:
            return None
        t = t_s - self.t0_s
        if t > self.max_rest_s:
            self.active = False
            return None
        if not resting:
            self.active = False
            return self._remaining_V()
        use = ok & np.isfinite(v_V)
        self.v0 = np.where(use & (self.n == 0), v_V, self.v0)
        v = np.where(use, v_V - self.v0, 0.0)
        self.n = self.n + use
        self.st = self.st + use * t
        self.sv = self.sv + v
        self.stt = self.stt + use * t * t
        self.stv = self.stv + v * t
        self.svv = self.svv + v * v
        return None

    def _remaining_V(self) -> FloatArray:
        slope, se = slope_from_sums(self.n, self.st, self.sv, self.stt, self.stv, self.svv)
        beyond = np.maximum(np.abs(slope) - 2.0 * se, 0.0)
        ok = (self.n >= MIN_SAMPLES) & np.isfinite(beyond)
        return np.where(ok, beyond * self.tau_s, 0.0)

    def state_dict(self) -> dict[str, Any]:
        return {
            "active": self.active,
            "t0_s": self.t0_s,
            **{k: self.__dict__[k].copy() for k in self._SUMS},
        }

    def load_state_dict(self, st: dict[str, Any]) -> None:
        load_arrays(self, st, self._SUMS, "state/observer/start_relaxation")
        self.active = bool(st["active"])
        self.t0_s = float(st["t0_s"])


def slope_from_sums(
    n: FloatArray, st: FloatArray, sv: FloatArray, stt: FloatArray, stv: FloatArray,
    svv: FloatArray, noise_floor_V: float = NOISE_FLOOR_V,
) -> tuple[FloatArray, FloatArray]:  # fmt: skip
    """Least-squares slope (V/s) of v against t from the sums of 1, t, v, t^2, t v, v^2 (per
    column), and its standard error from the fit's residual std, at least ``noise_floor_V``
    (a quantised flat rest has residuals of ~0). NaN where fewer than 3 points or no spread
    in t. Shift t and v before summing (the first sample) to keep the digits."""
    n = np.asarray(n, dtype=np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        m = np.where(n > 0, n, np.nan)
        tt = stt - st**2 / m
        tv = stv - st * sv / m
        vv = svv - sv**2 / m
        slope = np.where((n >= 3) & (tt > 0), tv / tt, np.nan)
        resid_sd = np.sqrt(np.maximum(vv - slope * tv, 0.0) / np.maximum(n - 2.0, 1.0))
        se = np.maximum(resid_sd, noise_floor_V) / np.sqrt(tt)
    return slope, se


def relaxation_tau_s(tau1_s: FloatArray, tau2_s: FloatArray) -> FloatArray:
    """sqrt(tau1 tau2), s: the middle (log scale) of a two-branch relaxation's remaining / rate."""
    return np.asarray(np.sqrt(np.maximum(tau1_s, 0.0) * np.maximum(tau2_s, 0.0)), np.float64)


def widened_variance(var: FloatArray, extra_V: FloatArray, slope_V: FloatArray,
                     sigma_max: float) -> FloatArray:  # fmt: skip
    """SOC variance (fraction^2) ``var`` plus ``(extra_V / |dOCV/dz|)^2``, at most
    ``sigma_max^2`` (or ``var`` where that is already larger)."""
    add = (extra_V / np.maximum(np.abs(slope_V), 1e-9)) ** 2
    cap = max(sigma_max, 0.0) ** 2
    return np.where(add > 0, np.maximum(np.minimum(var + add, cap), var), var)
