"""Known-truth low-rate OCV tests from the project's own simulator (pure numpy; seeded).

What ``bmsid fit-ocv`` must recover: a rest full (h = +1, as after a charge), a full C/20
discharge to empty, a rest, a full C/20 charge back to full, a rest; optionally a short
discharge pulse with a rest after it at each end (as many test schedules have) and a charge
coulombic efficiency below 1 (the charge then runs ``1/eta`` longer to return to full). The
terminal voltage is ``bmsid.model.simulator.simulate``'s 2RC model with Plett's one-state
hysteresis (Eq. 2, 5-9): ``U = OCV(z) + M(z) h - U1 - U2 - R0 i``, plus Gaussian noise on the
measured voltage and current.

At C/20 the RC branches run in steady state, so the charge-minus-discharge gap of the branches
is ``2 M + I_dis (R0 + R1 + R2) + I_chg (R0 + R1 + R2)``: a fit that takes one IR drop (R0) for
the polarisation overstates M, one that takes the raw gap for it zeroes M.

The two cells (``NMC_CELL``, ``LFP_CELL``): the mean OCV of the shipped configs
``configs/cells/calce_inr18650_20r_25C.toml`` (2.0 Ah NMC 18650, rest points) and
``configs/cells/a123_lfp_25C.toml`` (A123 LFP, Plett's C/30 test), copied here so the truth does
not move when those configs are regenerated.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt

from bmsid.model.ocv import OcvModel
from bmsid.model.simulator import simulate

FloatArray = npt.NDArray[np.float64]


@dataclass(frozen=True)
class OcvTestCell:
    """A cell's true mean OCV (Eq. 4 on [soc_min, soc_max] with end segments to the rested
    voltages ``v_empty_V``/``v_full_V``) and its 2RC parameters (ohm, s) and capacity (Ah)."""

    name: str
    coeffs: tuple[float, ...]
    soc_min: float
    soc_max: float
    v_empty_V: float
    v_full_V: float
    capacity_Ah: float
    R0_ohm: float
    R1_ohm: float
    tau1_s: float
    R2_ohm: float
    tau2_s: float

    @property
    def r_total_ohm(self) -> float:
        """DC polarisation resistance R0 + R1 + R2 (ohm): the branch offset at a constant rate."""
        return self.R0_ohm + self.R1_ohm + self.R2_ohm

    def ocv(self, m_V: float = 0.0, bump_V: float = 0.0) -> OcvModel:
        """The true OCV with a constant half-gap ``m_V`` (V) and, with ``bump_V`` (V), a
        staging-like bump that Eq. 4 cannot follow: ``bump_V exp(-(z - 0.55)^2 / (2 0.03^2))``
        (``BUMP_SOC``, ``BUMP_WIDTH``), sampled every 0.2 % of SOC (the dense table is the bump
        itself to well under 0.1 mV)."""
        table: dict[str, FloatArray] = {}
        if bump_V:
            z = np.linspace(self.soc_min, self.soc_max, round((self.soc_max - self.soc_min) / 2e-3))
            table = {"corr_soc": z, "corr_V": bump_V * _bump(z)}
        return OcvModel.from_coeffs(
            np.asarray(self.coeffs), self.soc_min, self.soc_max, [0.0, 1.0], [m_V, m_V],
            v_empty_V=self.v_empty_V, v_full_V=self.v_full_V, **table,
        )  # fmt: skip


#: Centre and width (SOC fractions) of the staging-like bump of ``OcvTestCell.ocv``.
BUMP_SOC, BUMP_WIDTH = 0.55, 0.03


def _bump(z: FloatArray) -> FloatArray:
    return np.asarray(np.exp(-0.5 * ((z - BUMP_SOC) / BUMP_WIDTH) ** 2), dtype=np.float64)


#: 2.0 Ah NMC 18650 (CALCE INR18650-20R's mean OCV at 25 C); R0 25 mOhm, R1 10 mOhm / 30 s,
#: R2 20 mOhm / 1000 s: 5.5 mV of polarisation per branch at C/20.
NMC_CELL = OcvTestCell(
    name="nmc-18650",
    coeffs=(4.608110138584939, -2.1867855037395425, 2.2213437237183666, 0.007931914689718428,
            0.43452627841734126, 0.14895913566742888),
    soc_min=0.05, soc_max=0.9019, v_empty_V=3.292533859464938, v_full_V=4.1871945720674955,
    capacity_Ah=2.0, R0_ohm=0.025, R1_ohm=0.010, tau1_s=30.0, R2_ohm=0.020, tau2_s=1000.0,
)  # fmt: skip

#: 2.07 Ah A123 LFP cell (the mean OCV of its C/30 test at 25 C); R0 10 mOhm,
#: R1 5 mOhm / 20 s, R2 10 mOhm / 800 s: 2.9 mV of polarisation per branch at C/20.
LFP_CELL = OcvTestCell(
    name="lfp-a123",
    coeffs=(3.571725944562073, -0.42340524178578204, 0.18447359724247706,
            -0.0037314329644171592, 0.1439271344249412, -0.016061978740258567),
    soc_min=0.02, soc_max=0.98, v_empty_V=2.2091301666666667, v_full_V=3.584126,
    capacity_Ah=2.07, R0_ohm=0.010, R1_ohm=0.005, tau1_s=20.0, R2_ohm=0.010, tau2_s=800.0,
)  # fmt: skip


@dataclass(frozen=True)
class SyntheticOcvTest:
    """A simulated OCV test as a tester logs it (time s, current A with + = discharge, voltage
    V; noisy) and the truth behind it (SOC, hysteresis state h, M V, gamma, eta)."""

    cell: OcvTestCell
    t_s: FloatArray
    current_A: FloatArray
    v_V: FloatArray
    soc_true: FloatArray
    h_true: FloatArray
    m_V: float
    gamma: float
    eta: float
    bump_V: float = 0.0
    segments: tuple[tuple[str, int, int], ...] = field(default_factory=tuple)
    """(name, first sample, stop sample) of each step of the schedule, in order."""


def c20_ocv_test(
    cell: OcvTestCell = NMC_CELL,
    *,
    m_V: float = 0.015,
    gamma: float = 100.0,
    rate_C: float = 1 / 20,
    eta: float = 1.0,
    dt_s: float = 10.0,
    rest_full_s: float = 3600.0,
    rest_empty_s: float = 7200.0,
    rest_end_s: float = 3600.0,
    pulse_C: float | None = None,
    pulse_s: float = 60.0,
    pulse_rest_s: float = 1800.0,
    v_noise_V: float = 1e-3,
    i_noise_A: float = 1e-3,
    seed: int = 1,
    bump_V: float = 0.0,
) -> SyntheticOcvTest:
    """One low-rate OCV test of ``cell`` (module doc) with a constant true half-gap ``m_V`` (V).

    ``gamma`` (Plett's dimensionless rate) 100 turns h from one side to the other within about
    3 % of SOC (e^-3 = 5 % left). ``pulse_C``: a discharge pulse of that C-rate for ``pulse_s``
    with ``pulse_rest_s`` of rest after it, right after the first rest at full and right after
    the rest at empty (None: no pulses; they move the SOC by ``pulse_C * pulse_s / 3600`` of the
    capacity, which the branches then cover less). ``eta``: charge coulombic efficiency (the
    charge runs ``1/eta`` as long). Samples every ``dt_s`` s (the current held over each).
    ``bump_V``: the true mean OCV carries a staging-like bump of that height (V) beyond Eq. 4
    (``OcvTestCell.ocv``).
    """
    cap = cell.capacity_Ah
    i_ocv = rate_C * cap
    n_branch = round(3600.0 / rate_C / dt_s)

    def n(s: float) -> int:
        return max(round(s / dt_s), 1)

    steps: list[tuple[str, float, int]] = [("rest full", 0.0, n(rest_full_s))]
    pulse_q = 0.0
    if pulse_C is not None:
        steps += [("pulse full", pulse_C * cap, n(pulse_s)), ("rest pulse full", 0.0,
                                                               n(pulse_rest_s))]  # fmt: skip
        pulse_q = pulse_C * n(pulse_s) * dt_s / 3600.0  # fraction of the capacity
    # The discharge ends at empty: the pulse already took its share.
    steps.append(("discharge", i_ocv, round(n_branch * (1.0 - pulse_q))))
    steps.append(("rest empty", 0.0, n(rest_empty_s)))
    charge_q = 1.0
    if pulse_C is not None:
        steps += [("pulse empty", -pulse_C * cap, n(pulse_s)), ("rest pulse empty", 0.0,
                                                                n(pulse_rest_s))]  # fmt: skip
        charge_q -= pulse_q  # a charge pulse at empty: the charge has that much less to do
    steps.append(("charge", -i_ocv, round(n_branch * charge_q / eta)))
    steps.append(("rest end", 0.0, n(rest_end_s)))
    return _run(cell, steps, dt_s, m_V, gamma, eta, v_noise_V, i_noise_A, seed, bump_V)


def _run(
    cell: OcvTestCell, steps: list[tuple[str, float, int]], dt_s: float, m_V: float,
    gamma: float, eta: float, v_noise_V: float, i_noise_A: float, seed: int, bump_V: float = 0.0,
) -> SyntheticOcvTest:  # fmt: skip
    """The schedule ``steps`` (name, current A, samples) simulated from full (h = +1) and
    measured with noise."""
    current = np.concatenate([np.full(k, i) for _, i, k in steps])
    bounds = np.cumsum([0, *[k for _, _, k in steps]])
    segments = tuple(
        (name, int(a), int(b)) for (name, _, _), a, b in zip(steps, bounds[:-1], bounds[1:],
                                                             strict=True)
    )  # fmt: skip
    t = np.arange(current.shape[0], dtype=np.float64) * dt_s
    sim = simulate(
        t, current, cell.ocv(m_V, bump_V), capacity_Ah=cell.capacity_Ah, R0_ohm=cell.R0_ohm,
        R1_ohm=cell.R1_ohm, tau1_s=cell.tau1_s, R2_ohm=cell.R2_ohm, tau2_s=cell.tau2_s,
        gamma=gamma, eta=eta, soc0=1.0, h0=1.0,
    )  # fmt: skip
    rng = np.random.default_rng(seed)
    v = sim.v_V[0] + rng.normal(0.0, v_noise_V, t.shape[0])
    i_meas = current + rng.normal(0.0, i_noise_A, t.shape[0])
    return SyntheticOcvTest(
        cell=cell, t_s=t, current_A=i_meas, v_V=v, soc_true=sim.soc, h_true=sim.h[0],
        m_V=m_V, gamma=gamma, eta=eta, bump_V=bump_V, segments=segments,
    )  # fmt: skip


def incremental_ocv_test(
    cell: OcvTestCell = NMC_CELL,
    *,
    m_V: float = 0.015,
    gamma: float = 30.0,
    pulse_C: float = 0.5,
    step_soc: float = 0.1,
    rest_s: float = 3600.0,
    rest_end_s: float = 7200.0,
    charge_back: bool = True,
    eta: float = 1.0,
    dt_s: float = 10.0,
    v_noise_V: float = 1e-3,
    i_noise_A: float = 1e-3,
    seed: int = 1,
) -> SyntheticOcvTest:
    """An incremental OCV test of ``cell`` with a constant true half-gap ``m_V`` (V): a rest
    full (h = +1), then discharge pulses of ``pulse_C`` each moving ``step_soc`` of the
    capacity, ``rest_s`` of rest after each (``rest_end_s`` after the one that empties the
    cell); with ``charge_back`` the same back up to full (the charge runs ``1/eta`` as long).
    Noise and sampling as ``c20_ocv_test``."""
    cap = cell.capacity_Ah
    n_steps = round(1.0 / step_soc)
    n_pulse = max(round(step_soc * 3600.0 / pulse_C / dt_s), 1)

    def n(s: float) -> int:
        return max(round(s / dt_s), 1)

    steps: list[tuple[str, float, int]] = [("rest full", 0.0, n(rest_s))]
    for k in range(n_steps):
        steps.append((f"discharge pulse {k + 1}", pulse_C * cap, n_pulse))
        steps.append((f"rest {k + 1}", 0.0, n(rest_end_s if k == n_steps - 1 else rest_s)))
    if charge_back:
        for k in range(n_steps):
            steps.append((f"charge pulse {k + 1}", -pulse_C * cap, round(n_pulse / eta)))
            steps.append((f"charge rest {k + 1}", 0.0, n(rest_s)))
    return _run(cell, steps, dt_s, m_V, gamma, eta, v_noise_V, i_noise_A, seed)
