"""R0 carried along an Arrhenius law while the current holds nothing to learn them from
(``estimate/arrhenius.py``): exact for the activation temperature in force, B learnt from the
cell's own pairs, nothing at all without a temperature."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from bmsid.estimate.arrhenius import B_PRIOR_K, KELVIN, PAIR_S, ArrheniusCarry

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
    assert a.step(temps[0], 1.0, YES, NO, R0) is None  # learnt: nothing carried
    r0 = R0.copy()
    for t_now in temps[1:]:
        out = a.step(t_now, 1.0, NO, YES, r0)
        if out is not None:
            r0 = out
        f = np.exp(B_PRIOR_K * (1 / (t_now + KELVIN) - 1 / (temps[0] + KELVIN)))
        np.testing.assert_allclose(r0, R0 * f, rtol=1e-9)
        assert np.all(np.isfinite(r0)) and np.all(r0 > 0)


def test_a_constant_temperature_changes_nothing() -> None:
    a = ArrheniusCarry(2)
    a.step(25.0, 1.0, YES, NO, R0)
    assert a.step(25.0, 1.0, NO, YES, R0 * 3) is None  # e.g. a swarm's new values kept


def test_no_temperature_changes_nothing() -> None:
    a = ArrheniusCarry(2)
    a.step(25.0, 1.0, YES, NO, R0)
    before = {k: v.copy() for k, v in a.state_dict().items()}
    assert a.step(float("nan"), 1.0, NO, YES, R0) is None
    for k, v in a.state_dict().items():
        np.testing.assert_array_equal(v, before[k], err_msg=k)


def test_the_first_temperature_carries_nothing() -> None:
    a = ArrheniusCarry(2)
    assert a.step(25.0, 1.0, NO, YES, R0) is None  # no previous temperature yet


@settings(max_examples=20, deadline=None)
@given(ea_kj=st.floats(15.0, 60.0), seed=st.integers(0, 2**16))
def test_the_activation_temperature_is_learnt_from_pairs_kelvins_apart(
    ea_kj: float, seed: int
) -> None:
    """Learnt R0 (1 % noise) at temperatures that differ by a few K from one pair to the next
    (a pack cooling or warming fast): B moves from the 30 kJ/mol prior to within 15 % of the
    truth. (A slow daily swing moves a fraction of a kelvin per pair: there B stays near its
    prior; measured on the 2-day multi-day record: 6 pairs used.)"""
    rng = np.random.default_rng(seed)
    b_true = ea_kj * 1e3 / 8.314
    a = ArrheniusCarry(1)
    for k in range(200):
        t_c = 25.0 + (4.0 if k % 2 else -4.0) + rng.uniform(-1.0, 1.0)
        r0 = 1e-3 * np.exp(b_true * (1 / (t_c + KELVIN) - 1 / (25 + KELVIN)))
        r0 *= 1 + 0.01 * rng.standard_normal()
        a.step(t_c, PAIR_S, np.ones(1, dtype=bool), np.zeros(1, dtype=bool), np.array([r0]))
    assert abs(a.b_K[0] / b_true - 1) < 0.15


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
