"""The hysteresis state's error, one for the pack: a state of the SOC observer (``observer.py``;
issue 11: "SOC and hysteresis state corrected from the measured voltage").

Plett's one-state hysteresis (Eq. 5-6) moves h towards -1 on discharge and +1 on charge at the
rate gamma, which no test here measures (every shipped cell config says 30), and under a mixed
current (a drive's regenerative pulses) h settles where the charge it saw in each direction
balances, whatever gamma is. Taken as exact, its error goes into SOC at every rest: on an LFP
plateau (about 1 mV of OCV per SOC point) a 10 mV hysteresis error is 10 points of SOC.

So the observer carries the error ``dh`` of h, one for the pack (the cells share the current
that drives h): ``h_true = h + dh``, ``dv_c / d dh = M_c``, the half-gap the model voltage uses
(0 for the variants without hysteresis). Its variance follows h's own dynamics: a current that
moves h a fraction ``1 - A`` of the way to a branch, ``A = exp(-kappa int |i| dt)`` (Eq. 6),
forgets that fraction of what was known of it, and what is then known is what a bounded state
allows: h in [-1, 1] with mean h has a variance of at most ``1 - h^2`` (Bhatia-Davis); spread
uniformly over what is still possible, ``(1 - h^2) / 3``. Saturated (|h| -> 1, after a long
charge or discharge) h is known; between the branches it is not. A rest then splits its
voltage error between SOC and h by their variances: on LFP (flat OCV, large M) mostly into h,
on NMC (steep OCV, small M) mostly into SOC. The estimate is folded into every cell's h after
each update, so ``dh`` is 0 again (an error state); only its covariance, the last row and
column of the observer's P, is kept.

Both the observer's numpy path and its compiled update call these ``@helper``s (the compiled
kernels name this file in their ``depends``).
"""

from __future__ import annotations

import math

from bmsid.estimate.jit_helpers import helper
from bmsid.estimate.stage import FloatArray


@helper
def target_variance(h: FloatArray, floor: float) -> float:
    """The variance of h's error once the current has moved it: the cells' mean of
    ``(1 - h^2) / 3`` (module docstring), at least ``floor`` (the play law's: its h sits at a
    branch, and how soon it got there depends on the rate, which is not measured)."""
    n = h.shape[0]
    acc = 0.0
    for c in range(n):
        hc = min(max(h[c], -1.0), 1.0)
        acc += (1.0 - hc * hc) / 3.0
    return max(acc / n if n else 0.0, floor)


@helper
def predict(P: FloatArray, log_decay: FloatArray, v_target: float) -> None:
    """Propagate the error's row of P (the last) over the interval whose h decays are
    ``log_decay`` (per cell, ``-kappa int |i| dt``, summed): scaled by their mean's ``A``, its
    variance pulled to ``v_target`` by ``1 - A^2``; ``log_decay`` zeroed (both in place)."""
    n, j = log_decay.shape[0], P.shape[0] - 1
    s = 0.0
    for c in range(n):
        s += log_decay[c]
        log_decay[c] = 0.0
    a = math.exp(s / n) if n else 1.0
    for k in range(j):
        P[j, k] = a * P[j, k]
        P[k, j] = P[j, k]
    P[j, j] = a * a * P[j, j] + (1.0 - a * a) * v_target


@helper
def fold(h: FloatArray, dh: float) -> FloatArray:
    """Every cell's h with the estimated error ``dh`` added, within [-1, 1] (a new array)."""
    out = h.copy()
    for c in range(h.shape[0]):
        out[c] = min(max(h[c] + dh, -1.0), 1.0)
    return out
