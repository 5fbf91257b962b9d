"""SOC against the tester's coulomb count on the measured records, as a user runs them (issue 11:
state that stays true). Prints a Markdown table.

    BMSID_REAL_DATA=../shared/data/real python bench/soc_real.py [--jobs 2] [--tuning K=V ...]

Every record of ``bench/accuracy_real.py`` (A123 LFP DYN50 at 25 C; CALCE INR18650-20R, four
profiles at 0, 25 and 45 C) through ``identify``'s path with ``hy-affrls-lpso``, the shipped cell
config and no start SOC. The reference is the tester's current counted from the record's known
start (A123: full; CALCE: ``accuracy_real.CALCE_SOC0``) with the config's capacity: a laboratory
count drifts only by the capacity's error (A123: its count ends at 4.6 % where the cell reached
its cut-off, so the config's 2.075 Ah is about 4 % above what this discharge gave; the count's
error grows to that at the end). Scored after the first hour: the largest and the RMS
difference (points), the share of ticks within 2 published ``soc_std``, the difference at the
end.
"""

from __future__ import annotations

import argparse
import sys
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

from accuracy_real import (
    A123_FILE,
    CALCE,
    CALCE_SOC0,
    CELLS,
    REAL,
)
from bmsid.estimate.tuning import EstimatorTuning
from bmsid.offline.identify import IdentifySpec, identify_file
from bmsid.offline.inputs import load_config, parse_tuning
from bmsid.offline.scoring import SocReference

Case = tuple[str, Path, Path, float]


def run(case: Case, tuning: EstimatorTuning) -> str:
    label, path, cfg, z0 = case
    cell = load_config(cfg)
    res = identify_file(path, IdentifySpec(cell=cell, variant="hy-affrls-lpso", tuning=tuning))
    tr = res.kept_trace()
    err = np.asarray(tr["soc"][:, 0] - SocReference.from_cell(cell, z0).soc(tr))
    sd = np.asarray(tr["soc_std"][:, 0])
    late = tr.t_s >= tr.t_s[0] + 3600.0
    e = err[late]
    within = 100.0 * float(np.mean(np.abs(e) <= 2.0 * sd[late]))
    return (
        f"| {label} | {100 * np.max(np.abs(e)):.2f} | {100 * np.sqrt(np.mean(e**2)):.2f} | "
        f"{within:.0f} | {100 * err[-1]:+.2f} |"
    )


def main() -> int:
    ap = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    ap.add_argument("--tuning", action="append", default=[], metavar="KEY=VALUE")
    ap.add_argument("--jobs", type=int, default=2, help="parallel runs (default 2)")
    args = ap.parse_args()
    if not A123_FILE.exists():
        print(f"no real data at {REAL}; set BMSID_REAL_DATA")
        return 2
    tuning = parse_tuning(args.tuning)
    todo: list[Case] = [("A123 DYN50 25C", A123_FILE, CELLS / "a123_lfp_25C.toml", 1.0)]
    for temp, z0 in CALCE_SOC0.items():
        cfg = CELLS / f"calce_inr18650_20r_{temp}C.toml"
        for prof in ("DST", "BJDST", "FUDS", "US06"):
            path = CALCE / f"calce_inr18650-20r_{temp}C_{prof}_80soc.csv.gz"
            todo.append((f"CALCE {prof} {temp}C", path, cfg, z0))
    print("| record | SOC - count max (pts) | RMS (pts) | within 2 std (%) | at the end (pts) |\n"
          "|---|---|---|---|---|")  # fmt: skip
    with ProcessPoolExecutor(args.jobs) as ex:
        for line in ex.map(run, todo, [tuning] * len(todo)):
            print(line, flush=True)
    print(f"tuning overrides: {args.tuning or 'none'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
