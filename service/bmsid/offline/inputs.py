"""What offline identification reads: recordings as sample blocks, cell configs and options.

A recording is opened as an :class:`InputSource` that yields :class:`~bmsid.samples.SampleBlock`
columns in time order, whatever the file format: tester CSV (``.csv``, ``.csv.gz``, read by
:func:`~bmsid.offline.csvio.iter_tester_csv`) or candump log (``.log``, decoded by
:func:`~bmsid.canbus.logs.iter_samples_from_log` exactly as the daemon decodes the bus). Both
are :class:`StreamedInput`: every ``blocks()`` call reads the file again, piece by piece
(``csvio.CHUNK_VALUES`` values: 65,536 samples of one cell), so memory does not grow with the
record; what needs the whole record
(sample count, gaps, merged rows, restarts) is known after one complete pass. In-memory columns
are a :class:`LoadedInput`.

What a reader did to the file (repeated timestamps merged, a restarted clock stitched on, the
channel and cell count taken from a log) is kept on the source: ``notes`` (lines to print),
``findings`` (warnings) and ``input_report`` (all of it as JSON for metrics.json).

The option parsers take the text a user typed (``KEY=VALUE``, ``LO,HI``) and raise
:class:`~bmsid.errors.UserError` with one line that names the command-line option it came from,
so every front end (CLI, benches) reports a bad value the same way.
"""

from __future__ import annotations

import itertools
import math
import re
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, Protocol

import numpy as np
import numpy.typing as npt
from pydantic import ValidationError

from bmsid.canbus.logs import (
    LogSummary,
    choose_channel,
    is_candump_path,
    iter_samples_from_log,
    summarize_log,
)
from bmsid.canbus.mapping import default_mapping, load_mapping
from bmsid.config.cell import CellConfig, OcvCurve, load_cell_config, paper_cell
from bmsid.errors import UserError
from bmsid.estimate.observer_tuning import ObserverTuning
from bmsid.estimate.tuning import EstimatorTuning
from bmsid.offline.csvio import (
    CANONICAL_COLUMNS,
    RESTART_GAP_S,
    ColumnMap,
    TesterData,
    chunk_rows_for,
    iter_tester_csv,
    tester_csv_columns,
)
from bmsid.offline.plausibility import GAP_S, Finding, SamplePeriod, sample_period
from bmsid.offline.scoring import EvalWindow, SocReference
from bmsid.samples import SampleBlock

FloatArray = npt.NDArray[np.float64]

#: Samples per block when a caller does not say (a few thousand: per-block overhead negligible,
#: a progress bar still moves every second or two).
DEFAULT_BLOCK_SIZE = 4096


class InputSource(Protocol):
    """A recording as a sequence of sample blocks.

    Attributes
    ----------
    source : str
        The path as the caller gave it (for messages and metrics.json).
    cell_names : list of str
        Name of each voltage column, in block column order.
    n_samples : int or None
        Number of samples, None when unknown before reading to the end.
    """

    @property
    def source(self) -> str: ...

    @property
    def cell_names(self) -> list[str]: ...

    @property
    def n_samples(self) -> int | None: ...

    @property
    def n_cells(self) -> int: ...

    @property
    def input_report(self) -> dict[str, Any]:
        """What the reader did and found, JSON-ready (see :class:`LoadedInput`)."""
        ...

    def blocks(self, size: int = DEFAULT_BLOCK_SIZE) -> Iterator[SampleBlock]:
        """Consecutive blocks of at most ``size`` samples, in time order."""
        ...

    def head(self, n: int) -> SampleBlock:
        """The first ``n`` samples (all of a shorter record) as one block."""
        ...


def _input_report(
    period: SamplePeriod, merged: int, restarts: Sequence[int], log_summary: LogSummary | None,
    channel: str | None, notes: Sequence[str], findings: Sequence[Finding],
) -> dict[str, Any]:  # fmt: skip
    """``input_report`` of a loaded or a streamed input (see ``LoadedInput.input_report``)."""
    cells = None
    if log_summary is not None:
        ch = log_summary.channels.get(channel or "")
        mapped = log_summary.mapped_channels
        if ch is None and len(mapped) == 1:
            ch = log_summary.channels[mapped[0]]
        cells = None if ch is None else ch.n_cells
    return {
        "merged_repeats": merged,
        "time_restarts": list(restarts),
        "median_dt_s": None if math.isnan(period.median_dt_s) else period.median_dt_s,
        "gaps_over_30s": period.n_gaps if period.gap_s == GAP_S else None,
        "gap_s": period.gap_s,
        "gaps_over_gap_s": period.n_gaps,
        "channel": channel,
        "cells_in_log": cells,
        "notes": list(notes),
        "findings": [f.as_dict() for f in findings],
    }


@dataclass(frozen=True)
class LoadedInput:
    """A recording held in memory as one block, yielded in slices (views, no copies).

    Attributes
    ----------
    temperature_C : array or None
        The tester file's temperature column (degC, shape (n,)), if any.
    merged_repeats : int
        Rows merged into a row with the same time stamp (the last of them is kept).
    time_restarts : tuple of int
        File lines where the clock restarted and was stitched on.
    notes : tuple of str
        Lines for the user about what the reader did (merges, the log's contents, cells found).
    findings : tuple of Finding
        Doubtful things the reader saw (warnings; errors are raised).
    log_summary : LogSummary or None
        A candump log's channels, ids and cells.
    channel : str or None
        The CAN channel read from a log (None: all frames, or a CSV).
    """

    source: str
    samples: SampleBlock
    cell_names: list[str]
    temperature_C: FloatArray | None = None
    merged_repeats: int = 0
    time_restarts: tuple[int, ...] = ()
    notes: tuple[str, ...] = ()
    findings: tuple[Finding, ...] = ()
    log_summary: LogSummary | None = None
    channel: str | None = None

    @property
    def n_samples(self) -> int:
        return len(self.samples)

    @property
    def n_cells(self) -> int:
        return self.samples.n_cells

    @property
    def input_report(self) -> dict[str, Any]:
        """JSON-ready: ``merged_repeats``, ``time_restarts`` (lines), ``median_dt_s`` (None
        when undefined), ``gaps_over_30s`` (None when counted over another ``gap_s``),
        ``gap_s`` and ``gaps_over_gap_s``, ``channel``, ``cells_in_log``, ``notes`` and
        ``findings`` (level, code, message)."""
        return _input_report(
            sample_period(self.samples.t_s), self.merged_repeats, self.time_restarts,
            self.log_summary, self.channel, self.notes, self.findings,
        )  # fmt: skip

    def blocks(self, size: int = DEFAULT_BLOCK_SIZE) -> Iterator[SampleBlock]:
        if size < 1:
            raise ValueError(f"block size must be >= 1, got {size}")
        for start in range(0, self.n_samples, size):
            yield self.samples.slice(start, start + size)

    def head(self, n: int) -> SampleBlock:
        return self.samples.slice(0, n)

    @classmethod
    def from_tester(cls, data: TesterData, source: str | None = None) -> LoadedInput:
        """A tester file's columns as a source (cells named by their voltage columns), with
        a note for merged repeats and a warning for a stitched clock restart."""
        block = SampleBlock.from_arrays(
            data.t_s, data.current_A, data.cell_voltages_V, data.temperature_C
        )
        notes: list[str] = []
        findings: list[Finding] = []
        if data.merged_repeats:
            notes.append(
                f"merged {data.merged_repeats} rows with repeated timestamps "
                "(the last row of each time is kept)"
            )
        if data.time_restarts:
            lines = ", ".join(str(n) for n in data.time_restarts)
            findings.append(
                Finding(
                    "warning",
                    "time_restart",
                    f"the clock t_s restarts at line(s) {lines}: stitched on after a "
                    f"{RESTART_GAP_S:g} s gap (a new segment from rest); if the parts are "
                    "separate tests, identify them separately",
                )
            )
        return cls(
            source=data.source if source is None else source,
            samples=block,
            cell_names=list(data.cell_names),
            temperature_C=data.temperature_C,
            merged_repeats=data.merged_repeats,
            time_restarts=data.time_restarts,
            notes=tuple(notes),
            findings=tuple(findings),
        )


def _restart_finding(lines: Sequence[int]) -> Finding:
    text = ", ".join(str(n) for n in lines)
    return Finding(
        "warning",
        "time_restart",
        f"the clock t_s restarts at line(s) {text}: stitched on after a {RESTART_GAP_S:g} s gap "
        "(a new segment from rest); if the parts are separate tests, identify them separately",
    )


def _merged_note(n: int) -> str:
    return f"merged {n} rows with repeated timestamps (the last row of each time is kept)"


#: A missing current (a blank or NaN in a CSV) is held this long, s: the daemon's default
#: ``can.staleness_s``, after which its CAN path drops the cycles. The rows of a longer run
#: without a current are dropped, so that the engine sees a gap there: held for 10 min of a
#: drive, one DST value counted as the current took an 8-cell pack's model error from 1.3 to
#: 10.5 mV and its current offset to -1.21 A for the rest of the record.
CURRENT_HOLD_S = 2.0


def drop_unheld_current(piece: SampleBlock, t_last_s: float) -> tuple[SampleBlock, float, int]:
    """``piece`` less the rows whose current is missing longer than ``CURRENT_HOLD_S`` after
    the last row with one (``t_last_s``, s, carried from the piece before; NaN: none yet, so
    a record's leading rows without a current go too), the new ``t_last_s`` and the number of
    rows dropped."""
    have = np.isfinite(piece.current_A)
    if have.all():
        return piece, (float(piece.t_s[-1]) if len(piece) else t_last_s), 0
    k = np.where(have, np.arange(len(piece)), -1)
    np.maximum.accumulate(k, out=k)
    last = np.where(k >= 0, piece.t_s[np.maximum(k, 0)], t_last_s)
    keep = have | (piece.t_s - last <= CURRENT_HOLD_S)
    n_drop = int(np.count_nonzero(~keep))
    t_last_s = float(last[-1])
    if not n_drop:
        return piece, t_last_s, 0
    temp, mono = piece.temperature_C, piece.t_complete_mono
    kept = SampleBlock(
        piece.t_s[keep], piece.current_A[keep], piece.cell_voltages_V[keep],
        None if mono is None else mono[keep], None if temp is None else temp[keep],
    )  # fmt: skip
    return kept, t_last_s, n_drop


class StreamedInput:
    """A recording read from its file piece by piece on every pass (see the module doc).

    ``n_samples``, ``period``, the merges and restarts a CSV reader did, and with them
    ``notes``, ``findings`` and ``input_report``, are complete after one full pass over
    :meth:`blocks` (:func:`bmsid.offline.identify.scan_record` makes one); ``notes`` and
    ``findings`` start with what opening the file found (a log's contents). ``findings`` may
    be extended by the caller (plausibility checks) and go into ``input_report``.
    The median step is that of the first piece (``chunk_rows_for``); gaps are counted over
    the whole record.
    """

    def __init__(
        self,
        source: str,
        cell_names: list[str],
        pieces: Callable[[], Iterator[SampleBlock | TesterData]],
        notes: Sequence[str] = (),
        findings: Sequence[Finding] = (),
        log_summary: LogSummary | None = None,
        channel: str | None = None,
    ) -> None:
        self.source = source
        self.cell_names = cell_names
        self._pieces = pieces
        self._notes = tuple(notes)
        self.findings: tuple[Finding, ...] = tuple(findings)
        self.log_summary = log_summary
        self.channel = channel
        self._scanned: tuple[int, SamplePeriod, int, tuple[int, ...]] | None = None
        self._missing = 0  # empty or NaN readings a CSV reader read as missing (a full pass)
        self._unheld = 0  # rows dropped for a current missing too long (a full pass)
        #: Steps longer than this (s) are counted as gaps (the engine's ``gap_s``).
        self.gap_s = GAP_S

    @property
    def n_cells(self) -> int:
        return len(self.cell_names)

    @property
    def n_samples(self) -> int | None:
        return None if self._scanned is None else self._scanned[0]

    def period(self, gap_s: float | None = None) -> SamplePeriod:
        """Median step (first piece) and the steps longer than ``gap_s`` (None: ``self.gap_s``)
        over the whole record; reads the record again when it was counted with another
        threshold."""
        if gap_s is not None and gap_s != self.gap_s:
            self.gap_s, self._scanned = gap_s, None
        scanned = self._complete()
        return scanned[1]

    @property
    def merged_repeats(self) -> int:
        """Rows merged into a row with the same time stamp (reads the file if not read yet)."""
        return self._complete()[2]

    @property
    def time_restarts(self) -> tuple[int, ...]:
        """File lines where the clock restarted and was stitched on (reads the file if not
        read yet)."""
        return self._complete()[3]

    @property
    def notes(self) -> tuple[str, ...]:
        merged = 0 if self._scanned is None else self._scanned[2]
        out = self._notes + ((_merged_note(merged),) if merged else ())
        if self._missing:
            out += (
                f"{self._missing} empty or NaN current/voltage/temperature value(s) read as "
                f"missing: a missing current holds the previous one for up to {CURRENT_HOLD_S:g}"
                " s, a missing voltage leaves its cell out of that tick (counted as nan_current"
                " / nan_voltage)",
            )
        if self._unheld:
            out += (
                f"{self._unheld} row(s) without a current for longer than {CURRENT_HOLD_S:g} s "
                "dropped: the charge moved then is unknown, so the engine sees a gap there "
                "(one longer than the engine's gap_s restarts its histories and, after "
                "observer.restart_gap_s, re-anchors SOC from the voltage)",
            )
        return out

    @property
    def all_findings(self) -> tuple[Finding, ...]:
        """What opening and reading the file found (a stitched clock), then ``findings``."""
        restarts = () if self._scanned is None else self._scanned[3]
        return ((_restart_finding(restarts),) if restarts else ()) + self.findings

    def _complete(self) -> tuple[int, SamplePeriod, int, tuple[int, ...]]:
        if self._scanned is None:
            for _ in self.blocks():
                pass
        assert self._scanned is not None
        return self._scanned

    @property
    def input_report(self) -> dict[str, Any]:
        """As :attr:`LoadedInput.input_report` (reads the file once if not read yet)."""
        _, period, merged, restarts = self._complete()
        return _input_report(
            period, merged, restarts, self.log_summary, self.channel, self.notes,
            self.all_findings,
        )  # fmt: skip

    def blocks(self, size: int = DEFAULT_BLOCK_SIZE) -> Iterator[SampleBlock]:
        if size < 1:
            raise ValueError(f"block size must be >= 1, got {size}")
        n = gaps = merged = missing = unheld = 0
        restarts: list[int] = []
        median = math.nan
        t_prev = t_current = math.nan
        rest: SampleBlock | None = None  # fewer than ``size`` samples carried to the next piece
        for raw in self._pieces():
            if isinstance(raw, TesterData):
                merged += raw.merged_repeats
                missing += raw.missing_values
                restarts += raw.time_restarts
                piece = SampleBlock.from_arrays(
                    raw.t_s, raw.current_A, raw.cell_voltages_V, raw.temperature_C
                )
            else:
                piece = raw
            piece, t_current, dropped = drop_unheld_current(piece, t_current)
            unheld += dropped
            if len(piece) == 0:
                continue
            dt = np.diff(np.concatenate(([t_prev], piece.t_s)))[0 if n else 1 :]
            gaps += int(np.count_nonzero(dt > self.gap_s))
            if math.isnan(median):
                median = sample_period(piece.t_s).median_dt_s
            t_prev = float(piece.t_s[-1])
            n += len(piece)
            if rest is not None:
                piece = SampleBlock.concat([rest, piece])
            full = len(piece) - len(piece) % size
            for start in range(0, full, size):
                yield piece.slice(start, start + size)
            rest = piece.slice(full, len(piece)) if full < len(piece) else None
        if rest is not None:
            yield rest
        self._scanned = (n, SamplePeriod(median, gaps, self.gap_s), merged, tuple(restarts))
        self._missing = missing
        self._unheld = unheld

    def head(self, n: int) -> SampleBlock:
        got: list[SampleBlock] = []
        have = 0
        for block in self.blocks(max(1, min(n, DEFAULT_BLOCK_SIZE))):
            got.append(block.slice(0, n - have))
            have += len(got[-1])
            if have >= n:
                break
        if not got:
            return SampleBlock.from_arrays(np.zeros(0), np.zeros(0), np.zeros((0, self.n_cells)))
        return SampleBlock.concat(got)


def read_csv_input(
    path: str | Path,
    *,
    charge_positive: bool = False,
    columns: Mapping[str, ColumnMap] | None = None,
    chunk_rows: int | None = None,
) -> StreamedInput:
    """A tester CSV as a streamed source (format in :mod:`bmsid.offline.csvio`), read in pieces
    of ``chunk_rows`` rows (None: ``csvio.chunk_rows_for`` the file's width).

    Parameters
    ----------
    path : str or Path
        ``.csv`` or ``.csv.gz`` file.
    charge_positive : bool
        The file counts charge current positive (the engine counts discharge positive).
    columns : mapping or None
        Foreign column names and unit scales (:func:`parse_columns`).

    Raises
    ------
    UserError
        A missing or malformed header at once; malformed rows (one line naming the file and
        the lines) in the pass that reaches them.
    """
    names = tester_csv_columns(path, columns)

    def pieces() -> Iterator[TesterData]:
        return iter_tester_csv(
            path, charge_positive=charge_positive, columns=columns, chunk_rows=chunk_rows,
            missing_ok=True,  # a blank reading is a missing one: the engine handles it
        )  # fmt: skip

    return StreamedInput(str(path), names, pieces)


def _cell_range(a: int, b: int) -> str:
    """Cells ``a..b`` (1-based) as text."""
    return f"cell {a}" if a == b else f"cells {a}-{b}"


def read_log_input(
    path: str | Path,
    *,
    n_cells: int | None = None,
    mapping: str | Path | None = None,
    charge_positive: bool = False,
    channel: str | None = None,
    chunk_rows: int | None = None,
) -> StreamedInput:
    """A candump log decoded as the daemon decodes the bus, as a streamed source (samples
    grouped in pieces of ``chunk_rows``; None: ``csvio.chunk_rows_for`` the cells and 2).

    The log is first summarised (:func:`~bmsid.canbus.logs.summarize_log`): its channels,
    frame counts and ids go into ``notes``, and the cells whose voltages it carries give the
    cell count when ``n_cells`` is None.

    Parameters
    ----------
    path : str or Path
        candump ``-l`` / ``-ta`` log.
    n_cells : int or None
        Cells of the pack on the bus; None: as many as the log carries. Fewer than the log
        carries is a warning (only the first are analysed), more is an error (every sample
        would lack the missing cells).
    mapping : str, Path or None
        Bus mapping TOML; None uses the default mapping.
    charge_positive : bool
        The bus counts charge current positive.
    channel : str or None
        CAN channel to read (e.g. ``can1``); required when the mapping's frames appear on
        more than one channel.

    Raises
    ------
    UserError
        A missing file, a bad mapping, several channels without ``channel``, a channel or
        cell count the log does not hold at once; no decodable sample or no timestamps in the
        first pass.
    """
    if n_cells is not None and n_cells < 1:
        raise UserError(f"--n-cells must be >= 1, got {n_cells}")
    if not Path(path).is_file():
        raise UserError(f"{path}: no such file")
    bus = load_mapping(mapping) if mapping else default_mapping()
    summary = summarize_log(path, bus)
    notes = [summary.text()]
    findings: list[Finding] = []
    chosen = choose_channel(summary, channel, "pass --channel NAME")
    found = summary.channels[chosen].n_cells if chosen is not None else 0
    where = f" on {chosen}" if chosen is not None and len(summary.channels) > 1 else ""
    if n_cells is None:
        n_cells = max(found, 1)  # none found: decoding below says what is missing
        if found:
            notes.append(f"{found} cells found in the log{where}")
    elif found and n_cells > found:
        raise UserError(
            f"--n-cells {n_cells} but the log carries voltages of {found} cells{where} "
            f"({_cell_range(found + 1, n_cells)} never have one): every sample would be "
            f"incomplete; pass --n-cells {found} or leave it out"
        )
    elif n_cells < found:
        findings.append(
            Finding(
                "warning",
                "n_cells_below_log",
                f"--n-cells {n_cells} but the log carries {found} cells{where}: only "
                f"{_cell_range(1, n_cells)} analysed (leave --n-cells out for all)",
            )
        )
    cells = n_cells
    rows = chunk_rows or chunk_rows_for(n_cells + 2)

    def pieces() -> Iterator[SampleBlock]:
        samples = iter_samples_from_log(path, bus, cells, channel=chosen)
        while chunk := list(itertools.islice(samples, rows)):
            block = SampleBlock.from_samples(chunk)
            if charge_positive:
                block = SampleBlock(
                    block.t_s, -block.current_A, block.cell_voltages_V, None, block.temperature_C
                )
            yield block

    names = [f"v_cell_{c + 1:02d}" for c in range(n_cells)]
    return StreamedInput(str(path), names, pieces, notes, findings, summary, chosen)


def open_input(
    path: str | Path,
    *,
    charge_positive: bool = False,
    mapping: str | Path | None = None,
    n_cells: int | None = None,
    channel: str | None = None,
    columns: Mapping[str, ColumnMap] | None = None,
    chunk_rows: int | None = None,
) -> StreamedInput:
    """The recording at ``path``: a candump log when it ends in ``.log`` (or ``.log.gz``),
    else a tester CSV.

    ``mapping``, ``n_cells`` (None: from the log) and ``channel`` apply to logs only,
    ``columns`` to CSV only (given for the other kind it is an error: the user meant something
    else). Errors as :func:`read_csv_input` and :func:`read_log_input`.
    """
    if is_candump_path(path):
        if columns:
            raise UserError("--columns applies to tester CSV inputs only")
        return read_log_input(
            path,
            n_cells=n_cells,
            mapping=mapping,
            charge_positive=charge_positive,
            channel=channel,
            chunk_rows=chunk_rows,
        )
    for given, option in ((mapping, "--mapping"), (channel, "--channel")):
        if given is not None:
            raise UserError(f"{option} applies to candump .log inputs only")
    return read_csv_input(path, charge_positive=charge_positive, columns=columns,
                          chunk_rows=chunk_rows)  # fmt: skip


# ----------------------------------------------------------------------------- cell config
def load_config(path: str | Path) -> CellConfig:
    """The cell config at ``path`` (.toml or .json); UserError naming the bad field."""
    try:
        return load_cell_config(path)
    except FileNotFoundError:
        raise UserError(f"cell config not found: {path}") from None
    except ValidationError as exc:
        err = exc.errors()[0]
        where = ".".join(str(x) for x in err["loc"])
        raise UserError(f"{path}: invalid cell config at {where}: {err['msg']}") from None
    except (OSError, ValueError) as exc:
        raise UserError(f"{path}: cannot read the cell config: {exc}".splitlines()[0]) from None


def cell_config(
    path: str | Path | None = None,
    capacity_Ah: float | None = None,
    ocv_coeffs: Sequence[float] | None = None,
) -> tuple[CellConfig, str]:
    """The cell config of a run and a note on where it came from (printed, and in metrics.json).

    Parameters
    ----------
    path : str, Path or None
        Cell config file; None takes the paper's cell (Table 1 OCV, 15 mV hysteresis).
    capacity_Ah : float or None
        Capacity override, Ah. Without a config file the paper's start values are dropped, so
        they scale with this capacity.
    ocv_coeffs : sequence of 6 floats or None
        Mean OCV curve override (Eq. 4 coefficients a0..a5, V); the SOC range is kept.
    """
    if path is not None:
        cell = load_config(path)
        note = f"cell config {path}"
    else:
        cell = paper_cell()
        note = "no --cell-config: the paper's cell (Table 1 OCV, 15 mV hysteresis)"
        if capacity_Ah is not None:
            cell = cell.model_copy(update={"initial": None})  # capacity-scaled start values
    update: dict[str, Any] = {}
    if capacity_Ah is not None:
        if not (math.isfinite(capacity_Ah) and 0 < capacity_Ah <= 10_000):
            raise UserError(f"--capacity-ah must lie in (0, 10000], got {capacity_Ah:g}")
        update["capacity_Ah"] = float(capacity_Ah)
        note += f", capacity {capacity_Ah:g} Ah"
    if ocv_coeffs is not None:
        coeffs = [float(c) for c in ocv_coeffs]
        if len(coeffs) != 6 or not all(math.isfinite(c) for c in coeffs):
            raise UserError("--ocv-coeffs needs six finite numbers a0,a1,a2,a3,a4,a5")
        update["ocv"] = OcvCurve(mean=coeffs, soc_min=cell.ocv.soc_min, soc_max=cell.ocv.soc_max)
        note += ", OCV from --ocv-coeffs"
    if update:
        cell = CellConfig.model_validate({**cell.model_dump(), **update})
    return cell, note


# ----------------------------------------------------------------------------- option text
def parse_tuning(items: Sequence[str]) -> EstimatorTuning:
    """``KEY=VALUE`` overrides of :class:`~bmsid.estimate.tuning.EstimatorTuning` fields; a
    nested field by its dotted path (``observer.enabled=false``)."""
    values: dict[str, Any] = {}
    for item in items:
        key, sep, val = item.partition("=")
        key = key.strip()
        if not sep or not key:
            raise UserError(f"--tuning: {item!r} is not KEY=VALUE")
        head, _, sub = key.partition(".")
        if head not in EstimatorTuning.model_fields:
            raise UserError(f"--tuning: unknown field {key!r} of EstimatorTuning")
        if sub:
            if sub not in ObserverTuning.model_fields or head != "observer":
                raise UserError(f"--tuning: unknown field {key!r} of EstimatorTuning")
            values.setdefault(head, {})[sub] = val.strip()
        else:
            values[key] = val.strip()
    try:
        # The option's values are text: convert them (the model is strict for TOML files).
        return EstimatorTuning.model_validate(values, strict=False)
    except ValidationError as exc:
        err = exc.errors()[0]
        where = ".".join(str(x) for x in err["loc"]) or "tuning"
        raise UserError(f"--tuning {where}: {err['msg']}") from None


def tuning_overrides(items: Sequence[str]) -> dict[str, str]:
    """The ``KEY=VALUE`` overrides as given (text), for metrics.json and compare.json."""
    return dict(item.partition("=")[::2] for item in items)


#: ``--columns``'s help, one text for every command that reads tester CSVs.
COLUMNS_HELP = (
    "CSV column names of another export, e.g. t_s=Time,current_A=Current*0.001,"
    "voltage_V=Voltage (NAME: t_s, current_A, voltage_V, temperature_C, v_cell_NN; "
    "*SCALE converts the unit)"
)


def parse_columns(text: str | None) -> dict[str, ColumnMap] | None:
    """``--columns t_s=Time,current_A=Current*0.001,voltage_V=Voltage`` as column maps.

    Each item is ``NAME=COLUMN`` or ``NAME=COLUMN*SCALE``: NAME one of ``t_s``, ``current_A``,
    ``voltage_V``, ``temperature_C`` or ``v_cell_NN``; COLUMN the export's header name; SCALE
    converts its unit (0.001 for ms or mA). None or empty text: no mapping.
    """
    if not text:
        return None
    known = {c.lower(): c for c in CANONICAL_COLUMNS}
    out: dict[str, ColumnMap] = {}
    for item in text.split(","):
        name, sep, col = (x.strip() for x in item.partition("="))
        if not sep or not name or not col:
            raise UserError(f"--columns: {item.strip()!r} is not NAME=COLUMN")
        if name.lower() in known:
            name = known[name.lower()]
        elif re.fullmatch(r"v_cell_\d+", name.lower()):
            name = name.lower()
        else:
            raise UserError(
                f"--columns: unknown name {name!r}; use {', '.join(CANONICAL_COLUMNS)} or v_cell_NN"
            )
        scale = 1.0
        head, star, tail = col.rpartition("*")
        if star:
            try:
                scale = float(tail)
            except ValueError:
                head = col  # a '*' inside the column name itself
            else:
                if not (math.isfinite(scale) and scale != 0.0):
                    raise UserError(f"--columns: scale of {name} must be finite and non-zero")
            col = head.strip()
        if name in out:
            raise UserError(f"--columns: {name} given twice")
        out[name] = ColumnMap(source=col, scale=scale)
    return out


def parse_window(soc_window: str | None, skip_fraction: float | None) -> EvalWindow:
    """The evaluation window from ``LO,HI`` SOC fractions and a skipped fraction of the ticks.

    Nothing is skipped by default: the start-up is part of what a user gets (metrics.json
    reports it on its own as well).
    """
    lo = hi = None
    if soc_window is not None:
        parts = soc_window.split(",")
        try:
            lo, hi = (float(x) for x in parts)
        except ValueError:
            raise UserError(f"--soc-window: expected LO,HI fractions, got {soc_window!r}") from None
        if lo > 1.0 or hi > 1.0:
            raise UserError("--soc-window takes fractions (0.15,0.95), not percent")
    skip = skip_fraction if skip_fraction is not None else 0.0
    try:
        return EvalWindow(skip_fraction=skip, soc_lo=lo, soc_hi=hi)
    except ValueError as exc:
        raise UserError(str(exc)) from None


def check_soc0(soc0: float | None) -> None:
    """UserError unless ``soc0`` is None or a fraction in [0, 1]."""
    if soc0 is not None and not (math.isfinite(soc0) and 0.0 <= soc0 <= 1.0):
        raise UserError(f"--soc0 is a fraction in [0, 1], got {soc0:g}")


def with_score_reference(
    window: EvalWindow, cell: CellConfig, score_soc0: float | None, gap_s: float
) -> EvalWindow:
    """``window`` scored against a coulomb count from ``score_soc0`` (``--score-soc0``) when
    given; a bad start is a UserError naming the option."""
    if score_soc0 is None:
        return window
    try:
        ref = SocReference.from_cell(cell, score_soc0, gap_s)
    except ValueError as exc:
        raise UserError(f"--score-soc0: {exc}") from None
    return replace(window, soc_reference=ref)
