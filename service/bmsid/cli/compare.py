"""``bmsid compare DATASETS... --out DIR``: the paper's comparison on your data.

Runs the three variants (non-hy-affrls, hy-affrls, hy-affrls-lpso) on every dataset (tester
CSVs) and writes:

- ``table2.md`` / ``table2.csv``: max error, RMSE, MAPE and run time per dataset (profile and
  temperature, read from names such as ``..._dst_25C...``) and variant (the paper's Table 2);
- ``consistency.md`` / ``consistency.csv`` and ``consistency_<group>.png``: the parameters'
  agreement across the profiles of one cell at one temperature (Fig. 14, method in
  ``bmsid.offline.report``);
- ``rmse.png`` and, per dataset and variant, ``<dataset>/<variant>/`` with ``metrics.json`` and
  the Fig. 10/11 plots (``--params-csv`` also writes each ``params.csv``).

Cell configs: one ``--cell-config`` for every dataset, or one per dataset in the same order.
For several cells per file, Table 2 pools all cells and the consistency analysis uses the first.
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path
from typing import Any

import numpy as np

from bmsid.config.cell import CellConfig
from bmsid.errors import UserError
from bmsid.estimate.tuning import Variant
from bmsid.estimate.types import VARIANTS
from bmsid.offline.identify import IdentifySpec, identify_source
from bmsid.offline.inputs import (
    LoadedInput,
    check_soc0,
    load_config,
    parse_tuning,
    parse_window,
    read_csv_input,
    tuning_overrides,
)
from bmsid.offline.outputs import OutputSpec, ocv_range_warning, soc_init_text
from bmsid.offline.plots import plot_consistency, plot_rmse_bars
from bmsid.offline.report import (
    Consistency,
    DatasetLabel,
    Table2Row,
    consistency,
    consistency_csv,
    consistency_markdown,
    label_dataset,
    table2_csv,
    table2_markdown,
    unique_displays,
)
from bmsid.offline.scoring import (
    IdentifyResult,
    metrics_document,
    parameter_medians,
    parameter_trajectories,
)

from .identify import add_model_options, progress_bar


def register(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = subparsers.add_parser(
        "compare",
        help="run the three variants on datasets; write Table 2 and the consistency analysis",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("datasets", nargs="+", metavar="DATASET", help="tester CSV files")
    p.add_argument("--out", required=True, metavar="DIR", help="output directory")
    p.add_argument(
        "--cell-config",
        action="append",
        default=[],
        metavar="FILE",
        help="cell config: once for all datasets, or once per dataset in order",
    )
    p.add_argument(
        "--soc0",
        action="append",
        default=[],
        type=float,
        metavar="Z",
        help="initial SOC (fraction): once for all datasets, or once per dataset; default: "
        "the cell config's soc_init (OCV at rest)",
    )
    p.add_argument(
        "--algorithms",
        default=",".join(VARIANTS),
        help=f"comma-separated subset of {', '.join(VARIANTS)}",
    )
    p.add_argument("--params-csv", action="store_true", help="also write each run's params.csv")
    add_model_options(p)
    p.set_defaults(func=run)


def _configs(paths: list[str], n: int) -> list[tuple[CellConfig, str]]:
    if not paths:
        raise UserError("give --cell-config (once, or once per dataset)")
    if len(paths) not in (1, n):
        raise UserError(f"{len(paths)} --cell-config for {n} datasets: give 1 or {n}")
    loaded = {p: load_config(p) for p in dict.fromkeys(paths)}
    chosen = paths * n if len(paths) == 1 else paths
    return [(loaded[p], p) for p in chosen]


def _soc0s(values: list[float], n: int) -> list[float | None]:
    if not values:
        return [None] * n
    if len(values) not in (1, n):
        raise UserError(f"{len(values)} --soc0 for {n} datasets: give 1 or {n}")
    for z in values:
        check_soc0(z)
    return list(values * n if len(values) == 1 else values)


def _variants(text: str) -> list[Variant]:
    out: list[Variant] = []
    for name in (x.strip() for x in text.split(",") if x.strip()):
        if name not in VARIANTS:
            raise UserError(f"--algorithms: unknown {name!r}; choose from {', '.join(VARIANTS)}")
        out.append(name)  # narrowed to a Variant by the check above
    if not out:
        raise UserError("--algorithms is empty")
    return out


def _group_name(label: DatasetLabel, cell: CellConfig) -> str:
    """Cell name plus temperature (unless the name already says it): one consistency group."""
    if label.temperature_C is None or f"{label.temperature_C:g}C" in cell.name:
        return cell.name
    return f"{cell.name}_{label.temperature_C:g}C"


def run(args: argparse.Namespace) -> int:
    tuning = parse_tuning(args.tuning)
    window = parse_window(args.soc_window, args.skip_fraction)
    variants = _variants(args.algorithms)
    configs = _configs(args.cell_config, len(args.datasets))
    soc0s = _soc0s(args.soc0, len(args.datasets))
    out = Path(args.out)
    if out.exists() and not out.is_dir():
        raise UserError(f"--out {out} exists and is not a directory")
    # Read everything first: a bad file fails before hours of identification.
    data: list[LoadedInput] = [
        read_csv_input(p, charge_positive=args.charge_positive) for p in args.datasets
    ]
    labels = [
        label_dataset(p, float(np.median(d.temperature_C)) if d.temperature_C is not None else None)
        for p, d in zip(args.datasets, data, strict=True)
    ]
    displays = unique_displays(labels)
    out.mkdir(parents=True, exist_ok=True)

    rows: list[Table2Row] = []
    medians: dict[str, dict[str, dict[str, dict[str, float]]]] = {}
    trajectories: dict[str, dict[str, dict[str, dict[str, list[float]]]]] = {}
    runs: list[dict[str, Any]] = []
    for d, lb, shown, (cell, cfg_path), soc0 in zip(
        data, labels, displays, configs, soc0s, strict=True
    ):
        for variant in variants:
            spec = IdentifySpec(
                cell=cell,
                variant=variant,
                tuning=tuning,
                soc0=soc0,
                window=window,
                charge_positive=args.charge_positive,
                output=OutputSpec(
                    params_csv=args.params_csv,
                    plots="first",  # Table 2 pools the cells; the figures show the first
                    title=f"{shown} - {variant}",
                    metadata={"input": d.source, "cell_config": cfg_path},
                ),
            )
            with progress_bar(d.n_samples, f"{shown} {variant}") as bar:
                res: IdentifyResult = identify_source(d, spec, out / lb.stem / variant, bar)
            doc = metrics_document(res, window)
            rows.append(
                Table2Row(
                    dataset=shown,
                    profile=lb.profile,
                    temperature_C=lb.temperature_C,
                    algorithm=variant,
                    n_samples=int(doc["n_samples"]),
                    max_abs_error_V=float(doc["max_abs_error_V"]),
                    rmse_V=float(doc["rmse_V"]),
                    mape_pct=float(doc["mape_pct"]),
                    runtime_s=res.runtime_s,
                )
            )
            med = parameter_medians(res.trace, window)
            group = _group_name(lb, cell)
            # Consistency looks at the first cell (a pack's cells differ by design).
            medians.setdefault(group, {}).setdefault(variant, {})[shown] = {
                k: float(v[0]) for k, v in med.items()
            }
            z0 = float(res.trace["soc"][0, 0]) if res.trace.n_ticks else math.nan
            traj = parameter_trajectories(res.trace, window, 0)
            trajectories.setdefault(group, {}).setdefault(variant, {})[shown] = {
                k: v.tolist() for k, v in traj.items()
            }
            runs.append(
                {"dataset": shown, "algorithm": variant, "soc_init": res.soc_init_method,
                 "soc0": z0}
            )  # fmt: skip
            if variant == variants[0]:
                warning = ocv_range_warning(res, cell)
                if res.soc_init_method.startswith("default") or warning:
                    print(f"{shown}: {soc_init_text(res)}", flush=True)
                if warning:
                    print(f"{shown}: {warning}", flush=True)
            print(
                f"{shown:<16} {variant:<15} RMSE {1e3 * doc['rmse_V']:7.2f} mV  "
                f"max {1e3 * doc['max_abs_error_V']:7.1f} mV  MAPE {doc['mape_pct']:.3f} %  "
                f"{res.runtime_s:6.1f} s",
                flush=True,
            )

    (out / "table2.md").write_text(table2_markdown(rows, window.describe()), encoding="utf-8")
    (out / "table2.csv").write_text(table2_csv(rows), encoding="utf-8")
    plot_rmse_bars([{"dataset": r.dataset, "algorithm": r.algorithm, "rmse_mV": r.rmse_mV}
                    for r in rows], out / "rmse.png")  # fmt: skip

    cons: list[Consistency] = []
    for group, by_variant in medians.items():
        if len(next(iter(by_variant.values()))) < 2:
            continue  # one profile only: nothing to be consistent with
        group_results = [
            consistency(group, v, m, trajectories[group][v]) for v, m in by_variant.items()
        ]
        cons += group_results
        plot_consistency(
            {c.algorithm: c.normalised for c in group_results},
            {c.algorithm: c.error_pct for c in group_results},
            out / f"consistency_{group}.png",
            f"parameter consistency - {group}",
        )
    (out / "consistency.md").write_text(consistency_markdown(cons), encoding="utf-8")
    (out / "consistency.csv").write_text(consistency_csv(cons), encoding="utf-8")
    summary = {
        "evaluation_window": window.as_dict(),
        "tuning_overrides": tuning_overrides(args.tuning),
        "runs": runs,
    }
    (out / "compare.json").write_text(json.dumps(summary, indent=2) + "\n", encoding="utf-8")
    print(table2_markdown(rows, window.describe()))
    print(consistency_markdown(cons))
    print(f"wrote {out}/table2.md, table2.csv, consistency.md, consistency.csv and plots")
    return 0
