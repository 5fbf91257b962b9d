"""A cell voltage reading that stopped moving: the ``v_frozen`` gate (``bmsid.gates``).

A BMS whose front end stopped converting often keeps sending the last value it had: plausible
in range and step, and wrong. A live cell's voltage cannot stay the same to the last bit while
the current moves: a change of the current by dI moves it by R0 dI at once (Eq. 9). So a reading
identical to the cell's last one for ``frozen_min_s`` or more, over which the pack current has
moved by ``frozen_dI_A`` (the current that moves the voltage by ``frozen_step_V`` through the
smallest start R0) from where it was when the value last changed, is refused from there on, until
the value changes. Readings near the top of the rested range are exempt: under constant-voltage
charging the voltage is held while the current tapers. Measured (a sweep): a CALCE DST log with
one cell's voltage held for 10 min mid-drive ran at 16.85 mV against 1.64, unflagged.

Pure and vectorised over the block's samples and cells; the run that reaches over the block's
end is carried in :class:`FrozenRuns`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

FloatArray = npt.NDArray[np.float64]
BoolArray = npt.NDArray[np.bool_]


@dataclass(frozen=True, slots=True)
class FrozenRuns:
    """Per cell, the run of identical readings the last block ended in: its value (V), the
    time (s) and pack current (A) when it began, and whether the current has moved by
    ``frozen_dI_A`` since (NaN, NaN, NaN, False: none)."""

    v_V: FloatArray
    t0_s: FloatArray
    i0_A: FloatArray
    moved: BoolArray

    @classmethod
    def fresh(cls, n_cells: int) -> FrozenRuns:
        nan = np.full(n_cells, np.nan)
        return cls(nan, nan.copy(), nan.copy(), np.zeros(n_cells, dtype=bool))


def frozen_readings(
    t_s: FloatArray, current_A: FloatArray, v_V: FloatArray, runs: FrozenRuns,
    min_s: float, dI_A: float, top_V: float,
) -> tuple[BoolArray, FrozenRuns]:  # fmt: skip
    """Which readings of ``v_V`` (samples, cells) are frozen (module docstring), and the runs
    to carry into the next block. ``dI_A`` infinite: none is."""
    n, c = v_V.shape
    if n == 0 or not np.isfinite(dI_A):
        return np.zeros((n, c), dtype=bool), runs
    # Row 0 is the carried run; a NaN reading never equals anything, so it ends a run.
    vv = np.vstack([runs.v_V[None, :], v_V])
    tt = np.vstack([runs.t0_s[None, :], np.broadcast_to(t_s[:, None], (n, c))])
    ii = np.vstack([runs.i0_A[None, :], np.broadcast_to(current_A[:, None], (n, c))])
    rows = np.arange(n + 1)[:, None]
    new_run = np.vstack([np.ones((1, c), dtype=bool), vv[1:] != vv[:-1]])
    start = np.maximum.accumulate(np.where(new_run, rows, 0), axis=0)
    t0 = np.take_along_axis(tt, start, axis=0)
    i0 = np.take_along_axis(ii, start, axis=0)
    with np.errstate(invalid="ignore"):
        moved = np.abs(ii - i0) >= dI_A  # a NaN current moves nothing
        moved[0] = runs.moved
        last_move = np.maximum.accumulate(np.where(moved, rows, -1), axis=0)
        since = last_move >= start
        frozen = since & (tt - t0 >= min_s) & (vv < top_V)  # NaN readings compare False
    carried = FrozenRuns(vv[-1].copy(), t0[-1].copy(), i0[-1].copy(), since[-1].copy())
    return frozen[1:], carried
