"""The SOC observer (estimate/observer.py, capacity.py): offset, start, anchors, checkpoints.

Records are the first hours of the multi-day known-truth generator (``synthetic/multiday.py``:
07:00 rest or auxiliary load, 07:30-09:00 drive, rest, 17:00 drive, 20:00 charge). The bank
ticks every 10 s (the tuning's upper bound) so a 14 h record costs ~5000 ticks; SOC is still
coulomb-counted at the raw 1 s rate.
"""

from __future__ import annotations

import functools
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st

from bmsid.config.cell import CellConfig, SocInit, load_cell_config, paper_cell
from bmsid.config.engine import build_bank, ocv_model
from bmsid.estimate.bank import EstimatorBank
from bmsid.estimate.capacity import REJECT_REL, CapacityTracker
from bmsid.estimate.fields import FIELD_NAMES
from bmsid.estimate.observer import ObserverState
from bmsid.estimate.observer_tuning import ObserverTuning
from bmsid.estimate.tuning import EstimatorTuning, Variant
from bmsid.estimate.types import EstimateBlock, Quality
from bmsid.model.simulator import simulate
from bmsid.profiles import dst_current
from bmsid.samples import SampleBlock
from bmsid.synthetic import TRUTH
from bmsid.synthetic.multiday import (
    DayPlan,
    MultidayOptions,
    MultidayRecord,
    generate,
    reference_cell,
)

TUN = EstimatorTuning(id_period_s=10.0)
TUN_COULOMB = TUN.model_copy(update={"observer": ObserverTuning(enabled=False)})
#: h as Plett's Eq. 5-6 alone makes it (the observer's hysteresis error not estimated).
TUN_H_EXACT = TUN.model_copy(update={"observer": ObserverTuning(hysteresis_error=False)})
PLAN = DayPlan()
H = 3600
DRIVE_END_S = PLAN.first_drive_s + PLAN.drive_s  # 09:00, the first drive's end


@functools.cache
def _record(hours: float, offset_A: float = 0.0, start_load_A: float = 0.0) -> MultidayRecord:
    opt = MultidayOptions(n_days=1, duration_s=int(hours * H), current_offset_A=offset_A,
                          start_load_A=start_load_A)  # fmt: skip
    return generate(opt)


def _block(rec: MultidayRecord, a: int = 0, b: int | None = None) -> SampleBlock:
    return SampleBlock.from_arrays(rec.t_s, rec.current_A, rec.voltage_V[:, None]).slice(
        a, rec.n_samples if b is None else b
    )


def _soc_error(rec: MultidayRecord, out: EstimateBlock) -> np.ndarray[Any, np.dtype[np.float64]]:
    """Estimated minus true SOC at each tick (fraction)."""
    k = np.searchsorted(rec.t_s, out.t_s)
    return np.asarray(out["soc"][:, 0] - rec.truth.soc[k], dtype=np.float64)


def _at(out: EstimateBlock, t_s: float) -> int:
    """Index of the first tick at or after ``t_s``."""
    return int(np.searchsorted(out.t_s, t_s))


# ----------------------------------------------------------------------------- current offset
@functools.cache
def _offset_runs() -> tuple[MultidayRecord, EstimateBlock, EstimateBlock]:
    """14 h with a +0.5 A sensor offset: a drive, the day's rest, the second drive and the
    first hour of the charge; with the observer and as a plain coulomb count."""
    rec = _record(14.0, offset_A=0.5)
    assert rec.truth.phase[-1] == 2  # ends in the charge
    obs = build_bank(rec.cell, 1, tuning=TUN, soc0=0.93).update_block(_block(rec))
    plain = build_bank(rec.cell, 1, tuning=TUN_COULOMB, soc0=0.93).update_block(_block(rec))
    return rec, obs, plain


def test_current_offset_is_learnt_and_soc_stays_on_the_truth() -> None:
    rec, obs, _ = _offset_runs()
    b_end = float(obs["current_offset_A"][-1, 0])
    assert b_end == pytest.approx(0.5, abs=0.1), f"published offset {b_end:.3f} A, truth 0.5 A"
    err = _soc_error(rec, obs)
    assert abs(err[-1]) < 0.02, f"SOC error at the end {err[-1]:+.4f}"


def test_the_offset_does_not_overshoot_at_the_first_rest() -> None:
    """At the first rest after the drive every 20 s update read the rest's few mV of systematic
    model error (the SOC error, the branches' residue) as white noise, and the offset's IR term
    (dv/db = R0 + R1 + R2, ~2 mV per A) turned it into offset: 1.05 A 35 min into the rest here
    for a true 0.5 A. The rest's reading is a measurement of the offset now, once a rest
    (``rest_anchor.draw_update``): the sensor reads its offset plus a draw within the rest
    limit."""
    _, obs, _ = _offset_runs()
    after = obs.t_s >= DRIVE_END_S
    b = obs["current_offset_A"][after, 0]
    assert b.max() <= 0.75, f"offset up to {b.max():.2f} A after the drive, truth 0.5 A"


def test_without_the_observer_the_offset_drifts_soc_much_further() -> None:
    rec, obs, plain = _offset_runs()
    e_obs, e_plain = abs(_soc_error(rec, obs)[-1]), abs(_soc_error(rec, plain)[-1])
    # 0.5 A over 14 h is 7 Ah = 10 points of a 70 Ah cell
    assert e_plain > 0.08, f"the plain count drifted only {e_plain:.4f}"
    assert e_obs < 0.25 * e_plain, f"observer {e_obs:.4f} vs plain count {e_plain:.4f}"
    np.testing.assert_array_equal(plain["current_offset_A"], 0.0)


@functools.cache
def _sense_wire_runs(agree_sigmas: float) -> tuple[MultidayRecord, EstimateBlock, EstimateBlock]:
    """A 4-cell pack of one cell (12 h: a drive, the day's rest), each cell with its own 1 mV
    noise; in the second run cell 2's voltage reads +50 mV on every tenth sample from the
    fifth on (an intermittent sense wire), 1 s ticks, no ``soc0``."""
    rec = _record(12.0)
    n = 4
    v = np.tile(rec.voltage_V[:, None], (1, n))
    v += np.random.default_rng(1).normal(0.0, 1e-3, v.shape)
    faulty = v.copy()
    faulty[5::10, 2] += 0.05
    tun = EstimatorTuning(observer=ObserverTuning(agree_sigmas=agree_sigmas))
    runs = [
        build_bank(rec.cell, n, tuning=tun).update_block(
            SampleBlock.from_arrays(rec.t_s, rec.current_A, volts)
        )
        for volts in (v, faulty)
    ]
    return rec, runs[0], runs[1]


@pytest.mark.parametrize("agree_sigmas", [3.0, 1e9])
def test_one_cells_sensing_fault_does_not_move_the_offset_or_the_other_cells(
    agree_sigmas: float,
) -> None:
    """The offset is the pack's (one sensor): one cell's glitches must not teach it, nor move
    the good cells' SOC through it (``ObserverTuning.agree_sigmas``); before, the offset ran to
    its 3.5 A bound here and the good cells' SOC 6 points off. Without the agreement test
    (1e9) the offset still ran to 1.94 A and the good cells' SOC 6 points off until the
    hysteresis map's uncertainty was in every update and rests held h (why either does it is
    not measured): now +0.047 A, within 0.0065; both must hold."""
    rec, clean, faulty = _sense_wire_runs(agree_sigmas)
    k = np.searchsorted(rec.t_s, faulty.t_s)
    good = [0, 1, 3]
    err = np.abs(faulty["soc"][:, good] - rec.truth.soc[k][:, None]).max()
    err_clean = np.abs(clean["soc"][:, good] - rec.truth.soc[k][:, None]).max()
    b = float(faulty["current_offset_A"][-1, 0])
    assert abs(b) < 0.1 and err < err_clean + 0.005, (
        f"BUG observer: one cell's +50 mV glitches moved the pack: offset {b:+.3f} A (truth 0, "
        f"clean {float(clean['current_offset_A'][-1, 0]):+.3f}), the good cells' SOC error up "
        f"to {err:.4f} (clean {err_clean:.4f})"
    )


# ----------------------------------------------------------------------------- start anywhere
def test_start_under_load_without_soc0_is_ocv_ir_corrected_and_tracks() -> None:
    """07:00-07:30 under a 1.5 A auxiliary load (above the 0.01 C = 0.7 A rest limit), then
    the drive: SOC from the first voltage, IR-corrected, as good as the true start."""
    load_A = 1.5
    rec = _record(3.0, start_load_A=load_A)
    assert load_A > rec.cell.soc_init.rest_current_C * rec.cell.capacity_Ah
    free = build_bank(rec.cell, 1, tuning=TUN)
    out = free.update_block(_block(rec))
    assert free.soc_init_method == "ocv_ir_corrected"
    err = _soc_error(rec, out)
    after_1h = err[_at(out, H) :]
    assert np.abs(after_1h).max() < 0.02, f"SOC error after the first hour up to {after_1h}"
    known = build_bank(rec.cell, 1, tuning=TUN, soc0=float(rec.truth.soc[0]))
    ref = known.update_block(_block(rec))

    def rmse(o: EstimateBlock) -> float:
        return float(np.sqrt(np.nanmean(o["v_error_V"] ** 2)))

    assert rmse(out) == pytest.approx(rmse(ref), abs=1e-3), (rmse(out), rmse(ref))


def test_a_start_mid_drive_without_rests_does_not_freeze_the_parameters_on_a_bound() -> None:
    """An hour of DST entered 16 s into the cycle (under load, no rest in the record): the
    start SOC is read under load, its std keeps the learn gate shut for most of the hour, and
    the first swarm (fitted while SOC was still uncertain) put tau2 on a bound. A parameter on
    a bound is not worth protecting from a SOC error: the cell learns on, and the model tracks
    (before: held on the bound from 450 s to the end, RMSE 20.7 mV against 1.7 mV with the
    start given)."""
    cell = paper_cell(M_V=0.015, gamma=30.0)
    t = np.arange(3600, dtype=np.float64)
    i = dst_current(t + 16.0, 140.0)
    sim = simulate(
        t, i, ocv_model(cell), capacity_Ah=cell.capacity_Ah, gamma=30.0, soc0=0.8,
        **{k: TRUTH[k] for k in ("R0_ohm", "R1_ohm", "tau1_s", "R2_ohm", "tau2_s")},
    )  # fmt: skip
    rng = np.random.default_rng(1)
    block = SampleBlock.from_arrays(
        t, i + rng.normal(0.0, 0.05, t.size), sim.v_V.T + rng.normal(0.0, 1e-3, (t.size, 1))
    )
    assert abs(i[0]) > 0.1 * cell.capacity_Ah  # starts under load

    def run(soc0: float | None) -> tuple[float, float]:
        bank = build_bank(cell, 1, "hy-affrls-lpso", EstimatorTuning(), soc0=soc0)
        out = bank.update_block(block)
        after = slice(out.t_s.size // 10, None)
        rmse = float(np.sqrt(np.nanmean(out["v_error_V"][after] ** 2)))
        held = float(np.mean(out.quality[after, 0] == int(Quality.OUT_OF_BOUNDS)))
        return rmse, held

    rmse_free, held = run(None)
    rmse_known, _ = run(0.8)
    assert rmse_free < rmse_known + 1e-3, (rmse_free, rmse_known)
    assert held < 0.5, f"held on a bound in {held:.0%} of the ticks after the first 10 %"


# ----------------------------------------------------------------------------- wrong start
@functools.cache
def _wrong_start_run() -> tuple[MultidayRecord, EstimatorBank, EstimateBlock]:
    """A cell config whose fixed start SOC is 0.2 below the truth (0.73 vs 0.93); 07:00-10:00:
    rest, the first drive, an hour of rest."""
    rec = _record(3.0)
    cell: CellConfig = rec.cell.model_copy(
        update={"soc_init": SocInit(policy="fixed", soc0=rec.options.soc0 - 0.2)}
    )
    bank = build_bank(cell, 1, tuning=TUN)
    return rec, bank, bank.update_block(_block(rec))


def test_a_wrong_fixed_start_converges_by_the_end_of_the_first_drive_and_rest() -> None:
    rec, bank, out = _wrong_start_run()
    assert bank.soc_init_method == "config"
    err = _soc_error(rec, out)
    assert err[0] == pytest.approx(-0.2, abs=1e-3)
    assert out.t_s[-1] >= DRIVE_END_S + H - 10
    # 2.2 points with the hysteresis scale identified, 3.1 with it fixed (the default since
    # M is learnt at rests): the first drive's slow branch absorbs part of the SOC error
    # (tau2 ~2600 s) and the 1 h rest is then too short for an anchor (3 tau2).
    assert abs(err[-1]) < 0.035, (
        f"BUG observer: SOC error {err[-1]:+.4f} after the first drive and 1 h rest; current "
        f"offset {out['current_offset_A'][-1, 0]:+.2f} A (truth 0), tau2 "
        f"{out['tau2_s'][-1, 0]:.0f} s (truth 600), anchors {bank.counters['anchors']}: see "
        f"test_a_wrong_start_is_not_learnt_as_a_current_offset"
    )


def test_a_record_too_little_excited_to_converge_still_corrects_its_soc() -> None:
    """Six hours of a C/20 constant-current discharge (3.5 A) of the reference cell from 90 %,
    1 mV of noise, with a cell config that fixes the start at 80 %: no current step, so the
    parameters never converge. After ``unconverged_wait_s`` (30 min) the observer corrects SOC
    through the start values anyway; it used to skip such a cell until an anchor: the 10-point
    error stayed to the end (0 updates, published std 31 points)."""
    cell = reference_cell()
    n = 6 * 360
    t = np.arange(n) * 10.0
    i = np.full(n, 3.5)
    sim = simulate(t, i, ocv_model(cell), capacity_Ah=cell.capacity_Ah,
                   gamma=cell.hysteresis.gamma, soc0=0.9, **TRUTH)  # fmt: skip
    v = sim.v_V[0] + np.random.default_rng(5).normal(0.0, 1e-3, n)
    fixed = cell.model_copy(update={"soc_init": SocInit(policy="fixed", soc0=0.8)})
    bank = build_bank(fixed, 1, tuning=TUN)
    out = bank.update_block(SampleBlock.from_arrays(t, i, v[:, None]))
    assert not (out.quality[:, 0] == Quality.CONVERGED).any()  # never converged
    err = out["soc"][:, 0] - sim.soc[np.searchsorted(t, out.t_s)]
    assert abs(err[0]) == pytest.approx(0.1, abs=2e-3)
    assert abs(err[_at(out, 1700.0)]) > 0.09  # nothing before the wait
    late = err[_at(out, 2 * H) :]
    assert np.abs(late).max() < 0.02, f"SOC error after 2 h up to {np.abs(late).max():.4f}"
    assert out["soc_std"][-1, 0] < 0.03


def test_a_wrong_start_is_not_learnt_as_a_current_offset() -> None:
    """The true offset is 0. The first anchor (07:15, rest) must correct SOC, not move the
    pack's current offset, which then miscounts every cell for the whole drive."""
    rec, _, out = _wrong_start_run()
    err = _soc_error(rec, out)
    drive = (out.t_s >= PLAN.first_drive_s) & (out.t_s <= DRIVE_END_S)
    b_max = float(np.abs(out["current_offset_A"][drive, 0]).max())
    e_max = float(np.abs(err[drive]).max())
    std = float(out["soc_std"][drive, 0][np.argmax(np.abs(err[drive]))])
    assert b_max < 1.0, (
        f"BUG observer: a 0.2 start SOC error was pushed into the current offset: "
        f"|offset| reached {b_max:.2f} A in the drive (truth 0; prior std 0.7 A, bound 3.5 A)"
    )
    # 3.25 points measured at 60 s updates: the 2 points from the first hour are not
    # met after a 20-point wrong start (README, "State over days"); this guards the 4.
    assert e_max < 0.04, (
        f"BUG observer: SOC error up to {e_max:+.4f} in the first drive after the start anchor "
        f"(soc_std published there {std:.4f})"
    )


# ----------------------------------------------------------------------------- restart
#: Downtime 08:30-09:30 (a 1 h gap over the last half hour of the drive and the first half
#: hour of the rest): the count misses the drive's end, the first voltage after it is rested.
GAP = (DRIVE_END_S - H // 2, DRIVE_END_S + H // 2)


@functools.cache
def _restart_run() -> tuple[MultidayRecord, float, EstimatorBank, EstimateBlock]:
    rec = _record(3.5)
    before = build_bank(rec.cell, 1, tuning=TUN, soc0=0.93)
    z_before = float(before.update_block(_block(rec, 0, GAP[0]))["soc"][-1, 0])
    after = build_bank(rec.cell, 1, tuning=TUN, soc0=0.93)
    after.load_state_dict(before.state_dict())
    assert after.counters["reanchors"] == 0
    return rec, z_before, after, after.update_block(_block(rec, GAP[1]))


def test_a_restart_after_downtime_reanchors_soc_toward_the_truth() -> None:
    rec, z_before, bank, out = _restart_run()
    missed = z_before - float(rec.truth.soc[GAP[1]])  # the plain count's error after the gap
    assert missed > 0.1, f"the gap hid only {missed:.3f} of SOC"
    assert bank.counters["gaps"] == 1
    assert bank.counters["reanchors"] == 1
    err = _soc_error(rec, out)
    assert abs(err[0]) < abs(missed), f"after the re-anchor {err[0]:+.4f}, count {missed:+.4f}"


def test_a_reanchor_corrects_soc_not_the_current_offset() -> None:
    """After the gap the pack has rested 30 min: its raw voltage alone gives SOC to ~2 points.
    The re-anchor should land near that, leave the offset (truth 0) alone, and the SOC must
    stay there for the hour of rest that follows."""
    rec, z_before, bank, out = _restart_run()
    missed = z_before - float(rec.truth.soc[GAP[1]])
    z_v = float(ocv_model(rec.cell).soc_from_ocv(rec.voltage_V[GAP[1]]))
    err = _soc_error(rec, out)
    hour = out.t_s < GAP[1] + H
    worst = float(np.abs(err[hour]).max())
    assert worst < 0.04, (
        f"BUG observer: SOC error {err[0]:+.4f} right after the re-anchor and up to "
        f"{worst:+.4f} in the hour of rest after it (the count alone {missed:+.4f}, the raw "
        f"voltage alone {z_v - rec.truth.soc[GAP[1]]:+.4f}); published soc_std "
        f"{out['soc_std'][0, 0]:.4f}, current offset {out['current_offset_A'][0, 0]:+.2f} A "
        f"(truth 0), observer_gated {bank.counters['observer_gated']}"
    )


def test_capacity_is_not_measured_across_a_restart_gap() -> None:
    """The charge moved during downtime is unknown: the anchor before the gap and the one after
    it must not make a capacity measurement (the truth stays 70 Ah: no fade)."""
    rec = _record(3.5)
    gap = (DRIVE_END_S - 20 * 60, DRIVE_END_S + 40 * 60)  # misses 20 min of the drive
    before = build_bank(rec.cell, 1, tuning=TUN, soc0=0.93)
    before.update_block(_block(rec, 0, gap[0]))
    after = build_bank(rec.cell, 1, tuning=TUN, soc0=0.93)
    after.load_state_dict(before.state_dict())
    out = after.update_block(_block(rec, gap[1]))
    assert after.counters["reanchors"] == 1
    q = out["capacity_Ah"][:, 0]
    assert np.all(np.abs(q / 70.0 - 1.0) < 0.03), (
        f"BUG observer/capacity: an anchor pair across the restart gap measured the capacity: "
        f"{q.min():.2f} Ah after the restart (truth 70 Ah); the count missed "
        f"{float(before.state.z[0] - rec.truth.soc[gap[1]]):+.3f} of SOC in the gap"
    )


def test_the_cells_short_of_capacity_still_anchor_and_measure_it() -> None:
    """8 cells of the paper's 70 Ah type, 1.5 % to 3 % apart in capacity (the config says 70):
    a cell short of capacity reads its count's drift as a slow relaxation (tau2 1,000-1,700 s
    against 600), and 3 of its own tau2 outlasted the record's 50-60 min rests, so the cells
    short of capacity, the ones a user looks for, never measured it. In a pack the anchor waits
    3 x the cells' median tau2 at most (``ObserverTuning.anchor_rest_taus``)."""
    cell = paper_cell()
    capm = np.array([0.97, 1.03, 1.0, 0.985, 1.015, 0.97, 1.03, 1.0])
    t = np.arange(5 * H, dtype=float)
    i = dst_current(t - 600, 140.0)
    for a, b in ((0, 600), (6000, 9600), (15000, 18000)):
        i[a:b] = 0.0
    v = np.column_stack([
        simulate(t, i, ocv_model(cell), capacity_Ah=70.0 * m, gamma=30.0, soc0=0.9,
                 **TRUTH).v_V[0]
        for m in capm
    ])  # fmt: skip
    rng = np.random.default_rng(3)
    v += rng.normal(0.0, 1e-3, v.shape)
    bank = build_bank(cell, capm.size, "hy-affrls-lpso")
    out = bank.update_block(SampleBlock.from_arrays(t, i + rng.normal(0, 0.035, t.size), v))
    q, q_std = out["capacity_Ah"][-1], out["capacity_std_Ah"][-1]
    err = q / (70.0 * capm) - 1.0
    assert np.all(q_std < 0.5 * 0.05 * 70.0) and np.all(np.abs(err) < 0.03), (
        f"BUG observer/capacity: capacities {np.round(q, 2)} Ah (truth {70.0 * capm}), std "
        f"{np.round(q_std, 2)} (prior 3.5): cells never measured, or off by "
        f"{100 * np.abs(err).max():.1f} %; anchors {bank.counters['anchors']}"
    )


# ----------------------------------------------------------------------------- capacity
def _tracker(n: int = 2, q_Ah: float = 70.0) -> CapacityTracker:
    return CapacityTracker(np.full(n, q_Ah), 0.05, 0.2, 0.005)


def test_two_anchors_half_apart_measure_the_capacity() -> None:
    """Cell 0 moves 30 Ah between SOC 0.9 and 0.4 (a 60 Ah cell), cell 1 35 Ah (70 Ah); the
    fusion is the scalar Kalman update of the docstring, computed here by hand."""
    cap = _tracker()
    all_cells = np.ones(2, dtype=bool)
    z_var = np.full(2, 1e-6)
    cap.anchor(0.0, np.full(2, 0.9), z_var, 0.0, all_cells)
    cap.count(np.array([30.0, 35.0]))
    cap.anchor(7200.0, np.full(2, 0.4), z_var, 0.01, all_cells)
    meas = np.array([60.0, 70.0])
    var = meas**2 * 2e-6 / 0.25 + 0.01 * (2.0 / 0.5) ** 2
    prior = (0.05 * 70.0) ** 2 + (0.005 * 70.0) ** 2 * (7200.0 / 86400.0)
    gain = prior / (prior + var)
    np.testing.assert_allclose(cap.q_Ah, 70.0 + gain * (meas - 70.0), rtol=1e-12)
    np.testing.assert_allclose(cap.var_Ah2, (1.0 - gain) * prior, rtol=1e-12)
    assert cap.q_Ah[0] == pytest.approx(60.0, abs=0.2)  # the prior keeps 1 % of its weight
    assert cap.counters == {"capacity_updates": 2, "capacity_rejected": 0}


def test_a_charge_between_anchors_measures_the_same_capacity() -> None:
    cap = _tracker(1)
    one = np.ones(1, dtype=bool)
    cap.anchor(0.0, np.array([0.3]), np.array([1e-6]), 0.0, one)
    cap.count(-0.5 * 66.0)  # charge: negative throughput, SOC up by 0.5
    cap.anchor(3600.0, np.array([0.8]), np.array([1e-6]), 0.0, one)
    assert cap.q_Ah[0] == pytest.approx(66.0, abs=0.05)


def test_anchors_closer_than_min_dsoc_change_nothing() -> None:
    cap = _tracker()
    all_cells = np.ones(2, dtype=bool)
    cap.anchor(0.0, np.array([0.5, 0.5]), np.full(2, 1e-6), 0.0, all_cells)
    cap.count(10.0)
    q, var = cap.q_Ah.copy(), cap.var_Ah2.copy()
    cap.anchor(3600.0, np.array([0.5 - 0.19, 0.5 + 0.199]), np.full(2, 1e-6), 0.0, all_cells)
    np.testing.assert_array_equal(cap.q_Ah, q)
    np.testing.assert_array_equal(cap.var_Ah2, var)
    assert cap.counters == {"capacity_updates": 0, "capacity_rejected": 0}


def test_a_measurement_beyond_reject_rel_is_rejected() -> None:
    cap = _tracker(1)
    one = np.ones(1, dtype=bool)
    cap.anchor(0.0, np.array([0.9]), np.array([1e-6]), 0.0, one)
    cap.count(0.5 * 70.0 * (1.0 + REJECT_REL + 0.05))
    cap.anchor(3600.0, np.array([0.4]), np.array([1e-6]), 0.0, one)
    assert cap.q_Ah[0] == 70.0
    assert cap.counters == {"capacity_updates": 0, "capacity_rejected": 1}


def test_capacity_state_dict_round_trips_exactly() -> None:
    cap = _tracker(3)
    cap.anchor(10.0, np.array([0.9, 0.8, 0.7]), np.full(3, 1e-5), 0.0, np.array([1, 1, 0], bool))
    cap.count(np.array([30.0, 20.0, 5.0]))
    cap.anchor(5000.0, np.array([0.45, 0.5, 0.6]), np.full(3, 2e-5), 0.04, np.ones(3, bool))
    cap.count(np.array([1.0, 2.0, 3.0]))
    st_a = cap.state_dict()
    other = _tracker(3)
    other.load_state_dict(st_a)
    st_b = other.state_dict()
    assert st_a.keys() == st_b.keys()
    for k in st_a:
        np.testing.assert_array_equal(st_b[k], st_a[k], err_msg=k)
    for c in (cap, other):  # and both continue identically
        c.count(np.array([20.0, 20.0, 20.0]))
        c.anchor(9000.0, np.array([0.15, 0.2, 0.3]), np.full(3, 1e-5), 0.04, np.ones(3, bool))
    np.testing.assert_array_equal(other.q_Ah, cap.q_Ah)
    np.testing.assert_array_equal(other.var_Ah2, cap.var_Ah2)


anchor_step = st.tuples(
    st.floats(-80.0, 80.0),  # throughput since the previous anchor, Ah
    st.floats(0.0, 1.0),  # OCV SOC at the anchor
    st.floats(1e-8, 0.1),  # its variance
    st.floats(0.0, 25.0),  # offset variance, A^2
    st.floats(0.0, 5 * 86400.0),  # time since the previous anchor, s
    st.lists(st.booleans(), min_size=2, max_size=2),  # which cells anchor
)


@settings(max_examples=60, deadline=None)
@given(st.lists(anchor_step, min_size=1, max_size=12))
def test_capacity_stays_finite_positive_and_moves_within_reject_rel(
    steps: list[tuple[float, float, float, float, float, list[bool]]],
) -> None:
    """Whatever the anchors, each fusion moves the estimate by at most REJECT_REL of the
    estimate before it (its prior), and the first one stays within REJECT_REL of the config."""
    cap = _tracker()
    t = 0.0
    for dq, z, z_var, b_var, dt, cells in steps:
        cap.count(dq)
        t += dt
        q_before = cap.q_Ah.copy()
        cap.anchor(t, np.full(2, z), np.full(2, z_var), b_var, np.array(cells))
        assert np.all(np.isfinite(cap.q_Ah)) and np.all(cap.q_Ah > 0)
        assert np.all(np.isfinite(cap.var_Ah2)) and np.all(cap.var_Ah2 >= 0)
        assert np.all(np.abs(cap.q_Ah / q_before - 1.0) <= REJECT_REL + 1e-12)
        if cap.counters["capacity_updates"] <= 1:
            assert np.all(np.abs(cap.q_Ah / 70.0 - 1.0) <= REJECT_REL + 1e-12)


# ----------------------------------------------------------------------------- invariants
#: Short everything, so that updates, anchors, re-anchors and capacity measurements all happen
#: within the few hundred samples hypothesis can afford.
QUICK = EstimatorTuning(
    window_s=240.0, min_window_s=60.0, swarm_period_s=90.0, n_iter=4, n_iter_first=5,
    n_particles=6, excitation_C=0.0,
    observer=ObserverTuning(update_period_s=2.0, anchor_min_rest_s=5.0, anchor_rest_taus=0.02,
                            restart_gap_s=60.0, capacity_min_dsoc=0.02),
)  # fmt: skip
OCV_CELL = reference_cell()
OCV = ocv_model(OCV_CELL)

segment = st.tuples(
    st.sampled_from(["rest", "constant", "random", "nan", "garbage", "gap"]),
    st.integers(5, 60),
    st.floats(-200.0, 200.0),
)


def _hostile(
    segments: list[tuple[str, int, float]], n_cells: int, seed: int
) -> tuple[SampleBlock, int]:
    """1 s samples of random current segments; per-cell voltages from the simulator (each cell
    from its own SOC) with NaN and out-of-model voltages mixed in. Returns the block and a
    sample index to checkpoint at."""
    rng = np.random.default_rng(seed)
    t_parts, i_parts, kinds = [], [], []
    t0 = 0.0
    for kind, n, level in segments:
        step = np.ones(n)
        if kind == "gap":
            step[0] = 120.0
        t_parts.append(t0 + np.cumsum(step))
        t0 = float(t_parts[-1][-1])
        levels = {"rest": np.zeros(n), "constant": np.full(n, level),
                  "random": rng.normal(0.0, 60.0, n)}  # fmt: skip
        i_parts.append(levels.get(kind, rng.normal(level, 20.0, n)))
        kinds += [kind] * n
    t = np.concatenate(t_parts)
    i = np.concatenate(i_parts)
    kind_arr = np.array(kinds)
    v = np.empty((t.shape[0], n_cells))
    for c in range(n_cells):
        z0 = float(rng.uniform(0.1, 0.9))
        sim = simulate(t, i, OCV, capacity_Ah=70.0, R0_ohm=1.2e-3, R1_ohm=0.8e-3, tau1_s=32.0,
                       R2_ohm=1e-3, tau2_s=600.0, gamma=30.0, soc0=z0)  # fmt: skip
        v[:, c] = sim.v_V[0] + rng.normal(0.0, 1e-3, t.shape[0])
    bad = (kind_arr == "nan")[:, None] & (rng.random(v.shape) < 0.5)
    v[bad] = np.nan
    junk = (kind_arr == "garbage")[:, None] & (rng.random(v.shape) < 0.3)
    v[junk] = rng.uniform(2.0, 5.0, int(junk.sum()))
    i_meas = i + rng.normal(0.0, 0.05, i.shape[0])
    cut = int(rng.integers(1, t.shape[0]))
    return SampleBlock.from_arrays(t, i_meas, v), cut


def _check_observer(bank: EstimatorBank, out: EstimateBlock) -> None:
    obs = bank.state
    assert isinstance(obs, ObserverState)
    # An update clips SOC to [0, 1]; the count between updates may pass an end by the guard's
    # margin (a charge's last seconds past full), never more.
    m = bank.tuning.divergence_soc_margin
    # A cell without a valid voltage since its start publishes nothing (every field NaN).
    no_data = out.quality == Quality.NO_DATA
    assert all(np.all(np.isnan(col[no_data])) for col in out.cells.values())
    soc, std = out["soc"][~no_data], out["soc_std"][~no_data]
    assert np.all((soc >= -m) & (soc <= 1.0 + m)), (soc.min(), soc.max())
    assert np.all(np.isfinite(std) & (std >= 0.0))
    b_max = bank.tuning.observer.offset_max_C * float(np.mean(bank.model.capacity_Ah))
    assert np.all(np.abs(out["current_offset_A"][~no_data]) <= b_max * (1 + 1e-12))
    assert np.all(np.isfinite(obs.P))
    np.testing.assert_array_equal(obs.P, obs.P.T)
    assert np.all(np.diag(obs.P) >= 0.0)
    assert np.all(np.isfinite(obs.capacity.q_Ah) & (obs.capacity.q_Ah > 0.0))


@settings(max_examples=15, deadline=None)
@given(
    st.lists(segment, min_size=1, max_size=6),
    st.integers(1, 4),
    st.sampled_from(["hy-affrls", "non-hy-affrls"]),
    st.integers(0, 2**31 - 1),
)
# A parameter on a bound at the cut: its finding opens the next tick's learn gate, so the guard's
# bound bits are part of the checkpoint (they were not: the restored bank learnt differently).
@example([("constant", 7, -75.0), ("constant", 15, 3.0), ("rest", 16, 0.0)], 1, "hy-affrls", 0)
def test_observer_invariants_and_checkpoint_continuation(
    segments: list[tuple[str, int, float]], n_cells: int, variant: Variant, seed: int
) -> None:
    """SOC, its std, the offset and P stay sane on hostile input; a bank restored from a
    checkpoint continues exactly as the one it was taken from. (The swarm variant is left
    out of the exact continuation: its running swarms are not checkpointed by design.)"""
    block, cut = _hostile(segments, n_cells, seed)
    bank = build_bank(OCV_CELL, n_cells, variant, QUICK)
    _check_observer(bank, bank.update_block(block.slice(0, cut)))
    # Built as the original (soc0 is configuration, not state: a cell the guard resets after
    # the restore starts again by it).
    restored = build_bank(OCV_CELL, n_cells, variant, QUICK)
    restored.load_state_dict(bank.state_dict())
    rest = block.slice(cut, len(block))
    a, b = bank.update_block(rest), restored.update_block(rest)
    _check_observer(bank, a)
    np.testing.assert_array_equal(a.t_s, b.t_s)
    np.testing.assert_array_equal(a.quality, b.quality)
    for name in FIELD_NAMES:
        np.testing.assert_array_equal(a[name], b[name], err_msg=name)
    assert bank.counters == restored.counters


# ----------------------------------------------------------------------------- old checkpoints
def _pre_observer_checkpoint(soc_error: float) -> tuple[MultidayRecord, dict[str, Any]]:
    """A format-2 state at 07:25 (25 min of rest), as an engine without the observer wrote it:
    no ``state/observer``; its coulomb-counted SOC off by ``soc_error``."""
    rec = _record(1.0)
    bank = build_bank(rec.cell, 1, tuning=TUN, soc0=float(rec.truth.soc[0]))
    bank.update_block(_block(rec, 0, 1500))
    state = bank.state_dict()
    assert state["format"] == 2
    del state["state"]["observer"]
    state["state"]["z"] = state["state"]["z"] + soc_error
    return rec, state


def test_a_checkpoint_from_before_the_observer_loads_and_reanchors_at_the_next_update() -> None:
    rec, state = _pre_observer_checkpoint(0.0)
    bank = build_bank(rec.cell, 1, tuning=TUN)
    bank.load_state_dict(state)
    assert bank.counters["reanchors"] == 0
    out = bank.update_block(_block(rec, 1500, 1510))  # one tick
    assert len(out) == 1
    assert bank.counters["reanchors"] == 1
    bank.update_block(_block(rec, 1510, 1800))
    assert bank.counters["reanchors"] == 1  # once


def test_the_reanchor_of_an_old_checkpoint_corrects_its_soc() -> None:
    """The old engine's SOC (a plain count) 5 points off; the pack has rested 25 min. The
    re-anchor is the observer's one chance to take SOC from the voltage: it must move SOC, not
    the current offset."""
    rec, state = _pre_observer_checkpoint(-0.05)
    bank = build_bank(rec.cell, 1, tuning=TUN)
    bank.load_state_dict(state)
    assert isinstance(bank.state, ObserverState)
    p_zz = float(bank.state.P[0, 0])
    out = bank.update_block(_block(rec, 1500, 1510))
    err = float(_soc_error(rec, out)[0])
    b = float(out["current_offset_A"][0, 0])
    assert abs(err) < 0.025 and abs(b) < 1.0, (
        f"BUG observer: after loading a checkpoint without state/observer, P[soc, soc] = "
        f"{p_zz:g} (the fresh bank's, never set by a start), so the re-anchor moved SOC from "
        f"-0.05 to {err:+.4f} and the offset to {b:+.2f} A (truth 0); published soc_std "
        f"{out['soc_std'][0, 0]:.5f}"
    )


# ----------------------------------------------------------------------------- hysteresis map
def test_three_days_of_rests_do_not_mislead_the_hysteresis_map() -> None:
    """Issue 11 item 6: the true M is 1.6x the table at empty and 0.4x at full. After three
    days of rests the learnt M at 20 % SOC (the second drive's rest, h = -1) is no further from
    the truth than the table, and the map stays physical and near its prior where the rests did
    not teach it. (It moved towards the truth, to 17.7 mV, while a swarm that finished on a
    window of rest could set R2 on its bound at that rest, and to 15.8 mV until the offset became
    a consider state under load: SOC's uncertainty after a drive now keeps the offset's, and the
    map is taught only where SOC is known better than M; README.)"""
    rec = generate(MultidayOptions(n_days=3, hysteresis_tilt=0.6))
    bank = build_bank(rec.cell, 1, tuning=TUN)
    bank.update_block(_block(rec))
    obs = bank.state
    assert isinstance(obs, ObserverState) and bank.counters["anchors"] >= 6
    z = np.array([0.2])
    table, learnt = float(obs.model.ocv.hysteresis_M(z)[0]), float(obs.hysteresis_m(z)[0])
    truth = table * (1.0 + 0.6 * (1.0 - 2.0 * 0.2))
    assert abs(learnt - truth) <= abs(table - truth), (table, learnt, truth)
    # the map stays physical and near its prior where it was not taught
    m_all = obs.hysteresis_m(np.linspace(0.0, 1.0, 101))
    assert np.all(np.isfinite(m_all)) and np.all(m_all >= 0.0)
    assert float(obs.hysteresis_m(np.array([0.05]))[0]) == pytest.approx(table, rel=0.1)


def test_a_rest_holds_the_hysteresis_state_whatever_the_sensors_noise() -> None:
    """The day's rest (09:00-17:00) after the first drive: the true h holds, the measured
    current is the sensor's noise (0.25 A std, within the 0.7 A rest limit). Eq. 5-6 driven by
    that noise relax h towards 0 (|i| > 0 either way: before, h went from -0.83 to -0.43 over
    the rest here); a current the sensor cannot tell from zero moves no hysteresis (Eq. 5-6
    alone: the observer's correction of h, which the rest's voltage drives, left out)."""
    opt = MultidayOptions(n_days=1, duration_s=PLAN.second_drive_s, i_noise_A=0.25)
    rec = generate(opt)
    out = build_bank(rec.cell, 1, tuning=TUN_H_EXACT, soc0=0.93).update_block(_block(rec))
    k0, k1 = _at(out, DRIVE_END_S + 600), out.n_ticks - 1
    h = out["h"][:, 0]
    assert h[k0] < -0.5  # the drive left it well below 0 (the truth: -0.65)
    assert h[k1] == pytest.approx(h[k0], abs=0.01), (h[k0], h[k1])


def test_the_soc_std_covers_the_error_of_a_clean_day() -> None:
    """Issue 11 ("with covariances"): on a clean day (no offset, the table's hysteresis) the
    published soc_std holds the SOC error within 2 std on >= 90 % of the ticks after the first
    hour. Before the map's uncertainty was in the updates that do not teach it, 60 %: the
    filter took M as exact and read a rest's SOC through it with a rested cell's noise."""
    rec = generate(MultidayOptions(n_days=1))
    out = build_bank(rec.cell, 1, tuning=TUN).update_block(_block(rec))
    keep = out.t_s >= H
    err = _soc_error(rec, out)[keep]
    within = np.abs(err) <= 2.0 * out["soc_std"][keep, 0]
    assert within.mean() >= 0.9, (within.mean(), np.abs(err).max())


def test_the_hysteresis_state_follows_every_raw_sample_between_ticks() -> None:
    """Eq. 5-6 moves h by |i|, which a tick's mean current loses: a 10 s tick that holds 8 s of
    discharge and 2 s of regenerative charge moves h by its net discharge only. Integrated
    from the tick's mean, the first drive left h at -0.83 against the truth's -0.65 (the DST's
    charge pulses averaged away) and the 2.7 mV of hysteresis voltage it missed went into
    the offset at the rest. Stepped through the raw samples, as SOC is, h is the truth's (the
    observer's correction of h left out: this is Eq. 5-6's stepping)."""
    rec = _record(12.0)
    out = build_bank(rec.cell, 1, tuning=TUN_H_EXACT, soc0=0.93).update_block(_block(rec))
    k = np.searchsorted(rec.t_s, out.t_s)
    drive = (out.t_s >= PLAN.first_drive_s) & (out.t_s <= DRIVE_END_S + 600)
    err = np.abs(out["h"][drive, 0] - rec.truth.h[k[drive]])
    assert err.max() <= 0.01, f"h up to {err.max():.3f} off the truth over the first drive"


def test_a_rest_stays_a_rest_when_the_offset_estimate_overshoots() -> None:
    """+0.7 A offset (1 % C, the rest limit) and the day's rest after the first drive: the
    sensor reads 0.7 A there. The offset estimate overshoots at the rest (above); tested on
    i - b alone the rest then ended, and none began again: b stayed a consider state frozen at
    1.5 A while h drifted on the count's -0.8 A (-0.66 -> +0.11) and SOC read 1.6 points low
    for the rest of the rest. A current at the rests' reading is a rest whatever b says, and b
    stays within the rest limit of that reading (rest_anchor.py)."""
    rec = _record(10.0, offset_A=0.7)
    out = build_bank(rec.cell, 1, tuning=TUN, soc0=0.93).update_block(_block(rec))
    k = np.searchsorted(rec.t_s, out.t_s)
    rest = (out.t_s >= DRIVE_END_S + 600) & (out.t_s < PLAN.second_drive_s)
    h_err = np.abs(out["h"][rest, 0] - rec.truth.h[k[rest]]).max()
    reading = float(
        rec.current_A[(rec.t_s >= DRIVE_END_S) & (rec.t_s < PLAN.second_drive_s)].mean()
    )
    b_over = float(out["current_offset_A"][rest, 0].max()) - reading  # the reading's noise: 0.03
    soc_err = abs(_soc_error(rec, out)[rest][-1])
    assert h_err < 0.05 and b_over < 0.73 and soc_err < 0.005, (h_err, b_over, soc_err)


@pytest.mark.parametrize("estimated", [True, False])
def test_a_hysteresis_state_the_model_does_not_know_is_learnt_at_a_rest_not_taken_into_soc(
    estimated: bool,
) -> None:
    """An LFP cell (the A123 config: about 1 mV of OCV per SOC point at 60 %, M ~16 mV) rests
    on its discharge branch (h = -1), the model's h starts at 0 with the SOC given right; an
    hour of rest, 30 min of DST, 1.5 h of rest. With the hysteresis error estimated
    (``hysteresis_error.py``) the rest's 16 mV go into h (-1.000) and SOC stays within 0.4
    points; taken as exact, h put them into SOC: 6-7 points low behind a 0.8-point std."""
    cell = load_cell_config(Path(__file__).resolve().parents[2] / "configs/cells/a123_lfp_25C.toml")
    t = np.arange(0.0, 3 * H)
    i = np.where((t >= H) & (t < 1.5 * H), dst_current(t - H, 2.0), 0.0)
    sim = simulate(
        t, i, ocv_model(cell), capacity_Ah=cell.capacity_Ah, R0_ohm=0.01, R1_ohm=0.005,
        tau1_s=20.0, R2_ohm=0.01, tau2_s=300.0, gamma=30.0, soc0=0.6, h0=-1.0,
    )  # fmt: skip
    v = sim.v_V.T + np.random.default_rng(0).normal(0.0, 1e-3, (t.size, 1))
    tun = EstimatorTuning(observer=ObserverTuning(hysteresis_error=estimated))
    out = build_bank(cell, 1, tuning=tun, soc0=0.6).update_block(SampleBlock.from_arrays(t, i, v))
    k = np.searchsorted(t, out.t_s)
    err = np.abs(out["soc"][:, 0] - np.ravel(sim.soc)[k])
    h_err = abs(float(out["h"][_at(out, H - 1), 0]) - float(np.ravel(sim.h)[k[_at(out, H - 1)]]))
    if estimated:
        assert err.max() < 0.005 and h_err < 0.05, (err.max(), h_err)
    else:  # what the estimate is for: this test fails if the two runs agree
        assert err[_at(out, 0.5 * H) :].min() > 0.05, err.min()
