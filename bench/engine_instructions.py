"""Instructions per identification tick, counted by valgrind (repeatable, unlike wall time on a
shared VM): the engine's per-tick cost without the noise of other jobs.

    python bench/engine_instructions.py                 # this tree
    python bench/engine_instructions.py --tree DIR      # another checkout (e.g. a5415e1's flat
                                                        # engine) with the same interpreter
    python bench/engine_instructions.py --observer      # with and without the SOC observer

Each case runs twice under ``valgrind --tool=callgrind`` (N1 and N2 ticks of the synthetic DST
case); the difference divided by N2 - N1 removes start-up and imports. Needs valgrind.
"""

from __future__ import annotations

import argparse
import os
import re
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
CASES = (("1", "hy-affrls", 500, 1500), ("1", "hy-affrls-lpso", 500, 2000),
         ("96", "hy-affrls", 200, 600))  # fmt: skip

#: Runs one case with whichever engine API the tree has (staged: build_bank + update_block;
#: flat, before issue 14: EstimatorBank(cell, n) + update per sample).
RUNNER = """
import sys, numpy as np
from bmsid.synthetic import paper_dst_case
n_cells, n, variant = int(sys.argv[1]), int(sys.argv[2]), sys.argv[3]
observer = sys.argv[4] == "on"
spread = np.random.default_rng(0).uniform(0.8, 1.3, n_cells)
run = paper_dst_case(n, r0_spread=spread if n_cells > 1 else None)
try:
    from bmsid.config.engine import build_bank
    from bmsid.samples import SampleBlock
except ImportError:
    from bmsid.estimate.bank import EstimatorBank
    bank = EstimatorBank(run.cell, n_cells, variant, soc0=0.98)
    for k in range(n):
        bank.update(run.t_s[k], run.current_A[k], run.voltages_V[k])
else:
    try:
        from bmsid.estimate.observer_tuning import ObserverTuning
        from bmsid.estimate.tuning import EstimatorTuning
        tuning = EstimatorTuning(observer=ObserverTuning(enabled=observer))
    except ImportError:  # a tree from before the observer
        tuning = None
    bank = build_bank(run.cell, n_cells, variant, tuning, soc0=0.98)
    bank.update_block(SampleBlock.from_arrays(run.t_s, run.current_A, run.voltages_V))
"""


def instructions(tree: Path, n_cells: str, variant: str, n: int, observer: str = "on") -> int:
    env = {**os.environ, "PYTHONPATH": str(tree / "service"), "OPENBLAS_NUM_THREADS": "1",
           "OMP_NUM_THREADS": "1"}  # fmt: skip
    out = subprocess.run(
        ["valgrind", "--tool=callgrind", "--callgrind-out-file=/dev/null", sys.executable, "-c",
         RUNNER, n_cells, str(n), variant, observer],
        capture_output=True, text=True, env=env, check=True,
    )  # fmt: skip
    m = re.search(r"Collected : (\d+)", out.stderr)
    if m is None:
        raise RuntimeError(f"no instruction count from valgrind:\n{out.stderr[-500:]}")
    return int(m.group(1))


def main() -> None:
    ap = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    ap.add_argument("--tree", type=Path, default=REPO, help="checkout to measure")
    ap.add_argument("--observer", action="store_true", help="also without the SOC observer")
    args = ap.parse_args()
    modes = ("on", "off") if args.observer else ("on",)
    head = " | ".join(f"instructions per tick, observer {m}" for m in modes)
    print(f"| cells | variant | {head} |\n|---|---|{'---|' * len(modes)}")
    for n_cells, variant, n1, n2 in CASES:
        per_tick = []
        for mode in modes:
            a = instructions(args.tree, n_cells, variant, n1, mode)
            b = instructions(args.tree, n_cells, variant, n2, mode)
            per_tick.append(f"{(b - a) / (n2 - n1):,.0f}")
        print(f"| {n_cells} | `{variant}` | {' | '.join(per_tick)} |", flush=True)


if __name__ == "__main__":
    main()
