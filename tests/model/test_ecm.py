"""The one ZOH step (model/ecm.py): its window form, its SOC form and its bounds."""

from __future__ import annotations

import numpy as np
import pytest
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
@given(
    h=st.floats(-1, 1), i=st.floats(-1e4, 1e4), dt=st.floats(0, 1e5), k=st.floats(0, 1),
    play=st.booleans(),
)  # fmt: skip
def test_hysteresis_stays_in_its_range_and_moves_against_the_current(
    h: float, i: float, dt: float, k: float, play: bool
) -> None:
    h1 = float(hysteresis_step(np.array(h), i, dt, k, play))
    assert -1.0 <= h1 <= 1.0
    if i > 0:
        assert h1 <= h + 1e-15  # discharge drives h towards -1
    elif i < 0:
        assert h1 >= h - 1e-15
    else:
        assert h1 == h


@settings(max_examples=60, deadline=None)
@given(h=st.floats(-1, 1), q=st.floats(0, 1e3), k=st.floats(1e-4, 1.0))
def test_the_play_leaves_its_branch_at_plett_s_initial_rate_and_returns_at_once(
    h: float, q: float, k: float
) -> None:
    """A charge q (A s) off the discharge branch moves h by 2 kappa q (Plett's slope there) and
    the same charge back returns it to the branch exactly; Plett's h does not return."""
    up = float(hysteresis_step(np.array(-1.0), -q, 1.0, k, True))
    assert up == pytest.approx(min(-1.0 + 2.0 * k * q, 1.0), abs=1e-12)
    if up < 1.0:  # not clipped at the other branch: the way back is the way there
        assert float(hysteresis_step(np.array(up), q, 1.0, k, True)) == pytest.approx(-1.0)
    # within the band, a step and its reverse cancel (no drift from a symmetric pulse)
    mid = float(hysteresis_step(np.array(h), q, 1.0, k, True))
    if -1.0 < mid < 1.0 and -1.0 < h < 1.0:
        assert float(hysteresis_step(np.array(mid), -q, 1.0, k, True)) == pytest.approx(h, abs=1e-9)


def test_under_a_discharge_with_short_regeneration_the_play_stays_at_its_branch() -> None:
    """60 s at 1 A, 15 s at -1 A regenerating, repeated (a drive's mixed current, 2/3 of the
    charge out): Plett's h settles between the branches (the charge-weighted mean of the signs,
    -0.6), the play's within 2 kappa x 15 A s of the discharge branch."""
    k = 30.0 / 7200.0  # gamma 30 on a 2 Ah cell, 1/(A s)
    hp = hq = 1.0
    tail_p, tail_q = [], []
    for cycle in range(400):
        for i, n in ((1.0, 60), (-1.0, 15)):
            for _ in range(n):
                hp = float(hysteresis_step(np.array(hp), i, 1.0, k))
                hq = float(hysteresis_step(np.array(hq), i, 1.0, k, True))
                if cycle >= 300:
                    tail_p.append(hp)
                    tail_q.append(hq)
    assert np.mean(tail_p) == pytest.approx(-0.6, abs=0.05)
    assert min(tail_q) == -1.0 and max(tail_q) <= -1.0 + 2.0 * k * 15.0 + 1e-12
