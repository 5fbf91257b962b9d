"""The SOC grid of the learnt hysteresis half-gap (estimate/hysteresis_map.py)."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from bmsid.estimate.hysteresis_map import hat_matrix, map_knots

SOCS = arrays(np.float64, st.integers(1, 40), elements=st.floats(-0.5, 1.5))
# a table's knots lie apart (a step within 1e-6 of SOC is merged into one knot)
TABLES = st.lists(st.floats(0.0, 1.0), min_size=1, max_size=12, unique=True).filter(
    lambda xs: len(xs) < 2 or float(np.diff(np.sort(xs)).min()) > 1e-3
)


@settings(max_examples=200, deadline=None)
@given(TABLES, SOCS)
def test_the_grid_holds_the_table_so_the_prior_is_the_table(table_soc: list[float], z) -> None:
    t_soc = np.sort(np.asarray(table_soc))
    t_m = np.linspace(0.02, 0.01, t_soc.shape[0])  # any half-gaps
    knots = map_knots(t_soc)
    assert np.all(np.diff(knots) > 1e-6)  # no zero-width region
    assert knots[0] <= 1e-6 and knots[-1] >= 1.0 - 1e-6
    W = hat_matrix(knots, z)
    np.testing.assert_allclose(W.sum(axis=1), 1.0, rtol=0, atol=1e-12)
    assert np.all(W >= 0.0) and np.all((W > 0).sum(axis=1) <= 2)
    prior = np.interp(knots, t_soc, t_m)
    np.testing.assert_allclose(W @ prior, np.interp(np.clip(z, 0, 1), t_soc, t_m), atol=1e-15)


def test_a_correction_at_one_knot_moves_only_its_two_regions() -> None:
    knots = map_knots(np.array([0.0, 1.0]))
    d = np.zeros(knots.shape[0])
    d[3] = 0.005  # the 30 % knot
    z = np.array([0.1, 0.2, 0.25, 0.3, 0.35, 0.4, 0.5])
    np.testing.assert_allclose(hat_matrix(knots, z) @ d, [0, 0, 0.0025, 0.005, 0.0025, 0, 0])
