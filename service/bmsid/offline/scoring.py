"""What an offline run produced and how well its model voltage tracks the cell (Eq. 31).

Evaluation window (:class:`EvalWindow`): the first ticks are spent converging from the start
values, so by default the first 10 % of the ticks are not scored; with a SOC window only the
ticks whose (coulomb-counted) SOC lies inside it are scored. Metrics over every tick are reported
as well. Pure: arrays in, numbers and dicts out.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
import numpy.typing as npt

from bmsid.estimate.tuning import Variant
from bmsid.estimate.types import EstimateBlock
from bmsid.metrics import VoltageMetrics, voltage_metrics

FloatArray = npt.NDArray[np.float64]
BoolArray = npt.NDArray[np.bool_]


@dataclass(frozen=True)
class EvalWindow:
    """Which ticks are scored: SOC inside [soc_lo, soc_hi] (fractions), after skipping the
    first ``skip_fraction`` of the ticks. ``None`` bounds are open."""

    skip_fraction: float = 0.1
    soc_lo: float | None = None
    soc_hi: float | None = None

    def __post_init__(self) -> None:
        if not 0.0 <= self.skip_fraction < 1.0:
            raise ValueError(f"skip fraction must lie in [0, 1), got {self.skip_fraction}")
        lo = -np.inf if self.soc_lo is None else self.soc_lo
        hi = np.inf if self.soc_hi is None else self.soc_hi
        if lo >= hi:
            raise ValueError(f"SOC window needs lo < hi, got {self.soc_lo}, {self.soc_hi}")

    def mask(self, trace: EstimateBlock) -> BoolArray:
        """Boolean (n_ticks, n_cells): the scored ticks of each cell."""
        n = trace.n_ticks
        keep = np.arange(n) >= int(np.floor(self.skip_fraction * n))
        m = np.repeat(keep[:, None], trace.n_cells, axis=1)
        soc = trace["soc"]
        if self.soc_lo is not None:
            m &= soc >= self.soc_lo
        if self.soc_hi is not None:
            m &= soc <= self.soc_hi
        return m

    def describe(self) -> str:
        parts = []
        if self.skip_fraction > 0:
            parts.append(f"first {100 * self.skip_fraction:g} % of the ticks skipped")
        if self.soc_lo is not None or self.soc_hi is not None:
            lo = "0" if self.soc_lo is None else f"{100 * self.soc_lo:g}"
            hi = "100" if self.soc_hi is None else f"{100 * self.soc_hi:g}"
            parts.append(f"estimated SOC within {lo}-{hi} %")
        return "; ".join(parts) or "all ticks"

    def as_dict(self) -> dict[str, Any]:
        return {
            "skip_fraction": self.skip_fraction,
            "soc_lo": self.soc_lo,
            "soc_hi": self.soc_hi,
            "description": self.describe(),
        }


@dataclass(frozen=True)
class IdentifyResult:
    """One bank run over a recording.

    Attributes
    ----------
    variant : str
        The estimator variant that ran.
    trace : EstimateBlock
        The bank's estimates at every identification tick.
    soc_init_method : str
        How the initial SOC was found (``given``, ``ocv_at_rest``, ``config``, ``default_0.5``).
    counters : dict of str to int
        The bank's event counters at the end.
    runtime_s : float
        Wall time of the identification alone (reading and writing excluded), s.
    n_samples : int
        Input samples fed to the bank.
    cell_names : list of str
        Name of each cell column.
    """

    variant: Variant
    trace: EstimateBlock
    soc_init_method: str
    counters: dict[str, int]
    runtime_s: float
    n_samples: int
    cell_names: list[str] = field(default_factory=list)


@dataclass(frozen=True)
class Scores:
    """Eq. 31 metrics: pooled over the cells and per cell, in the window and over all ticks."""

    window: VoltageMetrics
    overall: VoltageMetrics
    per_cell_window: list[VoltageMetrics]
    per_cell_overall: list[VoltageMetrics]


def score(trace: EstimateBlock, window: EvalWindow) -> Scores:
    """Eq. 31 on the model voltage, pooled over cells and per cell, in ``window`` and overall."""
    m = window.mask(trace)
    meas, model = trace["v_meas_V"], trace["v_model_V"]
    nan = np.nan
    return Scores(
        window=voltage_metrics(np.where(m, meas, nan).ravel(), model.ravel()),
        overall=voltage_metrics(meas.ravel(), model.ravel()),
        per_cell_window=[
            voltage_metrics(np.where(m[:, c], meas[:, c], nan), model[:, c])
            for c in range(trace.n_cells)
        ],
        per_cell_overall=[voltage_metrics(meas[:, c], model[:, c]) for c in range(trace.n_cells)],
    )


def metrics_document(result: IdentifyResult, window: EvalWindow) -> dict[str, Any]:
    """The content of metrics.json: window metrics at the top, per cell under ``cells``."""
    s = score(result.trace, window)
    cells: dict[str, Any] = {}
    for c, name in enumerate(result.cell_names):
        cells[name] = {
            "algorithm": result.variant,
            **s.per_cell_window[c].as_dict(),
            "runtime_s": result.runtime_s,
            "overall": s.per_cell_overall[c].as_dict(),
        }
    return {
        "algorithm": result.variant,
        **s.window.as_dict(),
        "runtime_s": result.runtime_s,
        "evaluation_window": window.as_dict(),
        "overall": s.overall.as_dict(),
        "n_input_samples": result.n_samples,
        "n_ticks": result.trace.n_ticks,
        "soc_init_method": result.soc_init_method,
        "counters": result.counters,
        "cells": cells,
    }


#: Parameters summarised by ``parameter_medians`` and ``parameter_trajectories``.
SUMMARY_PARAMS = ("R0_ohm", "R1_ohm", "C1_F", "R2_ohm", "C2_F", "tau1_s", "tau2_s")


def parameter_trajectories(
    trace: EstimateBlock, window: EvalWindow, cell: int
) -> dict[str, FloatArray]:
    """Each parameter of ``SUMMARY_PARAMS`` at the scored ticks of one cell (SI units)."""
    m = window.mask(trace)[:, cell]
    return {name: trace[name][m, cell].copy() for name in SUMMARY_PARAMS}


def parameter_medians(trace: EstimateBlock, window: EvalWindow) -> dict[str, FloatArray]:
    """Median of each identified parameter (R0, R1, C1, R2, C2 and the taus) over the scored
    ticks, per cell (NaN for a cell with no scored tick). Units as in ``CELL_FIELDS``."""
    m = window.mask(trace)
    out: dict[str, FloatArray] = {}
    for name in SUMMARY_PARAMS:
        vals = trace[name]
        out[name] = np.array(
            [
                float(np.median(vals[m[:, c], c])) if m[:, c].any() else np.nan
                for c in range(trace.n_cells)
            ]
        )
    return out
