"""The compiled window-fit kernel against its numpy reference (issue 12: a compiled engine, kept
equal to the reference to float tolerance)."""

from __future__ import annotations

import logging
import time

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from bmsid.config.engine import build_bank
from bmsid.estimate import jit, varpro_kernel
from bmsid.samples import SampleBlock
from bmsid.synthetic import paper_dst_case


def test_every_compiled_kernel_is_available() -> None:
    """numba is a dependency: a machine where a kernel does not compile must fail here, not
    fall back silently (the daemon's sandboxed unit chooses numpy explicitly)."""
    assert varpro_kernel.KERNEL in jit._REGISTRY and varpro_kernel.SOLVE in jit._REGISTRY
    for kernel in jit._REGISTRY:
        assert kernel.compiled() is not None, kernel.name


class _SlowKernel:
    """A kernel whose compiling takes a while (what a fresh install's first choice does)."""

    kind = "compiled"

    def _resolve(self) -> None:
        time.sleep(0.3)


def test_a_long_choice_says_it_is_compiling(
    restore_kernel: None, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    """The first run after an install compiles every kernel (about a minute): said once it
    takes longer than a cached load, not before and not after."""
    monkeypatch.setattr(jit, "_REGISTRY", [_SlowKernel()])
    monkeypatch.setattr(jit, "NOTICE_AFTER_S", 0.05)
    with caplog.at_level(logging.INFO, logger="bmsid.estimate.jit"):
        jit.select(None)
    assert [r.getMessage()[:34] for r in caplog.records] == ["compiling the engine's kernels: on"]
    caplog.clear()
    monkeypatch.setattr(jit, "NOTICE_AFTER_S", 5.0)
    with caplog.at_level(logging.INFO, logger="bmsid.estimate.jit"):
        jit.select(None)
        time.sleep(0.1)
    assert not caplog.records


@settings(max_examples=40, deadline=None)
@given(
    seed=st.integers(0, 2**32 - 1),
    n_w=st.integers(8, 300),
    p=st.integers(1, 6),
    use_h=st.booleans(),
    use_off=st.booleans(),
    prior=st.sampled_from([0.0, 1e-6, 1.0]),
    with_cov=st.booleans(),
)
def test_compiled_and_reference_window_solves_agree(
    seed: int, n_w: int, p: int, use_h: bool, use_off: bool, prior: float, with_cov: bool
) -> None:
    """The solves after the normal equations (parameters, RMSE, last branch states and the
    covariance) on random windows: equal to float tolerance."""
    compiled = varpro_kernel.SOLVE.compiled()
    assert compiled is not None
    rng = np.random.default_rng(seed)
    i = np.repeat(rng.uniform(-100.0, 100.0, n_w // 7 + 1), 7)[:n_w]
    y = rng.normal(0.0, 0.02, n_w) - 0.001 * i
    hm = rng.uniform(-0.02, 0.02, n_w)
    w = rng.uniform(0.1, 1.0, n_w)
    a1 = np.exp(-1.0 / rng.uniform(1.0, 60.0, p))
    a2 = np.exp(-1.0 / rng.uniform(60.0, 5000.0, p))
    active = np.array([True, True, True, use_h, use_off, True, True])
    s = np.concatenate([rng.uniform(1e-4, 1e-2, 3), [1.0, 0.01], [1.0, 1.0]])[active]
    G, b, last = varpro_kernel.normal_equations_numpy(i, y, hm, w, a1, a2, s, use_h, use_off)
    j_off = 3 + int(use_h) if use_off else -1
    idx = np.flatnonzero(active)
    out = [
        fn(G.copy(), b, last, y, w, a1, a2, s, idx, prior, j_off, with_cov)
        for fn in (compiled, varpro_kernel.solve_numpy)
    ]
    # Two LAPACKs (numpy's, scipy's under numba) round differently: allow the rounding times the
    # equilibrated system's condition number (an 8-sample window of 7 columns reaches 1e10).
    d = np.sqrt(np.einsum("pii->pi", G))
    cond = np.linalg.cond(G / (d[:, :, None] * d[:, None, :]))
    for got, ref, name in zip(out[0], out[1], ("theta", "rmse", "x_last", "cov"), strict=True):
        assert got.shape == ref.shape, name
        for j in range(p):
            g, r = got[j], ref[j]
            tol = 1e-14 * cond[j] * np.max(np.abs(r[np.isfinite(r)]), initial=0.0) + 1e-300
            np.testing.assert_allclose(g, r, rtol=1e-9, atol=tol, equal_nan=True, err_msg=name)


@settings(max_examples=40, deadline=None)
@given(
    seed=st.integers(0, 2**32 - 1),
    n_w=st.integers(2, 400),
    p=st.integers(1, 13),
    use_h=st.booleans(),
    use_off=st.booleans(),
)
def test_compiled_and_reference_normal_equations_agree(
    seed: int, n_w: int, p: int, use_h: bool, use_off: bool
) -> None:
    """G, b and the last branch states on random windows and weights: equal to float
    tolerance, for any number of candidates (the kernel takes them four at a time, a short
    group last), window (its decays change method at 64 ticks) and active columns."""
    compiled = varpro_kernel.KERNEL.compiled()
    assert compiled is not None
    rng = np.random.default_rng(seed)
    i = np.repeat(rng.uniform(-100.0, 100.0, n_w // 7 + 1), 7)[:n_w]
    y = rng.normal(0.0, 0.02, n_w)
    hm = rng.uniform(-0.02, 0.02, n_w)
    w = rng.uniform(0.0, 1.0, n_w)
    a1 = np.exp(-1.0 / rng.uniform(1.0, 60.0, p))
    a2 = np.exp(-1.0 / rng.uniform(60.0, 5000.0, p))
    n_a = 5 + int(use_h) + int(use_off)
    s = np.concatenate([rng.uniform(1e-4, 1e-2, 3), rng.uniform(0.01, 1.0, n_a - 3)])
    args = (i, y, hm, w, a1, a2, s, use_h, use_off)
    G, b, last = compiled(*args)
    G_ref, b_ref, last_ref = varpro_kernel.normal_equations_numpy(*args)
    assert G.shape == G_ref.shape == (p, n_a, n_a)
    scale = np.sqrt(np.abs(np.einsum("pii->pi", G_ref)))  # entries relative to their columns
    tol = 1e-10 * (scale[:, :, None] * scale[:, None, :]) + 1e-300
    assert np.all(np.abs(G - G_ref) <= tol)
    np.testing.assert_allclose(G, np.swapaxes(G, 1, 2))
    b_tol = 1e-10 * scale * np.sqrt(float(np.sum(w * y * y))) + 1e-300
    assert np.all(np.abs(b - b_ref) <= b_tol)
    np.testing.assert_allclose(last, last_ref, rtol=1e-10, atol=1e-10 * float(np.max(np.abs(i))))


def test_a_fused_bank_gives_the_same_estimates_with_either_kernel(restore_kernel: None) -> None:
    """Two cells of the reference DST, 1,500 s (several swarms each): every published estimate
    equal to float tolerance, and the same swarm decisions (time constants bit for bit)."""
    run = paper_dst_case(1500, r0_spread=np.array([1.0, 1.3]))
    block = SampleBlock.from_arrays(run.t_s, run.current_A, run.voltages_V)
    out = {}
    for name in ("numpy", "compiled"):
        assert jit.select(name) == name
        bank = build_bank(run.cell, 2, "hy-affrls-lpso", soc0=0.98)
        out[name] = bank.update_block(block)
        assert bank.counters["swarms"] >= 4
    ref, new = out["numpy"], out["compiled"]
    np.testing.assert_array_equal(new["tau1_s"], ref["tau1_s"])
    np.testing.assert_array_equal(new["tau2_s"], ref["tau2_s"])
    for name in ("R0_ohm", "R1_ohm", "R2_ohm", "v_model_V", "soc"):
        np.testing.assert_allclose(new[name], ref[name], rtol=1e-8, atol=0.0, err_msg=name)
