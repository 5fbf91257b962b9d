"""What blocks the daemon's event loop: wall lag vs the loop thread's own CPU per callback.

    PYTHONPATH=service python bench/bench_loop_blocking.py [--cells 96] [--seconds 300]
    PYTHONPATH=service python bench/bench_loop_blocking.py --replay-hours 24 --cells 16
    PYTHONPATH=service python bench/bench_loop_blocking.py --realtime-s 60

Runs one of ``bench_daemon``'s scenarios: the throughput flood (a pack's frames at 10 Hz as fast
as the daemon takes them, no MQTT; the default), the real-time run (``--realtime-s``: 10 Hz in
real time, MQTT to a Mosquitto started here) or the memory run (``--replay-hours``: 1 Hz data
replayed as fast as possible, MQTT), with every event-loop callback timed twice: wall
clock, and ``time.thread_time()`` of the loop thread. A callback whose wall time is far above
its CPU time was waiting for a core or for the interpreter lock (held by the in-process sender
and reader threads), not computing; one whose CPU time is large computed, or ran a garbage
collection that its allocations triggered. Full (generation 2) collections are counted and timed.
"""

from __future__ import annotations

import argparse
import asyncio
import asyncio.events
import gc
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import bench_daemon
from bmsid.daemon.core import SWITCH_INTERVAL_S
from bmsid.daemon.local_broker import start_mosquitto

SLOW_S = 0.001
_walls: list[float] = []
_cpus: list[float] = []
_names: list[str] = []
_gc2: list[float] = []
_gc_t0: dict[str, float] = {}


def _timed_run(self: asyncio.events.Handle, _orig: Any = asyncio.events.Handle._run) -> None:
    t0, c0 = time.perf_counter(), time.thread_time()
    _orig(self)
    wall = time.perf_counter() - t0
    if wall > SLOW_S:
        _walls.append(wall)
        _cpus.append(time.thread_time() - c0)
        _names.append(_callback_name(self))


def _callback_name(handle: asyncio.events.Handle) -> str:
    cb = handle._callback  # type: ignore[attr-defined]
    owner = getattr(cb, "__self__", None)
    if isinstance(owner, asyncio.Task):
        return f"task {owner.get_name()} ({owner.get_coro().__qualname__})"  # type: ignore[union-attr]
    return str(getattr(cb, "__qualname__", repr(cb)))[:80]


def _gc_callback(phase: str, info: dict[str, int]) -> None:
    if phase == "start":
        _gc_t0["t"] = time.perf_counter()
    elif info["generation"] == 2:
        _gc2.append(time.perf_counter() - _gc_t0["t"])


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--cells", type=int, default=96)
    ap.add_argument("--seconds", type=float, default=300.0, help="flood: seconds of data")
    ap.add_argument("--replay-hours", type=float, default=None, help="memory-run scenario")
    ap.add_argument("--realtime-s", type=float, default=None, help="real-time 10 Hz scenario")
    args = ap.parse_args()
    sys.setswitchinterval(SWITCH_INTERVAL_S)
    tmp = Path(tempfile.mkdtemp(prefix="bmsid-bench-"))
    fpt = 1 + (args.cells + 3) // 4
    broker = None
    realtime: dict[str, Any] = {}
    if args.realtime_s is not None:
        scenario = f"real time 10 Hz for {args.realtime_s:g} s"
        broker = start_mosquitto(tmp)
        n_ticks = int(args.realtime_s * 10)
        frames = bench_daemon._pack_frames(args.cells, n_ticks, 10.0, 0.0)
        port = broker[1] if broker else None
        settings = bench_daemon._settings("loop-blocking", args.cells, port, tmp / "state")
        realtime = {"realtime_hz": 10.0, "frames_per_tick": fpt}
    elif args.replay_hours is None:
        scenario = "flood"
        n_ticks = int(args.seconds * 10)
        frames = iter(list(bench_daemon._pack_frames(args.cells, n_ticks, 10.0, 1.7e9)))
        settings = bench_daemon._settings("loop-blocking", args.cells, None, tmp / "state")
    else:
        scenario = f"{args.replay_hours:g} h replay"
        broker = start_mosquitto(tmp)
        n_ticks = int(args.replay_hours * 3600)
        frames = bench_daemon._pack_frames(args.cells, n_ticks, 1.0, 1.7e9)
        port = broker[1] if broker else None
        settings = bench_daemon._settings("loop-blocking", args.cells, port, tmp / "state", 60.0)
    asyncio.events.Handle._run = _timed_run  # type: ignore[method-assign]
    gc.callbacks.append(_gc_callback)
    try:
        result = asyncio.run(bench_daemon._run(settings, frames, n_ticks * fpt, **realtime))
    finally:
        if broker is not None:
            broker[0].terminate()
            broker[0].wait(5)
    # the harness's own coroutine (bench_daemon._run: statistics, RSS) is not the daemon's
    keep = np.asarray([not n.endswith("(_run)") for n in _names], dtype=bool)
    walls, cpus = np.asarray(_walls)[keep] * 1e3, np.asarray(_cpus)[keep] * 1e3
    names = np.asarray(_names, dtype=object)[keep]
    print(f"{scenario}, {args.cells} cells, {result['frames_per_s']:.0f} frames/s")
    print(
        f"  loop lag (wall): p50 {result['loop_lag_p50_ms']:.2f} ms, p99 "
        f"{result['loop_lag_p99_ms']:.2f} ms, max {result['loop_lag_max_ms']:.2f} ms"
    )
    if cpus.size:
        print(
            f"  callbacks over {SLOW_S * 1e3:g} ms wall: {cpus.size}; wall max {walls.max():.2f} "
            "ms;"
            f" the loop thread's own CPU in them: p99 {np.percentile(cpus, 99):.2f} ms, "
            f"max {cpus.max():.2f} ms"
        )
    for i in np.argsort(cpus)[::-1][:5]:
        print(f"    {cpus[i]:6.2f} ms CPU, {walls[i]:6.2f} ms wall: {names[i]}")
    print(
        f"  full garbage collections during the run (the daemon's start-up one included): "
        f"{len(_gc2)}, longest {max(_gc2, default=0.0) * 1e3:.1f} ms"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
