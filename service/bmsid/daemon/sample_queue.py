"""The daemon's buffer between decoding (event loop) and the bank (worker): samples as columns.

When the bank falls behind (an accelerated replay, a burst after a stall) this buffer holds
tens of thousands of samples. Kept as :class:`~bmsid.samples.Sample` objects, each one adds
garbage-collector-tracked objects to the loop's heap (the sample, its flag set, the queue
entry), and every automatic full collection then walks all of them on the loop: 50k queued
samples cost ~55 ms a collection. As numpy columns they cost the collector nothing (arrays
are not tracked), one small object per block, and they pickle to the worker in one piece.
"""

from __future__ import annotations

import asyncio
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from bmsid.samples import FloatArray, Sample


@dataclass(frozen=True, slots=True)
class SampleBlock:
    """Consecutive pack samples as columns: what the bank worker consumes.

    Only what the estimator bank reads crosses over; temperatures, the bus counter and the
    decoder's flags stay with the decoder's counters.

    Attributes:
        t_s: sample times in seconds, shape (n,).
        current_A: pack current in amperes, positive = discharge, shape (n,).
        cell_voltages_V: cell terminal voltages in volts, NaN where missing, shape (n, n_cells).
        t_complete_mono: monotonic time in seconds at which each sample was complete (the
            start of the publish latency), shape (n,).
    """

    t_s: FloatArray
    current_A: FloatArray
    cell_voltages_V: FloatArray
    t_complete_mono: FloatArray

    def __len__(self) -> int:
        return int(self.t_s.shape[0])

    @classmethod
    def from_samples(
        cls, samples: Sequence[Sample], t_complete_mono: Sequence[float]
    ) -> SampleBlock:
        if len(samples) != len(t_complete_mono) or not samples:
            raise ValueError("a block needs one completion time per sample, and a sample")
        return cls(
            t_s=np.fromiter((s.t_s for s in samples), np.float64, len(samples)),
            current_A=np.fromiter((s.current_A for s in samples), np.float64, len(samples)),
            cell_voltages_V=np.stack([s.cell_voltages_V for s in samples]).astype(
                np.float64, copy=False
            ),
            t_complete_mono=np.asarray(t_complete_mono, dtype=np.float64),
        )

    @classmethod
    def concat(cls, blocks: Sequence[SampleBlock]) -> SampleBlock:
        if len(blocks) == 1:
            return blocks[0]
        return cls(
            t_s=np.concatenate([b.t_s for b in blocks]),
            current_A=np.concatenate([b.current_A for b in blocks]),
            cell_voltages_V=np.concatenate([b.cell_voltages_V for b in blocks]),
            t_complete_mono=np.concatenate([b.t_complete_mono for b in blocks]),
        )


class SampleQueue(asyncio.Queue[SampleBlock]):
    """An :class:`asyncio.Queue` of blocks whose bound (``maxsize``) counts samples, not blocks.

    ``put`` waits while ``maxsize`` samples or more are queued, so a block may overshoot the
    bound by less than its own length. ``task_done`` and ``join`` count blocks, as they were put.
    """

    def _init(self, maxsize: int) -> None:
        super()._init(maxsize)
        self._n_samples = 0

    def _put(self, item: SampleBlock) -> None:
        super()._put(item)
        self._n_samples += len(item)

    def _get(self) -> SampleBlock:
        item = super()._get()
        self._n_samples -= len(item)
        return item

    def qsize(self) -> int:
        """Samples queued (``full()`` compares this with ``maxsize``)."""
        return self._n_samples
