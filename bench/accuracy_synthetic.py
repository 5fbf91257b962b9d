"""Accuracy on the known-truth reference case (the README's engine table).

    python bench/accuracy_synthetic.py

Runs each variant over ``bmsid.synthetic.paper_dst_case`` and scores it after the first 10 % of
samples against the truth; also, for the fusion, the +30 % R0 ramp and a start just after a full
charge (true hysteresis state +1, which a rested voltage cannot tell the engine; no ``soc0``:
SOC from the first voltage, as a user runs it). "RMSE" is against the measured voltage, whose
1 mV noise sets its floor; "model error" is against the same record's noise-free voltage (the
generator run again without voltage noise, same seed: the same current), what the model misses.
"""

from __future__ import annotations

import numpy as np

from bmsid.config.engine import build_bank
from bmsid.estimate.tuning import VARIANTS_T, EstimatorTuning, Variant
from bmsid.metrics import voltage_metrics
from bmsid.samples import SampleBlock
from bmsid.synthetic import SyntheticRun, paper_dst_case
from bmsid.threads import one_blas_thread

one_blas_thread()  # the engine's matrices are small (bmsid/threads.py)


def score(
    run: SyntheticRun, clean: SyntheticRun, variant: Variant, tuning: EstimatorTuning,
    soc0: float | None = 0.98,
) -> dict[str, float]:  # fmt: skip
    """The table's figures after the first 10 % of ticks; ``clean`` is ``run`` without voltage
    noise (the model error's reference)."""
    bank = build_bank(run.cell, 1, variant, tuning, soc0=soc0)
    est = bank.update_block(SampleBlock.from_arrays(run.t_s, run.current_A, run.voltages_V))
    keys = ("R0_ohm", "R1_ohm", "R2_ohm", "tau1_s", "v_model_V", "v_meas_V")
    a = {k: est[k][est.n_ticks // 10 :, 0] for k in keys}
    v_clean = clean.voltages_V[np.searchsorted(run.t_s, est.t_s)[est.n_ticks // 10 :], 0]
    r0_true = run.R0_true_ohm[run.t_s.shape[0] // 10 :, 0]
    t = run.truth
    rsum_true = r0_true + t["R1_ohm"] + t["R2_ohm"]
    m = voltage_metrics(a["v_meas_V"], a["v_model_V"])
    rsum_rel = np.abs((a["R0_ohm"] + a["R1_ohm"] + a["R2_ohm"]) / rsum_true - 1)
    return {
        "rmse_mV": m.rmse_V * 1e3,
        "model_mV": 1e3 * float(np.sqrt(np.mean((a["v_model_V"] - v_clean) ** 2))),
        "max_err_mV": m.max_abs_error_V * 1e3,
        "r0_pct": 100 * float(np.max(np.abs(a["R0_ohm"] / r0_true - 1))),
        "rsum_pct": 100 * float(np.max(rsum_rel)),
        "rsum_med_pct": 100 * float(np.median(rsum_rel)),
        "tau1_pct": 100 * float(np.max(np.abs(a["tau1_s"] / t["tau1_s"] - 1))),
    }


def _case(r0_ramp: float = 0.0, h0: float = 0.0) -> tuple[SyntheticRun, SyntheticRun]:
    """The reference case (R0 ramp, start hysteresis state) and the same record without voltage
    noise."""
    return (
        paper_dst_case(r0_ramp=r0_ramp, h0=h0),
        paper_dst_case(r0_ramp=r0_ramp, h0=h0, v_noise_V=0.0),
    )


def main() -> None:
    base = _case()
    rows: list[tuple[str, dict[str, float]]] = []
    for variant in VARIANTS_T:
        rows.append((f"`{variant}`", score(*base, variant, EstimatorTuning())))
    rows.append((
        "`hy-affrls-lpso`, OCV offset identified",
        score(*base, "hy-affrls-lpso", EstimatorTuning(identify_ocv_offset=True)),
    ))  # fmt: skip
    rows.append((
        "`hy-affrls-lpso`, R0 ramping +30 %",
        score(*_case(r0_ramp=0.3), "hy-affrls-lpso", EstimatorTuning()),
    ))  # fmt: skip
    rows.append((
        "`hy-affrls-lpso`, start just after a full charge (h = +1), no `soc0`",
        score(*_case(h0=1.0), "hy-affrls-lpso", EstimatorTuning(), soc0=None),
    ))  # fmt: skip
    print("| variant | RMSE | model error | max error | max R0 error | max R0+R1+R2 error "
          "| median R0+R1+R2 error | max tau1 error |")  # fmt: skip
    print("|---|---|---|---|---|---|---|---|")
    for name, s in rows:
        print(
            f"| {name} | {s['rmse_mV']:.2f} mV | {s['model_mV']:.2f} mV "
            f"| {s['max_err_mV']:.1f} mV | {s['r0_pct']:.1f} % "
            f"| {s['rsum_pct']:.1f} % | {s['rsum_med_pct']:.1f} % | {s['tau1_pct']:.1f} % |"
        )


if __name__ == "__main__":
    main()
