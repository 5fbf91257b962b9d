"""The compiled per-tick kernels of the parameter stages against their numpy references (issue 12:
a compiled engine, kept equal to the reference to float tolerance)."""

from __future__ import annotations

import functools
from typing import Any

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from bmsid.config.engine import build_bank
from bmsid.estimate import jit, rls_kernel
from bmsid.estimate.fields import FIELD_NAMES
from bmsid.estimate.jit_helpers import register
from bmsid.estimate.rls_reference import arx_tick_numpy, fusion_tick_numpy
from bmsid.estimate.tuning import Variant
from bmsid.model.arx import params_to_theta, theta_to_rows
from bmsid.samples import SampleBlock
from bmsid.synthetic import paper_dst_case

CONSTS = (0.5e-3, 6.0, 3.0, 0.5)


def _compiled(kernel: jit.Kernel[Any]) -> Any:
    fn = kernel.compiled()
    assert fn is not None
    return fn


def test_the_compiled_tick_kernels_are_available() -> None:
    """numba is a dependency: a machine where they do not compile must fail here."""
    _compiled(rls_kernel.ARX_TICK)
    _compiled(rls_kernel.FUSION_TICK)


def _close(got: Any, want: Any, name: str, rtol: float = 1e-11) -> None:
    if isinstance(want, int):
        assert got == want, name
        return
    want, got = np.asarray(want), np.asarray(got)
    assert got.shape == want.shape and got.dtype == want.dtype, name
    if want.dtype == bool:
        np.testing.assert_array_equal(got, want, name)
        return
    scale = np.maximum(np.abs(want), 1e-300)
    if want.ndim == 3:  # a covariance: entries relative to its diagonal
        d = np.sqrt(np.abs(np.einsum("nii->ni", want)))
        scale = np.maximum(scale, d[:, :, None] * d[:, None, :])
    ok = (np.abs(got - want) <= rtol * scale) | (np.isnan(got) & np.isnan(want)) | (got == want)
    assert np.all(ok), (name, got, want)


def _cells(draw: st.DrawFn, n: int) -> dict[str, Any]:
    """Per-cell inputs both stages take, around the values a DST tick sees, with edge cases:
    cells without a voltage or that do not learn, zero currents, a rest."""
    seed = draw(st.integers(0, 2**32 - 1))
    rng = np.random.default_rng(seed)
    i = draw(st.sampled_from([0.0, 0.02, -3.0, 20.0, -60.0, 150.0]))
    ip = draw(st.sampled_from([0.0, i, 40.0, -25.0]))
    mask = st.lists(st.booleans(), min_size=n, max_size=n).map(lambda b: np.array(b, dtype=bool))
    return {
        "rng": rng,
        "x1": rng.normal(0.0, 30.0, n),
        "x2": rng.normal(0.0, 30.0, n),
        "tau1": rng.uniform(5.0, 60.0, n),
        "tau2": rng.uniform(100.0, 3000.0, n),
        "sig_e": rng.uniform(0.0, 3e-3, n),
        "v": rng.uniform(3.4, 4.1, n),
        "ocv": rng.uniform(3.4, 4.1, n),
        "hm": rng.uniform(-0.02, 0.02, n),
        "ok": draw(mask),
        "learn": draw(mask),
        "rest_A": np.full(n, draw(st.sampled_from([0.05, 1.0, 50.0]))),
        "i": i,
        "ip": ip,
        "dt": draw(st.sampled_from([1.0, 1.0, 0.5, 0.0, 10.0])),
        "lam_lo": 0.98,
        "lam_hi": draw(st.sampled_from([0.999, 1.0])),
        "g": draw(st.sampled_from([1.0 - np.exp(-1.0 / 300.0), 1.0])),
        "trace_max": draw(st.sampled_from([1e5, 1e-3])),  # 1e-3: the cap acts
    }


@st.composite
def _arx_args(draw: st.DrawFn) -> tuple[Any, ...]:
    n = draw(st.integers(1, 8))
    c = _cells(draw, n)
    rng = c["rng"]
    R0, R1, R2 = rng.uniform(5e-4, 2e-3, n), rng.uniform(2e-4, 1e-3, n), rng.uniform(2e-4, 1e-3, n)
    scale = np.stack([np.ones(n), np.ones(n), R0, R0, R0], axis=1)
    T = draw(st.sampled_from([1.0, 0.5]))
    theta = params_to_theta(R0, R1, c["tau1"], R2, c["tau2"], T) / scale
    theta *= 1.0 + rng.normal(0.0, draw(st.sampled_from([0.0, 1e-6, 1e-4, 0.05])), (n, 5))
    A = rng.normal(0.0, 1.0, (n, 5, 5))
    P = A @ A.transpose(0, 2, 1) * draw(st.sampled_from([1e-6, 1.0, 1e3]))
    lo = np.stack([R0 * 0.9, R1 * 0.5, R2 * 0.5, c["tau2"] * 0.5, c["tau1"] * 0.5])
    hi = lo * draw(st.sampled_from([1.2, 4.0]))  # 1.2: some rows clamped
    bounds = np.stack([lo, hi])
    return (
        c["x1"], c["x2"], c["tau1"], c["tau2"], R0, R1, R2, rng.uniform(0.98, 1.0, n),
        c["sig_e"], theta, P, rng.normal(0.0, 0.05, (n, 2)), scale, rng.normal(0.0, 50.0, 2),
        bounds, c["rest_A"], c["v"], c["ocv"], c["hm"], c["ok"], c["learn"],
        np.zeros(n, dtype=bool), rng.uniform(size=n) < 0.5, c["i"], c["ip"], c["dt"], T,
        c["lam_lo"], c["lam_hi"], c["g"], CONSTS, c["trace_max"], draw(st.booleans()),
        draw(st.booleans()),
    )  # fmt: skip


#: the arguments each kernel updates in place (index: name)
_ARX_IN_PLACE = {0: "x1", 1: "x2", 7: "lam", 8: "sig_e", 9: "theta", 10: "P", 11: "ue_hist",
                 13: "i_hist", 21: "clamped", 22: "arx_ok"}  # fmt: skip
_FUSION_IN_PLACE = {0: "x1", 1: "x2", 4: "theta", 5: "P", 6: "sig_e", 7: "lam", 15: "clamped"}


def _agree(kernel: Any, ref: Any, args: tuple[Any, ...], in_place: dict[int, str],
           rtol: float) -> None:  # fmt: skip
    """``kernel`` and ``ref`` on copies of ``args``: the same results and in-place updates."""
    mine = [a.copy() if isinstance(a, np.ndarray) else a for a in args]
    theirs = [a.copy() if isinstance(a, np.ndarray) else a for a in args]
    (out, count), (want, want_count) = kernel(*mine), ref(*theirs)
    assert count == want_count
    _close(out, want, "published rows", rtol)
    for k, name in in_place.items():
        _close(mine[k], theirs[k], name, rtol)
    untouched = [k for k, a in enumerate(args) if isinstance(a, np.ndarray) and k not in in_place]
    for k in untouched:  # the other arguments are left alone
        np.testing.assert_array_equal(mine[k], args[k])
        np.testing.assert_array_equal(theirs[k], args[k])


@settings(max_examples=300, deadline=None)
@given(args=_arx_args())
def test_compiled_and_reference_arx_ticks_agree(args: tuple[Any, ...]) -> None:
    _agree(_compiled(rls_kernel.ARX_TICK), arx_tick_numpy, args, _ARX_IN_PLACE, 1e-11)


@st.composite
def _fusion_args(draw: st.DrawFn) -> tuple[Any, ...]:
    n = draw(st.integers(1, 8))
    c = _cells(draw, n)
    rng = c["rng"]
    r = rng.uniform(2e-4, 2e-3, (n, 3))
    scale = np.concatenate([r, np.ones((n, 1)), np.full((n, 1), 0.05)], axis=1)
    fit_scale, fit_offset = draw(st.booleans()), draw(st.booleans())
    phi_scale = scale * np.array([1.0, 1.0, 1.0, float(fit_scale), 0.0])
    lo = np.concatenate([r * 0.3, np.full((n, 1), 0.5), np.full((n, 1), -0.05)], axis=1)
    hi = np.concatenate([r * 3.0, np.full((n, 1), 1.5), np.full((n, 1), 0.05)], axis=1)
    spread = draw(st.sampled_from([0.0, 0.1, 1.0, 5.0]))  # 1, 5: some cells leave the bounds
    theta = (1.0 + rng.normal(0.0, spread, (n, 5))) * np.array([1.0, 1.0, 1.0, 1.0, 0.0])
    A = rng.normal(0.0, 1.0, (n, 5, 5))
    P = A @ A.transpose(0, 2, 1) * draw(st.sampled_from([1e-3, 1.0, 100.0]))
    if draw(st.booleans()):  # the fusion's covariance: the offset's row and column zero
        P[:, 4, :] = P[:, :, 4] = 0.0
    lin = np.stack([scale, phi_scale, lo, hi, 1e-12 * scale])
    return (
        c["x1"], c["x2"], c["tau1"], c["tau2"], theta, P, c["sig_e"], rng.uniform(0.98, 1.0, n),
        lin, c["rest_A"], c["v"], c["ocv"], c["hm"], c["ok"], c["learn"], np.zeros(n, dtype=bool),
        c["i"],
        c["ip"], c["dt"], c["lam_lo"], c["lam_hi"], c["g"], CONSTS, c["trace_max"], fit_scale,
        fit_offset,
    )  # fmt: skip


@settings(max_examples=300, deadline=None)
@given(args=_fusion_args())
def test_compiled_and_reference_fusion_ticks_agree(args: tuple[Any, ...]) -> None:
    # rtol 1e-10: the projection divides by P's diagonal
    _agree(_compiled(rls_kernel.FUSION_TICK), fusion_tick_numpy, args, _FUSION_IN_PLACE, 1e-10)


ANY = st.floats(allow_nan=True, allow_infinity=True, width=64)
NEAR = st.floats(-3.0, 3.0)


@functools.cache
def _compiled_map() -> Any:
    """``_map_row`` as the kernels compile it (a helper compiled into its caller)."""
    import numba

    register()
    map_row = rls_kernel._map_row

    @numba.njit(cache=False)  # type: ignore[misc]
    def call(a1: float, a2: float, b0: float, b1: float, b2: float, T: float) -> Any:
        return map_row(a1, a2, b0, b1, b2, T)

    return call


@settings(max_examples=2000, deadline=None)
@given(theta=st.lists(st.one_of(NEAR, ANY), min_size=5, max_size=5), T=st.sampled_from([1.0, 0.1]))
def test_the_kernels_map_equals_theta_to_rows_to_the_bit(theta: list[float], T: float) -> None:
    """``_map_row`` (compiled with the kernels) against the model's map, any theta."""
    rows, status = theta_to_rows(np.array([theta]), T)
    got = _compiled_map()(*theta, T)
    assert int(got[0]) == int(status[0])
    assert np.array(got[1:]).tobytes() == rows[:, 0].tobytes()


@settings(max_examples=10, deadline=None)
@given(arx=_arx_args(), fusion=_fusion_args())
def test_the_kernels_sources_run_uncompiled(arx: tuple[Any, ...], fusion: tuple[Any, ...]) -> None:
    """The sources are plain Python (numba compiles them as they are): run as Python, with the
    helpers compiled or not, they give the references' results."""
    _agree(rls_kernel._arx_source, arx_tick_numpy, arx, _ARX_IN_PLACE, 1e-10)
    _agree(rls_kernel._fusion_source, fusion_tick_numpy, fusion, _FUSION_IN_PLACE, 1e-10)


@pytest.mark.parametrize("variant", ["hy-affrls", "non-hy-affrls", "hy-affrls-lpso"])
def test_a_bank_gives_the_same_estimates_with_either_kernel(
    restore_kernel: None, variant: Variant
) -> None:
    """Three cells of the reference DST with a gap in one cell's voltage and a NaN current:
    every published field equal to float tolerance, the quality codes and counters equal."""
    run = paper_dst_case(1200, r0_spread=np.array([1.0, 1.3, 0.8]))
    v, i = run.voltages_V.copy(), run.current_A.copy()
    v[100:110, 1] = np.nan
    i[500:503] = np.nan
    block = SampleBlock.from_arrays(run.t_s, i, v)
    out, counters = {}, {}
    for name in ("numpy", "compiled"):
        assert jit.select(name) == name
        bank = build_bank(run.cell, 3, variant, soc0=0.98)
        out[name] = bank.update_block(block)
        counters[name] = bank.counters
    ref, new = out["numpy"], out["compiled"]
    assert counters["numpy"] == counters["compiled"]
    np.testing.assert_array_equal(new.quality, ref.quality)
    for name in FIELD_NAMES:
        a, b = ref[name], new[name]
        # the model errors are differences of volts: tolerance relative to the voltage
        atol = 1e-11 if name.endswith("error_V") else 0.0
        np.testing.assert_allclose(b, a, rtol=1e-9, atol=atol, err_msg=name)
