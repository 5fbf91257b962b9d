"""Known-truth synthetic data from the project's own simulator (pure; seeded).

The reference case of the issue tracker: the paper's 70 Ah cell (Table 1 OCV), R0 1.2 mOhm,
R1 0.8 mOhm / tau1 32 s, R2 1.0 mOhm / tau2 600 s, M 15 mV, gamma 30, DST at 1 s with
100 % = 2C = 140 A from SOC 98 % to 10 %, noise 1 mV and 50 mA.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from bmsid.config.cell import CellConfig, paper_cell
from bmsid.config.engine import ocv_model
from bmsid.model.simulator import simulate
from bmsid.profiles import DST_STEPS, cycle_mean, dst_current

FloatArray = npt.NDArray[np.float64]

TRUTH = {"R0_ohm": 1.2e-3, "R1_ohm": 0.8e-3, "tau1_s": 32.0, "R2_ohm": 1.0e-3, "tau2_s": 600.0}


@dataclass(frozen=True)
class SyntheticRun:
    """Measured (noisy) signals and the truth behind them; voltages shape (n, n_cells)."""

    cell: CellConfig
    t_s: FloatArray
    current_A: FloatArray
    voltages_V: FloatArray
    soc_true: FloatArray
    R0_true_ohm: FloatArray  # (n, n_cells)
    truth: dict[str, float]


def dst_run_length_s(cell: CellConfig, peak_A: float, soc_from: float, soc_to: float) -> int:
    """Seconds of DST that move the SOC from ``soc_from`` to ``soc_to``."""
    mean_A = cycle_mean(DST_STEPS) * peak_A
    return int((soc_from - soc_to) * cell.capacity_Ah * 3600.0 / mean_A)


def paper_dst_case(
    n_samples: int | None = None,
    *,
    seed: int = 1,
    r0_ramp: float = 0.0,
    r0_spread: FloatArray | None = None,
    v_noise_V: float = 1e-3,
    i_noise_A: float = 0.05,
    soc0: float = 0.98,
    h0: float = 0.0,
) -> SyntheticRun:
    """The reference DST case; ``r0_ramp`` = relative R0 rise over the run (0.3 = +30 %);
    ``r0_spread`` = per-cell R0 multipliers for a pack (one cell per entry); ``h0`` = the true
    hysteresis state at the start (+1 just after a full charge, which the engine cannot know
    from a rested voltage: it starts from 0)."""
    cell = paper_cell(M_V=0.015, gamma=30.0)
    n = n_samples or dst_run_length_s(cell, 140.0, soc0, 0.10)
    t = np.arange(n, dtype=np.float64)
    i = dst_current(t, 140.0)
    mult = np.ones(1) if r0_spread is None else np.asarray(r0_spread, dtype=np.float64)
    r0 = TRUTH["R0_ohm"] * mult[:, None] * (1.0 + r0_ramp * t / max(t[-1], 1.0))[None, :]
    sim = simulate(
        t, i, ocv_model(cell), capacity_Ah=cell.capacity_Ah, R0_ohm=r0,
        R1_ohm=TRUTH["R1_ohm"], tau1_s=TRUTH["tau1_s"], R2_ohm=TRUTH["R2_ohm"],
        tau2_s=TRUTH["tau2_s"], gamma=cell.hysteresis.gamma, soc0=soc0, h0=h0,
        n_sets=mult.shape[0],
    )  # fmt: skip
    rng = np.random.default_rng(seed)
    v = sim.v_V.T + rng.normal(0.0, v_noise_V, (n, mult.shape[0]))
    i_meas = i + rng.normal(0.0, i_noise_A, n)
    return SyntheticRun(
        cell=cell, t_s=t, current_A=i_meas, voltages_V=v, soc_true=sim.soc,
        R0_true_ohm=r0.T, truth=dict(TRUTH),
    )  # fmt: skip
