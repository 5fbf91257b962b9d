"""The observer's EKF update (estimate/observer_ekf.py) against Joseph's form written out.

The module forms P H' and H P H' from the sparse H (one SOC column per cell, the offset, the
hysteresis map, the hysteresis error); the reference below builds H dense and applies the
textbook (I - K H) P (I - K H)' + K R K' with the consider gain (the offset's row zeroed for
unforced cells, the map's rows for cells that do not teach it, every entry but its own SOC's
zeroed for a lone cell)."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from bmsid.estimate.observer_ekf import joint_update
from bmsid.estimate.observer_kernel import lone_cells


def _reference(P, n, idx, hz, hb, G, e, r, forced, consider, lone, teach, n_map):  # type: ignore[no-untyped-def]
    """Dense H, Kalman gain, the offset row zeroed for unforced cells, the map's rows for cells
    not teaching it and a lone cell's column but for its own SOC, Joseph's form."""
    N = P.shape[0]
    H = np.zeros((idx.size, N))
    H[np.arange(idx.size), idx] = hz[idx]
    H[:, n] = hb[idx]
    H[:, n + 1 :] = G[idx]
    S = H @ P @ H.T + np.diag(r[idx])
    K = P @ H.T @ np.linalg.inv(S)
    if consider:
        K[n, ~forced[idx]] = 0.0
    K[n + 1 : n + 1 + n_map, ~teach[idx]] = 0.0
    for q, c in enumerate(idx):
        if lone[c]:
            own = K[c, q]
            K[:, q] = 0.0
            K[c, q] = own
    A = np.eye(N) - K @ H
    P_new = A @ P @ A.T + K @ np.diag(r[idx]) @ K.T
    return K @ e[idx], P_new


@settings(max_examples=150, deadline=None)
@given(
    n=st.integers(1, 8),
    k=st.integers(0, 3),
    seed=st.integers(0, 2**32 - 1),
    consider=st.booleans(),
    h_error=st.booleans(),
)
def test_the_update_is_josephs_form_of_the_consider_gain(
    n: int, k: int, seed: int, consider: bool, h_error: bool
) -> None:
    """``k`` map knots and, with ``h_error``, the hysteresis error after them: a state
    every update teaches (the map's consider rule is the map's alone)."""
    rng = np.random.default_rng(seed)
    N = n + 1 + k + int(h_error)
    A = rng.normal(size=(N, N))
    P = A @ A.T * 1e-3 + np.eye(N) * 1e-4
    hz = rng.uniform(0.05, 2.0, n)
    hb = rng.uniform(0.001, 0.2, n)
    G = rng.normal(size=(n, k + int(h_error))) * 0.5
    e = rng.normal(size=n) * 1e-3
    r = rng.uniform(1e-6, 1e-4, n)
    forced = rng.random(n) < 0.3
    lone = rng.random(n) < 0.3
    teach = rng.random(n) < 0.5
    idx = np.flatnonzero(rng.random(n) < 0.8)
    step = joint_update(P, n, idx, hz, hb, G, e, r, forced, gate_sigmas=1e9,
                        consider_offset=consider, lone=lone, teach=teach, n_map=k)  # fmt: skip
    if idx.size == 0:
        assert step.dx is None
        return
    dx_ref, P_ref = _reference(P, n, idx, hz, hb, G, e, r, forced, consider, lone, teach, k)
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


@settings(max_examples=200, deadline=None)
@given(
    e=st.lists(st.floats(-0.2, 0.2), min_size=1, max_size=12),
    shift=st.floats(-1.0, 1.0),
    seed=st.integers(0, 2**32 - 1),
)
def test_lone_cells_are_what_one_cell_shows_alone(e: list[float], shift: float, seed: int) -> None:
    """Fewer than 3 valid cells: none lone; a shift common to every cell (an offset) changes
    nothing; the median cell is never lone; invalid cells never are."""
    ev = np.asarray(e)
    valid = np.random.default_rng(seed).random(ev.size) < 0.8
    lone = lone_cells(ev, 1e-6, valid, 9.0)
    assert not lone[~valid].any()
    if valid.sum() < 3:
        assert not lone.any()
        return
    v = np.flatnonzero(valid)
    med = np.median(ev[v])
    thr = 9.0 * max((1.4826 * np.median(np.abs(ev[v] - med))) ** 2, 1e-6)
    clear = np.abs((ev - med) ** 2 - thr) > 1e-9  # not on the boundary, where rounding decides
    shifted = lone_cells(ev + shift, 1e-6, valid, 9.0)
    np.testing.assert_array_equal(shifted[clear], lone[clear])
    mid = v[np.argsort(ev[v])[v.size // 2]]
    assert not lone[mid]


def test_one_cell_far_off_is_lone_and_the_others_are_not() -> None:
    e = np.array([1e-3, 1.2e-3, 0.8e-3, 50e-3, 1.1e-3])
    lone = lone_cells(e, 1e-6, np.ones(5, dtype=bool), 9.0)
    np.testing.assert_array_equal(lone, [False, False, False, True, False])


def test_a_cell_that_does_not_teach_the_map_sees_its_uncertainty_and_leaves_it() -> None:
    """Consider states: a cell read through an uncertain half-gap M (its map row G) gets a
    smaller SOC gain and keeps a larger SOC variance than if M were exact (G = 0, what the
    update did before), and the map itself neither moves nor narrows."""
    n, k = 1, 2
    P = np.diag([1e-4, 1e-4, 4e-6, 4e-6])  # SOC 1 point, offset 0.01 A, M 2 mV per knot
    hz, hb, e, r = np.array([0.5]), np.array([0.01]), np.array([2e-3]), np.array([1e-6])
    G = np.array([[0.7, 0.3]])  # h s w(z)
    no = np.zeros(1, dtype=bool)
    seen = joint_update(P, n, np.arange(1), hz, hb, G, e, r, no, 1e9, False, teach=no)
    blind = joint_update(P, n, np.arange(1), hz, hb, np.zeros((1, k)), e, r, no, 1e9, False)
    assert seen.dx is not None and seen.P is not None
    assert blind.dx is not None and blind.P is not None
    assert 0.0 < seen.dx[0] < blind.dx[0]
    assert seen.P[0, 0] > blind.P[0, 0]
    np.testing.assert_array_equal(seen.dx[n + 1 :], 0.0)
    np.testing.assert_allclose(np.diag(seen.P)[n + 1 :], np.diag(P)[n + 1 :], rtol=1e-12)


def test_a_forced_cell_beyond_the_gate_updates_its_own_soc_only() -> None:
    """An anchor is forced (SOC may be far off), but one cell's 50 mV at its anchor (a glitch
    on its sense wire, the agreement test off) moved the pack's hysteresis error to its +1
    bound and its offset to -0.29 A: beyond the gate it is that cell's own SOC only."""
    n = 3
    P = np.diag([1e-4, 1e-4, 1e-4, 1e-4, 0.05])  # SOC 1 point each, offset 0.01 A, dh 0.22
    hz, hb = np.full(n, 0.5), np.full(n, 0.01)
    G = np.full((n, 1), 0.015)  # dv / d dh = M
    e, r = np.array([0.5e-3, 50e-3, -0.5e-3]), np.array([25e-6, 1e-6, 25e-6])
    forced = np.array([False, True, False])
    step = joint_update(P, n, np.arange(n), hz, hb, G, e, r, forced, 5.0, False, n_map=0)
    assert step.dx is not None
    assert step.dx[1] > 0.05  # its own SOC: 7 points up
    np.testing.assert_array_equal(step.dx[[n, n + 1]], 0.0)
