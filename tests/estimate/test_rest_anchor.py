"""When a rest anchors (``estimate/rest_anchor.py``): the own-tau2 rule, and in a pack of 3 or
more cells no cell waits longer than the cells' median tau2 asks."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from bmsid.estimate.observer_tuning import ObserverTuning
from bmsid.estimate.rest_anchor import anchors_due

TUN = ObserverTuning()


@settings(max_examples=200, deadline=None)
@given(
    rest_s=st.floats(0.0, 20_000.0),
    tau2=st.lists(st.floats(10.0, 5000.0), min_size=1, max_size=10),
    seed=st.integers(0, 2**32 - 1),
)
def test_a_rest_anchors_after_3_tau2_capped_at_the_packs_median(
    rest_s: float, tau2: list[float], seed: int
) -> None:
    tau = np.asarray(tau2)
    anchored = np.random.default_rng(seed).random(tau.size) < 0.3
    due = anchors_due(rest_s, anchored, tau, TUN)
    if rest_s < TUN.anchor_min_rest_s:
        assert due is None
        return
    assert due is not None and not due[anchored].any()
    own = ~anchored & (rest_s >= np.maximum(TUN.anchor_min_rest_s, 3.0 * tau))
    assert not (own & ~due).any()  # every cell its own tau2 anchors is anchored
    if tau.size < 3:
        np.testing.assert_array_equal(due, own)
    else:
        capped = ~anchored & (rest_s >= np.maximum(TUN.anchor_min_rest_s, 3.0 * np.median(tau)))
        np.testing.assert_array_equal(due, own | capped)
