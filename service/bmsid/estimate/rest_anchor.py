"""When a rest anchors a cell's SOC to its OCV (``observer.py``, issue 11 item 4).

A rest anchors once it has lasted ``anchor_rest_taus`` identified slow time constants (the RC
branches relaxed to within exp(-3) = 5 %; tau2 as identified under load before the rest: the
observer's SOC corrections during the rest read as a slower relaxation to the fits, which put
the anchor off by itself) and at least ``anchor_min_rest_s``
(``ObserverTuning``). In a pack of 3 or more cells a cell's tau2 counts at most as the cells'
median: a cell short of capacity reads its count's drift as a slow relaxation and inflates
its own tau2, which would keep it from the anchors that measure its capacity.
"""

from __future__ import annotations

import numpy as np

from bmsid.estimate.observer_tuning import ObserverTuning
from bmsid.estimate.stage import BoolArray, FloatArray


def anchors_due(
    rest_s: float, anchored: BoolArray, tau2_s: FloatArray, tun: ObserverTuning
) -> BoolArray | None:
    """The cells a rest of ``rest_s`` (s) anchors now (not ``anchored`` in this rest yet), from
    their slow time constants ``tau2_s`` (s); None (most ticks) below ``anchor_min_rest_s``."""
    if rest_s < tun.anchor_min_rest_s:
        return None
    if tau2_s.shape[0] >= 3:
        tau2_s = np.minimum(tau2_s, np.median(tau2_s))
    return ~anchored & (rest_s >= np.maximum(tun.anchor_min_rest_s, tun.anchor_rest_taus * tau2_s))
