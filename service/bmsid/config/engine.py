"""The cell config turned into what the engine takes: numbers, never a pydantic model.

``model/`` and ``estimate/`` do not import ``bmsid.config``; this module is the one arrow from
the file format to the numeric core.
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from bmsid.config.cell import CellConfig
from bmsid.estimate.bank import EstimatorBank
from bmsid.estimate.cellmodel import BOUNDED, INITIAL, CellModel, SocStart
from bmsid.estimate.startvalues import StartValues
from bmsid.estimate.tuning import EstimatorTuning, Variant
from bmsid.model.ocv import OcvModel

FloatArray = npt.NDArray[np.float64]


def ocv_model(cell: CellConfig) -> OcvModel:
    """The cell's mean OCV curve (Eq. 4, plus its correction table and its end segments to the
    rested voltages at empty and full when the config has them) and hysteresis table M(z)
    (Eq. 32)."""
    o = cell.ocv
    return OcvModel.from_coeffs(
        o.mean,
        o.soc_min,
        o.soc_max,
        cell.hysteresis.soc,
        cell.hysteresis.M_V,
        v_empty_V=o.v_empty_V,
        v_full_V=o.v_full_V,
        corr_soc=o.correction_soc,
        corr_V=o.correction_V,
    )


def cell_model(
    cell: CellConfig,
    n_cells: int,
    start: StartValues | None = None,
    tuning: EstimatorTuning | None = None,
) -> CellModel:
    """``n_cells`` cells of type ``cell`` as per-cell arrays (capacity Ah, efficiency, gamma,
    start values, bounds, SOC start policy).

    Start values and bounds the config leaves out come from ``start`` (measured on the record,
    ``estimate/startvalues.py``; bounds relative to its R0, the time constants' limits from the
    tuning's tick period and swarm window) or, without it, from the capacity rule and the wide
    default bounds.
    """
    if n_cells < 1:
        raise ValueError("n_cells must be >= 1")
    tun = tuning or EstimatorTuning()
    defaults = cell.parameter_bounds()
    bounds = {k: (getattr(defaults, k).lo, getattr(defaults, k).hi) for k in BOUNDED}
    if cell.bounds is None and start is not None:
        bounds = start.bounds(tun.id_period_s, tun.window_s, bounds)
    if cell.initial is None and start is not None:
        initial = {k: float(getattr(start, k)) for k in INITIAL}
    else:
        ini = cell.initial_parameters()
        initial = {k: float(getattr(ini, k)) for k in INITIAL}
    return CellModel.uniform(
        n_cells,
        name=cell.name,
        ocv=ocv_model(cell),
        capacity_Ah=cell.capacity_Ah,
        efficiency=cell.coulombic_efficiency,
        gamma=cell.hysteresis.gamma,
        initial=initial,
        bounds=bounds,
        soc_start=SocStart(
            policy=cell.soc_init.policy,
            soc0=cell.soc_init.soc0,
            rest_current_C=cell.soc_init.rest_current_C,
        ),
        hysteresis_play=cell.hysteresis_law == "play",
    )


def build_bank(
    cell: CellConfig,
    n_cells: int,
    variant: Variant = "hy-affrls-lpso",
    tuning: EstimatorTuning | None = None,
    soc0: float | FloatArray | None = None,
    cell_ids: npt.ArrayLike | None = None,
    n_stagger: int | None = None,
    start: StartValues | None = None,
    branch0_V: FloatArray | None = None,
    h0: FloatArray | None = None,
) -> EstimatorBank:
    """A new estimator bank of ``n_cells`` cells of type ``cell`` (see ``EstimatorBank``);
    ``start``: start values measured on the record (see ``cell_model``); ``branch0_V``: the
    branches' voltages at the first sample (V, (n_cells, 2)), None for empty ones; ``h0``: the
    hysteresis state a start at ``soc0`` takes (None: 0)."""
    model = cell_model(cell, n_cells, start, tuning)
    return EstimatorBank(model, variant, tuning, soc0, cell_ids, n_stagger, branch0_V, h0)
