"""``bmsid`` entry point: dispatches to one module per subcommand.

Each command module exposes ``register(subparsers) -> None`` that adds its parser and sets
``func`` (``Callable[[argparse.Namespace], int]``) as the default. Errors a user can fix raise
``UserError`` and are printed as one line with exit code 2, never a traceback.
"""

from __future__ import annotations

import argparse
import importlib
import logging
import sys
from collections.abc import Sequence

from bmsid import __version__
from bmsid.errors import UserError

#: Command modules under ``bmsid.cli``; a module missing here is simply not offered.
COMMANDS = (
    "demo",
    "identify",
    "fit_ocv",
    "compare",
    "make_log",
    "run",
    "check_config",
)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="bmsid", description="Live battery parameter identification for BMS gateways."
    )
    parser.add_argument("--version", action="version", version=f"bmsid {__version__}")
    parser.add_argument("-v", "--verbose", action="count", default=0, help="more log output")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name in COMMANDS:
        try:
            module = importlib.import_module(f"bmsid.cli.{name}")
        except ModuleNotFoundError as exc:
            if exc.name == f"bmsid.cli.{name}":
                continue
            raise
        module.register(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    logging.basicConfig(
        level=logging.WARNING - 10 * min(args.verbose, 2),
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
    )
    if not hasattr(args, "func"):
        parser.print_help()
        return 2
    try:
        return int(args.func(args))
    except UserError as exc:
        print(f"bmsid {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 130


if __name__ == "__main__":
    sys.exit(main())
