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

A tick is one call of ``KERNEL.impl`` (``jit.select`` chooses): the numpy reference
``average_numpy`` (the arrays' ``average_step``, or one cell in Python floats) or its compiled
twin, which steps each cell in a loop with the same operations in the same order (its
``expm1`` is libm's, numpy's own a last-bit different for a few percent of arguments: equal to
rounding, ``tests/estimate/test_guard_kernel.py``).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

import numpy as np
import numpy.typing as npt
from numpy._core.multiarray import count_nonzero as nnz  # np.count_nonzero less its dispatch

from bmsid.estimate import jit
from bmsid.estimate.statedict import load_arrays
from bmsid.estimate.types import Quality

FloatArray = npt.NDArray[np.float64]
BoolArray = npt.NDArray[np.bool_]
IntArray = npt.NDArray[np.int64]

#: The averaged fields, in the rows of :attr:`PublishAverage.avg`; C1 and C2 follow from them.
AVERAGED: tuple[str, ...] = ("R1_ohm", "R2_ohm", "tau1_s", "tau2_s")
#: The published fields, rows of the kernels' second output.
PUBLISHED: tuple[str, ...] = (*AVERAGED, "C1_F", "C2_F")
#: A literal, read by the compiled kernel (numba's cache follows this file, not types.py).
_CONVERGING = 0
if _CONVERGING != Quality.CONVERGING:
    raise RuntimeError("publish_average: _CONVERGING no longer matches Quality.CONVERGING")


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


def average_numpy(
    avg: FloatArray, raw: FloatArray, quality: IntArray, restart: BoolArray, dt_s: float,
    tau1_multiple: float,
) -> FloatArray:  # fmt: skip
    """One tick of the average, the reference: the published :data:`PUBLISHED` rows (6, n), a
    new array, from the average (4, n; updated in place, which spares the compiled call boxing
    it), the raw :data:`AVERAGED` rows, the quality codes, the cells to restart and the
    tick's step ``dt_s``; the other arguments are never written."""
    if raw.shape[1] == 1:
        return _average_one(avg, raw, int(quality[0]), bool(restart[0]), dt_s, tau1_multiple)
    fresh = restart | (quality == _CONVERGING)
    avg[...] = average_step(avg, raw, dt_s, tau1_multiple * raw[2], fresh)
    pub = np.empty((len(PUBLISHED), raw.shape[1]))
    pub[:4] = avg
    pub[4] = avg[2] / avg[0]
    pub[5] = avg[3] / avg[1]
    return pub


def _average_one(
    avg_: FloatArray, raw_: FloatArray, q: int, restart: bool, dt_s: float, tau1_multiple: float
) -> FloatArray:
    """:func:`average_numpy` for one cell in Python floats: the same operations in the same
    order (np.expm1 as the arrays use it), the same bits
    (``tests/estimate/test_publish_average.py``); a third of the array path's cost, which a
    single cell pays every tick."""
    raw = raw_[:, 0].tolist()
    avg = avg_[:, 0].tolist()
    tau = tau1_multiple * raw[2]
    ok = not restart and q != _CONVERGING and math.isfinite(tau) and tau > 0
    ok = ok and all(math.isfinite(x) for x in avg) and all(math.isfinite(x) for x in raw)
    if ok:
        g = float(-np.expm1(-max(dt_s, 0.0) / tau))
        raw = [a + g * (r - a) for a, r in zip(avg, raw, strict=True)]
    avg_[:, 0] = raw
    r1, r2, tau1, tau2 = raw
    return np.array([[r1], [r2], [tau1], [tau2], [tau1 / r1], [tau2 / r2]])


def _average_source(
    avg: FloatArray, raw: FloatArray, quality: IntArray, restart: BoolArray, dt_s: float,
    tau1_multiple: float,
) -> FloatArray:  # fmt: skip
    """The same tick per cell (compiled by numba)."""
    n_rows, n = raw.shape
    pub = np.empty((n_rows + 2, n))
    d = 0.0 if dt_s < 0.0 else dt_s  # Python's max(dt_s, 0.0): NaN stays
    for i in range(n):
        tau = tau1_multiple * raw[2, i]
        ok = not restart[i] and quality[i] != _CONVERGING and math.isfinite(tau) and tau > 0
        for r in range(n_rows):
            ok = ok and math.isfinite(avg[r, i]) and math.isfinite(raw[r, i])
        g = -math.expm1(-d / tau) if ok else 0.0
        for r in range(n_rows):  # in place: the cell's average was read above
            a = avg[r, i]
            avg[r, i] = a + g * (raw[r, i] - a) if ok else raw[r, i]
            pub[r, i] = avg[r, i]
        # np.true_divide: numpy's x / 0 (inf, NaN), where numba's "/" raises
        pub[n_rows, i] = np.true_divide(avg[2, i], avg[0, i])
        pub[n_rows + 1, i] = np.true_divide(avg[3, i], avg[1, i])
    return pub


def _warm(kernel: Any) -> object:
    for n in (1, 2):
        one = np.ones((len(AVERAGED), n))
        kernel(one, one, np.ones(n, dtype=np.int64), np.zeros(n, dtype=bool), 1.0, 1.0)
    return None


KERNEL = jit.Kernel("publish average", average_numpy, _average_source, _warm)


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
        raw = np.array([cells[k] for k in AVERAGED], dtype=np.float64)
        pub = KERNEL.impl(  # self.avg updated in place
            self.avg, raw, np.asarray(quality, dtype=np.int64), self.restart, float(dt_s),
            self.tau1_multiple,
        )  # fmt: skip
        if nnz(self.restart):
            self.restart = np.zeros(self.n, dtype=bool)
        for j, k in enumerate(PUBLISHED):
            out[k] = pub[j]
        return out

    def reset(self, mask: BoolArray) -> None:
        """The masked cells publish raw at their next tick (re-initialised by the bank)."""
        self.restart = self.restart | np.asarray(mask, dtype=bool)

    def state_dict(self) -> dict[str, Any]:
        return {"avg": self.avg.copy(), "restart": self.restart.copy()}

    def load_state_dict(self, st: dict[str, Any]) -> None:
        load_arrays(self, st, ("avg", "restart"), self.name)
