"""``bmsid identify`` with several inputs, a directory or a glob: one subdirectory of ``--out``
per input, ``summary.csv`` at its root, a progress bar over the inputs; on a local process
pool (``--workers``) or a Dask cluster (``--scheduler``). The work is ``bmsid.offline.fleet``'s;
this module turns the options into one spec and prints what comes back."""

from __future__ import annotations

import argparse
import math
import sys
from collections.abc import Sequence
from dataclasses import replace
from pathlib import Path

from tqdm import tqdm

from bmsid.canbus.logs import is_candump_path
from bmsid.cli.outputs import output_dir
from bmsid.errors import UserError
from bmsid.offline import fleet
from bmsid.offline.identify import IdentifySpec
from bmsid.offline.inputs import (
    cell_config,
    check_soc0,
    parse_columns,
    parse_tuning,
    parse_window,
    tuning_overrides,
    with_score_reference,
)
from bmsid.offline.outputs import OutputSpec
from bmsid.offline.record_checks import CheckOptions

DEFAULT_WORST = 5


def add_fleet_options(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--workers", type=int, default=None, metavar="N",
        help="several inputs: local worker processes (default: min(inputs, CPUs))",
    )  # fmt: skip
    p.add_argument(
        "--scheduler", default=None, metavar="tcp://HOST:PORT",
        help="several inputs: run one task per input on this Dask scheduler's workers (inputs "
        "and --out at the same paths on every worker; needs bmsid[fleet])",
    )  # fmt: skip
    p.add_argument(
        "--worst", type=int, default=DEFAULT_WORST, metavar="N",
        help=f"several inputs: the fleet's N cells of largest R0 ranked in summary.csv "
        f"(default {DEFAULT_WORST})",
    )  # fmt: skip


def fleet_spec(args: argparse.Namespace, ocv_coeffs: Sequence[float] | None) -> IdentifySpec:
    """The spec every input runs with, from the options as a single run reads them. Paths a
    worker opens (``--mapping``) are made absolute: workers may run elsewhere."""
    tuning = parse_tuning(args.tuning)
    window = parse_window(args.soc_window, args.skip_fraction)
    check_soc0(args.soc0)
    cell, note = cell_config(args.cell_config, args.capacity_ah, ocv_coeffs)
    window = with_score_reference(window, cell, args.score_soc0, tuning.gap_s)
    meta = {"cell_config": note, "tuning_overrides": tuning_overrides(args.tuning)}
    return IdentifySpec(
        cell=cell, variant=args.algorithm, tuning=tuning, soc0=args.soc0, window=window,
        charge_positive=args.charge_positive,
        mapping=str(Path(args.mapping).resolve()) if args.mapping else None,
        n_cells=args.n_cells, channel=args.channel, columns=parse_columns(args.columns),
        output=OutputSpec(
            metadata=meta, params_format=args.format, every_s=args.every,
            every_mode=args.every_mode,
        ),
    )  # fmt: skip


def check_options(args: argparse.Namespace, ocv_coeffs: Sequence[float] | None) -> CheckOptions:
    """What the record checks need of the options (``offline/record_checks.py``)."""
    columns = parse_columns(args.columns) or {}
    return CheckOptions(
        cell_config_given=args.cell_config is not None,
        capacity_given=args.capacity_ah is not None, soc0=args.soc0,
        charge_positive=args.charge_positive,
        ocv_coeffs=None if ocv_coeffs is None else tuple(float(c) for c in ocv_coeffs),
        t_source=columns["t_s"].source if "t_s" in columns else "t_s",
        t_scale=columns["t_s"].scale if "t_s" in columns else 1.0,
    )  # fmt: skip


def spec_for(spec: IdentifySpec, path: str) -> IdentifySpec:
    """The log options for logs, the CSV options for CSVs: a mixed fleet takes both."""
    if is_candump_path(path):
        return replace(spec, columns=None)
    return replace(spec, mapping=None, channel=None)


def _ok_line(s: fleet.InputSummary) -> str:
    ranked = [c for c in s.cells if math.isfinite(c.r0_median_ohm)]
    rmse = max(c.rmse_mV for c in s.cells)
    largest = ""
    if ranked:
        worst = max(ranked, key=lambda c: c.r0_median_ohm)
        largest = f", largest median R0 {1e3 * worst.r0_median_ohm:.3f} mOhm ({worst.cell})"
    return (
        f"{s.input.given} -> {s.input.name}/: {s.n_samples} samples, {len(s.cells)} cell(s), "
        f"RMSE up to {rmse:.2f} mV{largest}"
        + (f"; warnings: {', '.join(s.warnings)}" if s.warnings else "")
    )


def _error(s: fleet.InputSummary) -> str:
    """The failure, led by the input unless its message already names it first."""
    text = s.error or ""
    return text if text.startswith(f"{s.input.given}:") else f"{s.input.given}: {text}"


def run_fleet(
    args: argparse.Namespace, arguments: Sequence[str], ocv_coeffs: Sequence[float] | None
) -> int:
    """Identify every input of ``arguments``; exit code 1 when any failed, else 0."""
    if args.workers is not None and args.workers < 1:
        raise UserError(f"--workers must be at least 1, got {args.workers}")
    if args.workers is not None and args.scheduler is not None:
        raise UserError("--workers sets the local process pool; with --scheduler the cluster's "
                        "workers run the inputs")  # fmt: skip
    if args.worst < 0:
        raise UserError(f"--worst must be 0 or more, got {args.worst}")
    spec = fleet_spec(args, ocv_coeffs)
    root = output_dir(Path(args.out)).resolve()  # before any work, not after
    inputs = fleet.fleet_inputs(arguments)
    from_record = None
    cells_text = f"the cell config for all: {spec.output.metadata['cell_config']}"
    if args.cell_config is None and args.capacity_ah is None:
        from_record = fleet.CellFromRecord(args.score_soc0)
        cells_text = (
            "no --cell-config: the paper's cell, with the capacity (and an LFP-like record's "
            "OCV) read off each input where it tells them (its metrics.json: cell_config)"
        )
    checks = check_options(args, ocv_coeffs)
    tasks = [
        fleet.FleetTask(i, str(root / i.name), spec_for(spec, i.path), from_record, checks)
        for i in inputs
    ]
    if args.scheduler is not None:
        where = f"the Dask cluster at {args.scheduler}"
        results = fleet.run_dask(tasks, args.scheduler)
    else:
        workers = args.workers or fleet.default_workers(len(tasks))
        where = f"{workers} local worker process(es)"
        results = fleet.run_local(tasks, workers)
    print(f"{len(tasks)} input(s) on {where}, outputs under {root}/; {cells_text}")
    done: dict[str, fleet.InputSummary] = {}
    with tqdm(
        total=len(tasks), desc="inputs", unit="input", disable=None, leave=False, file=sys.stderr
    ) as bar:
        for s in results:
            done[s.input.path] = s
            if s.ok:
                bar.write(_ok_line(s), file=sys.stdout)
            else:
                bar.write(f"bmsid identify: error: {_error(s)}", file=sys.stderr)
            bar.update(1)
    summaries = [done[i.path] for i in inputs]
    fleet.write_summary(root / "summary.csv", summaries, args.worst)
    weakest = fleet.weakest(summaries, args.worst)
    if weakest:
        print(f"weakest cells (largest median R0 over the evaluation window, fleet's "
              f"{len(weakest)}):")  # fmt: skip
        for s, c in weakest:
            print(f"  {1e3 * c.r0_median_ohm:.3f} mOhm  {c.cell}  {s.input.given}")
    failed = [s for s in summaries if not s.ok]
    print(f"wrote {root}/summary.csv: {len(summaries) - len(failed)} of {len(summaries)} "
          f"input(s) identified, {len(failed)} failed")  # fmt: skip
    return 1 if failed else 0
