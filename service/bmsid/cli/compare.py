"""``bmsid compare DATASETS... --out DIR``: the paper's comparison on your data.

Runs the three variants (non-hy-affrls, hy-affrls, hy-affrls-lpso) on every dataset (tester
CSVs or candump logs, read as ``bmsid identify`` reads them, ``--columns`` and ``--mapping``
included) and writes:

- ``table2.md`` / ``table2.csv``: per dataset (profile and temperature, read from names such as
  ``..._dst_25C...``) and variant, the RMSE over the whole record, over its first 10 % of the
  ticks (start-up) and over the rest, beside the paper's Table 2 columns (max error, RMSE, MAPE
  over the evaluation window; run time);
- ``soc_bands.md`` / ``soc_bands.csv``: RMSE, max error and MAPE per 10 % SOC band of every
  dataset and variant;
- ``consistency.md`` / ``consistency.csv`` and ``consistency_<group>.png``: the parameters'
  agreement across the profiles of one cell at one temperature (group ``config NAME, data T C``;
  Fig. 14, method in ``bmsid.offline.report``);
- ``rmse.png`` and, per dataset and variant, ``<dataset>/<variant>/`` with ``metrics.json`` and
  the Fig. 10/11 plots (``--params-csv`` also writes each ``params.csv``).

Every dataset first gets identify's record checks for its cell config (time unit, current
sign, capacity, ...): their notes and warnings are printed, an error refuses the run (exit 2)
before any identification. A directory or a file given twice is refused too.

Cell configs: one ``--cell-config`` for every dataset, or one per dataset in the same order.
For several cells per file, Table 2 pools all cells and the consistency analysis uses the first.

Evaluation window: every tick by default; ``--skip-fraction`` leaves out a share of the first
ticks, ``--soc-window`` keeps the ticks whose SOC lies in a range. That SOC (and the SOC bands')
is the estimator's, or with ``--score-soc0`` a coulomb count of the measured current from a known
start: ``--score-soc0 1.0 --soc-window 0.15,0.95`` scores SOC 95..15 % counted from a full cell.
"""

from __future__ import annotations

import argparse
import json
import math
import re
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from bmsid.cli.outputs import output_dir
from bmsid.config.cell import CellConfig
from bmsid.errors import UserError
from bmsid.estimate.tuning import Variant
from bmsid.estimate.types import VARIANTS
from bmsid.offline.identify import IdentifySpec, identify_source
from bmsid.offline.inputs import (
    LoadedInput,
    load_config,
    parse_columns,
    parse_tuning,
    parse_window,
    tuning_overrides,
)
from bmsid.offline.outputs import SCORE_SOC0_HELP, OutputSpec, ocv_range_warning, soc_init_text
from bmsid.offline.plots import plot_consistency, plot_rmse_bars
from bmsid.offline.report import (
    Consistency,
    DatasetLabel,
    HeldShare,
    SocBandRow,
    Table2Row,
    consistency,
    consistency_csv,
    consistency_markdown,
    label_dataset,
    soc_band_rows,
    soc_bands_csv,
    soc_bands_markdown,
    table2_csv,
    table2_markdown,
    unique_displays,
)
from bmsid.offline.scoring import (
    EvalWindow,
    IdentifyResult,
    SocReference,
    metrics_document,
    parameter_medians,
    parameter_trajectories,
)

from .compare_inputs import check_paths, load_dataset
from .identify import add_input_options, add_model_options, progress_bar


def register(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = subparsers.add_parser(
        "compare",
        help="run the three variants on datasets; write Table 2 and the consistency analysis",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument(
        "datasets", nargs="+", metavar="DATASET",
        help="tester CSVs (.csv/.csv.gz) or candump logs (.log/.log.gz), as identify reads them",
    )  # fmt: skip
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
    p.add_argument(
        "--score-soc0",
        action="append",
        default=[],
        type=float,
        metavar="FRACTION",
        help=SCORE_SOC0_HELP + "; once for all datasets, or once per dataset",
    )
    p.add_argument("--params-csv", action="store_true", help="also write each run's params.csv")
    add_input_options(p)
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


def _soc0s(values: list[float], n: int, option: str = "--soc0") -> list[float | None]:
    if not values:
        return [None] * n
    if len(values) not in (1, n):
        raise UserError(f"{len(values)} {option} for {n} datasets: give 1 or {n}")
    for z in values:
        if not (math.isfinite(z) and 0.0 <= z <= 1.0):
            raise UserError(f"{option} is a fraction in [0, 1], got {z:g}")
    return list(values * n if len(values) == 1 else values)


def _window(
    base: EvalWindow, cell: CellConfig, score_soc0: float | None, gap_s: float
) -> EvalWindow:
    """``base`` with the dataset's reference SOC, when ``--score-soc0`` gives one."""
    if score_soc0 is None:
        return base
    return replace(base, soc_reference=SocReference.from_cell(cell, score_soc0, gap_s))


def _distinct(texts: list[str]) -> str:
    """One text when every dataset shares it, else each distinct one."""
    unique = list(dict.fromkeys(texts))
    return unique[0] if len(unique) == 1 else "per dataset: " + " | ".join(unique)


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
    """One consistency group: the cell config and the data's temperature, each named as such
    (``dfn-nmc-lgm50-25C_15C`` read as a contradiction: a 25 C config's name, 15 C data)."""
    if label.temperature_C is None:
        return f"config {cell.name}"
    return f"config {cell.name}, data {label.temperature_C:g} C"


def _file_stem(group: str) -> str:
    """A group name as a file name part: ``config_x-25C_data_15_C``."""
    return re.sub(r"[^A-Za-z0-9.-]+", "_", group).strip("_")


def run(args: argparse.Namespace) -> int:
    tuning = parse_tuning(args.tuning)
    # The default window is the whole record: the start-up is part of what a user gets.
    skip = 0.0 if args.skip_fraction is None else args.skip_fraction
    window = parse_window(args.soc_window, skip)
    variants = _variants(args.algorithms)
    configs = _configs(args.cell_config, len(args.datasets))
    soc0s = _soc0s(args.soc0, len(args.datasets))
    score_soc0s = _soc0s(args.score_soc0, len(args.datasets), "--score-soc0")
    columns = parse_columns(args.columns)
    check_paths(args.datasets)
    out = output_dir(Path(args.out))  # before hours of identification, not after
    # Read and check everything first: a bad file fails before hours of identification.
    data: list[LoadedInput] = [
        load_dataset(p, args, columns, cell, z, tuning)
        for p, (cell, _), z in zip(args.datasets, configs, soc0s, strict=True)
    ]
    labels = [
        label_dataset(p, float(np.median(d.temperature_C)) if d.temperature_C is not None else None)
        for p, d in zip(args.datasets, data, strict=True)
    ]
    displays = unique_displays(labels)

    rows: list[Table2Row] = []
    band_rows: list[SocBandRow] = []
    windows = [
        _window(window, cell, z, tuning.gap_s)
        for (cell, _), z in zip(configs, score_soc0s, strict=True)
    ]
    medians: dict[str, dict[str, dict[str, dict[str, float]]]] = {}
    trajectories: dict[str, dict[str, dict[str, dict[str, list[float]]]]] = {}
    helds: dict[str, dict[str, dict[str, HeldShare]]] = {}
    runs: list[dict[str, Any]] = []
    for d, lb, shown, (cell, cfg_path), soc0, win in zip(
        data, labels, displays, configs, soc0s, windows, strict=True
    ):
        for variant in variants:
            spec = IdentifySpec(
                cell=cell,
                variant=variant,
                tuning=tuning,
                soc0=soc0,
                window=win,
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
            doc = metrics_document(res, win)
            rows.append(
                Table2Row(
                    dataset=shown,
                    profile=lb.profile,
                    temperature_C=lb.temperature_C,
                    algorithm=variant,
                    n_samples=int(doc["n_samples"]),
                    max_abs_error_V=_err(doc["max_abs_error_V"]),
                    rmse_V=_err(doc["rmse_V"]),
                    mape_pct=_err(doc["mape_pct"]),
                    runtime_s=res.runtime_s,
                    rmse_whole_V=_err(doc["overall"]["rmse_V"]),
                    rmse_startup_V=_err(doc["startup"]["rmse_V"]),
                    rmse_after_startup_V=_err(doc["after_startup"]["rmse_V"]),
                )
            )
            band_rows += soc_band_rows(
                shown, lb.profile, lb.temperature_C, variant, doc["soc_bands"]
            )
            med = parameter_medians(res.kept_trace(), win)
            group = _group_name(lb, cell)
            # Consistency looks at the first cell (a pack's cells differ by design).
            medians.setdefault(group, {}).setdefault(variant, {})[shown] = {
                k: float(v[0]) for k, v in med.items()
            }
            z0 = float(res.kept_trace()["soc"][0, 0]) if res.n_ticks else math.nan
            traj = parameter_trajectories(res.kept_trace(), win, 0)
            trajectories.setdefault(group, {}).setdefault(variant, {})[shown] = {
                k: v.tolist() for k, v in traj.items()
            }
            held = HeldShare.of_cell(doc["cells"][res.cell_names[0]])
            helds.setdefault(group, {}).setdefault(variant, {})[shown] = held
            runs.append(
                {"dataset": shown, "algorithm": variant, "soc_init": res.soc_init_method,
                 "soc0": z0, "scoring_soc": doc["scoring_soc"]}
            )  # fmt: skip
            if variant == variants[0]:
                warning = ocv_range_warning(res, cell)
                if res.soc_init_method.startswith("default") or warning:
                    print(f"{shown}: {soc_init_text(res)}", flush=True)
                if warning:
                    print(f"{shown}: {warning}", flush=True)
            r = rows[-1]
            in_window = "" if win.is_whole_record else f"  window {1e3 * r.rmse_V:7.2f} mV"
            print(
                f"{shown:<16} {variant:<15} RMSE whole {1e3 * r.rmse_whole_V:7.2f} mV  "
                f"first 10 % {1e3 * r.rmse_startup_V:7.2f} mV{in_window}  "
                f"max {1e3 * r.max_abs_error_V:7.1f} mV  {res.runtime_s:6.1f} s",
                flush=True,
            )
            if held.flagged:
                print(f"{shown}: {variant}: {_held_text(held)}", flush=True)

    window_text = _distinct([w.describe() for w in windows])
    soc_text = _distinct(
        [
            "the estimator's (a coulomb count from its initial SOC)"
            if w.soc_reference is None
            else w.soc_reference.describe()
            for w in windows
        ]
    )
    (out / "table2.md").write_text(table2_markdown(rows, window_text), encoding="utf-8")
    (out / "table2.csv").write_text(table2_csv(rows), encoding="utf-8")
    bands_md = soc_bands_markdown(band_rows, soc_text)
    (out / "soc_bands.md").write_text(bands_md, encoding="utf-8")
    (out / "soc_bands.csv").write_text(soc_bands_csv(band_rows), encoding="utf-8")
    plot_rmse_bars([{"dataset": r.dataset, "algorithm": r.algorithm, "rmse_mV": r.rmse_mV}
                    for r in rows], out / "rmse.png")  # fmt: skip

    cons: list[Consistency] = []
    for group, by_variant in medians.items():
        if len(next(iter(by_variant.values()))) < 2:
            continue  # one profile only: nothing to be consistent with
        group_results = [
            consistency(group, v, m, trajectories[group][v], helds[group][v])
            for v, m in by_variant.items()
        ]
        cons += group_results
        plot_consistency(
            {c.algorithm: c.normalised for c in group_results},
            {c.algorithm: c.error_pct for c in group_results},
            out / f"consistency_{_file_stem(group)}.png",
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
    print(table2_markdown(rows, window_text))
    print(bands_md)
    print(consistency_markdown(cons))
    print(
        f"wrote {out}/table2.md, table2.csv, soc_bands.md, soc_bands.csv, consistency.md, "
        "consistency.csv and plots"
    )
    return 0


def _err(x: float | None) -> float:
    """An error figure of metrics_document for Table 2: null (no scored tick) as the 0 of
    ``VoltageMetrics`` with ``n_samples`` 0, which the table shows beside it."""
    return 0.0 if x is None else float(x)


def _held_text(h: HeldShare) -> str:
    return f"{h.text()}: its consistency row shows where the estimate stopped"
