"""The live daemon: frames -> samples -> estimator bank -> CAN and MQTT publishers.

::

    CAN source (socketcan add_reader | virtual thread)      [sources.py]
        | batches of frames
        v
    FrameToSamples (canbus)  --samples-->  SampleQueue of columnar blocks   [sample_queue.py]
                                                | batches (pickled)
                                                v
                         bank worker process: EstimatorBank.update_block, MQTT JSON,
                         checkpoints, sequence numbers               [bank_worker.py]
                                                | Estimates + encoded messages
                     +--------------------------+---------------------------+
                     v                                                      v
        CAN output every output_period_s                   MQTT outbox (bounded, drop-oldest)
        (pack summary + cells cycled, share cap)       -> MqttPublisher (reconnects) [publish/]

The event loop only moves data: decoding costs microseconds per frame, and the bank (whose
swarm iterations take milliseconds) runs in a child process, so it never holds the loop's
interpreter lock; the loop lag is measured by a monitor task (``loop_lag_max_ms``).
"""

from __future__ import annotations

import asyncio
import collections
import contextlib
import gc
import logging
import signal
import sys
import time
from collections.abc import Callable
from pathlib import Path

import can

from bmsid import __version__
from bmsid.canbus.bus import send_frames
from bmsid.canbus.encoder import CLASSIC_PAGES
from bmsid.canbus.frames_to_samples import DECODE_ERROR_KINDS, FrameToSamples
from bmsid.canbus.mapping import BusMapping, default_mapping, load_mapping
from bmsid.config.settings import Settings
from bmsid.daemon.bank_worker import BankSpec, BankWorker, BatchResult
from bmsid.daemon.canout import CellCycler, frame_bits, output_encoder, plan_output
from bmsid.daemon.checkpoint import CheckpointKey
from bmsid.daemon.sample_queue import SampleQueue
from bmsid.daemon.sdnotify import SdNotifier
from bmsid.daemon.sources import FrameSource, LogReplayer, open_source, replay_channel
from bmsid.daemon.statedir import StateLock, check_writable, remove_stale_temps
from bmsid.daemon.watchdog import Pipeline, stall
from bmsid.errors import UserError
from bmsid.estimate.types import Estimates
from bmsid.gates import GATE_COUNTERS
from bmsid.publish import payloads
from bmsid.publish.discovery import PublishedConfigs, discovery_messages
from bmsid.publish.mqtt import MqttPublisher
from bmsid.publish.outbox import Outbox, OutMessage, load_spool, save_spool
from bmsid.samples import Sample, SampleBlock

log = logging.getLogger(__name__)

#: Bank events the daemon says in one WARNING line each time their counter moves (``%.0f``:
#: ``gap_s``), as ``bmsid identify`` says them offline.
_SAID_ONCE = {
    "time_jumps_back": "the sample clock went back by more than %.0f s (a replay restarted, or "
    "the clock was set back): new estimation segment, state kept",
    "gaps_under_load": "a gap in the samples (over %.0f s) resumed under load (data lost "
    "mid-drive, or a clock that jumped): the charge moved in it is unknown; SOC re-anchored "
    "from the voltage",
    "readings_lost": "a cell has had no valid voltage for %.0f s (frames lost, or every reading "
    "refused by [gates]; see inputs in the status): published as no_data until its readings "
    "return",
}

CAN_ERR_BUSOFF = 0x40
LAG_INTERVAL_S = 0.05
#: samples held while the bank is behind (the reader waits beyond that)
SAMPLE_QUEUE = 50_000
#: samples per block put in the queue, and per batch sent to the bank
SAMPLE_BATCH = 64
FRAMES_PER_YIELD = 64
#: GIL switch interval of the daemon process: the loop gets the GIL back within 1 ms.
SWITCH_INTERVAL_S = 0.001
#: Beyond the MQTT flush's own limit, how long the shutdown waits for the publisher to return
#: (a connect or publish under way ends by ``publish_timeout_s``; this is the backstop), s.
MQTT_STOP_MARGIN_S = 5.0


class Daemon:
    """One pack's live identification; ``await run()`` until :meth:`request_stop`.

    Args:
        settings: validated settings.
        on_estimates: called on the loop with every estimator tick (live view, tests).
        shutdown_timeout_s: how long the shutdown may wait for the MQTT backlog (what is left
            then is spooled to the state directory and sent first after the restart).
    """

    def __init__(
        self,
        settings: Settings,
        *,
        on_estimates: Callable[[Estimates], None] | None = None,
        shutdown_timeout_s: float = 10.0,
    ) -> None:
        self.settings = settings
        self.on_estimates = on_estimates
        self.shutdown_timeout_s = shutdown_timeout_s
        cs = settings.can
        self.cell = settings.estimator.load_cell()
        self.mapping: BusMapping = (
            load_mapping(cs.mapping) if cs.mapping is not None else default_mapping()
        )
        if cs.n_cells > self.mapping.max_cells():
            raise UserError(
                f"can.n_cells={cs.n_cells}: mapping {self.mapping.name!r} carries "
                f"{self.mapping.max_cells()} cells"
            )
        # checked before anything starts: a log of two packs must not be merged into one
        self.replay_channel = (
            replay_channel(cs.replay, self.mapping) if cs.replay is not None else None
        )
        self.f2s = FrameToSamples(self.mapping, cs.n_cells, staleness_s=cs.staleness_s)
        self.encoder = output_encoder(cs)
        frames_per_cell = 1 if cs.output_fd else len(CLASSIC_PAGES)
        bits = frame_bits(64 if cs.output_fd else 8, cs.output_extended_id)
        self.cycler: CellCycler = plan_output(
            cs.n_cells, frames_per_cell, bits, cs.bitrate_bps, cs.max_bus_share, cs.output_period_s
        )
        self.ckpt_key = CheckpointKey(
            settings.pack_id,
            cs.n_cells,
            settings.config_hash(self.cell),
            settings.config_parts(self.cell),
        )
        self.ckpt_path = settings.state.directory / f"{settings.pack_id}.ckpt.npz"
        self.spool_path = settings.state.directory / f"{settings.pack_id}.spool"
        #: messages of the spool loaded at start; the file goes once they left the outbox
        self._spooled = 0
        est, m = settings.estimator, settings.mqtt
        self.bank_spec = BankSpec(
            cell=self.cell,
            n_cells=cs.n_cells,
            variant=est.variant,
            tuning=est.tuning,
            soc0=est.soc0,
            restore=settings.state.restore,
            ckpt_path=self.ckpt_path,
            ckpt_key=self.ckpt_key,
            pack_id=settings.pack_id,
            topic_prefix=m.topic_prefix,
            mqtt_enabled=m.enabled,
            qos=m.qos,
            publish_period_s=m.publish_period_s,
            keep_all_estimates=on_estimates is not None,
            kernels=est.kernels,
            gates=settings.gates,
        )
        #: the bank's counters (samples, ticks, swarms, ...) as of its latest batch
        self.bank_counters: dict[str, int] = dict.fromkeys(("samples", "ticks", "swarms"), 0)
        #: the bank's counters as the checkpoint restored them: the status counts since this
        #: process started, as frames and uptime do; the restored totals are only a baseline
        self._restored_counters: dict[str, int] = {}
        self.worker: BankWorker | None = None
        self.prefix = settings.mqtt.topic_prefix
        self.sd = SdNotifier(settings.systemd_notify)
        self.latest: Estimates | None = None
        #: what the plausibility gates refused per cell, missing and no-data cells (status)
        self.inputs: dict[str, object] | None = None
        self.soc_init: str | None = None
        self.restored = False
        self.seq = 0
        self.can_state = "starting"
        self.counters: dict[str, int] = collections.Counter()
        self.loop_lag_max_s = 0.0
        self.loop_lags_s: collections.deque[float] = collections.deque(maxlen=50_000)
        self._lag_window_max_s = 0.0
        #: sample complete -> broker ack, s: every message / the first of each tick (cell 0)
        self.latencies_s: collections.deque[float] = collections.deque(maxlen=50_000)
        self.latencies_first_s: collections.deque[float] = collections.deque(maxlen=50_000)
        self.replayer: LogReplayer | None = None
        self.outbox: Outbox | None = None
        self.mqtt: MqttPublisher | None = None
        self._source: FrameSource | None = None
        self._samples: SampleQueue | None = None
        #: decoded samples not yet in the queue (and their completion times); always empty
        #: while the reader awaits, so other tasks never see them missing
        self._pending: list[Sample] = []
        self._pending_mono: list[float] = []
        self._stop: asyncio.Event | None = None
        self._last_sample_mono = 0.0
        #: when the CAN reader last took frames or queued samples (the watchdog's view)
        self._reader_progress_mono = time.monotonic()
        #: frames of the batch the reader is working through (0 while it awaits the next)
        self._reader_holding = 0
        self._had_data = False
        self._t_start = time.monotonic()
        self._ready_sent = False
        self._restored_t_s: float | None = None

    # ------------------------------------------------------------------ lifecycle
    def request_stop(self) -> None:
        """Graceful stop (SIGTERM/SIGINT): stop reading, flush, checkpoint, offline, exit."""
        if self._stop is not None:
            self._stop.set()

    @property
    def reading(self) -> bool:
        """True once the bank worker is up and the frame sources run (systemd's READY=1)."""
        return self._ready_sent

    def idle(self) -> bool:
        """True when a replay has ended and every frame and sample has been processed."""
        return (
            self.replayer is not None
            and self.replayer.done.is_set()
            and self._samples is not None
            and self._samples.empty()
            and self.counters["batches_in_flight"] == 0
        )

    def on_sighup(self) -> None:
        """SIGHUP: ignored (never a stop without a checkpoint, as its default action was)."""
        log.warning(
            "SIGHUP ignored: bmsid reads its config only at start; restart it to apply a "
            "changed config (systemctl restart bmsid: the state is checkpointed on the way)"
        )

    async def run(self) -> int:
        """Run until :meth:`request_stop`.

        Raises:
            UserError: the state directory is not writable, or another daemon holds the
                pack's lock there (one line each; ``bmsid run`` exits 2).
        """
        directory = self.settings.state.directory
        check_writable(directory)
        lock = StateLock.acquire(directory, self.settings.pack_id)
        try:
            remove_stale_temps(directory, (p.name for p in self._state_files()))
            return await self._run_locked()
        finally:
            lock.release()

    async def _run_locked(self) -> int:
        self._stop = asyncio.Event()
        self._samples = SampleQueue(SAMPLE_QUEUE)
        self._t_start = time.monotonic()
        self.worker = BankWorker(self.bank_spec, self.settings.estimator.isolation)
        # ~120k long-lived objects (cantools' multiplexed DBC, pydantic, aiomqtt, numpy) make a
        # full collection cost ~60 ms, which stalls the loop now and then; frozen, the
        # collector only walks what the daemon allocates while it runs.
        gc.collect()
        gc.freeze()
        try:
            return await self._run_with_worker(self.worker)
        finally:
            gc.unfreeze()
            await asyncio.to_thread(self.worker.close)

    async def _run_with_worker(self, worker: BankWorker) -> int:
        log.info("%s", self._start_line())
        # before the worker looks at it (it may set an unusable checkpoint aside)
        had_checkpoint = self.ckpt_path.exists()
        info = await worker.start()
        self.seq = info.seq
        if info.restored:
            self.restored = True
            self._restored_t_s = info.t_s
            self._restored_counters = dict(info.counters)
            log.info(
                "restored %s (saved at sample time %s s); MQTT seq continues at %d",
                self.ckpt_path,
                info.t_s,
                self.seq,
            )
        else:
            if not self.settings.state.restore:
                why = "state.restore = false"
            elif not had_checkpoint:
                why = f"no checkpoint {self.ckpt_path} yet"
            else:
                why = f"checkpoint {self.ckpt_path} not usable (see the warning above)"
            log.info("fresh start (%s); MQTT seq starts at %d", why, self.seq)
        mqtt_task: asyncio.Task[None] | None = None
        if self.settings.mqtt.enabled:
            self.outbox = Outbox(self.settings.mqtt.outbox_size)
            self._load_spool(self.outbox)
            mqtt_task = asyncio.create_task(self._start_mqtt(), name="mqtt")
        tasks = [
            asyncio.create_task(self._can_input(), name="can-input"),
            asyncio.create_task(self._estimate(), name="estimator"),
            asyncio.create_task(self._can_output(), name="can-output"),
            asyncio.create_task(self._checkpoints(), name="checkpoints"),
            asyncio.create_task(self._status(), name="status"),
            asyncio.create_task(self._log_counters(), name="log-counters"),
            asyncio.create_task(self._lag_monitor(), name="loop-lag"),
        ]
        if self.sd.watchdog_s:
            tasks.append(asyncio.create_task(self._watchdog(), name="watchdog"))
        assert self._stop is not None
        stop_waiter = asyncio.create_task(self._stop.wait())
        watched = {stop_waiter, *tasks, *([mqtt_task] if mqtt_task is not None else [])}
        done, _ = await asyncio.wait(watched, return_when=asyncio.FIRST_COMPLETED)
        failed = [t for t in done if t is not stop_waiter and not t.cancelled() and t.exception()]
        stop_waiter.cancel()
        await self._shutdown(tasks, mqtt_task)
        if failed:
            exc = failed[0].exception()
            assert exc is not None
            raise exc
        return 0

    async def _shutdown(
        self, tasks: list[asyncio.Task[None]], mqtt_task: asyncio.Task[None] | None
    ) -> None:
        self.sd.notify("STOPPING=1")
        log.info("stopping: draining samples, checkpointing, flushing MQTT")
        input_task = tasks[0]
        input_task.cancel()
        await asyncio.gather(input_task, return_exceptions=True)
        if self.replayer is not None:
            await asyncio.to_thread(self.replayer.stop)  # joins the replay thread
        assert self._samples is not None
        with contextlib.suppress(TimeoutError):
            await asyncio.wait_for(self._samples.join(), timeout=self.shutdown_timeout_s)
        for t in tasks[1:]:
            t.cancel()
        await asyncio.gather(*tasks[1:], return_exceptions=True)
        assert self.worker is not None
        # samples still held for the start values: estimated, published, checkpointed, not lost
        self._take_result(await self.worker.release_held())
        await self._checkpoint(clean=True)
        if mqtt_task is not None:
            if self.mqtt is not None:
                self.mqtt.stop(self.shutdown_timeout_s)
            # asyncio.wait: neither its result nor its exception is lost (the caller raises
            # the exception of a task that failed; this one is retrieved either way).
            await asyncio.wait({mqtt_task}, timeout=self.shutdown_timeout_s + MQTT_STOP_MARGIN_S)
            if not mqtt_task.done():
                mqtt_task.cancel()
            await asyncio.gather(mqtt_task, return_exceptions=True)
            self._spool_backlog()
        log.info(
            "stopped: after %.0f s, %s", time.monotonic() - self._t_start, self._counter_line()
        )

    # ------------------------------------------------------------------ MQTT spool
    def _state_files(self) -> tuple[Path, ...]:
        """The pack's files in the state directory that are written atomically."""
        return (self.ckpt_path, self.bank_spec.seq_path, self.spool_path)

    def _load_spool(self, outbox: Outbox) -> None:
        """Put the messages the last stop could not deliver in the outbox, before any new."""
        messages, lost = load_spool(self.spool_path, self.settings.pack_id)
        outbox.dropped += lost
        for msg in messages:
            outbox.put(msg)
        self._spooled = len(messages)
        if not messages:  # a count of lost messages only: in this run's mqtt_drops now
            with contextlib.suppress(OSError):
                self.spool_path.unlink(missing_ok=True)
        if messages:
            log.info(
                "MQTT: %d messages spooled at the last stop are sent first (%s)",
                len(messages),
                self.spool_path,
            )

    def _spool_done(self) -> None:
        """Remove the spool once its messages left the outbox (kept until then: a crash
        before they are delivered sends them after the next start)."""
        assert self.outbox is not None
        if self._spooled and self.outbox.taken >= self._spooled:
            self._spooled = 0
            with contextlib.suppress(OSError):
                self.spool_path.unlink(missing_ok=True)

    def _spool_backlog(self) -> None:
        """Spool what the shutdown flush could not deliver; if it can't, count it as dropped
        in this run and, through a spool holding only that count, in the next one."""
        assert self.outbox is not None
        left = len(self.outbox)
        if left == 0:  # a spool loaded at start left the outbox: delivered or counted dropped
            self._spooled = 0
            with contextlib.suppress(OSError):
                self.spool_path.unlink(missing_ok=True)
            return
        why = (self.mqtt.last_error if self.mqtt is not None else None) or "no connection"
        try:
            save_spool(self.spool_path, self.settings.pack_id, self.outbox.peek(left))
        except OSError as exc:
            self.outbox.dropped += left
            try:
                save_spool(self.spool_path, self.settings.pack_id, [], dropped=left)
            except OSError:
                after = "but not after the restart: the state directory cannot hold even the count"
            else:
                after = "and after the restart"
            log.error(
                "MQTT: %d messages not delivered at shutdown (%s) and not spooled (%s): lost, a "
                "seq gap counted in mqtt_drops now %s",
                left,
                why,
                exc.strerror or exc,
                after,
            )
            return
        log.warning(
            "MQTT: %d messages not delivered at shutdown (%s): spooled to %s, sent first after "
            "the restart",
            left,
            why,
            self.spool_path,
        )

    # ------------------------------------------------------------------ state
    async def _checkpoint(self, clean: bool = False) -> None:
        """Checkpoint in the bank's worker, between two batches (the state is consistent)."""
        assert self.worker is not None
        self._merge_bank_counters(await self.worker.checkpoint(clean))

    @property
    def state_dir_failing(self) -> bool:
        """The worker's latest checkpoint or ``.seq`` write failed (health bit 32)."""
        return bool(self.bank_counters.get("state_dir_failing", 0))

    def _merge_bank_counters(self, counters: dict[str, int]) -> None:
        """Take the worker's counters; a change of the state directory's state is published
        in the status at once, as a change of the CAN state is."""
        failing = self.state_dir_failing
        self.bank_counters.update(counters)
        if self.state_dir_failing != failing and self.mqtt is not None:
            self.mqtt.publish_status()

    async def _checkpoints(self) -> None:
        while True:
            await asyncio.sleep(self.settings.state.checkpoint_period_s)
            await self._checkpoint()

    # ------------------------------------------------------------------ CAN input
    def _set_can_state(self, state: str, detail: str = "") -> None:
        """Log and publish a change of the CAN state: one line per change (``detail`` ends it)."""
        if state != self.can_state:
            cs = self.settings.can
            log.log(
                logging.INFO if state == "up" else logging.WARNING,
                "CAN %s/%s %s%s",
                cs.interface,
                cs.channel,
                state,
                detail,
            )
            self.can_state = state
            if self.mqtt is not None:
                self.mqtt.publish_status()

    async def _can_input(self) -> None:
        cs = self.settings.can
        backoff = cs.reopen_min_s
        assert self._samples is not None
        failed_opens = 0  # in a row: the journal gets the 1st, 10th, 100th, ... of an outage
        while True:
            try:
                src = open_source(cs.interface, cs.channel, cs.output_fd, cs.reader_queue_frames)
            except (can.CanError, OSError, ValueError) as exc:
                self.counters["can_open_failures"] += 1
                self._set_can_state("down")
                failed_opens += 1
                if failed_opens == 10 ** (len(str(failed_opens)) - 1):
                    log.warning(
                        "CAN %s/%s cannot be opened (%d attempt(s) so far): %s (retrying up "
                        "to every %.0f s)",
                        cs.interface,
                        cs.channel,
                        failed_opens,
                        exc,
                        cs.reopen_max_s,
                    )
                await asyncio.sleep(backoff)
                backoff = min(backoff * 2.0, cs.reopen_max_s)
                continue
            failed_opens = 0
            self._source = src
            self._reader_progress_mono = time.monotonic()
            backoff = cs.reopen_min_s
            self._set_can_state("up")
            self._on_bus_open()
            try:
                await self._read(src)
            except (can.CanError, OSError) as exc:
                self.counters["can_reopens"] += 1
                self._set_can_state("down")
                log.warning("CAN %s failed: %s (reopen in %.1f s)", cs.channel, exc, backoff)
            finally:
                self._source = None
                self._reader_holding = 0  # the rest of a batch cut by a bus error is gone
                self.counters["reader_dropped"] += src.dropped
                await src.aclose()
            await asyncio.sleep(backoff)
            backoff = min(backoff * 2.0, cs.reopen_max_s)

    def _on_bus_open(self) -> None:
        cs = self.settings.can
        if cs.replay is not None and self.replayer is None:
            self.replayer = LogReplayer(
                cs.replay.log,
                cs.channel,
                cs.replay.speed,
                cs.replay.start_delay_s,
                resume_after_s=self._restored_t_s,
                log_channel=self.replay_channel,
            )
            self.replayer.start()
        if not self._ready_sent:
            self._ready_sent = True
            self.sd.notify("READY=1", f"STATUS=reading {cs.channel}")

    async def _read(self, src: FrameSource) -> None:
        assert self._samples is not None
        expire = self.settings.can.interface == "socketcan"
        while True:
            if expire:
                try:
                    batch = await asyncio.wait_for(src.get_batch(), self.settings.can.staleness_s)
                except TimeoutError:
                    self._reader_progress_mono = time.monotonic()
                    self._pend(self.f2s.expire(time.time()))
                    if self._pending:
                        with contextlib.suppress(asyncio.QueueFull):
                            self._samples.put_nowait(self._take_block())
                    continue
            else:
                batch = await src.get_batch()
            self._reader_progress_mono = time.monotonic()
            self._reader_holding = len(batch)
            for n, msg in enumerate(batch, 1):
                if n % FRAMES_PER_YIELD == 0:
                    # ~10 us a frame: yield now and then so a flood cannot starve timers
                    await self._flush_samples()
                    await asyncio.sleep(0)
                if msg.is_error_frame and msg.arbitration_id & CAN_ERR_BUSOFF:
                    self.counters["bus_off"] += 1
                    self.f2s.count_error_frame()  # still in decode_errors; the line is below
                    self._set_can_state(
                        "bus_off",
                        f" (bus-off error frame, {self.counters['bus_off']} so far; up again "
                        "with the next data frame)",
                    )
                    continue
                if self.can_state == "bus_off" and not msg.is_error_frame:
                    self._set_can_state("up")
                samples = self.f2s.feed(msg)
                if samples:
                    self._pend(samples)
                    if len(self._pending) >= SAMPLE_BATCH:
                        await self._flush_samples()
            await self._flush_samples()
            self._reader_holding = 0

    def _pend(self, samples: list[Sample]) -> None:
        now = time.monotonic()
        self._pending += samples
        self._pending_mono += [now] * len(samples)

    def _take_block(self) -> SampleBlock:
        block = SampleBlock.from_samples(self._pending, self._pending_mono)
        self._pending, self._pending_mono = [], []
        return block

    async def _flush_samples(self) -> None:
        """Queue the pending samples as one block (waits while the queue is full)."""
        if self._pending:
            assert self._samples is not None
            await self._samples.put(self._take_block())
            self._reader_progress_mono = time.monotonic()

    # ------------------------------------------------------------------ estimator
    async def _estimate(self) -> None:
        q = self._samples
        assert q is not None and self.worker is not None
        while True:
            blocks = [await q.get()]
            n = len(blocks[0])
            while n < SAMPLE_BATCH and not q.empty():
                blocks.append(q.get_nowait())
                n += len(blocks[-1])
            self.counters["batches_in_flight"] += 1
            try:
                result = await self.worker.update(SampleBlock.concat(blocks))
                if not self._had_data:
                    self._had_data = True
                    log.info(
                        "first data: %d samples of %d cells up to sample time %.3f s "
                        "(%d frames decoded)",
                        n,
                        self.settings.can.n_cells,
                        float(blocks[-1].t_s[-1]),
                        self.f2s.counters["frames"],
                    )
                self._last_sample_mono = time.monotonic()
                self._take_result(result)
            finally:
                self.counters["batches_in_flight"] -= 1
                for _ in blocks:
                    q.task_done()

    def _take_result(self, result: BatchResult) -> None:
        """A batch's estimates, messages and counters from the bank worker."""
        self.seq = result.seq
        self.inputs = result.inputs
        self.soc_init = result.soc_init
        before = {k: self.bank_counters.get(k, 0) for k in _SAID_ONCE}
        self._merge_bank_counters(result.counters)
        for name, line in _SAID_ONCE.items():  # one line each time a counter moves
            if self.bank_counters.get(name, 0) > before[name]:
                log.warning(line, self.settings.estimator.tuning.gap_s)
        for est in result.estimates:
            self.latest = est
            if self.on_estimates is not None:
                self.on_estimates(est)
        if self.outbox is not None:
            for msg in result.messages:
                self.outbox.put(msg)

    def _health(self, est: Estimates) -> int:
        bits = payloads.health_bits(est, state_dir_failing=self.state_dir_failing)
        if time.monotonic() - self._last_sample_mono > self.settings.can.staleness_s + 1.0:
            bits |= payloads.HEALTH_INPUT_STALE
        return bits

    # ------------------------------------------------------------------ CAN output
    async def _can_output(self) -> None:
        cs = self.settings.can
        if not cs.output:
            return
        period = cs.output_period_s
        next_t = time.monotonic()
        while True:
            next_t += period
            await asyncio.sleep(max(0.0, next_t - time.monotonic()))
            if time.monotonic() - next_t > period:  # fell behind (suspend): do not burst
                next_t = time.monotonic()
            est, src = self.latest, self._source
            if est is None or src is None:
                continue
            frames = self.encoder.pack_frames(est, self._health(est))
            frames += self.encoder.cell_frames(est, self.cycler.next_round())
            try:
                self.counters["can_frames_sent"] += await send_frames(src.bus, frames)
            except (can.CanError, OSError) as exc:
                self.counters["can_send_errors"] += 1
                n = self.counters["can_send_errors"]
                if n == 10 ** (len(str(n)) - 1):
                    log.warning("CAN send failed (%d so far): %s", n, exc)

    # ------------------------------------------------------------------ MQTT
    async def _start_mqtt(self) -> None:
        s = self.settings
        assert self.outbox is not None
        status_topic = payloads.topic(self.prefix, s.pack_id, "status")
        offline = payloads.encode(
            payloads.status_payload("offline", s.pack_id, version=__version__)
        )
        discovery = None
        record: PublishedConfigs | None = None
        if s.mqtt.homeassistant.enabled:
            ha = s.mqtt.homeassistant.prefix
            n = s.can.n_cells
            record = published = PublishedConfigs(s.state.directory)

            def discovery() -> list[tuple[str, bytes]]:
                current = discovery_messages(ha, self.prefix, s.pack_id, n, __version__)
                return published.messages(current)

        self.mqtt = MqttPublisher(
            s.mqtt,
            s.client_id(),
            self.outbox,
            status_topic,
            self._online_payload,
            offline,
            discovery=discovery,
            on_discovery_sent=None if record is None else record.sent,
            on_published=self._on_published,
        )
        await self.mqtt.run()

    def _on_published(self, msg: OutMessage) -> None:
        if self._spooled:
            self._spool_done()
        if msg.t_sample_mono is not None:
            lat = time.monotonic() - msg.t_sample_mono
            self.latencies_s.append(lat)
            if msg.topic.endswith("/cell/0"):
                self.latencies_first_s.append(lat)

    def _online_payload(self) -> bytes:
        return payloads.encode(
            payloads.status_payload(
                "online",
                self.settings.pack_id,
                can_state=self.can_state,
                uptime_s=time.monotonic() - self._t_start,
                counters=self.snapshot(),
                lifetime=self.lifetime(),
                version=__version__,
                inputs=self.inputs,
                mqtt=(
                    {"state": self.mqtt.state, "last_error": self.mqtt.last_error}
                    if self.mqtt is not None
                    else None
                ),
                state_dir="failing" if self.state_dir_failing else "ok",
                soc_init=self.soc_init,
            )
        )

    # ------------------------------------------------------------------ counters
    def snapshot(self) -> dict[str, float]:
        """Counters for the status payload and the log."""
        f = self.f2s.counters
        out: dict[str, float] = {
            "frames": f["frames"],
            "decode_errors": sum(f[k] for k in DECODE_ERROR_KINDS),
            "incomplete_cycles": f["incomplete_cycles"],
            "stale_current": f["stale_current"],
            "samples": f["samples"],
            "ticks": self._since_start("ticks"),
            "swarms": self._since_start("swarms"),
            "time_jumps_back": self._since_start("time_jumps_back"),
            **{
                k: self._since_start(k)
                for k in ("anchors", "reanchors", "gaps_under_load", "readings_lost")
            },
            **{k: self._since_start(k) for k in GATE_COUNTERS},
            "can_frames_sent": self.counters["can_frames_sent"],
            "can_send_errors": self.counters["can_send_errors"],
            "can_reopens": self.counters["can_reopens"],
            "can_open_failures": self.counters["can_open_failures"],
            "can_bus_off": self.counters["bus_off"],
            "watchdog_withheld": self.counters["watchdog_withheld"],
            "reader_drops": self.counters["reader_dropped"]
            + (self._source.dropped if self._source is not None else 0),
            "checkpoints": self.bank_counters.get("checkpoints", 0),
            "checkpoint_errors": self.bank_counters.get("checkpoint_errors", 0),
            "checkpoints_refused": self.bank_counters.get("checkpoints_refused", 0),
            "seq_file_errors": self.bank_counters.get("seq_file_errors", 0),
            "mqtt_withheld": self.bank_counters.get("mqtt_withheld", 0),
            "start_refits": self.bank_counters.get("start_refits", 0),
            "loop_lag_max_ms": round(self.loop_lag_max_s * 1e3, 3),
            "seq": self.seq,
        }
        if self.mqtt is not None and self.outbox is not None:
            out |= {
                "publishes": self.mqtt.counters["publishes"],
                "mqtt_drops": self.outbox.dropped,
                "mqtt_backlog": len(self.outbox),
                "mqtt_reconnects": self.mqtt.counters["reconnects"],
                "mqtt_connect_failures": self.mqtt.counters["connect_failures"],
            }
        return out

    def _since_start(self, name: str) -> int:
        """A bank counter since this process started (the checkpoint carries lifetime totals)."""
        return self.bank_counters.get(name, 0) - self._restored_counters.get(name, 0)

    def lifetime(self) -> dict[str, int]:
        """The estimator state's totals since it began, across restarts from its checkpoint."""
        return {k: self.bank_counters.get(k, 0) for k in ("samples", "ticks", "swarms")}

    def _start_line(self) -> str:
        """What this daemon is about to do: version, pack, bus, broker, state directory."""
        s = self.settings
        cs, m = s.can, s.mqtt
        bus = f"CAN {cs.interface}/{cs.channel} ({self.mapping.name})"
        if cs.replay is not None:
            bus += f" replaying {cs.replay.log} at {cs.replay.speed:g}x"
            if self.replay_channel is not None:
                bus += f" (its {self.replay_channel} frames)"
        if not cs.output:
            bus += ", no output frames"
        if m.enabled:
            host, port, tls = m.endpoint()
            broker = f"MQTT {host}:{port}{' TLS' if tls else ''} as {s.client_id()}"
            broker += f" under {self.prefix}/{s.pack_id}/"
            if m.homeassistant.enabled:
                broker += " with Home Assistant discovery"
        else:
            broker = "MQTT off"
        return (
            f"bmsid {__version__} starting: pack {s.pack_id}, {cs.n_cells} cells "
            f"({self.cell.name}, {s.estimator.variant}); {bus}; {broker}; "
            f"state in {s.state.directory}"
        )

    def _counter_line(self) -> str:
        return " ".join(f"{k}={v}" for k, v in self.snapshot().items())

    async def _status(self) -> None:
        while True:
            await asyncio.sleep(self.settings.status_period_s)
            log.debug("counters: %s", self._counter_line())
            if self.mqtt is not None:
                self.mqtt.publish_status()

    async def _log_counters(self) -> None:
        """The counters at INFO every ``log_period_s``: a healthy daemon's heartbeat."""
        while True:
            await asyncio.sleep(self.settings.log_period_s)
            mqtt = f" mqtt={self.mqtt.state}" if self.mqtt is not None else ""
            log.info(
                "counters: can=%s%s %s window_lag_max_ms=%.2f",
                self.can_state,
                mqtt,
                self._counter_line(),
                self._lag_window_max_s * 1e3,
            )
            self._lag_window_max_s = 0.0

    async def _lag_monitor(self) -> None:
        while True:
            t0 = time.monotonic()
            await asyncio.sleep(LAG_INTERVAL_S)
            lag = max(0.0, time.monotonic() - t0 - LAG_INTERVAL_S)
            self.loop_lags_s.append(lag)
            self.loop_lag_max_s = max(self.loop_lag_max_s, lag)
            self._lag_window_max_s = max(self._lag_window_max_s, lag)

    def pipeline(self) -> Pipeline:
        """The pipeline as the watchdog sees it (:mod:`bmsid.daemon.watchdog`)."""
        src, worker, q = self._source, self.worker, self._samples
        return Pipeline(
            now_s=time.monotonic(),
            frames_waiting=self._reader_holding + (src.waiting if src is not None else 0),
            reader_progress_s=self._reader_progress_mono,
            samples_waiting=q.qsize() if q is not None else 0,
            bank_calls=worker.calls if worker is not None else 0,
            bank_progress_s=worker.progress_mono if worker is not None else time.monotonic(),
        )

    async def _watchdog(self) -> None:
        """``WATCHDOG=1`` every ``WatchdogSec``/2 while the pipeline moves or idles, none
        while it is stuck (:func:`~bmsid.daemon.watchdog.stall`): systemd then restarts it."""
        assert self.sd.watchdog_s is not None and self.worker is not None
        limit = self.sd.watchdog_s
        probe: asyncio.Task[None] | None = None
        stuck_since: float | None = None
        try:
            while True:
                await asyncio.sleep(limit / 2.0)
                if probe is not None and probe.done():
                    probe.result()  # a dead worker raises: the daemon stops, as on a batch
                    probe = None
                worker = self.worker
                if probe is None and worker.calls == 0:
                    # a silent bus gives the worker no call: ask it one, so a hung worker
                    # shows as a call unanswered
                    probe = asyncio.create_task(worker.ping(), name="bank-probe")
                why = stall(self.pipeline(), limit)
                if why is None:
                    self.sd.notify("WATCHDOG=1")
                    if stuck_since is not None:
                        log.warning(
                            "watchdog: the pipeline moves again after %.1f s: WATCHDOG=1 resumed",
                            time.monotonic() - stuck_since,
                        )
                        stuck_since = None
                    continue
                self.counters["watchdog_withheld"] += 1
                if stuck_since is None:
                    stuck_since = time.monotonic()
                    log.error(
                        "watchdog: %s: WATCHDOG=1 withheld, systemd restarts bmsid once "
                        "WatchdogSec has passed since the last one",
                        why,
                    )
        finally:
            if probe is not None:
                probe.cancel()


def run_daemon(settings: Settings) -> int:
    """``bmsid run``: the daemon with SIGTERM/SIGINT as graceful stop, SIGHUP ignored (logged);
    returns the exit code."""

    async def main() -> int:
        daemon = Daemon(settings)
        sys.setswitchinterval(SWITCH_INTERVAL_S)
        loop = asyncio.get_running_loop()
        for sig in (signal.SIGTERM, signal.SIGINT):
            loop.add_signal_handler(sig, daemon.request_stop)
        loop.add_signal_handler(signal.SIGHUP, daemon.on_sighup)
        return await daemon.run()

    return asyncio.run(main())


def state_file(settings: Settings) -> Path:
    return settings.state.directory / f"{settings.pack_id}.ckpt.npz"
