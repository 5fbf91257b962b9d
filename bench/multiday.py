"""The estimator per day over a simulated week (issue 11, evidence): known truth from
``bmsid.synthetic.multiday``, run the way a user runs ``bmsid identify``.

Each scenario writes its record (``record.csv.gz``: ``t_s,current_A,voltage_V``), the truth
(``truth.npz``) and the cell config (``cell.toml``: the paper's 70 Ah cell with no ``[initial]``
or ``[bounds]``, so start values and bounds are measured on the record) and runs
``bmsid.offline.identify.identify_file`` on them with no ``--soc0``. Equivalent CLI::

    bmsid identify DIR/clean/record.csv.gz --cell-config DIR/clean/cell.toml --out out/clean

Scenarios (``--scenario``, default all):

- ``clean``: no offset, constant parameters, start at rest at 93 %;
- ``offset-0.3``: current sensor reads 0.3 A more discharge than flows;
- ``rest-draw``: ``offset-0.3`` with a pack that draws 0.2 A at every rest (a converter left on,
  within the 0.7 A rest limit): a rest's reading is then 0.5 A, offset and draw together;
- ``offset-0.7-soc-wrong``: 0.7 A (1 % of 1C) and a start the engine does not know: the config
  says ``[soc_init] policy = "fixed", soc0 = 0.63`` (it does not read the first voltage) while
  the truth starts at 93 %, 30 points higher;
- ``start-load``: the first 30 min under a 0.17 A auxiliary load instead of at rest;
- ``temp-ageing``: +-8 degC a day (Arrhenius on R0 and R1, 30 kJ/mol), R0 +3 %/day, capacity
  -0.5 %/day;
- ``temp-ea50``: ``temp-ageing`` with a 50 kJ/mol activation energy (the engine's prior is 30);
- ``after-charge``: the clean case starting as a pack does after the evening charge and a
  night's rest: the true hysteresis state +1, which the rested voltage cannot tell the engine
  (it assumes 0) and whose swing to -1 in the first drive looks like a slow RC branch;
- ``m-tilt``: the clean case with a true hysteresis half-gap of another shape than the cell's
  table (1.6x the table at empty, 0.4x at full): the table is only a prior;
- ``all``: all of the above at once (0.7 A offset) but the after-charge start.

Per day: SOC error (max |error| and RMS, SOC points); the share of ticks whose SOC error is
within two published ``soc_std`` (95 % if that std were calibrated and the error Gaussian); the
offset estimate's error at the day's last tick (A); R0 median and 95th-percentile |relative
error| against the time-varying truth under load (|true I| > 0.05C); tau1 and R0+R1+R2 median
|relative error| under load; the published hysteresis half-gap M's median |relative error|
against the truth's M at the true SOC; model RMSE (v_meas - v_model, mV); and the capacity
estimate's error at the day's last tick (%). The record's first hour is left out of every
per-tick figure (the start-up). A field the engine does not
publish (``soc``, ``current_offset_A``, ``capacity_Ah``) prints ``-``.

    python bench/multiday.py [--quick] [--days N] [--scenario NAME ...] [--jobs 3]
        [--json PATH] [--out DIR] [--variant V] [--tuning KEY=VALUE ...]
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import tempfile
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import numpy.typing as npt

from bmsid.config.cell import SocInit, save_cell_config
from bmsid.estimate.tuning import VARIANTS_T, EstimatorTuning, Variant
from bmsid.estimate.types import EstimateBlock
from bmsid.offline.identify import IdentifySpec, identify_file
from bmsid.offline.inputs import load_config, parse_tuning
from bmsid.synthetic.multiday import (
    DAY_S,
    MultidayOptions,
    MultidayTruth,
    generate,
    options_document,
    reference_cell,
    write_record,
)
from bmsid.threads import one_blas_thread

one_blas_thread()  # the engine's matrices are small (bmsid/threads.py)

FloatArray = npt.NDArray[np.float64]

#: Ticks with |true current| above this C-rate count as under load for the parameter errors.
LOAD_C = 0.05
#: The record's start-up left out of every per-tick figure, s.
SKIP_S = 3600.0
#: The temperature-and-ageing case: +-8 degC a day, R0 +3 %/day, capacity -0.5 %/day.
TEMP_AGEING = MultidayOptions(temp_swing_C=8.0, r0_growth_per_day=0.03,
                              capacity_fade_per_day=0.005)  # fmt: skip


@dataclass(frozen=True)
class Scenario:
    name: str
    options: MultidayOptions
    #: SOC error of the config's fixed start (points as a fraction); None: the OCV-at-rest rule.
    start_soc_error: float | None = None


SCENARIOS: tuple[Scenario, ...] = (
    Scenario("clean", MultidayOptions()),
    Scenario("offset-0.3", MultidayOptions(current_offset_A=0.3)),
    Scenario("rest-draw", MultidayOptions(current_offset_A=0.3, rest_draw_A=0.2)),
    Scenario("offset-0.7-soc-wrong", MultidayOptions(current_offset_A=0.7), -0.30),
    Scenario("start-load", MultidayOptions(start_load_A=0.17)),
    Scenario("temp-ageing", TEMP_AGEING),
    # the same with an activation energy far from the engine's 30 kJ/mol prior: B is learnt
    Scenario("temp-ea50", replace(TEMP_AGEING, activation_energy_J_mol=50_000.0)),
    Scenario("after-charge", MultidayOptions(h0=1.0)),
    # the true hysteresis half-gap 1.6x the table at empty, 0.4x at full (the table a prior)
    Scenario("m-tilt", MultidayOptions(hysteresis_tilt=0.6)),
    Scenario("all", replace(TEMP_AGEING, current_offset_A=0.7, start_load_A=0.17), -0.30),
)
BY_NAME = {s.name: s for s in SCENARIOS}

#: (JSON key, table header, format of the value) per day.
COLUMNS: tuple[tuple[str, str, str], ...] = (
    ("soc_max_abs_pts", "SOC max (pts)", "{:.2f}"),
    ("soc_rms_pts", "SOC RMS (pts)", "{:.2f}"),
    ("soc_in_2sd_pct", "SOC in 2 std (%)", "{:.0f}"),
    ("offset_err_A", "offset err (A)", "{:+.3f}"),
    ("r0_med_pct", "R0 med (%)", "{:.1f}"),
    ("r0_p95_pct", "R0 p95 (%)", "{:.1f}"),
    ("tau1_med_pct", "tau1 med (%)", "{:.1f}"),
    ("rsum_med_pct", "R0+R1+R2 med (%)", "{:.1f}"),
    ("m_med_pct", "M med (%)", "{:.1f}"),
    ("rmse_mV", "RMSE (mV)", "{:.2f}"),
    ("capacity_err_pct", "capacity err (%)", "{:+.2f}"),
)


def _column(trace: EstimateBlock, name: str) -> FloatArray | None:
    """The first cell's column ``name``, None when the engine does not publish it."""
    if name not in trace.cells:
        return None
    return np.asarray(trace[name][:, 0], dtype=np.float64)


def _pct(x: FloatArray, q: float) -> float:
    x = x[np.isfinite(x)]
    return float(np.percentile(np.abs(x), q)) * 100.0 if x.size else math.nan


def _last(est: FloatArray | None, mask: npt.NDArray[np.bool_]) -> float:
    if est is None or not mask.any():
        return math.nan
    return float(est[np.flatnonzero(mask)[-1]])


def score_days(trace: EstimateBlock, truth: MultidayTruth, n_days: int) -> list[dict[str, float]]:
    """The per-day figures of ``COLUMNS`` (NaN where the engine publishes no such field)."""
    t = trace.t_s
    k = np.clip(np.searchsorted(truth.t_s, t, side="right") - 1, 0, truth.t_s.shape[0] - 1)
    cap_C = float(truth.capacity_Ah[0])
    load = np.abs(truth.current_A[k]) > LOAD_C * cap_C
    est = {n: _column(trace, n) for n in ("soc", "soc_std", "current_offset_A", "capacity_Ah",
                                          "R0_ohm", "R1_ohm", "R2_ohm", "tau1_s", "v_model_V",
                                          "v_meas_V", "M_V")}  # fmt: skip
    rows: list[dict[str, float]] = []
    for d in range(n_days):
        day = (t >= d * DAY_S) & (t < (d + 1) * DAY_S)
        m = day & (t >= SKIP_S)
        ml = m & load
        row = dict.fromkeys((c[0] for c in COLUMNS), math.nan)
        soc = est["soc"]
        if soc is not None and m.any():
            err = (soc[m] - truth.soc[k[m]]) * 100.0
            row["soc_max_abs_pts"] = float(np.nanmax(np.abs(err)))
            row["soc_rms_pts"] = float(np.sqrt(np.nanmean(err**2)))
            sd = est["soc_std"]
            if sd is not None:  # a calibrated std holds ~95 % of the errors within 2 std
                row["soc_in_2sd_pct"] = 100.0 * float(np.mean(np.abs(err) <= 200.0 * sd[m]))
        off = _last(est["current_offset_A"], day)
        if math.isfinite(off):
            row["offset_err_A"] = off - float(truth.current_offset_A[k[day][-1]])
        cap = _last(est["capacity_Ah"], day)
        if math.isfinite(cap):
            row["capacity_err_pct"] = 100.0 * (cap / float(truth.capacity_Ah[k[day][-1]]) - 1.0)
        r0, r1, r2, tau1 = est["R0_ohm"], est["R1_ohm"], est["R2_ohm"], est["tau1_s"]
        if r0 is not None and r1 is not None and r2 is not None and ml.any():
            kl = k[ml]
            rel0 = r0[ml] / truth.R0_ohm[kl] - 1.0
            row["r0_med_pct"], row["r0_p95_pct"] = _pct(rel0, 50), _pct(rel0, 95)
            rsum = truth.R0_ohm[kl] + truth.R1_ohm[kl] + truth.R2_ohm[kl]
            row["rsum_med_pct"] = _pct((r0[ml] + r1[ml] + r2[ml]) / rsum - 1.0, 50)
            if tau1 is not None:
                row["tau1_med_pct"] = _pct(tau1[ml] / truth.tau1_s[kl] - 1.0, 50)
        m_est = est["M_V"]
        if m_est is not None and m.any():
            row["m_med_pct"] = _pct(m_est[m] / truth.M_V[k[m]] - 1.0, 50)
        vm, vv = est["v_model_V"], est["v_meas_V"]
        if vm is not None and vv is not None and m.any():
            e = (vv[m] - vm[m])[np.isfinite(vv[m] - vm[m])]
            row["rmse_mV"] = float(np.sqrt(np.mean(e**2))) * 1e3 if e.size else math.nan
        rows.append(row)
    return rows


@dataclass(frozen=True)
class Job:
    scenario: Scenario
    n_days: int
    variant: Variant
    tuning: EstimatorTuning
    out: Path | None


@dataclass(frozen=True)
class Result:
    scenario: str
    soc_init_method: str
    published: tuple[str, ...]
    days: list[dict[str, float]]
    runtime_s: float


def run(job: Job) -> Result:
    sc = job.scenario
    opt = replace(sc.options, n_days=job.n_days)
    rec = generate(opt)
    with tempfile.TemporaryDirectory(prefix=f"multiday-{sc.name}-") as tmp:
        d = (job.out / sc.name) if job.out is not None else Path(tmp)
        d.mkdir(parents=True, exist_ok=True)
        write_record(rec, d / "record.csv.gz", d / "truth.npz")
        soc_init = (
            SocInit()
            if sc.start_soc_error is None
            else SocInit(policy="fixed", soc0=round(opt.soc0 + sc.start_soc_error, 4))
        )
        cell = reference_cell().model_copy(
            update={"initial": None, "bounds": None, "soc_init": soc_init}
        )
        save_cell_config(cell, d / "cell.toml")
        spec = IdentifySpec(cell=load_config(d / "cell.toml"), variant=job.variant,
                            tuning=job.tuning)  # fmt: skip
        res = identify_file(d / "record.csv.gz", spec)
    days = score_days(res.kept_trace(), rec.truth, opt.n_days)
    wanted = ("soc", "soc_std", "capacity_Ah", "capacity_std_Ah", "current_offset_A")
    published = tuple(n for n in wanted if n in res.kept_trace().cells)
    return Result(sc.name, res.soc_init_method, published, days, res.runtime_s)


def result_document(r: Result, n_days: int) -> dict[str, object]:
    """One scenario's figures for ``--json`` (NaN: null)."""
    sc = BY_NAME[r.scenario]
    per_day = [{k: (v if math.isfinite(v) else None) for k, v in row.items()} for row in r.days]
    return {
        "options": options_document(replace(sc.options, n_days=n_days)),
        "start_soc_error": sc.start_soc_error,
        "soc_init_method": r.soc_init_method,
        "published": list(r.published),
        "runtime_s": r.runtime_s,
        "per_day": per_day,
    }


def _fmt(x: float, f: str) -> str:
    return f.format(x) if math.isfinite(x) else "-"


def main() -> int:
    ap = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    ap.add_argument("--scenario", action="append", choices=list(BY_NAME), default=[],
                    help="scenario to run (repeatable; default all)")  # fmt: skip
    ap.add_argument("--days", type=int, default=7, help="days per record (default 7)")
    ap.add_argument("--quick", action="store_true", help="2 days")
    ap.add_argument("--variant", choices=VARIANTS_T, default="hy-affrls-lpso")
    ap.add_argument("--tuning", action="append", default=[], metavar="KEY=VALUE")
    ap.add_argument("--jobs", type=int, default=2, help="parallel runs (default 2)")
    ap.add_argument("--json", type=Path, help="write the figures here")
    ap.add_argument("--out", type=Path, help="keep each scenario's record, truth and config here")
    args = ap.parse_args()
    n_days = 2 if args.quick else args.days
    tuning = parse_tuning(args.tuning)
    todo = [BY_NAME[n] for n in (args.scenario or list(BY_NAME))]
    jobs = [Job(s, n_days, args.variant, tuning, args.out) for s in todo]
    with ProcessPoolExecutor(args.jobs) as ex:
        results = list(ex.map(run, jobs))
    print(f"variant `{args.variant}`, {n_days} day(s), first {SKIP_S / 3600:g} h left out\n")
    print("| scenario | day | " + " | ".join(c[1] for c in COLUMNS) + " |")
    print("|---|---|" + "---|" * len(COLUMNS))
    for r in results:
        for d, row in enumerate(r.days):
            cells = " | ".join(_fmt(row[key], f) for key, _, f in COLUMNS)
            print(f"| {r.scenario} | {d + 1} | {cells} |")
    for r in results:
        print(f"{r.scenario}: SOC start {r.soc_init_method}; publishes "
              f"{', '.join(r.published) or 'none of the SOC/offset/capacity fields'}; "
              f"engine {r.runtime_s:.0f} s")  # fmt: skip
    if args.json:
        doc = {
            "variant": args.variant,
            "days": n_days,
            "tuning_overrides": args.tuning,
            "skip_s": SKIP_S,
            "load_C": LOAD_C,
            "scenarios": {r.scenario: result_document(r, n_days) for r in results},
        }
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(doc, indent=2) + "\n", encoding="utf-8")
    return 0


if __name__ == "__main__":
    sys.exit(main())
