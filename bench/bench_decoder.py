"""Decoded frames per second: bmsid's decoder + sample assembler vs a bare cantools loop.

One core, in-process (no bus): the frames of a 96-cell pack at one tick per row (current frame
+ 24 cell frames per tick), bmsid's own DBC. A saturated 1 Mbit/s classic CAN bus carries about
8,800 frames/s; bmsid must handle at least twice that.

    PYTHONPATH=service python bench/bench_decoder.py [--ticks 2000] [--cells 96]
"""

from __future__ import annotations

import argparse
import time

import can
import cantools
import numpy as np

from bmsid.canbus.frames_to_samples import FrameToSamples
from bmsid.canbus.logs import csv_to_messages
from bmsid.canbus.mapping import BusMapping, default_mapping

BUS_LIMIT_FPS = 8_800


def make_frames(mapping: BusMapping, ticks: int, cells: int) -> list[can.Message]:
    rng = np.random.default_rng(0)
    t = np.arange(ticks) * 0.1
    return list(
        csv_to_messages(
            t, rng.uniform(-100, 100, ticks), rng.uniform(3.0, 4.2, (ticks, cells)), mapping
        )
    )


def bench_bmsid(mapping: BusMapping, frames: list[can.Message], cells: int) -> tuple[float, int]:
    f2s = FrameToSamples(mapping, cells)
    t0 = time.perf_counter()
    n = 0
    for m in frames:
        n += len(f2s.feed(m))
    return time.perf_counter() - t0, n


def bench_cantools(db: cantools.database.can.Database, frames: list[can.Message]) -> float:
    cache = {(m.frame_id, m.is_extended_frame): m for m in db.messages}
    t0 = time.perf_counter()
    for f in frames:
        cache[(f.arbitration_id, f.is_extended_id)].decode(bytes(f.data), decode_choices=False)
    return time.perf_counter() - t0


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__)
    p.add_argument("--ticks", type=int, default=2000)
    p.add_argument("--cells", type=int, default=96)
    p.add_argument("--repeat", type=int, default=5)
    args = p.parse_args()
    mapping = default_mapping()
    frames = make_frames(mapping, args.ticks, args.cells)
    t_bmsid = min(bench_bmsid(mapping, frames, args.cells)[0] for _ in range(args.repeat))
    _, n_samples = bench_bmsid(mapping, frames, args.cells)
    t_bare = min(bench_cantools(mapping.database(), frames) for _ in range(args.repeat))
    fps_bmsid, fps_bare = len(frames) / t_bmsid, len(frames) / t_bare
    print(f"frames: {len(frames)}  samples: {n_samples}  cells: {args.cells}")
    print(
        f"bmsid decoder + assembler: {fps_bmsid:10,.0f} frames/s ({1e6 / fps_bmsid:.2f} us/frame)"
    )
    print(f"bare cantools decode:      {fps_bare:10,.0f} frames/s ({1e6 / fps_bare:.2f} us/frame)")
    print(f"ratio bmsid / bare:        {fps_bmsid / fps_bare:10.2f}")
    headroom = fps_bmsid / BUS_LIMIT_FPS
    print(f"headroom vs a saturated 1 Mbit/s bus ({BUS_LIMIT_FPS} fps): {headroom:.1f}x")
    if fps_bmsid < 2 * BUS_LIMIT_FPS:
        raise SystemExit("FAIL: below twice a saturated 1 Mbit/s bus")


if __name__ == "__main__":
    main()
