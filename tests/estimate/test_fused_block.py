"""``update_block`` in compiled mode (the block's ticks at once, the ARX variants' ordinary ticks
in one compiled loop: ``estimate/block_run.py``) equals the per-tick path (``update`` sample by
sample: ``TickAssembler.push`` and ``_run_tick``), bit for bit, with every event the loop hands
back to Python: NaN voltages and currents, gaps, time jumps back, repeated and non-finite times,
0.5 s sampling, temperatures, a start from rest (the start's relaxation watch), a long rest
(anchors), a voltage fault (a divergence re-initialises the cell), blocks that end mid-bin.
"""

from __future__ import annotations

import itertools
from dataclasses import fields
from functools import lru_cache
from typing import Any

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from bmsid.config.engine import build_bank
from bmsid.estimate import jit
from bmsid.estimate.bank import EstimatorBank
from bmsid.estimate.observer_tuning import ObserverTuning
from bmsid.estimate.tick_block import assemble
from bmsid.estimate.ticks import Tick, TickAssembler
from bmsid.estimate.tuning import EstimatorTuning, Variant
from bmsid.samples import SampleBlock
from bmsid.synthetic import SyntheticRun, paper_dst_case

NO_OBSERVER = EstimatorTuning(observer=ObserverTuning(enabled=False))
#: Shorter anchors, updates and divergence holds, so that a short run holds them.
#: (and short swarms: the fusion's loop stops for each)
_FAST_GUARD: dict[str, Any] = {
    "divergence_hold_s": 20.0, "divergence_fast_s": 5.0, "divergence_scale_s": 300.0,
    "window_s": 120.0, "min_window_s": 40.0, "swarm_period_s": 60.0, "n_iter": 3,
    "n_iter_first": 4, "n_particles": 4, "swarm_min_steps": 0,
}  # fmt: skip
QUICK = EstimatorTuning(
    observer=ObserverTuning(anchor_min_rest_s=60.0, anchor_rest_taus=0.5, update_period_s=5.0),
    **_FAST_GUARD,
)
QUICK_NO_OBSERVER = EstimatorTuning(observer=ObserverTuning(enabled=False), **_FAST_GUARD)
#: The other branches: no average, the OCV offset identified, no knees, M not learnt (and the
#: fusion's hysteresis scale identified).
OTHER = EstimatorTuning(
    publish_average_tau1=0.0, identify_ocv_offset=True, knee_slope_factor=1e9,
    identify_hysteresis_scale=True, observer=ObserverTuning(learn_hysteresis=False),
)  # fmt: skip


@lru_cache(maxsize=8)
def _run(n_samples: int, n_cells: int) -> SyntheticRun:
    spread = np.linspace(0.8, 1.3, n_cells) if n_cells > 1 else None
    return paper_dst_case(n_samples, r0_spread=spread, seed=5)


def _inputs(n_samples: int, n_cells: int, events: dict[str, Any], seed: int) -> tuple[Any, ...]:
    run = _run(n_samples, n_cells)
    t, i, v = run.t_s.copy(), run.current_A.copy(), run.voltages_V.copy()
    m, rng = t.shape[0], np.random.default_rng(seed)
    temp = None
    if events["nan_v"]:
        v[rng.random(v.shape) < 0.05] = np.nan
        v[m // 5 : m // 5 + 3, 0] = np.nan
    if events["nan_i"]:
        i[rng.random(m) < 0.02] = np.nan
    if events["rest"]:  # a long rest: anchors (QUICK) and the offset learnt
        i[m // 3 : m // 3 + min(400, m // 3)] = 0.0
    if events["fault"]:  # a current sensor fault: SOC counted out of range, cells re-initialised
        i[m // 2 : m // 2 + 40] = -3000.0
    if events["gap"]:
        t[m // 4 :] += 45.0
        t[(2 * m) // 3 :] += 900.0
    if events["repeat"]:
        rep = rng.choice(m - 1, 5, replace=False)
        t[rep + 1] = t[rep]
        t[rng.choice(m, 2, replace=False)] = np.nan
    if events["jump_back"]:
        t[(3 * m) // 4 :] -= 100.0
    if events["half"]:
        t = t * 0.5
    if events["temperature"]:
        temp = 25.0 + 5.0 * np.sin(np.arange(m) / 50.0)
        temp[rng.random(m) < 0.1] = np.nan
    if events["rest_start"]:
        i[:60] = 0.0
    return t, i, v, temp


def _bank(variant: Variant, n_cells: int, tuning: EstimatorTuning, rest_start: bool) -> Any:
    return build_bank(_run(8, 1).cell, n_cells, variant, tuning,
                      soc0=None if rest_start else 0.98)  # fmt: skip


def _by_block(bank: EstimatorBank, t: Any, i: Any, v: Any, temp: Any, cuts: list[int]) -> Any:
    out = []
    for a, b in itertools.pairwise(cuts):
        tc = None if temp is None else temp[a:b]
        blk = SampleBlock.from_arrays(t[a:b], i[a:b], v[a:b], temperature_C=tc)
        out.append(bank.update_block(blk))
    return out


def _by_sample(bank: EstimatorBank, t: Any, i: Any, v: Any, temp: Any) -> list[Any]:
    out = []
    for k in range(t.shape[0]):
        e = bank.update(float(t[k]), float(i[k]), v[k], np.nan if temp is None else float(temp[k]))
        if e is not None:
            out.append(e)
    return out


def _flat(x: Any, prefix: str = "") -> dict[str, Any]:
    if isinstance(x, dict):
        return {k2: v2 for k, v in x.items() for k2, v2 in _flat(v, f"{prefix}/{k}").items()}
    return {prefix: x}


def _assert_same(blocks: list[Any], ticks: list[Any], a: EstimatorBank, b: EstimatorBank) -> None:
    t_s = np.concatenate([blk.t_s for blk in blocks])
    assert t_s.shape[0] == len(ticks)
    np.testing.assert_array_equal(t_s, [e.t_s for e in ticks])
    np.testing.assert_array_equal(np.concatenate([blk.current_A for blk in blocks]),
                                  [e.current_A for e in ticks])  # fmt: skip
    quality = np.array([e.quality for e in ticks]).reshape(-1, a.n)
    np.testing.assert_array_equal(np.concatenate([blk.quality for blk in blocks]), quality)
    for name in blocks[0].cells:
        got = np.concatenate([blk.cells[name] for blk in blocks])
        want = np.array([e.cells[name] for e in ticks]).reshape(-1, a.n)
        np.testing.assert_array_equal(got, want, err_msg=name)
        assert got.shape[0] == 0 or np.isfinite(got[~np.isnan(want)]).all()
    assert a.counters == b.counters
    sa, sb = _flat(a.state_dict()), _flat(b.state_dict())
    assert sa.keys() == sb.keys()
    for k in sa:
        if isinstance(sa[k], np.ndarray | float | int):
            np.testing.assert_array_equal(sa[k], sb[k], err_msg=k)
        else:
            assert sa[k] == sb[k], k


EVENTS = ("nan_v", "nan_i", "rest", "fault", "gap", "repeat", "jump_back", "half",
          "temperature", "rest_start")  # fmt: skip


@settings(
    max_examples=60,
    deadline=None,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture],
)
@given(
    variant=st.sampled_from(["non-hy-affrls", "hy-affrls", "hy-affrls", "hy-affrls-lpso"]),
    n_cells=st.sampled_from([1, 3]),
    n_samples=st.integers(60, 500),
    flags=st.fixed_dictionaries({e: st.booleans() for e in EVENTS}),
    tuning=st.sampled_from([None, NO_OBSERVER, QUICK, QUICK_NO_OBSERVER, OTHER]),
    cut=st.lists(st.floats(0.0, 1.0), max_size=3),
    seed=st.integers(0, 1000),
)
def test_update_block_equals_the_per_tick_path(
    restore_kernel: None, variant: Variant, n_cells: int, n_samples: int, flags: dict[str, bool],
    tuning: EstimatorTuning | None, cut: list[float], seed: int,
) -> None:  # fmt: skip
    jit.select("compiled")
    t, i, v, temp = _inputs(n_samples, n_cells, flags, seed)
    tun = tuning or EstimatorTuning()
    a = _bank(variant, n_cells, tun, flags["rest_start"])
    b = _bank(variant, n_cells, tun, flags["rest_start"])
    m = t.shape[0]
    cuts = sorted({0, m, *(int(c * m) for c in cut)})
    _assert_same(_by_block(a, t, i, v, temp, cuts), _by_sample(b, t, i, v, temp), a, b)


def _count_python_ticks(bank: EstimatorBank) -> list[int]:
    """Make ``bank`` count the ticks its Python path (``_run_tick``) runs: the list's one item."""
    count = [0]
    run_tick = bank._run_tick

    def counted(tick: Any) -> Any:
        count[0] += 1
        return run_tick(tick)

    bank._run_tick = counted  # type: ignore[method-assign]
    return count


@pytest.mark.parametrize("variant", ["non-hy-affrls", "hy-affrls", "hy-affrls-lpso"])
@pytest.mark.parametrize("tuning", [QUICK, QUICK_NO_OBSERVER])
def test_events_go_through_the_python_path_and_back(
    restore_kernel: None, variant: Variant, tuning: EstimatorTuning
) -> None:
    """Every kind of return to Python at once (anchors, a divergence, gaps, a rest start), and
    the loop runs the ordinary ticks in between."""
    jit.select("compiled")
    flags = dict.fromkeys(EVENTS, True) | {"half": False}
    t, i, v, temp = _inputs(1500, 3, flags, 1)
    a = _bank(variant, 3, tuning, True)
    b = _bank(variant, 3, tuning, True)
    python_ticks = _count_python_ticks(a)
    blocks = _by_block(a, t, i, v, temp, [0, 700, t.shape[0]])
    _assert_same(blocks, _by_sample(b, t, i, v, temp), a, b)
    c = a.counters
    assert c["gaps"] >= 2 and c["time_jumps_back"] >= 1 and c["diverged"] >= 1
    if tuning.observer.enabled:
        assert c["anchors"] >= 1 and c["observer_updates"] >= 10
    n_python = python_ticks[0]
    if variant == "hy-affrls-lpso":  # swarms and temperatures: the Python path, often
        assert c["swarms"] >= 10 and n_python < c["ticks"]
    else:
        assert 0 < n_python < 0.5 * c["ticks"]


@pytest.mark.parametrize(("variant", "share"), [("hy-affrls", 0.002), ("hy-affrls-lpso", 0.002)])
def test_the_loop_runs_nearly_every_tick_of_a_drive(
    restore_kernel: None, variant: Variant, share: float
) -> None:
    """A drive without events: the ARX variants' loop runs all but the first ticks, the
    fusion's too (its swarms run ahead, their starts and ends called back from the loop), and both
    give the per-tick path's bits."""
    jit.select("compiled")
    run = _run(2000, 1)
    bank = _bank(variant, 1, EstimatorTuning(), False)
    python_ticks = _count_python_ticks(bank)
    t, i, v = run.t_s, run.current_A, run.voltages_V
    blocks = _by_block(bank, t, i, v, None, [0, 2000])
    other = _bank(variant, 1, EstimatorTuning(), False)
    _assert_same(blocks, _by_sample(other, t, i, v, None), bank, other)
    assert len(blocks[0]) == 2000 and python_ticks[0] <= share * 2000
    assert variant != "hy-affrls-lpso" or bank.counters["swarms"] >= 2


@pytest.mark.parametrize("offset", [False, True])
def test_swarms_run_ahead_end_on_their_tick(restore_kernel: None, offset: bool) -> None:
    """``update_block`` runs a swarm to its end at its start (the loop calls back into the stage
    when one is due or ends) and gives the bits of ``update``, sample by sample, which steps it
    tick by tick: also with a budget that does not divide the particles (its last tick is
    counted right), in blocks cut mid-swarm; with the OCV offset (whose ridge follows the tick)
    the swarms are stepped tick by tick, through the Python path."""
    jit.select("compiled")
    quick = _FAST_GUARD | {"n_particles": 5, "fits_per_update": 2, "n_iter": 4}
    tun = EstimatorTuning(identify_ocv_offset=offset, **quick)
    run = _run(1500, 3)
    t, i, v = run.t_s, run.current_A, run.voltages_V
    a, b = _bank("hy-affrls-lpso", 3, tun, False), _bank("hy-affrls-lpso", 3, tun, False)
    python_ticks = _count_python_ticks(a)
    blocks = _by_block(a, t, i, v, None, [0, 333, 700, 1500])
    _assert_same(blocks, _by_sample(b, t, i, v, None), a, b)
    assert a.counters["swarms"] >= 20 and a.counters == b.counters
    ran_ahead = python_ticks[0] <= 5  # (the first ticks of the blocks)
    assert ran_ahead != offset


@settings(
    max_examples=60,
    deadline=None,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture],
)
@given(
    n_cells=st.sampled_from([1, 2]),
    n_samples=st.integers(1, 300),
    flags=st.fixed_dictionaries({e: st.booleans() for e in EVENTS}),
    cut=st.floats(0.0, 1.0),
    seed=st.integers(0, 1000),
)  # fmt: skip
def test_tick_assembly_equals_push(
    restore_kernel: None, n_cells: int, n_samples: int, flags: dict[str, bool], cut: float,
    seed: int,
) -> None:  # fmt: skip
    """``tick_block.assemble`` of two blocks gives ``TickAssembler.push``'s ticks, field by
    field, and leaves the assembler in the same state."""
    jit.select("compiled")
    t, i, v, temp = _inputs(max(n_samples, 8), n_cells, flags, seed)
    t, i, v = t[:n_samples], i[:n_samples], v[:n_samples]
    temp = None if temp is None else temp[:n_samples]
    tun = EstimatorTuning()
    a, b = TickAssembler(n_cells, tun), TickAssembler(n_cells, tun)
    m = int(cut * n_samples)
    got = []
    for s in (slice(0, m), slice(m, n_samples)):
        tc = None if temp is None else temp[s]
        ta = assemble(a, SampleBlock.from_arrays(t[s], i[s], v[s], temperature_C=tc))
        got += [ta.tick(k) for k in range(ta.n)]
    want = [
        tk for k in range(n_samples)
        if (tk := b.push(float(t[k]), float(i[k]), v[k],
                         np.nan if temp is None else float(temp[k]))) is not None
    ]  # fmt: skip
    assert len(got) == len(want)
    for x, y in zip(got, want, strict=True):
        for f in fields(Tick):
            np.testing.assert_array_equal(getattr(x, f.name), getattr(y, f.name), err_msg=f.name)
    assert a.counters == b.counters
    sa, sb = a.state_dict(), b.state_dict()
    for k in sa:
        np.testing.assert_array_equal(sa[k], sb[k], err_msg=k)
