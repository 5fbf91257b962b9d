"""Load profiles as pure functions of time (positive = discharge).

* DST: the USABC Dynamic Stress Test, one 360 s cycle of 20 steps, as fractions of the peak
  (table in ``shared/notes/paper-notes.md``). Used here as a *current* profile.
* BBDST-like: a 300 s stop-and-go city-bus cycle of 19 steps with regenerative pulses, the
  unofficial "BBDST working condition" step table quoted in the paper notes (relative to step 1).
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

FloatArray = npt.NDArray[np.float64]

#: (duration s, fraction of peak) for one DST cycle; negative = charge (regeneration).
DST_STEPS: tuple[tuple[float, float], ...] = (
    (16, 0.0), (28, 0.125), (12, 0.25), (8, -0.125), (16, 0.0), (24, 0.125), (12, 0.25),
    (8, -0.125), (16, 0.0), (24, 0.125), (12, 0.25), (8, -0.125), (16, 0.0), (36, 0.125),
    (8, 1.0), (24, 0.625), (8, -0.25), (32, 0.25), (8, -0.5), (44, 0.0),
)  # fmt: skip

#: (duration s, current relative to step 1) for one BBDST-like cycle (300 s).
BBDST_STEPS: tuple[tuple[float, float], ...] = (
    (21, 1.00), (12, 2.06), (16, 0.115), (6, -0.37), (21, 1.00), (16, 0.115), (6, -0.37),
    (9, 2.06), (6, 2.78), (21, 1.01), (16, 0.115), (6, -0.37), (9, 2.06), (6, 2.78),
    (21, 1.01), (16, 0.115), (9, -0.92), (12, -0.37), (71, 0.115),
)  # fmt: skip


def step_profile(
    t_s: FloatArray, steps: tuple[tuple[float, float], ...], scale_A: float
) -> FloatArray:
    """Current in A at times ``t_s`` for a cyclic step table scaled by ``scale_A`` (A per unit)."""
    durations = np.array([d for d, _ in steps], dtype=float)
    levels = np.array([f for _, f in steps], dtype=float) * scale_A
    edges = np.concatenate(([0.0], np.cumsum(durations)))
    phase = np.mod(np.asarray(t_s, dtype=float), edges[-1])
    idx = np.searchsorted(edges, phase, side="right") - 1
    return np.asarray(levels[np.clip(idx, 0, len(levels) - 1)], dtype=np.float64)


def dst_current(t_s: FloatArray, peak_A: float) -> FloatArray:
    """DST current in A (100 % of the table = ``peak_A``)."""
    return step_profile(t_s, DST_STEPS, peak_A)


def bbdst_current(t_s: FloatArray, step1_A: float) -> FloatArray:
    """BBDST-like bus current in A (step 1 = ``step1_A``, about C/3 in the source model)."""
    return step_profile(t_s, BBDST_STEPS, step1_A)


def cycle_mean(steps: tuple[tuple[float, float], ...]) -> float:
    """Mean of one cycle in units of the table (for sizing runs to a SOC window)."""
    d = np.array([s[0] for s in steps], dtype=float)
    f = np.array([s[1] for s in steps], dtype=float)
    return float((d * f).sum() / d.sum())
