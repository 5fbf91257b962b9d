"""Exact ZOH simulator (Eq. 2, 7-9) and the OCV/hysteresis pieces."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from bmsid.config.cell import paper_cell
from bmsid.config.engine import ocv_model
from bmsid.model.ecm import hysteresis_step
from bmsid.model.simulator import simulate

CELL = paper_cell(M_V=0.015, gamma=30.0)
OCV = ocv_model(CELL)


def test_step_response_matches_the_analytic_solution() -> None:
    t = np.arange(0.0, 600.0, 1.0)
    i = np.full_like(t, 70.0)
    sim = simulate(
        t, i, OCV, capacity_Ah=70.0, R0_ohm=1.2e-3, R1_ohm=0.8e-3, tau1_s=32.0,
        R2_ohm=1.0e-3, tau2_s=600.0, gamma=0.0, soc0=0.9,
    )  # fmt: skip
    u1 = 0.8e-3 * 70.0 * (1 - np.exp(-t / 32.0))
    u2 = 1.0e-3 * 70.0 * (1 - np.exp(-t / 600.0))
    np.testing.assert_allclose(sim.U1_V[0], u1, rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(sim.U2_V[0], u2, rtol=1e-12, atol=1e-15)
    z = 0.9 - 70.0 * t / (70.0 * 3600.0)
    np.testing.assert_allclose(sim.soc, z, rtol=1e-12)
    expected = OCV.ocv(z) - u1 - u2 - 1.2e-3 * 70.0
    np.testing.assert_allclose(sim.v_V[0], expected, rtol=1e-12)


def test_hysteresis_sign_follows_plett() -> None:
    h = np.array([0.0])
    for _ in range(2000):
        h = hysteresis_step(h, 10.0, 1.0, 1e-3)  # discharge
    assert h[0] < -0.99
    for _ in range(2000):
        h = hysteresis_step(h, -10.0, 1.0, 1e-3)  # charge
    assert h[0] > 0.99
    assert hysteresis_step(np.array([0.3]), 0.0, 5.0, 1e-3)[0] == 0.3  # rest: unchanged


def test_discharge_branch_lies_below_the_mean() -> None:
    t = np.arange(0.0, 3600.0, 1.0)
    i = np.full_like(t, 7.0)
    sim = simulate(
        t, i, OCV, capacity_Ah=70.0, R0_ohm=0.0 + 1e-9, R1_ohm=1e-9, tau1_s=1.0,
        R2_ohm=1e-9, tau2_s=2.0, gamma=100.0, soc0=0.8,
    )  # fmt: skip
    assert sim.v_V[0, -1] < OCV.ocv(sim.soc[-1:])[0] - 0.014


@settings(max_examples=30, deadline=None)
@given(st.integers(2, 6), st.integers(0, 2**31 - 1))
def test_vectorised_sets_equal_single_runs(p: int, seed: int) -> None:
    rng = np.random.default_rng(seed)
    t = np.cumsum(rng.uniform(0.1, 3.0, 300))
    i = rng.normal(0, 50, 300)
    r0, r1, r2 = rng.uniform(1e-4, 5e-3, (3, p))
    t1, t2 = rng.uniform(1, 50, p), rng.uniform(100, 2000, p)
    g = rng.uniform(0, 100, p)
    many = simulate(t, i, OCV, capacity_Ah=70, R0_ohm=r0, R1_ohm=r1, tau1_s=t1, R2_ohm=r2,
                    tau2_s=t2, gamma=g, soc0=0.5, n_sets=p)  # fmt: skip
    for k in range(p):
        one = simulate(t, i, OCV, capacity_Ah=70, R0_ohm=r0[k], R1_ohm=r1[k], tau1_s=t1[k],
                       R2_ohm=r2[k], tau2_s=t2[k], gamma=g[k], soc0=0.5)  # fmt: skip
        np.testing.assert_allclose(many.v_V[k], one.v_V[0], rtol=1e-12)


@given(st.floats(-1.0, 2.0, allow_nan=False))
def test_ocv_never_takes_the_log_of_a_nonpositive_number(z: float) -> None:
    v = OCV.ocv(np.array([z]))
    assert np.isfinite(v).all()
    zc, flag = OCV.clamp(np.array([z]))
    assert OCV.soc_min <= zc[0] <= OCV.soc_max
    assert bool(flag[0]) == (not OCV.soc_min <= z <= OCV.soc_max)


def test_soc_from_ocv_inverts_the_curve() -> None:
    z = np.linspace(0.05, 0.95, 19)
    np.testing.assert_allclose(OCV.soc_from_ocv(OCV.ocv(z)), z, atol=1e-3)


def test_a_capacity_per_sample_counts_against_the_present_capacity() -> None:
    t = np.arange(0.0, 900.0, 1.0)
    i = np.where(t < 600, 70.0, -35.0)
    q = 70.0 * (1.0 - 0.2 * t / t[-1])  # a (fast) fade
    kw = {"R0_ohm": 1.2e-3, "R1_ohm": 0.8e-3, "tau1_s": 32.0, "R2_ohm": 1e-3, "tau2_s": 600.0,
          "gamma": 30.0, "soc0": 0.9}  # fmt: skip
    sim = simulate(t, i, OCV, capacity_Ah=q, **kw)
    z = 0.9 + np.concatenate(([0.0], np.cumsum(-i[:-1] / (q[:-1] * 3600.0))))
    np.testing.assert_allclose(sim.soc, z, rtol=0, atol=1e-14)
    same = simulate(t, i, OCV, capacity_Ah=np.full_like(t, 70.0), **kw)
    scalar = simulate(t, i, OCV, capacity_Ah=70.0, **kw)
    np.testing.assert_array_equal(same.v_V, scalar.v_V)
    np.testing.assert_array_equal(same.h, scalar.h)
    with pytest.raises(ValueError, match="one value per sample"):
        simulate(t, i, OCV, capacity_Ah=q[:-1], **kw)
