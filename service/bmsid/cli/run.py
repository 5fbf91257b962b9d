"""``bmsid run --config FILE``: the live daemon (CAN in, parameters out on CAN and MQTT).

Logs its lifecycle at INFO (``-q``: warnings only, ``-v``: debug). Stops gracefully on
SIGTERM/SIGINT (flush, checkpoint, retained ``offline``) with exit code 0.
"""

from __future__ import annotations

import argparse
import importlib
import logging
from pathlib import Path

from bmsid.cli.preflight import check_replay_log, secret_file_warnings
from bmsid.config.settings import load_settings

log = logging.getLogger("bmsid.run")


def register(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = subparsers.add_parser("run", help="run the live identification daemon", description=__doc__)
    p.add_argument("--config", type=Path, required=True, help="daemon config TOML")
    p.set_defaults(func=run, log_level=logging.INFO)


def run(args: argparse.Namespace) -> int:
    settings = load_settings(args.config)
    check_replay_log(settings)
    for warning in secret_file_warnings(args.config, settings):
        log.warning("%s", warning)
    # Imported here: the estimator stack (scipy) would slow down every other bmsid command.
    core = importlib.import_module("bmsid.daemon.core")
    code: int = core.run_daemon(settings)
    return code
