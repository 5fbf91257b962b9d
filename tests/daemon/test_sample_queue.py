"""The columnar sample buffer between the daemon's decoder and its bank worker."""

from __future__ import annotations

import asyncio
import gc
import pickle

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from bmsid.daemon.sample_queue import SampleQueue
from bmsid.samples import Sample, SampleBlock

finite = st.floats(allow_nan=False, allow_infinity=False, width=64)
voltage = st.floats(allow_infinity=False, width=64)  # NaN = a missing cell


def _sample(t: float, n_cells: int = 4) -> Sample:
    return Sample(t_s=t, current_A=t / 10.0, cell_voltages_V=np.full(n_cells, 3.6 + t * 1e-6))


@given(
    st.integers(1, 6).flatmap(
        lambda n_cells: st.lists(
            st.lists(
                st.tuples(finite, finite, st.lists(voltage, min_size=n_cells, max_size=n_cells)),
                min_size=1,
                max_size=8,
            ),
            min_size=1,
            max_size=5,
        )
    )
)
def test_blocks_carry_every_sample_exactly_and_in_order(
    chunks: list[list[tuple[float, float, list[float]]]],
) -> None:
    samples = [[Sample(t, i, np.asarray(v)) for t, i, v in chunk] for chunk in chunks]
    blocks = [SampleBlock.from_samples(c, [float(k) for k in range(len(c))]) for c in samples]
    block = pickle.loads(pickle.dumps(SampleBlock.concat(blocks)))  # as the worker gets it
    flat = [s for c in samples for s in c]
    assert len(block) == len(flat)
    for k, s in enumerate(flat):
        assert block.t_s[k] == s.t_s and block.current_A[k] == s.current_A
        np.testing.assert_array_equal(block.cell_voltages_V[k], s.cell_voltages_V)
    assert block.t_complete_mono is not None
    assert block.t_complete_mono.tolist() == [float(k) for c in samples for k in range(len(c))]


def test_a_block_needs_samples_and_their_times() -> None:
    with pytest.raises(ValueError):
        SampleBlock.from_samples([], [])
    with pytest.raises(ValueError):
        SampleBlock.from_samples([_sample(0.0)], [0.0, 1.0])


def test_the_bound_counts_samples_not_blocks() -> None:
    async def main() -> None:
        q = SampleQueue(100)
        block = SampleBlock.from_samples([_sample(t) for t in range(30)], [0.0] * 30)
        for _ in range(4):  # 120 samples: the last block overshoots, as documented
            q.put_nowait(block)
        assert q.qsize() == 120 and q.full()
        with pytest.raises(asyncio.QueueFull):
            q.put_nowait(block)
        waiting = asyncio.create_task(q.put(block))
        await asyncio.sleep(0.01)
        assert not waiting.done()  # the reader waits while the bank is behind
        q.get_nowait()
        q.task_done()
        await asyncio.wait_for(waiting, 1.0)
        assert q.qsize() == 120
        for _ in range(4):
            q.get_nowait()
            q.task_done()
        assert q.qsize() == 0 and q.empty()
        await asyncio.wait_for(q.join(), 1.0)

    asyncio.run(main())


def _tracked_objects_added(build: object) -> int:
    gc.collect()
    before = len(gc.get_objects())
    assert callable(build)
    keep = build()
    gc.collect()
    added = len(gc.get_objects()) - before
    del keep
    return added


def test_queued_samples_add_no_work_for_the_garbage_collector() -> None:
    """A full collection walks every tracked object: a backlog of samples must not be ~3 each."""
    n, per_block = 12_800, 64
    samples = [_sample(float(t), 16) for t in range(n)]

    def queue_blocks() -> SampleQueue:
        q = SampleQueue(n)
        for k in range(0, n, per_block):
            q.put_nowait(SampleBlock.from_samples(samples[k : k + per_block], [0.0] * per_block))
        return q

    def queue_samples() -> list[tuple[Sample, float]]:  # what the daemon queued before
        return [(_sample(float(t), 16), 0.0) for t in range(n)]

    assert _tracked_objects_added(queue_samples) >= 2 * n  # the measure sees a sample backlog
    assert _tracked_objects_added(queue_blocks) < 2 * (n // per_block) + 50
