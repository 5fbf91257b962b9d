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


def _requested_command(argv: Sequence[str]) -> str | None:
    """The command module named by ``argv`` (its first positional word), if it is one of ours."""
    word = next((a for a in argv if not a.startswith("-")), None)
    module = word.replace("-", "_") if word is not None else None
    return module if module in COMMANDS else None


def build_parser(only: str | None = None) -> argparse.ArgumentParser:
    """The parser of every command, or of ``only`` (a module name of ``COMMANDS``).

    ``bmsid run`` builds only its own: the other commands' modules import the offline stack
    (scipy, matplotlib), which would cost the daemon ~65 MB of resident memory for nothing.
    """
    parser = argparse.ArgumentParser(
        prog="bmsid", description="Live battery parameter identification for BMS gateways."
    )
    parser.add_argument("--version", action="version", version=f"bmsid {__version__}")
    parser.add_argument("-v", "--verbose", action="count", default=0, help="more log output")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name in COMMANDS if only is None else (only,):
        try:
            module = importlib.import_module(f"bmsid.cli.{name}")
        except ModuleNotFoundError as exc:
            if exc.name == f"bmsid.cli.{name}":
                continue
            raise
        module.register(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    parser = build_parser(_requested_command(argv))
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
