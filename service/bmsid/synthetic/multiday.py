"""A multi-day known-truth record of the paper's 70 Ah cell (pure numpy apart from the writers;
seeded): an electric vehicle's week, for scoring the estimator per day.

Each day (t = 0 is 07:00 local time and every day starts then; 1 s samples):

* 07:00-07:30 rest (on the first day the small auxiliary load ``start_load_A`` instead, when
  given: a pack that is never quite at rest when the BMS wakes);
* 07:30-09:00 drive: DST (``profiles.dst_current``, 100 % = 140 A = 2C, mean 17.5 A, 37.5 SOC
  points per drive);
* 09:00-17:00 rest; 17:00-18:30 the second drive; 18:30-20:00 rest;
* 20:00 CC charge at C/3 up to ``charge_to_soc`` (about 2 h 15 min), then rest overnight.

From the default start (93 %) the SOC swings between about 93 % and 18 % every day. A drive
stops early where the true SOC would pass ``soc_floor`` (a low start or a faded capacity), so the
truth always stays inside the OCV curve's range (0.02..0.98 of the paper cell).

The truth is the 2RC hysteresis model of ``bmsid.synthetic`` (``TRUTH``: R0 1.2 mOhm, R1 0.8
mOhm / tau1 32 s, R2 1.0 mOhm / tau2 600 s; M 15 mV, gamma 30) simulated exactly
(``model.simulator.simulate``) with, per sample:

* temperature ``T = temp_mean_C + temp_swing_C cos(2 pi (clock - 15 h) / 24 h)`` (warmest at
  15:00, coldest at 03:00), acting on R0 and R1 by Arrhenius,
  ``R(T) = R(T_ref) exp(Ea / R_gas (1 / T - 1 / T_ref))`` with ``T_ref = temp_mean_C`` (kelvin
  inside); R2, tau1, tau2 and the OCV do not depend on temperature;
* R0 ageing, linear in time: ``R0 x (1 + r0_growth_per_day t / 1 day)``;
* capacity fade, linear: ``Q(t) = 70 Ah (1 - capacity_fade_per_day t / 1 day)``; the SOC counts
  against the present capacity (``z+ = z - i dt / Q(t)``, the simulator's time-varying Q).

Measured signals: ``current_A = true current + current_offset_A + N(0, i_noise_A)`` (+ offset =
the sensor reads more discharge than flows) and ``voltage_V = model voltage + N(0, v_noise_V)``.
"""

from __future__ import annotations

import itertools
import json
from dataclasses import asdict, dataclass, field, fields
from enum import IntEnum
from pathlib import Path

import numpy as np
import numpy.typing as npt

from bmsid.config.cell import CellConfig, paper_cell
from bmsid.config.engine import ocv_model
from bmsid.model.ecm import soc_delta
from bmsid.model.simulator import coulomb_count, simulate
from bmsid.offline.csvio import TesterData, write_tester_csv
from bmsid.profiles import dst_current
from bmsid.synthetic import TRUTH

FloatArray = npt.NDArray[np.float64]
PhaseArray = npt.NDArray[np.int8]

DAY_S = 86_400
#: Gas constant, J/(mol K).
R_GAS = 8.314462618
#: 0 degC in kelvin.
KELVIN = 273.15


class Phase(IntEnum):
    """What the pack does at a sample (the truth's ``phase`` column)."""

    REST = 0  #: no current at all
    DRIVE = 1  #: a DST drive
    CHARGE = 2  #: the evening CC charge
    AUX = 3  #: the small auxiliary load at the record's start


@dataclass(frozen=True)
class DayPlan:
    """The day's timetable and currents (defaults: the module docstring's day)."""

    start_clock_h: float = 7.0
    """Local clock time of t = 0 and of every day's start, h (sets the temperature's phase)."""
    first_drive_s: int = 1_800
    """Start of the morning drive after the day's start, s (the rest or auxiliary load before)."""
    second_drive_s: int = 36_000
    """Start of the evening drive after the day's start, s (17:00)."""
    drive_s: int = 5_400
    """Length of each drive, s: 15 DST cycles of 360 s (1.5 h)."""
    charge_start_s: int = 46_800
    """Start of the CC charge after the day's start, s (20:00): 1.5 h after the second drive."""
    peak_A: float = 140.0
    """100 % of the DST table, A (2C): mean 17.5 A, 26.25 Ah = 37.5 SOC points per drive."""
    charge_C: float = 1.0 / 3.0
    """CC charge current as a C-rate (C/3 = 23.3 A)."""
    charge_to_soc: float = 0.93
    """The charge stops when the true SOC reaches this (fraction)."""
    soc_floor: float = 0.10
    """A drive stops (rest instead) where the true SOC would fall below this (fraction)."""

    def __post_init__(self) -> None:
        times = (self.first_drive_s, self.first_drive_s + self.drive_s, self.second_drive_s,
                 self.second_drive_s + self.drive_s, self.charge_start_s, DAY_S)  # fmt: skip
        if self.first_drive_s < 0 or any(b < a for a, b in itertools.pairwise(times)):
            raise ValueError(f"day plan: events out of order or beyond one day: {times}")
        if not 0.02 < self.soc_floor < self.charge_to_soc < 0.98:
            raise ValueError("day plan: need 0.02 < soc_floor < charge_to_soc < 0.98")
        if self.peak_A <= 0 or self.charge_C <= 0:
            raise ValueError("day plan: peak and charge current must be positive")


@dataclass(frozen=True)
class MultidayOptions:
    """The scenario knobs; the defaults are the clean case (no offset, constant parameters)."""

    n_days: int = 7
    """Days in the record (each ``DAY_S`` samples)."""
    duration_s: int | None = None
    """Cut the record to its first ``duration_s`` samples (s); None: ``n_days`` whole days."""
    current_offset_A: float = 0.0
    """Current-sensor offset, A: measured = true + offset (+ = reads more discharge)."""
    soc0: float = 0.93
    """True SOC at t = 0 (fraction; the evening charge's target, as after a night's rest)."""
    h0: float = 0.0
    """True hysteresis state at t = 0, in [-1, 1] (+1: the night after the evening charge;
    0, the default, is what the engine assumes at a start)."""
    start_load_A: float = 0.0
    """Auxiliary load on the first day until the first drive, A (0: rest). 0.17 A is a typical
    BMS + contactor + telematics draw; it is below the engine's rest threshold (0.01 C)."""
    rest_draw_A: float = 0.0
    """A current the pack draws at every rest, A (true; e.g. a DC/DC converter left on): the
    sensor reads it with its offset, as a rest's reading (0: the pack rests at 0 A)."""
    temp_mean_C: float = 25.0
    """Daily mean temperature and the Arrhenius reference, degC (the truth's R at this T)."""
    temp_swing_C: float = 0.0
    """Amplitude of the daily temperature swing, degC (8: 17..33 degC)."""
    activation_energy_J_mol: float = 30_000.0
    """Arrhenius activation energy of R0 and R1, J/mol: 30 kJ/mol, typical of the ohmic and
    charge-transfer resistances of NMC/graphite cells near room temperature (R x 1.40 at 17 degC,
    x 0.73 at 33 degC against 25 degC)."""
    hysteresis_tilt: float = 0.0
    """Shape of the true hysteresis half-gap against the cell's table: true M(z) = table M(z) x
    (1 + tilt (1 - 2 z)) (0.6: 1.6x the table at empty, 0.4x at full; 0: the table)."""
    r0_growth_per_day: float = 0.0
    """R0 rise per day, relative, linear in time (0.03: +3 % a day; accelerated ageing)."""
    capacity_fade_per_day: float = 0.0
    """Capacity loss per day, relative, linear in time (0.005: -0.5 % a day)."""
    v_noise_V: float = 1e-3
    """Voltage noise, V (1 sigma, white)."""
    i_noise_A: float = 0.05
    """Current noise, A (1 sigma, white)."""
    seed: int = 1
    """Seed of the noise."""
    plan: DayPlan = field(default_factory=DayPlan)
    """The daily timetable."""

    def __post_init__(self) -> None:
        if self.n_days < 1:
            raise ValueError("n_days must be >= 1")
        if self.duration_s is not None and not 0 < self.duration_s <= self.n_days * DAY_S:
            raise ValueError("duration_s must lie in (0, n_days days]")
        if not self.plan.soc_floor < self.soc0 < 0.97:
            raise ValueError(f"soc0 must lie in ({self.plan.soc_floor:g}, 0.97)")
        if not -1.0 <= self.h0 <= 1.0:
            raise ValueError("h0 must lie in [-1, 1]")
        if not -1.0 < self.hysteresis_tilt < 1.0:
            raise ValueError("hysteresis_tilt must lie in (-1, 1): M stays positive")
        if self.capacity_fade_per_day * self.n_days >= 0.5:
            raise ValueError("capacity fade above 50 % over the record")
        amounts = (self.v_noise_V, self.i_noise_A, self.start_load_A, self.rest_draw_A)
        if min(*amounts, self.temp_swing_C) < 0:
            raise ValueError("noise, start load, rest draw and temperature swing must be >= 0")


@dataclass(frozen=True)
class MultidayTruth:
    """The truth per sample, every array shape (n,): SI units as in the names."""

    t_s: FloatArray
    current_A: FloatArray
    """True current, A (+ = discharge)."""
    voltage_V: FloatArray
    """Noise-free terminal voltage, V."""
    soc: FloatArray
    h: FloatArray
    M_V: FloatArray
    """True hysteresis half-gap M(z) at the true SOC, V."""
    R0_ohm: FloatArray
    R1_ohm: FloatArray
    R2_ohm: FloatArray
    tau1_s: FloatArray
    tau2_s: FloatArray
    capacity_Ah: FloatArray
    current_offset_A: FloatArray
    temperature_C: FloatArray
    phase: PhaseArray
    """``Phase`` codes."""


@dataclass(frozen=True)
class MultidayRecord:
    """What a logger would record (measured current and voltage) and the truth behind it."""

    cell: CellConfig
    options: MultidayOptions
    t_s: FloatArray
    current_A: FloatArray
    """Measured current, A (+ = discharge): true + offset + noise."""
    voltage_V: FloatArray
    """Measured terminal voltage, V, shape (n,)."""
    truth: MultidayTruth

    @property
    def n_samples(self) -> int:
        return int(self.t_s.shape[0])


def reference_cell() -> CellConfig:
    """The truth's cell: the paper's 70 Ah cell, M 15 mV, gamma 30 (as ``paper_dst_case``)."""
    return paper_cell(M_V=0.015, gamma=30.0)


def temperature_C(t_s: FloatArray, options: MultidayOptions) -> FloatArray:
    """The daily temperature swing, degC (warmest at 15:00 local time)."""
    clock_h = options.plan.start_clock_h + np.asarray(t_s, dtype=np.float64) / 3600.0
    swing = np.cos(2.0 * np.pi * (clock_h - 15.0) / 24.0)
    return np.asarray(options.temp_mean_C + options.temp_swing_C * swing, dtype=np.float64)


def arrhenius_factor(temp_C: FloatArray, ref_C: float, activation_J_mol: float) -> FloatArray:
    """``exp(Ea / R_gas (1 / T - 1 / T_ref))``: a resistance at ``temp_C`` over its value at
    ``ref_C`` (> 1 when colder)."""
    inv = 1.0 / (np.asarray(temp_C, dtype=np.float64) + KELVIN) - 1.0 / (ref_C + KELVIN)
    return np.asarray(np.exp(activation_J_mol / R_GAS * inv), dtype=np.float64)


def capacity_Ah(t_s: FloatArray, options: MultidayOptions, nominal_Ah: float) -> FloatArray:
    """The true capacity at ``t_s``, Ah (linear fade)."""
    days = np.asarray(t_s, dtype=np.float64) / DAY_S
    return np.asarray(nominal_Ah * (1.0 - options.capacity_fade_per_day * days), dtype=np.float64)


def _first_below(z0: float, dz: FloatArray, floor: float) -> int:
    """Index of the first step after which the SOC counted from ``z0`` is below ``floor``
    (``len(dz)`` when none)."""
    below = np.flatnonzero(z0 + np.cumsum(dz) < floor)
    return int(below[0]) if below.size else int(dz.shape[0])


def true_current(
    options: MultidayOptions, cell: CellConfig
) -> tuple[FloatArray, FloatArray, PhaseArray, FloatArray]:
    """The true current of the record and its plan: ``(t_s, current_A, phase, capacity_Ah)``.

    Built day by day while counting the SOC (Eq. 2 against the fading capacity), so a drive can
    stop at ``plan.soc_floor`` and the charge stops at ``plan.charge_to_soc``.
    """
    plan = options.plan
    n = options.n_days * DAY_S
    t = np.arange(n, dtype=np.float64)
    q_As = capacity_Ah(t, options, cell.capacity_Ah) * 3600.0
    i = np.full(n, options.rest_draw_A)  # the rests' draw; drives and charges overwrite it
    phase = np.full(n, Phase.REST, dtype=np.int8)
    eta = cell.coulombic_efficiency
    if options.start_load_A > 0:
        i[: plan.first_drive_s] = options.start_load_A
        phase[: plan.first_drive_s] = Phase.AUX
    z = options.soc0
    k = 0  # the SOC z is counted up to sample k (the state before sample k's current)

    def advance(to: int) -> float:
        nonlocal k
        dz = soc_delta(i[k:to], 1.0, q_As[k:to], eta)
        k = to
        return z + float(np.sum(dz))

    for day in range(options.n_days):
        d0 = day * DAY_S
        for start in (plan.first_drive_s, plan.second_drive_s):
            a = d0 + start
            z = advance(a)
            seg = dst_current(np.arange(plan.drive_s, dtype=np.float64), plan.peak_A)
            dz = soc_delta(seg, 1.0, q_As[a : a + plan.drive_s], eta)
            m = _first_below(z, dz, plan.soc_floor)
            i[a : a + m] = seg[:m]
            phase[a : a + m] = Phase.DRIVE
        a = d0 + plan.charge_start_s
        z = advance(a)
        i_ch = -plan.charge_C * cell.capacity_Ah
        room = d0 + DAY_S - a
        gained = np.cumsum(soc_delta(np.full(room, i_ch), 1.0, q_As[a : a + room], eta))
        need = plan.charge_to_soc - z  # the first step that reaches the target is the last one
        m = min(int(np.searchsorted(gained, need)) + 1, room) if need > 0 else 0
        i[a : a + m] = i_ch
        phase[a : a + m] = Phase.CHARGE
        z = advance(d0 + DAY_S)
    m = n if options.duration_s is None else options.duration_s
    return t[:m], i[:m], phase[:m], np.asarray(q_As[:m] / 3600.0, dtype=np.float64)


def generate(options: MultidayOptions | None = None) -> MultidayRecord:
    """Simulate the record of ``options`` (default: the clean 7-day case)."""
    opt = options or MultidayOptions()
    cell = reference_cell()
    t, i_true, phase, q = true_current(opt, cell)
    n = t.shape[0]
    temp = temperature_C(t, opt)
    arr = arrhenius_factor(temp, opt.temp_mean_C, opt.activation_energy_J_mol)
    age = 1.0 + opt.r0_growth_per_day * t / DAY_S
    r0 = TRUTH["R0_ohm"] * arr * age
    r1 = TRUTH["R1_ohm"] * arr
    const = {k: np.full(n, TRUTH[k]) for k in ("R2_ohm", "tau1_s", "tau2_s")}
    ocv = ocv_model(cell)
    # The SOC does not depend on M: counted first, it sets the true M's shape per sample.
    dt = np.diff(t, append=t[-1] + 1.0)
    z = coulomb_count(i_true, dt, opt.soc0, q, cell.coulombic_efficiency)
    m_scale = 1.0 + opt.hysteresis_tilt * (1.0 - 2.0 * z)
    sim = simulate(
        t, i_true, ocv, capacity_Ah=q, R0_ohm=r0[None, :], R1_ohm=r1[None, :],
        tau1_s=TRUTH["tau1_s"], R2_ohm=TRUTH["R2_ohm"], tau2_s=TRUTH["tau2_s"],
        gamma=cell.hysteresis.gamma, eta=cell.coulombic_efficiency, soc0=opt.soc0, h0=opt.h0,
        M_scale=m_scale[None, :],
    )  # fmt: skip
    if sim.soc_clamped.any():
        raise ValueError("the true SOC left the OCV curve's range: check soc0 and the plan")
    rng = np.random.default_rng(opt.seed)
    v_true = sim.v_V[0]
    v = v_true + rng.normal(0.0, opt.v_noise_V, n)
    i_meas = i_true + opt.current_offset_A + rng.normal(0.0, opt.i_noise_A, n)
    truth = MultidayTruth(
        t_s=t, current_A=i_true, voltage_V=v_true, soc=sim.soc, h=sim.h[0],
        M_V=m_scale * ocv.hysteresis_M(sim.soc), R0_ohm=r0,
        R1_ohm=r1, R2_ohm=const["R2_ohm"], tau1_s=const["tau1_s"], tau2_s=const["tau2_s"],
        capacity_Ah=q, current_offset_A=np.full(n, opt.current_offset_A), temperature_C=temp,
        phase=phase,
    )  # fmt: skip
    return MultidayRecord(cell=cell, options=opt, t_s=t, current_A=i_meas, voltage_V=v,
                          truth=truth)  # fmt: skip


# ----------------------------------------------------------------------------- files
def options_document(options: MultidayOptions) -> dict[str, object]:
    """``options`` as plain JSON values (the plan nested)."""
    return asdict(options)


def write_record(record: MultidayRecord, csv_path: str | Path, truth_path: str | Path) -> None:
    """Write the measured record as a tester CSV (``t_s,current_A,voltage_V,temperature_C``;
    gzip when the name ends in .gz) that ``bmsid identify`` reads, and the truth as an ``.npz``
    (one array per ``MultidayTruth`` field, plus ``options_json``: the scenario as JSON text).
    The temperature is the pack's, as a gateway's BMS reports it (0.1 degC resolution)."""
    data = TesterData(
        t_s=record.t_s, current_A=record.current_A, cell_voltages_V=record.voltage_V[:, None],
        cell_names=["voltage_V"], temperature_C=np.round(record.truth.temperature_C, 1),
    )  # fmt: skip
    write_tester_csv(data, csv_path)
    arrays = {f.name: getattr(record.truth, f.name) for f in fields(MultidayTruth)}
    doc = json.dumps(options_document(record.options))
    with Path(truth_path).open("wb") as fh:
        np.savez_compressed(fh, options_json=np.array(doc), **arrays)


def read_truth(path: str | Path) -> tuple[MultidayTruth, dict[str, object]]:
    """The truth and the options document written by :func:`write_record`."""
    with np.load(Path(path)) as z:
        truth = MultidayTruth(**{f.name: np.asarray(z[f.name]) for f in fields(MultidayTruth)})
        doc = json.loads(str(z["options_json"]))
    if not isinstance(doc, dict):
        raise ValueError(f"{path}: options_json is not an object")
    return truth, doc
