"""A 96-cell bank equals 96 single-cell estimators (one vectorised call per sample).

The SOC observer couples the cells of a bank through three things only, the pack's current
offset (one sensor), the hysteresis map they share (its uncertainty is in every cell's update)
and the error of the hysteresis state (one current drives every cell's); with all three pinned
(priors of 0, the error not estimated), the cells must be independent.
"""

from __future__ import annotations

import numpy as np
import pytest

from bmsid.config.cell import paper_cell
from bmsid.config.engine import build_bank
from bmsid.estimate.observer_tuning import ObserverTuning
from bmsid.estimate.tuning import EstimatorTuning, Variant
from bmsid.samples import SampleBlock
from bmsid.synthetic import paper_dst_case
from bmsid.synthetic.multiday import MultidayOptions, generate

N_CELLS = 96
# Short windows: every cell runs (staggered) swarms within the 240 samples.
TUNING = EstimatorTuning(window_s=120.0, min_window_s=40.0, swarm_period_s=60.0, n_iter=3,
                         n_iter_first=4, n_particles=4, swarm_min_steps=0,
                         observer=ObserverTuning(offset_prior_C=1e-12,
                                                 offset_walk_C_per_sqrt_day=0.0,
                                                 hysteresis_prior_rel=1e-12,
                                                 hysteresis_prior_floor_V=0.0,
                                                 hysteresis_error=False))  # fmt: skip


@pytest.mark.parametrize("variant", ["hy-affrls-lpso", "non-hy-affrls"])
def test_bank_of_96_equals_96_single_estimators(variant: Variant) -> None:
    spread = np.random.default_rng(7).uniform(0.7, 1.5, N_CELLS)
    run = paper_dst_case(240, r0_spread=spread)
    bank = build_bank(run.cell, N_CELLS, variant, TUNING, soc0=0.98)
    singles = [
        build_bank(run.cell, 1, variant, TUNING, soc0=0.98, cell_ids=[c], n_stagger=N_CELLS)
        for c in range(N_CELLS)
    ]
    names = ("R0_ohm", "R1_ohm", "tau1_s", "R2_ohm", "tau2_s", "v_model_V", "soc", "lambda_")
    n_t = run.t_s.shape[0]
    got_bank = {n: np.zeros((n_t, N_CELLS)) for n in names}
    got_single = {n: np.zeros((n_t, N_CELLS)) for n in names}
    for k in range(n_t):
        eb = bank.update(run.t_s[k], run.current_A[k], run.voltages_V[k])
        assert eb is not None
        for name in names:
            got_bank[name][k] = getattr(eb, name)
        for c, single in enumerate(singles):
            es = single.update(run.t_s[k], run.current_A[k], run.voltages_V[k, c : c + 1])
            assert es is not None
            for name in names:
                got_single[name][k, c] = getattr(es, name)[0]
    for name in names:
        np.testing.assert_allclose(got_bank[name], got_single[name], rtol=1e-9, err_msg=name)
    assert bank.counters.get("swarms", 0) > 0 or variant != "hy-affrls-lpso"


def test_the_estimates_do_not_depend_on_the_clocks_origin() -> None:
    """A gateway's sample clock is Unix time (SocketCAN timestamps), a test's starts at 0: the
    engine must compute the same from both. (The capacity fusion once added the fade of the
    years since 1970 to its prior at the first update: capacity and SOC jumped, and R0 followed.)
    """
    rec = generate(MultidayOptions(n_days=1, duration_s=3 * 3600, current_offset_A=0.3))
    outs, banks = [], [build_bank(paper_cell(), 1), build_bank(paper_cell(), 1)]
    for bank, t0_s in zip(banks, (0.0, 1.7e9), strict=True):
        block = SampleBlock.from_arrays(rec.t_s + t0_s, rec.current_A, rec.voltage_V[:, None])
        outs.append(bank.update_block(block))
    assert banks[0].counters["capacity_updates"] > 0  # the record reaches a capacity fusion
    assert banks[1].counters == banks[0].counters
    for name in ("soc", "capacity_Ah", "current_offset_A", "R0_ohm", "R2_ohm", "tau2_s"):
        np.testing.assert_allclose(outs[1][name], outs[0][name], rtol=1e-9, err_msg=name)
