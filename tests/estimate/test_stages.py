"""The engine as stages: blocks equal samples, per-cell numbers, reset, checkpoint formats."""

from __future__ import annotations

from itertools import pairwise
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from bmsid.config.engine import build_bank, cell_model
from bmsid.daemon.checkpoint import CheckpointKey, load_checkpoint
from bmsid.estimate.bank import EstimatorBank
from bmsid.estimate.fields import FIELD_NAMES
from bmsid.estimate.observer_tuning import ObserverTuning
from bmsid.estimate.tuning import EstimatorTuning, Variant
from bmsid.estimate.types import EstimateBlock, Quality
from bmsid.samples import SampleBlock
from bmsid.synthetic import paper_dst_case

DATA = Path(__file__).parent / "data"
# The observer couples the cells of a bank only through the pack's current offset, the hysteresis
# map, the hysteresis state's error and the draw at rest they share (the rests' reading and the
# rest limit are the pack's): all pinned here, so cells compare one by one.
FAST = EstimatorTuning(window_s=120.0, min_window_s=40.0, swarm_period_s=60.0, n_iter=3,
                       n_iter_first=4, n_particles=4, swarm_min_steps=0,
                       observer=ObserverTuning(offset_prior_C=1e-12,
                                               offset_walk_C_per_sqrt_day=0.0,
                                               hysteresis_prior_rel=1e-12,
                                               hysteresis_prior_floor_V=0.0,
                                               hysteresis_error=False,
                                               rest_draw=False))  # fmt: skip
#: The engine of bmsid 0.1 had no observer: its checkpoints continue as it did without one.
FAST_COULOMB = FAST.model_copy(update={"observer": ObserverTuning(enabled=False)})
RUN = paper_dst_case(400, r0_spread=np.array([1.0, 1.3]))
BLOCK = SampleBlock.from_arrays(RUN.t_s, RUN.current_A, RUN.voltages_V)


def _assert_same(a: EstimateBlock, b: EstimateBlock) -> None:
    np.testing.assert_array_equal(a.t_s, b.t_s)
    np.testing.assert_array_equal(a.quality, b.quality)
    for name in FIELD_NAMES:
        np.testing.assert_array_equal(a[name], b[name], err_msg=name)


def _by_samples(bank: EstimatorBank, block: SampleBlock) -> EstimateBlock:
    cols = zip(block.t_s, block.current_A, block.cell_voltages_V, strict=True)
    rows = [bank.update(t, i, v) for t, i, v in cols]
    return EstimateBlock.from_rows([r for r in rows if r is not None], bank.n)


@settings(max_examples=8, deadline=None)
@given(cuts=st.lists(st.integers(1, 399), max_size=6, unique=True))
def test_blocks_of_any_size_equal_sample_by_sample(cuts: list[int]) -> None:
    edges = [0, *sorted(cuts), len(BLOCK)]
    bank = build_bank(RUN.cell, 2, "hy-affrls-lpso", FAST, soc0=0.98)
    parts = [bank.update_block(BLOCK.slice(a, b)) for a, b in pairwise(edges)]
    ref = _by_samples(build_bank(RUN.cell, 2, "hy-affrls-lpso", FAST, soc0=0.98), BLOCK)
    _assert_same(EstimateBlock.concat(parts, 2), ref)


def test_cells_of_different_capacity_equal_their_single_banks() -> None:
    """Capacity, efficiency and bounds are per-cell arrays: a bank of unlike cells is the same
    as one bank per cell."""
    model = cell_model(RUN.cell, 2)
    model = type(model)(**{**model.__dict__, "capacity_Ah": np.array([70.0, 55.0]),
                           "efficiency": np.array([1.0, 0.98])})  # fmt: skip
    both = EstimatorBank(model, "hy-affrls-lpso", FAST, soc0=0.98).update_block(BLOCK)
    for c in range(2):
        one = EstimatorBank(model.take([c]), "hy-affrls-lpso", FAST, soc0=0.98, cell_ids=[c],
                            n_stagger=2)  # fmt: skip
        got = one.update_block(SampleBlock.from_arrays(BLOCK.t_s, BLOCK.current_A,
                                                       BLOCK.cell_voltages_V[:, c]))  # fmt: skip
        for name in FIELD_NAMES:
            np.testing.assert_allclose(both[name][:, c], got[name][:, 0], rtol=1e-12,
                                       atol=1e-18, err_msg=name)  # fmt: skip
    assert not np.allclose(both["soc"][-1, 0], both["soc"][-1, 1])  # the capacities mattered


@pytest.mark.parametrize("variant", ["hy-affrls-lpso", "hy-affrls", "non-hy-affrls"])
def test_reset_restarts_only_the_masked_cells(variant: Variant) -> None:
    ref = build_bank(RUN.cell, 2, variant, FAST, soc0=0.98)
    bank = build_bank(RUN.cell, 2, variant, FAST, soc0=0.98)
    ref.update_block(BLOCK.slice(0, 300))
    bank.update_block(BLOCK.slice(0, 300))
    bank.reset([False, True])
    a, b = ref.update_block(BLOCK.slice(300, 301)), bank.update_block(BLOCK.slice(300, 301))
    for name in ("R0_ohm", "tau2_s", "soc", "v_model_V"):
        np.testing.assert_array_equal(a[name][:, 0], b[name][:, 0], err_msg=name)
    start = cell_model(RUN.cell, 1).start("R0_ohm")[0]
    assert b.quality[0, 1] == Quality.CONVERGING
    assert b["soc"][0, 1] == pytest.approx(0.98, abs=1e-3)  # restarted at soc0, one step on
    if variant == "hy-affrls-lpso":  # one RLS step from the start value
        assert b["R0_ohm"][0, 1] == pytest.approx(start, rel=0.5)
    else:  # ARX: nothing accepted yet, the start value holds
        assert b["R0_ohm"][0, 1] == start


@pytest.mark.parametrize("variant", ["hy-affrls-lpso", "hy-affrls"])
def test_format1_checkpoint_is_migrated_and_continues_as_the_old_engine(variant: Variant) -> None:
    """``data/bank_v1_*.npz``: checkpoints written by bmsid 0.1's flat bank after 250 samples,
    and what that bank estimated for the next 150 (tests/estimate/data/README.md)."""
    ck = load_checkpoint(DATA / f"bank_v1_{variant}.npz", CheckpointKey("v1test", 2, "x"))
    assert ck is not None and "format" not in ck.state
    # the old engine identified a hysteresis scale (the default until issue 11's M work) and
    # carried the window fit's covariance after a swarm
    old = FAST_COULOMB.model_copy(
        update={"identify_hysteresis_scale": True, "swarm_rls_restart": False}
    )
    bank = build_bank(RUN.cell, 2, variant, old, soc0=0.5)
    bank.load_state_dict(ck.state)
    got = bank.update_block(BLOCK.slice(250, 400))
    want = np.load(DATA / "bank_v1_continuation.npz")
    for name in ("R0_ohm", "soc", "v_model_V"):
        np.testing.assert_allclose(got[name], want[f"{variant}__{name}"], rtol=1e-9, err_msg=name)


def test_state_of_an_unknown_format_is_refused_with_one_line() -> None:
    bank = build_bank(RUN.cell, 2, "hy-affrls-lpso", FAST)
    st = bank.state_dict()
    with pytest.raises(ValueError, match="format 7") as err:
        bank.load_state_dict({**st, "format": 7})
    assert "\n" not in str(err.value)
    with pytest.raises(ValueError, match="2 cells / hy-affrls-lpso, not 2 / hy-affrls"):
        build_bank(RUN.cell, 2, "hy-affrls", FAST).load_state_dict(st)


def test_checkpoint_nests_one_state_per_stage_and_round_trips() -> None:
    a = build_bank(RUN.cell, 2, "hy-affrls-lpso", FAST, soc0=0.98)
    a.update_block(BLOCK.slice(0, 250))
    st = a.state_dict()
    assert {"ticks", "state", "params"} <= set(st) and st["format"] == 2
    b = build_bank(RUN.cell, 2, "hy-affrls-lpso", FAST, soc0=0.1)
    b.load_state_dict(st)
    _assert_same(a.update_block(BLOCK.slice(250, 400)), b.update_block(BLOCK.slice(250, 400)))
