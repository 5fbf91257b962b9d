"""AFFRLS (Eq. 16-21) and LPSO (Eq. 24-30) building blocks."""

from __future__ import annotations

import itertools

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from bmsid.estimate import lpso
from bmsid.estimate.affrls import adaptive_lambda, reset_covariance, rls_update


@given(st.floats(-10, 10), st.floats(1e-6, 1.0), st.floats(0.5, 0.999), st.floats(0.01, 0.99))
def test_lambda_stays_in_its_interval(e: float, e_base: float, lmin: float, base: float) -> None:
    lam = adaptive_lambda(np.array([e]), np.array([e_base]), lmin, 1.0, base)
    assert lmin <= lam[0] <= 1.0
    small = adaptive_lambda(np.array([0.0]), np.array([e_base]), lmin, 1.0, base)
    assert small[0] == 1.0  # no surprise -> maximal memory (Eq. 21)


def test_rls_recovers_a_linear_model_and_bounds_its_trace() -> None:
    rng = np.random.default_rng(0)
    truth = np.array([[1.0, -2.0, 0.5]])
    theta = np.zeros((1, 3))
    P = reset_covariance(1, 3, 1e4)
    for _ in range(500):
        phi = rng.normal(size=(1, 3))
        y = (phi * truth).sum(1) + rng.normal(0, 1e-3)
        e = y - (phi * theta).sum(1)
        theta, P = rls_update(theta, P, phi, e, np.array([0.99]), np.array([True]), 1e3)
        assert np.trace(P[0]) <= 1e3 * (1 + 1e-12)
    np.testing.assert_allclose(theta, truth, atol=1e-3)


def test_rls_leaves_inactive_rows_untouched() -> None:
    theta = np.ones((2, 2))
    P = reset_covariance(2, 2, 1.0)
    t2, P2 = rls_update(theta, P, np.ones((2, 2)), np.ones(2), np.ones(2),
                        np.array([True, False]), 1e6)  # fmt: skip
    assert not np.allclose(t2[0], 1.0)
    np.testing.assert_array_equal(t2[1], theta[1])
    np.testing.assert_array_equal(P2[1], P[1])


def _run(seed: int) -> lpso.Swarm:
    rng = np.random.default_rng(seed)
    lo, hi = np.array([-5.0, -5.0]), np.array([5.0, 5.0])
    s = lpso.swarm_init(lo, hi, 16, 40, rng)
    p = lpso.SwarmParams()
    while not s.done:
        f = ((s.x - np.array([1.5, -2.0])) ** 2).sum(1)
        s = lpso.swarm_tell(s, f, rng, p)
        assert np.all(s.x >= lo) and np.all(s.x <= hi)
    return s


def test_swarm_finds_the_minimum_inside_the_bounds_reproducibly() -> None:
    a, b = _run(3), _run(3)
    np.testing.assert_allclose(a.gbest, [1.5, -2.0], atol=1e-2)
    np.testing.assert_array_equal(a.gbest, b.gbest)


def test_inertia_schedule_decreases_from_w_max_to_w_min() -> None:
    p = lpso.SwarmParams(w_max=0.9, w_min=0.4, shape=0.5)
    w = [lpso.inertia(k, 20, p) for k in range(21)]
    assert w[0] == 0.9 and all(a >= b for a, b in itertools.pairwise(w))
    assert abs(w[-1] - 0.4) < 0.01


@settings(max_examples=20, deadline=None)
@given(st.floats(-100, 100), st.floats(-100, 100))
def test_swarm_clamps_particles_starting_anywhere(x0: float, x1: float) -> None:
    rng = np.random.default_rng(0)
    lo, hi = np.array([0.0, 0.0]), np.array([1.0, 1.0])
    s = lpso.swarm_init(lo, hi, 6, 5, rng, seeds=np.array([[x0, x1]]))
    assert np.all((s.x >= lo) & (s.x <= hi))
