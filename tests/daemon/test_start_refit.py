"""The daemon's start SOC fitted over its first window (issue 11, "start from anywhere" live):
a gateway that starts mid-drive publishes at once from the first voltage, then continues from
the fitted start exactly as an offline run of the same record does."""

from __future__ import annotations

import logging
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from bmsid.config.engine import build_bank
from bmsid.daemon import bank_worker, start_refit
from bmsid.daemon.bank_worker import BankHost, BankSpec
from bmsid.daemon.checkpoint import CheckpointKey
from bmsid.daemon.start_refit import StartHead
from bmsid.estimate.start_fit import WINDOW_S
from bmsid.offline import start_soc
from bmsid.offline.start_soc import WINDOW_FIT, fitted_start_soc
from bmsid.samples import SampleBlock
from bmsid.synthetic import SyntheticRun, paper_dst_case

N_CELLS = 2
ENTER_S = 2016  # into the paper cell's DST: loaded, branches charged (as test_start_fit)


def _record(enter_s: int) -> tuple[SyntheticRun, SampleBlock]:
    run = paper_dst_case(ENTER_S + 3000, soc0=0.9, r0_spread=np.linspace(1.0, 1.3, N_CELLS))
    k = slice(enter_s, None)
    return run, SampleBlock.from_arrays(run.t_s[k], run.current_A[k], run.voltages_V[k])


def _host(tmp_path: Path, run: SyntheticRun, **kw: object) -> BankHost:
    base: dict[str, object] = {
        "cell": run.cell, "n_cells": N_CELLS, "variant": "hy-affrls-lpso",
        "tuning": build_bank(run.cell, N_CELLS).tuning, "soc0": None, "restore": False,
        "ckpt_path": tmp_path / "p.ckpt.npz", "ckpt_key": CheckpointKey("p", N_CELLS, "h"),
        "pack_id": "p", "topic_prefix": "bmsid", "mqtt_enabled": False, "qos": 1,
        "publish_period_s": 0.0,
    }  # fmt: skip
    host = BankHost(BankSpec(**(base | kw)))  # type: ignore[arg-type]
    host.start()
    return host


def _counting(fit: Callable[..., Any], beats: list[int]) -> Callable[..., Any]:
    """``fit`` whose ``each_cell`` callback also marks ``beats`` with -1 (a beat from the fit)."""

    def counted(*args: Any, each_cell: Callable[[], None] | None = None, **kw: Any) -> Any:
        def mark() -> None:
            beats.append(-1)
            if each_cell is not None:
                each_cell()

        return fit(*args, each_cell=mark, **kw)

    return counted


def _feed(host: BankHost, block: SampleBlock, batch: int = 97) -> str:
    """Feed ``block`` in batches; the ``soc_init`` the last batch reported."""
    soc_init = ""
    for a in range(0, len(block), batch):
        soc_init = host.update(block.slice(a, a + batch)).soc_init
    return soc_init


def test_a_start_mid_drive_continues_from_the_fitted_start_as_offline(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    run, block = _record(ENTER_S)
    host = _host(tmp_path, run)
    assert host.bank.soc_init_method == "pending"
    truth = run.soc_true[ENTER_S]
    with caplog.at_level(logging.INFO, logger="bmsid.daemon.bank_worker"):
        assert _feed(host, block) == WINDOW_FIT  # what the daemon's status payload says
    assert host.counters["start_refits"] == 1
    assert host.bank.soc_init_method == WINDOW_FIT
    assert "start SOC fitted over the first 1200 s (it opened under load)" in caplog.text
    # Offline: the fit over the record's first window, then one bank over the whole record.
    fitted = fitted_start_soc([block], run.cell, host.spec.tuning, None)
    assert fitted is not None
    assert np.all(np.abs(fitted.soc0 - truth) < 0.015), (fitted.soc0, truth)
    ref = build_bank(run.cell, N_CELLS, "hy-affrls-lpso", host.spec.tuning, soc0=fitted.soc0,
                     branch0_V=fitted.branch_V)  # fmt: skip
    ref.update_block(block)
    np.testing.assert_allclose(host.bank.state.z, ref.state.z, rtol=0, atol=1e-12)
    np.testing.assert_allclose(host.bank.params.outputs()["R0_ohm"],
                               ref.params.outputs()["R0_ohm"], rtol=1e-12)  # fmt: skip
    assert np.all(np.abs(host.bank.state.z - run.soc_true[-1]) < 0.015)


def test_a_rested_start_and_a_restore_keep_their_start(tmp_path: Path) -> None:
    run, block = _record(0)  # paper_dst_case opens with a rest: the first voltage is an OCV
    host = _host(tmp_path / "rested", run)
    assert _feed(host, block.slice(0, int(WINDOW_S) + 200)) == "ocv_at_rest"
    assert host.counters["start_refits"] == 0
    assert host.bank.soc_init_method == "ocv_at_rest"
    assert host._head is None  # the window was seen: nothing more is kept
    given = _host(tmp_path / "given", run, soc0=0.9)
    given.checkpoint(clean=True)
    restored = _host(tmp_path / "given", run, restore=True)
    assert restored._head is None


def test_a_rested_start_after_a_discharge_gets_its_hysteresis_state_live(
    tmp_path: Path, caplog: pytest.LogCaptureFixture, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A gateway that starts at rest after a discharge (h0 = -1, which its first voltage cannot
    show): it publishes from that voltage at once (1.5 SOC points low), then refits (SOC, h0)
    over the first window as ``identify`` does, and continues from there. The fit beats the
    watchdog's heartbeat between cells (a large pack's fit takes seconds)."""
    run = paper_dst_case(5000, soc0=0.7, h0=-1.0, r0_spread=np.linspace(1.0, 1.3, N_CELLS))
    block = SampleBlock.from_arrays(run.t_s, run.current_A, run.voltages_V)
    host = _host(tmp_path, run)
    beats: list[int] = []
    host.beat = lambda: beats.append(host.counters["start_refits"])
    monkeypatch.setattr(bank_worker, "HEARTBEAT_S", 0.0)
    monkeypatch.setattr(start_soc, "fit_start_soc", _counting(start_soc.fit_start_soc, beats))
    with caplog.at_level(logging.INFO, logger="bmsid.daemon.bank_worker"):
        assert _feed(host, block) == WINDOW_FIT
    assert host.counters["start_refits"] == 1
    assert beats.count(-1) == N_CELLS - 1  # one between each two cells' fits
    assert "(it opened at rest, hysteresis state -0.9" in caplog.text  # -0.90: 1 mV noise
    fitted = fitted_start_soc([block], run.cell, host.spec.tuning, None)
    assert fitted is not None and fitted.h0 is not None
    np.testing.assert_allclose(fitted.h0, -1.0, atol=0.15)
    ref = build_bank(run.cell, N_CELLS, "hy-affrls-lpso", host.spec.tuning, soc0=fitted.soc0,
                     branch0_V=fitted.branch_V, h0=fitted.h0)  # fmt: skip
    ref.update_block(block)
    np.testing.assert_allclose(host.bank.state.z, ref.state.z, rtol=0, atol=1e-12)
    assert np.all(np.abs(host.bank.state.z - run.soc_true[-1]) < 0.006)  # before: 0.015-0.016


def test_a_configured_soc0_entered_under_load_keeps_it_and_fits_the_branches(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """The true SOC configured, entered mid-drive: the SOC stays as configured, the branches
    are fitted over the first window, as ``identify --soc0`` does."""
    run, block = _record(ENTER_S)
    truth = float(run.soc_true[ENTER_S])
    host = _host(tmp_path, run, soc0=truth)
    with caplog.at_level(logging.INFO, logger="bmsid.daemon.bank_worker"):
        assert _feed(host, block) == "given"
    assert host.counters["start_refits"] == 1
    assert "start branches fitted (SOC as configured) over the first 1200 s" in caplog.text
    fitted = fitted_start_soc([block], run.cell, host.spec.tuning, None, soc0=truth)
    assert fitted is not None and not fitted.soc_fitted
    assert np.all(fitted.soc0 == truth) and np.all(fitted.branch_V > 0.01)
    ref = build_bank(run.cell, N_CELLS, "hy-affrls-lpso", host.spec.tuning, soc0=truth,
                     branch0_V=fitted.branch_V)  # fmt: skip
    ref.update_block(block)
    np.testing.assert_allclose(host.bank.state.z, ref.state.z, rtol=0, atol=1e-12)
    np.testing.assert_allclose(host.bank.params.outputs()["R0_ohm"],
                               ref.params.outputs()["R0_ohm"], rtol=1e-12)  # fmt: skip


def test_a_fast_bus_keeps_the_first_voltage_start_and_says_so(
    monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    _, block = _record(ENTER_S)
    monkeypatch.setattr(start_refit, "MAX_HEAD_CELL_SAMPLES", 500)
    head = StartHead()
    with caplog.at_level(logging.WARNING, logger="bmsid.daemon.start_refit"):
        got = [head.add(block.slice(a, a + 100)) for a in range(0, 1300, 100)]
    assert all(g is None for g in got)
    assert not head.open and not head.blocks
    assert "start SOC not refitted" in caplog.text


def test_the_head_after_a_long_rest_spans_the_window_from_the_load() -> None:
    """A gateway that boots on a parked car: it keeps the rest and closes its head 20 min after
    the load (from a minute before it), not after 20 min of rest that show nothing."""
    t = np.arange(3 * 3600, dtype=np.float64)
    i = np.where(t < 7200.0, 0.1, 30.0)  # 0.1 A of auxiliary load: within the rest limit
    block = SampleBlock.from_arrays(t, i, np.full((t.shape[0], 1), 3.7))
    head = StartHead(rest_limit_A=0.7)
    got = [head.add(block.slice(a, a + 100)) for a in range(0, len(block), 100)]
    done = [g for g in got if g is not None]
    assert len(done) == 1 and not head.open
    assert done[0].t_s[-1] == pytest.approx(7200.0 - 60.0 + WINDOW_S, abs=100.0)
    quick = StartHead(rest_limit_A=0.7)  # a load within the first 10 min: the first 20 min
    got = [quick.add(block.slice(a, a + 100)) for a in range(6600, len(block), 100)]
    assert next(g for g in got if g is not None).t_s[-1] == pytest.approx(6600 + WINDOW_S, abs=100)


def test_a_noisy_sensor_at_rest_is_no_load_even_a_sample_at_a_time() -> None:
    """The parked car again, its current sensor's noise 0.3 A std around the 0.1 A draw (the
    rest limit 0.7 A: one sample in seventy beyond it), fed as the bus does, a sample per
    block: the noise seen so far (``StartHead.noise_sd_A``) keeps the load at the drive's
    start, not at the first noisy sample (the head then closed after 20 min of rest)."""
    t = np.arange(3 * 3600, dtype=np.float64)
    rng = np.random.default_rng(0)
    i = np.where(t < 7200.0, 0.1 + rng.normal(0.0, 0.3, t.shape[0]), 30.0)
    assert np.count_nonzero(np.abs(i[:7200]) > 0.7) > 10
    block = SampleBlock.from_arrays(t, i, np.full((t.shape[0], 1), 3.7))
    head = StartHead(rest_limit_A=0.7)
    done = next(g for g in (head.add(block.slice(a, a + 1)) for a in range(len(block))) if g)
    assert head.load_s == pytest.approx(7200.0, abs=60.0)
    assert done.t_s[-1] == pytest.approx(7200.0 - 60.0 + WINDOW_S, abs=100.0)
