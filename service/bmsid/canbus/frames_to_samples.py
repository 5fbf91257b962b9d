"""CAN frames -> one :class:`~bmsid.samples.Sample` per tick.

Frames of one tick arrive at different times; these rules turn them into samples (the daemon
and ``bmsid identify`` on a candump log both go through :class:`FrameToSamples`):

1. **Current** is held from its latest valid frame.
2. **Cycle.** The first cell-voltage value after a tick opens a cycle. The cycle is *complete*, and
   a sample is emitted at once, when every cell ``0 .. n_cells-1`` has a value.
3. A cycle is *closed half-complete* when (a) a value arrives for a cell that already has one in
   the open cycle (the BMS has started its next cycle), (b) the sample counter changes (when the
   mapping names one; the counter frame closes the open cycle before its current is taken), (c) the
   cycle is older than ``staleness_s`` when a later frame arrives or :meth:`FrameToSamples.expire`
   is called, or (d) :meth:`FrameToSamples.flush` is called at the end of a log.
   A half-complete cycle is emitted with NaN for the missing cells and the flag ``incomplete``.
4. A sample is only emitted with a current no older than ``staleness_s`` at the sample time,
   nor older than usual: once the bus has shown its rhythm (:data:`_RHYTHM_MIN` cycles), more
   than :data:`LATE_PERIODS` of the longer of the current's frame period and the cycle period
   beyond the age the held current usually has at a close (each the low quantile
   :data:`_USUAL_Q` of its last :data:`_RHYTHM` values: lost frames lengthen intervals and
   ages, and up to half of them lost leave that quantile alone; a current sent faster than the
   cycles is judged on the cycle, so its jitter drops nothing). Older, its frame of this cycle
   was lost and the held value is a cycle old; paired with this cycle's voltages across a
   current step it is a sample the cell never produced (a 140 A step on a 1.2 mOhm cell:
   170 mV; 20 % of the frames of a 1 s log dropped at random gave 18.6 mV RMSE instead of 1.2).
   The rule holds for a current sent with, before or after the voltages, and for one sent
   slower or faster than them. Otherwise the cycle is dropped and counted as
   ``stale_current`` (there is no NaN convention for the current, and guessing one would
   corrupt the estimate).
5. ``t_s`` is the (monotonic-guarded) timestamp of the last cell frame of the cycle. Wall-clock
   steps backwards are absorbed into an offset (counted as ``time_backwards``).
6. Temperatures are held per sensor; NaN when never received or older than ``staleness_s``.

Bad frames never raise and never reach a sample; each kind is counted in
:attr:`FrameToSamples.counters` and logged at a rate that thins out (1st, 10th, 100th, ...):
error frames, remote frames, unknown identifiers, wrong DLC, multiplexer index outside the DBC or
outside ``n_cells``, values outside the signal's DBC range (that cell becomes NaN, flag
``out_of_range``), and any other decode error. A signal's not-available value (SNA,
``dbc/README.md``) is a missing reading, not a bad one: a cell's becomes NaN with the flag
``not_available``, a current's keeps the held one, each counted as ``not_available``; a
temperature's (a sensor of a group that is not fitted, as ``make-log`` writes them) is NaN,
neither counted nor logged. A frame repeated with the same identifier, data and timestamp (a log
recorded or merged twice) is counted as ``duplicate_frames`` and used once: a repeated cell frame
would otherwise close its cycle half-complete and add samples the bus never sent.
"""

from __future__ import annotations

import logging
import math
from collections import deque
from collections.abc import Mapping
from dataclasses import dataclass, field

import can
import cantools
import numpy as np

from bmsid.canbus.codec import raw_range
from bmsid.canbus.mapping import BusMapping, ListedGroup, MultiplexedGroup
from bmsid.errors import UserError
from bmsid.samples import Sample

log = logging.getLogger(__name__)

#: Rule 4: a held current this many of its frame periods older than its usual age at a close
#: missed its frame (3/4: a lost frame adds a whole period; bus jitter is far less).
LATE_PERIODS = 0.75
#: Closes and current frames the usual age and the period are taken over (at least, at most) ...
_RHYTHM_MIN, _RHYTHM = 8, 25
#: ... as this quantile.
_USUAL_Q = 0.2

#: Counters of frames that were rejected (their sum is the daemon's ``decode_errors``).
DECODE_ERROR_KINDS = (
    "unknown_id",
    "wrong_dlc",
    "mux_out_of_range",
    "error_frames",
    "remote_frames",
    "out_of_range",
    "not_available",  # no decode error, but in the daemon's decode_errors as before its split
    "decode_error",
)
COUNTER_NAMES = (
    "frames",
    "decoded",
    "duplicate_frames",
    *DECODE_ERROR_KINDS,
    "samples",
    "incomplete_cycles",
    "stale_current",
    "time_backwards",
)


@dataclass(frozen=True, slots=True)
class _Slot:
    """One mapped signal: its item index (or offset within a mux group) and SI conversion."""

    signal: str
    index: int
    scale: float
    offset: float
    lo: float
    hi: float
    sna: float  # the DBC's not-available value (physical; NaN: the signal has none)


@dataclass(slots=True)
class _Plan:
    """What to do with one arbitration id."""

    message: cantools.database.can.Message
    length: int
    counter: str | None = None
    current: _Slot | None = None
    cells: list[_Slot] = field(default_factory=list)
    cell_mux: str | None = None  # multiplexer signal when ``cells`` are offsets in a group
    temps: list[_Slot] = field(default_factory=list)
    temp_mux: str | None = None


def _low(values: deque[float]) -> float:
    """The :data:`_USUAL_Q` quantile of ``values`` (lower order statistic)."""
    return sorted(values)[int(_USUAL_Q * (len(values) - 1))]


def _bounds(sig: cantools.database.can.Signal) -> tuple[float, float, float]:
    """Physical range of ``sig`` (a millionth of a step wider) and its not-available value
    (``codec.raw_range``: NaN when it has none)."""
    eps = abs(float(sig.scale)) * 1e-6
    lo = -math.inf if sig.minimum is None else float(sig.minimum) - eps
    hi = math.inf if sig.maximum is None else float(sig.maximum) + eps
    sna = raw_range(sig).sna
    return lo, hi, math.nan if sna is None else sna * float(sig.scale) + float(sig.offset)


class RepeatFilter:
    """Tells exact repeats: a frame whose id and data came already with the same timestamp."""

    def __init__(self) -> None:
        self._t = math.nan
        self._keys: set[tuple[int, bool, bytes]] = set()  # frames at timestamp _t

    def seen(self, msg: can.Message) -> bool:
        """Whether ``msg`` repeats a frame given before at its timestamp (then it is no new one)."""
        key = (int(msg.arbitration_id), bool(msg.is_extended_id), bytes(msg.data))
        if msg.timestamp != self._t:
            self._t = msg.timestamp
            self._keys.clear()
        elif key in self._keys:
            return True
        self._keys.add(key)
        return False


class FrameToSamples:
    """Decode frames with cantools and assemble samples (rules in the module docstring)."""

    def __init__(
        self, mapping: BusMapping, n_cells: int, staleness_s: float = 2.0,
        told: dict[str, int] | None = None,
    ) -> None:  # fmt: skip
        if n_cells < 1 or n_cells > mapping.max_cells():
            raise UserError(
                f"n_cells={n_cells}: mapping {mapping.name!r} addresses 1..{mapping.max_cells()}"
            )
        if not staleness_s > 0:
            raise UserError(f"staleness_s must be > 0, got {staleness_s}")
        self.mapping = mapping
        self.n_cells = n_cells
        self.n_temps = mapping.max_temperatures()
        self.staleness_s = float(staleness_s)
        self.counters: dict[str, int] = dict.fromkeys(COUNTER_NAMES, 0)
        # counts already logged per kind by an earlier pass over the same log (logs.told_counts)
        self._told = told if told is not None else {}
        self._plans = self._build_plans(mapping)
        # held current and temperatures
        self._current_A = math.nan
        self._current_t = -math.inf
        self._current_dt: deque[float] = deque(maxlen=_RHYTHM)  # intervals of current frames
        self._close_age: deque[float] = deque(maxlen=_RHYTHM)  # held current's age at closes
        self._close_dt: deque[float] = deque(maxlen=_RHYTHM)  # intervals of closes (cycles)
        self._t_close = -math.inf
        self._temps = [math.nan] * self.n_temps
        self._temps_t = [-math.inf] * self.n_temps
        self._counter: int | None = None
        # the open cycle
        self._v = [math.nan] * n_cells
        self._seen = bytearray(n_cells)
        self._n_seen = 0
        self._t_first = 0.0
        self._t_last = 0.0
        self._cycle_counter: int | None = None
        self._flags: set[str] = set()
        # monotonic guard
        self._t_offset = 0.0
        self._t_prev = -math.inf
        self._repeats = RepeatFilter()

    # --- construction -------------------------------------------------------------------------

    def _build_plans(self, mapping: BusMapping) -> dict[tuple[int, bool], _Plan]:
        db = mapping.database()
        plans: dict[tuple[int, bool], _Plan] = {}

        def plan_for(name: str) -> _Plan:
            msg = db.get_message_by_name(name)
            key = (int(msg.frame_id), bool(msg.is_extended_frame))
            if key not in plans:
                plans[key] = _Plan(message=msg, length=int(msg.length))
            return plans[key]

        def slot(msg_name: str, sig_name: str, index: int, scale: float, offset: float) -> _Slot:
            sig = db.get_message_by_name(msg_name).get_signal_by_name(sig_name)
            lo, hi, sna = _bounds(sig)
            return _Slot(sig_name, index, scale, offset, lo, hi, sna)

        cur = mapping.current
        sign = 1.0 if cur.positive == "discharge" else -1.0
        plan_for(cur.message).current = slot(
            cur.message, cur.signal, 0, sign * cur.scale, sign * cur.offset
        )
        if mapping.counter is not None:
            plan_for(mapping.counter.message).counter = mapping.counter.signal

        def add_group(group: MultiplexedGroup | ListedGroup, kind: str) -> None:
            if isinstance(group, ListedGroup):
                for i, ref in enumerate(group.signals):
                    p = plan_for(ref.message)
                    getattr(p, kind).append(slot(ref.message, ref.signal, i, ref.scale, ref.offset))
                return
            p = plan_for(group.message)
            setattr(p, "cell_mux" if kind == "cells" else "temp_mux", group.multiplexer)
            for k, name in enumerate(group.signals):
                getattr(p, kind).append(slot(group.message, name, k, group.scale, group.offset))

        add_group(mapping.cells, "cells")
        if mapping.temperatures is not None:
            add_group(mapping.temperatures, "temps")
        return plans

    # --- bookkeeping --------------------------------------------------------------------------

    def _note(self, kind: str, detail: str, level: int = logging.WARNING) -> None:
        n = self.counters.get(kind, 0) + 1
        self.counters[kind] = n
        # 1, 10, 100, ...: logs thin out under a flood; a count an earlier pass told is not
        if n == 10 ** (len(str(n)) - 1) and n > self._told.get(kind, 0):
            self._told[kind] = n
            log.log(level, "%s: %s (%d so far)", kind, detail, n)

    def _time(self, timestamp: float) -> float:
        t = float(timestamp) + self._t_offset
        if t < self._t_prev:
            self._note("time_backwards", f"timestamp stepped back by {self._t_prev - t:.6f} s")
            self._t_offset += self._t_prev - t
            t = self._t_prev
        self._t_prev = t
        return t

    # --- public API ---------------------------------------------------------------------------

    def count_error_frame(self) -> None:
        """Count an error frame whose caller says it itself (the daemon's bus-off state line):
        in ``frames`` and ``error_frames`` as :meth:`feed` would, without a line of its own, so
        that a bus-off is one line in the log."""
        self.counters["frames"] += 1
        self.counters["error_frames"] += 1

    def feed(self, msg: can.Message) -> list[Sample]:
        """Take one frame; return the samples it completes (usually none or one). Never raises."""
        self.counters["frames"] += 1
        if msg.is_error_frame:
            on = "" if msg.channel is None else f" on {msg.channel}"
            self._note("error_frames", f"error frame{on} id=0x{msg.arbitration_id:X}")
            return []
        if msg.is_remote_frame:
            self._note("remote_frames", f"remote frame id=0x{msg.arbitration_id:X}")
            return []
        plan = self._plans.get((msg.arbitration_id, bool(msg.is_extended_id)))
        if plan is None:
            self._note("unknown_id", f"id=0x{msg.arbitration_id:X}", logging.INFO)
            return []
        data = bytes(msg.data)
        if len(data) != plan.length:
            self._note(
                "wrong_dlc",
                f"{plan.message.name}: {len(data)} bytes instead of {plan.length}",
            )
            return []
        if self._repeats.seen(msg):
            again = f"{plan.message.name}: the same frame again at t={msg.timestamp:.6f} s"
            self._note("duplicate_frames", again)
            return []
        try:
            values = plan.message.decode(data, decode_choices=False)
        except Exception as exc:  # cantools/bitstruct raise several types; none may escape
            kind = "mux_out_of_range" if "multiplexer" in str(exc) else "decode_error"
            self._note(kind, f"{plan.message.name}: {exc}"[:200])
            return []
        if not isinstance(values, dict):  # container messages are not mapped
            self._note("decode_error", f"{plan.message.name}: not a plain message")
            return []
        self.counters["decoded"] += 1
        return self._apply(plan, values, self._time(msg.timestamp))

    def expire(self, now_s: float) -> list[Sample]:
        """Close the open cycle if it is older than ``staleness_s`` at ``now_s`` (frame clock)."""
        out: list[Sample] = []
        if self._n_seen and now_s + self._t_offset - self._t_first > self.staleness_s:
            self._close(out)
        return out

    def flush(self) -> list[Sample]:
        """End of input: emit the open cycle half-complete (rule 3d), if there is one."""
        out: list[Sample] = []
        if self._n_seen:
            self._close(out)
        return out

    # --- assembly -----------------------------------------------------------------------------

    def _value(
        self, values: Mapping[str, object], s: _Slot, what: str, quiet_sna: bool = False
    ) -> float:
        raw = values.get(s.signal)
        v = float(raw) if isinstance(raw, int | float) else math.nan
        if v == s.sna:  # missing, not out of range; a temperature's: a sensor not fitted
            if not quiet_sna:
                self._note("not_available", f"{what} signal {s.signal} not available")
            return math.nan
        if not (s.lo <= v <= s.hi):  # also catches NaN
            self._note("out_of_range", f"{what} signal {s.signal}={raw!r}")
            return math.nan
        return s.scale * v + s.offset

    def _apply(self, plan: _Plan, values: Mapping[str, object], t: float) -> list[Sample]:
        out: list[Sample] = []
        if self._n_seen and t - self._t_first > self.staleness_s:
            self._close(out)
        if plan.counter is not None:
            c = values.get(plan.counter)
            if isinstance(c, int | float):
                if self._counter is not None and int(c) != self._counter and self._n_seen:
                    self._close(out)
                self._counter = int(c)
        if plan.current is not None:
            i = self._value(values, plan.current, "current")
            if not math.isnan(i):
                if 0.0 < t - self._current_t <= self.staleness_s:
                    self._current_dt.append(t - self._current_t)
                self._current_A, self._current_t = i, t
        if plan.temps:
            self._take_temps(plan, values, t)
        if plan.cells:
            self._take_cells(plan, values, t, out)
        return out

    def _group_base(
        self, plan: _Plan, values: Mapping[str, object], mux: str, stride: int, limit: int
    ) -> int:
        """First item index of the multiplexed group in ``values``; -1 when beyond ``limit``."""
        g = values.get(mux)
        base = int(g) * stride if isinstance(g, int | float) else limit
        if base >= limit:
            self._note("mux_out_of_range", f"{plan.message.name}: {mux}={g} beyond {limit} items")
            return -1
        return base

    def _take_temps(self, plan: _Plan, values: Mapping[str, object], t: float) -> None:
        base = 0
        if plan.temp_mux is not None:
            base = self._group_base(plan, values, plan.temp_mux, len(plan.temps), self.n_temps)
            if base < 0:
                return
        for s in plan.temps:
            j = base + s.index
            if j < self.n_temps:
                v = self._value(values, s, "temperature", quiet_sna=True)
                self._temps[j], self._temps_t[j] = v, t

    def _take_cells(
        self, plan: _Plan, values: Mapping[str, object], t: float, out: list[Sample]
    ) -> None:
        base = 0
        if plan.cell_mux is not None:
            base = self._group_base(plan, values, plan.cell_mux, len(plan.cells), self.n_cells)
            if base < 0:
                return
        n = self.n_cells
        idx = [base + s.index for s in plan.cells]
        if self._n_seen and any(j < n and self._seen[j] for j in idx):
            self._close(out)  # rule 3a: the next cycle has begun
        if not self._n_seen:
            self._t_first = t
            self._cycle_counter = self._counter
        for s, j in zip(plan.cells, idx, strict=True):
            if j >= n:
                continue  # padding of the last group beyond n_cells
            v = self._value(values, s, "cell voltage")
            if math.isnan(v):
                sna = values.get(s.signal) == s.sna
                self._flags.add("not_available" if sna else "out_of_range")
            self._v[j] = v
            self._seen[j] = 1
            self._n_seen += 1
        self._t_last = t
        if self._n_seen == n:
            self._close(out)

    def _late_limit_s(self) -> float:
        """The oldest the held current may be at this close (rule 4), s."""
        rhythm = (self._close_age, self._current_dt, self._close_dt)
        if min(len(d) for d in rhythm) < _RHYTHM_MIN:
            return self.staleness_s
        period = max(_low(self._current_dt), _low(self._close_dt))
        return min(self.staleness_s, _low(self._close_age) + LATE_PERIODS * period)

    def _close(self, out: list[Sample]) -> None:
        t = self._t_last
        if 0.0 < t - self._t_close <= self.staleness_s:
            self._close_dt.append(t - self._t_close)
        self._t_close = t
        if t - self._current_t <= self.staleness_s:
            self._close_age.append(t - self._current_t)
        if self._n_seen < self.n_cells:
            self._flags.add("incomplete")
            self._note(
                "incomplete_cycles",
                f"cycle at t={t:.3f} s closed with {self._n_seen}/{self.n_cells} cells",
            )
        age = t - self._current_t
        if age > self.staleness_s:
            self._note("stale_current", f"no current within {self.staleness_s} s of t={t:.3f} s")
        elif age > self._late_limit_s():
            self._note("stale_current", f"the current frame of the cycle at t={t:.3f} s was lost "
                       f"(the held one is {age:.3g} s old)")  # fmt: skip
        else:
            temps = None
            if self.n_temps:
                temps = np.array(
                    [
                        v if t - tt <= self.staleness_s else math.nan
                        for v, tt in zip(self._temps, self._temps_t, strict=True)
                    ],
                    dtype=np.float64,
                )
            out.append(
                Sample(
                    t_s=t,
                    current_A=self._current_A,
                    cell_voltages_V=np.array(self._v, dtype=np.float64),
                    temperatures_C=temps,
                    counter=self._cycle_counter,
                    flags=frozenset(self._flags),
                )
            )
            self.counters["samples"] += 1
        self._v = [math.nan] * self.n_cells
        self._seen = bytearray(self.n_cells)
        self._n_seen = 0
        self._flags = set()
