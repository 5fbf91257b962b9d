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

from bmsid.samples import SampleBlock

__all__ = ["SampleBlock", "SampleQueue"]


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
