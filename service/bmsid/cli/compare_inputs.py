"""How ``bmsid compare`` reads its datasets: as ``bmsid identify`` reads one input (CSV or
candump log, ``--columns``), with the same record checks (``offline/record_checks.py``).

Before, compare read every file as a tester CSV and ran no check: a sign-flipped file went into
Table 2 at 676 mV and one with time in ms at 27 mV, where identify refuses both (a sweep).
"""

from __future__ import annotations

import argparse
from collections.abc import Mapping
from pathlib import Path

from bmsid.canbus.logs import is_candump_path
from bmsid.config.cell import CellConfig
from bmsid.errors import UserError
from bmsid.estimate.tuning import EstimatorTuning
from bmsid.offline import plausibility
from bmsid.offline.csvio import ColumnMap
from bmsid.offline.identify import too_short
from bmsid.offline.inputs import LoadedInput, StreamedInput, open_input
from bmsid.offline.record_checks import CheckOptions, check_record
from bmsid.offline.report import file_stem
from bmsid.offline.tick_count import count_tick_times
from bmsid.samples import SampleBlock


def check_paths(paths: list[str]) -> None:
    """One line for a directory, or a file given twice or two files of one name: each dataset
    gets the output folder and the table row of its name (a file given twice overwrote its
    folder, and the consistency analysis then found no group)."""
    seen: dict[Path, str] = {}
    names: dict[str, str] = {}
    for p in paths:
        if Path(p).is_dir():
            raise UserError(f"{p}: is a directory: give its files (e.g. {p}/*.csv)")
        key = Path(p).resolve()
        if key in seen:
            also = "" if seen[key] == p else f" (also as {seen[key]})"
            raise UserError(f"{p}: given twice{also}: give each dataset once")
        if (stem := file_stem(p)) in names:
            raise UserError(
                f"{p} and {names[stem]} have one name ({stem}): their outputs would share "
                "one folder; rename one"
            )
        seen[key], names[stem] = p, p


def load_dataset(
    path: str,
    args: argparse.Namespace,
    columns: Mapping[str, ColumnMap] | None,
    cell: CellConfig,
    soc0: float | None,
    tuning: EstimatorTuning,
) -> LoadedInput:
    """The dataset at ``path`` in memory, checked for ``cell`` as identify checks it: its
    notes and warnings printed (prefixed with the path), its first error raised."""
    src = open_input(
        path, charge_positive=args.charge_positive, mapping=args.mapping, n_cells=args.n_cells,
        channel=args.channel, columns=None if is_candump_path(path) else columns,
    )  # fmt: skip
    src.gap_s = tuning.gap_s
    samples = _read_all(src)  # one pass: the reader's notes (NaN readings, merges) are complete
    head = samples.slice(0, plausibility.check_head_samples(src.n_cells))
    t_map = (columns or {}).get("t_s")
    opts = CheckOptions(
        cell_config_given=True, soc0=soc0, charge_positive=args.charge_positive,
        t_source=t_map.source if t_map else "t_s", t_scale=t_map.scale if t_map else 1.0,
    )  # fmt: skip
    findings = [*src.all_findings, *check_record(head, cell, opts, tuning).findings]
    for line in src.notes:
        print(f"{path}: {line}", flush=True)
    for f in findings:
        if f.level != "error":
            print(f"{path}: {f.line()}", flush=True)
    if (error := plausibility.first_error(findings)) is not None:
        raise UserError(f"{path}: {error.message}")
    clock = count_tick_times(iter([samples.t_s]), tuning)
    if (short := too_short(clock.n_ticks, clock.n_samples)) is not None:
        raise UserError(f"{path}: {short}")
    return LoadedInput(
        source=str(path), samples=samples, cell_names=src.cell_names,
        temperature_C=samples.temperature_C, merged_repeats=src.merged_repeats,
        time_restarts=src.time_restarts, notes=src.notes, findings=tuple(findings),
        log_summary=src.log_summary, channel=src.channel,
    )  # fmt: skip


def _read_all(src: StreamedInput) -> SampleBlock:
    blocks = list(src.blocks())
    return SampleBlock.concat(blocks) if blocks else src.head(0)
