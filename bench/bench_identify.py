"""Wall time of an offline identification per variant on a DST file, beside the paper's run times.

Input: the physics 15 C DST file (``data/physics/dfn_nmc_dst_15C.csv.gz``, 12,588 samples at
1 s) with a cell config fitted by ``bmsid fit-ocv`` from ``data/physics/dfn_nmc_ocv_c20_25C``
when both exist, else a synthetic DST run of the paper's 70 Ah cell (8,250 samples, the length
of the paper's DST test) generated here. Each variant calls the library function behind
``bmsid identify``, :func:`bmsid.offline.identify.identify_file`, in-process (cell config load,
CSV read, identification, params.csv, metrics.json, plots: the command without its argument
parsing and printing); "loop" is the identification alone (``runtime_s`` in metrics.json).
The paper: 18.7-22.3 s per DST run (MATLAB, their PC).

    PYTHONPATH=service python bench/bench_identify.py [--input FILE --cell-config FILE]
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

import numpy as np

from bmsid.config.cell import paper_cell, save_cell_config
from bmsid.config.engine import ocv_model
from bmsid.errors import UserError
from bmsid.estimate.types import VARIANTS
from bmsid.model.simulator import simulate
from bmsid.offline.csvio import TesterData, write_tester_csv
from bmsid.offline.identify import IdentifySpec, identify_file
from bmsid.offline.inputs import load_config
from bmsid.offline.ocv_config import OcvFitSpec, fit_ocv_files
from bmsid.offline.report import PAPER_RUNTIME_S
from bmsid.profiles import dst_current
from bmsid.threads import one_blas_thread

one_blas_thread()  # the engine's matrices are small (bmsid/threads.py)

REPO = Path(__file__).resolve().parents[1]
PHYSICS_DST = REPO / "data" / "physics" / "dfn_nmc_dst_15C.csv.gz"
PHYSICS_OCV = REPO / "data" / "physics" / "dfn_nmc_ocv_c20_25C.csv.gz"


def synthetic_dst(tmp: Path, n: int = 8250) -> tuple[Path, Path]:
    """The paper's cell on DST (2C peak) with 1 mV noise: CSV and cell config paths."""
    cell = paper_cell()
    t = np.arange(n, dtype=float)
    i = dst_current(t, 2.0 * cell.capacity_Ah)
    sim = simulate(
        t, i, ocv_model(cell), capacity_Ah=cell.capacity_Ah, R0_ohm=1.2e-3,
        R1_ohm=0.8e-3, tau1_s=30.0, R2_ohm=1.0e-3, tau2_s=600.0, gamma=30.0, soc0=0.95,
    )  # fmt: skip
    v = sim.v_V[0] + np.random.default_rng(0).normal(0.0, 1e-3, n)
    csv_path = tmp / "synthetic_dst_25C.csv"
    write_tester_csv(TesterData(t, i, v[:, None], ["voltage_V"]), csv_path)
    cfg = tmp / "paper_cell.toml"
    save_cell_config(paper_cell(), cfg)
    return csv_path, cfg


def physics_config(tmp: Path) -> Path:
    """``bmsid fit-ocv`` of the physics OCV test (chemistry NMC), saved as a cell config."""
    cfg = tmp / "dfn_fitted.toml"
    try:
        fit = fit_ocv_files([PHYSICS_OCV], OcvFitSpec(cfg.stem, chemistry="NMC"))
    except UserError as exc:
        raise SystemExit(f"fit-ocv failed on {PHYSICS_OCV}: {exc}") from None
    save_cell_config(fit.config, cfg)
    return cfg


def main_bench() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--input", type=Path, default=None)
    ap.add_argument("--cell-config", type=Path, default=None)
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as td:
        tmp = Path(td)
        if args.input is not None:
            src, cfg = args.input, args.cell_config
            if cfg is None:
                raise SystemExit("--input needs --cell-config")
        elif PHYSICS_DST.exists() and PHYSICS_OCV.exists():
            src, cfg = PHYSICS_DST, physics_config(tmp)
        else:
            src, cfg = synthetic_dst(tmp)
        print(f"input: {src} (cell config {cfg.name})")
        print(f"{'variant':<16} {'samples':>8} {'wall s':>8} {'loop s':>8} {'us/sample':>10} "
              f"{'RMSE mV':>8}")  # fmt: skip
        for variant in VARIANTS:
            out = tmp / variant
            t0 = time.perf_counter()
            try:
                identify_file(src, IdentifySpec(cell=load_config(cfg), variant=variant), out)
            except UserError as exc:
                raise SystemExit(f"identify failed for {variant}: {exc}") from None
            wall = time.perf_counter() - t0
            doc = json.loads((out / "metrics.json").read_text(encoding="utf-8"))
            n = int(doc["n_input_samples"])
            print(
                f"{variant:<16} {n:>8d} {wall:>8.2f} {doc['runtime_s']:>8.2f} "
                f"{1e6 * doc['runtime_s'] / n:>10.1f} {1e3 * doc['rmse_V']:>8.2f}"
            )
    lo, hi = PAPER_RUNTIME_S["DST"]
    print(f"paper (MATLAB, their PC): {lo}-{hi} s per DST run of 8,250 samples")


if __name__ == "__main__":
    main_bench()
