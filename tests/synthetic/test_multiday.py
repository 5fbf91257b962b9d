"""The multi-day known-truth generator (``bmsid.synthetic.multiday``): its truth is consistent
with itself, its scenario knobs do what they say, and it is deterministic.

Two 16 h records (07:00-23:00: both drives, the charge, an hour of the night; about 1 s each to
simulate); the schedule's property test needs no simulation."""

from __future__ import annotations

from dataclasses import fields, replace
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from bmsid.offline.csvio import read_tester_csv
from bmsid.synthetic import TRUTH
from bmsid.synthetic.multiday import (
    DAY_S,
    DayPlan,
    MultidayOptions,
    MultidayRecord,
    MultidayTruth,
    Phase,
    arrhenius_factor,
    generate,
    read_truth,
    reference_cell,
    true_current,
    write_record,
)

#: Every knob on: the bench's "all" scenario over the first 16 h.
ALL = MultidayOptions(
    n_days=1, duration_s=16 * 3600, current_offset_A=0.7, start_load_A=0.17, temp_swing_C=8.0,
    r0_growth_per_day=0.03, capacity_fade_per_day=0.005,
)  # fmt: skip
PLAN = DayPlan()
CAPACITY_AH = reference_cell().capacity_Ah


@pytest.fixture(scope="module")
def rec() -> MultidayRecord:
    return generate(ALL)


@pytest.fixture(scope="module")
def quiet() -> MultidayRecord:
    """The same day without noise."""
    return generate(replace(ALL, v_noise_V=0.0, i_noise_A=0.0))


def test_a_hand_count_of_the_true_current_is_the_true_soc(rec: MultidayRecord) -> None:
    tr = rec.truth
    dz = -tr.current_A / (tr.capacity_Ah * 3600.0)  # 1 s steps, efficiency 1 (the paper cell)
    z = ALL.soc0 + np.concatenate(([0.0], np.cumsum(dz[:-1])))
    np.testing.assert_allclose(tr.soc, z, rtol=0, atol=1e-12)
    assert tr.soc.min() > 0.1 and tr.soc.max() < 0.95


def test_the_offset_is_exactly_measured_minus_true_current(
    rec: MultidayRecord, quiet: MultidayRecord
) -> None:
    np.testing.assert_allclose(quiet.current_A - quiet.truth.current_A, 0.7, rtol=0, atol=1e-12)
    np.testing.assert_array_equal(quiet.truth.current_offset_A, 0.7)
    np.testing.assert_array_equal(quiet.voltage_V, quiet.truth.voltage_V)
    noise = rec.current_A - rec.truth.current_A - 0.7
    assert abs(noise.mean()) < 1e-3 and noise.std() == pytest.approx(0.05, rel=0.02)
    np.testing.assert_array_equal(rec.truth.current_A, quiet.truth.current_A)


def test_rests_are_rests_and_the_start_load_is_the_aux_load(quiet: MultidayRecord) -> None:
    tr = quiet.truth
    rest = tr.phase == Phase.REST
    assert rest.mean() > 0.6
    np.testing.assert_array_equal(tr.current_A[rest], 0.0)
    aux = np.flatnonzero(tr.phase == Phase.AUX)
    np.testing.assert_array_equal(aux, np.arange(PLAN.first_drive_s))
    np.testing.assert_array_equal(tr.current_A[aux], 0.17)
    drive = tr.phase == Phase.DRIVE
    assert drive.sum() == 2 * PLAN.drive_s
    assert tr.current_A[drive].max() == 140.0


def test_a_rest_draw_is_the_true_current_at_every_rest_and_the_count_sees_it() -> None:
    """``rest_draw_A``: the pack draws that current at every rest (a converter left on); the
    drives and charges are the plan's, the evening charge still fills to its target."""
    opt = MultidayOptions(n_days=2, rest_draw_A=0.2, i_noise_A=0.0, v_noise_V=0.0)
    tr = generate(opt).truth
    rest = tr.phase == Phase.REST
    np.testing.assert_array_equal(tr.current_A[rest], 0.2)
    drive = tr.phase == Phase.DRIVE
    assert drive.sum() == 2 * 2 * PLAN.drive_s
    night = np.flatnonzero(rest & (tr.t_s > PLAN.charge_start_s) & (tr.t_s < DAY_S))  # night 1
    dz = tr.soc[night[0]] - tr.soc[night[-1]]
    assert dz == pytest.approx(0.2 * (night[-1] - night[0]) / 3600.0 / 70.0, rel=0.05)


def test_the_evening_charge_fills_to_the_target(quiet: MultidayRecord) -> None:
    tr = quiet.truth
    ch = np.flatnonzero(tr.phase == Phase.CHARGE)
    assert ch[0] == PLAN.charge_start_s and np.all(np.diff(ch) == 1)  # one block, at 20:00
    np.testing.assert_allclose(tr.current_A[ch], -CAPACITY_AH / 3.0)
    assert 1.5 * 3600 < ch.size < 3 * 3600
    end = ch[-1] + 1  # the SOC after the last charging second
    one_step = CAPACITY_AH / 3.0 / (tr.capacity_Ah[end] * 3600.0)
    assert PLAN.charge_to_soc <= tr.soc[end] < PLAN.charge_to_soc + one_step
    assert tr.soc[ch[0]] < 0.25  # after both drives
    assert np.all(tr.soc[end:] == tr.soc[end])  # rest overnight
    assert np.all(np.diff(tr.h[ch]) >= 0) and tr.h[end] > 0.5  # charge drives h to +1


def test_arrhenius_raises_the_resistances_when_cold(rec: MultidayRecord) -> None:
    f = arrhenius_factor(np.array([17.0, 25.0, 33.0]), 25.0, ALL.activation_energy_J_mol)
    assert f[0] > 1.0 == f[1] > f[2]
    tr = rec.truth
    warm = int(np.argmax(tr.temperature_C))
    assert warm == 8 * 3600 and tr.temperature_C[warm] == pytest.approx(33.0)  # 15:00
    assert tr.temperature_C[0] == pytest.approx(21.0)  # 07:00: 25 + 8 cos(-120 deg)
    r1 = tr.R1_ohm / TRUTH["R1_ohm"]
    assert r1[0] > 1.0 > r1[warm]
    age = 1.0 + ALL.r0_growth_per_day * tr.t_s / DAY_S
    np.testing.assert_allclose(tr.R0_ohm / (TRUTH["R0_ohm"] * age), r1, rtol=1e-12)
    assert np.corrcoef(r1, tr.temperature_C)[0, 1] < -0.95
    for k in ("R2_ohm", "tau1_s", "tau2_s"):
        np.testing.assert_array_equal(getattr(tr, k), TRUTH[k])
    fade = 1.0 - 0.005 * tr.t_s / DAY_S
    np.testing.assert_allclose(tr.capacity_Ah, CAPACITY_AH * fade, rtol=1e-12)


def test_the_same_options_give_the_same_truth_and_the_noise_is_the_seeds(
    rec: MultidayRecord, quiet: MultidayRecord
) -> None:
    for f in fields(MultidayTruth):  # two calls, noise aside: the same truth
        np.testing.assert_array_equal(getattr(quiet.truth, f.name), getattr(rec.truth, f.name))
    rng = np.random.default_rng(ALL.seed)  # the voltage noise is drawn first, then the current's
    n = rec.n_samples
    np.testing.assert_array_equal(rec.voltage_V, rec.truth.voltage_V + rng.normal(0, 1e-3, n))
    i_noise = rng.normal(0, 0.05, n)
    np.testing.assert_allclose(rec.current_A - i_noise, quiet.current_A, rtol=0, atol=1e-12)


def test_the_record_is_a_tester_csv_and_the_truth_reads_back(
    rec: MultidayRecord, tmp_path: Path
) -> None:
    write_record(rec, tmp_path / "record.csv", tmp_path / "truth.npz")
    data = read_tester_csv(tmp_path / "record.csv")
    assert data.cell_names == ["voltage_V"] and data.n_samples == ALL.duration_s
    np.testing.assert_array_equal(data.t_s, rec.t_s)
    np.testing.assert_allclose(data.current_A, rec.current_A, rtol=1e-9)
    np.testing.assert_allclose(data.cell_voltages_V[:, 0], rec.voltage_V, rtol=1e-9)
    truth, doc = read_truth(tmp_path / "truth.npz")
    for f in fields(MultidayTruth):
        np.testing.assert_array_equal(getattr(truth, f.name), getattr(rec.truth, f.name))
    assert doc["current_offset_A"] == 0.7 and doc["n_days"] == 1


@settings(max_examples=40, deadline=None)
@given(
    n_days=st.integers(1, 3),
    soc0=st.floats(0.12, 0.96),
    fade=st.floats(0.0, 0.1),
    start_load=st.floats(0.0, 2.0),
)
def test_the_schedule_keeps_the_soc_in_range_whatever_the_start(
    n_days: int, soc0: float, fade: float, start_load: float
) -> None:
    opt = MultidayOptions(n_days=n_days, soc0=soc0, capacity_fade_per_day=fade,
                          start_load_A=start_load)  # fmt: skip
    cell = reference_cell()
    t, i, phase, q = true_current(opt, cell)
    assert t.shape == i.shape == phase.shape == q.shape == (n_days * DAY_S,)
    z = soc0 + np.concatenate(([0.0], np.cumsum(-i[:-1] / (q[:-1] * 3600.0))))
    assert z.min() > PLAN.soc_floor - 1e-3 and z.max() < 0.97
    np.testing.assert_array_equal(i[phase == Phase.REST], 0.0)
    assert np.all(i[phase == Phase.CHARGE] < 0) and np.all(i[phase == Phase.AUX] > 0)
    for d in range(n_days):
        day = slice(d * DAY_S, (d + 1) * DAY_S)
        end_of_day = z[(d + 1) * DAY_S - 1]
        one_step = CAPACITY_AH / 3.0 / (float(q[day].min()) * 3600.0)
        if (phase[day] == Phase.CHARGE).any():  # charged to the target (or it started above)
            assert PLAN.charge_to_soc - 1e-9 <= end_of_day < PLAN.charge_to_soc + one_step
        else:
            assert z[d * DAY_S + PLAN.charge_start_s] >= PLAN.charge_to_soc
