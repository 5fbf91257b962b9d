"""The cell a run without a cell config uses: the paper's cell, with what the record itself
tells of the cell in its place.

* its capacity (Ah), when the record discharges the cell to the cut-off
  (``plausibility.derive_capacity``: from full, or from a part-charged rest or small load whose
  SOC the assumed OCV reads);
* its OCV, when the record reads LFP-like and the paper's NMC curve cannot follow it
  (``pseudo_ocv.py``: the IR-corrected voltage against the count, Eq. 4), with no hysteresis
  and bounds derived from the record.

``bmsid identify`` of one file and each input of a fleet run (``fleet.py``) call
:func:`cell_from_record` on the record's head (its first samples), so the two agree.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from bmsid.config.cell import CellConfig, HysteresisTable
from bmsid.config.engine import ocv_model
from bmsid.gates import GateConfig, GateState, gate_block
from bmsid.model.ocv import OcvModel
from bmsid.offline import plausibility
from bmsid.offline.inputs import cell_config
from bmsid.offline.plausibility import CapacityEstimate, FloatArray
from bmsid.offline.pseudo_ocv import pseudo_ocv
from bmsid.samples import SampleBlock

#: A cell reading below this anywhere is a dead tap or a dropout (0 V, 1 V), not a cell at its
#: cut-off (the lowest measured: A123 LFP 1.99 V; the input gate's floor is 0.6 x the rested
#: empty voltage, 1.33 V for LFP): such a column tells neither the cut-off nor the OCV.
DEAD_TAP_V = 1.2


@dataclass(frozen=True)
class RecordCell:
    """The cell read off a record: the config, the note on where it came from (the run's first
    line, ``metrics.json``'s ``cell_config``), the chemistry the record reads as, and the
    description of an OCV read off it (None: the assumed cell's curve)."""

    cell: CellConfig
    note: str
    record_chemistry: str
    pseudo_ocv_text: str | None


#: Passes of reading the capacity and re-gating with it (the current gate scales with it).
MAX_GATE_PASSES = 4
#: The read-off capacity is settled when a pass moves it by less than this share.
GATE_SETTLED_REL = 0.01


def accepted_readings(
    t_s: FloatArray, current_A: FloatArray, voltages_V: FloatArray, cell: CellConfig,
    gap_s: float, gates: GateConfig | None = None,
) -> tuple[FloatArray, FloatArray]:  # fmt: skip
    """The current (A) and voltages (V, (samples, cells)) the run's input gates
    (``bmsid.gates``, limits from ``cell``) accept: a refused voltage NaN, a refused current
    NaN (``plausibility.held`` holds it, as the engine does). What the estimators never see
    must not decide the capacity either (11 samples of 2999 A read a 2 Ah cell as 13.3 Ah; a
    dead channel's 0 V read as the pack's cut-off)."""
    ocv = ocv_model(cell)
    v_ends = ocv.ocv(np.array([ocv.soc_min, ocv.soc_max]))
    limits = (gates or GateConfig()).limits(
        float(v_ends[0]), float(v_ends[1]), cell.capacity_Ah, gap_s
    )
    block = SampleBlock.from_arrays(t_s, current_A, voltages_V)
    out, _ = gate_block(block, limits, GateState.fresh(block.n_cells), drop_refused_current=False)
    return out.current_A, out.cell_voltages_V


def capacity_as_recorded(
    t_s: FloatArray,
    current_A: FloatArray,
    voltages_V: FloatArray,
    gap_s: float,
    ocv_coeffs: Sequence[float] | None = None,
    cell: CellConfig | None = None,
) -> CapacityEstimate | None:
    """The capacity the record's own readings imply, ungated (for the time-unit check, before
    any gate whose current limit would scale with it): a cut-off or the SOC change, read on
    ``cell``'s OCV curve (None: the assumed cell's, with ``ocv_coeffs``). A cell that reads
    below :data:`DEAD_TAP_V` anywhere is left out, as in :func:`cell_from_record`: one tap
    reading 0 V for 10 min of a 4 h, 8-cell record read its pack 510 Ah (config 100) and
    warned that the config's capacity was 0.196x the record's."""
    if cell is None:
        cell, _ = cell_config(None, None, ocv_coeffs)
    v = _live_taps(voltages_V)
    return None if v is None else _read_capacity(t_s, current_A, v, ocv_model(cell), gap_s)


def _live_taps(voltages_V: FloatArray) -> FloatArray | None:
    """The voltages (samples, cells; V; (samples,) for one cell) less the cells that read below
    :data:`DEAD_TAP_V` anywhere (NaN is left to the reader and the gates); None when none is
    left."""
    v = np.asarray(voltages_V, dtype=np.float64)
    v = v[:, None] if v.ndim == 1 else v
    live = ~np.any(v < DEAD_TAP_V, axis=0)
    return v[:, live] if np.count_nonzero(live) else None


def _read_capacity(
    t_s: FloatArray, current_A: FloatArray, voltages_V: FloatArray, ocv: OcvModel, gap_s: float
) -> CapacityEstimate | None:
    """A discharge to the cut-off, else the SOC change the rests read on ``ocv``."""
    return plausibility.derive_capacity(
        t_s, current_A, voltages_V, gap_s, lambda v_V: float(ocv.soc_from_ocv(v_V))
    ) or plausibility.capacity_from_soc_change(
        t_s, current_A, voltages_V, ocv.soc_from_ocv, (ocv.soc_min, ocv.soc_max), gap_s
    )


def cell_from_record(
    t_s: FloatArray,
    current_A: FloatArray,
    voltages_V: FloatArray,
    gap_s: float,
    ocv_coeffs: Sequence[float] | None = None,
    gates: GateConfig | None = None,
) -> RecordCell | None:
    """The paper's cell (with ``ocv_coeffs``, ``--ocv-coeffs``, if given) with the capacity and,
    for an LFP-like record without ``ocv_coeffs``, the OCV read off the record (see the module
    docstring); None when the record tells no capacity. ``voltages_V``: (samples, cells); a
    cell that reads below :data:`DEAD_TAP_V` anywhere is left out (a 0 V tap read as a
    discharge to the cut-off gave a whole pack 66.6 Ah instead of 70).

    Only readings the input gates accept are used (:func:`accepted_readings`). The current gate
    scales with the capacity, so the capacity is read with the assumed cell's gates, then again
    with the gates of the capacity read, until it settles: a value that the run's own gates
    would not reproduce is no capacity (None)."""
    assumed, _ = cell_config(None, None, ocv_coeffs)
    ocv = ocv_model(assumed)
    live = _live_taps(voltages_V)
    if live is None:
        return None
    voltages_V = live
    gated = assumed
    est: CapacityEstimate | None = None
    for _ in range(MAX_GATE_PASSES):
        i_ok, v_ok = accepted_readings(t_s, current_A, voltages_V, gated, gap_s, gates)
        est = _read_capacity(t_s, i_ok, v_ok, ocv, gap_s)
        if est is None:
            return None
        if math.isclose(est.capacity_Ah, gated.capacity_Ah, rel_tol=GATE_SETTLED_REL):
            break
        gated = assumed.model_copy(update={"capacity_Ah": est.capacity_Ah})
    assert est is not None
    cell, note = cell_config(None, round(est.capacity_Ah, 3), ocv_coeffs)
    note = f"{note} ({est.text()})"
    text = None
    if ocv_coeffs is None and est.chemistry != assumed.chemistry:
        cell, text = with_pseudo_ocv(cell, est, t_s, i_ok, v_ok, gap_s)
        if text is not None:  # the paper's curve and hysteresis are gone: say what is left
            note = f"no --cell-config: capacity {cell.capacity_Ah:g} Ah ({est.text()}); {text}"
    return RecordCell(cell, note, est.chemistry, text)


def with_pseudo_ocv(
    cell: CellConfig, est: CapacityEstimate, t: FloatArray, i: FloatArray, v: FloatArray,
    gap_s: float,
) -> tuple[CellConfig, str | None]:  # fmt: skip
    """``cell`` with the OCV read off the record (``pseudo_ocv.py``), no hysteresis and bounds
    from the record (the paper cell's wide defaults let a 70 Ah cell's slow branch take 0.4 ohm
    on the A123 record: 51 mV instead of 9); unchanged (None) when none can be read."""
    v_full = est.v_full_V if est.start_soc >= 1.0 else None  # a part-charged start is not full
    ps = pseudo_ocv(t, i, v, est.capacity_Ah, est.start_soc, gap_s, (est.v_empty_V, v_full))
    if ps is None:
        return cell, None
    flat = HysteresisTable(soc=[0.0, 1.0], M_V=[0.0, 0.0], gamma=cell.hysteresis.gamma)
    update = {"ocv": ps.curve, "hysteresis": flat, "chemistry": est.chemistry, "bounds": None,
              "name": f"record-{est.chemistry}"}  # fmt: skip
    return CellConfig.model_validate({**cell.model_dump(), **update}), ps.text()
