"""``bmsid check-config FILE``: validate a daemon config and print the effective values.

The output is TOML (environment overrides applied, relative paths resolved, defaults filled in)
with secrets redacted; a bad file or override gets one line naming the field and exit code 2.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import tomli_w

from bmsid.canbus.mapping import default_mapping, load_mapping
from bmsid.config.settings import load_settings
from bmsid.errors import UserError


def register(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = subparsers.add_parser(
        "check-config",
        help="validate a bmsid run config and print the effective values",
        description=__doc__,
    )
    p.add_argument("config", type=Path, help="daemon config TOML")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    settings = load_settings(args.config)
    # The referenced files must be usable too: the daemon would fail on them at start.
    settings.estimator.load_cell()
    if settings.can.mapping is not None:
        mapping = load_mapping(settings.can.mapping)
    else:
        mapping = default_mapping()
    if settings.can.n_cells > mapping.max_cells():
        raise UserError(
            f"{args.config}: field can.n_cells: {settings.can.n_cells} > "
            f"{mapping.max_cells()} cells the mapping {mapping.name!r} carries"
        )
    print(f"# {args.config}: valid (environment overrides applied, secrets redacted)")
    print(tomli_w.dumps(settings.redacted()), end="")
    return 0
