"""When a rest anchors (``estimate/rest_anchor.py``): the own-tau2 rule, and in a pack of 3 or
more cells no cell waits longer than the cells' median tau2 asks; the current sensor's noise,
which must neither end a rest nor start a load."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from bmsid.config.cell import load_cell_config
from bmsid.config.engine import build_bank, ocv_model
from bmsid.estimate.observer_tuning import ObserverTuning
from bmsid.estimate.rest_anchor import anchors_due, next_noise, noise_std_A, rest_limit
from bmsid.estimate.start_fit import first_load_s
from bmsid.model.simulator import simulate
from bmsid.profiles import dst_current
from bmsid.samples import SampleBlock

TUN = ObserverTuning()
CELL = Path(__file__).resolve().parents[2] / "configs" / "cells" / "a123_lfp_25C.toml"
H = 3600.0


@settings(max_examples=200, deadline=None)
@given(
    rest_s=st.floats(0.0, 20_000.0),
    tau2=st.lists(st.floats(10.0, 5000.0), min_size=1, max_size=10),
    seed=st.integers(0, 2**32 - 1),
)
def test_a_rest_anchors_after_3_tau2_capped_at_the_packs_median(
    rest_s: float, tau2: list[float], seed: int
) -> None:
    tau = np.asarray(tau2)
    anchored = np.random.default_rng(seed).random(tau.size) < 0.3
    due = anchors_due(rest_s, anchored, tau, TUN)
    if rest_s < TUN.anchor_min_rest_s:
        assert due is None
        return
    assert due is not None and not due[anchored].any()
    own = ~anchored & (rest_s >= np.maximum(TUN.anchor_min_rest_s, 3.0 * tau))
    assert not (own & ~due).any()  # every cell its own tau2 anchors is anchored
    if tau.size < 3:
        np.testing.assert_array_equal(due, own)
    else:
        capped = ~anchored & (rest_s >= np.maximum(TUN.anchor_min_rest_s, 3.0 * np.median(tau)))
        np.testing.assert_array_equal(due, own | capped)


# ------------------------------------------------------------------ the current sensor's noise
@settings(max_examples=50, deadline=None)
@given(
    sigma=st.floats(0.0, 0.05), base=st.floats(0.005, 0.7), offset=st.floats(-0.5, 0.5),
    seed=st.integers(0, 2**32 - 1),
)  # fmt: skip
def test_the_noise_estimate_is_the_sensors_and_a_load_is_none(
    sigma: float, base: float, offset: float, seed: int
) -> None:
    """Ticks at rest (an offset or draw within half the rest limit, Gaussian noise of std
    ``sigma`` up to half the limit): the
    running estimate (``next_noise``) and the head's robust estimate (``noise_std_A``) find
    sigma within 15 %; an offset cancels in the differences; ticks under load (20 rest limits,
    a drive) and a missing previous current (NaN) leave it as it was; the rest limit is the
    base plus 3 std."""
    assume(sigma <= 0.5 * base)  # more: a rest within the limit is noise's chance (truncated)
    rng = np.random.default_rng(seed)
    i = offset * base + rng.normal(0.0, sigma, 6000)
    sd, prev = 0.0, math.nan
    for x in i:
        sd, prev = next_noise(sd, float(x), prev, base, 1.0), float(x)
    assert math.isclose(sd, sigma, rel_tol=0.15, abs_tol=1e-9)
    assert math.isclose(noise_std_A(i, base), sigma, rel_tol=0.15, abs_tol=1e-9)
    assert next_noise(sd, 20.0 * base, 0.0, base, 1.0) == sd
    assert next_noise(sd, 0.0, math.nan, base, 1.0) == sd
    assert next_noise(sd, 0.0, 0.0, base, 0.0) == sd
    assert rest_limit(base, sd) == base + 3.0 * sd
    assert noise_std_A(np.zeros(100), base) == 0.0  # a tester's 0.000 A at rest
    for k in (1.0, 2.0):  # a noise as large as the limit, or twice it: the head finds it too
        loud = rng.normal(0.0, k * base, 3600)
        assert math.isclose(noise_std_A(loud, base), k * base, rel_tol=0.15)
    assert noise_std_A(np.full(100, 30.0 * base), base) == 0.0  # a drive: no pair near rest


def test_a_noisy_sensor_neither_hides_the_rests_nor_the_first_load() -> None:
    """A 2 Ah LFP cell (the shipped A123 config) with 10 mA of current noise, half its 1 % C
    rest limit: 1 h of rest, a 1.5 h drive, 2.5 h of rest. The start fit's load is the drive's
    (the first noisy sample past the limit put it at the record's second sample), and the
    rest after the drive anchors; before, a tick of noise past the limit ended a rest one tick
    in twenty, and a 12-hour record anchored once instead of four times."""
    cell = load_cell_config(CELL)
    t = np.arange(0.0, 5 * H)
    i = np.where((t >= H) & (t < 2.5 * H), dst_current(t - H, 2.0), 0.0)
    sim = simulate(
        t, i, ocv_model(cell), capacity_Ah=cell.capacity_Ah, R0_ohm=0.01, R1_ohm=0.005,
        tau1_s=20.0, R2_ohm=0.01, tau2_s=300.0, gamma=30.0, soc0=0.9, h0=0.0,
        play=cell.hysteresis_law == "play",
    )  # fmt: skip
    rng = np.random.default_rng(0)
    i_meas = i + rng.normal(0.0, 0.01, t.size)
    limit = cell.soc_init.rest_current_C * cell.capacity_Ah
    assert first_load_s(t, i_meas, limit) == pytest.approx(H, abs=60.0)
    block = SampleBlock.from_arrays(t, i_meas, sim.v_V.T + rng.normal(0.0, 1e-3, (t.size, 1)))
    bank = build_bank(cell, 1, "hy-affrls", soc0=0.9)
    bank.update_block(block)
    assert bank.counters["anchors"] >= 2  # the start's rest and the one after the drive
