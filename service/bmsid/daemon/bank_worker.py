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
instead of reusing numbers that consumers may already have seen.
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import contextlib
import dataclasses
import gc
import logging
import logging.handlers
import multiprocessing
import os
import signal
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal

import numpy as np
import numpy.typing as npt

from bmsid.config.cell import CellConfig
from bmsid.daemon.checkpoint import CheckpointKey, load_checkpoint, save_checkpoint
from bmsid.estimate.startvalues import StartValues, start_values_from_record
from bmsid.estimate.tuning import EstimatorTuning, Variant
from bmsid.estimate.types import Estimates
from bmsid.gates import GateConfig, InputGate
from bmsid.publish import payloads
from bmsid.publish.outbox import OutMessage
from bmsid.samples import SampleBlock

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
#: How often the worker checks that the daemon still lives, s.
PARENT_POLL_S = 0.5


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

    @property
    def seq_path(self) -> Path:
        return self.ckpt_path.with_name(f"{self.pack_id}.seq")


@dataclass(frozen=True)
class StartInfo:
    restored: bool
    seq: int
    t_s: float | None


@dataclass(frozen=True)
class BatchResult:
    #: the ticks' estimates (all, or only the newest unless ``keep_all_estimates``)
    estimates: list[Estimates]
    messages: list[OutMessage]
    counters: dict[str, int]
    seq: int
    #: what the plausibility gates refused, missing and no-data cells (``GateState.report``)
    inputs: dict[str, Any] = field(default_factory=dict)


@dataclass
class BankHost:
    """Runs in the worker: bank updates, MQTT message encoding, checkpoints, sequence numbers."""

    spec: BankSpec
    bank: EstimatorBank = field(init=False)
    seq: int = 0
    counters: dict[str, int] = field(default_factory=dict)
    _seq_reserved: int = 0
    _last_pub_t: float = -float("inf")

    #: start values measured on the first samples (None: the config's or the capacity rule's)
    start_values: StartValues | None = None
    _probe: list[SampleBlock] = field(default_factory=list)
    _probing: bool = False

    def __post_init__(self) -> None:
        self.bank = self._fresh_bank()
        # Limits from the OCV curve and capacity: the same whatever start values are measured.
        limits = self.spec.gates.for_model(self.bank.model, self.spec.tuning.gap_s)
        self.gate = InputGate(limits, self.spec.n_cells)
        log.info("input gates: %s", limits.describe())
        self.counters = {"checkpoints": 0, "checkpoint_errors": 0, "seq_file_errors": 0}
        # A config without start values or bounds: measure them on the first samples, as
        # offline identification does on a record, before the estimators start.
        self._probing = self.spec.cell.initial is None or self.spec.cell.bounds is None

    def _fresh_bank(self) -> EstimatorBank:
        from bmsid.config.engine import build_bank  # noqa: PLC0415 (see TYPE_CHECKING)

        s = self.spec
        return build_bank(
            s.cell, s.n_cells, s.variant, s.tuning, soc0=s.soc0, start=self.start_values
        )

    def _probe_block(self, block: SampleBlock) -> SampleBlock | None:
        """Hold samples until the start values are measured; then the held samples, to feed."""
        self._probe.append(block)
        held = SampleBlock.concat(self._probe)
        found = start_values_from_record(held.t_s, held.current_A, held.cell_voltages_V)
        span = float(held.t_s[-1] - held.t_s[0]) if len(held) else 0.0
        if found is None and span < PROBE_LIMIT_S and len(held) < PROBE_LIMIT_SAMPLES:
            return None
        self._probing = False
        self._probe = []
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
            try:
                sv = ck.extra.get("start_values")
                if sv is not None:  # the bank's normalisation depends on them: rebuild first
                    self.start_values = StartValues(**sv)
                    self.bank = self._fresh_bank()
                self.bank.load_state_dict(ck.state)
            except (ValueError, KeyError, TypeError) as exc:
                log.warning(
                    "checkpoint %s does not fit this bank (%s): starting fresh",
                    self.spec.ckpt_path,
                    exc,
                )
                self.start_values = None
                self.bank = self._fresh_bank()
            else:
                restored = True
                self._probing = False
                ck_seq = int(ck.extra.get("seq", 0))
                t_raw = ck.extra.get("t_s")
                t_s = float(t_raw) if t_raw is not None else None
        self.seq = max(ck_seq, self._read_seq_file())
        self._seq_reserved = self.seq
        return StartInfo(restored=restored, seq=self.seq, t_s=t_s)

    def _read_seq_file(self) -> int:
        try:
            return max(0, int(self.spec.seq_path.read_text(encoding="ascii").strip()))
        except FileNotFoundError:
            return 0
        except (OSError, ValueError) as exc:
            log.warning("sequence file %s unreadable (%s): ignored", self.spec.seq_path, exc)
            return 0

    def _write_seq_file(self, value: int) -> bool:
        path = self.spec.seq_path
        tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            with tmp.open("w", encoding="ascii") as fh:
                fh.write(f"{value}\n")
                fh.flush()
                os.fsync(fh.fileno())
            os.replace(tmp, path)
        except OSError as exc:
            self.counters["seq_file_errors"] += 1
            log.error("sequence file %s cannot be written: %s", path, exc)
            with contextlib.suppress(OSError):
                tmp.unlink(missing_ok=True)
            return False
        return True

    def _next_seq(self) -> int:
        if self.seq >= self._seq_reserved:
            # Reserve before use; if the disk refuses, go on (numbers may repeat after a crash).
            self._write_seq_file(self.seq + SEQ_BLOCK)
            self._seq_reserved = self.seq + SEQ_BLOCK
        n = self.seq
        self.seq += 1
        return n

    # ------------------------------------------------------------------ samples
    def update(self, block: SampleBlock) -> BatchResult:
        """Feed a block of samples to the bank, in order, in chunks of about one tick."""
        estimates: list[Estimates] = []
        messages: list[OutMessage] = []
        block = self.gate.apply(block)
        if self._probing:
            held = self._probe_block(block)
            if held is None:
                return BatchResult(
                    estimates, messages, self._counters(), self.seq, self.gate.state.report()
                )
            block = held
        step = samples_per_tick(block.t_s, self.spec.tuning.id_period_s)
        for start in range(0, len(block), step):
            chunk = block.slice(start, start + step)
            ticks = self.bank.update_block(chunk)
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
            time.sleep(0)
        return BatchResult(
            estimates, messages, self._counters(), self.seq, self.gate.state.report()
        )

    def _counters(self) -> dict[str, int]:
        return {**self.bank.counters, **self.gate.state.counters(), **self.counters}

    def _messages(self, est: Estimates, t_mono: float | None) -> list[OutMessage]:
        s = self.spec
        if not s.mqtt_enabled:
            return []
        tol = 0.5 * s.tuning.id_period_s
        if s.publish_period_s > 0 and est.t_s - self._last_pub_t < s.publish_period_s - tol:
            return []
        self._last_pub_t = est.t_s
        out = []
        missing = self.gate.state.missing  # never on the bus: reported in the pack, not cells
        for i in np.flatnonzero(self.gate.state.seen).tolist():
            body = payloads.cell_payload(est, i, s.pack_id, self._next_seq())
            topic = payloads.topic(s.topic_prefix, s.pack_id, "cell", i)
            out.append(OutMessage(topic, payloads.encode(body), s.qos, t_sample_mono=t_mono))
        # Input staleness cannot be true here: a sample just arrived.
        body = payloads.pack_payload(
            est, s.pack_id, self._next_seq(), payloads.health_bits(est), missing
        )
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
            self.counters["checkpoint_errors"] += 1
            log.error("checkpoint %s failed: %s", self.spec.ckpt_path, exc)
        else:
            self.counters["checkpoints"] += 1
        if clean and self._write_seq_file(self.seq):
            self._seq_reserved = self.seq
        return self._counters()


# ---------------------------------------------------------------------- child process side
#: the child's one host (a dict, not a global statement)
_CHILD: dict[str, BankHost] = {}


def _exit_with_parent(parent_pid: int) -> None:
    # A parent killed with SIGKILL cannot stop its worker: the worker notices it was re-parented
    # and exits, so a crash-restart never leaves an orphan bank computing (and checkpointing).
    while os.getppid() == parent_pid:
        time.sleep(PARENT_POLL_S)
    os._exit(0)


def _child_init(spec: BankSpec, log_queue: Any, level: int, parent_pid: int) -> None:
    # The parent decides when to stop: a terminal's ^C or systemd's SIGTERM to the whole
    # cgroup must not kill the bank before the parent's final checkpoint.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    root = logging.getLogger()
    root.handlers[:] = [logging.handlers.QueueHandler(log_queue)]
    root.setLevel(level)
    threading.Thread(target=_exit_with_parent, args=(parent_pid,), daemon=True).start()
    _CHILD["host"] = BankHost(spec)
    gc.collect()
    gc.freeze()  # the start-up heap, as in the daemon: full collections stay short


def _child_call(method: str, *args: Any) -> Any:
    return getattr(_CHILD["host"], method)(*args)


class _ForwardToLogger(logging.Handler):
    """Parent side of the child's log queue: re-emit under the record's own logger."""

    def emit(self, record: logging.LogRecord) -> None:
        logging.getLogger(record.name).handle(record)


class BankWorker:
    """Parent-side handle: ``await start()``, ``await update(block)``, ``await checkpoint()``.

    Calls are serialised by the single worker; a dead child process raises
    ``concurrent.futures.process.BrokenProcessPool`` from the call (the daemon then exits
    non-zero and its supervisor restarts it from the last checkpoint).
    """

    def __init__(self, spec: BankSpec, isolation: Isolation = "process") -> None:
        self.isolation = isolation
        self._listener: logging.handlers.QueueListener | None = None
        self._host: BankHost | None = None
        self._executor: concurrent.futures.Executor
        if isolation == "process":
            ctx = multiprocessing.get_context("spawn")  # fork is unsafe with threads running
            queue = ctx.Queue()
            self._listener = logging.handlers.QueueListener(queue, _ForwardToLogger())
            self._listener.start()
            self._executor = concurrent.futures.ProcessPoolExecutor(
                1,
                mp_context=ctx,
                initializer=_child_init,
                initargs=(spec, queue, logging.getLogger().getEffectiveLevel(), os.getpid()),
            )
        else:
            self._host = BankHost(spec)
            self._executor = concurrent.futures.ThreadPoolExecutor(
                1, thread_name_prefix="bmsid-bank"
            )

    async def _call(self, method: str, *args: Any) -> Any:
        loop = asyncio.get_running_loop()
        if self._host is not None:
            return await loop.run_in_executor(self._executor, getattr(self._host, method), *args)
        return await loop.run_in_executor(self._executor, _child_call, method, *args)

    async def start(self) -> StartInfo:
        t0 = time.monotonic()
        info: StartInfo = await self._call("start")
        log.debug("bank worker (%s) ready in %.2f s", self.isolation, time.monotonic() - t0)
        return info

    async def update(self, block: SampleBlock) -> BatchResult:
        result: BatchResult = await self._call("update", block)
        return result

    async def checkpoint(self, clean: bool = False) -> dict[str, int]:
        counters: dict[str, int] = await self._call("checkpoint", clean)
        return counters

    def close(self) -> None:
        self._executor.shutdown(wait=True, cancel_futures=True)
        if self._listener is not None:
            self._listener.stop()
