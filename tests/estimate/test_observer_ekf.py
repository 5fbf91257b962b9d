"""The observer's EKF update (estimate/observer_ekf.py) against Joseph's form written out.

The module forms P H' and H P H' from the sparse H (one SOC column per cell, the offset, the
hysteresis map); the reference below builds H dense and applies the textbook
(I - K H) P (I - K H)' + K R K' with the consider gain (the offset's row zeroed for unforced
cells)."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from bmsid.estimate.observer_ekf import joint_update


def _reference(P, n, idx, hz, hb, G, e, r, forced, consider):  # type: ignore[no-untyped-def]
    """Dense H, Kalman gain, the offset row zeroed for unforced cells, Joseph's form."""
    N = P.shape[0]
    H = np.zeros((idx.size, N))
    H[np.arange(idx.size), idx] = hz[idx]
    H[:, n] = hb[idx]
    H[:, n + 1 :] = G[idx]
    S = H @ P @ H.T + np.diag(r[idx])
    K = P @ H.T @ np.linalg.inv(S)
    if consider:
        K[n, ~forced[idx]] = 0.0
    A = np.eye(N) - K @ H
    P_new = A @ P @ A.T + K @ np.diag(r[idx]) @ K.T
    return K @ e[idx], P_new


@settings(max_examples=150, deadline=None)
@given(
    n=st.integers(1, 8),
    k=st.integers(0, 3),
    seed=st.integers(0, 2**32 - 1),
    consider=st.booleans(),
)
def test_the_update_is_josephs_form_of_the_consider_gain(
    n: int, k: int, seed: int, consider: bool
) -> None:
    rng = np.random.default_rng(seed)
    N = n + 1 + k
    A = rng.normal(size=(N, N))
    P = A @ A.T * 1e-3 + np.eye(N) * 1e-4
    hz = rng.uniform(0.05, 2.0, n)
    hb = rng.uniform(0.001, 0.2, n)
    G = rng.normal(size=(n, k)) * 0.5
    e = rng.normal(size=n) * 1e-3
    r = rng.uniform(1e-6, 1e-4, n)
    forced = rng.random(n) < 0.3
    idx = np.flatnonzero(rng.random(n) < 0.8)
    step = joint_update(P, n, idx, hz, hb, G, e, r, forced, gate_sigmas=1e9,
                        consider_offset=consider)  # fmt: skip
    if idx.size == 0:
        assert step.dx is None
        return
    dx_ref, P_ref = _reference(P, n, idx, hz, hb, G, e, r, forced, consider)
    assert step.dx is not None and step.P is not None
    np.testing.assert_allclose(step.dx, dx_ref, rtol=1e-7, atol=1e-12)
    P_ref = 0.5 * (P_ref + P_ref.T)
    np.testing.assert_allclose(step.P, P_ref, rtol=1e-6, atol=1e-12 * np.abs(P).max())


def test_a_gated_cell_is_left_out_and_counted() -> None:
    P = np.eye(3) * 1e-2
    hz, hb, G = np.array([1.0, 1.0]), np.array([0.01, 0.01]), np.zeros((2, 0))
    e, r = np.array([1e-3, 1.0]), np.full(2, 1e-6)
    forced = np.zeros(2, dtype=bool)
    step = joint_update(P, 2, np.arange(2), hz, hb, G, e, r, forced, 5.0, consider_offset=True)
    assert step.n_gated == 1
    assert step.dx is not None
    assert step.dx[1] == pytest.approx(0.0)  # the gated cell's SOC did not move
    assert step.dx[2] == 0.0  # unforced: the offset is a consider state
