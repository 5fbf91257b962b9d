"""``bmsid identify INPUT --out DIR``: identify a recording offline, write parameters, metrics
and plots.

INPUT is a tester CSV (``t_s,current_A,voltage_V`` or ``v_cell_01,...``, optional ``temperature_C``,
``.csv`` or ``.csv.gz``) or a candump log (``.log`` or ``.log.gz``, decoded with ``--mapping``
exactly as the daemon decodes the bus). Writes ``DIR/params.csv`` (one row per identification tick
and cell; with the default 1 s tick that is one row per sample of a 1 s recording),
``DIR/metrics.json`` (Eq. 31 over the evaluation window, and over all ticks under ``overall``) and
PNG plots (parameters over time as the paper's Fig. 10, voltage and error as Fig. 11).

Evaluation window: by default every tick is scored (the start-up is part of what a user gets);
``--skip-fraction 0.1`` leaves the first 10 % out, ``--soc-window 0.15,0.95`` scores only ticks
whose SOC lies in that range.

Before the run the input is checked (bmsid.offline.plausibility): time in milliseconds or steps
beyond the gap threshold and a flipped current sign stop it (exit 2); a capacity that does not
fit the record, too little excitation for the capacity and a missing cell config are WARNING
lines. Exports with other column names load with ``--columns t_s=Time,current_A=Current,...``
(``NAME=COLUMN*SCALE`` converts units, e.g. ``t_s=Time_ms*0.001``).

Long records: the input is read in pieces and the run is streamed (a first pass counts the
ticks, then metrics and plots are accumulated block by block), so memory does not grow with the
record. The checks before the run look at its first two days of 1 s samples. ``--every 10``
writes one row per 10 s and cell (the last tick of each interval; ``--every-mode mean`` the
mean); a record of more than 86,400 ticks gets a decimation by default, announced on stdout and
in metrics.json (``output``); ``--every 0`` keeps every tick. ``--format parquet`` writes
``params.parquet`` (the same columns and units) instead of ``params.csv``.

Several inputs, a directory (searched for .csv, .csv.gz, .log, .log.gz) or a glob: each input into
its own subdirectory of DIR and DIR/summary.csv (per input and cell the latest parameters, quality,
RMSE and R0 ranks), on --workers local processes or the Dask cluster at --scheduler; a failed input
is one line and the others go on (exit 1 when any failed). Each input gets the checks above (an
error fails that input only) and, without --cell-config, the cell read off its own record.
"""

from __future__ import annotations

import argparse
import math
import sys
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from tqdm import tqdm

from bmsid.cli.identify_fleet import add_fleet_options, check_options, run_fleet
from bmsid.cli.outputs import output_dir
from bmsid.config.engine import ocv_model
from bmsid.errors import UserError
from bmsid.estimate.types import VARIANTS
from bmsid.offline import fleet, plausibility
from bmsid.offline.identify import (
    IdentifySpec,
    Progress,
    identify_source,
    params_interval,
    scan_record,
    too_short,
)
from bmsid.offline.inputs import (
    COLUMNS_HELP,
    cell_config,
    check_soc0,
    open_input,
    parse_columns,
    parse_tuning,
    parse_window,
    tuning_overrides,
    with_score_reference,
)
from bmsid.offline.outputs import (
    SCORE_SOC0_HELP,
    OutputSpec,
    error_band_line,
    fit_warnings,
    observer_text,
    ocv_range_warning,
    soc_init_text,
    start_warnings,
    summary_line,
    temperature_law_text,
)
from bmsid.offline.record_checks import check_record
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
        help="fraction of the first ticks not scored (default 0: the whole record)",
    )
    p.add_argument(
        "--charge-positive", action="store_true", help="the input counts charge current positive"
    )


def add_input_options(p: argparse.ArgumentParser) -> None:
    """How ``identify`` and ``compare`` read an input: a candump log's mapping, cells and
    channel; a CSV's foreign column names."""
    p.add_argument("--mapping", default=None, help="bus mapping TOML for .log input")
    p.add_argument(
        "--n-cells",
        type=int,
        default=None,
        help="cells in a .log input (default: as many as the log carries)",
    )
    p.add_argument(
        "--channel",
        default=None,
        metavar="NAME",
        help="CAN channel of a .log input to read (required when several carry the mapping)",
    )
    p.add_argument(
        "--columns",
        default=None,
        metavar="NAME=COLUMN,...",
        help=COLUMNS_HELP,
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
    p.add_argument(
        "input", metavar="INPUT", nargs="+",
        help="tester CSV (.csv/.csv.gz) or candump .log (.log.gz); several, a directory or a "
        "glob: one subdirectory of --out each and OUT/summary.csv",
    )  # fmt: skip
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
    p.add_argument("--score-soc0", type=float, default=None, metavar="FRACTION",
                   help=SCORE_SOC0_HELP)  # fmt: skip
    p.add_argument(
        "--every",
        type=float,
        default=None,
        metavar="SECONDS",
        help="one params row per interval of SECONDS and cell (0: every tick; default: every "
        "tick up to 86,400 ticks, a longer record gets an announced 2-3600 s interval)",
    )
    p.add_argument(
        "--every-mode",
        choices=("last", "mean"),
        default="last",
        help="per --every interval: the last tick's values (default) or the mean of its ticks",
    )
    p.add_argument(
        "--format",
        choices=("csv", "parquet"),
        default="csv",
        help="params.csv (default) or params.parquet: the same columns and units",
    )
    add_input_options(p)
    add_model_options(p)
    add_fleet_options(p)
    p.set_defaults(func=run)


def _ocv_coeffs(text: str | None) -> list[float] | None:
    if text is None:
        return None
    try:
        return [float(x) for x in text.split(",")]
    except ValueError:
        raise UserError(f"--ocv-coeffs: not numbers: {text!r}") from None


def run(args: argparse.Namespace) -> int:
    if args.scheduler is not None or fleet.is_fleet(args.input):
        return run_fleet(args, args.input, _ocv_coeffs(args.ocv_coeffs))
    args = argparse.Namespace(**{**vars(args), "input": args.input[0]})  # one file, as always
    tuning = parse_tuning(args.tuning)
    # The default window is the whole record (as compare and the library): the start-up is part
    # of what a user gets.
    window = parse_window(args.soc_window, args.skip_fraction)
    check_soc0(args.soc0)
    if args.every is not None and not (math.isfinite(args.every) and args.every >= 0):
        raise UserError(f"--every is a number of seconds >= 0, got {args.every:g}")
    columns = parse_columns(args.columns)
    cell, note = cell_config(args.cell_config, args.capacity_ah, _ocv_coeffs(args.ocv_coeffs))
    out = output_dir(Path(args.out))  # before reading and identifying, not after
    source = open_input(
        args.input, charge_positive=args.charge_positive, mapping=args.mapping,
        n_cells=args.n_cells, channel=args.channel, columns=columns,
    )  # fmt: skip
    source.gap_s = tuning.gap_s  # its gaps are counted over the run's threshold
    # the record's head, for the checks only: not held through the run
    head = source.head(plausibility.check_head_samples(source.n_cells))
    checked = check_record(head, cell, check_options(args, _ocv_coeffs(args.ocv_coeffs)), tuning)
    del head
    cell, note, checks = checked.cell, checked.note or note, checked.findings
    window = with_score_reference(window, cell, args.score_soc0, tuning.gap_s)
    meta = {
        "input": str(args.input),
        "cell_config": note,
        "tuning_overrides": tuning_overrides(args.tuning),
    }
    output = OutputSpec(
        title=f"{Path(args.input).name} - {args.algorithm}", metadata=meta,
        params_format=args.format, every_s=args.every, every_mode=args.every_mode,
    )  # fmt: skip
    spec = IdentifySpec(
        cell=cell, variant=args.algorithm, tuning=tuning, soc0=args.soc0, window=window,
        charge_positive=args.charge_positive, mapping=args.mapping, n_cells=source.n_cells,
        output=output, keep_trace=False,
    )  # fmt: skip
    with progress_bar(None, "reading") as bar:
        scan = scan_record(source, spec)  # a bad row anywhere stops the run here
        bar(scan.n_samples)
    print(
        f"{args.input}: {scan.n_samples} samples, {source.n_cells} cell(s), "
        f"{source.period(tuning.gap_s).text()}; {note}"
    )
    for line in source.notes:
        print(line)
    findings = [*source.all_findings, *checks]
    for f in findings:
        if f.level != "error":
            print(f.line())
    error = plausibility.first_error(findings)
    if error is not None:
        raise UserError(f"{args.input}: {error.message}")
    if (short := too_short(scan.n_ticks, scan.n_samples)) is not None:
        raise UserError(f"{args.input}: {short}")  # before any output is written
    # The checks travel with the source (``input_report``), for metrics.json.
    source.findings = (*source.findings, *checks)
    every, announced = params_interval(output, scan, tuning.id_period_s)
    if args.every and every is None:
        print(
            f"--every {args.every:g} s is no longer than the identification tick "
            f"({tuning.id_period_s:g} s): params.{args.format} gets every tick"
        )
    if announced:
        print(
            f"{scan.n_ticks} ticks: params.{args.format} gets one row per {every:g} s and cell "
            f"({args.every_mode} value of each interval; --every 0 for every tick)"
        )
    with progress_bar(scan.n_samples, args.algorithm) as bar:
        result = identify_source(source, spec, out, bar, scan)
    print(soc_init_text(result, cell.soc_init.rest_current_C * cell.capacity_Ah))
    for _, start_line in start_warnings(result, ocv_model(cell)):
        print(start_line)
    warning = ocv_range_warning(result, cell)
    if warning:
        print(warning)
    if result.n_ticks == 0:
        raise UserError(f"{args.input}: no identification tick (too short or no valid time)")
    if result.soc_init_method != "given":  # with --soc0 the coulomb count was checked before
        start = {"ocv_at_rest": "the OCV at rest"}.get(result.soc_init_method, "its start")
        soc_findings = plausibility.check_soc_range(result.soc_extremes(), cell.capacity_Ah, start)
        for f in soc_findings:
            print(f.line())
    doc = {**metrics_document(result, window), **meta}
    print(summary_line(doc))
    if (band := error_band_line(doc)) is not None:
        print(band)
    for _, line in fit_warnings(result, window):
        print(line)
    if (obs := observer_text(result)) is not None:
        print(obs)
    if (law := temperature_law_text(result)) is not None:
        print(law)
    print(f"wrote {out}/params.{args.format}, metrics.json and plots")
    return 0
