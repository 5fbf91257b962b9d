"""Compare ``EstimatorBank.update_block`` of two source trees, array by array (issue 12).

    PYTHONPATH=/tmp/old/service python scripts/compare_engine_outputs.py dump /tmp/out-old
    PYTHONPATH=service python scripts/compare_engine_outputs.py dump /tmp/out-new
    python scripts/compare_engine_outputs.py compare /tmp/out-old /tmp/out-new

``dump`` runs every case (variant x cells x input events, compiled kernels) and saves, per
case, every published array, the quality codes, the counters and the flattened ``state_dict``
(``.npz``); ``compare`` reports the number of arrays compared and the largest difference
(relative to each array's scale), and fails on any mismatch beyond 1e-12 relative.
"""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Any

import numpy as np

CASES: dict[str, dict[str, Any]] = {}


def _events(n_samples: int, n_cells: int, seed: int, kind: str) -> tuple[Any, ...]:
    from bmsid.synthetic import paper_dst_case  # noqa: PLC0415

    spread = np.random.default_rng(seed).uniform(0.8, 1.3, n_cells) if n_cells > 1 else None
    run = paper_dst_case(n_samples, r0_spread=spread, seed=seed)
    t, i, v = run.t_s.copy(), run.current_A.copy(), run.voltages_V.copy()
    temp = None
    rng = np.random.default_rng(seed + 100)
    if kind in ("events", "events_half"):
        m = t.shape[0]
        v[rng.random(v.shape) < 0.01] = np.nan  # scattered NaN voltages
        v[m // 3 : m // 3 + 5, 0] = np.nan  # a cell without data for a few samples
        i[rng.random(m) < 0.003] = np.nan  # NaN currents
        t[m // 4 :] += 45.0  # a gap (longer than gap_s)
        t[m // 2 :] += 1000.0  # downtime: an observer restart
        rep = rng.choice(m - 1, 10, replace=False)
        t[rep + 1] = t[rep]  # repeated samples
        t[(2 * m) // 3 :] -= 200.0  # a time jump back
        t[rng.choice(m, 3, replace=False)] = np.nan  # non-finite times
        temp = 25.0 + 10.0 * np.sin(np.arange(m) / 500.0)
        temp[rng.random(m) < 0.05] = np.nan
    if kind == "events_half":
        t = t * 0.5  # 0.5 s sampling: two samples a tick
    if kind == "rest_start":  # start from OCV at rest (the start relaxation watch opens)
        i[:400] = 0.0
    return run.cell, t, i, v, temp


def _cases() -> list[tuple[str, str, int, str, bool]]:
    out = []
    for variant in ("non-hy-affrls", "hy-affrls", "hy-affrls-lpso"):
        for n_cells in (1, 8):
            for kind in ("plain", "events", "events_half", "rest_start"):
                out.append((variant, f"{variant}-{n_cells}-{kind}", n_cells, kind, True))
    out.append(("hy-affrls", "hy-affrls-8-events-noobs", 8, "events", False))
    out.append(("hy-affrls", "hy-affrls-1-plain-noobs", 1, "plain", False))
    for variant in ("hy-affrls", "hy-affrls-lpso"):  # the other branches (OTHER)
        out.append((variant, f"{variant}-8-events-other", 8, "events", True))
        out.append((variant, f"{variant}-1-plain-other", 1, "plain", True))
    return out


def _flatten(prefix: str, x: Any, out: dict[str, np.ndarray]) -> None:
    if isinstance(x, dict):
        for k, v in x.items():
            _flatten(f"{prefix}/{k}", v, out)
    elif isinstance(x, str):
        out[prefix] = np.array(x)
    elif x is None:
        out[prefix] = np.array("None")
    else:
        out[prefix] = np.asarray(x)


def dump(dest: Path) -> None:
    from bmsid.config.engine import build_bank  # noqa: PLC0415
    from bmsid.estimate import jit  # noqa: PLC0415
    from bmsid.estimate.observer_tuning import ObserverTuning  # noqa: PLC0415
    from bmsid.estimate.tuning import EstimatorTuning  # noqa: PLC0415
    from bmsid.samples import SampleBlock  # noqa: PLC0415

    jit.select("compiled")
    dest.mkdir(parents=True, exist_ok=True)
    for variant, name, n_cells, kind, observer in _cases():
        cell, t, i, v, temp = _events(3000 if n_cells > 1 else 5000, n_cells, 3, kind)
        tuning = None if observer else EstimatorTuning(observer=ObserverTuning(enabled=False))
        if name.endswith("-other"):  # no average, OCV offset, no knees, M not learnt
            tuning = EstimatorTuning(
                publish_average_tau1=0.0, identify_ocv_offset=True, knee_slope_factor=1e9,
                identify_hysteresis_scale=True, observer=ObserverTuning(learn_hysteresis=False),
            )  # fmt: skip
        soc0 = None if kind == "rest_start" else 0.98
        bank = build_bank(cell, n_cells, variant, tuning, soc0=soc0)  # type: ignore[arg-type]
        res: dict[str, np.ndarray] = {}
        # three blocks of uneven length: the bins and histories carry across block ends
        cuts = [0, 777, 2001, t.shape[0]]
        for b in range(3):
            s = slice(cuts[b], cuts[b + 1])
            blk = SampleBlock.from_arrays(
                t[s], i[s], v[s], temperature_C=None if temp is None else temp[s]
            )
            est = bank.update_block(blk)
            res[f"b{b}/t_s"] = est.t_s
            res[f"b{b}/current_A"] = est.current_A
            res[f"b{b}/quality"] = est.quality
            for k, a in est.cells.items():
                res[f"b{b}/cells/{k}"] = a
        _flatten("counters", bank.counters, res)
        _flatten("state", bank.state_dict(), res)
        np.savez(dest / f"{name}.npz", **res)  # type: ignore[arg-type]
        print(name, len(res), "arrays")


def compare(a_dir: Path, b_dir: Path) -> int:
    n_arrays, worst, worst_at, bad = 0, 0.0, "", []
    for fa in sorted(a_dir.glob("*.npz")):
        fb = b_dir / fa.name
        a, b = np.load(fa, allow_pickle=False), np.load(fb, allow_pickle=False)
        if set(a.files) != set(b.files):
            bad.append(f"{fa.stem}: keys differ {set(a.files) ^ set(b.files)}")
        for k in sorted(set(a.files) & set(b.files)):
            x, y = a[k], b[k]
            n_arrays += 1
            if x.shape != y.shape or x.dtype.kind != y.dtype.kind:
                bad.append(f"{fa.stem}:{k}: {x.shape}/{x.dtype} vs {y.shape}/{y.dtype}")
                continue
            if x.dtype.kind in "US":
                if not np.array_equal(x, y):
                    bad.append(f"{fa.stem}:{k}: {x} vs {y}")
                continue
            xf, yf = x.astype(np.float64), y.astype(np.float64)
            if not np.array_equal(np.isnan(xf), np.isnan(yf)):
                bad.append(f"{fa.stem}:{k}: NaN pattern differs")
                continue
            fin = np.isfinite(xf)
            if not np.array_equal(xf[np.isinf(xf)], yf[np.isinf(xf)]):
                bad.append(f"{fa.stem}:{k}: infinities differ")
            if not fin.any():
                continue
            scale = max(float(np.max(np.abs(xf[fin]))), 1e-300)
            d = float(np.max(np.abs(xf[fin] - yf[fin]))) / scale
            if d > worst:
                worst, worst_at = d, f"{fa.stem}:{k}"
            if d > 1e-12:
                bad.append(f"{fa.stem}:{k}: relative difference {d:.3g}")
    print(f"{n_arrays} arrays compared; largest relative difference {worst:.3g} ({worst_at})")
    for line in bad[:40]:
        print("MISMATCH", line)
    return 1 if bad else 0


if __name__ == "__main__":
    if sys.argv[1] == "dump":
        dump(Path(sys.argv[2]))
    else:
        sys.exit(compare(Path(sys.argv[2]), Path(sys.argv[3])))
