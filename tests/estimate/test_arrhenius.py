"""R0 carried along an Arrhenius law while the current holds nothing to learn them from
(``estimate/arrhenius.py``): exact for the activation temperature in force, B learnt from the
cell's own window fits, a window fit's R0 taken to the temperature now, nothing at all without
a temperature."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from bmsid.estimate.arrhenius import B_MAX_K, B_MIN_K, B_PRIOR_K, KELVIN, ArrheniusCarry

YES, NO = np.ones(2, dtype=bool), np.zeros(2, dtype=bool)
R0 = np.array([1e-3, 2e-3])


@settings(max_examples=100, deadline=None)
@given(temps=st.lists(st.floats(-10.0, 45.0), min_size=2, max_size=30))
def test_carried_resistances_follow_the_law_from_the_last_learnt_values(
    temps: list[float],
) -> None:
    """Learnt at the first temperature, carried through the others: at every tick R is the
    law from the learnt value (the per-tick factors telescope), finite and > 0."""
    a = ArrheniusCarry(2)
    assert a.step(temps[0], NO, R0) is None  # the first temperature: nothing carried
    r0 = R0.copy()
    for t_now in temps[1:]:
        out = a.step(t_now, YES, r0)
        if out is not None:
            r0 = out
        f = np.exp(B_PRIOR_K * (1 / (t_now + KELVIN) - 1 / (temps[0] + KELVIN)))
        np.testing.assert_allclose(r0, R0 * f, rtol=1e-9)
        assert np.all(np.isfinite(r0)) and np.all(r0 > 0)


def test_a_constant_temperature_changes_nothing() -> None:
    a = ArrheniusCarry(2)
    a.step(25.0, YES, R0)
    assert a.step(25.0, YES, R0 * 3) is None  # e.g. a swarm's new values kept


def test_no_temperature_changes_nothing() -> None:
    a = ArrheniusCarry(2)
    a.step(25.0, YES, R0)
    before = {k: v.copy() for k, v in a.state_dict().items()}
    assert a.step(float("nan"), YES, R0) is None
    for k, v in a.state_dict().items():
        np.testing.assert_array_equal(v, before[k], err_msg=k)


def test_the_first_temperature_carries_nothing() -> None:
    a = ArrheniusCarry(2)
    assert a.step(25.0, YES, R0) is None  # no previous temperature yet


@settings(max_examples=20, deadline=None)
@given(ea_kj=st.floats(15.0, 60.0), seed=st.integers(0, 2**16))
def test_the_activation_temperature_is_learnt_from_fits_kelvins_apart(
    ea_kj: float, seed: int
) -> None:
    """Window fits' R0 (1 % noise) at temperatures that differ by a few K from one fit to the
    next (a morning's drive and an afternoon's): B moves from the 30 kJ/mol prior to within
    10 % of the truth. Fits less than 1 K apart teach nothing (a drive's consecutive swarms)."""
    rng = np.random.default_rng(seed)
    b_true = ea_kj * 1e3 / 8.314
    a = ArrheniusCarry(1)
    for k in range(60):
        t_c = 25.0 + (4.0 if k % 2 else -4.0) + rng.uniform(-1.0, 1.0)
        r0 = 1e-3 * np.exp(b_true * (1 / (t_c + KELVIN) - 1 / (25 + KELVIN)))
        a.step(t_c, np.zeros(1, dtype=bool), np.array([r0]))
        a.learn_fit(0, float(r0 * (1 + 0.01 * rng.standard_normal())), 0.5 + 0.02 * (k % 3))
    assert abs(a.b_K[0] / b_true - 1) < 0.10
    b = ArrheniusCarry(1)
    for k in range(60):
        t_c = 25.0 + 0.4 * np.sin(k)
        b.step(t_c, np.zeros(1, dtype=bool), np.array([1e-3]))
        b.learn_fit(0, 1e-3 * (1 + 0.01 * rng.standard_normal()), 0.5)
    assert b.b_K[0] == B_PRIOR_K and b.counters["arrhenius_pairs"] == 0


def test_fits_far_apart_in_soc_teach_nothing() -> None:
    """R0 depends on SOC as well: a fit at 80 % and one at 30 % 5 K apart are no pair (a DFN
    cell's R0 rose 16 -> 26 mOhm over a discharge while it warmed, and such a pair took B to
    0); the same two fits at one SOC are."""
    a, b = ArrheniusCarry(1), ArrheniusCarry(1)
    for carry, socs in ((a, (0.8, 0.3)), (b, (0.5, 0.52))):
        for t_c, r0, z in ((20.0, 1.0e-3, socs[0]), (25.0, 1.3e-3, socs[1])):
            carry.step(t_c, np.zeros(1, dtype=bool), np.array([r0]))
            carry.learn_fit(0, r0, z)
    assert a.b_K[0] == B_PRIOR_K and a.counters["arrhenius_pairs"] == 0
    assert b.b_K[0] == B_MIN_K and b.counters["arrhenius_pairs"] == 1  # R0 up as it warmed


@settings(max_examples=50, deadline=None)
@given(
    temps=st.lists(st.floats(-20.0, 60.0), min_size=2, max_size=20),
    r0s=st.lists(st.floats(1e-5, 1.0), min_size=20, max_size=20),
)
def test_the_activation_temperature_stays_physical_whatever_the_fits_say(
    temps: list[float], r0s: list[float]
) -> None:
    """Any fits at any temperatures: B stays within 10-90 kJ/mol, finite, its variance > 0."""
    a = ArrheniusCarry(1)
    for t_c, r0 in zip(temps, r0s, strict=False):
        a.step(t_c, np.zeros(1, dtype=bool), np.array([r0]))
        a.learn_fit(0, r0, 0.5)
        assert B_MIN_K <= a.b_K[0] <= B_MAX_K and a.b_var[0] > 0


@settings(max_examples=50, deadline=None)
@given(
    t_steps=st.floats(15.0, 35.0),
    t_now=st.floats(15.0, 35.0),
    b_k=st.floats(1000.0, 9000.0),
    n_steps=st.integers(1, 20),
    seed=st.integers(0, 2**16),
)
def test_a_window_fits_r0_is_taken_from_its_steps_temperature_to_the_temperature_now(
    t_steps: float, t_now: float, b_k: float, n_steps: int, seed: int
) -> None:
    """Every current step of the window at one temperature, the rest of it (no steps: a rest,
    a constant current) at others: the factor is the law's from the steps' temperature to the
    last tick's; 1 exactly at one temperature throughout, or with none known."""
    rng = np.random.default_rng(seed)
    n = 600
    current = np.zeros(n)
    at = np.sort(rng.choice(np.arange(1, n // 2), size=n_steps, replace=False))
    for k in at:
        current[k:] += rng.choice([-1.0, 1.0]) * rng.uniform(1.0, 30.0)
    inv_t = np.full(n, 1.0 / (t_now + KELVIN))
    inv_t[: n // 2] = 1.0 / (t_steps + KELVIN)
    inv_t[n // 2 : n // 2 + 10] = np.nan  # readings missing for a while
    weights = np.where(rng.random(n) < 0.1, 0.0, 0.999 ** np.arange(n)[::-1])
    weights[at] = 0.999 ** (n - 1 - at)  # every step weighs
    a = ArrheniusCarry(1)
    a.b_K[0] = b_k
    a.step(t_now, np.zeros(1, dtype=bool), np.array([1e-3]))
    want = np.exp(b_k * (1 / (t_now + KELVIN) - 1 / (t_steps + KELVIN)))
    np.testing.assert_allclose(a.window_factor(0, inv_t, current, weights), want, rtol=1e-12)
    flat = np.full(n, 1.0 / (t_now + KELVIN))
    assert a.window_factor(0, flat, current, weights) == 1.0
    assert a.window_factor(0, np.full(n, np.nan), current, weights) == 1.0


def test_a_buffer_slot_the_compiled_loop_refilled_has_no_temperature() -> None:
    """The compiled loop pushes ticks without a temperature and writes neither 1 / T nor the
    time: a slot it refilled (as ``fused_kernel`` does: arrays, head and count) reads NaN, as one
    pushed here without a temperature; the others keep theirs."""
    from bmsid.estimate.swarms import WindowBuffer

    buf = WindowBuffer(size=11, n_cells=1)
    one, yes = np.zeros(1), np.ones(1, dtype=bool)
    for k in range(15):
        buf.push(1.0, one, one, yes, 1.0 / (20.0 + k + KELVIN), float(k))
    for _ in range(3):  # three ticks of the compiled loop
        j = buf.head
        buf.current_A[j], buf.y_V[0, j], buf.valid[0, j] = 1.0, 0.0, True
        buf.head, buf.count = (j + 1) % buf.size, min(buf.count + 1, buf.size)
    buf.push(1.0, one, one, yes)  # a tick without a temperature, pushed here
    inv = buf.inv_temperature(1.0, 10.0, 18.0)
    assert inv.shape == (11,)
    np.testing.assert_allclose(1.0 / inv[:7] - KELVIN, 20.0 + np.arange(8, 15))
    assert np.isnan(inv[7:]).all()
    st_ = buf.state_dict()
    back = WindowBuffer(size=11, n_cells=1)
    back.load_state_dict({k: v for k, v in st_.items() if k not in ("inv_T_K", "t_s")})
    assert np.isnan(back.inv_temperature(1.0, 10.0, 18.0)).all()  # a checkpoint from before
    back.load_state_dict(st_)
    np.testing.assert_array_equal(back.inv_temperature(1.0, 10.0, 18.0), inv)
    buf.clear()  # the clock jumped back 1000 s (a new segment): the slots keep later times
    for k in range(11):
        buf.push(1.0, one, one, yes, t_s=float(k) - 1000.0)  # no temperature
    assert np.isnan(buf.inv_temperature(1.0, 10.0, -990.0)).all()


def test_the_pack_temperature_reaches_the_ticks_as_the_mean_of_its_sensors() -> None:
    """Samples with two sensors (one NaN at times) -> SampleBlock column -> tick bin mean."""
    from bmsid.estimate.ticks import TickAssembler
    from bmsid.estimate.tuning import EstimatorTuning
    from bmsid.samples import Sample, SampleBlock

    samples = [
        Sample(t_s=0.5 * k, current_A=1.0, cell_voltages_V=np.array([3.7]),
               temperatures_C=np.array([20.0 + k, np.nan if k % 2 else 22.0 + k]))
        for k in range(6)
    ]  # fmt: skip
    block = SampleBlock.concat(
        [SampleBlock.from_samples(samples), SampleBlock.from_arrays([3.0], [1.0], [3.7])]
    )
    assert block.temperature_C is not None
    np.testing.assert_allclose(block.temperature_C, [21, 21, 23, 23, 25, 25, np.nan])
    ticks = TickAssembler(1, EstimatorTuning(id_period_s=1.0))
    temps = [
        tk.temperature_C
        for k in range(len(block))
        if (tk := ticks.push(block.t_s[k], block.current_A[k], block.cell_voltages_V[k],
                             block.temperature_C[k])) is not None
    ]  # fmt: skip
    # first sample alone, then 1 s bins of two samples; the last bin's NaN is left out
    np.testing.assert_allclose(temps, [21.0, 22.0, 24.0, 25.0])
