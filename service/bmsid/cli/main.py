"""``bmsid`` entry point: dispatches to one module per subcommand.

Each command module exposes ``register(subparsers) -> None`` that adds its parser and sets
``func`` (``Callable[[argparse.Namespace], int]``) as the default, and may set
``log_level`` (default WARNING; ``run`` sets INFO). ``-v``/``-q`` are accepted before and after
the command. Every path ends in one line on stderr, never a traceback: errors a user can fix
raise ``UserError`` (exit code 2), a file the system refuses is an ``OSError`` (exit code 1,
the file and the reason), and anything else is a bug (exit code 1, its type, message and
place; ``-vv`` logs the traceback).
"""

from __future__ import annotations

import argparse
import importlib
import logging
import sys
import traceback
from collections.abc import Sequence

from bmsid import __version__
from bmsid.cli import logsetup
from bmsid.errors import UserError
from bmsid.threads import one_blas_thread

log = logging.getLogger(__name__)

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
    _add_verbosity(parser, "")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name in COMMANDS if only is None else (only,):
        try:
            module = importlib.import_module(f"bmsid.cli.{name}")
        except ModuleNotFoundError as exc:
            if exc.name == f"bmsid.cli.{name}":
                continue
            raise
        module.register(sub)
    # after the command too (`bmsid run --config f -v`); other dests, or the subcommand's
    # defaults would overwrite what was given before it
    for command_parser in sub.choices.values():
        _add_verbosity(command_parser, "sub_")
    return parser


def _add_verbosity(parser: argparse.ArgumentParser, prefix: str) -> None:
    parser.add_argument(
        "-v", "--verbose", action="count", default=0, dest=f"{prefix}verbose",
        help="more log output (repeat for more)",
    )  # fmt: skip
    parser.add_argument(
        "-q", "--quiet", action="count", default=0, dest=f"{prefix}quiet",
        help="less log output (repeat for less)",
    )  # fmt: skip


def _where(exc: BaseException) -> str:
    """``file:line`` of the innermost frame of ``exc``'s traceback (for a bug report)."""
    frames = traceback.extract_tb(exc.__traceback__)
    if not frames:
        return "?"
    last = frames[-1]
    parts = last.filename.replace("\\", "/").split("/")
    short = "/".join(parts[parts.index("bmsid") :]) if "bmsid" in parts else parts[-1]
    return f"{short}:{last.lineno}"


def _os_error_line(exc: OSError) -> str:
    """``reason: file`` of an OSError, as the system says it (no traceback needed)."""
    reason = exc.strerror or str(exc) or type(exc).__name__
    files = [f for f in (exc.filename, exc.filename2) if f is not None]
    return f"{reason}: {' -> '.join(str(f) for f in files)}" if files else reason


def main(argv: Sequence[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    parser = build_parser(_requested_command(argv))
    args = parser.parse_args(argv)
    level = logsetup.log_level(
        getattr(args, "log_level", logging.WARNING),
        args.verbose + getattr(args, "sub_verbose", 0),
        args.quiet + getattr(args, "sub_quiet", 0),
    )
    logsetup.configure(level)
    # `run` estimates in its bank worker, which limits its own BLAS (daemon/bank_worker.py)
    one_blas_thread(compiled_kernels=getattr(args, "command", None) != "run")
    if not hasattr(args, "func"):
        parser.print_help()
        return 2
    name = f"bmsid {args.command}"
    try:
        return int(args.func(args))
    except UserError as exc:
        print(f"{name}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 130
    except OSError as exc:
        log.debug("traceback of the error below", exc_info=True)
        print(f"{name}: error: {_os_error_line(exc)}", file=sys.stderr)
        return 1
    except Exception as exc:  # a bug: one line to quote in a report, the traceback on request
        log.debug("traceback of the internal error below", exc_info=True)
        more = "" if level <= logging.DEBUG else "; -vv logs the traceback"
        print(
            f"{name}: internal error: {type(exc).__name__}: {exc} (at {_where(exc)}{more})",
            file=sys.stderr,
        )
        return 1


if __name__ == "__main__":
    sys.exit(main())
