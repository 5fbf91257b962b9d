"""Engine benchmarks (issue: identification engine). Prints a Markdown table.

    python bench/bench_engine.py            # full (about a minute on one core)
    python bench/bench_engine.py --quick    # smaller runs, for a smoke check

Measures: single-cell ``hy-affrls`` samples/s; ``hy-affrls-lpso`` wall time over the 8250-sample
DST run (the paper: ~20 s in MATLAB); a 96-cell bank's cell-samples/s without the swarm; the
worst and the 99.9th-percentile single ``update`` call of a 96-cell bank with the swarm active;
and what the SOC observer costs (issue 11: at most 30 % of the bank's throughput): the same runs
with ``observer.enabled`` off, alternated with on in this one process, best of two each.
Throughputs feed the run as one ``SampleBlock`` (``update_block``, as the daemon and offline
identification do); the per-call figures come from a second, sample-by-sample run. Every
benchmark runs twice: every kernel compiled (``estimate/jit.py``: the window fits and the swarm
fitness, the state and observer steps, the RLS ticks, the guard and the average, the tick's
tail of codes, guard and average in one call, and ``update_block``'s tick assembly and loop over
ordinary ticks: ``estimate/block_run.py``) and every kernel on its numpy reference, alternated
in one process.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from bmsid.config.engine import build_bank
from bmsid.estimate import jit
from bmsid.estimate.observer_tuning import ObserverTuning
from bmsid.estimate.tuning import EstimatorTuning, Variant
from bmsid.samples import SampleBlock
from bmsid.synthetic import SyntheticRun, paper_dst_case
from bmsid.threads import one_blas_thread

one_blas_thread()  # the engine's matrices are small (bmsid/threads.py)


def _block(run: SyntheticRun) -> SampleBlock:
    return SampleBlock.from_arrays(run.t_s, run.current_A, run.voltages_V)


def _run_block(run: SyntheticRun, variant: Variant, tuning: EstimatorTuning | None = None) -> float:
    """Wall time, s, of the whole run fed as one block (the daemon's and offline path)."""
    bank = build_bank(run.cell, run.voltages_V.shape[1], variant, tuning, soc0=0.98)
    block = _block(run)
    t0 = time.perf_counter()
    bank.update_block(block)
    return time.perf_counter() - t0


def _update_calls(run: SyntheticRun, variant: Variant) -> np.ndarray:
    """Wall time, s, of each single-sample ``update`` call (what the worst stall is made of)."""
    bank = build_bank(run.cell, run.voltages_V.shape[1], variant, soc0=0.98)
    calls = np.zeros(run.t_s.shape[0])
    t, i, v = run.t_s.tolist(), run.current_A.tolist(), run.voltages_V
    for k in range(len(t)):
        c0 = time.perf_counter()
        bank.update(t[k], i[k], v[k])
        calls[k] = time.perf_counter() - c0
    return calls


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--quick", action="store_true")
    args = ap.parse_args()
    n_single = 2000 if args.quick else 8250
    n_bank = 700 if args.quick else 2400
    single = paper_dst_case(n_single)
    spread = np.random.default_rng(0).uniform(0.8, 1.3, 96)
    pack = paper_dst_case(n_bank, r0_spread=spread)
    # Every kernel (jit.py) compiled and the numpy reference, alternated in this one process.
    res: dict[str, list[str]] = {}
    for kernel in ("numpy", "compiled"):
        jit.select(kernel)
        dt = _run_block(single, "hy-affrls")
        out = [f"{n_single / dt:,.0f} samples/s"]
        dt = _run_block(pack, "hy-affrls")
        out.append(f"{96 * n_bank / dt:,.0f} cell-samples/s")
        dt = _run_block(single, "hy-affrls-lpso")
        out.append(f"{dt:.2f} s")
        dt = _run_block(pack, "hy-affrls-lpso")
        out.append(f"{96 * n_bank / dt:,.0f} cell-samples/s")
        # A second run, sample by sample: the same computation, timed per call.
        calls = _update_calls(pack, "hy-affrls-lpso")
        out += [f"{calls.max() * 1e3:.1f} ms", f"{np.quantile(calls, 0.999) * 1e3:.1f} ms"]
        res[kernel] = out
    names = (
        "single cell `hy-affrls`",
        "96-cell bank `hy-affrls` (no swarm)",
        f"single cell `hy-affrls-lpso`, {n_single}-sample DST",
        "96-cell bank `hy-affrls-lpso`",
        "  worst single `update` call (swarms active)",
        "  99.9th percentile `update` call",
    )
    print("| benchmark | compiled kernels | numpy reference |\n|---|---|---|")
    for name, compiled, ref in zip(names, res["compiled"], res["numpy"], strict=True):
        print(f"| {name} | {compiled} | {ref} |")
    print()
    _observer_cost(single, pack, n_single, n_bank)


def _observer_cost(single: SyntheticRun, pack: SyntheticRun, n_single: int, n_bank: int) -> None:
    """The observer's share of the throughput: on and off alternated, best of two each."""
    off = EstimatorTuning(observer=ObserverTuning(enabled=False))
    print("| benchmark | observer on | observer off | observer's cost |\n|---|---|---|---|")
    cases: tuple[tuple[str, SyntheticRun, Variant, int], ...] = (
        ("single cell `hy-affrls`", single, "hy-affrls", n_single),
        ("single cell `hy-affrls-lpso`", single, "hy-affrls-lpso", n_single),
        ("96-cell bank `hy-affrls-lpso`", pack, "hy-affrls-lpso", 96 * n_bank),
    )
    for name, run, variant, n in cases:
        best = {True: np.inf, False: np.inf}
        for _ in range(2):
            for on in (True, False):
                best[on] = min(best[on], _run_block(run, variant, None if on else off))
        rate_on, rate_off = n / best[True], n / best[False]
        print(f"| {name} | {rate_on:,.0f} /s | {rate_off:,.0f} /s | "
              f"{100 * (1 - rate_on / rate_off):.0f} % |")  # fmt: skip


if __name__ == "__main__":
    main()
