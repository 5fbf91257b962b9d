"""The estimator bank in its own process, so its swarm never holds the event loop's GIL.

The daemon's event loop must answer within 5 ms. A 96-cell bank with swarms running spends
milliseconds per sample in Python and numpy; in a thread of the daemon's process it competes
with the loop for the interpreter lock and the loop's lag grows with the load (measured: max
8-42 ms under a frame flood). In a child process the two only exchange pickled batches.

The child (:class:`BankHost`) owns everything the bank's output depends on: the bank, its
checkpoint, the MQTT sequence number and the JSON encoding of the messages. The parent
(:class:`BankWorker`) sends blocks of samples (:class:`SampleBlock`) and gets back estimates,
ready messages and counters. ``isolation="thread"`` runs the same host in one worker thread
instead (platforms without process spawning; tests compare the two).

Sequence numbers never repeat across restarts: the host reserves them in blocks in
``<pack_id>.seq`` (written before a block is used) and writes the exact value at a clean
stop, so a graceful restart continues contiguously and a crash (``kill -9``) leaves a gap
instead of reusing numbers that consumers may already have seen. A block that cannot be
reserved (a disk error, a file system gone read-only) is not used: the tick's messages are
withheld and counted (``mqtt_withheld``) until a reservation succeeds again, so a number is
never published unreserved. A sequence file that exists but cannot be read refuses the start:
the numbers already published are unknown. Only one daemon per pack uses these files (the
lock of :mod:`bmsid.daemon.statedir`, taken by the daemon before the worker starts). The lock
is the daemon's, so a worker must not outlive it: on Linux the kernel kills the worker the
moment the daemon dies (``PR_SET_PDEATHSIG``), before a checkpoint or ``.seq`` write of an
orphan could land on the files of the daemon started next.

A write to the state directory that fails (a checkpoint, a ``.seq`` reservation) is a state,
not only a count: until the same write succeeds again, the pack's health carries
:data:`~bmsid.publish.payloads.HEALTH_STATE_DIR` and the counters ``state_dir_failing`` = 1.

The worker process talks to the daemon over two pipes (calls, log records), not through
``ProcessPoolExecutor`` and ``multiprocessing.Queue``: those create 8 named POSIX semaphores
that only multiprocessing's resource tracker removes, and a SIGKILL of the whole service
(systemd's cgroup kill) took the tracker too and left them in ``/dev/shm`` at every crash.
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import contextlib
import ctypes
import dataclasses
import gc
import logging
import logging.handlers
import math
import multiprocessing
import os
import signal
import sys
import threading
import time
import traceback
from collections.abc import Callable
from dataclasses import dataclass, field
from multiprocessing.connection import Connection
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal

import numpy as np
import numpy.typing as npt

from bmsid.config.cell import CellConfig
from bmsid.daemon.checkpoint import (
    CheckpointKey,
    load_checkpoint,
    save_checkpoint,
    state_problem,
)
from bmsid.daemon.lone_cell_watch import WINDOW_S as LONE_WINDOW_S
from bmsid.daemon.lone_cell_watch import LoneCellWatch
from bmsid.daemon.start_refit import StartHead
from bmsid.daemon.statedir import atomic_write, quarantine
from bmsid.errors import UserError
from bmsid.estimate.start_fit import WINDOW_S
from bmsid.estimate.startvalues import (
    MIN_STEPS,
    StartValues,
    min_step_for,
    r0_misfit,
    start_values_from_record,
)
from bmsid.estimate.tuning import EstimatorTuning, Variant
from bmsid.estimate.types import Estimates
from bmsid.gates import GateConfig, InputGate
from bmsid.publish import payloads
from bmsid.publish.outbox import OutMessage
from bmsid.quiet_logs import quiet_libraries
from bmsid.samples import SampleBlock
from bmsid.threads import blas_threads, one_blas_thread

if TYPE_CHECKING:
    # Imported where the bank is built: with process isolation the daemon itself never loads
    # the estimator stack (scipy.signal alone adds ~65 MB of resident memory).
    from bmsid.estimate.bank import EstimatorBank

log = logging.getLogger(__name__)

Isolation = Literal["process", "thread"]
FloatArray = npt.NDArray[np.float64]
IntpArray = npt.NDArray[np.intp]
#: Sequence numbers reserved per write of the ``.seq`` file.
SEQ_BLOCK = 100_000
#: Longest the daemon holds samples to measure start values (and samples, whichever first).
PROBE_LIMIT_S = 1800.0
PROBE_LIMIT_SAMPLES = 200_000
#: How often the worker checks that the daemon still lives, s (where the kernel cannot
#: kill it with its parent: not Linux).
PARENT_POLL_S = 0.5
#: prctl(2) option: the signal a process gets when the thread that created it dies (Linux).
PR_SET_PDEATHSIG = 1
#: Longest wait for the worker process to end after ``close()`` asked it to, s.
CLOSE_TIMEOUT_S = 10.0
#: A call taking longer sends a heartbeat between ticks at most this often, s: the daemon's
#: watchdog tells a long call (a start-up probe releasing its samples) from a stuck one by it.
#: Far below any ``WatchdogSec`` that makes sense, and one small pickle a second at most.
HEARTBEAT_S = 1.0
#: What the worker process sends on its log pipe as a heartbeat (a log record otherwise).
HEARTBEAT = "heartbeat"
#: Ticks per bank call in a worker process of its own, where nothing waits for the interpreter
#: lock between ticks: the per-call glue (a block slice, the estimates' arrays, the tick
#: times) is paid once per 64 ticks, not per tick (a day of 1 s samples: 16.5 -> 7.6 s of
#: worker time, ``update`` fed 2,000-sample blocks). Milliseconds a tick for a large pack
#: with swarms: a call stays far below ``HEARTBEAT_S``.
CHUNK_TICKS_ALONE = 64


def _span_s(block: SampleBlock) -> float:
    """Sample time from the first to the last sample of ``block``, s (0 when empty)."""
    return float(block.t_s[-1] - block.t_s[0]) if len(block) else 0.0


def _log_now(n: int) -> bool:
    """Log the 1st, 10th, 100th, ... occurrence of a repeating failure only."""
    return bool(n == 10 ** (len(str(n)) - 1))


def samples_per_tick(t_s: FloatArray, id_period_s: float) -> int:
    """Samples per chunk fed to the bank: as many as one identification tick spans (>= 1).

    Args:
        t_s: the block's sample times, s, shape (n,).
        id_period_s: the bank's tick period, s.

    A tick (milliseconds for a large pack with swarms) is what holds the interpreter lock; the
    loop got it back after every tick when the bank was fed sample by sample, and chunks of one
    tick keep that cadence (at 10 Hz and 1 s ticks: 10 samples). The bank closes a tick half a
    sample early, so it ticks every ``round(id_period_s / dt)`` samples; the median sample
    period ``dt`` ignores gaps and jumps.
    """
    dt = np.diff(t_s)
    dt = dt[dt > 0]  # NaN and non-increasing times compare False
    if dt.size == 0:
        return 1
    return max(1, round(id_period_s / float(np.median(dt))))


def tick_samples(t_s: FloatArray, tick_t_s: FloatArray) -> IntpArray:
    """Index of the sample that completed each tick, shape (n_ticks,).

    Args:
        t_s: the sample times fed to the bank, s, shape (n,).
        tick_t_s: the times of the ticks it emitted, s, in order, shape (n_ticks,).

    A tick is emitted at a sample and carries its time; ticks come in sample order, so a
    pointer walks forward to the next sample of that time. A time base that jumps back repeats
    times later in the block, but a jump starts a new segment with a tick at the jump's sample,
    so the pointer is past every earlier sample of a repeated time when it looks for it.

    Raises:
        ValueError: a tick time matches no later sample (the bank broke its contract).
    """
    times = t_s.tolist()
    out = np.empty(tick_t_s.shape[0], dtype=np.intp)
    j = 0
    for k, t in enumerate(tick_t_s.tolist()):
        while j < len(times) and times[j] != t:
            j += 1
        if j == len(times):
            raise ValueError(f"tick at t={t!r} s matches no sample after the previous tick")
        out[k] = j
        j += 1
    return out


@dataclass(frozen=True)
class BankSpec:
    """Everything the host needs; picklable (sent to the child once)."""

    cell: CellConfig
    n_cells: int
    variant: Variant
    tuning: EstimatorTuning
    soc0: float | None
    restore: bool
    ckpt_path: Path
    ckpt_key: CheckpointKey
    pack_id: str
    topic_prefix: str
    mqtt_enabled: bool
    qos: int
    publish_period_s: float
    #: return every tick's estimates (live view, tests), not only the newest of a batch
    keep_all_estimates: bool = False
    #: plausibility gates before the bank (``bmsid.gates``)
    gates: GateConfig = field(default_factory=GateConfig)
    #: ``compiled`` (numba, where it compiles) or ``numpy`` window fits (``estimator.kernels``)
    kernels: str = "compiled"

    @property
    def seq_path(self) -> Path:
        return self.ckpt_path.with_name(f"{self.pack_id}.seq")


@dataclass(frozen=True)
class StartInfo:
    restored: bool
    seq: int
    t_s: float | None
    #: the bank's counters as restored (lifetime totals; empty on a fresh start)
    counters: dict[str, int] = field(default_factory=dict)


@dataclass(frozen=True)
class BatchResult:
    #: the ticks' estimates (all, or only the newest unless ``keep_all_estimates``)
    estimates: list[Estimates]
    messages: list[OutMessage]
    counters: dict[str, int]
    seq: int
    #: what the plausibility gates refused, missing and no-data cells (``GateState.report``)
    inputs: dict[str, Any] = field(default_factory=dict)
    #: how the bank's SOC started (``EstimatorBank.soc_init_method``)
    soc_init: str = "pending"


@dataclass
class BankHost:
    """Runs in the worker: bank updates, MQTT message encoding, checkpoints, sequence numbers."""

    spec: BankSpec
    bank: EstimatorBank = field(init=False)
    seq: int = 0
    counters: dict[str, int] = field(default_factory=dict)
    _seq_reserved: int = 0
    _last_pub_t: float = -float("inf")
    #: why the latest checkpoint / ``.seq`` write failed; None once one succeeds again
    _ckpt_error: str | None = None
    _seq_error: str | None = None

    #: start values measured on the first samples (None: the config's or the capacity rule's)
    start_values: StartValues | None = None
    #: the first samples, until their current steps measure R0 (or ``PROBE_LIMIT_S``): held
    #: from the bank while ``_probing``, and checked against the cell config either way
    _first: list[SampleBlock] | None = field(default_factory=list)
    _probing: bool = False
    _config_r0_ohm: float = 0.0
    #: a fresh start's first samples, for the start SOC fit (``daemon/start_refit.py``)
    _head: StartHead | None = None
    #: called between ticks of a long call, at most every HEARTBEAT_S (set by the worker)
    beat: Callable[[], None] = field(default=lambda: None, repr=False)
    _beat_t: float = 0.0
    #: the host runs in a thread of the daemon's process (``isolation="thread"``): one tick
    #: per bank call, the lock handed to the event loop after each; False in a worker process
    shares_gil: bool = True

    def __post_init__(self) -> None:
        # The window-fit kernel, chosen (and compiled or loaded) before any bank exists here,
        # fresh or restored: ``numpy`` where the sandbox forbids a JIT.
        from bmsid.estimate import jit  # noqa: PLC0415 (numba only where it runs)

        # The bank's process sets its own limit: a worker process starts without the daemon's,
        # and scipy's BLAS (the compiled kernels') on two threads made a 96-cell observer
        # update 100x slower on a busy 2-core machine (threads.py).
        one_blas_thread()
        log.debug("bank: BLAS threads %s", blas_threads())
        jit.select("numpy" if self.spec.kernels == "numpy" else None)
        self.bank = self._fresh_bank()
        # the config's own start R0 (or its capacity rule's), before any measured start value
        self._config_r0_ohm = float(np.median(self.bank.model.start("R0_ohm")))
        #: a fresh state: what a restored or saved one must look like (state_problem)
        self._reference = self.bank.state_dict()
        # Limits from the OCV curve, capacity and configured start R0 (v_frozen): the same
        # whatever start values the record then gives.
        limits = self.spec.gates.for_model(self.bank.model, self.spec.tuning.gap_s)
        self.gate = InputGate(limits, self.spec.n_cells)
        log.info("input gates: %s", limits.describe())
        self.counters = {
            "checkpoints": 0,
            "checkpoint_errors": 0,
            "checkpoints_refused": 0,
            "seq_file_errors": 0,
            "mqtt_withheld": 0,
        }
        # A config without start values or bounds: measure them on the first samples, as
        # offline identification does on a record, before the estimators start.
        self._probing = self.spec.cell.initial is None or self.spec.cell.bounds is None
        # a fresh start: its first window refits it (the SOC too, unless configured)
        if self.spec.soc0 is not None or self.spec.cell.soc_init.policy == "ocv_at_rest":
            cell = self.spec.cell
            self._head = StartHead(cell.soc_init.rest_current_C * cell.capacity_Ah)
        self.counters["start_refits"] = 0
        self._lone = LoneCellWatch(self.spec.n_cells)

    def _fresh_bank(self) -> EstimatorBank:
        from bmsid.config.engine import build_bank  # noqa: PLC0415 (see TYPE_CHECKING)

        s = self.spec
        return build_bank(
            s.cell, s.n_cells, s.variant, s.tuning, soc0=s.soc0, start=self.start_values
        )

    def _measure_first(self, block: SampleBlock) -> tuple[SampleBlock, StartValues | None] | None:
        """Add ``block`` to the first samples; once their current steps measure the start
        values (or ``PROBE_LIMIT_S`` of samples passed): those samples and what they measured
        (None: too few steps), with a WARNING when that R0 and the cell config's start R0 are
        far apart (``r0_misfit``); before that, None."""
        assert self._first is not None
        if not self._first and self._probing:  # nothing is published meanwhile: say why
            log.info(
                "holding samples until %d current steps measure the start values (at most "
                "%.0f s of samples)",
                MIN_STEPS,
                PROBE_LIMIT_S,
            )
        self._first.append(block)
        seen = SampleBlock.concat(self._first)
        step_A = min_step_for(
            float(np.min(self.bank.model.capacity_Ah)), self.bank.tuning.excitation_C
        )
        found = start_values_from_record(seen.t_s, seen.current_A, seen.cell_voltages_V, step_A)
        if found is None and _span_s(seen) < PROBE_LIMIT_S and len(seen) < PROBE_LIMIT_SAMPLES:
            return None
        self._first = None
        why = None if found is None else r0_misfit(found, self._config_r0_ohm)
        if why is not None:
            log.warning("estimator.cell: %s", why)
        return seen, found

    def _end_probe(self, held: SampleBlock, found: StartValues | None) -> SampleBlock:
        """Start the bank from ``found`` (None: the fallback values); ``held`` is to feed."""
        self._probing = False
        span = _span_s(held)
        self.start_values = found
        if found is None:
            log.warning(
                "no current steps in the first %.0f s: start values from the capacity rule and "
                "default bounds (put [initial] and [bounds] in the cell config to avoid this)",
                span,
            )
        else:
            log.info("start values from the first %.0f s of samples: %s", span, found.describe())
        self.bank = self._fresh_bank()
        return held

    # ------------------------------------------------------------------ start
    def start(self) -> StartInfo:
        """Restore the checkpoint (if allowed and matching) and the sequence high-water mark."""
        t_s = None
        restored = False
        ck_seq = 0
        ck = load_checkpoint(self.spec.ckpt_path, self.spec.ckpt_key) if self.spec.restore else None
        if ck is not None:
            seq_raw, t_raw = ck.extra.get("seq", 0), ck.extra.get("t_s")
            # Its seq bounds the numbers published even when its state is unusable.
            if isinstance(seq_raw, int) and seq_raw >= 0:
                ck_seq = seq_raw
            try:
                sv = ck.extra.get("start_values")
                if sv is not None:  # the bank's normalisation depends on them: rebuild first
                    self.start_values = StartValues(**sv)
                    self.bank = self._fresh_bank()
                self.bank.load_state_dict(ck.state)
                problem = state_problem(self.bank.state_dict(), self._reference)
            except (ValueError, KeyError, TypeError) as exc:
                problem = f"inconsistent: {exc}"
            if problem is None and not (isinstance(seq_raw, int) and seq_raw >= 0):
                problem = f"inconsistent: seq {seq_raw!r}"
            if problem is None and not (
                t_raw is None or (isinstance(t_raw, float | int) and math.isfinite(t_raw))
            ):
                problem = f"non-finite sample time {t_raw!r}"
            if problem is not None:
                quarantine(self.spec.ckpt_path, "checkpoint", problem)
                self.start_values = None
                self.bank = self._fresh_bank()
            else:
                restored = True
                self._probing = False
                self._head = None  # the restore re-anchors from the voltage at restart
                t_s = float(t_raw) if t_raw is not None else None
        self.seq = max(ck_seq, self._read_seq_file())
        self._seq_reserved = self.seq
        counters = dict(self.bank.counters) if restored else {}
        return StartInfo(restored=restored, seq=self.seq, t_s=t_s, counters=counters)

    def _read_seq_file(self) -> int:
        """The reserved high-water mark; 0 when there is no file yet.

        Raises:
            UserError: the file exists but holds no number or cannot be read. Ignoring it
                (as before) restarted the numbering below what subscribers had seen.
        """
        path = self.spec.seq_path
        try:
            text = path.read_text(encoding="ascii", errors="replace").strip()
        except (FileNotFoundError, NotADirectoryError):
            return 0
        except OSError as exc:
            text, why = "", exc.strerror or type(exc).__name__
        else:
            if text.isdigit():
                return int(text)
            why = f"it holds {text[:20]!r}, not a number"
        raise UserError(
            f"sequence file {path} is unreadable ({why}): bmsid cannot tell which MQTT seq "
            "numbers were already published; write a number above every seq your subscribers "
            "have seen into it (or remove it, which restarts from the checkpoint's seq and may "
            "reuse numbers)"
        )

    def _write_seq_file(self, value: int) -> bool:
        path = self.spec.seq_path
        try:
            atomic_write(path, lambda fh: fh.write(f"{value}\n".encode("ascii")))
        except OSError as exc:
            self._seq_error = str(exc.strerror or exc)
            self.counters["seq_file_errors"] += 1
            n = self.counters["seq_file_errors"]
            if _log_now(n):
                log.error(
                    "sequence file %s cannot be written (%s; %d time(s)): MQTT data messages "
                    "are withheld until it can (mqtt_withheld counts them)",
                    path,
                    exc.strerror or exc,
                    n,
                )
            return False
        self._seq_error = None
        return True

    def _take_seqs(self, n: int) -> int | None:
        """The first of ``n`` consecutive reserved numbers, or None when no reservation
        could be persisted (then none are used: a crash could not tell they were)."""
        if self.seq + n > self._seq_reserved:
            target = self.seq + max(n, SEQ_BLOCK)
            if not self._write_seq_file(target):
                return None
            if self.counters["seq_file_errors"]:
                log.warning(
                    "sequence file %s written again: MQTT data messages resume at seq %d "
                    "(%d withheld so far)",
                    self.spec.seq_path,
                    self.seq,
                    self.counters["mqtt_withheld"],
                )
            self._seq_reserved = target
        first = self.seq
        self.seq += n
        return first

    # ------------------------------------------------------------------ samples
    def ping(self) -> None:
        """Nothing: the daemon's watchdog asks it on a silent bus to see that the worker answers."""

    def update(self, block: SampleBlock) -> BatchResult:
        """Feed a block of samples to the bank, in order, in chunks of about one tick."""
        self._beat_t = time.monotonic()
        block = self.gate.apply(block)
        measured = self._measure_first(block) if self._first is not None else None
        if self._probing:  # the first samples are held until they measure the start values
            if measured is None:
                return self._result([], [])
            block = self._end_probe(*measured)
        return self._feed(block)

    def release_held(self) -> BatchResult:
        """At stop: the samples still held for the start values go through the bank with the
        fallback start values (as at ``PROBE_LIMIT_S``), so that none is lost."""
        self._beat_t = time.monotonic()
        if not self._probing or not self._first:
            return self._result([], [])
        held = SampleBlock.concat(self._first)
        self._first = None
        log.info(
            "stopping: the %d samples (%.0f s) held for the start values go through the bank now",
            len(held),
            _span_s(held),
        )
        # The latest probe found too few steps in exactly these samples: no need to look again.
        return self._feed(self._end_probe(held, None))

    def _feed(self, block: SampleBlock) -> BatchResult:
        estimates: list[Estimates] = []
        messages: list[OutMessage] = []
        head = self._head.add(block) if self._head is not None else None
        step = samples_per_tick(block.t_s, self.spec.tuning.id_period_s)
        if not self.shares_gil:
            step *= CHUNK_TICKS_ALONE
        for start in range(0, len(block), step):
            chunk = block.slice(start, start + step)
            ticks = self.bank.update_block(chunk)
            for c, rms_V, med_V in self._lone.add(ticks):
                log.warning(
                    "cell %d: model error %.1f mV RMS over the last %.0f min of data, %.1fx the "
                    "pack's median (%.2f mV): a fault of this cell's own (a loose or intermittent "
                    "sense wire, a bad tap, a failing cell) more than its dynamics; the SOC "
                    "observer keeps it from the pack's current offset",
                    c, 1e3 * rms_V, LONE_WINDOW_S / 60, rms_V / med_V, 1e3 * med_V,
                )  # fmt: skip
            rows = ticks.rows()
            if rows and not self.spec.keep_all_estimates:
                estimates[:] = rows[-1:]
            elif rows:
                estimates += rows
            mono = chunk.t_complete_mono
            for est, k in zip(rows, tick_samples(chunk.t_s, ticks.t_s).tolist(), strict=True):
                messages += self._messages(est, None if mono is None else float(mono[k]))
            # In thread isolation, hand the GIL to the event loop between chunks: otherwise the
            # loop waits a whole switch interval for every GIL release it makes (convoy effect).
            # Alone in a process it would only give the core away (6 s a day of 1 s ticks).
            if self.shares_gil:
                time.sleep(0)
            self._beat_due()
        if head is not None:
            self._head = None
            self._refit_start(head)
        return self._result(estimates, messages)

    def _beat_due(self) -> None:
        """A heartbeat if ``HEARTBEAT_S`` passed since the last: a long call is not a stuck one."""
        if (now := time.monotonic()) - self._beat_t >= HEARTBEAT_S:
            self._beat_t = now
            self.beat()

    def _result(self, estimates: list[Estimates], messages: list[OutMessage]) -> BatchResult:
        return BatchResult(
            estimates, messages, self._counters(), self.seq, self.gate.state.report(),
            self.bank.soc_init_method,
        )  # fmt: skip

    def _refit_start(self, head: SampleBlock) -> None:
        """Where the start fitted over ``head`` holds (its branches, and its SOC unless that
        is configured), a bank from it that has replayed ``head`` replaces the running one
        (``daemon/start_refit.py``)."""
        from bmsid.config.engine import build_bank  # noqa: PLC0415 (see TYPE_CHECKING)
        from bmsid.offline.start_soc import WINDOW_FIT, fitted_start_soc  # noqa: PLC0415

        s = self.spec
        # a cell's fit is ~0.1 s here, a 96-cell pack's seconds more on a gateway's core
        fitted = fitted_start_soc([head], s.cell, s.tuning, self.start_values, soc0=s.soc0,
                                  each_cell=self._beat_due)  # fmt: skip
        if fitted is None:
            log.info(
                "start kept after %.0f s (%s): the first voltage was at rest, relaxed and "
                "showed no hysteresis state, or no start fit held", WINDOW_S,
                self.bank.soc_init_method,
            )  # fmt: skip
            return
        soc0 = fitted.soc0 if fitted.soc_fitted else s.soc0
        bank = build_bank(s.cell, s.n_cells, s.variant, s.tuning, soc0=soc0,
                          start=self.start_values, branch0_V=fitted.branch_V,
                          h0=fitted.h0)  # fmt: skip
        step = 64 * samples_per_tick(head.t_s, s.tuning.id_period_s)
        for start in range(0, len(head), step):
            bank.update_block(head.slice(start, start + step))
            self._beat_due()
        opened = {"ocv_ir_corrected": "under load"}.get(self.bank.soc_init_method, "relaxing")
        if fitted.h0 is not None and np.any(fitted.h0):  # a rested start whose h the window showed
            opened = f"at rest, hysteresis state {float(np.mean(fitted.h0)):+.2f} (mean)"
        what = "start SOC fitted"
        if fitted.soc_fitted:
            bank.state.soc_init_method = WINDOW_FIT
        else:  # the configured SOC stays (its start method too); loaded or relaxing, as judged
            what, opened = "start branches fitted (SOC as configured)", "under load or relaxing"
        log.info(
            "%s over the first %.0f s (it opened %s): %.1f %%, branches %.1f mV (means of %d "
            "cells); the bank replayed those samples from there: SOC now %.1f %% (was %.1f %%)",
            what, WINDOW_S, opened, 100 * float(fitted.soc0.mean()),
            1e3 * float(fitted.branch_V.sum(axis=1).mean()), s.n_cells,
            100 * float(bank.state.z.mean()), 100 * float(self.bank.state.z.mean()),
        )  # fmt: skip
        self.bank = bank
        self.counters["start_refits"] += 1

    @property
    def state_dir_failing(self) -> bool:
        """The latest checkpoint or ``.seq`` write failed (and has not succeeded since)."""
        return self._ckpt_error is not None or self._seq_error is not None

    def _counters(self) -> dict[str, int]:
        # state_dir_failing is a state (0/1), sent with the counters the daemon merges after
        # every batch and checkpoint: its CAN health and status follow without another call.
        return {
            **self.bank.counters,
            **self.gate.state.counters(),
            **self.counters,
            "state_dir_failing": int(self.state_dir_failing),
        }

    def _messages(self, est: Estimates, t_mono: float | None) -> list[OutMessage]:
        s = self.spec
        if not s.mqtt_enabled:
            return []
        tol = 0.5 * s.tuning.id_period_s
        if s.publish_period_s > 0 and est.t_s - self._last_pub_t < s.publish_period_s - tol:
            return []
        self._last_pub_t = est.t_s
        seen = np.flatnonzero(self.gate.state.seen).tolist()
        first = self._take_seqs(len(seen) + 1)
        if first is None:
            self.counters["mqtt_withheld"] += len(seen) + 1
            return []
        out = []
        for k, i in enumerate(seen):
            body = payloads.cell_payload(est, i, s.pack_id, first + k)
            topic = payloads.topic(s.topic_prefix, s.pack_id, "cell", i)
            out.append(OutMessage(topic, payloads.encode(body), s.qos, t_sample_mono=t_mono))
        # Input staleness cannot be true here: a sample just arrived.
        seq = first + len(seen)
        missing = self.gate.state.missing  # never on the bus: reported in the pack, not cells
        health = payloads.health_bits(est, state_dir_failing=self.state_dir_failing)
        body = payloads.pack_payload(est, s.pack_id, seq, health, missing)
        topic = payloads.topic(s.topic_prefix, s.pack_id, "pack")
        out.append(OutMessage(topic, payloads.encode(body), s.qos, t_sample_mono=t_mono))
        return out

    # ------------------------------------------------------------------ state
    def checkpoint(self, clean: bool = False) -> dict[str, int]:
        """Atomic checkpoint of the whole bank; ``clean`` (shutdown) also pins the exact seq."""
        state = self.bank.state_dict()
        # The newest sample time (s, None before the first): a restarted replay resumes after it.
        t_s = self.bank.last_sample_t_s
        sv = self.start_values
        problem = state_problem(state, self._reference)
        if problem is not None:
            # Keep the last good checkpoint: a restart from it beats a state that is lost.
            self.counters["checkpoints_refused"] += 1
            if _log_now(self.counters["checkpoints_refused"]):
                log.warning(
                    "checkpoint %s not written (%d time(s)): the estimator state has %s; the "
                    "previous checkpoint is kept",
                    self.spec.ckpt_path,
                    self.counters["checkpoints_refused"],
                    problem,
                )
        else:
            self._save(state, t_s, sv)
        if clean and self._write_seq_file(self.seq):
            self._seq_reserved = self.seq
        return self._counters()

    def _save(self, state: dict[str, Any], t_s: float | None, sv: StartValues | None) -> None:
        try:
            save_checkpoint(
                self.spec.ckpt_path,
                self.spec.ckpt_key,
                state,
                extra={
                    "seq": self.seq,
                    "t_s": t_s,
                    "start_values": None if sv is None else dataclasses.asdict(sv),
                },
            )
        except OSError as exc:
            self._ckpt_error = str(exc.strerror or exc)
            self.counters["checkpoint_errors"] += 1
            if _log_now(self.counters["checkpoint_errors"]):
                log.error(
                    "checkpoint %s failed (%d time(s)): %s; health bit %d set until one succeeds",
                    self.spec.ckpt_path,
                    self.counters["checkpoint_errors"],
                    exc,
                    payloads.HEALTH_STATE_DIR,
                )
        else:
            if self._ckpt_error is not None:
                log.warning(
                    "checkpoint %s written again (%d failure(s) so far)",
                    self.spec.ckpt_path,
                    self.counters["checkpoint_errors"],
                )
            self._ckpt_error = None
            self.counters["checkpoints"] += 1


# ---------------------------------------------------------------------- child process side
class BankWorkerError(RuntimeError):
    """The worker process died (the daemon exits non-zero; its supervisor restarts it from
    the last checkpoint)."""


class _RemoteTracebackError(Exception):
    """The worker's traceback of an exception re-raised in the daemon (its ``__cause__``)."""

    def __str__(self) -> str:
        return str(self.args[0])


def _die_with_parent() -> bool:
    """Ask the kernel to SIGKILL this process when its parent dies; True if it will (Linux).

    A daemon killed with SIGKILL cannot stop its worker, and the lock of the pack's files died
    with the daemon: an orphan still computing could write a checkpoint over the one the next
    daemon restored (polling the parent left it up to :data:`PARENT_POLL_S` to do so). SIGKILL
    ends it before its next instruction; a write already in its rename lands whole or not at
    all (:func:`~bmsid.daemon.statedir.atomic_write`). The kernel sends it when the *thread*
    that started the worker exits: :class:`BankWorker` is created on the event loop's thread.
    """
    if not sys.platform.startswith("linux"):
        return False
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        return bool(libc.prctl(PR_SET_PDEATHSIG, int(signal.SIGKILL), 0, 0, 0) == 0)
    except (OSError, AttributeError):
        return False


def _exit_with_parent(parent_pid: int) -> None:
    # Where the kernel cannot (see _die_with_parent): notice the re-parenting and exit.
    while os.getppid() == parent_pid:
        time.sleep(PARENT_POLL_S)
    os._exit(0)


class _PipeQueue:
    """The ``put_nowait`` a ``QueueHandler`` needs, over a pipe (the handler's lock serialises
    the sends of several threads)."""

    def __init__(self, conn: Connection) -> None:
        self.conn = conn
        # serialises the handler's sends with the heartbeat's, which bypass the handler
        self._lock = threading.Lock()

    def put_nowait(self, record: logging.LogRecord | str) -> None:
        with self._lock, contextlib.suppress(OSError):  # the daemon is gone: nobody to tell
            self.conn.send(record)


def _child_main(
    conn: Connection, log_conn: Connection, spec: BankSpec, level: int, parent_pid: int
) -> None:
    """The worker process: answer ``(method, args)`` calls on ``conn`` until told to close."""
    # The parent decides when to stop: a terminal's ^C or hang-up, or systemd's SIGTERM to the
    # whole cgroup, must not kill the bank before the parent's final checkpoint.
    for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP):
        signal.signal(sig, signal.SIG_IGN)
    root = logging.getLogger()
    pipe = _PipeQueue(log_conn)
    root.handlers[:] = [logging.handlers.QueueHandler(pipe)]  # type: ignore[arg-type]
    root.setLevel(level)
    quiet_libraries(level)  # a child process: the parent's logger levels do not carry over
    if not _die_with_parent():
        threading.Thread(target=_exit_with_parent, args=(parent_pid,), daemon=True).start()
    if os.getppid() != parent_pid:  # died before the kernel was asked: nobody to serve
        os._exit(0)
    host: BankHost | None = None
    init_error: BaseException | None = None
    try:
        host = BankHost(spec)
        host.beat = lambda: pipe.put_nowait(HEARTBEAT)
        host.shares_gil = False
    except Exception as exc:  # answered to every call: the daemon reports it as its own
        init_error = exc
    gc.collect()
    gc.freeze()  # the start-up heap, as in the daemon: full collections stay short
    while True:
        try:
            method, args = conn.recv()
        except EOFError:
            return
        if method == "close":
            return
        try:
            if host is None:
                assert init_error is not None
                raise init_error
            reply: tuple[str, Any, str] = ("ok", getattr(host, method)(*args), "")
        except Exception as exc:
            reply = ("error", exc, traceback.format_exc())
        try:
            conn.send(reply)
        except Exception as exc:  # an exception that does not pickle: its text does
            conn.send(("error", RuntimeError(f"{type(reply[1]).__name__}: {reply[1]}"), str(exc)))


def _forward_logs(conn: Connection, on_beat: Callable[[], None]) -> None:
    """Daemon side of the worker's log pipe: re-emit each record under its own logger; a
    heartbeat calls ``on_beat``."""
    while True:
        try:
            record: logging.LogRecord | str = conn.recv()
        except (EOFError, OSError):
            return
        if isinstance(record, str):
            on_beat()
        else:
            logging.getLogger(record.name).handle(record)


class BankWorker:
    """Parent-side handle: ``await start()``, ``await update(block)``, ``await checkpoint()``.

    Calls are serialised (one at a time, in order); a dead worker process raises
    :class:`BankWorkerError` from the call, an exception in the worker is re-raised with
    the worker's traceback as its cause. ``calls`` and ``progress_mono`` are what the daemon's
    watchdog reads (:mod:`bmsid.daemon.watchdog`).
    """

    def __init__(self, spec: BankSpec, isolation: Isolation = "process") -> None:
        self.isolation = isolation
        #: calls made and not answered yet (queued or running)
        self.calls = 0
        #: ``time.monotonic()`` of the worker's last answer or heartbeat, or of a call made
        #: while none was outstanding (an idle worker owes nothing)
        self.progress_mono = time.monotonic()
        self._host: BankHost | None = None
        self._process: multiprocessing.process.BaseProcess | None = None
        self._log_thread: threading.Thread | None = None
        # One thread makes the calls: over the pipe (process) or on the host itself (thread).
        self._executor = concurrent.futures.ThreadPoolExecutor(1, thread_name_prefix="bmsid-bank")
        if isolation == "process":
            ctx = multiprocessing.get_context("spawn")  # fork is unsafe with threads running
            self._conn, child_conn = ctx.Pipe()
            log_recv, log_send = ctx.Pipe(duplex=False)
            level = logging.getLogger().getEffectiveLevel()
            self._process = ctx.Process(
                target=_child_main,
                args=(child_conn, log_send, spec, level, os.getpid()),
                name="bmsid-bank",
            )
            self._process.start()
            child_conn.close()  # the child's ends: EOF on our side once it exits
            log_send.close()
            self._log_thread = threading.Thread(
                target=_forward_logs,
                args=(log_recv, self._on_beat),
                name="bmsid-bank-log",
                daemon=True,
            )
            self._log_thread.start()
        else:
            self._host = BankHost(spec)
            self._host.beat = self._on_beat

    def _on_beat(self) -> None:
        # from the log thread or the worker thread: one float store, atomic under the GIL
        self.progress_mono = time.monotonic()

    def _roundtrip(self, method: str, args: tuple[Any, ...]) -> Any:
        assert self._process is not None
        try:
            self._conn.send((method, args))
            status, value, remote_tb = self._conn.recv()
        except (EOFError, OSError) as exc:
            self._process.join(1.0)
            raise BankWorkerError(
                f"the bank worker process exited (exit code {self._process.exitcode}) "
                f"during {method}()"
            ) from exc
        if status == "error":
            raise value from _RemoteTracebackError(remote_tb)
        return value

    async def _call(self, method: str, *args: Any) -> Any:
        loop = asyncio.get_running_loop()
        if self.calls == 0:
            self.progress_mono = time.monotonic()
        self.calls += 1
        try:
            if self._host is not None:
                return await loop.run_in_executor(
                    self._executor, getattr(self._host, method), *args
                )
            return await loop.run_in_executor(self._executor, self._roundtrip, method, args)
        finally:
            self.calls -= 1
            self.progress_mono = time.monotonic()

    async def start(self) -> StartInfo:
        t0 = time.monotonic()
        info: StartInfo = await self._call("start")
        log.debug("bank worker (%s) ready in %.2f s", self.isolation, time.monotonic() - t0)
        return info

    async def update(self, block: SampleBlock) -> BatchResult:
        result: BatchResult = await self._call("update", block)
        return result

    async def ping(self) -> None:
        """A no-op call: answered when the worker is alive and done with the calls before it."""
        await self._call("ping")

    async def release_held(self) -> BatchResult:
        """The samples held for the start values, through the bank (at stop: none lost)."""
        result: BatchResult = await self._call("release_held")
        return result

    async def checkpoint(self, clean: bool = False) -> dict[str, int]:
        counters: dict[str, int] = await self._call("checkpoint", clean)
        return counters

    def close(self) -> None:
        """Wait for the call under way, end the worker process, join its log thread."""
        self._executor.shutdown(wait=True, cancel_futures=True)
        process = self._process
        if process is None:
            return
        with contextlib.suppress(OSError):
            self._conn.send(("close", ()))
        self._conn.close()
        process.join(CLOSE_TIMEOUT_S)
        if process.is_alive():  # stuck: it ignores SIGTERM (see _child_main), so SIGKILL
            log.warning("bank worker did not end within %.0f s: killed", CLOSE_TIMEOUT_S)
            process.kill()
            process.join()
        if self._log_thread is not None:
            self._log_thread.join(CLOSE_TIMEOUT_S)
