"""The start SOC of a record whose first voltage misleads (``estimate/start_fit.py``), offline.

Used when no ``--soc0`` is given and the cell config reads SOC from the first voltage
(``soc_init.policy = "ocv_at_rest"``), where that voltage is known to mislead: the record
opens under load (the engine IR-corrects it with R0 alone) or at rest with the voltage still
moving (``plausibility.check_start_relaxation``). A start at rest and relaxed reads OCV + M h0
with h0 unknown (-1 after a discharge, +1 after a charge): its h0 is fitted along the first
voltage's SOC-h0 line and kept only where it explains the window clearly better than h = 0
(``start_fit.H0_GAIN_MIN``); else it keeps the first voltage's reading, the better one there.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from bmsid.config.cell import CellConfig
from bmsid.config.engine import build_bank
from bmsid.estimate.start_fit import (
    MAX_HEAD_CELL_SAMPLES,
    WINDOW_S,
    first_load_s,
    fit_start_soc,
    head_end_s,
)
from bmsid.estimate.startvalues import StartValues
from bmsid.estimate.state import starts_at_rest
from bmsid.estimate.tuning import EstimatorTuning
from bmsid.gates import InputGate
from bmsid.offline.plausibility import check_start_relaxation
from bmsid.samples import SampleBlock

FloatArray = npt.NDArray[np.float64]

#: ``soc_init_method`` of a run whose start SOC was fitted here
WINDOW_FIT = "window_fit"


@dataclass(frozen=True)
class FittedStart:
    """Per cell, the start a bank takes (``build_bank(soc0=..., branch0_V=...)``): the SOC
    (fraction) and the two RC branches' voltages at the first sample (V, (cells, 2); 0 for a
    cell the fit did not hold for, which keeps its first voltage's reading)."""

    soc0: FloatArray
    branch_V: FloatArray
    #: False where the start SOC was given: only the branches were fitted, and the start
    #: keeps its own ``soc_init_method``
    soc_fitted: bool = True
    #: per cell, the fit's RMSE over its window (V; NaN where no fit held)
    rmse_V: FloatArray | None = None
    #: per cell, the hysteresis state at the first sample ([-1, 1]): fitted on a rested start
    #: (which the first voltage cannot tell from SOC), else 0, as the engine starts it
    h0: FloatArray | None = None


def fitted_start_soc(
    blocks: Iterable[SampleBlock], cell: CellConfig, tuning: EstimatorTuning | None,
    start: StartValues | None, gate: InputGate | None = None,
    soc0: float | FloatArray | None = None, each_cell: Callable[[], None] | None = None,
) -> FittedStart | None:  # fmt: skip
    """Per cell, the start SOC and branch voltages fitted over the record's first ``WINDOW_S``
    (through ``gate``, fresh plausibility gates, when given; ``each_cell`` called after each
    cell's fit: the daemon's heartbeat), or None where the first voltage
    is to be trusted or no fit holds (cells without one keep their first voltage's reading).
    A known start SOC (``soc0``: ``--soc0``, the daemon's configured one) is kept as it is
    and only the branches are fitted; a cell config's fixed ``soc0`` is a standing guess, not
    this start's SOC: such a start is not fitted (a wrong SOC would be fitted into the
    branches).

    The branches' voltages matter as much as the SOC: a bank started at the fitted SOC with
    its branches empty meets, under load, a first voltage off by what the branches hold (CALCE
    25 C BJDST entered 1,800 s in: 16 mV), and its first updates put that into R0 (74 -> 121
    mOhm): 3.26 mV over SOC 95-15 %, against 1.04 mV with the fitted branches."""
    si = cell.soc_init
    if soc0 is None and si.policy != "ocv_at_rest":
        return None
    b = start_head(blocks, cell.soc_init.rest_current_C * cell.capacity_Ah, gate)
    if b is None:
        return None
    bank = build_bank(cell, b.n_cells, "hy-affrls", tuning, soc0=soc0, start=start)
    first = bank.update_block(SampleBlock.from_arrays(b.t_s[:2], b.current_A[:2],
                                                      b.cell_voltages_V[:2]))  # fmt: skip
    if not len(first.t_s):
        return None
    loaded = not starts_at_rest(float(first.current_A[0]), bank.model)
    r0 = float(bank.model.start("R0_ohm")[0])
    capacity = float(bank.model.capacity_Ah[0])
    relaxing = check_start_relaxation(
        b.t_s, b.current_A, b.cell_voltages_V, capacity, r0, si.rest_current_C
    )
    known = soc0 is not None
    rested = not (loaded or relaxing)
    if rested and known:
        return None
    guess = np.full(b.n_cells, soc0, dtype=np.float64) if known else first.cells["soc"][0]
    fit = fit_start_soc(
        b.t_s, b.current_A, b.cell_voltages_V, bank.model, guess, tuning=bank.tuning,
        soc_known=known, rested=rested, each_cell=each_cell,
    )  # fmt: skip
    fitted = np.isfinite(fit.soc0)
    start_soc = np.where(fitted, fit.soc0, guess)
    # No fit anywhere, or a cell without a first voltage (it must start at its own first valid
    # reading, which only the engine's start does): the engine's start for every cell.
    if not np.count_nonzero(fitted) or not np.all(np.isfinite(start_soc)):
        return None
    return FittedStart(
        start_soc, np.where(fitted[:, None], fit.branch_V, 0.0), not known,
        np.where(fitted, fit.rmse_V, np.nan), np.where(fitted, fit.h0, 0.0),
    )  # fmt: skip


def start_head(
    blocks: Iterable[SampleBlock], rest_limit_A: float, gate: InputGate | None = None
) -> SampleBlock | None:
    """The record's samples up to the end of its start window (through ``gate``, fresh gates,
    when given): its first ``WINDOW_S``, or ``WINDOW_S`` from just before the load where a rest
    longer than half of that comes first (``start_fit.window_start``; at most
    ``MAX_LEADING_REST_S`` of it, and past the first ``WINDOW_S`` at most
    ``MAX_HEAD_CELL_SAMPLES``, read). None for a record without blocks."""
    head: list[SampleBlock] = []
    load: float | None = None
    cell_samples = 0
    for block in blocks:
        head.append(block if gate is None else gate.apply(block))
        if not len(block):
            continue
        cell_samples += len(block) * block.n_cells
        if load is None:
            load = first_load_s(head[-1].t_s, head[-1].current_A, rest_limit_A)
        first, last = next(float(h.t_s[0]) for h in head if len(h)), float(block.t_s[-1])
        if last >= head_end_s(first, load, last):
            break
        if last - first >= WINDOW_S and cell_samples > MAX_HEAD_CELL_SAMPLES:
            break  # past the first window, a long rest of a large, fast pack: memory bounded
    return SampleBlock.concat(head) if head else None
