"""A cell whose model error is far beyond its pack's, said in the daemon's log once per episode
(offline, ``identify`` says it of the whole record: ``offline/scoring.lone_cell_warnings``).

One cell of a series string that the model follows several times worse than its siblings has
a fault of its own: a loose or intermittent sense wire, a bad tap, a failing cell. The SOC
observer already keeps such a cell from the pack's current offset (``observer_kernel.
lone_cells``); this tells the operator, whose dashboard showed it ``converged`` (sweep G:
+50 mV on every tenth sample of one of 8 cells, 15.7 mV RMS against 1.6 mV, no log line).
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from bmsid.estimate.types import EstimateBlock
from bmsid.offline.scoring import lone_by_rmse

#: Data time (s) over which each cell's model error is judged: several drive cycles.
WINDOW_S = 1800.0


class LoneCellWatch:
    """Per ``WINDOW_S`` of estimates, the cells whose model error RMS is far beyond the
    cells' median (``offline.scoring.lone_by_rmse``, the rule ``identify`` applies)."""

    def __init__(self, n_cells: int) -> None:
        self.sq = np.zeros(n_cells)
        self.n = np.zeros(n_cells, dtype=np.int64)
        self.t0: float | None = None
        self.flagged = np.zeros(n_cells, dtype=bool)

    def add(self, block: EstimateBlock) -> list[tuple[int, float, float]]:
        """Take a block of estimates; at the end of each window, the cells newly found alone:
        (cell index, its RMS V, the cells' median RMS V). A cell is said again only after a
        window in which it was not alone."""
        if block.n_ticks == 0:
            return []
        e: npt.NDArray[np.float64] = np.asarray(block["v_error_V"], dtype=np.float64)
        ok = np.isfinite(e)
        self.sq += np.sum(np.where(ok, e * e, 0.0), axis=0)
        self.n += np.count_nonzero(ok, axis=0)
        t_last = float(block.t_s[-1])
        if self.t0 is None:
            self.t0 = float(block.t_s[0])
        if t_last - self.t0 < WINDOW_S:
            return []
        rms = np.where(self.n > 0, np.sqrt(self.sq / np.maximum(self.n, 1)), np.nan)
        self.sq[:], self.n[:], self.t0 = 0.0, 0, None
        lone, med = lone_by_rmse(rms)
        new = np.flatnonzero(lone & ~self.flagged)
        self.flagged = lone
        return [(int(c), float(rms[c]), med) for c in new]
