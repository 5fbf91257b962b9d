"""Measured records entered mid-drive, as a gateway that restarts under load sees them (issue 11,
"start from anywhere").

    python bench/starts_midrive.py [--jobs 2] [--cuts 1800 4500]

Each 80 % CALCE record (DST, BJDST, FUDS, US06 at 0, 25, 45 C) and the A123 DYN50 record is cut
``--cuts`` seconds in (the cut file starts at t = 0 there, whatever the current), and the cut is
identified twice with ``hy-affrls-lpso`` and the shipped config: with the SOC at the cut given
(the known start minus the charge counted up to the cut over the config's capacity) and without
it (no ``--soc0``: the first voltage IR-corrected, then the start fit over the first 20 min where
it opens under load or relaxing). Both are scored on SOC 95..15 % of the same count from the
SOC at the cut; the difference is what the unknown start costs there.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

from accuracy_real import A123_FILE, CALCE, CELLS, REAL, Case, run
from bmsid.estimate.tuning import EstimatorTuning
from bmsid.offline.csvio import TesterData, read_tester_csv, write_tester_csv
from bmsid.offline.inputs import load_config

#: (label, record, config, known SOC at its start): the data README's starts
RECORDS = [
    (f"CALCE {prof} {temp}C", CALCE / f"calce_inr18650-20r_{temp}C_{prof}_80soc.csv.gz",
     CELLS / f"calce_inr18650_20r_{temp}C.toml", 0.819 if temp == 0 else 0.8)
    for temp in (25, 45, 0) for prof in ("DST", "BJDST", "FUDS", "US06")
] + [("A123 DYN50 25C", A123_FILE, CELLS / "a123_lfp_25C.toml", 1.0)]  # fmt: skip


def cut_record(path: Path, cfg: Path, soc_start: float, t_cut_s: float, out: Path) -> float:
    """Write the record from ``t_cut_s`` on to ``out`` (time from 0); the SOC at the cut."""
    d = read_tester_csv(path)
    t, i = d.t_s, d.current_A
    dt = np.diff(t, prepend=t[0])
    charge_Ah = np.cumsum(np.concatenate(([0.0], i[:-1])) * dt) / 3600.0
    k = int(np.searchsorted(t, t[0] + t_cut_s))
    temp = None if d.temperature_C is None else d.temperature_C[k:]
    write_tester_csv(
        TesterData(t_s=t[k:] - t[k], current_A=i[k:], cell_voltages_V=d.cell_voltages_V[k:],
                   cell_names=d.cell_names, temperature_C=temp),
        out,
    )  # fmt: skip
    return float(soc_start - charge_Ah[k] / load_config(cfg).capacity_Ah)


def main() -> int:
    ap = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    ap.add_argument("--jobs", type=int, default=2, help="parallel runs (default 2)")
    ap.add_argument("--cuts", type=float, nargs="+", default=[1800.0, 4500.0], metavar="S")
    args = ap.parse_args()
    if not CALCE.exists():
        print(f"no real data at {REAL}; set BMSID_REAL_DATA")
        return 2
    with tempfile.TemporaryDirectory() as tmp:
        todo: list[Case] = []
        for label, path, cfg, soc_start in RECORDS:
            for t_cut in args.cuts:
                out = Path(tmp) / f"{label.replace(' ', '_')}_{int(t_cut)}.csv"
                z = cut_record(path, cfg, soc_start, t_cut, out)
                name = f"{label} from {int(t_cut)} s ({100 * z:.1f} %)"
                todo += [Case(name, out, cfg, soc0, z, "hy-affrls-lpso") for soc0 in (z, None)]
        with ProcessPoolExecutor(args.jobs) as ex:
            rows = list(ex.map(run, todo, [EstimatorTuning()] * len(todo)))
    print("| record entered at | start given | no start | difference |\n|---|---|---|---|")
    diffs = []
    for given, unknown in zip(rows[::2], rows[1::2], strict=True):
        d = 1e3 * (unknown.window_V - given.window_V)
        diffs.append(d)
        print(f"| {given.case.label} | {1e3 * given.window_V:.2f} mV "
              f"| {1e3 * unknown.window_V:.2f} mV | {d:+.2f} mV |")  # fmt: skip
    print(
        f"\nmean difference {np.mean(diffs):+.2f} mV, largest {max(diffs):+.2f} mV; "
        f"{sum(d > 1.0 for d in diffs)} of {len(diffs)} more than 1 mV worse without the start"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
