"""``bmsid make-log INPUT.csv --out FILE.log``: a battery tester's CSV as a candump log.

The log replays with ``canplayer -I FILE.log vcan0=can0`` and reads back through
``bmsid identify`` with the same mapping.
"""

from __future__ import annotations

import argparse
import importlib
import math
from pathlib import Path
from typing import Any

from bmsid.canbus.logs import csv_to_messages, write_log
from bmsid.canbus.mapping import default_mapping, load_mapping
from bmsid.cli.outputs import output_file, positive
from bmsid.errors import UserError


def load_csv(path: Path) -> Any:
    """The tester CSV as ``TesterData`` (``bmsid.offline.csvio``, imported when needed)."""
    try:
        csvio = importlib.import_module("bmsid.offline.csvio")
    except ModuleNotFoundError as exc:
        raise UserError("the CSV reader (bmsid.offline.csvio) is not installed") from exc
    return csvio.read_tester_csv(path, missing_ok=True)  # sent as "not available"


#: latest --t0: the year 2286, beyond any recording
MAX_T0_S = 1e10


def register(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = subparsers.add_parser(
        "make-log",
        help="turn a battery tester's CSV into a candump log",
        description=__doc__,
    )
    p.add_argument("input", type=Path, help="CSV: t_s,current_A,voltage_V or v_cell_01,...")
    p.add_argument("--out", type=Path, required=True, help="candump -l log to write")
    p.add_argument("--mapping", type=Path, help="bus mapping TOML (default: bmsid's own DBC)")
    p.add_argument(
        "--rate-hz", type=float, help="resample to this tick rate (default: one tick per row)"
    )
    p.add_argument("--channel", default="can0", help="interface name written into the log")
    p.add_argument(
        "--t0", type=float, default=0.0, help="timestamp of t_s = 0 in the log, s (default 0)"
    )
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    output_file(args.out)
    positive(args.rate_hz, "--rate-hz")
    # a candump line is "(time) channel id#data": a nan time or a blank in the channel name
    # would write a log that no reader (bmsid's, candump's) takes back
    if not (math.isfinite(args.t0) and 0.0 <= args.t0 < MAX_T0_S):
        raise UserError(f"--t0 must be a Unix time in [0, {MAX_T0_S:.0e}) s, got {args.t0}")
    if not args.channel or any(c.isspace() for c in args.channel):
        raise UserError(f"--channel must be an interface name without blanks, got {args.channel!r}")
    mapping = load_mapping(args.mapping) if args.mapping else default_mapping()
    data = load_csv(args.input)
    messages = csv_to_messages(
        data.t_s,
        data.current_A,
        data.cell_voltages_V,
        mapping,
        rate_hz=args.rate_hz,
        temperature_C=data.temperature_C,
        t0_s=args.t0,
    )
    try:
        write_log(args.out, messages, channel=args.channel)
    except OSError as exc:
        raise UserError(f"cannot write {args.out}: {exc.strerror}") from None
    if data.missing_values:
        print(
            f"{data.missing_values} empty or NaN reading(s) sent as their signal's not-available "
            "value (bmsid's decoder reads a missing current as a stale one, a missing voltage "
            "as a missing cell)"
        )
    print(f"wrote {args.out}")
    return 0
