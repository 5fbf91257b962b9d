"""``bmsid demo`` and its bundled log."""

from __future__ import annotations

from pathlib import Path

import pytest

from bmsid.cli.main import main
from bmsid.daemon.demo_data import DEMO_LOG, write_demo_log


def test_bundled_demo_log_is_reproducible_and_small(tmp_path: Path) -> None:
    assert DEMO_LOG.stat().st_size < 3_000_000
    again = write_demo_log(tmp_path / "demo.log")
    assert again.read_bytes() == DEMO_LOG.read_bytes()


def test_demo_runs_without_hardware_or_broker(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert (
        main(["demo", "--duration-s", "6", "--speed", "100", "--no-mqtt", "--out", str(tmp_path)])
        == 0
    )
    out = capsys.readouterr().out
    assert "MQTT disabled: --no-mqtt" in out
    assert "weakest cell (largest R0): 5" in out  # the simulated weak cell, found online
    assert "decode errors 0" in out
    assert (tmp_path / "demo_report.png").stat().st_size > 10_000


def test_demo_rejects_bad_speed(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["demo", "--speed", "0"]) == 2
    assert "--speed" in capsys.readouterr().err
