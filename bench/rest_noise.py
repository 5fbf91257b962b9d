"""Rests seen through the current sensor's noise (issue 11): a known-truth LFP record whose
measured current carries 0, 3 or 10 mA of noise (the A123 config's 2.07 Ah cell: its rest
limit, 1 % C, is 20.7 mA). Prints a Markdown table.

    python bench/rest_noise.py [--jobs 2]

The truth: the shipped A123 config's OCV curve and half-gap, a 2RC model (R0 10, R1 5, R2 10
mOhm; tau 20 / 300 s), h a play operator at the config's gamma 30; 12 h at 1 s: 1 h rest, two
1.5 h DST drives at 2 A peak with 2.5 h rests, a 0.3 A charge, 1 mV of voltage noise. Starts at
90 % (h -1) and 60 % (h 0 and +1), run through ``identify``'s path without a start SOC. Per
noise level and start: the RMS SOC error (points) and model RMSE (mV) after the first hour, and
the anchors the observer took (``rest_anchor.next_noise``, ``rest_limit``).
"""

from __future__ import annotations

import argparse
import itertools
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

from bmsid.config.cell import load_cell_config
from bmsid.config.engine import ocv_model
from bmsid.estimate.tuning import EstimatorTuning
from bmsid.model.simulator import simulate
from bmsid.offline.identify import IdentifySpec, identify_source
from bmsid.offline.inputs import LoadedInput
from bmsid.profiles import dst_current
from bmsid.samples import SampleBlock

CELL = Path(__file__).resolve().parents[1] / "configs" / "cells" / "a123_lfp_25C.toml"
H = 3600.0
NOISES_A = (0.0, 0.003, 0.01)
STARTS = ((0.9, -1.0), (0.6, 0.0), (0.6, 1.0))


def run(args: tuple[float, float, float]) -> tuple[float, float, int]:
    """(RMS SOC error in points, model RMSE in mV) after the first hour, and the anchors."""
    noise_A, z0, h0 = args
    cell = load_cell_config(CELL)
    t = np.arange(0.0, 12 * H)
    i = np.zeros_like(t)
    for start_h in (1.0, 5.0):
        m = (t >= start_h * H) & (t < (start_h + 1.5) * H)
        i[m] = dst_current(t[m] - start_h * H, 2.0)
    i[(t >= 9 * H) & (t < 10.5 * H)] = -0.3
    sim = simulate(
        t, i, ocv_model(cell), capacity_Ah=cell.capacity_Ah, R0_ohm=0.01, R1_ohm=0.005,
        tau1_s=20.0, R2_ohm=0.01, tau2_s=300.0, gamma=cell.hysteresis.gamma, soc0=z0, h0=h0,
        play=cell.hysteresis_law == "play",
    )  # fmt: skip
    rng = np.random.default_rng(0)
    block = SampleBlock.from_arrays(
        t, i + rng.normal(0.0, noise_A, t.size), sim.v_V.T + rng.normal(0.0, 1e-3, (t.size, 1))
    )
    src = LoadedInput(source="<known truth>", samples=block, cell_names=["cell_01"])
    out = identify_source(src, IdentifySpec(cell=cell, tuning=EstimatorTuning()))
    tr = out.kept_trace()
    k = np.searchsorted(t, tr.t_s)
    late = tr.t_s >= H
    err = (np.asarray(tr["soc"][:, 0]) - np.ravel(sim.soc)[k])[late]
    e = np.asarray(tr["v_error_V"][:, 0])[late]
    rms = 100.0 * float(np.sqrt(np.mean(err**2)))
    return rms, 1e3 * float(np.sqrt(np.nanmean(e**2))), int(out.counters.get("anchors", 0))


def main() -> int:
    ap = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    ap.add_argument("--jobs", type=int, default=2, help="parallel runs (default 2)")
    args = ap.parse_args()
    todo = list(itertools.product(NOISES_A, STARTS))
    with ProcessPoolExecutor(max_workers=args.jobs) as pool:
        res = list(pool.map(run, [(n, z, h) for n, (z, h) in todo]))
    print("| noise | 90 %, h -1 | 60 %, h 0 | 60 %, h +1 | anchors |")
    print("|---|---|---|---|---|")
    for j, noise in enumerate(NOISES_A):
        row = res[3 * j : 3 * j + 3]
        cells = " | ".join(f"{r[0]:.2f} pts, {r[1]:.2f} mV" for r in row)
        anchors = "/".join(str(r[2]) for r in row)
        print(f"| {1e3 * noise:.0f} mA | {cells} | {anchors} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
