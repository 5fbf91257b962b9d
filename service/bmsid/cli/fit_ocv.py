"""``bmsid fit-ocv``: fit OCV (Eq. 4) and hysteresis M(z) from a test; write a cell config.

Inputs:

- a low-rate (C/20-C/30) discharge-then-charge test as tester CSV files (one file, or several
  in time order, e.g. the discharge and the charge files, or all four parts of Plett's test);
  a discharge (or charge) alone is fitted as its one branch (``ocv_one_branch``: M from
  ``--hysteresis-from``, else 0);
- an incremental test (pulses with rests of >= 10 min between, GITT-like): the rests'
  voltages are the points (``ocv_incremental``);
- ``--points``: rest-point tables (SOC, OCV) with one or both branches (``read_ocv_points``).

Where Eq. 4's six terms miss the test's mean OCV by more than its voltage noise, a correction
table dU(z) (knots ~2.5 % SOC apart) is written beside it (``--no-ocv-correction``: Eq. 4
alone). The report gives M(z) per knot with its 95 % CI, the polarisation taken out of the
branch gap (R0 + R1 + R2 from the test's rests and current steps) and the pooled mid-SOC
evidence for hysteresis; a knot is never written as 0 silently (a note says why). The method and its
conventions are documented in ``bmsid.offline.ocv_fit``; the command is
:func:`bmsid.offline.ocv_config.fit_ocv_files` with its options as an ``OcvFitSpec``.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from bmsid.cli.outputs import output_dir, output_file
from bmsid.config.cell import InitialParameters, ParameterBounds, Range, save_cell_config
from bmsid.errors import UserError
from bmsid.offline.inputs import COLUMNS_HELP, parse_columns
from bmsid.offline.ocv_config import OcvFitSpec, fit_ocv_files, write_report
from bmsid.offline.ocv_fit import EQ32_KNOTS

_INITIAL_KEYS = ("R0_ohm", "R1_ohm", "tau1_s", "R2_ohm", "tau2_s")
_BOUND_KEYS = ("R0_ohm", "R1_ohm", "R2_ohm", "tau1_s", "tau2_s", "M_scale", "ocv_offset_V")


def register(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = subparsers.add_parser(
        "fit-ocv",
        help="fit OCV (Eq. 4) and hysteresis M(z) from an OCV test; write a cell config",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("inputs", nargs="+", metavar="FILE", help="test CSV(s) in time order, or tables")
    p.add_argument("--out", required=True, help="cell config to write (.toml or .json)")
    p.add_argument(
        "--report",
        default=None,
        metavar="DIR",
        help="folder for ocv_fit.txt/.json/.png (default: <out stem>_report/ beside --out)",
    )
    p.add_argument(
        "--no-ends",
        action="store_true",
        help="do not extend the OCV to the rested voltages at empty/full (clamp as before)",
    )
    p.add_argument(
        "--no-ocv-correction",
        action="store_true",
        help="write Eq. 4 alone: no correction table beyond it, even where the test resolves "
        "one (see the report's 'OCV correction table' line)",
    )
    p.add_argument("--name", default=None, help="cell name (default: the output file's stem)")
    p.add_argument("--chemistry", default="unknown", help="chemistry label, e.g. LFP, NMC")
    p.add_argument(
        "--capacity-ah", type=float, default=None, help="capacity, Ah (default: measured)"
    )
    p.add_argument(
        "--coulombic-efficiency", type=float, default=None, help="default: measured from the test"
    )
    p.add_argument(
        "--temperature-c",
        type=float,
        default=None,
        metavar="DEGC",
        help="the test's temperature, degC, written to the config (default: the median of the "
        "files' temperature column; rest-point tables carry none)",
    )
    p.add_argument("--charge-positive", action="store_true", help="the files count charge positive")
    p.add_argument("--cell", default=None, help="voltage column to use when a file has several")
    p.add_argument("--columns", default=None, metavar="NAME=COLUMN,...", help=COLUMNS_HELP)
    p.add_argument(
        "--trim-soc",
        type=float,
        default=0.02,
        help="SOC trimmed at each end of the fit (default 0.02)",
    )
    p.add_argument(
        "--gamma",
        type=float,
        default=30.0,
        help="hysteresis rate gamma (not fitted; each M knot's CI carries its change over "
        "gamma/3..3*gamma)",
    )
    p.add_argument(
        "--m-knots",
        default=",".join(str(k) for k in EQ32_KNOTS),
        help="SOC knots of the piecewise-linear M(z) table (default: Eq. 32's)",
    )
    p.add_argument(
        "--initial",
        default=None,
        metavar="R0_ohm=X,R1_ohm=X,tau1_s=X,R2_ohm=X,tau2_s=X",
        help="starting parameter values stored in the config",
    )
    p.add_argument(
        "--bound",
        action="append",
        default=[],
        metavar="NAME=LO:HI",
        help=f"parameter bound, repeatable; NAME in {', '.join(_BOUND_KEYS)}",
    )
    g = p.add_argument_group("rest-point tables")
    g.add_argument("--points", action="store_true", help="inputs are rest-point tables")
    g.add_argument(
        "--branch",
        choices=("discharge", "charge"),
        default=None,
        help="branch of tables whose column names do not say it",
    )
    g.add_argument(
        "--soc-anchor",
        choices=("auto", "none", "full"),
        default="auto",
        help="auto (default): shift a table whose SOC runs above 100 %% so that its highest "
        "discharge point is 100 %%; full: every table; none: the SOC as given",
    )
    g.add_argument(
        "--hysteresis-from",
        default=None,
        metavar="CONFIG",
        help="take M(z) from this cell config when the tables have one branch only",
    )
    p.set_defaults(func=run)


def _float_list(text: str, what: str) -> list[float]:
    try:
        return [float(x) for x in text.split(",") if x.strip()]
    except ValueError:
        raise UserError(f"{what}: expected comma-separated numbers, got {text!r}") from None


def _initial(text: str | None) -> InitialParameters | None:
    if text is None:
        return None
    values: dict[str, float] = {}
    for item in text.split(","):
        key, _, val = item.partition("=")
        if key.strip() not in _INITIAL_KEYS:
            raise UserError(
                f"--initial: unknown key {key.strip()!r}; use {', '.join(_INITIAL_KEYS)}"
            )
        try:
            values[key.strip()] = float(val)
        except ValueError:
            raise UserError(f"--initial: {item!r} is not KEY=NUMBER") from None
    if set(values) != set(_INITIAL_KEYS):
        raise UserError(f"--initial needs all of {', '.join(_INITIAL_KEYS)}")
    try:
        return InitialParameters(**values)
    except ValueError as exc:
        raise UserError(f"--initial: {exc}".splitlines()[0]) from None


def _bounds(items: list[str]) -> ParameterBounds | None:
    if not items:
        return None  # no [bounds] in the config: identify derives them from the record
    ranges: dict[str, Range] = {}
    for item in items:
        key, _, span = item.partition("=")
        lo, _, hi = span.partition(":")
        if key.strip() not in _BOUND_KEYS:
            raise UserError(f"--bound: unknown name {key.strip()!r}; use {', '.join(_BOUND_KEYS)}")
        try:
            ranges[key.strip()] = Range(lo=float(lo), hi=float(hi))
        except ValueError:
            raise UserError(f"--bound: {item!r} is not NAME=LO:HI with LO < HI") from None
    try:
        return ParameterBounds(**ranges)
    except ValueError as exc:
        raise UserError(f"--bound: {exc}".splitlines()[0]) from None


def run(args: argparse.Namespace) -> int:
    out = Path(args.out)
    if out.suffix.lower() not in (".toml", ".json"):
        raise UserError(f"--out {out}: use a .toml or .json file name")
    output_file(out)
    if args.report:
        output_dir(Path(args.report), "--report")
    spec = OcvFitSpec(
        name=args.name or out.stem,
        chemistry=args.chemistry,
        points=args.points,
        capacity_Ah=args.capacity_ah,
        coulombic_efficiency=args.coulombic_efficiency,
        charge_positive=args.charge_positive,
        columns=parse_columns(args.columns),
        cell=args.cell,
        trim_soc=args.trim_soc,
        gamma=args.gamma,
        knots=tuple(_float_list(args.m_knots, "--m-knots")),
        initial=_initial(args.initial),
        bounds=_bounds(args.bound),
        branch=args.branch,
        soc_anchor=args.soc_anchor,
        hysteresis_from=args.hysteresis_from,
        ends=not args.no_ends,
        correction=not args.no_ocv_correction,
        temperature_C=args.temperature_c,
    )
    fit = fit_ocv_files(args.inputs, spec)
    print(fit.report())
    save_cell_config(fit.config, out)
    print(f"wrote {out}")
    report_dir = Path(args.report) if args.report else out.with_name(f"{out.stem}_report")
    paths = write_report(fit, report_dir)
    print(f"wrote {', '.join(str(p) for p in paths)}")
    return 0
