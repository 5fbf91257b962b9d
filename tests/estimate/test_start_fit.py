"""The start SOC fitted over a record's first window (issue 11, "start from anywhere": a start
under load or still relaxing, which the first voltage misreads)."""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
import numpy.typing as npt
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from bmsid.config.cell import SocInit, load_cell_config
from bmsid.config.engine import build_bank, ocv_model
from bmsid.estimate import tau_grid
from bmsid.estimate.start_fit import fit_start_soc
from bmsid.estimate.tau_grid import branch_states
from bmsid.model.simulator import SimResult, simulate
from bmsid.offline import start_soc
from bmsid.offline.csvio import TesterData, write_tester_csv
from bmsid.offline.identify import IdentifySpec, identify_file
from bmsid.offline.outputs import soc_init_text
from bmsid.offline.start_soc import WINDOW_FIT, fitted_start_soc, start_head
from bmsid.profiles import dst_current
from bmsid.samples import SampleBlock
from bmsid.synthetic import TRUTH, SyntheticRun, paper_dst_case

FloatArray = npt.NDArray[np.float64]


def _mid_drive(start_s: int, n_cells: int = 1) -> tuple[object, slice]:
    spread = np.linspace(1.0, 1.3, n_cells)
    run = paper_dst_case(start_s + 3000, soc0=0.9, r0_spread=spread)
    return run, slice(start_s, None)


def _csv(path: Path, run: SyntheticRun, part: slice) -> Path:
    """``run``'s samples ``part`` as a one-cell tester CSV, its time from 0."""
    write_tester_csv(
        TesterData(t_s=run.t_s[part] - run.t_s[part][0], current_A=run.current_A[part],
                   cell_voltages_V=run.voltages_V[part], cell_names=["voltage_V"]),
        path,
    )  # fmt: skip
    return path


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
        path = _csv(tmp_path / f"{name}.csv", run, part)
        res = identify_file(path, IdentifySpec(cell=run.cell, variant="hy-affrls-lpso"))
        first = res.first_tick()
        assert first is not None
        if name == "loaded":
            assert res.soc_init_method == WINDOW_FIT
            assert abs(float(first["soc"][0][0]) - truth) < 0.015
            assert res.start_branch_V is not None and res.start_branch_V[0] > 0.01
            assert "; RC branches from " in soc_init_text(res)
        else:
            assert res.soc_init_method == "ocv_at_rest"
            assert res.start_branch_V is None  # at rest and relaxed: empty branches


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


def _entered_under_load(start_s: int) -> tuple[SimResult, FloatArray, FloatArray, slice]:
    """The paper cell's DST from 90 %, noise-free, entered ``start_s`` in (truth kept)."""
    cell = paper_dst_case(10).cell
    t = np.arange(start_s + 3000, dtype=np.float64)
    i = dst_current(t, 140.0)
    sim = simulate(
        t, i, ocv_model(cell), capacity_Ah=cell.capacity_Ah, gamma=cell.hysteresis.gamma,
        soc0=0.9, **{k: TRUTH[k] for k in ("R0_ohm", "R1_ohm", "tau1_s", "R2_ohm", "tau2_s")},
    )  # fmt: skip
    return sim, t, i, slice(start_s, None)


def test_a_start_under_load_finds_the_voltage_its_branches_hold() -> None:
    """Entered mid-DST, the two RC branches hold 24-28 mV; the fit finds their sum within
    2 mV (the split between the two follows its time-constant grid)."""
    cell = paper_dst_case(10).cell
    model = build_bank(cell, 1, "hy-affrls").model
    for start_s in (1500, 2016):
        sim, t, i, k = _entered_under_load(start_s)
        truth_V = sim.U1_V[0, start_s] + sim.U2_V[0, start_s]
        assert truth_V > 0.02
        z = float(sim.soc[start_s])
        fit = fit_start_soc(t[k], i[k], sim.v_V.T[k], model, np.array([z + 0.03]))
        assert abs(fit.branch_V[0].sum() - truth_V) < 2e-3, (start_s, fit.branch_V, truth_V)


def test_a_bank_started_from_the_fit_opens_with_its_branches() -> None:
    """A bank given the fitted branch voltages holds them across its start R1, R2, and its
    model tracks the record from the first minutes: the first 300 s of the paper cell entered
    2,016 s into DST have a third of the model error of the same start with empty branches
    (whose error the first updates put into R0)."""
    run, k = _mid_drive(2016)
    block = SampleBlock.from_arrays(run.t_s[k], run.current_A[k], run.voltages_V[k])
    fitted = fitted_start_soc([block], run.cell, None, None)
    assert fitted is not None and np.all(fitted.branch_V > 0)
    rmse = {}
    for name, branch in (("seeded", fitted.branch_V), ("empty", None)):
        bank = build_bank(run.cell, 1, "hy-affrls-lpso", soc0=fitted.soc0, branch0_V=branch)
        if branch is not None:
            p = bank.params.outputs()
            held = np.stack([bank.params.x1 * p["R1_ohm"], bank.params.x2 * p["R2_ohm"]], 1)
            np.testing.assert_allclose(held, branch, rtol=1e-12)
        out = bank.update_block(block)
        rmse[name] = float(np.sqrt(np.mean(out["v_error_V"][:300] ** 2)))
    assert rmse["seeded"] < 0.6 * rmse["empty"], rmse


def test_identify_with_soc0_keeps_it_and_fits_only_the_branches(tmp_path: Path) -> None:
    """``identify --soc0`` on the loaded start: the SOC is the one given (no dz fitted), the
    branches start where the fit finds them, and the run says so."""
    run, k = _mid_drive(2016)
    truth = float(run.soc_true[k][0])
    path = tmp_path / "loaded.csv"
    write_tester_csv(
        TesterData(t_s=run.t_s[k] - run.t_s[k][0], current_A=run.current_A[k],
                   cell_voltages_V=run.voltages_V[k], cell_names=["voltage_V"]),
        path,
    )  # fmt: skip
    res = identify_file(path, IdentifySpec(cell=run.cell, variant="hy-affrls-lpso", soc0=truth))
    first = res.first_tick()
    assert first is not None and float(first["soc"][0][0]) == truth
    assert res.soc_init_method == "given"
    assert res.start_branch_V is not None and res.start_branch_V[0] > 0.01
    assert soc_init_text(res).startswith(f"initial SOC {100 * truth:.1f} %: given by --soc0; RC")


def test_a_config_fixed_start_soc_gets_no_fit() -> None:
    """A cell config's fixed ``soc0`` is a standing guess, not the record's start: a loaded
    start is not fitted then (a wrong SOC would be fitted into the branches)."""
    run, k = _mid_drive(2016)
    block = SampleBlock.from_arrays(run.t_s[k], run.current_A[k], run.voltages_V[k])
    fixed = run.cell.model_copy(update={"soc_init": SocInit(policy="fixed", soc0=0.6)})
    assert fitted_start_soc([block], fixed, None, None) is None
    assert fitted_start_soc([block], run.cell, None, None) is not None


def _rested(soc0: float, h0: float) -> tuple[SyntheticRun, SampleBlock]:
    run = paper_dst_case(soc0=soc0, h0=h0, v_noise_V=0.5e-3)
    return run, SampleBlock.from_arrays(run.t_s, run.current_A, run.voltages_V)


def test_a_rested_start_gets_the_hysteresis_state_the_window_shows() -> None:
    """A rested first voltage reads OCV + M h0 (M 15 mV here): after a discharge (h0 = -1) the
    first voltage read 1.5-3 SOC points low, after a charge high. The fit along that voltage's
    SOC-h0 line finds h0 and the SOC within 0.1 point; a start with h0 = 0 is not fitted (the
    window shows nothing h = 0 does not explain) and keeps its first voltage."""
    for soc0, h0 in ((0.7, -1.0), (0.45, -1.0), (0.7, 1.0), (0.45, 1.0)):
        run, block = _rested(soc0, h0)
        fit = fitted_start_soc([block], run.cell, None, None)
        assert fit is not None and fit.h0 is not None, (soc0, h0)
        assert abs(fit.h0[0] - h0) < 0.1, (soc0, h0, fit.h0)
        assert abs(fit.soc0[0] - soc0) < 0.001, (soc0, h0, fit.soc0)
    run, block = _rested(0.7, 0.0)
    assert fitted_start_soc([block], run.cell, None, None) is None


def test_identify_from_a_rest_after_a_discharge_keeps_soc_and_dc_resistance(
    tmp_path: Path,
) -> None:
    """``identify`` without ``--soc0`` on the paper cell's DST from 45 % after a discharge
    (h0 = -1): SOC within 0.2 point and R0 + R1 + R2 within 3 % over the second half (with
    h started at 0: SOC 3.0 points low all through, R0 + R1 + R2 -27 %: the slow branch took
    the OCV error)."""
    run, _ = _rested(0.45, -1.0)
    path = _csv(tmp_path / "rested.csv", run, slice(None))
    res = identify_file(path, IdentifySpec(cell=run.cell, variant="hy-affrls-lpso"))
    assert res.soc_init_method == WINDOW_FIT
    assert res.start_h is not None and abs(res.start_h[0] + 1.0) < 0.1
    text = soc_init_text(res)
    assert "hysteresis state -1.00" in text and "RC branches" not in text, text
    trace = res.trace
    assert trace is not None
    half = slice(trace.n_ticks // 2, None)
    soc_err = trace["soc"][half, 0] - run.soc_true[: trace.n_ticks][half]
    assert np.max(np.abs(soc_err)) < 0.002
    r_dc = trace["R0_ohm"] + trace["R1_ohm"] + trace["R2_ohm"]
    truth = TRUTH["R0_ohm"] + TRUTH["R1_ohm"] + TRUTH["R2_ohm"]
    assert np.median(np.abs(r_dc[half, 0] / truth - 1.0)) < 0.03


def test_an_lfp_start_at_rest_is_read_through_its_hysteresis_state() -> None:
    """LFP (the shipped A123 config's curve and half-gap, known-truth 2RC model): its flat middle
    (1 mV per SOC point) turns the 15 mV half-gap into 11-19 SOC points, which the first voltage
    read with h = 0 carried through the discharge (from 50 % after a charge: 22.7 points off,
    R0 + R1 + R2 18 times its value). The fitted (SOC, h0) start: within 0.5 point, after a
    discharge too (where h = 0 has no physical fit at all), and SOC stays within 0.5 point."""
    cell = load_cell_config(Path(__file__).resolve().parents[2] / "configs/cells/a123_lfp_25C.toml")
    truth = {"R0_ohm": 0.012, "R1_ohm": 0.006, "tau1_s": 25.0, "R2_ohm": 0.008, "tau2_s": 500.0}
    n = int(0.45 * cell.capacity_Ah * 3600 / 1.5)
    t = np.arange(n, dtype=np.float64)
    i = dst_current(t, 4.0)
    for h0 in (-1.0, 1.0):
        sim = simulate(t, i, ocv_model(cell), capacity_Ah=cell.capacity_Ah,
                       gamma=cell.hysteresis.gamma, soc0=0.5, h0=h0,
                       play=cell.hysteresis_law == "play", **truth)  # fmt: skip
        rng = np.random.default_rng(1)
        v = sim.v_V.T + rng.normal(0.0, 0.5e-3, (n, 1))
        block = SampleBlock.from_arrays(t, i + rng.normal(0.0, 0.01, n), v)
        fit = fitted_start_soc([block], cell, None, None)
        assert fit is not None and fit.h0 is not None, h0
        assert abs(fit.h0[0] - h0) < 0.1 and abs(fit.soc0[0] - 0.5) < 0.005, (h0, fit)
        bank = build_bank(cell, 1, "hy-affrls-lpso", soc0=fit.soc0, branch0_V=fit.branch_V,
                          h0=fit.h0)  # fmt: skip
        est = bank.update_block(block)
        assert np.max(np.abs(est["soc"][:, 0] - sim.soc[: est.n_ticks])) < 0.005, h0


@settings(max_examples=40, deadline=None)
@given(
    st.lists(st.floats(-200.0, 200.0), min_size=2, max_size=300),
    st.floats(0.05, 30.0),
    st.lists(st.floats(0.5, 5000.0), min_size=1, max_size=12),
)
def test_branch_states_of_an_even_record_are_the_zoh_recursion(
    current: list[float], dt_s: float, taus: list[float]
) -> None:
    """The filter an evenly sampled record takes is Eq. 8's recursion, to rounding."""
    i, tau = np.array(current), np.array(taus)
    dt = np.full(i.shape[0], dt_s)
    x = branch_states(i, dt, tau)
    a = np.exp(-dt_s / tau)
    ref = np.zeros((tau.shape[0], i.shape[0] + 1))
    for k in range(i.shape[0]):
        ref[:, k + 1] = a * ref[:, k] + (1.0 - a) * i[k]
    np.testing.assert_allclose(x, ref, rtol=1e-9, atol=1e-9)


def test_the_pairs_solved_in_chunks_give_the_same_start(monkeypatch: pytest.MonkeyPatch) -> None:
    """A fast record's window holds many samples: its tau pairs are solved a chunk at a time
    (``SOLVE_BYTES``), with the same result as all at once."""
    run, block = _rested(0.45, -1.0)
    whole = fitted_start_soc([block], run.cell, None, None)
    monkeypatch.setattr(tau_grid, "SOLVE_BYTES", 1)  # one pair a solve
    chunked = fitted_start_soc([block], run.cell, None, None)
    assert whole is not None and chunked is not None
    np.testing.assert_allclose(chunked.soc0, whole.soc0, rtol=0, atol=1e-12)
    np.testing.assert_allclose(np.asarray(chunked.h0), np.asarray(whole.h0), rtol=0, atol=1e-12)


def test_a_cell_whose_window_shows_no_h0_takes_its_packs() -> None:
    """Cells in series share one history: a cell whose noisy tap (5 mV) hides its h0 takes the
    median of the others' along its own first voltage's line; where most cells show none, none
    keeps a fit (the engine's start, as before)."""
    run = paper_dst_case(soc0=0.7, h0=-1.0, v_noise_V=0.5e-3, r0_spread=np.ones(3))
    v = run.voltages_V.copy()
    v[:, 2] += np.random.default_rng(5).normal(0.0, 5e-3, v.shape[0])
    fit = fitted_start_soc([SampleBlock.from_arrays(run.t_s, run.current_A, v)], run.cell, None,
                           None)  # fmt: skip
    assert fit is not None and fit.h0 is not None and fit.rmse_V is not None
    assert np.isnan(fit.rmse_V[2]) and np.all(np.isfinite(fit.rmse_V[:2]))  # not its own fit
    np.testing.assert_allclose(fit.h0, -1.0, atol=0.1)
    assert fit.h0[2] == np.median(fit.h0[:2])
    np.testing.assert_allclose(fit.soc0[:2], 0.7, atol=0.002)
    assert abs(fit.soc0[2] - 0.7) < 0.006  # its first voltage read 1.5 points low, +-5 mV
    v[:, 1] += np.random.default_rng(6).normal(0.0, 5e-3, v.shape[0])  # now two of three
    block = SampleBlock.from_arrays(run.t_s, run.current_A, v)
    assert fitted_start_soc([block], run.cell, None, None) is None


def test_a_flat_point_of_the_curve_gets_no_h0_fit_and_no_warning(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Where the OCV's slope at the start is 0 (a table's flat point) the first voltage's line
    has no SOC direction: no fit, quietly (no division by zero)."""
    run, _ = _rested(0.7, -1.0)
    model = build_bank(run.cell, 1, "hy-affrls").model
    monkeypatch.setattr(type(model.ocv), "docv_dz", lambda self, z: np.zeros_like(z))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        fit = fit_start_soc(run.t_s, run.current_A, run.voltages_V, model, np.array([0.69]),
                            rested=True)  # fmt: skip
    assert np.isnan(fit.soc0).all() and fit.h0[0] == 0.0


def _after_a_rest(rest_s: int, soc0: float, h0: float) -> tuple[FloatArray, FloatArray, SimResult]:
    """The paper cell's DST after ``rest_s`` of rest (1 s samples; 0.5 mV, 50 mA noise)."""
    cell = paper_dst_case(10).cell
    t = np.arange(rest_s + 3000, dtype=np.float64)
    i = np.where(t < rest_s, 0.0, dst_current(t - rest_s, 140.0))
    truth = {k: TRUTH[k] for k in ("R0_ohm", "R1_ohm", "tau1_s", "R2_ohm", "tau2_s")}
    sim = simulate(t, i, ocv_model(cell), capacity_Ah=cell.capacity_Ah,
                   gamma=cell.hysteresis.gamma, soc0=soc0, h0=h0, **truth)  # fmt: skip
    rng = np.random.default_rng(3)
    return t, i + rng.normal(0.0, 0.05, t.shape[0]), sim


def test_a_long_rest_first_moves_the_window_to_the_load() -> None:
    """A car parked for half an hour, then driven (the 3-day records open so): the first 20 min
    are all rest and showed nothing; the window now starts a minute before the load, and h0
    and SOC come out as at once (h0 = -1 after a discharge: SOC within 0.2 point)."""
    cell = paper_dst_case(10).cell
    for rest_s in (0, 1800, 5 * 3600):
        t, i, sim = _after_a_rest(rest_s, 0.7, -1.0)
        v = sim.v_V.T + np.random.default_rng(4).normal(0.0, 0.5e-3, (t.shape[0], 1))
        block = SampleBlock.from_arrays(t, i, v)
        head = start_head([block.slice(a, a + 600) for a in range(0, len(block), 600)], 0.7)
        assert head is not None and head.t_s[-1] >= rest_s - 60 + 1200 - 1, rest_s
        fit = fitted_start_soc([block], cell, None, None)
        assert fit is not None and fit.h0 is not None, rest_s
        assert abs(fit.h0[0] + 1.0) < 0.1 and abs(fit.soc0[0] - 0.7) < 0.002, (rest_s, fit)


def test_the_head_after_a_long_rest_is_bounded(monkeypatch: pytest.MonkeyPatch) -> None:
    """Past the first window a long rest is read only up to ``MAX_HEAD_CELL_SAMPLES`` (a large,
    fast pack parked for hours); the first window itself always whole."""
    t, i, sim = _after_a_rest(5 * 3600, 0.7, -1.0)
    block = SampleBlock.from_arrays(t, i, sim.v_V.T)
    parts = [block.slice(a, a + 300) for a in range(0, len(block), 300)]
    monkeypatch.setattr(start_soc, "MAX_HEAD_CELL_SAMPLES", 1500)
    head = start_head(parts, 0.7)
    assert head is not None and head.t_s[-1] == pytest.approx(1500.0, abs=300.0)
    monkeypatch.setattr(start_soc, "MAX_HEAD_CELL_SAMPLES", 10**9)
    head = start_head(parts, 0.7)
    assert head is not None and head.t_s[-1] >= 5 * 3600 - 60 + 1200 - 1
