"""The start SOC fitted over a record's first window (issue 11, "start from anywhere": a start
under load or still relaxing, which the first voltage misreads)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from bmsid.config.engine import build_bank
from bmsid.estimate.start_fit import fit_start_soc
from bmsid.offline.csvio import TesterData, write_tester_csv
from bmsid.offline.identify import IdentifySpec, identify_file
from bmsid.offline.start_soc import WINDOW_FIT
from bmsid.synthetic import paper_dst_case


def _mid_drive(start_s: int, n_cells: int = 1) -> tuple[object, slice]:
    spread = np.linspace(1.0, 1.3, n_cells)
    run = paper_dst_case(start_s + 3000, soc0=0.9, r0_spread=spread)
    return run, slice(start_s, None)


def test_a_start_mid_drive_is_fitted_to_its_true_soc_from_a_wrong_guess() -> None:
    """Entered 2,016 s into the paper cell's DST (loaded, branches charged, h away from 0): the
    fit lands within 1.5 points of the true SOC (it reads ~1 point low: it starts h at 0, the
    engine's start, where the truth has discharged it towards -1) from guesses 6 points off
    either way; both cells of a pack with different R0 on their own."""
    run, k = _mid_drive(2016, n_cells=2)
    model = build_bank(run.cell, 2, "hy-affrls").model
    truth = run.soc_true[k][0]
    for off in (-0.06, 0.06):
        fit = fit_start_soc(run.t_s[k], run.current_A[k], run.voltages_V[k], model,
                            np.full(2, truth + off))  # fmt: skip
        assert np.all(np.abs(fit.soc0 - truth) < 0.015), (off, fit.soc0, truth)
        assert np.all(fit.rmse_V < 3e-3)


def test_no_fit_without_enough_record_or_charge_moved() -> None:
    run, k = _mid_drive(2016)
    model = build_bank(run.cell, 1, "hy-affrls").model
    short = slice(2016, 2016 + 300)  # five minutes: too short to tell branches from a level
    fit = fit_start_soc(run.t_s[short], run.current_A[short], run.voltages_V[short], model,
                        np.array([0.8]))  # fmt: skip
    assert np.isnan(fit.soc0).all()
    rest = np.zeros_like(run.current_A[k])  # a rest moves no charge: nothing to fit SOC from
    fit = fit_start_soc(run.t_s[k], rest, run.voltages_V[k], model, np.array([0.8]))
    assert np.isnan(fit.soc0).all()


def test_identify_fits_a_loaded_start_and_keeps_a_rested_one(tmp_path: Path) -> None:
    """``identify`` without ``--soc0``: the loaded start is fitted (within 1.5 points), the
    record that opens at rest keeps the first voltage's reading."""
    run, k = _mid_drive(2016)
    truth = float(run.soc_true[k][0])
    cases = {"loaded": k, "rested": slice(0, None)}  # paper_dst_case opens with a rest
    for name, part in cases.items():
        path = tmp_path / f"{name}.csv"
        write_tester_csv(
            TesterData(t_s=run.t_s[part] - run.t_s[part][0], current_A=run.current_A[part],
                       cell_voltages_V=run.voltages_V[part], cell_names=["voltage_V"]),
            path,
        )  # fmt: skip
        res = identify_file(path, IdentifySpec(cell=run.cell, variant="hy-affrls-lpso"))
        first = res.first_tick()
        assert first is not None
        if name == "loaded":
            assert res.soc_init_method == WINDOW_FIT
            assert abs(float(first["soc"][0][0]) - truth) < 0.015
        else:
            assert res.soc_init_method == "ocv_at_rest"


def test_a_dead_tap_or_a_late_cell_gets_no_fit_and_does_not_stop_the_others(
    tmp_path: Path,
) -> None:
    """A cell without voltages (a dead tap) or with only its first few: no fit for it, no
    error, the others fitted; ``identify`` then keeps the engine's start, which leaves a cell
    without a first voltage pending until its own first reading."""
    run, k = _mid_drive(2016, n_cells=3)
    v = run.voltages_V[k].copy()
    v[:, 1] = np.nan
    v[5:, 2] = np.nan
    model = build_bank(run.cell, 3, "hy-affrls").model
    truth = float(run.soc_true[k][0])
    fit = fit_start_soc(run.t_s[k], run.current_A[k], v, model, np.full(3, truth - 0.05))
    assert abs(fit.soc0[0] - truth) < 0.015
    assert np.isnan(fit.soc0[1:]).all()
    path = tmp_path / "dead.csv"
    write_tester_csv(
        TesterData(t_s=run.t_s[k] - run.t_s[k][0], current_A=run.current_A[k], cell_voltages_V=v,
                   cell_names=["v_cell_01", "v_cell_02", "v_cell_03"]),
        path,
    )  # fmt: skip
    res = identify_file(path, IdentifySpec(cell=run.cell, variant="hy-affrls"))
    assert res.soc_init_method != WINDOW_FIT


def test_nan_currents_hold_the_last_one() -> None:
    """Lost current readings (5 % of them): those samples are not fitted, the count and the
    branches hold the current before through them; the fit stays within 1.5 points."""
    run, k = _mid_drive(2016)
    model = build_bank(run.cell, 1, "hy-affrls").model
    truth = float(run.soc_true[k][0])
    i = run.current_A[k].copy()
    i[np.random.default_rng(0).random(i.shape[0]) < 0.05] = np.nan
    fit = fit_start_soc(run.t_s[k], i, run.voltages_V[k], model, np.array([truth + 0.05]))
    assert abs(fit.soc0[0] - truth) < 0.015, (fit.soc0, truth)
