"""The cell read off a record without a config (``record_cell.cell_from_record``) uses only the
readings the run's input gates accept (``bmsid.gates``): a current glitch or a dead channel the
estimators never see must not decide the capacity either."""

from __future__ import annotations

import numpy as np
import numpy.typing as npt
import pytest
from test_identify_cli import synthetic_columns
from test_plausibility import part_charged_discharge

from bmsid.config.cell import paper_cell
from bmsid.config.engine import ocv_model
from bmsid.model.simulator import simulate
from bmsid.offline import plausibility as pl
from bmsid.offline.record_cell import capacity_as_recorded, cell_from_record

FloatArray = npt.NDArray[np.float64]


def discharge(
    soc0: float, stop_V: float = 3.0, n_cells: int = 1, i_start_A: float = 0.0
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """A 2 Ah cell's rest (or start at ``i_start_A``) then 1C to ``stop_V``, (samples, cells)."""
    return part_charged_discharge(soc0, i_start_A, stop_V=stop_V, n_cells=n_cells)


@pytest.mark.parametrize("glitch_A", [1000.0, 2999.0])
def test_current_glitches_the_gates_refuse_do_not_make_the_capacity(glitch_A: float) -> None:
    """11 single samples of a glitch: 2999 A lies beyond the assumed 70 Ah cell's gate (30 C),
    1000 A within it and beyond the 2 Ah cell's (60 A): the capacity is read again with the
    gates of the capacity read until it settles."""
    t, i, v = discharge(0.8)
    clean = cell_from_record(t, i, v, 30.0)
    assert clean is not None and 0.95 * 2.0 <= clean.cell.capacity_Ah <= 2.0
    bad = i.copy()
    bad[np.linspace(300, t.size - 300, 11).astype(int)] = glitch_A
    raw = pl.derive_capacity(
        t, bad, v, soc_at_rest=lambda x: float(ocv_model(paper_cell()).soc_from_ocv(x))
    )
    assert raw is not None and raw.capacity_Ah > 1.5 * 2.0  # what the record read before
    found = cell_from_record(t, bad, v, 30.0)
    assert found is not None
    assert found.cell.capacity_Ah == pytest.approx(clean.cell.capacity_Ah, rel=0.01)


def test_a_dead_channel_is_not_the_packs_cut_off() -> None:
    """A 3-cell pack discharged from 80 % to 3.4 V (not empty) whose cell 2 reads 0 V from
    halfway: the gates refuse its 0 V, so no cut-off is read off it."""
    t, i, v = discharge(0.8, stop_V=3.4, n_cells=3)
    v[t.size // 2 :, 1] = 0.0
    assert (
        pl.derive_capacity(t, i, v) is not None
        or pl.derive_capacity(
            t, i, v, soc_at_rest=lambda x: float(ocv_model(paper_cell()).soc_from_ocv(x))
        )
        is not None
    )  # the raw record reads the 0 V as the cut-off
    found = cell_from_record(t, i, v, 30.0)
    assert found is None or "0.000 V" not in found.note


def test_held_and_cell_mean_min_leave_refused_readings_out() -> None:
    x = np.array([np.nan, 1.0, np.nan, np.nan, 3.0])
    np.testing.assert_array_equal(pl.held(x, 0.0), [0.0, 1.0, 1.0, 1.0, 3.0])
    v = np.array([[3.0, np.nan], [np.nan, np.nan], [3.2, 3.6]])
    mean, low = pl.cell_mean_min(v)
    np.testing.assert_allclose(mean, [3.0, 3.0, 3.4])
    np.testing.assert_allclose(low, [3.0, 3.0, 3.2])


def test_a_discharge_to_the_cut_off_under_load_from_its_first_sample() -> None:
    """The record opens under C/4 (a quarter of the 1C peak, which the old share-of-peak rule
    refused): the first voltage is IR-corrected and the capacity read as from a rest."""
    clean = cell_from_record(*discharge(0.8), 30.0)
    found = cell_from_record(*discharge(0.8, i_start_A=0.5), 30.0)
    assert clean is not None and found is not None
    assert found.cell.capacity_Ah == pytest.approx(clean.cell.capacity_Ah, rel=0.03)
    assert "(IR-corrected from under 0.5 A)" in found.note


def dst_without_cut_off(capacity_Ah: float, hours: float = 2.0) -> tuple[FloatArray, ...]:
    """60 s rest at 90 %, then DST at 2C peak for ``hours`` (ends around 40 %, no cut-off)."""
    from bmsid.profiles import dst_current

    t = np.arange(int(3600 * hours), dtype=np.float64)
    i = np.where(t < 60, 0.0, dst_current(t - 60, 2.0 * capacity_Ah))
    r = 1.2e-3 * 70.0 / capacity_Ah
    sim = simulate(
        t, i, ocv_model(paper_cell()), capacity_Ah=capacity_Ah, gamma=30.0, soc0=0.9,
        R0_ohm=r, R1_ohm=0.7 * r, tau1_s=30.0, R2_ohm=0.8 * r, tau2_s=600.0,
    )  # fmt: skip
    return t, i, sim.v_V[0] + np.random.default_rng(2).normal(0.0, 1e-3, t.size)


@pytest.mark.parametrize("capacity_Ah", [2.0, 100.0])
def test_capacity_from_the_soc_change_when_no_cut_off_is_reached(capacity_Ah: float) -> None:
    """No cut-off: the charge over the SOC change the rest ends read on the assumed OCV, with
    their polarisation fitted (read as they are the capacity comes out 10-15 % low)."""
    t, i, v = dst_without_cut_off(capacity_Ah)
    ocv = ocv_model(paper_cell())
    est = pl.capacity_from_soc_change(t, i, v, ocv.soc_from_ocv, (ocv.soc_min, ocv.soc_max))
    assert est is not None and est.n_rests >= pl.SOC_CHANGE_MIN_POINTS
    assert 0.92 * capacity_Ah <= est.capacity_Ah <= 1.05 * capacity_Ah
    assert est.polarisation_V < 0  # rest voltages below the OCV after a discharge
    found = cell_from_record(t, i, v, 30.0)
    assert found is not None and found.cell.capacity_Ah == pytest.approx(est.capacity_Ah, rel=0.01)
    assert "no cut-off in the record" in found.note and "give --capacity-ah" in found.note
    # 20 minutes move too little SOC to tell: no capacity, not a guess
    n = 1200
    assert (
        pl.capacity_from_soc_change(
            t[:n], i[:n], v[:n], ocv.soc_from_ocv, (ocv.soc_min, ocv.soc_max)
        )
        is None
    )


@pytest.mark.parametrize("dead_from", [2000, 4800])
def test_a_dead_tap_does_not_read_as_the_packs_capacity(dead_from: int) -> None:
    """One of 3 taps reads 0 V for 10 min (at the end: the rest ends the SOC-change read uses):
    the capacity the record implies is the other cells' (it read 26.3 Ah for ~67, and the
    config's capacity was then said to be 2.5x the record's)."""
    cols = synthetic_columns(5400, n_cells=3)
    v = np.column_stack([cols[f"v_cell_0{k}"] for k in (1, 2, 3)])
    dead = v.copy()
    dead[dead_from : dead_from + 600, 1] = 0.0
    got = capacity_as_recorded(cols["t_s"], cols["current_A"], dead, 30.0)
    live = capacity_as_recorded(cols["t_s"], cols["current_A"], v[:, [0, 2]], 30.0)
    assert got is not None and live is not None
    assert got.capacity_Ah == pytest.approx(live.capacity_Ah)
