"""``bmsid identify INPUT --out DIR``: identify a recording offline, write parameters, metrics
and plots.

INPUT is a tester CSV (``t_s,current_A,voltage_V`` or ``v_cell_01,...``, optional
``temperature_C``, ``.csv`` or ``.csv.gz``) or a candump log (``.log``, decoded with ``--mapping``
exactly as the daemon decodes the bus). Writes ``DIR/params.csv`` (one row per identification
tick and cell; with the default 1 s tick that is one row per sample of a 1 s recording),
``DIR/metrics.json`` (Eq. 31 over the evaluation window, and over all ticks under ``overall``)
and PNG plots (parameters over time as the paper's Fig. 10, voltage and error as Fig. 11).

Evaluation window: by default the first 10 % of the ticks (convergence from the start values)
are not scored; ``--soc-window 0.15,0.95`` scores only ticks whose SOC lies in that range instead.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from tqdm import tqdm

from bmsid.errors import UserError
from bmsid.estimate.types import VARIANTS
from bmsid.offline.identify import IdentifySpec, Progress, identify_source
from bmsid.offline.inputs import (
    cell_config,
    check_soc0,
    open_input,
    parse_tuning,
    parse_window,
    tuning_overrides,
)
from bmsid.offline.outputs import OutputSpec, ocv_range_warning, soc_init_text, summary_line
from bmsid.offline.scoring import metrics_document


# ----------------------------------------------------------------------------- shared options
def add_model_options(p: argparse.ArgumentParser) -> None:
    """Options ``identify`` and ``compare`` share: tuning, window, current sign."""
    p.add_argument(
        "--tuning",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="override an EstimatorTuning field, repeatable (e.g. identify_ocv_offset=true)",
    )
    p.add_argument(
        "--soc-window",
        default=None,
        metavar="LO,HI",
        help="score only ticks with SOC in [LO, HI] (fractions, e.g. 0.15,0.95)",
    )
    p.add_argument(
        "--skip-fraction",
        type=float,
        default=None,
        help="fraction of the first ticks not scored (default 0.1, or 0 with --soc-window)",
    )
    p.add_argument(
        "--charge-positive", action="store_true", help="the input counts charge current positive"
    )


@contextmanager
def progress_bar(total: int | None, desc: str) -> Iterator[Progress]:
    """A tqdm bar on stderr when it is a terminal, silent when piped (``disable=None``)."""
    bar = tqdm(total=total, desc=desc, unit="sample", disable=None, leave=False, file=sys.stderr)

    def update(n: int) -> None:
        bar.update(n)

    try:
        yield update
    finally:
        bar.close()


# ----------------------------------------------------------------------------- identify
def register(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = subparsers.add_parser(
        "identify",
        help="identify a tester CSV or candump log offline; write params, metrics, plots",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("input", metavar="INPUT", help="tester CSV (.csv/.csv.gz) or candump .log")
    p.add_argument("--out", required=True, metavar="DIR", help="output directory")
    p.add_argument("--algorithm", choices=VARIANTS, default="hy-affrls-lpso")
    p.add_argument("--cell-config", default=None, metavar="FILE", help="cell config .toml/.json")
    p.add_argument("--capacity-ah", type=float, default=None, help="override the capacity, Ah")
    p.add_argument("--soc0", type=float, default=None, help="initial SOC, fraction (0..1)")
    p.add_argument(
        "--ocv-coeffs",
        default=None,
        metavar="a0,a1,a2,a3,a4,a5",
        help="override the mean OCV curve (Eq. 4 coefficients, V)",
    )
    p.add_argument("--mapping", default=None, help="bus mapping TOML for .log input")
    p.add_argument("--n-cells", type=int, default=1, help="cells in a .log input (default 1)")
    add_model_options(p)
    p.set_defaults(func=run)


def _ocv_coeffs(text: str | None) -> list[float] | None:
    if text is None:
        return None
    try:
        return [float(x) for x in text.split(",")]
    except ValueError:
        raise UserError(f"--ocv-coeffs: not numbers: {text!r}") from None


def run(args: argparse.Namespace) -> int:
    tuning = parse_tuning(args.tuning)
    window = parse_window(args.soc_window, args.skip_fraction)
    check_soc0(args.soc0)
    cell, note = cell_config(args.cell_config, args.capacity_ah, _ocv_coeffs(args.ocv_coeffs))
    source = open_input(
        args.input, charge_positive=args.charge_positive, mapping=args.mapping, n_cells=args.n_cells
    )
    out = Path(args.out)
    if out.exists() and not out.is_dir():
        raise UserError(f"--out {out} exists and is not a directory")
    print(f"{args.input}: {source.n_samples} samples, {source.n_cells} cell(s); {note}")
    meta = {
        "input": str(args.input),
        "cell_config": note,
        "tuning_overrides": tuning_overrides(args.tuning),
    }
    spec = IdentifySpec(
        cell=cell,
        variant=args.algorithm,
        tuning=tuning,
        soc0=args.soc0,
        window=window,
        charge_positive=args.charge_positive,
        mapping=args.mapping,
        n_cells=args.n_cells,
        output=OutputSpec(title=f"{Path(args.input).name} - {args.algorithm}", metadata=meta),
    )
    with progress_bar(source.n_samples, args.algorithm) as bar:
        result = identify_source(source, spec, out, bar)
    print(soc_init_text(result))
    warning = ocv_range_warning(result, cell)
    if warning:
        print(warning)
    if result.trace.n_ticks == 0:
        raise UserError(f"{args.input}: no identification tick (too short or no valid time)")
    print(summary_line({**metrics_document(result, window), **meta}))
    print(f"wrote {out}/params.csv, metrics.json and plots")
    return 0
