"""Regenerate the physics-based reference data in ``data/physics/`` with PyBaMM.

A DFN model (lumped thermal) of the LG M50 cell (PyBaMM's bundled ``ORegan2022`` set) runs the
DST and a bus-like stop-and-go profile (``bmsid.profiles``) at 15, 25 and 35 C ambient, a
C/20 discharge/charge OCV test at 25 C and a two-day gateway record at 25 C (drives, rests,
CC-CV charges; it starts under an auxiliary load). The simulated current, voltage and
temperature get seeded tester noise and resolution; the model's true SOC is kept as an extra
column. See ``data/README.md``.

PyBaMM is the ``physics`` extra (``pip install -e '.[physics]'``) and is needed by this script
only. The script installs nothing and refuses any network connection, so it fails rather than
downloading (the parameter set must ship inside the pybamm wheel).

Usage: ``python scripts/make_physics_data.py [--only NAME ...] [--out DIR]``.
"""

from __future__ import annotations

import argparse
import gzip
import importlib.util
import io
import json
import math
import os
import re
import socket
import sys
import time
import zlib
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from functools import partial
from pathlib import Path
from typing import Any, NoReturn

import numpy as np
import numpy.typing as npt

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "service"))

from bmsid.profiles import BBDST_STEPS, DST_STEPS, cycle_mean  # noqa: E402

FloatArray = npt.NDArray[np.float64]

PARAMETER_SET = "ORegan2022"
NOMINAL_CAPACITY_AH = 5.0  # "Nominal cell capacity [A.h]" of the set; C-rates refer to it
V_MIN_V = 2.5  # LG M50 datasheet discharge cut-off, also the set's value
V_MAX_V = 4.2  # LG M50 datasheet charge voltage (the set's own 4.4 V is replaced, see README)
SOC_START = 0.98  # room for the regenerative pulses below the 4.2 V limit
SOC_END = 0.10
INITIAL_REST_S = 60.0  # a rest before the first cycle, so the start OCV can be read
AMBIENTS_C = (15, 25, 35)
DST_PEAK_A = 2.0 * NOMINAL_CAPACITY_AH  # 100 % of the DST table = 2C = 10 A
BBDST_STEP1_A = NOMINAL_CAPACITY_AH / 3.0  # step 1 of the bus table = C/3
OCV_TEST_CRATE = 1.0 / 20.0
OCV_TEST_PERIOD_S = 10.0
OCV_REST_H = 2.0
OCV_CURVE_POINTS = 201
REFERENCE_TEMPERATURE_C = 25.0

# Gateway record: a vehicle's days as its gateway logs them (record time 0 = gateway start).
GATEWAY_DAYS = 2
GATEWAY_NAME = f"dfn_nmc_gateway_{GATEWAY_DAYS}days_25C"
GATEWAY_SOC0 = 0.75  # equilibrium SOC before the auxiliary load came on (before the record)
AUX_LOAD_A = 0.17  # auxiliaries on while the gateway restarts: the record starts under load
AUX_PREROLL_S = 1800.0  # the load ran this long before the record starts (not logged)
AUX_LOGGED_S = 900.0  # ... and this long into the record
DAY_S = 86400.0
DRIVE1_START_S = 3600.0  # morning drive, from the start of each day
DRIVE1_CYCLES = 15  # bus-like cycles of 300 s: 1.25 h (its regeneration is mild at full charge)
MIDDAY_REST_S = 7.0 * 3600.0
DRIVE2_CYCLES = 12  # DST cycles of 360 s: 1.2 h
EVENING_REST_S = 2.0 * 3600.0  # between the second drive and the charge
CHARGE_A = NOMINAL_CAPACITY_AH / 3.0  # CC at C/3 to V_MAX_V ...
CV_END_A = NOMINAL_CAPACITY_AH / 20.0  # ... then CV at V_MAX_V until C/20
REST_FINE_S = 600.0  # the first 10 min of a rest are logged every 1 s ...
REST_PERIOD_S = 10.0  # ... the rest of it every 10 s

# Tester model: Gaussian noise then quantisation to the logger's resolution.
VOLTAGE_NOISE_V = 1e-3
CURRENT_NOISE_A = 1e-3 * NOMINAL_CAPACITY_AH  # 0.1 % of the 1C current = 5 mA
VOLTAGE_RESOLUTION_V = 1e-4
CURRENT_RESOLUTION_A = 1e-3
TEMPERATURE_RESOLUTION_C = 0.1
NOISE_SEED = 20240903

HEADER = "t_s,current_A,voltage_V,temperature_C,soc_true"
README_BEGIN = "<!-- physics-files:begin (written by scripts/make_physics_data.py) -->"
README_END = "<!-- physics-files:end -->"


@dataclass(frozen=True)
class Trace:
    """A simulated test, noise-free, on its sample times (SI units; positive = discharge)."""

    t_s: FloatArray
    current_A: FloatArray
    voltage_V: FloatArray
    temperature_C: FloatArray
    soc: FloatArray
    ended_by: str
    #: Phases of a composed record (gateway): kind, day, start/end in record time and facts.
    schedule: tuple[dict[str, Any], ...] = ()


@dataclass(frozen=True)
class Window:
    """Electrode stoichiometries at 0 % and 100 % SOC and the capacity between them."""

    x0: float
    x100: float
    y0: float
    y100: float
    capacity_Ah: float


def forbid_network() -> None:
    """Make every socket connection fail: nothing may be downloaded while generating."""

    def refuse(*_args: object, **_kwargs: object) -> NoReturn:
        raise RuntimeError("network access attempted while generating physics data")

    socket.socket.connect = refuse  # type: ignore[method-assign]
    socket.create_connection = refuse
    socket.getaddrinfo = refuse


def import_pybamm() -> Any:
    """Import PyBaMM offline (telemetry off) and check the parameter set ships with it."""
    os.environ["PYBAMM_DISABLE_TELEMETRY"] = "true"
    forbid_network()
    try:
        import pybamm  # noqa: PLC0415 - imported only after the network guard is in place
    except ImportError:
        sys.exit("pybamm is missing: pip install -e '.[physics]'")
    module = f"pybamm.input.parameters.lithium_ion.{PARAMETER_SET}"
    spec = importlib.util.find_spec(module)
    package_dir = Path(pybamm.__file__).resolve().parent
    if spec is None or spec.origin is None or package_dir not in Path(spec.origin).parents:
        sys.exit(f"parameter set {PARAMETER_SET} is not bundled with pybamm {pybamm.__version__}")
    return pybamm


def parameter_values(pybamm: Any, ambient_C: float) -> Any:
    """The bundled set with the datasheet voltage window and the given ambient/start temperature."""
    pv = pybamm.ParameterValues(PARAMETER_SET)
    ambient_K = ambient_C + 273.15
    pv.update(
        {
            "Lower voltage cut-off [V]": V_MIN_V,
            "Upper voltage cut-off [V]": V_MAX_V,
            "Open-circuit voltage at 0% SOC [V]": V_MIN_V,
            "Open-circuit voltage at 100% SOC [V]": V_MAX_V,
            "Ambient temperature [K]": ambient_K,
            "Initial temperature [K]": ambient_K,
        }
    )
    return pv


def soc_window(pybamm: Any) -> Window:
    """Stoichiometry limits of the 2.5-4.2 V OCV window at 25 C and the capacity between them."""
    pv = parameter_values(pybamm, REFERENCE_TEMPERATURE_C)
    x0, x100, y100, y0 = (float(v) for v in pybamm.lithium_ion.get_min_max_stoichiometries(pv))
    param = pybamm.LithiumIonParameters()
    q_n_Ah = float(pv.evaluate(param.n.Q_init))
    return Window(x0=x0, x100=x100, y0=y0, y100=y100, capacity_Ah=q_n_Ah * (x100 - x0))


def ocv_curve(pybamm: Any, window: Window, n: int) -> tuple[FloatArray, FloatArray]:
    """Equilibrium OCV in V at the reference temperature on an SOC grid (fraction, 0..1)."""
    pv = parameter_values(pybamm, REFERENCE_TEMPERATURE_C)
    soc = np.linspace(0.0, 1.0, n)
    x = window.x0 + soc * (window.x100 - window.x0)
    y = window.y0 + soc * (window.y100 - window.y0)
    u_p = pv.evaluate(pv["Positive electrode OCP [V]"](pybamm.Vector(y)))
    u_n = pv.evaluate(pv["Negative electrode OCP [V]"](pybamm.Vector(x)))
    return soc, np.asarray(u_p - u_n, dtype=np.float64).ravel()


def cycle_steps(
    pybamm: Any, steps: Sequence[tuple[float, float]], scale_A: float, cycles: int
) -> list[Any]:
    """Experiment steps for ``cycles`` repeats of a step table (current = fraction x scale_A)."""
    one = [
        pybamm.step.current(f * scale_A, duration=d, period=1.0)
        if f != 0.0
        else pybamm.step.rest(duration=d, period=1.0)
        for d, f in steps
    ]
    return one * cycles


def simulation(pybamm: Any, ambient_C: float, experiment: Any) -> Any:
    """The lumped-thermal DFN set up for an experiment."""
    model = pybamm.lithium_ion.DFN({"thermal": "lumped"})
    return pybamm.Simulation(
        model,
        parameter_values=parameter_values(pybamm, ambient_C),
        experiment=experiment,
        solver=pybamm.IDAKLUSolver(rtol=1e-6, atol=1e-8),
    )


def trace_of(sol: Any, window: Window, t_from_s: float = 0.0) -> Trace:
    """A solution's samples from simulation time ``t_from_s`` on, with that time as zero."""
    t = np.asarray(sol["Time [s]"].entries, dtype=np.float64)
    x = np.asarray(sol["Average negative particle stoichiometry"].entries, dtype=np.float64)
    # At a step change the solution holds the end of one step and the start of the next at the
    # same time: keep the later one, as a tester logs the new step's first record.
    keep = np.append(np.diff(t) > 1e-9, True) & (t >= t_from_s - 1e-9)
    last = sol.termination
    return Trace(
        t_s=t[keep] - t_from_s,
        current_A=np.asarray(sol["Current [A]"].entries, dtype=np.float64)[keep],
        voltage_V=np.asarray(sol["Voltage [V]"].entries, dtype=np.float64)[keep],
        temperature_C=np.asarray(
            sol["Volume-averaged cell temperature [C]"].entries, dtype=np.float64
        )[keep],
        soc=(x[keep] - window.x0) / (window.x100 - window.x0),
        ended_by="end of test" if last == "final time" else str(last),
    )


def run(pybamm: Any, ambient_C: float, experiment: Any, soc0: float, window: Window) -> Trace:
    """Solve the lumped-thermal DFN for an experiment and return its samples."""
    sol = simulation(pybamm, ambient_C, experiment).solve(initial_soc=soc0)
    return trace_of(sol, window)


def until_soc(trace: Trace, soc_end: float) -> Trace:
    """Cut a discharge trace at its first sample with SOC <= ``soc_end`` (kept)."""
    below = np.flatnonzero(trace.soc <= soc_end)
    if below.size == 0:
        return trace
    n = int(below[0]) + 1
    return Trace(
        t_s=trace.t_s[:n],
        current_A=trace.current_A[:n],
        voltage_V=trace.voltage_V[:n],
        temperature_C=trace.temperature_C[:n],
        soc=trace.soc[:n],
        ended_by=f"SOC reached {soc_end:.2f}",
    )


def profile_trace(
    pybamm: Any,
    steps: Sequence[tuple[float, float]],
    scale_A: float,
    ambient_C: float,
    window: Window,
) -> Trace:
    """Rest, then repeat a load cycle from SOC_START until SOC_END or the voltage cut-off."""
    period_s = sum(d for d, _ in steps)
    mean_A = cycle_mean(tuple(steps)) * scale_A
    cycles = math.ceil((SOC_START - SOC_END) * window.capacity_Ah * 3600.0 / mean_A / period_s)
    rest = pybamm.step.rest(duration=INITIAL_REST_S, period=1.0)
    experiment = pybamm.Experiment([rest, *cycle_steps(pybamm, steps, scale_A, cycles + 1)])
    return until_soc(run(pybamm, ambient_C, experiment, SOC_START, window), SOC_END)


def ocv_test_trace(pybamm: Any, window: Window) -> Trace:
    """C/20 discharge to 2.5 V, rest, C/20 charge to 4.2 V, from 100 % SOC at 25 C."""
    i_A = OCV_TEST_CRATE * NOMINAL_CAPACITY_AH
    p = OCV_TEST_PERIOD_S
    experiment = pybamm.Experiment(
        [
            pybamm.step.rest(duration=1800.0, period=p),
            pybamm.step.current(i_A, termination=f"{V_MIN_V} V", period=p),
            pybamm.step.rest(duration=OCV_REST_H * 3600.0, period=p),
            pybamm.step.current(-i_A, termination=f"{V_MAX_V} V", period=p),
            pybamm.step.rest(duration=1800.0, period=p),
        ]
    )
    return run(pybamm, REFERENCE_TEMPERATURE_C, experiment, 1.0, window)


@dataclass(frozen=True)
class Phase:
    """One part of the gateway record: one experiment cycle (its steps) and what it is."""

    kind: str  # "aux_load", "rest", "drive" or "charge"
    day: int
    steps: tuple[Any, ...]
    facts: dict[str, Any]


def rest_steps(pybamm: Any, duration_s: float) -> tuple[Any, ...]:
    """A rest logged every 1 s for its first REST_FINE_S or so, then every REST_PERIOD_S.

    The coarse part is a whole number of periods, so both parts keep their exact sample spacing
    (PyBaMM spreads a step's samples evenly over its duration).
    """
    coarse = max(0.0, math.floor((duration_s - REST_FINE_S) / REST_PERIOD_S) * REST_PERIOD_S)
    fine = duration_s - coarse
    steps = [pybamm.step.rest(duration=fine, period=1.0)]
    if coarse > 0.0:
        steps.append(pybamm.step.rest(duration=coarse, period=REST_PERIOD_S))
    return tuple(steps)


def realign_step(pybamm: Any, t_s: float) -> tuple[Any, float]:
    """A rest step from ``t_s`` to a whole second 0.5-1.5 s later, and its duration.

    A charge ends on a condition (voltage, current) between whole seconds; the rest after it
    starts with this step so that every later sample is on whole seconds again.
    """
    align_s = math.ceil(t_s) - t_s
    if align_s < 0.5:
        align_s += 1.0
    return pybamm.step.rest(duration=align_s, period=align_s), align_s


def day_phases(pybamm: Any, day: int) -> list[Phase]:
    """A day from its first drive to the end of its evening charge."""
    return [
        Phase(
            "drive",
            day,
            tuple(cycle_steps(pybamm, BBDST_STEPS, BBDST_STEP1_A, DRIVE1_CYCLES)),
            {"profile": "bbdst", "scale_A": BBDST_STEP1_A},
        ),
        Phase("rest", day, rest_steps(pybamm, MIDDAY_REST_S), {}),
        Phase(
            "drive",
            day,
            tuple(cycle_steps(pybamm, DST_STEPS, DST_PEAK_A, DRIVE2_CYCLES)),
            {"profile": "dst", "scale_A": DST_PEAK_A},
        ),
        Phase("rest", day, rest_steps(pybamm, EVENING_REST_S), {}),
        Phase(
            "charge",
            day,
            (
                pybamm.step.current(-CHARGE_A, termination=f"{V_MAX_V} V", period=1.0),
                pybamm.step.voltage(V_MAX_V, termination=f"{CV_END_A} A", period=1.0),
            ),
            {"current_A": -CHARGE_A, "voltage_V": V_MAX_V, "end_current_A": CV_END_A},
        ),
    ]


def check_complete(sol: Any, phases: Sequence[Phase]) -> None:
    """Fail unless every phase and every step of the last one ran (no cut-off event hit)."""
    ended = sol.termination == "final time" or str(sol.termination).endswith("[experiment]")
    if (
        not ended
        or len(sol.cycles) != len(phases)
        or len(sol.cycles[-1].steps) != len(phases[-1].steps)
    ):
        raise RuntimeError(f"gateway run stopped early: {sol.termination}")


def gateway_trace(pybamm: Any, window: Window) -> Trace:
    """GATEWAY_DAYS days at 25 C: drives, rests and evening charges; starts under a load.

    Simulation time 0 is the equilibrium at GATEWAY_SOC0 when the auxiliary load comes on; the
    record starts AUX_PREROLL_S later. Solved in pieces, each from the end of the previous one,
    cut after each charge: the overnight rest then lasts until the next day's first drive, so the
    days keep their clock (day k starts at (k - 1) * DAY_S in record time).
    """
    off = AUX_PREROLL_S
    phases = [
        Phase(
            "aux_load",
            1,
            (
                pybamm.step.current(AUX_LOAD_A, duration=AUX_PREROLL_S, period=REST_PERIOD_S),
                pybamm.step.current(AUX_LOAD_A, duration=AUX_LOGGED_S, period=1.0),
            ),
            {"current_A": AUX_LOAD_A, "on_before_record_s": AUX_PREROLL_S},
        ),
        Phase("rest", 1, rest_steps(pybamm, DRIVE1_START_S - AUX_LOGGED_S), {}),
        *day_phases(pybamm, 1),
    ]
    sol = None
    solved = 0
    for day in range(2, GATEWAY_DAYS + 2):
        experiment = pybamm.Experiment([p.steps for p in phases[solved:]])
        sim = simulation(pybamm, REFERENCE_TEMPERATURE_C, experiment)
        sol = (
            sim.solve(initial_soc=GATEWAY_SOC0) if sol is None else sim.solve(starting_solution=sol)
        )
        check_complete(sol, phases)
        solved = len(phases)
        # Overnight rest: from the end of the charge to the next day's first drive (the last
        # one to the end of the record).
        t_end_s = float(sol["Time [s]"].entries[-1])
        next_s = off + (day - 1) * DAY_S + (DRIVE1_START_S if day <= GATEWAY_DAYS else 0.0)
        align, align_s = realign_step(pybamm, t_end_s)
        rest_s = round(next_s - t_end_s - align_s)
        phases.append(Phase("rest", day - 1, (align, *rest_steps(pybamm, rest_s)), {}))
        if day <= GATEWAY_DAYS:
            phases += day_phases(pybamm, day)
    experiment = pybamm.Experiment([p.steps for p in phases[solved:]])
    sol = simulation(pybamm, REFERENCE_TEMPERATURE_C, experiment).solve(starting_solution=sol)
    check_complete(sol, phases)

    schedule = []
    for phase, cycle in zip(phases, sol.cycles, strict=True):
        t = cycle["Time [s]"].entries
        entry: dict[str, Any] = {
            "kind": phase.kind,
            "day": phase.day,
            "start_s": round(max(float(t[0]) - off, 0.0), 3),
            "end_s": round(float(t[-1]) - off, 3),
            **phase.facts,
        }
        if phase.kind == "charge":
            entry["cv_start_s"] = round(float(cycle.steps[0]["Time [s]"].entries[-1]) - off, 3)
        schedule.append(entry)
    trace = trace_of(sol, window, t_from_s=off)
    return replace(trace, schedule=tuple(schedule))


def measured(trace: Trace, seed: int) -> FloatArray:
    """Columns as a tester would log them: seeded noise, then the logger's resolution."""
    rng = np.random.default_rng(seed)
    n = trace.t_s.size
    current = trace.current_A + rng.normal(0.0, CURRENT_NOISE_A, n)
    voltage = trace.voltage_V + rng.normal(0.0, VOLTAGE_NOISE_V, n)
    return np.column_stack(
        (
            np.round(trace.t_s, 3),
            np.round(current / CURRENT_RESOLUTION_A) * CURRENT_RESOLUTION_A,
            np.round(voltage / VOLTAGE_RESOLUTION_V) * VOLTAGE_RESOLUTION_V,
            np.round(trace.temperature_C / TEMPERATURE_RESOLUTION_C) * TEMPERATURE_RESOLUTION_C,
            np.round(trace.soc, 5),
        )
    )


def format_time(t_s: float) -> str:
    """Seconds without trailing zeros (integer sample times print as integers)."""
    return f"{t_s:.3f}".rstrip("0").rstrip(".")


def write_csv_gz(path: Path, rows: FloatArray) -> None:
    """Write the CSV gzip-compressed with a zero mtime so reruns are byte-identical."""
    text = io.StringIO()
    text.write(HEADER + "\n")
    for t, i, v, temp, soc in rows:
        text.write(f"{format_time(t)},{i:.3f},{v:.4f},{temp:.1f},{soc:.5f}\n")
    with (
        path.open("wb") as raw,
        gzip.GzipFile(filename="", mode="wb", fileobj=raw, mtime=0, compresslevel=9) as gz,
    ):
        gz.write(text.getvalue().encode("ascii"))


def seed_for(name: str) -> int:
    """A stable per-dataset seed (independent of run order)."""
    return NOISE_SEED + zlib.crc32(name.encode("ascii"))


def dataset_builders(
    pybamm: Any, window: Window
) -> dict[str, tuple[dict[str, Any], Callable[[], Trace]]]:
    """Every dataset: name -> (description for the manifest, thunk that simulates it)."""
    out: dict[str, tuple[dict[str, Any], Callable[[], Trace]]] = {}
    for ambient in AMBIENTS_C:
        for label, steps, scale in (
            ("dst", DST_STEPS, DST_PEAK_A),
            ("bbdst", BBDST_STEPS, BBDST_STEP1_A),
        ):
            info = {
                "profile": label,
                "ambient_C": ambient,
                "scale_A": scale,
                "profile_start_s": INITIAL_REST_S,
                "sample_period_s": 1.0,
            }
            out[f"dfn_nmc_{label}_{ambient}C"] = (
                info,
                partial(profile_trace, pybamm, steps, scale, ambient, window),
            )
    out["dfn_nmc_ocv_c20_25C"] = (
        {
            "profile": "ocv_c20",
            "ambient_C": REFERENCE_TEMPERATURE_C,
            "scale_A": OCV_TEST_CRATE * NOMINAL_CAPACITY_AH,
            "sample_period_s": OCV_TEST_PERIOD_S,
        },
        partial(ocv_test_trace, pybamm, window),
    )
    out[GATEWAY_NAME] = (
        {
            "profile": "gateway",
            "ambient_C": REFERENCE_TEMPERATURE_C,
            "days": GATEWAY_DAYS,
            "soc_before_aux_load": GATEWAY_SOC0,
            "sample_period_s": 1.0,
            "rest_sample_period_s": REST_PERIOD_S,
            "rest_fine_s": REST_FINE_S,
        },
        partial(gateway_trace, pybamm, window),
    )
    return out


def branch_capacity_Ah(trace: Trace, sign: float) -> float:
    """Charge in Ah moved with the current's sign equal to ``sign`` (+1 discharge, -1 charge)."""
    i_A = np.clip(sign * trace.current_A, 0.0, None)
    return float(np.sum(0.5 * (i_A[1:] + i_A[:-1]) * np.diff(trace.t_s)) / 3600.0)


def summary(trace: Trace, rows: FloatArray, path: Path, wall_s: float) -> dict[str, Any]:
    """Per-file facts for cell.json and the README table."""
    return {
        "file": path.name,
        "rows": int(rows.shape[0]),
        "bytes": path.stat().st_size,
        "duration_s": float(trace.t_s[-1] - trace.t_s[0]),
        "soc_start": round(float(trace.soc[0]), 4),
        "soc_end": round(float(trace.soc[-1]), 4),
        "voltage_min_V": round(float(trace.voltage_V.min()), 4),
        "voltage_max_V": round(float(trace.voltage_V.max()), 4),
        "temperature_max_C": round(float(trace.temperature_C.max()), 2),
        "ended_by": trace.ended_by,
        "wall_time_s": round(wall_s, 1),
    }


def readme_table(datasets: dict[str, dict[str, Any]]) -> str:
    """The README's file table (markdown)."""
    lines = [
        "| file | rows | size | duration | SOC start -> end | V min..max | T max | ended by |"
        " wall time |",
        "|---|---:|---:|---:|---|---|---:|---|---:|",
    ]
    for d in datasets.values():
        lines.append(
            f"| `{d['file']}` | {d['rows']} | {d['bytes'] / 1024:.0f} KiB"
            f" | {d['duration_s'] / 3600:.2f} h | {d['soc_start']:.3f} -> {d['soc_end']:.3f}"
            f" | {d['voltage_min_V']:.3f}..{d['voltage_max_V']:.3f} V"
            f" | {d['temperature_max_C']:.1f} C | {d['ended_by']} | {d['wall_time_s']:.0f} s |"
        )
    total = sum(d["bytes"] for d in datasets.values())
    lines.append("")
    lines.append(f"Total: {total / 1024 / 1024:.2f} MiB in {len(datasets)} files.")
    return "\n".join(lines)


def update_readme(readme: Path, table: str) -> None:
    """Replace the generated block of ``data/README.md`` (the rest is hand-written)."""
    if not readme.exists():
        return
    text = readme.read_text(encoding="utf-8")
    pattern = re.compile(re.escape(README_BEGIN) + ".*?" + re.escape(README_END), re.DOTALL)
    if not pattern.search(text):
        print(f"note: no generated block in {readme}; table not written", file=sys.stderr)
        return
    block = f"{README_BEGIN}\n{table}\n{README_END}"
    readme.write_text(pattern.sub(lambda _m: block, text), encoding="utf-8")


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0] if __doc__ else None)
    parser.add_argument("--out", type=Path, default=REPO / "data" / "physics")
    parser.add_argument("--only", nargs="*", default=None, help="dataset names to regenerate")
    args = parser.parse_args(argv)
    pybamm = import_pybamm()
    out: Path = args.out
    out.mkdir(parents=True, exist_ok=True)

    window = soc_window(pybamm)
    soc, ocv = ocv_curve(pybamm, window, OCV_CURVE_POINTS)
    cell_path = out / "cell.json"
    previous = json.loads(cell_path.read_text()) if cell_path.exists() else {}
    datasets: dict[str, dict[str, Any]] = dict(previous.get("datasets", {}))

    builders = dataset_builders(pybamm, window)
    unknown = set(args.only or ()) - set(builders)
    if unknown:
        parser.error(f"unknown dataset(s): {', '.join(sorted(unknown))}")
    for name, (info, build) in builders.items():
        if args.only and name not in args.only:
            continue
        started = time.perf_counter()
        trace = build()
        wall_s = time.perf_counter() - started
        rows = measured(trace, seed_for(name))
        path = out / f"{name}.csv.gz"
        write_csv_gz(path, rows)
        datasets[name] = {**info, **summary(trace, rows, path, wall_s)}
        if info["profile"] == "ocv_c20":
            datasets[name]["discharge_capacity_Ah"] = round(branch_capacity_Ah(trace, 1.0), 4)
            datasets[name]["charge_capacity_Ah"] = round(branch_capacity_Ah(trace, -1.0), 4)
        if trace.schedule:
            datasets[name]["soc_min"] = round(float(trace.soc.min()), 4)
            datasets[name]["soc_max"] = round(float(trace.soc.max()), 4)
            datasets[name]["schedule"] = list(trace.schedule)
        print(
            f"{name}: {rows.shape[0]} rows, SOC {trace.soc[0]:.3f}->{trace.soc[-1]:.3f},"
            f" {trace.ended_by}, wall {wall_s:.1f} s",
            flush=True,
        )

    ocv_test = datasets.get("dfn_nmc_ocv_c20_25C", {})
    ordered = {k: datasets[k] for k in builders if k in datasets}
    cell = {
        "source": f"PyBaMM {pybamm.__version__} DFN, parameter set {PARAMETER_SET} (LG M50)",
        "chemistry": "NMC811 / graphite-SiOx",
        "nominal_capacity_Ah": NOMINAL_CAPACITY_AH,
        "soc_window_capacity_Ah": round(window.capacity_Ah, 5),
        "c20_discharge_capacity_Ah": ocv_test.get("discharge_capacity_Ah"),
        "c20_charge_capacity_Ah": ocv_test.get("charge_capacity_Ah"),
        "voltage_min_V": V_MIN_V,
        "voltage_max_V": V_MAX_V,
        "stoichiometry": {
            "negative_at_soc0": round(window.x0, 6),
            "negative_at_soc100": round(window.x100, 6),
            "positive_at_soc0": round(window.y0, 6),
            "positive_at_soc100": round(window.y100, 6),
        },
        "ocv_curve": {
            "temperature_C": REFERENCE_TEMPERATURE_C,
            "soc": [round(float(s), 4) for s in soc],
            "ocv_V": [round(float(v), 6) for v in ocv],
        },
        "noise": {
            "voltage_sigma_V": VOLTAGE_NOISE_V,
            "current_sigma_A": CURRENT_NOISE_A,
            "voltage_resolution_V": VOLTAGE_RESOLUTION_V,
            "current_resolution_A": CURRENT_RESOLUTION_A,
            "temperature_resolution_C": TEMPERATURE_RESOLUTION_C,
            "seed": "NOISE_SEED + crc32(name)",
        },
        "datasets": ordered,
    }
    cell_path.write_text(json.dumps(cell, indent=1) + "\n", encoding="utf-8")
    update_readme(out.parent / "README.md", readme_table(ordered))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
