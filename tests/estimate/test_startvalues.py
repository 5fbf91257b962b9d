"""Start values and bounds measured on the record (estimate/startvalues.py)."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from bmsid.config.cell import paper_cell
from bmsid.config.engine import cell_model, ocv_model
from bmsid.estimate.startvalues import min_step_for, start_values_from_record, step_resistances
from bmsid.estimate.tuning import EstimatorTuning
from bmsid.model.simulator import simulate
from bmsid.profiles import dst_current


@settings(max_examples=25, deadline=None)
@given(
    r0_ah=st.floats(0.005, 0.2),  # R0 x capacity, ohm Ah: 1 mOhm at 20 Ah .. 100 mOhm at 2 Ah
    r1_share=st.floats(0.1, 2.0),
    tau1=st.floats(5.0, 100.0),
    capacity=st.floats(1.0, 200.0),
)
def test_r0_from_the_steps_of_a_drive_cycle(
    r0_ah: float, r1_share: float, tau1: float, capacity: float
) -> None:
    """The median one-sample -dV/dI of a DST drive recovers R0 within the share of R1 that
    one second of the fast branch adds (1 - exp(-1/tau1)), plus 5 % for the OCV, hysteresis
    and branch drift over that second."""
    r0 = r0_ah / capacity
    t = np.arange(0.0, 1800.0)
    i = dst_current(t, capacity / 2.0)  # 2C peak
    r1 = r1_share * r0
    sim = simulate(t, i, ocv_model(paper_cell()), capacity_Ah=capacity, R0_ohm=r0, R1_ohm=r1,
                   tau1_s=tau1, R2_ohm=r0, tau2_s=600.0, soc0=0.9)  # fmt: skip
    sv = start_values_from_record(t, i, sim.v_V[0])
    assert sv is not None and sv.n_steps >= 3
    extra = r1_share * (1.0 - np.exp(-1.0 / tau1)) + (1.0 - np.exp(-1.0 / 600.0))
    assert abs(sv.R0_ohm - r0) <= r0 * (extra + 0.05)


def test_no_steps_no_start_values() -> None:
    t = np.arange(0.0, 600.0)
    assert start_values_from_record(t, np.full(600, 2.0), np.full(600, 3.6)) is None


def test_nan_samples_and_slow_steps_do_not_count() -> None:
    t = np.array([0.0, 1.0, 2.0, 10.0, 11.0])
    i = np.array([0.0, 10.0, 0.0, 10.0, 0.0])
    v = np.array([3.7, 3.69, np.nan, 3.69, 3.7])
    r = step_resistances(t, i, v)
    np.testing.assert_allclose(r, [1e-3, 1e-3])  # 0->10 A and 10->0 A; the 8 s step is out


def test_bounds_follow_the_measured_r0_and_the_tick_rate() -> None:
    """Config without [initial]/[bounds]: start values and bounds from the record."""
    cell = paper_cell().model_copy(update={"initial": None, "bounds": None})
    t = np.arange(0.0, 1200.0)
    i = dst_current(t, 35.0)
    sim = simulate(t, i, ocv_model(cell), capacity_Ah=70.0, R0_ohm=5e-3, R1_ohm=2e-3,
                   tau1_s=20.0, R2_ohm=3e-3, tau2_s=500.0, soc0=0.9)  # fmt: skip
    sv = start_values_from_record(t, i, sim.v_V[0])
    assert sv is not None
    tun = EstimatorTuning(id_period_s=2.0, window_s=1200.0)
    m = cell_model(cell, 3, sv, tun)
    lo, hi = m.bound("R0_ohm")
    assert lo[0] == pytest.approx(sv.R0_ohm / 4) and hi[0] == pytest.approx(sv.R0_ohm * 4)
    assert m.bound("tau1_s")[0][0] == 4.0  # two ticks of 2 s
    assert m.bound("tau2_s")[1][0] == 1200.0  # no slower than the swarm window
    assert m.start("R0_ohm")[0] == sv.R0_ohm
    # a config that gives them keeps them
    fixed = cell_model(paper_cell(), 1, sv, tun)
    assert fixed.start("R0_ohm")[0] == 2e-3 and fixed.bound("R0_ohm")[1][0] == 0.5


def _ramped_steps(rate_hz: float, ramp_samples: int, duration_s: float = 120.0) -> np.ndarray:
    """A current (A) stepping by 15 A every 10 s (a staircase up to +-45 A), each step a
    linear ramp over ``ramp_samples`` samples (a BMS current filter, a charger's slew) at
    ``rate_hz``: no sample-to-sample change reaches a tenth of the 95th-percentile |I|."""
    t = np.arange(0.0, duration_s, 1.0 / rate_hz)
    stairs = np.array([0, 1, 2, 3, 2, 1, 0, -1, -2, -3, -2, -1], dtype=np.float64)
    levels = 15.0 * stairs[(t // 10.0).astype(int) % stairs.shape[0]]
    ramp = np.ones(ramp_samples) / ramp_samples  # a moving average turns each jump into a ramp
    padded = np.concatenate([np.full(ramp_samples - 1, levels[0]), levels])
    return np.convolve(padded, ramp, "valid")


@pytest.mark.parametrize("ramp_samples", [5, 50, 100])
def test_steps_ramped_over_many_samples_at_100_hz_are_measured(ramp_samples: int) -> None:
    """Measured: at 100 Hz a step ramped over 5 samples has no sample-to-sample difference
    above the threshold, so the daemon held 300 s of samples and published nothing. Thinned
    to 0.5 s the steps count again, R0 within what 0.5 s of the fast branch adds, + 5 %."""
    rate_hz, r0, tau1 = 100.0, 0.002, 20.0
    i = _ramped_steps(rate_hz, ramp_samples)
    t = np.arange(i.shape[0]) / rate_hz
    sim = simulate(t, i, ocv_model(paper_cell()), capacity_Ah=70.0, R0_ohm=r0, R1_ohm=r0,
                   tau1_s=tau1, R2_ohm=r0, tau2_s=600.0, soc0=0.8)  # fmt: skip
    sv = start_values_from_record(t, i, sim.v_V[0])
    assert sv is not None and sv.n_steps >= 3
    extra = 1.0 - np.exp(-1.5 / tau1)  # a ramp of 1 s split over two 0.5 s differences
    assert abs(sv.R0_ohm - r0) <= r0 * (extra + 0.05)


def test_one_second_records_difference_every_sample_as_before() -> None:
    """1 s records (and anything slower than 1/3 s) keep the one-sample differences bit for
    bit: the thinning is for fast records only."""
    rng = np.random.default_rng(3)
    for dt in (1.0, 0.4, 5.0):
        t = np.cumsum(rng.uniform(0.9 * dt, 1.1 * dt, 2000))
        i = dst_current(t, 35.0)
        v = 3.7 - 0.002 * i + rng.normal(0.0, 2e-4, t.shape[0])
        di, dv, dtt = np.diff(i), np.diff(v), np.diff(t)
        big = max(0.1 * float(np.percentile(np.abs(i), 95)), 0.05)
        step = (np.abs(di) >= big) & (dtt > 0) & (dtt <= 2.0)
        r = -dv[step] / di[step]
        expected = r[np.isfinite(r) & (r > 0)]
        assert np.array_equal(step_resistances(t, i, v), expected)


def test_a_cell_absent_from_the_record_does_not_hold_the_start_values_back() -> None:
    """A daemon configured for 8 cells on a bus carrying 4 held its samples for 1800 s and then
    said "no current steps": the absent cells' zero steps were the pooled count. The cells
    that read a voltage give the start values; a record with none gives none."""
    t = np.arange(120.0)
    i = np.where((t // 10) % 2 == 0, 2.0, 0.0)
    v_live = 3.7 - 0.05 * i
    v = np.stack([v_live, v_live, np.full_like(t, np.nan)], axis=1)
    sv = start_values_from_record(t, i, v)
    assert sv is not None and sv.R0_ohm == pytest.approx(0.05) and sv.n_steps >= 10
    assert start_values_from_record(t, i, np.full((t.size, 2), np.nan)) is None


@pytest.mark.parametrize("deadband", [False, True])
def test_a_rested_heads_sensor_noise_is_no_step(deadband: bool) -> None:
    """A 100 Ah cell (R0 0.8 mOhm) rests 600 s, then drives DST; 0.05 A of current and 1 mV of
    voltage noise (with ``deadband``, the current reads 0 below 0.2 A). A gateway started at
    rest probed the head as it grew and took noise for steps (17 mOhm); with the excitation
    threshold as the smallest step, the rest measures nothing and the drive's steps R0."""
    rng = np.random.default_rng(5)
    t = np.arange(0.0, 900.0)
    i_true = np.where(t < 600, 0.0, dst_current(t - 600, 200.0))
    sim = simulate(t, i_true, ocv_model(paper_cell()), capacity_Ah=100.0, R0_ohm=0.8e-3,
                   R1_ohm=0.5e-3, tau1_s=15.0, R2_ohm=0.6e-3, tau2_s=500.0, soc0=0.88)  # fmt: skip
    i = i_true + rng.normal(0.0, 0.05, t.size)
    if deadband:
        i = np.where(np.abs(i) < 0.2, 0.0, i)
    v = sim.v_V[0] + rng.normal(0.0, 1e-3, t.size)
    step_A = min_step_for(100.0, EstimatorTuning().excitation_C)
    for head_s in (20, 35, 60, 300, 599):
        assert start_values_from_record(t[:head_s], i[:head_s], v[:head_s], step_A) is None
    sv = start_values_from_record(t, i, v, step_A)
    assert sv is not None and sv.R0_ohm == pytest.approx(0.8e-3, rel=0.1), sv
