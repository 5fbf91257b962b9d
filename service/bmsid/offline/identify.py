"""Run an estimator bank over a whole recording and score its model voltage (Eq. 31).

The library behind ``bmsid identify`` and ``bmsid compare``: feed every sample of a tester file
(or of decoded CAN samples) to an :class:`~bmsid.estimate.bank.EstimatorBank`, collect its
per-tick estimates into arrays, and compute the accuracy metrics over an evaluation window.
Pure apart from the clock read for the run time.

Evaluation window (``EvalWindow``): the first ticks are spent converging from the start values,
so by default the first 10 % of the ticks are not scored; with a SOC window only the ticks whose
(coulomb-counted) SOC lies inside it are scored. Metrics over every tick are reported as well.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import numpy.typing as npt

from bmsid.config.cell import CellConfig
from bmsid.estimate.bank import EstimatorBank
from bmsid.estimate.tuning import EstimatorTuning, Variant
from bmsid.estimate.types import Estimates
from bmsid.metrics import VoltageMetrics, voltage_metrics
from bmsid.offline.csvio import TesterData
from bmsid.samples import Sample

FloatArray = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]
BoolArray = npt.NDArray[np.bool_]

#: Per-tick, per-cell fields of ``Trace`` (shape (n_ticks, n_cells)), in params.csv order.
CELL_FIELDS = (
    "R0_ohm", "R1_ohm", "C1_F", "R2_ohm", "C2_F", "tau1_s", "tau2_s", "lambda_", "h", "soc",
    "v_model_V", "v_meas_V", "M_V", "ocv_offset_V",
)  # fmt: skip

#: Called with the number of samples consumed since the last call (progress bars).
Progress = Callable[[int], None]


@dataclass(frozen=True)
class Trace:
    """What the bank reported at every identification tick.

    ``t_s`` and ``current_A`` (tick-averaged, A, + = discharge) have shape (n_ticks,); every
    name in ``CELL_FIELDS`` and ``quality`` has shape (n_ticks, n_cells), units as in
    :class:`~bmsid.estimate.types.Estimates`.
    """

    t_s: FloatArray
    current_A: FloatArray
    cells: dict[str, FloatArray]
    quality: IntArray

    @property
    def n_ticks(self) -> int:
        return int(self.t_s.shape[0])

    @property
    def n_cells(self) -> int:
        return int(self.quality.shape[1])

    def __getitem__(self, name: str) -> FloatArray:
        return self.cells[name]


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

    def mask(self, trace: Trace) -> BoolArray:
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
    """One bank run: its trace, how SOC was initialised, its counters and its wall time (s)."""

    variant: Variant
    trace: Trace
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


def _collect(estimates: list[Estimates], n_cells: int) -> Trace:
    if not estimates:
        empty = np.zeros((0, n_cells))
        return Trace(
            t_s=np.zeros(0),
            current_A=np.zeros(0),
            cells={k: empty.copy() for k in CELL_FIELDS},
            quality=np.zeros((0, n_cells), dtype=np.int64),
        )
    cells = {
        k: np.stack([getattr(e, k) for e in estimates]).astype(np.float64) for k in CELL_FIELDS
    }
    return Trace(
        t_s=np.array([e.t_s for e in estimates], dtype=np.float64),
        current_A=np.array([e.current_A for e in estimates], dtype=np.float64),
        cells=cells,
        quality=np.stack([e.quality for e in estimates]).astype(np.int64),
    )


def run_arrays(
    t_s: FloatArray,
    current_A: FloatArray,
    voltages_V: FloatArray,
    cell: CellConfig,
    variant: Variant,
    tuning: EstimatorTuning | None = None,
    soc0: float | None = None,
    progress: Progress | None = None,
    cell_names: Sequence[str] | None = None,
) -> IdentifyResult:
    """Feed samples (time s, pack current A + = discharge, voltages V of shape (n, n_cells))
    one by one to a new bank; ``progress`` is called every few thousand samples."""
    v = np.asarray(voltages_V, dtype=np.float64)
    if v.ndim == 1:
        v = v[:, None]
    n, n_cells = v.shape
    if t_s.shape[0] != n or current_A.shape[0] != n:
        raise ValueError("t_s, current_A and voltages_V need the same number of samples")
    bank = EstimatorBank(cell, n_cells, variant, tuning, soc0=soc0)
    out: list[Estimates] = []
    step = 2000
    t_list = t_s.tolist()
    i_list = current_A.tolist()
    start = time.perf_counter()
    for k in range(n):
        est = bank.update(t_list[k], i_list[k], v[k])
        if est is not None:
            out.append(est)
        if progress is not None and (k + 1) % step == 0:
            progress(step)
    runtime = time.perf_counter() - start
    if progress is not None and n % step:
        progress(n % step)
    names = list(cell_names) if cell_names else [f"cell_{c + 1:02d}" for c in range(n_cells)]
    return IdentifyResult(
        variant=variant,
        trace=_collect(out, n_cells),
        soc_init_method=bank.soc_init_method,
        counters=dict(bank.counters),
        runtime_s=runtime,
        n_samples=n,
        cell_names=names,
    )


def run_tester(
    data: TesterData,
    cell: CellConfig,
    variant: Variant,
    tuning: EstimatorTuning | None = None,
    soc0: float | None = None,
    progress: Progress | None = None,
) -> IdentifyResult:
    """``run_arrays`` over a tester file (cells named by their voltage columns)."""
    return run_arrays(
        data.t_s, data.current_A, data.cell_voltages_V, cell, variant, tuning, soc0, progress,
        data.cell_names,
    )  # fmt: skip


def samples_to_arrays(samples: Sequence[Sample]) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Decoded samples as (t_s, current_A, voltages_V (n, n_cells)) arrays."""
    if not samples:
        raise ValueError("no samples")
    t = np.array([s.t_s for s in samples], dtype=np.float64)
    i = np.array([s.current_A for s in samples], dtype=np.float64)
    v = np.stack([np.asarray(s.cell_voltages_V, dtype=np.float64) for s in samples])
    return t, i, v


def run_samples(
    samples: Sequence[Sample],
    cell: CellConfig,
    variant: Variant,
    tuning: EstimatorTuning | None = None,
    soc0: float | None = None,
    progress: Progress | None = None,
) -> IdentifyResult:
    """``run_arrays`` over decoded CAN samples (the daemon's input type)."""
    t, i, v = samples_to_arrays(samples)
    return run_arrays(t, i, v, cell, variant, tuning, soc0, progress)


def score(trace: Trace, window: EvalWindow) -> Scores:
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


def parameter_trajectories(trace: Trace, window: EvalWindow, cell: int) -> dict[str, FloatArray]:
    """Each parameter of ``SUMMARY_PARAMS`` at the scored ticks of one cell (SI units)."""
    m = window.mask(trace)[:, cell]
    return {name: trace[name][m, cell].copy() for name in SUMMARY_PARAMS}


def parameter_medians(trace: Trace, window: EvalWindow) -> dict[str, FloatArray]:
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
