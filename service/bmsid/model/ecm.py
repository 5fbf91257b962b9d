"""The zero-order-hold step of the hysteresis 2RC model (Eq. 2, 5-8): written once, used by the
simulator, the estimators' state propagation and the swarm's window fits.

States: SOC z (fraction), the RC branch states and Plett's hysteresis state h in [-1, 1]. Over an
interval dt the current i is held (ZOH), which makes each step exact for any dt:

* SOC (Eq. 2): ``z+ = z - eta i dt / Q`` with eta applied on charge (i < 0) only, Q in A s;
* RC branch (Eq. 7-8): ``u+ = a u + g (1 - a) i`` with ``a = exp(-dt / tau)``; ``g`` = R gives the
  branch voltage (V), ``g`` = 1 the unit-gain state x (A) that the estimators use (U = R x);
* hysteresis (Eq. 5-6, Plett's sign): ``h+ = exp(-|kappa i| dt) h - (1 - exp(-|kappa i| dt))
  sgn(i)``, kappa = eta gamma / Q in 1/(A s): discharge drives h to -1, charge to +1; or, as a
  play operator (``play``, the cell config's ``hysteresis.law``), ``h+ = clip(h - 2 kappa i dt,
  -1, 1)``: the same initial rate off a branch, but a short reversal leaves h near its branch.

Positive current = discharge throughout.
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

FloatArray = npt.NDArray[np.float64]
Num = float | FloatArray


def charge_efficiency(current_A: Num, eta: Num) -> Num:
    """Coulombic efficiency that applies to ``current_A``: ``eta`` on charge, 1 on discharge."""
    if isinstance(current_A, float):  # one held current (the estimators' case): no array op
        return eta if current_A < 0 else 1.0
    return np.asarray(np.where(np.asarray(current_A) < 0, eta, 1.0), dtype=np.float64)


def soc_delta(current_A: Num, dt_s: Num, capacity_As: Num, eta: Num) -> FloatArray:
    """Change of SOC (fraction) over ``dt_s`` at the held ``current_A`` (Eq. 2)."""
    return -charge_efficiency(current_A, eta) * current_A * dt_s / capacity_As  # type: ignore[return-value]


def soc_step(z: Num, current_A: Num, dt_s: Num, capacity_As: Num, eta: Num) -> FloatArray:
    """SOC after ``dt_s`` at the held ``current_A`` (Eq. 2); not clamped (see ``OcvModel``)."""
    return z + soc_delta(current_A, dt_s, capacity_As, eta)


def rc_decay(dt_s: Num, tau_s: Num) -> FloatArray:
    """ZOH pole ``a = exp(-dt / tau)`` of an RC branch (Eq. 7)."""
    return np.exp(-dt_s / np.asarray(tau_s))


def rc_step(u: Num, a: Num, current_A: Num, gain: Num = 1.0) -> FloatArray:
    """One exact ZOH step of an RC branch (Eq. 8): ``a u + gain (1 - a) i``.

    ``gain`` = R (ohm) steps the branch voltage in V; the default 1 steps the unit-gain state
    (A), whose voltage is R x: the form the estimators use, linear in R.
    """
    return a * u + gain * (1.0 - a) * current_A  # type: ignore[return-value]


def branches_step(
    x1: FloatArray,
    x2: FloatArray,
    tau1_s: FloatArray,
    tau2_s: FloatArray,
    current_A: float,
    dt_s: float,
) -> tuple[FloatArray, FloatArray]:
    """Both unit-gain branch states of the 2RC model over ``dt_s`` at the held current (Eq. 8);
    unchanged when ``dt_s`` <= 0 (the first sample, a time base that jumped back)."""
    if dt_s <= 0:
        return x1, x2
    # rc_step(x, rc_decay(dt_s, tau), current_A) inlined (a gain of 1 multiplies by 1.0: the
    # same numbers); this runs every tick, the calls were a third of its cost on one cell
    a1 = np.exp(-dt_s / tau1_s)
    a2 = np.exp(-dt_s / tau2_s)
    return a1 * x1 + (1.0 - a1) * current_A, a2 * x2 + (1.0 - a2) * current_A


def rc_filter(current_A: FloatArray, a: float) -> FloatArray:
    """``rc_step`` with unit gain iterated over a whole window from x_0 = 0: ``x_k = a x_(k-1) +
    (1 - a) i_(k-1)`` for k = 0..W-1 (state *before* sample k's current acts). One C-level
    recursion per window, what the swarm's window fits need; equal to the loop to rounding.

    scipy.signal is imported here, not with the module: it imports scipy.stats and optimize
    (75 MB of resident memory, 0.65 s), which a run on the compiled kernels never needs."""
    from scipy.signal import lfilter  # noqa: PLC0415 (see above)

    return np.asarray(lfilter([0.0, 1.0 - a], [1.0, -a], current_A), dtype=np.float64)


def hysteresis_kappa(gamma: Num, capacity_As: Num, eta: Num, current_A: Num) -> FloatArray:
    """The paper's decay factor kappa in 1/(A s) (Eq. 6) from Plett's dimensionless rate gamma:
    ``kappa = eta gamma / Q`` with eta applied on charge only."""
    return gamma / capacity_As * charge_efficiency(current_A, eta)  # type: ignore[return-value]


def hysteresis_step(
    h: Num, current_A: Num, dt_s: Num, kappa: Num, play: bool = False
) -> FloatArray:
    """Advance the hysteresis state over ``dt_s`` (s) with the current (A) held (Eq. 8, last row;
    ``play``: the play operator of the module docstring)."""
    if play:
        return np.clip(h - 2.0 * np.asarray(kappa) * current_A * dt_s, -1.0, 1.0)
    decay = np.exp(-np.abs(np.asarray(kappa) * current_A) * dt_s)
    return decay * h - (1.0 - decay) * np.sign(current_A)
