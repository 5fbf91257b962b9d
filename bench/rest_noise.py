"""Rests seen through the current sensor's noise (issue 11): a known-truth LFP record whose
measured current carries 0, 3, 10 or 20 mA of noise (the A123 config's 2.07 Ah cell: its rest
limit, 1 % C, is 20.7 mA). Prints a Markdown table.

    python bench/rest_noise.py [--jobs 2]

The truth: ``hysteresis_lfp.py``'s record (the shipped A123 config's curve and half-gap, a 2RC
model, 12 h of rest, two DST drives and a charge), h a play operator at the config's gamma 30,
1 mV of voltage noise. Starts at 90 % (h -1) and 60 % (h 0 and +1), run through ``identify``'s
path without a start SOC. Per
noise level and start: the RMS SOC error (points) and model RMSE (mV) after the first hour, and
the anchors the observer took (``rest_anchor.next_noise``, ``rest_limit``).
"""

from __future__ import annotations

import argparse
import itertools
from concurrent.futures import ProcessPoolExecutor

from bmsid.config.cell import load_cell_config
from bmsid.estimate.tuning import EstimatorTuning
from hysteresis_lfp import CELL, score

NOISES_A = (0.0, 0.003, 0.01, 0.02)
STARTS = ((0.9, -1.0), (0.6, 0.0), (0.6, 1.0))


def run(args: tuple[float, float, float]) -> tuple[float, float, int]:
    """(RMS SOC error in points, model RMSE in mV) after the first hour, and the anchors."""
    noise_A, z0, h0 = args
    cell = load_cell_config(CELL)
    play = cell.hysteresis_law == "play"
    return score(cell, z0, h0, cell.hysteresis.gamma, play, EstimatorTuning(), noise_A)


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
