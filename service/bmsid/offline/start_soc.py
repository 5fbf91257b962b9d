"""The start SOC of a record whose first voltage misleads (``estimate/start_fit.py``), offline.

Used when no ``--soc0`` is given and the cell config reads SOC from the first voltage
(``soc_init.policy = "ocv_at_rest"``), only where that voltage is known to mislead: the record
opens under load (the engine IR-corrects it with R0 alone) or at rest with the voltage still
moving (``plausibility.check_start_relaxation``). A start at rest and relaxed keeps the first
voltage's reading, which is the better one there.
"""

from __future__ import annotations

from collections.abc import Iterable

import numpy as np
import numpy.typing as npt

from bmsid.config.cell import CellConfig
from bmsid.config.engine import build_bank
from bmsid.estimate.start_fit import WINDOW_S, fit_start_soc
from bmsid.estimate.startvalues import StartValues
from bmsid.estimate.tuning import EstimatorTuning
from bmsid.gates import InputGate, gated_head
from bmsid.offline.plausibility import check_start_relaxation
from bmsid.samples import SampleBlock

FloatArray = npt.NDArray[np.float64]

#: ``soc_init_method`` of a run whose start SOC was fitted here
WINDOW_FIT = "window_fit"


def fitted_start_soc(
    blocks: Iterable[SampleBlock], cell: CellConfig, tuning: EstimatorTuning | None,
    start: StartValues | None, gate: InputGate | None = None,
) -> FloatArray | None:  # fmt: skip
    """Per cell, the start SOC fitted over the record's first ``WINDOW_S`` (through ``gate``,
    fresh plausibility gates, when given), or None where the first voltage is to be trusted or
    no fit holds (cells without one keep their first voltage's reading)."""
    if cell.soc_init.policy != "ocv_at_rest":
        return None
    b = gated_head(blocks, WINDOW_S, gate)
    if b is None:
        return None
    bank = build_bank(cell, b.n_cells, "hy-affrls", tuning, start=start)
    first = bank.update_block(SampleBlock.from_arrays(b.t_s[:2], b.current_A[:2],
                                                      b.cell_voltages_V[:2]))  # fmt: skip
    if not len(first.t_s):
        return None
    loaded = bank.soc_init_method == "ocv_ir_corrected"
    r0 = float(bank.model.start("R0_ohm")[0])
    capacity = float(bank.model.capacity_Ah[0])
    relaxing = check_start_relaxation(
        b.t_s, b.current_A, b.cell_voltages_V, capacity, r0, cell.soc_init.rest_current_C
    )
    if not (loaded or relaxing):
        return None
    guess = first.cells["soc"][0]
    fit = fit_start_soc(
        b.t_s, b.current_A, b.cell_voltages_V, bank.model, guess, tuning=bank.tuning
    )
    soc0 = np.where(np.isfinite(fit.soc0), fit.soc0, guess)
    # No fit anywhere, or a cell without a first voltage (it must start at its own first valid
    # reading, which only the engine's start does): the engine's start for every cell.
    if not np.count_nonzero(np.isfinite(fit.soc0)) or not np.all(np.isfinite(soc0)):
        return None
    return soc0
