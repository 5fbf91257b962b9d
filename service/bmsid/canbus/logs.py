"""candump logs in and out, and battery-tester data -> frames (``bmsid make-log``).

Two candump text formats are read, chosen per line:

- the log file format of ``candump -l`` / ``-L``: ``(1600000000.123456) can0 123#1122`` (read by
  python-can's ``CanutilsLogReader``; error frames of every class are kept as error frames,
  with their channel);
- the console format of ``candump``: ``  can0  123   [2]  11 22``, optionally preceded by a
  ``-ta``/``-tz`` timestamp ``(1600000000.123456)`` or a ``-tA`` date; ``remote request``,
  ``ERRORFRAME`` and ``-a`` ASCII columns are understood. Without timestamps every frame gets
  ``timestamp=0.0``.

``-td`` (delta) timestamps, the time since the previous frame, are told once and summed into
the time since the first frame (python-can's reader takes every timestamp as absolute); ``-tz``
(zero-based) ones are read as they are.

Malformed lines are skipped, counted and logged (thinning out: 1st, 10th, 100th, ...).
"""

from __future__ import annotations

import datetime as dt
import gzip
import itertools
import logging
import math
import re
from collections import deque
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

import can
import cantools
import numpy as np
import numpy.typing as npt

from bmsid.canbus.codec import encode_saturating
from bmsid.canbus.frames_to_samples import FrameToSamples, RepeatFilter
from bmsid.canbus.mapping import BusMapping, ListedGroup, MultiplexedGroup
from bmsid.errors import UserError
from bmsid.samples import Sample

log = logging.getLogger(__name__)

CAN_ERR_FLAG = 0x20000000
_HEX = "[0-9A-Fa-f]"
_LOGFILE_RE = re.compile(
    rf"^\(\d+\.\d+\)\s+\S+\s+(?P<id>{_HEX}{{3}}|{_HEX}{{8}})#"
    rf"(?:R\d*|#{_HEX}(?:{_HEX}{{2}}){{0,64}}|(?:{_HEX}{{2}}){{0,8}})(?:\s+[RTrt])?$"
)
_CONSOLE_RE = re.compile(
    r"^(?:\((?P<ts>[0-9]{4}-[0-9]{2}-[0-9]{2} [0-9:.]+|[0-9]+\.[0-9]+)\)\s+)?"
    rf"(?P<chan>\S+)\s+(?P<id>{_HEX}{{3}}|{_HEX}{{8}})\s+\[(?P<dlc>\d{{1,2}})\]"
    r"(?P<rest>.*)$"
)
_HEX_BYTES = re.compile(f"(?:{_HEX}{{2}})*")
_CONSOLE_BYTES_RE = re.compile(rf"^\s*((?:{_HEX}{{2}}\s*)*)(?:'.*')?\s*(ERRORFRAME.*)?$")


#: Per log file, the counts already told of per kind (skipped lines, the decoder's notes): an
#: offline run reads a log in several passes (checks, start values, the run), and each pass
#: would tell the same lines again; a pass tells only counts beyond the ones told.
_TOLD: dict[str, dict[str, int]] = {}


def told_counts(path: str | Path) -> dict[str, int]:
    """The counts told of for ``path`` in this process, per kind (shared, mutable)."""
    return _TOLD.setdefault(str(Path(path).resolve()), {})


class _SkipCounter:
    def __init__(self, path: Path) -> None:
        self.path = path
        self.n = 0
        self._told = told_counts(path)

    def skip(self, lineno: int, why: str) -> None:
        self.n += 1
        if self.n == 10 ** (len(str(self.n)) - 1) and self.n > self._told.get("skipped", 0):
            self._told["skipped"] = self.n
            log.warning(
                "%s:%d: skipped (%s); %d lines skipped so far", self.path, lineno, why, self.n
            )


def _parse_console(line: str) -> can.Message | None:
    m = _CONSOLE_RE.match(line.strip())
    if m is None:
        return None
    ident = m["id"]
    can_id = int(ident, 16)
    ts_text = m["ts"]
    timestamp = 0.0
    if ts_text:
        if "-" in ts_text:
            timestamp = dt.datetime.fromisoformat(ts_text).timestamp()
        else:
            timestamp = float(ts_text)
    dlc = int(m["dlc"])
    rest = m["rest"]
    if "remote request" in rest:
        return can.Message(
            timestamp=timestamp,
            arbitration_id=can_id & 0x1FFFFFFF,
            is_extended_id=len(ident) == 8,
            is_remote_frame=True,
            dlc=dlc,
            channel=m["chan"],
        )
    b = _CONSOLE_BYTES_RE.match(rest)
    if b is None:
        return None
    data = bytes.fromhex(b[1].replace(" ", ""))
    if len(data) != dlc or dlc > 64:
        return None
    if (len(ident) == 8 and can_id & CAN_ERR_FLAG) or b[2]:
        return can.Message(
            timestamp=timestamp,
            is_error_frame=True,
            arbitration_id=can_id & 0x1FFFFFFF,
            data=data[:8],
            channel=m["chan"],
        )
    # candump prints FD lengths as two digits ("[08]", "[12]") and classic ones as one ("[8]")
    is_fd = len(m["dlc"]) == 2
    if dlc > 8 and not is_fd:
        return None
    return can.Message(
        timestamp=timestamp,
        arbitration_id=can_id,
        is_extended_id=len(ident) == 8,
        is_fd=is_fd,
        data=data,
        channel=m["chan"],
    )


def _logfile_lines(
    lines: Iterable[tuple[int, str]], skipped: _SkipCounter, errors: deque[can.Message]
) -> Iterator[str]:
    """The valid lines for python-can; an error frame's line is also built into ``errors``."""
    for lineno, line in lines:
        m = _LOGFILE_RE.match(line)
        if m is None:
            skipped.skip(lineno, "not a candump log line")
            continue
        ident = m["id"]
        if len(ident) == 8 and int(ident, 16) & CAN_ERR_FLAG:
            # python-can only recognises the bus-error class and drops the channel (its error
            # frames were filed under "None"): built here, python-can reads a placeholder
            ts, chan, frame = line.split()[:3]
            data = frame.partition("#")[2]
            errors.append(
                can.Message(
                    timestamp=float(ts[1:-1]),
                    is_error_frame=True,
                    arbitration_id=int(ident, 16) & 0x1FFFFFFF,
                    data=bytes.fromhex(data)[:8] if _HEX_BYTES.fullmatch(data) else None,
                    channel=chan,
                )
            )
            yield f"{ts} {chan} {CAN_ERR_FLAG | 0x80:08X}#"
        else:
            yield line


def _logfile_frames(
    lines: Iterable[tuple[int, str]], skipped: _SkipCounter
) -> Iterator[can.Message]:
    """Frames of ``candump -l`` lines (python-can's reader, error frames as built above)."""
    errors: deque[can.Message] = deque()
    for msg in can.CanutilsLogReader(_logfile_lines(lines, skipped, errors)):  # type: ignore[arg-type]
        yield errors.popleft() if msg.is_error_frame else msg


#: Names of candump logs (a rotated or archived one gzipped), as inputs are told apart.
LOG_SUFFIXES = (".log", ".log.gz")


def is_candump_path(path: str | Path) -> bool:
    """A candump log by its name (``.log``, ``.log.gz``), else a tester CSV."""
    return str(path).lower().endswith(LOG_SUFFIXES)


def _lines_of(fh: Iterable[str], p: Path) -> Iterator[str]:
    """The file's lines; a gzip that is cut short (a log archived while still written) ends
    them with a warning, one that is no gzip at all is a UserError."""
    n = 0
    try:
        for n, line in enumerate(fh, start=1):  # noqa: B007 (n is read after the loop)
            yield line
    except gzip.BadGzipFile as exc:
        if n == 0:
            raise UserError(f"{p}: not a gzip file ({exc}): a plain log is named .log") from None
        log.warning(
            "%s: gzip data damaged after line %d (%s): the lines before are used", p, n, exc
        )
    except EOFError:
        log.warning("%s: gzip file cut short after line %d: the lines before are used", p, n)


#: Delta stamps read as absolute ones step back at every longer interval (a false
#: ``time_backwards`` per tick). A log is read as delta when its first frames step back at least
#: twice (once: a clock set back) on no wall clock (``-ta`` stamps are ~1.7e9 s); ``-tz`` and
#: ``make-log`` stamps never step back.
_DELTA_HEAD = 1000
_DELTA_MAX_S = 1e6


def _absolute_times(msgs: Iterator[can.Message], p: Path) -> Iterator[can.Message]:
    """``msgs`` with delta timestamps (``candump -td``) summed, in whole microseconds (exact)."""
    head = list(itertools.islice(msgs, _DELTA_HEAD))
    stamps = [m.timestamp for m in head]
    backs = sum(b < a for a, b in itertools.pairwise(stamps))
    if backs < 2 or max(stamps) >= _DELTA_MAX_S:
        yield from head
        yield from msgs
        return
    told = told_counts(p)
    if not told.get("delta_timestamps"):
        told["delta_timestamps"] = 1
        log.warning(
            "%s: relative timestamps (candump -td: each the time since the previous frame): "
            "summed into the time since the first frame",
            p,
        )
    us = 0
    for m in itertools.chain(head, msgs):
        us += round(m.timestamp * 1e6)
        m.timestamp = us / 1e6
        yield m


def read_log(path: str | Path) -> Iterator[can.Message]:
    """Frames of a candump log (``-l``/``-L`` file or console output; gzipped when its name
    ends in ``.gz``), in file order; delta timestamps (``-td``) summed from 0 s."""
    p = Path(path)
    return _absolute_times(_frames_of(p), p)


def _frames_of(p: Path) -> Iterator[can.Message]:
    try:
        if p.name.lower().endswith(".gz"):  # closed by the with below
            fh = gzip.open(p, "rt", encoding="utf-8", errors="replace")  # noqa: SIM115
        else:
            fh = p.open(encoding="utf-8", errors="replace")
    except OSError as exc:
        raise UserError(f"cannot read CAN log {p}: {exc.strerror}") from None
    skipped = _SkipCounter(p)
    with fh:
        pending: list[tuple[int, str]] = []
        for lineno, raw in enumerate(_lines_of(fh, p), start=1):
            line = raw.strip()
            if not line or line.startswith("#"):
                continue
            if "#" in line and line.startswith("("):
                pending.append((lineno, line))
                if len(pending) >= 1024:
                    yield from _logfile_frames(pending, skipped)
                    pending = []
                continue
            if pending:
                yield from _logfile_frames(pending, skipped)
                pending = []
            msg = None
            try:
                msg = _parse_console(line)
            except ValueError:
                msg = None
            if msg is None:
                skipped.skip(lineno, "not a candump line")
                continue
            yield msg
        if pending:
            yield from _logfile_frames(pending, skipped)
    told = told_counts(p)
    if skipped.n > told.get("skipped_total", 0):
        told["skipped_total"] = skipped.n
        log.warning("%s: %d malformed lines skipped in total", p, skipped.n)


def write_log(path: str | Path, messages: Iterable[can.Message], channel: str = "can0") -> None:
    """Write ``candump -l`` format (readable by ``canplayer`` and :func:`read_log`)."""
    writer = can.CanutilsLogWriter(str(path), channel=channel)
    try:
        for msg in messages:
            msg.channel = channel
            writer.on_message_received(msg)
    finally:
        writer.stop()


# --- tester data -> frames ---------------------------------------------------------------------

FloatArray = npt.NDArray[np.float64]


def _resample(
    t_s: FloatArray, current_A: FloatArray, v: FloatArray, temps: FloatArray | None, rate_hz: float
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray | None]:
    grid = np.arange(t_s[0], t_s[-1] + 1e-9, 1.0 / rate_hz)
    cur = np.interp(grid, t_s, current_A)
    vv = np.column_stack([np.interp(grid, t_s, v[:, j]) for j in range(v.shape[1])])
    tt = None if temps is None else np.interp(grid, t_s, temps)
    return grid, cur, vv, tt


def csv_to_messages(
    t_s: npt.ArrayLike,
    current_A: npt.ArrayLike,
    cell_voltages_V: npt.ArrayLike,
    mapping: BusMapping,
    rate_hz: float | None = None,
    *,
    temperature_C: npt.ArrayLike | None = None,
    t0_s: float = 0.0,
) -> Iterator[can.Message]:
    """Frames of one tick per row (or per ``1/rate_hz`` s, linearly interpolated) in ``mapping``.

    Order within a tick: the current/counter frame, the temperatures, then the cell frames; all
    frames of a tick carry the tick's time ``t0_s + t``. Values outside a signal's range are
    clamped (logged once with a count); NaN is sent as the signal's not-available value.
    """
    t = np.asarray(t_s, dtype=np.float64)
    cur = np.asarray(current_A, dtype=np.float64)
    v = np.asarray(cell_voltages_V, dtype=np.float64)
    if v.ndim == 1:
        v = v[:, None]
    temps = None if temperature_C is None else np.asarray(temperature_C, dtype=np.float64)
    if not (t.shape[0] == cur.shape[0] == v.shape[0]) or t.shape[0] == 0:
        raise UserError("t_s, current_A and cell_voltages_V need the same, non-zero length")
    if v.shape[1] > mapping.max_cells():
        raise UserError(
            f"{v.shape[1]} cells; mapping {mapping.name!r} carries {mapping.max_cells()}"
        )
    if rate_hz is not None:
        if not rate_hz > 0:
            raise UserError(f"--rate-hz must be > 0, got {rate_hz}")
        t, cur, v, temps = _resample(t, cur, v, temps, rate_hz)
    db = mapping.database()
    cm = mapping.current
    sign = 1.0 if cm.positive == "discharge" else -1.0
    counter_modulo = 0
    if mapping.counter is not None:
        sig = db.get_message_by_name(mapping.counter.message).get_signal_by_name(
            mapping.counter.signal
        )
        counter_modulo = 1 << int(sig.length)
    cell_frames = _group_frames(mapping.cells, v.shape[1])
    temp_frames: list[_FrameLayout] = []
    if temps is not None and mapping.temperatures is not None:
        temps = temps[:, None]
        temp_frames = _group_frames(mapping.temperatures, 1)
    n_saturated = 0
    for k in range(t.shape[0]):
        ts = t0_s + float(t[k])
        head: dict[str, dict[str, float]] = {
            cm.message: {cm.signal: (sign * cur[k] - cm.offset) / cm.scale}
        }
        if mapping.counter is not None:
            head.setdefault(mapping.counter.message, {})[mapping.counter.signal] = float(
                k % counter_modulo
            )
        frames = list(head.items())
        if temps is not None:  # before the cells: the last cell frame completes the tick
            frames += [(f.message, f.values(temps[k])) for f in temp_frames]
        frames += [(f.message, f.values(v[k])) for f in cell_frames]
        for msg_name, vals in frames:
            message = db.get_message_by_name(msg_name)
            data, sat = encode_saturating(message, vals)
            if sat and n_saturated == 0:
                log.warning("t=%.3f s: %s saturated at the DBC range", ts, ", ".join(sat))
            n_saturated += len(sat)
            yield can.Message(
                timestamp=ts,
                arbitration_id=int(message.frame_id),
                is_extended_id=bool(message.is_extended_frame),
                is_fd=bool(message.is_fd),
                data=data,
            )
    if n_saturated:
        log.warning("%d values saturated at their DBC range in total", n_saturated)


class _FrameLayout:
    """One frame of a value group: which item goes into which signal (decoded units)."""

    def __init__(
        self, message: str, slots: list[tuple[str, int, float, float]], mux: tuple[str, int] | None
    ) -> None:
        self.message = message
        self.slots = slots  # (signal, item index, scale, offset)
        self.mux = mux

    def values(self, items: FloatArray) -> dict[str, float]:
        out = {sig: (float(items[i]) - offset) / scale for sig, i, scale, offset in self.slots}
        if self.mux is not None:
            out[self.mux[0]] = float(self.mux[1])
        return out


def _group_frames(group: MultiplexedGroup | ListedGroup, n: int) -> list[_FrameLayout]:
    if isinstance(group, ListedGroup):
        by_msg: dict[str, list[tuple[str, int, float, float]]] = {}
        for i, ref in enumerate(group.signals[:n]):
            by_msg.setdefault(ref.message, []).append((ref.signal, i, ref.scale, ref.offset))
        return [_FrameLayout(msg, slots, None) for msg, slots in by_msg.items()]
    stride = len(group.signals)
    return [
        _FrameLayout(
            group.message,
            [
                (sig, g * stride + k, group.scale, group.offset)
                for k, sig in enumerate(group.signals)
                if g * stride + k < n
            ],
            (group.multiplexer, g),
        )
        for g in range(math.ceil(n / stride))
    ]


# --- what a log holds: channels, identifiers, cells ------------------------------------------

#: A cell index counts as present when at least this share of the frames that carry it hold a
#: valid voltage (the DBC's range, above ``_MIN_CELL_V``): padding of a last, partly used group
#: is sent as not-available, and some BMSs send 0 V for slots without a cell.
_PRESENT_SHARE = 0.5
_MIN_CELL_V = 0.5
_IDS_LISTED = 8


@dataclass
class ChannelSummary:
    """The frames of one CAN channel of a log.

    ``ids`` counts frames per (arbitration id, extended); ``mapped`` counts the frames whose id
    the mapping decodes (current, counter, cells, temperatures), ``wrong_dlc`` and ``repeated``
    those of them of another length than the DBC's or repeating a frame at its timestamp
    (dropped as :class:`FrameToSamples` drops them);
    ``cell_valid`` and ``cell_seen`` count, per cell index (0-based), the frames with a valid
    voltage for it and all frames that carried a slot for it.
    """

    frames: int = 0
    mapped: int = 0
    wrong_dlc: int = 0
    repeated: int = 0
    ids: dict[tuple[int, bool], int] = field(default_factory=dict)
    cell_valid: dict[int, int] = field(default_factory=dict)
    cell_seen: dict[int, int] = field(default_factory=dict)
    repeats: RepeatFilter = field(default_factory=RepeatFilter, repr=False, compare=False)

    @property
    def cells(self) -> list[int]:
        """Cell indices (0-based) present in this channel (see ``_PRESENT_SHARE``)."""
        return sorted(
            c for c, n in self.cell_seen.items() if self.cell_valid.get(c, 0) >= _PRESENT_SHARE * n
        )

    @property
    def n_cells(self) -> int:
        """Cells of the pack as the log shows them: the highest present index + 1 (0: none)."""
        cells = self.cells
        return cells[-1] + 1 if cells else 0

    def text(self, name: str) -> str:
        ids = sorted(self.ids.items(), key=lambda kv: kv[0])
        shown = ", ".join(f"0x{i:0{8 if ext else 3}X} x{n}" for (i, ext), n in ids[:_IDS_LISTED])
        more = f", ... ({len(ids) - _IDS_LISTED} more ids)" if len(ids) > _IDS_LISTED else ""
        return (
            f"{name}: {self.frames} frames, {len(ids)} id(s) ({shown}{more}); "
            f"{self.decoded} decoded by the mapping{self._dropped()}, "
            f"{self.n_cells} cell(s)"
        )

    @property
    def decoded(self) -> int:
        """Frames of the mapping that reach the decoder (not dropped before it)."""
        return self.mapped - self.wrong_dlc - self.repeated

    def _dropped(self) -> str:
        """The mapped frames not decoded, by why (empty when none)."""
        why = [
            (self.wrong_dlc, "with a wrong DLC"),
            (self.repeated, "repeated at the same timestamp"),
        ]
        told = ", ".join(f"{n} {what}" for n, what in why if n)
        return f" ({told}: dropped)" if told else ""


@dataclass(frozen=True)
class LogSummary:
    """What a candump log holds, per channel (see :func:`summarize_log`)."""

    path: str
    mapping: str
    channels: dict[str, ChannelSummary]

    @property
    def mapped_channels(self) -> list[str]:
        """Channels carrying frames the mapping decodes, in name order."""
        return sorted(c for c, s in self.channels.items() if s.mapped)

    def text(self) -> str:
        """One line: every channel's frames, ids and cells."""
        if not self.channels:
            return f"{self.path}: no CAN frames"
        parts = "; ".join(s.text(c) for c, s in sorted(self.channels.items()))
        return f"{Path(self.path).name} holds {parts}"


#: signal, item index (listed) or offset in its group (multiplexed), scale, offset, DBC min, max
_CellSlot = tuple[str, int, float, float, float, float]


@dataclass
class _CellFrame:
    """A cell-voltage message: its multiplexer signal (None when listed) and voltage slots."""

    message: cantools.database.can.Message
    mux: str | None
    slots: list[_CellSlot] = field(default_factory=list)


def _cell_frames(mapping: BusMapping) -> dict[tuple[int, bool], _CellFrame]:
    """The mapping's cell-voltage messages by (arbitration id, extended)."""
    db = mapping.database()
    group = mapping.cells
    out: dict[tuple[int, bool], _CellFrame] = {}

    def add(
        msg_name: str, mux: str | None, sig_name: str, item: int, sc: float, off: float
    ) -> None:
        msg = db.get_message_by_name(msg_name)
        sig = msg.get_signal_by_name(sig_name)
        eps = abs(float(sig.scale)) * 1e-6  # as FrameToSamples: decoded floats may round
        lo = -math.inf if sig.minimum is None else float(sig.minimum) - eps
        hi = math.inf if sig.maximum is None else float(sig.maximum) + eps
        key = (int(msg.frame_id), bool(msg.is_extended_frame))
        out.setdefault(key, _CellFrame(msg, mux)).slots.append((sig_name, item, sc, off, lo, hi))

    if isinstance(group, ListedGroup):
        for i, ref in enumerate(group.signals):
            add(ref.message, None, ref.signal, i, ref.scale, ref.offset)
    else:
        for k, name in enumerate(group.signals):
            add(group.message, group.multiplexer, name, k, group.scale, group.offset)
    return out


def mapped_ids(mapping: BusMapping) -> set[tuple[int, bool]]:
    """(arbitration id, extended) of every frame the mapping decodes."""
    return set(_mapped_lengths(mapping))


def _mapped_lengths(mapping: BusMapping) -> dict[tuple[int, bool], int]:
    """The DBC's data length (bytes) of every frame the mapping decodes, by (id, extended)."""
    db = mapping.database()
    names = {mapping.current.message}
    if mapping.counter is not None:
        names.add(mapping.counter.message)
    for group in (mapping.cells, mapping.temperatures):
        if isinstance(group, ListedGroup):
            names.update(ref.message for ref in group.signals)
        elif isinstance(group, MultiplexedGroup):
            names.add(group.message)
    msgs = [db.get_message_by_name(n) for n in names]
    return {(int(m.frame_id), bool(m.is_extended_frame)): int(m.length) for m in msgs}


def summarize_log(path: str | Path, mapping: BusMapping, *, cells: bool = True) -> LogSummary:
    """Channels, frame counts, ids and the cells whose voltages a candump log carries.

    One pass over the log (error and remote frames count as frames, not as ids). A cell frame
    is decoded with the DBC only to see which cell indices hold a valid voltage, so the count
    does not depend on a guessed ``n_cells``; ``cells=False`` skips that decoding (most of the
    pass's time) when only the channels matter. Raises ``UserError`` for an unreadable file.
    """
    cell_frames = _cell_frames(mapping)
    known = _mapped_lengths(mapping)
    channels: dict[str, ChannelSummary] = {}
    limit = mapping.max_cells()
    for msg in read_log(path):
        ch = channels.setdefault(str(msg.channel), ChannelSummary())
        ch.frames += 1
        if msg.is_error_frame or msg.is_remote_frame:
            continue
        key = (int(msg.arbitration_id), bool(msg.is_extended_id))
        ch.ids[key] = ch.ids.get(key, 0) + 1
        if key not in known:
            continue
        ch.mapped += 1
        if len(msg.data) != known[key]:  # as FrameToSamples: dropped, not decoded
            ch.wrong_dlc += 1
            continue
        if ch.repeats.seen(msg):
            ch.repeated += 1
            continue
        cf = cell_frames.get(key) if cells else None
        if cf is None:
            continue
        try:
            values = cf.message.decode(bytes(msg.data), decode_choices=False)
        except Exception:  # a bad frame says nothing about the cells; FrameToSamples counts it
            continue
        if not isinstance(values, dict):
            continue
        base = 0
        if cf.mux is not None:
            g = values.get(cf.mux)
            if not isinstance(g, int | float):
                continue
            base = int(g) * len(cf.slots)
        for sig, k, sc, off, lo, hi in cf.slots:
            c = base + k
            raw = values.get(sig)
            if raw is None or c >= limit:
                continue
            ch.cell_seen[c] = ch.cell_seen.get(c, 0) + 1
            v = float(raw) if isinstance(raw, int | float) else math.nan
            if lo <= v <= hi and sc * v + off > _MIN_CELL_V:
                ch.cell_valid[c] = ch.cell_valid.get(c, 0) + 1
    return LogSummary(path=str(path), mapping=mapping.name, channels=channels)


def choose_channel(summary: LogSummary, channel: str | None, ask: str) -> str | None:
    """The channel of ``summary`` to read: ``channel``, else the only one carrying mapped frames
    (None when none does: decoding then says what is missing).

    ``ask`` tells the user how to pick one (``pass --channel NAME``). Raises ``UserError`` when
    the mapping's frames are on several channels and ``channel`` is None (two buses interleaved
    into one stream give samples of neither), or when ``channel`` carries none of them.
    """
    mapped = summary.mapped_channels
    if channel is None and len(mapped) > 1:
        counts = ", ".join(f"{c}: {summary.channels[c].mapped}" for c in mapped)
        raise UserError(
            f"{summary.path}: frames of mapping {summary.mapping!r} on {len(mapped)} CAN "
            f"channels ({counts} frames): {ask} (one of {', '.join(mapped)}); mixed they give "
            "samples of neither"
        )
    if channel is not None and channel not in mapped:
        held = ", ".join(sorted(summary.channels)) or "none"
        raise UserError(
            f"{summary.path}: no frames of mapping {summary.mapping!r} on channel {channel!r} "
            f"(the log holds: {held})"
        )
    return channel if channel is not None else (mapped[0] if mapped else None)


def samples_from_log(
    path: str | Path,
    mapping: BusMapping,
    n_cells: int,
    staleness_s: float = 2.0,
    *,
    channel: str | None = None,
) -> list[Sample]:
    """Every sample of a candump log in a list (:func:`iter_samples_from_log`)."""
    return list(iter_samples_from_log(path, mapping, n_cells, staleness_s, channel=channel))


def iter_samples_from_log(
    path: str | Path,
    mapping: BusMapping,
    n_cells: int,
    staleness_s: float = 2.0,
    *,
    channel: str | None = None,
) -> Iterator[Sample]:
    """Samples of a candump log, through :class:`FrameToSamples` exactly as the daemon does.

    Parameters
    ----------
    path : str or Path
        candump ``-l`` / ``-ta`` log.
    mapping : BusMapping
        Which frames and signals carry the current, cell voltages and temperatures.
    n_cells : int
        Cells of the pack (indices 0 .. n_cells-1 of the mapping's cell group).
    staleness_s : float
        Staleness limit of :class:`FrameToSamples`, s.
    channel : str or None
        Only frames of this CAN channel (e.g. ``can1``); None takes every frame, and then
        frames of the mapping on more than one channel are refused: two buses interleaved into
        one stream would give samples of neither.

    Raises
    ------
    UserError
        No sample decoded, no timestamps, several channels without ``channel``, or ``channel``
        absent from the log.
    """
    f2s = FrameToSamples(mapping, n_cells, staleness_s=staleness_s, told=told_counts(path))
    known = mapped_ids(mapping)
    n_out = 0
    any_time = False
    seen: dict[str, int] = {}  # frames of the mapping per channel
    for msg in read_log(path):
        name = str(msg.channel)
        if (msg.arbitration_id, bool(msg.is_extended_id)) in known:
            seen[name] = seen.get(name, 0) + 1
        if channel is not None and name != channel:
            continue
        any_time = any_time or msg.timestamp != 0.0
        for sample in f2s.feed(msg):
            n_out += 1
            yield sample
    for sample in f2s.flush():
        n_out += 1
        yield sample
    if channel is None and len(seen) > 1:
        raise UserError(
            f"{path}: frames of mapping {mapping.name!r} on {len(seen)} CAN channels "
            f"({', '.join(f'{c}: {n}' for c, n in sorted(seen.items()))}): pass --channel "
            f"NAME (one of {', '.join(sorted(seen))}); mixed they give samples of neither"
        )
    if channel is not None and channel not in seen:
        held = ", ".join(sorted(seen)) or "none"
        raise UserError(
            f"{path}: no frames of mapping {mapping.name!r} on channel {channel!r} "
            f"(channels with such frames: {held})"
        )
    if not n_out:
        raise UserError(
            f"{path}: no samples decoded with mapping {mapping.name!r} "
            f"(counters: {_nonzero(f2s.counters)})"
        )
    if not any_time:
        raise UserError(f"{path}: the log has no timestamps; record with candump -l or -ta")
    log.info("%s: %s", path, _nonzero(f2s.counters))
    _warn_stale(path, f2s.counters, staleness_s)


#: Cycles dropped for a stale current beyond this share are worth a warning: the estimates
#: see a fraction of the data (a current frame every 5 s against 1 s cell frames: 60 % dropped,
#: 18.9 mV against 2.3, and only the per-decade lines said it).
STALE_WARN_SHARE = 0.1


def _warn_stale(path: str | Path, counters: dict[str, int], staleness_s: float) -> None:
    stale, kept = counters["stale_current"], counters["samples"]
    told = told_counts(path)
    if stale <= STALE_WARN_SHARE * (stale + kept) or told.get("stale_share"):
        return
    told["stale_share"] = 1
    log.warning(
        "%s: %d of %d cell-voltage cycles (%.0f %%) dropped for a stale current (no current "
        "frame within %g s, or a lost one): the pack's current frames come too seldom or are "
        "lost; the estimates see the rest only",
        path, stale, stale + kept, 100.0 * stale / (stale + kept), staleness_s,
    )  # fmt: skip


def _nonzero(counters: dict[str, int]) -> str:
    return ", ".join(f"{k}={v}" for k, v in counters.items() if v)
