"""The daemon names a cell whose model error is far beyond its pack's, once per episode
(``daemon/lone_cell_watch.py``)."""

from __future__ import annotations

import numpy as np

from bmsid.daemon.lone_cell_watch import WINDOW_S, LoneCellWatch
from bmsid.estimate.fields import FIELD_NAMES
from bmsid.estimate.types import EstimateBlock


def _block(t: np.ndarray, err: np.ndarray) -> EstimateBlock:
    cells = {k: np.zeros_like(err) for k in FIELD_NAMES}
    cells["v_error_V"] = err
    return EstimateBlock(t_s=t, current_A=np.zeros(t.size), cells=cells,
                         quality=np.ones(err.shape, dtype=np.int64))  # fmt: skip


def test_a_cell_far_off_its_pack_is_named_once_per_episode() -> None:
    """4 cells at 1 mV of model error, cell 2 at 15 mV (every tenth tick 150 mV) for two
    windows, then healed for one, then off again: named after the first and the fourth."""
    watch = LoneCellWatch(4)
    said = []
    rng = np.random.default_rng(0)
    n = int(WINDOW_S) + 1  # a window's ticks: its first to its last is WINDOW_S
    for w, faulty in enumerate((True, True, False, True)):
        t = w * n + np.arange(float(n))
        err = rng.normal(0.0, 1e-3, (n, 4))
        if faulty:
            err[::10, 2] += 0.15
        for a in range(0, n, 100):  # blocks as the worker's chunks come
            said += [(w, c) for c, _, _ in watch.add(_block(t[a : a + 100], err[a : a + 100]))]
    assert said == [(0, 2), (3, 2)]


def test_two_cells_cannot_tell_which_is_off() -> None:
    watch = LoneCellWatch(2)
    n = int(WINDOW_S) + 1
    err = np.full((n, 2), 1e-3)
    err[:, 1] = 0.05
    assert watch.add(_block(np.arange(float(n)), err)) == []
