"""What an unknown start costs on measured cells (issue 11, "start from anywhere").

    python bench/starts_real.py [--jobs 2] [--tuning KEY=VALUE ...]

All 24 CALCE INR18650-20R records (DST, BJDST, FUDS, US06 at 0, 25 and 45 C, started at 80 %
and at 50 % SOC), each run twice with ``hy-affrls-lpso`` and the shipped per-temperature
config: with the cycler's known start given (``--soc0``) and without it (SOC from the first
voltage, as a user without the test log runs it). Both are scored on SOC 95..15 % of the same
coulomb count from the known start, so the difference is what the unknown start costs. The
50 % starts were not tuned on: ``bench/accuracy_real.py`` runs the 80 % ones.
"""

from __future__ import annotations

import argparse
import sys
from concurrent.futures import ProcessPoolExecutor

from accuracy_real import CALCE, CELLS, REAL, Case, run
from bmsid.offline.inputs import parse_tuning

#: The known starts (data README): 80 / 50 % of 2.0 Ah at 25 and 45 C; at 0 C 0.3615 /
#: 0.9035 Ah out of a full charge.
STARTS = {(0, 80): 0.819, (0, 50): 0.548, (25, 80): 0.8, (25, 50): 0.5, (45, 80): 0.8,
          (45, 50): 0.5}  # fmt: skip
PROFILES = ("DST", "BJDST", "FUDS", "US06")


def main() -> int:
    ap = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    ap.add_argument("--tuning", action="append", default=[], metavar="KEY=VALUE")
    ap.add_argument("--jobs", type=int, default=2, help="parallel runs (default 2)")
    args = ap.parse_args()
    if not CALCE.exists():
        print(f"no real data at {REAL}; set BMSID_REAL_DATA")
        return 2
    tuning = parse_tuning(args.tuning)
    todo: list[Case] = []
    for (temp, pct), z0 in STARTS.items():
        cfg = CELLS / f"calce_inr18650_20r_{temp}C.toml"
        for prof in PROFILES:
            path = CALCE / f"calce_inr18650-20r_{temp}C_{prof}_{pct}soc.csv.gz"
            label = f"CALCE {prof} {temp}C from {pct} %"
            todo += [Case(label, path, cfg, soc0, z0, "hy-affrls-lpso") for soc0 in (z0, None)]
    with ProcessPoolExecutor(args.jobs) as ex:
        rows = list(ex.map(run, todo, [tuning] * len(todo)))
    print("| record | start given | start from the first voltage | difference |\n|---|---|---|---|")
    diffs: list[float] = []
    for given, unknown in zip(rows[::2], rows[1::2], strict=True):
        d = 1e3 * (unknown.window_V - given.window_V)
        diffs.append(d)
        print(f"| {given.case.label} | {1e3 * given.window_V:.2f} mV "
              f"| {1e3 * unknown.window_V:.2f} mV | {d:+.2f} mV |")  # fmt: skip
    worse = sum(d > 1.0 for d in diffs)
    print(f"\nmean difference {sum(diffs) / len(diffs):+.2f} mV, largest {max(diffs):+.2f} mV; "
          f"{worse} of {len(diffs)} records more than 1 mV worse without the start; "
          f"tuning overrides: {args.tuning or 'none'}")  # fmt: skip
    return 0


if __name__ == "__main__":
    sys.exit(main())
