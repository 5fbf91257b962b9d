"""Published parameters averaged over each cell's fast time constant.

The last stage of a tick, after the publish guard (``estimate/guard.py``): what leaves the bank
(``params.csv``, CAN, MQTT) is the guarded R1, R2, tau1, tau2 through a first-order average of
time constant ``publish_average_tau1`` x the cell's identified tau1 (s), with C1 = tau1 / R1 and
C2 = tau2 / R2 computed from the averages. R0 is published as estimated: the RLS keeps its
variance through a restart, and it follows temperature every tick (``arrhenius.py``), which an
average would only delay (averaged too, the 3-day records' R0 median rose by up to 0.1 points
where the temperature swings). The estimators, the model voltage and the SOC observer use the
raw estimates; only what is published is averaged.

Why: the RLS restarts its branch covariances after each swarm (``affrls.swarm_covariance``),
and its first updates then take a noisy sample's innovation whole into R1 and R2: on the
known-truth cell one 4 mV sample (4 sigma of the noise) moved R0+R1+R2 by 7.5 % for one tick,
back within 1.5 % four ticks later (README, engine accuracy). A change that lives for a tick or
for less than the fast branch's time constant is not one the data can tell; a BMS that reads R
for its power limits should not see it. The lag is tau1 (~30 s on the reference cell).

A cell is published raw (and its average restarts there) while ``CONVERGING`` (start values,
and the step from them to the first fused values is a change of model, not of the cell), when
its tau1 or any averaged value is not finite, and after a re-initialisation.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

import numpy as np
import numpy.typing as npt

from bmsid.estimate.statedict import load_arrays
from bmsid.estimate.types import Quality

FloatArray = npt.NDArray[np.float64]
BoolArray = npt.NDArray[np.bool_]
IntArray = npt.NDArray[np.int64]

#: The averaged fields, in the rows of :attr:`PublishAverage.avg`; C1 and C2 follow from them.
AVERAGED: tuple[str, ...] = ("R1_ohm", "R2_ohm", "tau1_s", "tau2_s")
_CONVERGING = int(Quality.CONVERGING)


def average_step(
    avg: FloatArray, raw: FloatArray, dt_s: float, tau_s: FloatArray, fresh: BoolArray
) -> FloatArray:
    """One step of the first-order average (rows: fields, columns: cells): ``avg`` moves by
    ``1 - exp(-dt_s / tau_s)`` of the way to ``raw``; ``fresh`` columns, and those whose
    ``tau_s`` or values are not finite, start at ``raw``. Never leaves the interval between
    the previous average and ``raw`` (so never a bound the raw values respect)."""
    ok = ~fresh & np.isfinite(tau_s) & (tau_s > 0) & np.isfinite(avg).all(axis=0)
    ok &= np.isfinite(raw).all(axis=0)
    g = -np.expm1(-max(dt_s, 0.0) / np.where(ok, tau_s, 1.0))
    return np.where(ok, avg + g * (raw - avg), raw)


class PublishAverage:
    """The average of each cell's published parameters (module docstring).

    Args:
        n_cells: cells of the bank.
        tau1_multiple: the average's time constant in units of the cell's tau1; 0 publishes
            the raw values.
    """

    name = "average"

    def __init__(self, n_cells: int, tau1_multiple: float) -> None:
        self.n = n_cells
        self.tau1_multiple = float(tau1_multiple)
        self.avg = np.full((len(AVERAGED), n_cells), np.nan)
        self.restart = np.ones(n_cells, dtype=bool)

    def apply(
        self, cells: Mapping[str, FloatArray], quality: IntArray, dt_s: float
    ) -> dict[str, FloatArray]:
        """The published fields of one tick: ``cells`` (never modified) with R1, R2, tau1, tau2
        averaged and C1, C2 from them; ``dt_s`` the tick's step, s."""
        out = dict(cells)
        if self.tau1_multiple <= 0.0:
            return out
        if self.n == 1:
            return self._apply_one(cells, out, int(quality[0]), dt_s)
        raw = np.array([cells[k] for k in AVERAGED], dtype=np.float64)
        fresh = self.restart | (np.asarray(quality) == _CONVERGING)
        self.avg = average_step(self.avg, raw, dt_s, self.tau1_multiple * raw[2], fresh)
        self.restart = np.zeros(self.n, dtype=bool)
        for j, k in enumerate(AVERAGED):
            out[k] = self.avg[j].copy()
        out["C1_F"] = out["tau1_s"] / out["R1_ohm"]
        out["C2_F"] = out["tau2_s"] / out["R2_ohm"]
        return out

    def _apply_one(
        self, cells: Mapping[str, FloatArray], out: dict[str, FloatArray], q: int, dt_s: float
    ) -> dict[str, FloatArray]:
        """:meth:`apply` for one cell in Python floats: the same operations in the same order
        (np.expm1 as the arrays use it), the same bits (``tests/estimate/test_publish_average.py``);
        a third of the array path's cost, which a single cell pays every tick."""
        raw = [float(cells[k][0]) for k in AVERAGED]
        avg = self.avg[:, 0].tolist()
        tau = self.tau1_multiple * raw[2]
        ok = not self.restart[0] and q != _CONVERGING and math.isfinite(tau) and tau > 0
        ok = ok and all(math.isfinite(x) for x in avg) and all(math.isfinite(x) for x in raw)
        if ok:
            g = float(-np.expm1(-max(dt_s, 0.0) / tau))
            raw = [a + g * (r - a) for a, r in zip(avg, raw, strict=True)]
        self.avg = np.array(raw)[:, None]
        if self.restart[0]:
            self.restart = np.zeros(1, dtype=bool)
        r1, r2, tau1, tau2 = raw
        out["R1_ohm"], out["R2_ohm"] = np.array([r1]), np.array([r2])
        out["tau1_s"], out["tau2_s"] = np.array([tau1]), np.array([tau2])
        out["C1_F"], out["C2_F"] = np.array([tau1 / r1]), np.array([tau2 / r2])
        return out

    def reset(self, mask: BoolArray) -> None:
        """The masked cells publish raw at their next tick (re-initialised by the bank)."""
        self.restart = self.restart | np.asarray(mask, dtype=bool)

    def state_dict(self) -> dict[str, Any]:
        return {"avg": self.avg.copy(), "restart": self.restart.copy()}

    def load_state_dict(self, st: dict[str, Any]) -> None:
        load_arrays(self, st, ("avg", "restart"), self.name)
