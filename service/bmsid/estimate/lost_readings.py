"""Cells whose readings stopped: published ``no_data`` after ``gap_s`` without a valid voltage.

A broken voltage tap, or a cell whose every reading the gates refuse, leaves the cell's state on
the coulomb count and its parameters held: what was last identified, not what the cell does now.
Published as ``converged`` they read as live values (a live daemon with one cell's readings
refused for 10 min did exactly that). After ``EstimatorTuning.gap_s`` without a valid voltage
(the horizon beyond which a jump in time is a gap: what happened is no longer known) the cell is
published as before its first reading, every field NaN and quality ``NO_DATA``, until a valid
reading returns. Its state is untouched, so SOC resumes from the count and the observer corrects
it from the first voltage. Episodes are counted (``readings_lost``).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from bmsid.estimate.stage import BoolArray, FloatArray
from bmsid.estimate.state import without_data
from bmsid.estimate.statedict import load_arrays
from bmsid.estimate.types import IntArray


class ReadingWatch:
    """Per cell, the time of its last valid voltage (s) and whether it is published as lost."""

    def __init__(self, n_cells: int, hold_s: float) -> None:
        self.hold_s = float(hold_s)
        #: time of each cell's last valid voltage, s (NaN: none yet; such a cell is the state's
        #: ``no_data`` already, not lost)
        self.last_valid_t_s = np.full(n_cells, math.nan)
        self.lost: BoolArray = np.zeros(n_cells, dtype=bool)
        self.counters = {"readings_lost": 0}

    def apply(
        self, t_s: FloatArray, cells: dict[str, FloatArray], quality: IntArray
    ) -> tuple[dict[str, FloatArray], IntArray]:
        """The ticks ``t_s`` (s, shape (T,)) with ``cells[name]`` and ``quality`` of shape
        (T, n): the lost cells' fields NaN and their quality ``NO_DATA`` (new arrays where any
        cell is lost; the inputs untouched)."""
        valid = np.isfinite(cells["v_meas_V"])
        t = np.asarray(t_s, dtype=np.float64)
        if valid.all():  # the usual block: nothing to look at
            self.last_valid_t_s = np.full_like(self.last_valid_t_s, t[-1])
            self.lost = np.zeros_like(self.lost)
            return cells, quality
        rows = np.arange(t.shape[0])[:, None]
        latest = np.maximum.accumulate(np.where(valid, rows, -1), axis=0)
        last_t = np.where(latest >= 0, t[np.maximum(latest, 0)], self.last_valid_t_s[None, :])
        lost = (t[:, None] - last_t) > self.hold_s  # NaN (no valid reading yet): False
        started = lost & ~np.vstack([self.lost[None, :], lost[:-1]])
        self.counters["readings_lost"] += int(started.sum())
        self.last_valid_t_s, self.lost = last_t[-1].copy(), lost[-1].copy()
        return without_data(cells, quality, lost) if lost.any() else (cells, quality)

    def state_dict(self) -> dict[str, Any]:
        return {"last_valid_t_s": self.last_valid_t_s.copy(), "lost": self.lost.copy()}

    def load_state_dict(self, st: dict[str, Any]) -> None:
        load_arrays(self, st, ("last_valid_t_s", "lost"), "readings")
