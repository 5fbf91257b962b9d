"""The one loader for battery-tester CSV files (``.csv`` or ``.csv.gz``).

Format: a header line, then one row per sample, comma separated (a header without commas but
with semicolons or tabs selects that separator; double quotes around names and values are
dropped). Columns (names are matched case-insensitively, surrounding blanks ignored; other
names are mapped with ``columns``, see :class:`ColumnMap`):

- ``t_s`` (s) and ``current_A`` (A, positive = discharge) are required;
- the cell voltage(s) in volts: ``voltage_V`` for one cell, or ``v_cell_01, v_cell_02, ...`` for
  several (ordered by their number; when both exist the ``v_cell_*`` columns are the cells and
  ``voltage_V`` goes to ``extra``);
- ``temperature_C`` is optional; any other column that is numeric in every row lands in
  ``extra`` (e.g. ``soc_true``), non-numeric ones (step names, dates) are ignored.

Time as testers write it (gaps and sample-rate changes need nothing: the engine handles them):

- rows with the same ``t_s`` (a record logged twice at a step change) are merged into the last
  of them and counted (``TesterData.merged_repeats``);
- a clock that restarts at the record's first time stamp (records appended to each other, a
  tester that reset its clock) is stitched: the times after it continue the previous ones after
  a gap of ``RESTART_GAP_S``, which the engine treats like any gap (a new segment after a rest
  of unknown length); the lines are in ``TesterData.time_restarts``. More than
  ``MAX_TIME_RESTARTS`` restarts look like a per-step time column and are refused;
- any other step back in time is an error naming its line.

Every rejected file raises ``UserError`` with one line that names the file and the lines
(1-based, the header being line 1). Unit heuristics:

- voltages: a median above 100 is not a cell voltage in volts (cells are below 5 V); the usual
  cause is a millivolt column;
- current: a magnitude above ``MAX_PLAUSIBLE_CURRENT_A`` (3 kA) is taken for milliamperes.
  Smaller mA values (a 2 A test logged as 2000) cannot be told from a large cell's real current
  here; ``bmsid fit-ocv`` catches them later with its C-rate check, where the capacity is known.
"""

from __future__ import annotations

import codecs
import gzip
import io
import itertools
import logging
import re
import warnings
import zlib
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import ClassVar

import numpy as np
import numpy.typing as npt

from bmsid.errors import UserError
from bmsid.offline.timetext import seconds_from_text

FloatArray = npt.NDArray[np.float64]
BoolArray = npt.NDArray[np.bool_]

log = logging.getLogger(__name__)

MAX_PLAUSIBLE_CURRENT_A = 3000.0
MAX_PLAUSIBLE_CELL_VOLTAGE_V = 100.0
#: Gap (s) put where a restarted clock is stitched on: longer than the engine's gap threshold
#: (``EstimatorTuning.gap_s``, 30 s), so the pause of unknown length starts a new segment.
RESTART_GAP_S = 60.0
#: More restarts than this are a per-step time column (Arbin "Step_Time", Neware "Relative
#: Time"), not appended records: refused, the user maps the test time instead.
MAX_TIME_RESTARTS = 3
_MAX_LINES_LISTED = 5
_CELL_RE = re.compile(r"^v_cell_(\d+)$")
#: Names ``columns`` may map to (besides ``v_cell_NN``).
CANONICAL_COLUMNS = ("t_s", "current_A", "voltage_V", "temperature_C")


@dataclass(frozen=True)
class ColumnMap:
    """Where a canonical column (``t_s``, ``current_A``, ...) comes from in a foreign export.

    ``source`` is the export's column name (matched case-insensitively), ``scale`` multiplies its
    values into the canonical unit (0.001 for a time in ms or a current in mA).
    """

    source: str
    scale: float = 1.0


@dataclass(frozen=True)
class TesterData:
    """One tester file: time (s), current (A, + = discharge), cell voltages (V) and extras.

    ``cell_voltages_V`` has shape (n, n_cells) with columns named by ``cell_names``.
    """

    t_s: FloatArray
    current_A: FloatArray
    cell_voltages_V: FloatArray
    cell_names: list[str]
    temperature_C: FloatArray | None = None
    extra: dict[str, FloatArray] = field(default_factory=dict)
    source: str = ""
    #: Rows dropped because the next row has the same ``t_s`` (the last of equal times is kept).
    merged_repeats: int = 0
    #: File lines (1-based) where the clock restarted and was stitched on (see the module doc).
    time_restarts: tuple[int, ...] = ()
    #: Empty or NaN cells of the current, voltage and temperature columns, read as NaN
    #: (missing: the engine holds the previous current, leaves a cell out of its tick).
    missing_values: int = 0
    __test__: ClassVar[bool] = False  # "Test..." name: not a pytest class

    @property
    def n_samples(self) -> int:
        return int(self.t_s.shape[0])

    @property
    def n_cells(self) -> int:
        return int(self.cell_voltages_V.shape[1])


def _lines_text(lines: Sequence[int]) -> str:
    shown = ", ".join(str(n) for n in lines[:_MAX_LINES_LISTED])
    more = len(lines) - _MAX_LINES_LISTED
    return shown + (f" (and {more} more)" if more > 0 else "")


#: Bytes of a file's head that decide its text encoding (the header and the first rows).
_ENCODING_PROBE_BYTES = 1 << 16


def _encoding(path: Path) -> tuple[str, str]:
    """(encoding, errors) of a tester export: UTF-8 (a BOM skipped) when its head decodes so,
    else Windows-1252, as Windows cyclers' software writes a header's "Temperature(°C)" (the
    numbers are ASCII either way; a byte 1252 leaves undefined becomes U+FFFD)."""
    try:
        with gzip.open(path, "rb") if path.name.lower().endswith(".gz") else path.open("rb") as fh:
            head = fh.read(_ENCODING_PROBE_BYTES)
    except (OSError, EOFError, zlib.error):
        return "utf-8-sig", "strict"  # the read itself reports it
    try:
        codecs.getincrementaldecoder("utf-8")().decode(head, final=False)
    except UnicodeDecodeError:
        log.info("%s: not UTF-8, read as Windows-1252", path)
        return "cp1252", "replace"
    return "utf-8-sig", "strict"


def _require_file(path: Path) -> None:
    if path.is_dir():  # a folder of exports: say so, not "no such file"
        raise UserError(f"{path}: is a directory; give the CSV files in it")
    if not path.is_file():
        raise UserError(f"{path}: no such file")


def _read_text(path: Path) -> str:
    _require_file(path)
    enc, errors = _encoding(path)
    try:
        if path.name.lower().endswith(".gz"):
            with gzip.open(path, "rt", encoding=enc, errors=errors, newline="") as fh:
                return fh.read()
        return path.read_text(encoding=enc, errors=errors)
    except (OSError, EOFError, UnicodeDecodeError) as exc:
        raise UserError(f"{path}: cannot read: {exc}") from exc


def _read_lines(path: Path) -> Iterator[str]:
    """The file's lines without their ends, read as they are needed; blank lines at the end of
    the file are dropped (blank lines before a data line are kept: they are bad rows)."""
    _require_file(path)
    blanks = 0
    enc, errors = _encoding(path)
    try:
        gz = path.name.lower().endswith(".gz")
        with (gzip.open(path, "rt", encoding=enc, errors=errors, newline="") if gz else
              path.open(encoding=enc, errors=errors, newline="")) as fh:  # fmt: skip
            for raw in fh:
                line = raw.rstrip("\r\n")
                if not line.strip():
                    blanks += 1
                    continue
                for _ in range(blanks):
                    yield ""
                blanks = 0
                yield line
    except (OSError, EOFError, UnicodeDecodeError, zlib.error) as exc:
        raise UserError(f"{path}: cannot read: {exc}".splitlines()[0]) from exc


_DECIMAL_COMMA = re.compile(r"^[+-]?\d+,\d+([eE][+-]?\d+)?$")
_MISSING_TEXT = ("", "nan")


def _parse_column(
    values: list[str], name: str, path: Path, first_line: int, required: bool,
    missing_ok: bool = False,
) -> FloatArray | None:  # fmt: skip
    """Column as float64; for a required column any bad cell is a UserError naming the lines.
    ``missing_ok``: an empty or NaN cell is NaN (missing, counted by the caller), only text
    that is no number is an error."""
    try:
        arr = np.asarray(values, dtype=np.float64)
    except ValueError:
        arr = None
    if arr is not None and bool(np.all(np.isfinite(arr) | (missing_ok & np.isnan(arr)))):
        return arr
    if not required:
        return None
    bad: list[int] = []
    parsed = np.full(len(values), np.nan)
    for k, s in enumerate(values):
        if missing_ok and s.strip().lower() in _MISSING_TEXT:
            continue
        try:
            parsed[k] = x = float(s)
            ok = bool(np.isfinite(x))
        except ValueError:
            ok = False
        if not ok:
            bad.append(first_line + k)
    if not bad:
        return parsed
    comma = next((s for s in values if _DECIMAL_COMMA.match(s.strip())), None)
    hint = (
        f": {comma!r} looks like a decimal comma; export the file with a decimal point"
        if comma is not None
        else ""
    )
    what = "non-numeric or infinite" if missing_ok else "empty, NaN or non-numeric"
    raise UserError(
        f"{path}: column {name!r} has {what} values on line(s) {_lines_text(bad)}{hint}"
    )


def _finite_numbers(lines: list[str], sep: str, n_fields: int) -> FloatArray | None:
    """``lines`` as a (rows, n_fields) float64 array when every field of every line is a finite
    number (quotes and spaces around it allowed, as the per-cell parse allows them), else None.
    numpy's C reader rounds as ``float()`` does: the same values, ~5x faster."""
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("error")  # "empty input" and the like: not this path
            arr = np.loadtxt(lines, delimiter=sep, dtype=np.float64, comments=None,
                             quotechar='"', ndmin=2)  # fmt: skip
    except (ValueError, UserWarning):
        return None
    # loadtxt skips blank lines, which are bad rows here
    if arr.shape != (len(lines), n_fields) or not bool(np.isfinite(arr).all()):
        return None
    return arr


def _separator(header_line: str) -> str:
    """The field separator: a comma, else what the header uses (European exports: ';' or tab)."""
    if "," in header_line:
        return ","
    for sep in (";", "\t"):
        if sep in header_line:
            return sep
    return ","


def _apply_column_map(
    header: list[str], columns: Mapping[str, ColumnMap], path: Path
) -> tuple[list[str], dict[int, float]]:
    """``header`` with mapped columns renamed to their canonical names, and the scale per column.

    A column that already carries a mapped-to name gives way: it is renamed ``NAME_unmapped``
    (and lands in ``extra`` if numeric), so the user's mapping always wins.
    """
    keys = [h.lower() for h in header]
    out = list(header)
    scales: dict[int, float] = {}
    taken: dict[int, str] = {}
    for target, cm in columns.items():
        j = keys.index(cm.source.strip().lower()) if cm.source.strip().lower() in keys else -1
        if j < 0:
            raise UserError(
                f"{path}: no column {cm.source!r} (mapped to {target}); found: {', '.join(header)}"
            )
        if j in taken:
            raise UserError(f"{path}: column {cm.source!r} is mapped to {taken[j]} and {target}")
        taken[j] = target
        scales[j] = cm.scale
    for j, target in taken.items():
        for k, key in enumerate(keys):
            if k not in taken and key == target.lower():
                out[k] = f"{header[k]}_unmapped"
        out[j] = target
    return out, scales


#: Values (rows x columns) parsed at a time by :func:`iter_tester_csv`: 65,536 rows of a one-cell
#: file (``t_s,current_A,voltage_V``), 10,922 of a 16-cell one. Parsed as Python text a piece
#: holds about 0.3 kB per value at its peak (~60 MB here), whatever the file's width.
CHUNK_VALUES = 196_608
#: The fewest rows of a piece, however wide the file.
MIN_CHUNK_ROWS = 1024


def chunk_rows_for(n_columns: int) -> int:
    """Rows per piece of a file of ``n_columns`` columns (``CHUNK_VALUES`` values)."""
    return max(MIN_CHUNK_ROWS, CHUNK_VALUES // max(n_columns, 1))


class _TimeCleaner:
    """Stitches restarted clocks on, chunk after chunk (see the module doc).

    The record's first time ``t[0]`` and the median forward step (from the first chunk that has
    one: a restart is told from rows out of order by going back to near ``t[0]``, the stitch gap
    is ``max(RESTART_GAP_S, median step)``) are fixed once seen; each restart adds its offset to
    every later row.
    """

    def __init__(self, path: Path) -> None:
        self.path = path
        self.t_first: float | None = None
        self.dt_med: float | None = None
        self.prev: float | None = None  # the previous chunk's last time as read
        self.offset = 0.0
        self.restarts: list[int] = []

    def clean(self, t_raw: FloatArray, row0: int) -> tuple[FloatArray, list[int]]:
        """Stitched times of the chunk whose first row is data row ``row0`` (0-based), and the
        file lines (1-based) where the clock restarted in it."""
        if self.t_first is None:
            self.t_first = float(t_raw[0])
        ext = t_raw if self.prev is None else np.concatenate(([self.prev], t_raw))
        lead = ext.shape[0] - t_raw.shape[0]  # 1 when the previous time is prepended
        steps = np.diff(ext)
        if self.dt_med is None:
            forward = steps[steps > 0]
            if forward.size:
                self.dt_med = float(np.median(forward))
        back = np.flatnonzero(steps < 0)
        offsets = np.zeros(t_raw.shape[0])
        found: list[int] = []
        dt_med = 1.0 if self.dt_med is None else self.dt_med
        for b in back.tolist():
            line = row0 - lead + b + 3  # the line of the row after the step
            near_start = ext[b + 1] <= self.t_first + max(dt_med, 1.0)
            if not (near_start and ext[b] - ext[b + 1] > RESTART_GAP_S):
                raise UserError(
                    f"{self.path}: time t_s is not increasing at line {line} "
                    f"({ext[b + 1]:g} s after {ext[b]:g} s): rows "
                    "out of order? (equal times are merged and a clock that restarts at the "
                    f"record's start, {self.t_first:g} s, is stitched on)"
                )
            found.append(line)
            offsets[b + 1 - lead :] += ext[b] + max(RESTART_GAP_S, dt_med) - ext[b + 1]
        self.restarts += found
        if len(self.restarts) > MAX_TIME_RESTARTS:  # counted up to this chunk's end
            raise UserError(
                f"{self.path}: time t_s restarts {len(self.restarts)} times (line(s) "
                f"{_lines_text(self.restarts)}): a per-step time column? Map the test's "
                "total time to t_s (e.g. --columns t_s=Test_Time(s))"
            )
        self.prev = float(t_raw[-1])
        t = t_raw + self.offset + offsets
        self.offset += float(offsets[-1])
        return t, found


#: The columns bmsid reads by name (lower case), besides v_cell_NN: one of each.
_KNOWN_COLUMNS = ("t_s", "current_a", "voltage_v", "temperature_c")


def _units_row(line: str, sep: str, used: set[int], n_fields: int) -> bool:
    """The line under the header names units ("s,A,V", "[s];[mA];[V]"): no field bmsid reads
    holds a digit (a time as text does, "00:00:01"; an empty or NaN reading is a row)."""
    parts = [x.strip().strip('"') for x in line.split(sep)]
    if len(parts) != n_fields:
        return False
    read = [parts[j] for j in used]
    return all(x and x.lower() != "nan" and not any(ch.isdigit() for ch in x) for x in read)


@dataclass(frozen=True)
class _Layout:
    """Where a file's columns are: the header as mapped, the separator, the scales."""

    header: list[str]
    keys: list[str]
    sep: str
    scales: dict[int, float]
    cell_cols: list[int]


def _layout(path: Path, first: str, columns: Mapping[str, ColumnMap] | None) -> _Layout:
    sep = _separator(first)
    header = [h.strip().strip('"').strip() for h in first.split(sep)]
    scales: dict[int, float] = {}
    if columns:
        header, scales = _apply_column_map(header, columns, path)
    keys = [h.lower() for h in header]
    cells = sorted(
        ((int(m.group(1)), j) for j, k in enumerate(keys) if (m := _CELL_RE.match(k))),
        key=lambda nj: nj[0],
    )
    missing = [c for c in ("t_s", "current_a") if c not in keys]
    if not cells and "voltage_v" not in keys:
        missing.append("voltage_V (or v_cell_01, v_cell_02, ...)")
    if missing:
        names = ", ".join(m.replace("current_a", "current_A") for m in missing)
        raise UserError(
            f"{path}: missing column(s) {names}; found: {', '.join(header)} "
            "(other names: --columns t_s=NAME,current_A=NAME,voltage_V=NAME)"
        )
    used = [k for k in keys if k in _KNOWN_COLUMNS or _CELL_RE.match(k)]
    if twice := sorted({header[keys.index(k)] for k in used if used.count(k) > 1}):
        raise UserError(
            f"{path}: column(s) {', '.join(twice)} appear more than once in the header: which "
            "is meant? rename one, or map one with --columns"
        )
    cell_cols = [j for _, j in cells] if cells else [keys.index("voltage_v")]
    return _Layout(header, keys, sep, scales, cell_cols)


def tester_csv_columns(
    path: str | Path, columns: Mapping[str, ColumnMap] | None = None
) -> list[str]:
    """The cell voltage column names of a tester CSV, from its header alone."""
    p = Path(path)
    first = next(_read_lines(p), None)
    if first is None:
        raise UserError(f"{p}: empty file")
    lay = _layout(p, first, columns)
    return [lay.header[j] for j in lay.cell_cols]


def _take(d: TesterData, idx: slice | npt.NDArray[np.bool_]) -> TesterData:
    return TesterData(
        t_s=d.t_s[idx], current_A=d.current_A[idx], cell_voltages_V=d.cell_voltages_V[idx],
        cell_names=d.cell_names,
        temperature_C=None if d.temperature_C is None else d.temperature_C[idx],
        extra={k: v[idx] for k, v in d.extra.items()}, source=d.source,
    )  # fmt: skip


def _join(a: TesterData, b: TesterData) -> TesterData:
    """``a``'s rows then ``b``'s (extras both have)."""
    return TesterData(
        t_s=np.concatenate([a.t_s, b.t_s]),
        current_A=np.concatenate([a.current_A, b.current_A]),
        cell_voltages_V=np.concatenate([a.cell_voltages_V, b.cell_voltages_V]),
        cell_names=a.cell_names,
        temperature_C=None if a.temperature_C is None or b.temperature_C is None
        else np.concatenate([a.temperature_C, b.temperature_C]),
        extra={k: np.concatenate([v, b.extra[k]]) for k, v in a.extra.items() if k in b.extra},
        source=a.source,
    )  # fmt: skip


def iter_tester_csv(
    path: str | Path,
    *,
    charge_positive: bool = False,
    columns: Mapping[str, ColumnMap] | None = None,
    chunk_rows: int | None = None,
    missing_ok: bool = False,
) -> Iterator[TesterData]:
    """A tester CSV (see the module docstring) as consecutive pieces of at most about
    ``chunk_rows`` rows (None: :func:`chunk_rows_for` its columns), read as they are needed:
    memory does not grow with the file.

    Each piece carries its own ``merged_repeats`` and ``time_restarts`` (file lines); the row
    before a piece's end is held back until the next piece shows whether it repeats a time.
    What needs the whole column in :func:`read_tester_csv`'s checks is decided on the first
    piece here: the median voltage (millivolts?) and the median step (restarts); a bad row
    or a current that looks like milliamperes is an error in whichever piece it lies.
    Errors as :func:`read_tester_csv`; ``missing_ok``: an empty or NaN current, voltage or
    temperature cell is NaN (a missing reading, counted in ``missing_values``) instead of an
    error (identification handles missing readings; an OCV fit does not).
    """
    if chunk_rows is not None and chunk_rows < 1:
        raise ValueError(f"chunk_rows must be >= 1, got {chunk_rows}")
    p = Path(path)
    lines = _read_lines(p)
    first = next(lines, None)
    if first is None:
        raise UserError(f"{p}: empty file")
    lay = _layout(p, first, columns)
    header, keys = lay.header, lay.keys
    has_temp = "temperature_c" in keys
    used = {keys.index("t_s"), keys.index("current_a"), *lay.cell_cols}
    if has_temp:
        used.add(keys.index("temperature_c"))
    row0 = 0
    second = next(lines, None)
    if second is not None and _units_row(second, lay.sep, used, len(header)):
        log.info("%s: line 2 (%s) read as a row of units and skipped", p, second.strip())
        row0 = 1
    elif second is not None:
        lines = itertools.chain([second], lines)
    cleaner = _TimeCleaner(p)
    time_form: str | None = None  # "numbers" or a timetext form, fixed by the first piece
    held: TesterData | None = None
    checked_mv = False
    n_fields = len(header)
    rows_per_piece = chunk_rows or chunk_rows_for(n_fields)
    while True:
        body = list(itertools.islice(lines, rows_per_piece))
        if not body:
            break
        # Once the first piece read the time as numbers: a piece of finite numbers in every
        # field is parsed in C; anything else (a bad row, a blank, a NaN, text) takes the
        # per-cell path below, which names the lines.
        fast = _finite_numbers(body, lay.sep, n_fields) if time_form == "numbers" else None
        rows: list[list[str]] = []
        bad_rows: list[int] = []
        for k, line in enumerate(body if fast is None else ()):
            parts = line.split(lay.sep)
            if len(parts) != n_fields:
                bad_rows.append(row0 + k + 2)
            else:
                rows.append(parts)
        if bad_rows:
            raise UserError(
                f"{p}: line(s) {_lines_text(bad_rows)} are empty or do not have the "
                f"{n_fields} fields of the header"
            )
        columns_text = list(zip(*rows, strict=True))

        def cells_of(j: int, text: list[tuple[str, ...]] = columns_text) -> list[str]:
            return [s.strip().strip('"') for s in text[j]]

        missing = 0

        def times(text: list[tuple[str, ...]] = columns_text) -> FloatArray:
            """``t_s`` in s: numbers, else cyclers' time text (``timetext``) once the first
            piece read as such."""
            nonlocal time_form
            j = keys.index("t_s")
            if time_form != "numbers":
                read = seconds_from_text(cells_of(j, text))
                if read is not None:
                    if time_form is None:
                        log.info("%s: column %r read as %s", p, header[j], read[1])
                    time_form = read[1]
                    return read[0] * lay.scales[j] if j in lay.scales else read[0]
            if time_form is None:
                time_form = "numbers"
            return required("t_s")  # numbers, or the error that names the lines that are not

        def required(name: str, text: list[tuple[str, ...]] = columns_text,
                     first_line: int = row0 + 2,
                     numbers: FloatArray | None = fast) -> FloatArray:  # fmt: skip
            nonlocal missing
            j = keys.index(name.lower())
            if numbers is not None:
                arr = np.ascontiguousarray(numbers[:, j])
            else:
                # a blank or NaN reading is a missing one (the time stamp must be there)
                ok_missing = missing_ok and name.lower() != "t_s"
                got = _parse_column(cells_of(j, text), header[j], p, first_line, True, ok_missing)
                assert got is not None
                arr = got
            missing += int(np.count_nonzero(np.isnan(arr)))
            return arr * lay.scales[j] if j in lay.scales else arr

        t, restarts = cleaner.clean(times(), row0)
        current = required("current_A")
        if charge_positive:
            current = -current
        if float(np.nanmax(np.abs(current), initial=0.0)) > MAX_PLAUSIBLE_CURRENT_A:
            raise UserError(
                f"{p}: |current_A| reaches {np.nanmax(np.abs(current)):g} > "
                f"{MAX_PLAUSIBLE_CURRENT_A:g}: looks like milliamperes; give the current in A"
            )
        volts = np.column_stack([required(header[j]) for j in lay.cell_cols])
        if not checked_mv:
            checked_mv = True
            for c, j in enumerate(lay.cell_cols):
                med = float(np.nanmedian(volts[:, c])) if np.isfinite(volts[:, c]).any() else 0.0
                if med > MAX_PLAUSIBLE_CELL_VOLTAGE_V:
                    raise UserError(
                        f"{p}: column {header[j]!r} has median {med:g}: looks like "
                        "millivolts; give cell voltages in V"
                    )
        extra: dict[str, FloatArray] = {}
        for j, name in enumerate(header):
            if j in used or not name:
                continue
            arr = (
                np.ascontiguousarray(fast[:, j])
                if fast is not None
                else _parse_column(cells_of(j), name, p, row0 + 2, False)
            )
            if arr is not None:
                extra[name] = arr
        piece = TesterData(
            t_s=t, current_A=current, cell_voltages_V=volts,
            cell_names=[header[j] for j in lay.cell_cols],
            temperature_C=required("temperature_C") if has_temp else None,
            extra=extra, source=str(p),
        )  # fmt: skip
        row0 += len(body)
        if held is not None:
            piece = _join(held, piece)
        # Equal times: keep the LAST row of each run. A tester logs the end of the old step and
        # the start of the new one at the same instant; the new step's current is what flows
        # until the next row (the engine holds a sample's current over the following interval),
        # and its voltage is the response to it. An average would invent a current that never
        # flowed.
        keep = np.diff(piece.t_s) != 0.0
        held = _take(piece, slice(piece.n_samples - 1, None))
        out = _take(_take(piece, slice(0, piece.n_samples - 1)), keep)
        out = TesterData(**{**out.__dict__, "merged_repeats": int(keep.size - keep.sum()),
                            "time_restarts": tuple(restarts),
                            "missing_values": missing})  # fmt: skip
        if out.n_samples or out.merged_repeats or out.time_restarts or out.missing_values:
            yield out
    if held is None:
        raise UserError(f"{p}: header only, no data rows")
    yield held


def read_tester_csv(
    path: str | Path,
    *,
    charge_positive: bool = False,
    columns: Mapping[str, ColumnMap] | None = None,
    missing_ok: bool = False,
) -> TesterData:
    """Load a tester CSV (see the module docstring) into memory: the pieces of
    :func:`iter_tester_csv` joined (an extra column is kept when numeric in every row).

    Parameters
    ----------
    path : str or Path
        ``.csv`` or ``.csv.gz`` file.
    charge_positive : bool
        The file counts charge current positive: the current's sign is flipped.
    columns : mapping of canonical name to ColumnMap, or None
        Where ``t_s``, ``current_A``, ``voltage_V``, ``v_cell_NN`` or ``temperature_C`` come
        from in an export with other names (applied before the rules above), with a unit scale.
    missing_ok : bool
        An empty or NaN current, voltage or temperature is NaN, counted in ``missing_values``
        (``bmsid identify``); False: an error, as every reading is needed (``bmsid fit-ocv``).

    Raises
    ------
    UserError
        A missing/empty file, missing columns, bad rows, time that goes back (other than a
        restart of the clock), and values that look like mV or mA.
    """
    pieces = list(
        iter_tester_csv(
            path, charge_positive=charge_positive, columns=columns, missing_ok=missing_ok
        )
    )
    data = pieces[0]
    for piece in pieces[1:]:
        data = _join(data, piece)
    merged = sum(piece.merged_repeats for piece in pieces)
    restarts = tuple(n for piece in pieces for n in piece.time_restarts)
    missing = sum(piece.missing_values for piece in pieces)
    if merged:
        log.info("%s: merged %d rows with repeated timestamps", path, merged)
    return TesterData(**{**data.__dict__, "merged_repeats": merged, "time_restarts": restarts,
                         "missing_values": missing})  # fmt: skip


def write_tester_csv(data: TesterData, path: str | Path) -> None:
    """Write ``data`` in the format ``read_tester_csv`` reads (gzip when the name ends in .gz)."""
    names = ["t_s", "current_A", *data.cell_names]
    cols = [data.t_s, data.current_A, *data.cell_voltages_V.T]
    if data.temperature_C is not None:
        names.append("temperature_C")
        cols.append(data.temperature_C)
    for k, v in data.extra.items():
        names.append(k)
        cols.append(v)
    buf = io.StringIO()
    np.savetxt(buf, np.column_stack(cols), delimiter=",", fmt="%.10g")
    text = ",".join(names) + "\n" + buf.getvalue()
    p = Path(path)
    if p.name.lower().endswith(".gz"):
        with gzip.open(p, "wt", encoding="utf-8") as fh:
            fh.write(text)
    else:
        p.write_text(text, encoding="utf-8")


@dataclass(frozen=True)
class OcvPoints:
    """One (SOC, OCV) column pair of a rest-point table: SOC as a fraction, OCV in V.

    ``branch`` is "discharge" or "charge" when the column names say so, else None.
    """

    branch: str | None
    soc: FloatArray
    ocv_V: FloatArray


def read_ocv_points(path: str | Path) -> list[OcvPoints]:
    """Read a rest-point table: a header and column pairs (SOC, OCV), one pair per branch.

    A pair's branch comes from its names ("discharge"/"charge"); SOC is in percent when its name
    says "percent" or any value exceeds 1.5, else a fraction. A pair may be blank on some lines
    (branches of different lengths), but never only half of it.
    """
    p = Path(path)
    lines = [ln for ln in _read_text(p).splitlines()]
    while lines and not lines[-1].strip():
        lines.pop()
    if len(lines) < 2:
        raise UserError(f"{p}: no rest points (need a header and data lines)")
    header = [h.strip() for h in lines[0].split(",")]
    if len(header) % 2 or not all("soc" in h.lower() for h in header[::2]):
        raise UserError(
            f"{p}: expected column pairs SOC,OCV (e.g. SOC_percent,OCV_V); "
            f"found: {', '.join(header)}"
        )
    pairs: list[OcvPoints] = []
    for j in range(0, len(header), 2):
        names = (header[j] + " " + header[j + 1]).lower()
        branch = "discharge" if "discharge" in names else "charge" if "charge" in names else None
        zs: list[float] = []
        vs: list[float] = []
        for n, line in enumerate(lines[1:], start=2):
            parts = [s.strip() for s in line.split(",")]
            if len(parts) != len(header):
                raise UserError(f"{p}: line {n} does not have the {len(header)} header fields")
            a, b = parts[j], parts[j + 1]
            if not a and not b:
                continue
            try:
                z, v = float(a), float(b)
            except ValueError:
                raise UserError(f"{p}: line {n}: {header[j]}/{header[j + 1]} not numeric") from None
            if not (np.isfinite(z) and np.isfinite(v)):
                raise UserError(f"{p}: line {n}: NaN or infinite value")
            zs.append(z)
            vs.append(v)
        soc = np.asarray(zs, dtype=np.float64)
        ocv = np.asarray(vs, dtype=np.float64)
        if soc.size == 0:
            raise UserError(f"{p}: column pair {header[j]},{header[j + 1]} is empty")
        if "percent" in header[j].lower() or "%" in header[j] or float(np.max(soc)) > 1.5:
            soc = soc / 100.0
        if float(np.median(ocv)) > MAX_PLAUSIBLE_CELL_VOLTAGE_V:
            raise UserError(f"{p}: {header[j + 1]} looks like millivolts; give volts")
        pairs.append(OcvPoints(branch=branch, soc=soc, ocv_V=ocv))
    return pairs
