"""``bmsid check-config FILE``: validate a daemon config and print the effective values.

The output is TOML (environment overrides applied, relative paths resolved, defaults filled in)
with secrets redacted (``password`` as ``**********``; ``password_file`` by its path, never its
content); a bad file or override gets one line naming the field and exit code 2. The files the
daemon will read are checked too: cell config, bus mapping, a replay log (one pack's channel),
the output DBC, and with MQTT enabled
the password file (readable, not empty) and the TLS files (CA, client certificate and its key);
and the state directory must be writable (the daemon refuses to start otherwise), or creatable.
A secret every local user can read (a config holding ``mqtt.password``, the password file, the
client key) gets a ``# WARNING:`` line: the config is still valid.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import tomli_w

from bmsid.canbus.mapping import default_mapping, load_mapping
from bmsid.cli.preflight import check_replay_log, secret_file_warnings
from bmsid.config.settings import load_settings
from bmsid.daemon.canout import output_encoder
from bmsid.daemon.sources import replay_channel
from bmsid.daemon.statedir import writable_problem
from bmsid.errors import UserError
from bmsid.publish.mqtt import tls_context


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
    check_replay_log(settings)
    if settings.can.replay is not None:
        replay_channel(settings.can.replay, mapping)  # a log of two packs is refused at start
    output_encoder(settings.can)
    problem = writable_problem(settings.state.directory)
    if problem is not None:
        raise UserError(
            f"{args.config}: field state.directory: {problem} (the daemon keeps its checkpoint "
            "and MQTT sequence numbers there and refuses to start without it)"
        )
    if settings.mqtt.enabled:
        settings.mqtt.password_value()  # the value is not kept, let alone printed
        tls_context(settings.mqtt)
    print(f"# {args.config}: valid (environment overrides applied, secrets redacted)")
    if settings.mqtt.enabled and settings.mqtt.tls_insecure:
        print("# WARNING: mqtt.tls_insecure = true: the broker's certificate is not verified")
    for warning in secret_file_warnings(args.config, settings):
        print(f"# WARNING: {warning}")
    print(tomli_w.dumps(settings.redacted()), end="")
    return 0
