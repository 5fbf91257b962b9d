"""The state stage's and the SOC observer's compiled tick kernels (estimate/observer_kernel.py)
against their numpy reference: the stages' own code (issue 12: a compiled engine, kept equal
to the reference to float tolerance, with the same decisions)."""

from __future__ import annotations

import copy
import dataclasses
import functools
import math
from typing import Any

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from bmsid.config.cell import PAPER_OCV_MEAN, paper_cell
from bmsid.config.engine import build_bank, cell_model
from bmsid.estimate import jit, observer_kernel, observer_update_kernel, ocv_kernel, rest_anchor
from bmsid.estimate.jit_helpers import register
from bmsid.estimate.observer import ObserverState
from bmsid.estimate.observer_tuning import ObserverTuning
from bmsid.estimate.stage import TickContext
from bmsid.estimate.state import CoulombState
from bmsid.estimate.state_jit import ocv_params
from bmsid.estimate.ticks import Tick
from bmsid.estimate.tuning import EstimatorTuning
from bmsid.model.ocv import OcvModel
from bmsid.samples import SampleBlock
from bmsid.synthetic import paper_dst_case
from bmsid.synthetic.multiday import MultidayOptions, generate

PAPER = np.asarray(PAPER_OCV_MEAN)
M_SOC, M_V = [0.0, 0.3, 0.7, 1.0], [0.02, 0.012, 0.01, 0.015]


def test_the_compiled_kernels_are_available() -> None:
    """numba is a dependency: both kernels compile here (no silent fallback)."""
    assert observer_kernel.STEP.compiled() is not None
    assert observer_update_kernel.UPDATE.compiled() is not None


# ----------------------------------------------------------------------------- random stages
def _ocv(ends: bool, table: bool = False, seed: int = 0) -> OcvModel:
    """The paper's curve on [0.03, 0.97], with end segments and/or a random correction table
    (knots 2-5 % apart as ``fit-ocv`` spaces them, jittered, the end ones at or beyond the
    curve's range; values of a few mV, halved until the corrected curve increases). Knots far
    apart are no table a test gives: the slope limit at a knot (``model.ocv.table_slopes``)
    assumes Eq. 4 is nearly cubic between knots, and near Eq. 4's steep low end over tens of
    percent it is not (such a table is refused, however small its values)."""
    lo, hi = 0.03, 0.97
    kw: dict[str, Any] = {}
    if table:
        rng = np.random.default_rng(seed)
        step = rng.uniform(0.02, 0.05)
        grid = np.arange(0.04, 0.96, step)
        inner = np.round(
            np.clip(grid + rng.uniform(-0.3, 0.3, grid.shape[0]) * step, 0.04, 0.96), 6
        )
        x = np.unique(np.concatenate([rng.choice([[0.0], [0.03], [0.01]]), inner,
                                      rng.choice([[1.0], [0.97], [0.99]])]))  # fmt: skip
        kw = {"corr_soc": x, "corr_V": rng.uniform(-0.008, 0.008, x.shape[0])}
    for _ in range(40):
        try:
            if not ends:
                return OcvModel.from_coeffs(PAPER, lo, hi, M_SOC, M_V, **kw)
            ref = OcvModel.from_coeffs(PAPER, lo, hi, M_SOC, M_V, **kw)
            v_lo, v_hi = (float(ref.ocv(np.array([z]))[0]) for z in (lo, hi))
            d_lo, d_hi = (float(ref.docv_dz(np.array([z]))[0]) for z in (lo, hi))
            return OcvModel.from_coeffs(
                PAPER, lo, hi, M_SOC, M_V, v_empty_V=v_lo - d_lo * lo,
                v_full_V=v_hi + d_hi * (1 - hi), **kw,
            )  # fmt: skip
        except ValueError:  # the table leaves the curve falling: a smaller one
            kw["corr_V"] = 0.5 * kw["corr_V"]
    raise AssertionError(f"no table of seed {seed} (values halved 40 times) is accepted")


@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), ends=st.booleans())
def test_the_kernels_ocv_helpers_agree_with_the_model_with_a_table(seed: int, ends: bool) -> None:
    """``ocv_kernel.ocv_at`` / ``docv_dz_at`` (plain and compiled) over the packed vector equal
    ``OcvModel.ocv`` / ``docv_dz`` of a curve with a random correction table, at its knots, on
    both sides of them, beyond the curve and at NaN."""
    m = _ocv(ends, table=True, seed=seed)
    assert m.corr_soc is not None
    p = ocv_params(m)
    assert p.shape[0] == ocv_kernel.N_OCV + 3 * m.corr_soc.shape[0]
    rng = np.random.default_rng(seed)
    z = np.concatenate([m.corr_soc, m.corr_soc + 1e-9, m.corr_soc - 1e-9,
                        rng.uniform(-0.1, 1.1, 200), [0.0, 1.0, 0.03, 0.97, np.nan]])  # fmt: skip
    for fn in (_probe, _compiled_probe()):
        v, d = fn(p, z)
        np.testing.assert_allclose(v, m.ocv(z), rtol=1e-12, atol=1e-13, equal_nan=True)
        np.testing.assert_allclose(d, m.docv_dz(z), rtol=1e-11, atol=1e-11, equal_nan=True)


@functools.cache
def _compiled_probe() -> Any:
    """``_probe`` compiled once per process (numba only for the tests that compile)."""
    import numba

    register()
    return numba.njit(cache=False)(_probe)


def _probe(p: np.ndarray, z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    v, d = np.empty_like(z), np.empty_like(z)
    for i in range(z.shape[0]):
        v[i] = observer_kernel.ocv_at(p, z[i])
        d[i] = observer_kernel.docv_dz_at(p, z[i])
    return v, d


def _stage(rng: np.random.Generator, n: int, cfg: dict[str, Any]) -> CoulombState:
    """A stage of ``n`` cells in a random state (every cell started)."""
    model = cell_model(paper_cell(), n)
    model = dataclasses.replace(model, ocv=_ocv(cfg["ends"], cfg["table"], int(rng.integers(1e9))))
    model = dataclasses.replace(model, hysteresis_play=cfg.get("play", False))
    if not cfg["uniform"]:
        model = dataclasses.replace(
            model, capacity_Ah=rng.uniform(1.5, 3.0, n), efficiency=rng.uniform(0.95, 1.0, n),
            gamma=rng.uniform(10.0, 200.0, n),
        )  # fmt: skip
    knee = cfg["knee"]
    if not cfg["observer"]:
        stage = CoulombState(model, None, knee)
    else:
        tun = ObserverTuning(learn_hysteresis=cfg["map"], update_period_s=5.0,
                             anchor_min_rest_s=30.0, restart_gap_s=50.0,
                             rest_draw=bool(rng.random() < 0.8))  # fmt: skip
        stage = ObserverState(model, None, knee, tun, 0.05)
    stage.z = rng.uniform(-0.05, 1.05, n)
    stage.h = rng.uniform(-1.0, 1.0, n)
    stage._pending = rng.random(n) < 0.1 if cfg["pending"] else np.zeros(n, dtype=bool)
    if isinstance(stage, ObserverState):
        N = stage.P.shape[0]
        sd = np.concatenate([rng.uniform(0.001, 0.1, n), [0.1], rng.uniform(1e-4, 5e-3, N - n - 1)])
        a = rng.normal(size=(N, N)) + 3.0 * np.eye(N)
        corr = a @ a.T
        corr /= np.sqrt(np.outer(np.diag(corr), np.diag(corr)))
        stage.P = corr * np.outer(sd, sd)
        stage.b = float(rng.choice([0.0, rng.uniform(-0.1, 0.1)]))
        if cfg["map"] and rng.random() < 0.7:
            stage.d = rng.uniform(-3e-3, 3e-3, stage.d.shape[0])
        stage._g = rng.uniform(0.0, 1e-3, n)
        stage._qz = rng.uniform(0.0, 1e-6, n)
        stage._lh = rng.uniform(-2.0, 0.0, n)  # h's log decay since the last update
        stage._qb, stage._since_s = float(rng.uniform(0, 1e-4)), float(rng.uniform(0, 10))
        stage._rest_s = float(rng.choice([0.0, 10.0, 40.0, 500.0]))
        stage._anchored = rng.random(n) < 0.3
        stage._reanchor = bool(rng.random() < 0.2)
        stage._learn_gate = rng.random(n) < (0.0 if rng.random() < 0.3 else 0.7)
        stage._i_load_A = rng.uniform(0.0, 3.0, n)
        stage._tau_load_s = rng.uniform(5.0, 300.0, n)
        # the rests' reading: none yet, or one that a tick near it continues (h moves with the
        # draw it and the offset leave: rest_anchor.rest_draw)
        stage._rest_i_A = float(rng.choice([rest_anchor.NO_REST_A, rng.uniform(-1.0, 1.0)]))
        # the sensor's noise so far and the last tick's current (rest_anchor.next_noise)
        stage._noise_sd_A = float(rng.choice([0.0, rng.uniform(0.0, 0.02)]))
        stage._i_prev_A = float(rng.choice([math.nan, rng.uniform(-0.05, 0.05), 3.0]))
        if rng.random() < 0.3:  # an offset known well (its row and column scaled: P stays PSD)
            s = float(rng.uniform(0.01, 0.3))
            stage.P[n, :] *= s
            stage.P[:, n] *= s
    return stage


def _tick(rng: np.random.Generator, t: float, z: np.ndarray, ocv: OcvModel) -> Tick:
    n = z.shape[0]

    def current() -> float:
        return float(rng.choice([0.0, rng.uniform(-0.02, 0.02), rng.uniform(-6.0, 6.0)]))

    steps = tuple((current(), float(rng.choice([1.0, rng.uniform(0.1, 2.0)])))
                  for _ in range(int(rng.integers(0, 4))))  # fmt: skip
    dt = float(rng.choice([0.0, 1.0, rng.uniform(0.5, 3.0), 60.0]))
    ok = np.asarray(rng.random(n) < 0.85, dtype=bool)
    v = np.where(ok, ocv.ocv(np.clip(z, 0.0, 1.0)) + rng.normal(0.0, 0.01, n), np.nan)
    new_segment = bool(rng.random() < 0.1)
    return Tick(
        t_s=t, current_A=current(), i_prev_A=current(), dt_s=dt, period_s=1.0, v_V=v, ok=ok,
        coulomb_steps=steps, current_std_A=1.0, temperature_C=math.nan, first=False,
        new_segment=new_segment,
    )  # fmt: skip


def _params(rng: np.random.Generator, v: np.ndarray) -> dict[str, np.ndarray]:
    n = v.shape[0]
    e = rng.normal(0.0, rng.choice([0.002, 0.02, 0.2]), n)
    return {
        "R0_ohm": rng.uniform(0.01, 0.05, n), "R1_ohm": rng.uniform(0.005, 0.02, n),
        "R2_ohm": rng.uniform(0.005, 0.03, n), "tau2_s": rng.uniform(5.0, 300.0, n),
        "v_model_V": v - e, "M_V": rng.uniform(0.0, 0.03, n),
    }  # fmt: skip


_CTX = ("soc_clamped", "ocv_V", "m_table_V", "h", "hm_V", "v_safe_V")
_OBS_ARRAYS = ("P", "_g", "_qz", "_lh", "d", "_i_load_A", "_learn_gate", "_anchored", "_q_As")
_OBS_SCALARS = ("b", "_qb", "_since_s", "_rest_s", "_reanchor", "soc_init_method", "_noise_sd_A",
                "_i_prev_A", "_rest_limit_A", "_h_rest_A")  # fmt: skip


def _close(a: Any, b: Any, what: str) -> None:
    a, b = np.asarray(a), np.asarray(b)
    if a.dtype == bool or a.dtype.kind in "iUO":
        np.testing.assert_array_equal(b, a, err_msg=what)
        return
    scale = float(np.nanmax(np.abs(a))) if a.size and np.any(np.isfinite(a)) else 0.0
    np.testing.assert_allclose(b, a, rtol=1e-9, atol=1e-12 * max(scale, 1.0), err_msg=what)


def _same(ref: CoulombState, new: CoulombState, cref: TickContext, cnew: TickContext) -> None:
    for name in ("z", "h", "_pending"):
        _close(getattr(ref, name), getattr(new, name), name)
    for name in _CTX:
        _close(getattr(cref, name), getattr(cnew, name), f"ctx.{name}")
    np.testing.assert_array_equal(cnew.learn, cref.learn, err_msg="ctx.learn")
    assert new.counters == ref.counters
    if isinstance(ref, ObserverState):
        assert isinstance(new, ObserverState)
        for name in _OBS_ARRAYS:
            _close(getattr(ref, name), getattr(new, name), name)
        for name in _OBS_SCALARS:
            _close(getattr(ref, name), getattr(new, name), name)
        for name, x in ref.capacity.state_dict().items():
            _close(x, new.capacity.state_dict()[name], f"capacity.{name}")
        _close(cref.tick.current_A, cnew.tick.current_A, "tick.current_A")
        _close(cref.tick.i_prev_A, cnew.tick.i_prev_A, "tick.i_prev_A")


@settings(max_examples=60, deadline=None)
@given(
    n=st.integers(1, 8),
    seed=st.integers(0, 2**32 - 1),
    observer=st.booleans(),
    ends=st.booleans(),
    table=st.booleans(),
    learn_map=st.booleans(),
    uniform=st.booleans(),
    pending=st.booleans(),
    knee=st.sampled_from([math.inf, 3.0]),
    play=st.booleans(),
)
def test_compiled_and_numpy_ticks_agree(
    n: int, seed: int, observer: bool, ends: bool, table: bool, learn_map: bool, uniform: bool,
    pending: bool, knee: float, play: bool,
) -> None:  # fmt: skip
    """Random states and ticks (currents at rest and under load, several or no coulomb steps,
    zero dt, gaps, cells without a voltage, SOC beyond the curve, a correction table on the OCV
    curve, an offset, a learnt map, h by Plett's law or as a play operator, a draw at rest, due
    updates with anchors, re-anchors and gated innovations): the compiled step and update (and
    their sources run as plain Python, the registry's reference) leave every state, context
    field and counter equal to the stages' own numpy code."""
    rng = np.random.default_rng(seed)
    cfg = {"observer": observer, "ends": ends, "table": table, "map": learn_map,
           "uniform": uniform, "pending": pending, "knee": knee, "play": play}  # fmt: skip
    ref = _stage(rng, n, cfg)
    new, src = copy.deepcopy(ref), copy.deepcopy(ref)
    before = jit.MODE
    try:
        for k in range(6):
            tick = _tick(rng, 100.0 * (k + 1), ref.z, ref.model.ocv)
            params = _params(rng, np.where(tick.ok, tick.v_V, 3.7))
            converged = rng.random(n) < 0.7
            ctx = {}
            for name, stage in (("numpy", ref), ("compiled", new), ("source", src)):
                assert jit.select("numpy" if name == "numpy" else "compiled")
                if name == "source":  # the kernels' own sources run uncompiled
                    for kernel in (observer_kernel.STEP, observer_update_kernel.UPDATE):
                        kernel.impl = kernel.reference
                ctx[name] = TickContext(copy.deepcopy(tick))
                stage.step(ctx[name])
                stage.correct(ctx[name], {k: v.copy() for k, v in params.items()}, converged)
            _same(ref, new, ctx["numpy"], ctx["compiled"])
            _same(ref, src, ctx["numpy"], ctx["source"])
    finally:
        jit.restore(before)


# ----------------------------------------------------------------------------- whole banks
@pytest.mark.parametrize("variant", ["hy-affrls", "hy-affrls-lpso"])
@pytest.mark.parametrize("observer", [True, False])
def test_a_bank_gives_the_same_estimates_with_either_kernel(
    restore_kernel: None, variant: str, observer: bool
) -> None:
    """Three cells of the reference DST (1,200 s), with the observer and as a plain count."""
    run = paper_dst_case(1200, r0_spread=np.array([1.0, 1.15, 1.3]))
    block = SampleBlock.from_arrays(run.t_s, run.current_A, run.voltages_V)
    tun = EstimatorTuning(observer=ObserverTuning(enabled=observer))
    out, counters = {}, {}
    for name in ("numpy", "compiled"):
        assert jit.select(name) == name
        bank = build_bank(run.cell, 3, variant, tun, soc0=0.98)  # type: ignore[arg-type]
        out[name] = bank.update_block(block)
        counters[name] = bank.counters
    ref, new = out["numpy"], out["compiled"]
    assert counters["compiled"] == counters["numpy"]
    np.testing.assert_array_equal(new.quality, ref.quality)
    for name in ref.cells:
        np.testing.assert_allclose(new[name], ref[name], rtol=1e-7, atol=1e-12, err_msg=name)


def test_an_observer_with_anchors_a_gap_and_an_offset_decides_alike(
    restore_kernel: None,
) -> None:
    """14 h of the multi-day record with a +0.5 A offset and an hour of downtime: the same
    anchors, re-anchor, capacity updates and observer updates, estimates to tolerance."""
    rec = generate(MultidayOptions(n_days=1, duration_s=14 * 3600, current_offset_A=0.5,
                                   hysteresis_tilt=0.6))  # fmt: skip
    keep = np.ones(rec.n_samples, dtype=bool)
    keep[30000:33600] = False
    block = SampleBlock.from_arrays(rec.t_s[keep], rec.current_A[keep], rec.voltage_V[keep, None])
    tun = EstimatorTuning(id_period_s=10.0)
    out, counters = {}, {}
    for name in ("numpy", "compiled"):
        assert jit.select(name) == name
        bank = build_bank(rec.cell, 1, "hy-affrls", tun)
        out[name] = bank.update_block(block)
        counters[name] = bank.counters
    assert counters["compiled"] == counters["numpy"]
    assert counters["numpy"]["anchors"] >= 2 and counters["numpy"]["reanchors"] == 1
    ref, new = out["numpy"], out["compiled"]
    np.testing.assert_array_equal(new.quality, ref.quality)
    for name in ref.cells:
        np.testing.assert_allclose(new[name], ref[name], rtol=1e-6, atol=1e-12, err_msg=name)
