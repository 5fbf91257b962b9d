"""Regenerate the known-truth synthetic datasets in data/synthetic/ (deterministic, seeded).

    python scripts/make_synthetic_data.py [--out data/synthetic]

Every file is a tester-style CSV (``t_s,current_A,voltage_V`` or ``v_cell_NN``) plus truth
columns that bmsid ignores (``soc_true``, ``R0_true_ohm``...). See data/README.md.
"""

from __future__ import annotations

import argparse
import gzip
import json
from pathlib import Path

import numpy as np
import numpy.typing as npt

from bmsid.config.cell import paper_cell, save_cell_config
from bmsid.config.engine import ocv_model
from bmsid.model.simulator import simulate
from bmsid.profiles import dst_current
from bmsid.synthetic import TRUTH, dst_run_length_s

FloatArray = npt.NDArray[np.float64]
CELL = paper_cell(M_V=0.015, gamma=30.0)
OCV = ocv_model(CELL)
PEAK_A = 140.0  # DST 100 % = 2C of the 70 Ah cell
V_NOISE_V, I_NOISE_A = 1e-3, 0.05


def _write(path: Path, cols: dict[str, FloatArray], fmt: dict[str, str]) -> int:
    names = list(cols)
    n = len(next(iter(cols.values())))
    with gzip.GzipFile(path, "wb", mtime=0) as gz:  # mtime=0: byte-identical reruns
        gz.write((",".join(names) + "\n").encode())
        lines = (
            ",".join(format(cols[c][k], fmt.get(c, ".6g")) for c in names) + "\n" for k in range(n)
        )
        gz.write("".join(lines).encode())
    return n


def _sim(t: FloatArray, i: FloatArray, **kw: object) -> FloatArray:
    params: dict[str, object] = {**TRUTH, "gamma": CELL.hysteresis.gamma, "soc0": 0.98}
    params.update(kw)
    sim = simulate(t, i, OCV, capacity_Ah=CELL.capacity_Ah, **params)  # type: ignore[arg-type]
    return sim.v_V


def _noisy(rng: np.random.Generator, v: FloatArray, i: FloatArray) -> tuple[FloatArray, FloatArray]:
    return v + rng.normal(0, V_NOISE_V, v.shape), i + rng.normal(0, I_NOISE_A, i.shape)


def make_all(out: Path) -> dict[str, int]:
    out.mkdir(parents=True, exist_ok=True)
    rows: dict[str, int] = {}
    fmt = {"t_s": ".1f", "current_A": ".4f", "voltage_V": ".5f", "soc_true": ".6f"}
    n = dst_run_length_s(CELL, PEAK_A, 0.98, 0.10)
    t = np.arange(n, dtype=float)
    i = dst_current(t, PEAK_A)
    soc = 0.98 - np.concatenate(([0.0], np.cumsum(i[:-1]))) / (CELL.capacity_Ah * 3600)

    # 1. constant parameters (the reference case)
    rng = np.random.default_rng(101)
    v, im = _noisy(rng, _sim(t, i)[0], i)
    rows["synthetic_dst_constant"] = _write(
        out / "synthetic_dst_constant.csv.gz",
        {"t_s": t, "current_A": im, "voltage_V": v, "soc_true": soc}, fmt)  # fmt: skip

    # 2. drifting parameters: R0 +30 % and tau1 -20 % over the run (ageing/heating)
    rng = np.random.default_rng(102)
    r0 = TRUTH["R0_ohm"] * (1 + 0.3 * t / t[-1])
    tau1 = TRUTH["tau1_s"] * (1 - 0.2 * t / t[-1])
    v, im = _noisy(rng, _sim(t, i, R0_ohm=r0[None, :], tau1_s=tau1[None, :])[0], i)
    rows["synthetic_dst_drifting"] = _write(
        out / "synthetic_dst_drifting.csv.gz",
        {"t_s": t, "current_A": im, "voltage_V": v, "soc_true": soc, "R0_true_ohm": r0,
         "tau1_true_s": tau1}, {**fmt, "R0_true_ohm": ".7g", "tau1_true_s": ".5g"})  # fmt: skip

    # 3. rest-heavy: 20 min of DST, then 20 min of rest, repeated (half the time at rest)
    tr = np.arange(2 * n, dtype=float)
    on = (tr % 2400) < 1200
    ir = np.where(on, dst_current(tr, PEAK_A), 0.0)
    socr = 0.98 - np.concatenate(([0.0], np.cumsum(ir[:-1]))) / (CELL.capacity_Ah * 3600)
    rng = np.random.default_rng(103)
    v, im = _noisy(rng, _sim(tr, ir)[0], ir)
    rows["synthetic_dst_rest_heavy"] = _write(
        out / "synthetic_dst_rest_heavy.csv.gz",
        {"t_s": tr, "current_A": im, "voltage_V": v, "soc_true": socr}, fmt)  # fmt: skip

    # 4. a 12-cell series pack, cell 7 weak: R0 x1.6, R1 x1.4, 85 % capacity (own SOC)
    rng = np.random.default_rng(104)
    mult = rng.uniform(0.95, 1.05, 12)
    mult[6] = 1.6
    cols: dict[str, FloatArray] = {"t_s": t, "current_A": i + rng.normal(0, I_NOISE_A, n)}
    for c in range(12):
        cap = CELL.capacity_Ah * (0.85 if c == 6 else 1.0)
        sim = simulate(
            t, i, OCV, capacity_Ah=cap, R0_ohm=TRUTH["R0_ohm"] * mult[c],
            R1_ohm=TRUTH["R1_ohm"] * (1.4 if c == 6 else 1.0), tau1_s=TRUTH["tau1_s"],
            R2_ohm=TRUTH["R2_ohm"], tau2_s=TRUTH["tau2_s"], gamma=CELL.hysteresis.gamma,
            soc0=0.98,
        )  # fmt: skip
        cols[f"v_cell_{c + 1:02d}"] = sim.v_V[0] + rng.normal(0, V_NOISE_V, n)
    cut = int(0.75 * n)  # stop before the weak cell (85 % capacity) leaves the OCV range
    rows["synthetic_pack12_weak_cell"] = _write(
        out / "synthetic_pack12_weak_cell.csv.gz", {k: v[:cut] for k, v in cols.items()},
        {**fmt, **{f"v_cell_{c + 1:02d}": ".5f" for c in range(12)}})  # fmt: skip

    save_cell_config(CELL, out / "cell.toml")
    truth = {
        **TRUTH, "M_V": 0.015, "gamma": CELL.hysteresis.gamma, "capacity_Ah": CELL.capacity_Ah,
        "soc0": 0.98, "dst_peak_A": PEAK_A, "v_noise_V": V_NOISE_V, "i_noise_A": I_NOISE_A,
        "pack12_R0_multipliers": [round(float(m), 6) for m in mult], "pack12_weak_cell": 7,
        "rows": rows,
    }  # fmt: skip
    (out / "truth.json").write_text(json.dumps(truth, indent=2) + "\n")
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--out", type=Path, default=Path("data/synthetic"))
    args = ap.parse_args()
    for name, n in make_all(args.out).items():
        print(f"{name}: {n} rows")


if __name__ == "__main__":
    main()
