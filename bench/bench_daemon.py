"""Benchmarks of the live daemon on python-can's ``virtual`` bus (``bmsid run`` in-process).

    PYTHONPATH=service python bench/bench_daemon.py [--quick]

1. throughput: a pack's frames sent as fast as the daemon takes them (the virtual reader pushes
   back, so nothing is dropped): sustained frames/s and samples/s through decoder + bank.
2. real time, 96 cells at 10 Hz for ``--realtime-s`` seconds, MQTT to a Mosquitto started here
   (when installed): latency from the completed sample (its last frame decoded) to the broker's
   acknowledgement of its MQTT message (p50/p99), CPU share of one core (CPU time of the daemon
   and its bank worker process over wall time; includes the in-process sender thread, so it is
   an upper bound), loop lag.
3. memory: ``--hours`` of data for ``--mem-cells`` cells at 1 Hz replayed as fast as possible;
   resident set size (daemon + bank worker) sampled along the way (it must stay flat).

The frames of run 1 are generated before the clock starts; runs 2 and 3 generate them on the
fly in the sender thread (run 3 would not fit in memory otherwise).

Results are printed as one table (and as JSON with ``--json``).
"""

from __future__ import annotations

import argparse
import asyncio
import gc
import json
import os
import resource
import sys
import tempfile
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import can
import numpy as np

from bmsid.canbus.logs import csv_to_messages
from bmsid.canbus.mapping import default_mapping
from bmsid.config.settings import Settings
from bmsid.daemon.core import SWITCH_INTERVAL_S, Daemon
from bmsid.daemon.local_broker import start_mosquitto
from bmsid.profiles import dst_current


def _children() -> list[int]:
    """Direct child processes of this one (the bank worker, multiprocessing's tracker)."""
    pids: list[int] = []
    for f in Path("/proc/self/task").glob("*/children"):
        pids += [int(x) for x in f.read_text().split()]
    return pids


def _rss_of_mb(pid: str) -> float:
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024.0
    except OSError:
        pass
    return 0.0


def _rss_mb() -> float:
    """Resident set of the daemon: this process plus its children, MB."""
    return sum(_rss_of_mb(pid) for pid in ["self", *map(str, _children())])


def _cpu_s() -> float:
    """CPU time of this process and its live children, s."""
    tick = os.sysconf("SC_CLK_TCK")
    total = time.process_time()
    for pid in _children():
        try:
            fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        total += (int(fields[11]) + int(fields[12])) / tick  # utime + stime
    return total


def _pack_frames(
    n_cells: int, n_ticks: int, rate_hz: float, t0: float, seed: int = 0
) -> Iterator[can.Message]:
    """DST current (1C peak, 70 Ah cells), voltages of a resistive cell plus noise, in chunks."""
    rng = np.random.default_rng(seed)
    chunk = 2000
    for k0 in range(0, n_ticks, chunk):
        k = np.arange(k0, min(k0 + chunk, n_ticks))
        t = k / rate_hz
        i = dst_current(t, 70.0)
        r0 = 2e-3 * (1.0 + 0.1 * np.arange(n_cells) / n_cells)
        v = 3.7 - i[:, None] * r0[None, :] + rng.normal(0.0, 5e-4, (k.size, n_cells))
        yield from csv_to_messages(t, i, v, default_mapping(), t0_s=t0)


def _settings(
    channel: str, n_cells: int, port: int | None, state: Path, publish_period_s: float = 1.0
) -> Settings:
    return Settings(
        pack_id="bench",
        systemd_notify=False,
        status_period_s=3600.0,
        can={"interface": "virtual", "channel": channel, "n_cells": n_cells},
        mqtt={
            "enabled": port is not None,
            "url": f"mqtt://127.0.0.1:{port or 1883}",
            "publish_period_s": publish_period_s,
        },
        state={"directory": state, "checkpoint_period_s": 60.0},
    )


async def _run(
    settings: Settings,
    frames: Iterator[can.Message],
    n_frames: int,
    *,
    realtime_hz: float | None = None,
    frames_per_tick: int = 1,
    sample_rss_s: float = 0.0,
    probe_full_gc: bool = False,
) -> dict[str, Any]:
    daemon = Daemon(settings, shutdown_timeout_s=5.0)
    task = asyncio.create_task(daemon.run())
    while daemon.can_state != "up":
        await asyncio.sleep(0.01)
    if daemon.mqtt is not None:
        while not daemon.mqtt.connected:
            await asyncio.sleep(0.01)
    done = threading.Event()

    def send() -> None:
        bus = can.Bus(interface="virtual", channel=settings.can.channel, preserve_timestamps=True)

        def drain() -> None:
            # the daemon's CAN output arrives on this bus too: drop it, or this process's
            # memory and heap (what the figures measure) hold every output frame of the run
            while bus.recv(0) is not None:
                pass

        t_start = time.monotonic()
        for n, m in enumerate(frames):
            if realtime_hz is not None:
                tick = n // frames_per_tick
                delay = t_start + tick / realtime_hz - time.monotonic()
                if delay > 0:
                    time.sleep(delay)
                m.timestamp = time.time()
            else:
                # stay at most ~20k frames ahead: the virtual bus queues without bound, and the
                # memory figure should be the daemon's, not the sender's backlog
                while n - daemon.f2s.counters["frames"] > 20_000:
                    drain()
                    time.sleep(0.005)
            bus.send(m)
            if n % 512 == 0:
                drain()
        bus.shutdown()
        done.set()

    rss: list[tuple[float, float]] = []
    cpu0, wall0 = _cpu_s(), time.monotonic()
    threading.Thread(target=send, daemon=True).start()
    last_rss = 0.0
    q = daemon._samples
    while True:
        await asyncio.sleep(0.05)
        now = time.monotonic()
        if sample_rss_s and now - last_rss >= sample_rss_s:
            rss.append((daemon.bank_counters["samples"], _rss_mb()))
            last_rss = now
        idle = q is not None and q.empty() and daemon.counters["batches_in_flight"] == 0
        flushed = daemon.outbox is None or len(daemon.outbox) == 0
        if done.is_set() and daemon.f2s.counters["frames"] >= n_frames and idle and flushed:
            break
    wall, cpu = time.monotonic() - wall0, _cpu_s() - cpu0
    gc_ms = None
    if probe_full_gc:  # what a full collection costs the loop with this run's live objects
        t_gc = time.perf_counter()
        gc.collect()
        gc_ms = (time.perf_counter() - t_gc) * 1e3
    children = [_rss_of_mb(str(pid)) for pid in _children()]
    rss_split = {"daemon": _rss_of_mb("self"), "children": children}
    snap = daemon.snapshot()
    lat = np.asarray(daemon.latencies_s) * 1e3
    lat1 = np.asarray(daemon.latencies_first_s) * 1e3
    lags = np.asarray(daemon.loop_lags_s) * 1e3
    daemon.request_stop()
    await task
    return {
        "wall_s": wall,
        "cpu_share": cpu / wall,
        "frames": snap["frames"],
        "samples": snap["samples"],
        "frames_per_s": snap["frames"] / wall,
        "samples_per_s": snap["samples"] / wall,
        "reader_drops": snap["reader_drops"],
        "mqtt_drops": snap.get("mqtt_drops", 0),
        "loop_lag_max_ms": snap["loop_lag_max_ms"],
        "loop_lag_p99_ms": float(np.percentile(lags, 99)) if lags.size else None,
        "loop_lag_p50_ms": float(np.percentile(lags, 50)) if lags.size else None,
        "latency_p50_ms": float(np.percentile(lat, 50)) if lat.size else None,
        "latency_p99_ms": float(np.percentile(lat, 99)) if lat.size else None,
        "latency_first_p50_ms": float(np.percentile(lat1, 50)) if lat1.size else None,
        "latency_first_p99_ms": float(np.percentile(lat1, 99)) if lat1.size else None,
        "publishes": snap.get("publishes", 0),
        "rss_mb": rss,
        "rss_split_mb": rss_split,
        "full_gc_ms": gc_ms,
    }


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--cells", type=int, default=96)
    ap.add_argument("--throughput-s", type=float, default=300.0, help="seconds of data")
    ap.add_argument("--realtime-s", type=float, default=60.0, help="wall seconds at 10 Hz")
    ap.add_argument("--hours", type=float, default=24.0, help="memory run: hours of data")
    ap.add_argument("--mem-cells", type=int, default=16)
    ap.add_argument("--quick", action="store_true", help="short runs (smoke test)")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args()
    if args.quick:
        args.throughput_s, args.realtime_s, args.hours = 60.0, 10.0, 0.5
    sys.setswitchinterval(SWITCH_INTERVAL_S)
    tmp = Path(tempfile.mkdtemp(prefix="bmsid-bench-"))
    broker = start_mosquitto(tmp)
    port = broker[1] if broker else None
    fpt = 1 + (args.cells + 3) // 4  # current frame + one frame per 4 cells
    results: dict[str, Any] = {"cells": args.cells, "mosquitto": broker is not None}
    try:
        n_ticks = int(args.throughput_s * 10)
        results["throughput"] = asyncio.run(
            _run(
                _settings("bench-tp", args.cells, None, tmp / "s1"),
                iter(list(_pack_frames(args.cells, n_ticks, 10.0, 1.7e9))),
                n_ticks * fpt,
            )
        )
        n_ticks = int(args.realtime_s * 10)
        results["realtime"] = asyncio.run(
            _run(
                _settings("bench-rt", args.cells, port, tmp / "s2"),
                _pack_frames(args.cells, n_ticks, 10.0, 0.0),
                n_ticks * fpt,
                realtime_hz=10.0,
                frames_per_tick=fpt,
                probe_full_gc=True,
            )
        )
        n_ticks = int(args.hours * 3600)
        mfpt = 1 + (args.mem_cells + 3) // 4
        results["memory"] = asyncio.run(
            _run(
                # MQTT every 60 s of data: at ~100x real time 1 s would outrun the broker and the
                # RSS would show the (bounded) outbox filling up, not the daemon
                _settings("bench-mem", args.mem_cells, port, tmp / "s3", publish_period_s=60.0),
                _pack_frames(args.mem_cells, n_ticks, 1.0, 1.7e9),
                n_ticks * mfpt,
                sample_rss_s=2.0,
            )
        )
    finally:
        if broker is not None:
            broker[0].terminate()
            broker[0].wait(5)
    results["max_rss_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    if args.json:
        print(json.dumps(results, indent=2))
        return 0
    tp, rt, mem = results["throughput"], results["realtime"], results["memory"]
    print(f"bmsid daemon benchmark, virtual bus, {args.cells} cells")
    print(
        f"  throughput (no MQTT): {tp['frames_per_s']:.0f} frames/s = "
        f"{tp['samples_per_s']:.0f} samples/s sustained, drops {tp['reader_drops']}, "
        f"loop lag p50 {tp['loop_lag_p50_ms']:.1f} ms, p99 {tp['loop_lag_p99_ms']:.1f} ms, "
        f"max {tp['loop_lag_max_ms']:.1f} ms"
    )
    lat = (
        f"all messages p50 {rt['latency_p50_ms']:.1f} ms, p99 {rt['latency_p99_ms']:.1f} ms; "
        f"first message of a tick p50 {rt['latency_first_p50_ms']:.1f} ms, "
        f"p99 {rt['latency_first_p99_ms']:.1f} ms"
        if rt["latency_p50_ms"] is not None
        else "n/a (no mosquitto)"
    )
    print(
        f"  real time 10 Hz, {args.realtime_s:.0f} s: CPU {100 * rt['cpu_share']:.1f} % of one "
        f"core, latency last frame -> MQTT ack {lat}, loop lag p99 "
        f"{rt['loop_lag_p99_ms']:.1f} ms, max {rt['loop_lag_max_ms']:.1f} ms, "
        f"MQTT messages {rt['publishes']}, a full garbage collection at the end "
        f"{rt['full_gc_ms']:.1f} ms"
    )
    r = np.asarray(mem["rss_mb"])
    if r.size >= 4 and np.unique(r[:, 0]).size >= 3:
        half = r[r.shape[0] // 2 :]
        slope = np.polyfit(half[:, 0], half[:, 1], 1)[0] * 1e5
        print(
            f"  memory, {args.hours:g} h of data x {args.mem_cells} cells in "
            f"{mem['wall_s']:.0f} s: RSS {r[0, 1]:.0f} -> {r[-1, 1]:.0f} MB (max "
            f"{r[:, 1].max():.0f}), slope over the 2nd half {slope:+.2f} MB per 100k samples; "
            f"at the end this process {mem['rss_split_mb']['daemon']:.0f} MB, children "
            f"{', '.join(f'{c:.0f}' for c in mem['rss_split_mb']['children'])} MB"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
