"""The cell config turned into what the engine takes: numbers, never a pydantic model.

``model/`` and ``estimate/`` do not import ``bmsid.config``; this module is the one arrow from
the file format to the numeric core.
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from bmsid.config.cell import CellConfig
from bmsid.estimate.bank import EstimatorBank
from bmsid.estimate.cellmodel import BOUNDED, CellModel, SocStart
from bmsid.estimate.tuning import EstimatorTuning, Variant
from bmsid.model.ocv import OcvModel

FloatArray = npt.NDArray[np.float64]


def ocv_model(cell: CellConfig) -> OcvModel:
    """The cell's mean OCV curve (Eq. 4) and hysteresis table M(z) (Eq. 32)."""
    return OcvModel.from_coeffs(
        cell.ocv.mean, cell.ocv.soc_min, cell.ocv.soc_max, cell.hysteresis.soc, cell.hysteresis.M_V
    )


def cell_model(cell: CellConfig, n_cells: int) -> CellModel:
    """``n_cells`` cells of type ``cell`` as per-cell arrays (capacity Ah, efficiency, gamma,
    start values, bounds, SOC start policy)."""
    if n_cells < 1:
        raise ValueError("n_cells must be >= 1")
    ini = cell.initial_parameters()
    b = cell.bounds
    return CellModel.uniform(
        n_cells,
        name=cell.name,
        ocv=ocv_model(cell),
        capacity_Ah=cell.capacity_Ah,
        efficiency=cell.coulombic_efficiency,
        gamma=cell.hysteresis.gamma,
        initial={k: getattr(ini, k) for k in ("R0_ohm", "R1_ohm", "tau1_s", "R2_ohm", "tau2_s")},
        bounds={k: (getattr(b, k).lo, getattr(b, k).hi) for k in BOUNDED},
        soc_start=SocStart(
            policy=cell.soc_init.policy,
            soc0=cell.soc_init.soc0,
            rest_current_C=cell.soc_init.rest_current_C,
        ),
    )


def build_bank(
    cell: CellConfig,
    n_cells: int,
    variant: Variant = "hy-affrls-lpso",
    tuning: EstimatorTuning | None = None,
    soc0: float | FloatArray | None = None,
    cell_ids: npt.ArrayLike | None = None,
    n_stagger: int | None = None,
) -> EstimatorBank:
    """A new estimator bank of ``n_cells`` cells of type ``cell`` (see ``EstimatorBank``)."""
    return EstimatorBank(cell_model(cell, n_cells), variant, tuning, soc0, cell_ids, n_stagger)
