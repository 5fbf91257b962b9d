"""The one ZOH step (model/ecm.py): its window form, its SOC form and its bounds."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from bmsid.model.ecm import hysteresis_step, rc_decay, rc_filter, rc_step, soc_step
from bmsid.model.simulator import coulomb_count

currents = arrays(np.float64, st.integers(1, 200), elements=st.floats(-300, 300))


@settings(max_examples=60, deadline=None)
@given(i=currents, tau=st.floats(0.2, 5000.0), dt=st.floats(0.01, 10.0))
def test_window_filter_equals_the_step_iterated(i: np.ndarray, tau: float, dt: float) -> None:
    a = float(rc_decay(dt, tau))
    x, want = 0.0, np.zeros_like(i)
    for k in range(i.shape[0]):
        want[k] = x
        x = float(rc_step(x, a, i[k]))
    np.testing.assert_allclose(rc_filter(i, a), want, rtol=1e-9, atol=1e-9 * (1 + abs(i).max()))


@settings(max_examples=60, deadline=None)
@given(i=currents, eta=st.floats(0.9, 1.0), cap=st.floats(0.5, 300.0))
def test_soc_steps_equal_the_coulomb_count(i: np.ndarray, eta: float, cap: float) -> None:
    dt = np.full(i.shape[0], 0.5)
    z, want = 0.5, coulomb_count(i, dt, 0.5, cap, eta)
    for k in range(i.shape[0]):
        np.testing.assert_allclose(z, want[k], rtol=0, atol=1e-12)
        z = float(soc_step(z, i[k], dt[k], cap * 3600.0, eta))


@settings(max_examples=100, deadline=None)
@given(h=st.floats(-1, 1), i=st.floats(-1e4, 1e4), dt=st.floats(0, 1e5), k=st.floats(0, 1))
def test_hysteresis_stays_in_its_range_and_moves_against_the_current(
    h: float, i: float, dt: float, k: float
) -> None:
    h1 = float(hysteresis_step(np.array(h), i, dt, k))
    assert -1.0 <= h1 <= 1.0
    if i > 0:
        assert h1 <= h + 1e-15  # discharge drives h towards -1
    elif i < 0:
        assert h1 >= h - 1e-15
    else:
        assert h1 == h
