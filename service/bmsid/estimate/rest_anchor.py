"""When the pack rests, and when a rest anchors a cell's SOC to its OCV (``observer.py``, issue
11 item 4).

A rest is a current within the rest limit after the offset, or a measured current within the
rest limit of the rests' reading (their running mean, ``REST_MEAN_S``), whatever the offset
estimate says: tested on i - b alone, a rest ended when b moved past the limit and none began
again, so b stayed a consider state, frozen where it stood, and h drifted on the count's
current (``offset-0.7-soc-wrong``: b 1.5 A for 0.7, 1.8 h without a rest, h -0.67 -> +0.10;
A123 DYN50: b -0.024 A for 8 h, its 12-minute rests unseen, the sensor reading 0.000 there).
At a rest the sensor reads its offset plus a draw within the rest limit, so b stays within that
limit of the reading, and once a rest (at its first anchor) the reading is a measurement of b
(``draw_update``): the draw, unknown within the limit either way, is its error. Before, b was
learnt at a rest only through the model's IR term (dv/db = R0 + R1 + R2, 2 mV per A on a 70 Ah
cell), which took a few mV of model error at a rest for an offset of an ampere: the first rest
of a +0.5 A offset drove b to 1.05 A, and on the A123 DYN50 (a tester's current, 0.000 A at
rest) b sat at -0.02 A for hours and the count drifted a SOC point an hour.

A rest anchors once it has lasted ``anchor_rest_taus`` identified slow time constants (the RC
branches relaxed to within exp(-3) = 5 %; tau2 as identified under load before the rest: the
observer's SOC corrections during the rest read as a slower relaxation to the fits, which put
the anchor off by itself) and at least ``anchor_min_rest_s``
(``ObserverTuning``). In a pack of 3 or more cells a cell's tau2 counts at most as the cells'
median: a cell short of capacity reads its count's drift as a slow relaxation and inflates
its own tau2, which would keep it from the anchors that measure its capacity.
"""

from __future__ import annotations

import math

import numpy as np

from bmsid.estimate.jit_helpers import helper
from bmsid.estimate.observer_tuning import ObserverTuning
from bmsid.estimate.stage import BoolArray, FloatArray

#: The rests' reading before any rest, A (finite: checkpoints), and its running mean's time
#: constant over rest ticks, s: seconds of light load hardly move it.
NO_REST_A, REST_MEAN_S = 1e30, 60.0
#: The current sensor's noise: its running estimate's time constant over ticks at rest, s.
NOISE_MEAN_S = 600.0

# The ``@helper``s below (all but ``noise_std_A``, numpy's, for a record's head): the compiled
# step and fused loop call them too (both name this file in their ``depends``).


@helper
def at_rest_reading(i_meas_A: float, reading_A: float, limit_A: float) -> bool:
    """The measured current (A) is the rests' reading within the rest limit (A)."""
    return abs(i_meas_A - reading_A) < limit_A


@helper
def next_rest_reading(reading_A: float, i_meas_A: float, dt_s: float) -> float:
    """The rests' reading (A) after a rest tick of ``dt_s`` (s) measuring ``i_meas_A`` (A)."""
    w = 1.0 if reading_A >= NO_REST_A else min(1.0, dt_s / REST_MEAN_S)
    return i_meas_A if w >= 1.0 else reading_A + (i_meas_A - reading_A) * w


@helper
def offset_within_rest(b_A: float, reading_A: float, limit_A: float) -> float:
    """The offset estimate (A) within the rest limit (A) of the rests' reading (A)."""
    return min(max(b_A, reading_A - limit_A), reading_A + limit_A)


@helper
def next_noise(sd_A: float, i_A: float, i_prev_A: float, base_A: float, dt_s: float) -> float:
    """The current sensor's noise std (A) after a tick measuring ``i_A`` (A) after one measuring
    ``i_prev_A`` (A; NaN: none), from the |difference| of the two (two draws of the noise, an
    offset or a steady draw cancels; its mean is 2 std / sqrt(pi) for Gaussian noise, and the
    mean of |d| is not carried off by a few larger steps as a mean square is) where both lie
    at rest (within the rest limit ``base_A`` plus 3 std: a drive's current crossing zero is
    no noise), at most 2 base (a step into a light load), averaged over ``NOISE_MEAN_S`` (the
    first such pair taken whole: a start at rest must not wait ten minutes for its noise)."""
    near = rest_limit(base_A, sd_A)
    if not (dt_s > 0.0 and abs(i_A) < near and abs(i_prev_A) < near):  # (NaN: False)
        return sd_A
    w = 1.0 if sd_A <= 0.0 else min(1.0, dt_s / NOISE_MEAN_S)
    return sd_A + w * (min(0.5 * math.sqrt(math.pi) * abs(i_A - i_prev_A), 2.0 * base_A) - sd_A)


def noise_std_A(current_A: FloatArray, base_A: float) -> float:
    """The current sensor's noise std (A) over a stretch of samples (A), as ``next_noise`` sees
    it but robustly, for a record's head: 1.4826 x the median |difference| of successive
    samples at rest (within the rest limit ``base_A`` plus 3 of this std, found by iterating
    from the bare limit: a noise as large as the limit is not truncated to it) / sqrt(2), at
    most 2 base; 0 with fewer than 10 such pairs (a tester's 0.000 A at rest: 0)."""
    i = np.asarray(current_A, dtype=np.float64)
    sd = 0.0
    for _ in range(4):  # 0.02 A of noise on a 0.02 A limit: 0.012, then 0.020 A
        near = np.abs(i) < rest_limit(base_A, sd)  # (NaN: False)
        d = np.diff(i)[near[1:] & near[:-1]]
        if d.size < 10:
            return sd
        sd = min(float(1.4826 * np.median(np.abs(d)) / math.sqrt(2.0)), 2.0 * base_A)
    return sd


@helper
def rest_limit(base_A: float, sd_A: float) -> float:
    """The rest limit (A): the configured one ``base_A`` plus 3 std of the sensor's noise
    (``next_noise``), so that noise alone does not end a rest: 10 mA on a 2 Ah cell, half its
    1 % C limit, ended a rest on one tick in twenty, and a 12-hour known-truth record anchored
    once instead of four times (its SOC 3.9 points RMS off instead of 0.8)."""
    return base_A + 3.0 * max(sd_A, 0.0)


@helper
def rest_draw(reading_A: float, b_A: float, p_bb: float) -> float:
    """The current the pack draws at rest (A, + = discharge) as far as it is known: the rests'
    reading less the offset estimate, shrunk by 2 std of the offset (``p_bb``, A^2); 0 within
    them (what the offset's uncertainty explains moves no h) and without a reading. h moves
    with it at rest (a converter left on discharges the cell along its hysteresis loop too)."""
    if reading_A >= NO_REST_A:
        return 0.0
    d = reading_A - b_A
    m = abs(d) - 2.0 * math.sqrt(max(p_bb, 0.0))
    if m <= 0.0:
        return 0.0
    return m if d > 0.0 else -m


def draw_update(
    P: FloatArray, n: int, b_A: float, reading_A: float, limit_A: float
) -> tuple[FloatArray, FloatArray]:
    """The rests' reading ``reading_A`` (A) as a measurement of the offset, index ``n`` of the
    observer's state (covariance ``P``, estimate ``b_A``, A): the pack's draw at a rest, within
    the rest limit ``limit_A`` (A) either way, taken as uniform there (variance limit^2 / 3).
    Returns the state's correction and the covariance after it (Joseph's form for H = e_n)."""
    s = P[n, n] + limit_A**2 / 3.0
    k = P[:, n] / s
    P_new = P - np.outer(k, P[n, :])
    return k * (reading_A - b_A), 0.5 * (P_new + P_new.T)


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
