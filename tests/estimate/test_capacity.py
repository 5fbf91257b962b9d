"""The capacity estimate from anchor pairs (``estimate/capacity.py``)."""

from __future__ import annotations

import numpy as np
from hypothesis import given
from hypothesis import strategies as st

from bmsid.estimate.capacity import CapacityTracker

UNIX_T0_S = 1.7e9


def _track(t0_s: float, q_Ah: float, dz: float, gap_s: float) -> CapacityTracker:
    """Two anchors ``dz`` apart with the charge of a ``q_Ah`` cell moved between, from ``t0_s``."""
    cap = CapacityTracker(np.array([70.0]), prior_rel=0.05, min_dsoc=0.2,
                          fade_rel_per_sqrt_day=0.005)  # fmt: skip
    cells = np.array([True])
    cap.anchor(t0_s, np.array([0.9]), np.array([1e-4]), 0.0, cells)
    cap.count(q_Ah * dz)
    cap.anchor(t0_s + gap_s, np.array([0.9 - dz]), np.array([1e-4]), 0.0, cells)
    return cap


@given(
    q_Ah=st.floats(55.0, 85.0),
    dz=st.floats(0.2, 0.8),
    gap_s=st.floats(600.0, 30 * 86400.0),
    t0_s=st.sampled_from([0.0, 3600.0, UNIX_T0_S]),
)
def test_the_capacity_does_not_depend_on_the_clocks_origin(
    q_Ah: float, dz: float, gap_s: float, t0_s: float
) -> None:
    ref, got = _track(0.0, q_Ah, dz, gap_s), _track(t0_s, q_Ah, dz, gap_s)
    np.testing.assert_allclose(got.q_Ah, ref.q_Ah, rtol=1e-9)
    np.testing.assert_allclose(got.var_Ah2, ref.var_Ah2, rtol=1e-6)
    # the prior still weighs: one pair moves the estimate only part of the way
    assert abs(got.q_Ah[0] - 70.0) < abs(q_Ah - 70.0) or abs(q_Ah - 70.0) < 1e-9


def test_a_checkpoint_from_before_the_fix_keeps_its_prior() -> None:
    """Older checkpoints stored 0.0 for "no fusion yet": on a Unix-time clock that counted the
    fade since 1970 into the prior, and the first pair replaced the capacity whole."""
    fresh = CapacityTracker(np.array([70.0]), 0.05, 0.2, 0.005)
    state = fresh.state_dict() | {"t_s": 0.0}
    restored = CapacityTracker(np.array([70.0]), 0.05, 0.2, 0.005)
    restored.load_state_dict(state)
    cells = np.array([True])
    restored.anchor(UNIX_T0_S, np.array([0.9]), np.array([1e-4]), 0.0, cells)
    restored.count(80.0 * 0.5)  # a pair that says 80 Ah
    restored.anchor(UNIX_T0_S + 7200.0, np.array([0.4]), np.array([1e-4]), 0.0, cells)
    assert 70.0 < restored.q_Ah[0] < 78.0  # pulled towards 80, not replaced by it
