"""Bilinear ARX mapping (Eq. 11-15, corrected Eq. 22-23): round trip and explicit failures."""

from __future__ import annotations

import numpy as np
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from bmsid.model.arx import (
    MapStatus,
    _theta_to_params,
    _theta_to_params_rows,
    denominator_condition,
    params_to_theta,
    theta_to_params,
)

R = st.floats(1e-4, 0.1)  # ohm: 0.1 mOhm .. 100 mOhm
TAU = st.floats(0.1, 5000.0)  # s
T = st.floats(0.01, 10.0)  # s


def test_paper_notes_example_round_trips() -> None:
    th = params_to_theta(1.2e-3, 0.8e-3, 32.0, 1.0e-3, 600.0, 1.0)
    assert abs(float(denominator_condition(th)) - 5.12e-5) < 1e-7
    p, status = theta_to_params(th, 1.0)
    assert status == MapStatus.OK
    np.testing.assert_allclose(
        [p.R0_ohm, p.R1_ohm, p.tau1_s, p.R2_ohm, p.tau2_s, p.C1_F, p.C2_F],
        [1.2e-3, 0.8e-3, 32.0, 1.0e-3, 600.0, 40e3, 600e3],
        rtol=1e-9,
    )


def test_branch_order_is_fast_first_whatever_the_input_order() -> None:
    th = params_to_theta(1.2e-3, 1.0e-3, 600.0, 0.8e-3, 32.0, 1.0)
    p, _ = theta_to_params(th, 1.0)
    assert float(p.tau1_s) < float(p.tau2_s)
    np.testing.assert_allclose([p.R1_ohm, p.R2_ohm], [0.8e-3, 1.0e-3], rtol=1e-9)


@settings(max_examples=400, deadline=None)
@given(R, R, TAU, R, TAU, T)
def test_round_trip_where_well_conditioned(
    r0: float, r1: float, ta: float, r2: float, tb: float, t_s: float
) -> None:
    """Where it is well conditioned the map is exact to 1e-5 relative.

    Measured over 200k random draws: the relative error grows like ~1e-12 / (1 - th1 - th2), so
    we require both bilinear denominators 1 - th1 - th2 and 1 + th1 - th2 > 1e-6 (i.e. T is not
    tiny against sqrt(tau1 tau2), nor huge against the taus) and distinct branches
    (tau2 / tau1 > 1.5). Outside that, e.g. tau = 5000 s at T = 0.01 s, the ARX form cannot
    carry the time constants in float64 at all: the reason bmsid decimates before identifying
    and lets the swarm own the poles.
    """
    t1, t2 = min(ta, tb), max(ta, tb)
    assume(t2 / t1 > 1.5)
    th = params_to_theta(r0, r1, t1, r2, t2, t_s)
    assume(float(denominator_condition(th)) > 1e-6)
    assume(float(1 + th[0] - th[1]) > 1e-6)
    p, status = theta_to_params(th, t_s)
    assert status == MapStatus.OK
    got = np.array([p.R0_ohm, p.R1_ohm, p.tau1_s, p.R2_ohm, p.tau2_s], dtype=float)
    np.testing.assert_allclose(got, [r0, r1, t1, r2, t2], rtol=1e-5)


@given(st.lists(st.floats(allow_nan=True, allow_infinity=True, width=64), min_size=5, max_size=5))
def test_any_theta_gives_finite_output_and_a_status(theta: list[float]) -> None:
    p, status = theta_to_params(np.array(theta), 1.0)
    vals = np.array([p.R0_ohm, p.R1_ohm, p.tau1_s, p.R2_ohm, p.tau2_s], dtype=float)
    assert np.all(np.isfinite(vals))
    if status == MapStatus.OK:
        assert np.all(vals > 0)
    else:
        assert np.all(vals == 0)


def test_failure_statuses_are_explicit() -> None:
    # poles outside the unit circle
    _, s = theta_to_params(np.array([1.5, 0.0, -1e-3, 1e-3, 0.0]), 1.0)
    assert s == MapStatus.UNSTABLE
    # complex conjugate poles (oscillatory, not two RC branches)
    _, s = theta_to_params(np.array([1.0, -0.5, -1e-3, 1e-3, 0.0]), 1.0)
    assert s == MapStatus.COMPLEX_POLES
    # negative resistance: flip the sign of the numerator
    th = -params_to_theta(1.2e-3, 0.8e-3, 32.0, 1.0e-3, 600.0, 1.0)
    th[:2] *= -1
    _, s = theta_to_params(th, 1.0)
    assert s == MapStatus.NONPOSITIVE_R
    _, s = theta_to_params(np.array([np.nan, 0, 0, 0, 0]), 1.0)
    assert s == MapStatus.NOT_FINITE


def _both_paths(theta: np.ndarray, t_s: float) -> None:
    """The per-set Python path (few rows) and the array path give the same bits."""
    with np.errstate(all="ignore"):
        v_arr, s_arr = _theta_to_params(theta, t_s)
    v_row, s_row = _theta_to_params_rows(theta, t_s)
    np.testing.assert_array_equal(s_row, s_arr, strict=True)
    np.testing.assert_array_equal(v_row, v_arr, strict=True)


@given(
    st.lists(
        st.lists(st.floats(allow_nan=True, allow_infinity=True, width=64), min_size=5, max_size=5),
        min_size=1, max_size=4,
    ),
    T,
)  # fmt: skip
def test_scalar_path_equals_array_path_any_theta(rows: list[list[float]], t_s: float) -> None:
    _both_paths(np.array(rows, dtype=np.float64), t_s)


@settings(max_examples=300)
@given(R, R, TAU, R, TAU, T, st.floats(-1e-3, 1e-3), st.floats(-1e-3, 1e-3))
def test_scalar_path_equals_array_path_near_real_sets(
    r0: float, r1: float, t1: float, r2: float, t2: float, t_s: float, d1: float, d2: float
) -> None:
    th = params_to_theta(r0, r1, t1, r2, t2, t_s)
    bent = th * np.array([1.0 + d1, 1.0 + d2, 1.0 - d1, 1.0, 1.0 + d2])  # invalid sets too
    _both_paths(np.stack([th, bent]), t_s)
