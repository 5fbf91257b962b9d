"""Mappings validate against their DBC; make-log writes a log that reads back as the CSV."""

from __future__ import annotations

import types
from pathlib import Path

import numpy as np
import pytest

from bmsid.canbus.logs import samples_from_log
from bmsid.canbus.mapping import default_mapping, load_mapping
from bmsid.cli import make_log
from bmsid.cli.main import main
from bmsid.errors import UserError

REPO = Path(__file__).resolve().parents[2]
GOOD = (REPO / "dbc" / "bmsid_mapping.toml").read_text()


def _write(tmp_path: Path, text: str) -> Path:
    (tmp_path / "bmsid.dbc").write_text((REPO / "dbc" / "bmsid.dbc").read_text())
    p = tmp_path / "m.toml"
    p.write_text(text)
    return p


def test_default_mapping_addresses_512_cells() -> None:
    m = default_mapping()
    assert m.max_cells() == 512 and m.dbc.is_file()


@pytest.mark.parametrize(
    ("old", "new", "field"),
    [
        ('signal = "PackCurrent"', 'signal = "PackCurent"', "current.signal"),
        (
            'message = "BMSID_PackCurrent"\nsignal = "PackCurrent"',
            'message = "Nope"\nsignal = "PackCurrent"',
            "current.message",
        ),
        ('positive = "discharge"', 'positive = "up"', "current.positive"),
        ('multiplexer = "CellGroup"', 'multiplexer = "CellVoltage0"', "cells.multiplexer"),
        (
            'layout = "multiplexed"\nmessage = "BMSID_CellVoltages"',
            'layout = "diagonal"\nmessage = "BMSID_CellVoltages"',
            "cells",
        ),
        ("count = 3", "count = 999", "temperatures.count"),
        ('dbc = "bmsid.dbc"', 'dbc = "missing.dbc"', "dbc"),
        ('name = "bmsid"', 'name = "bmsid"\ncolour = "red"', "colour"),
    ],
)
def test_bad_mapping_names_the_field(tmp_path: Path, old: str, new: str, field: str) -> None:
    assert old in GOOD
    with pytest.raises(UserError, match=field.replace(".", r"\.")):
        load_mapping(_write(tmp_path, GOOD.replace(old, new)))


def test_unreadable_toml(tmp_path: Path) -> None:
    with pytest.raises(UserError, match="TOML"):
        load_mapping(_write(tmp_path, "this is = = not toml"))


def _fake_csv(t: np.ndarray, i: np.ndarray, v: np.ndarray) -> types.SimpleNamespace:
    return types.SimpleNamespace(
        t_s=t,
        current_A=i,
        cell_voltages_V=v,
        temperature_C=np.full(t.shape, 25.0),
        missing_values=int(np.count_nonzero(~np.isfinite(i)) + np.count_nonzero(~np.isfinite(v))),
    )


@pytest.mark.parametrize("mapping_file", [None, "example_bms_mapping.toml"])
def test_make_log_cli(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, mapping_file: str | None
) -> None:
    rng = np.random.default_rng(3)
    t = np.arange(100) * 0.5
    i = rng.uniform(-20, 20, 100)
    v = rng.uniform(3.2, 4.1, (100, 3))
    monkeypatch.setattr(make_log, "load_csv", lambda path: _fake_csv(t, i, v))
    argv = ["make-log", str(tmp_path / "in.csv"), "--out", str(tmp_path / "o.log"), "--t0", "1e9"]
    if mapping_file:
        argv += ["--mapping", str(REPO / "dbc" / mapping_file)]
    assert main(argv) == 0
    mapping = load_mapping(REPO / "dbc" / mapping_file) if mapping_file else default_mapping()
    samples = samples_from_log(tmp_path / "o.log", mapping, 3)
    assert len(samples) == 100
    np.testing.assert_allclose(np.array([s.cell_voltages_V for s in samples]), v, atol=5e-4)
    np.testing.assert_allclose([s.current_A for s in samples], i, atol=0.05)
    assert samples[3].temperatures_C is not None and samples[3].temperatures_C[0] == pytest.approx(
        25.0
    )


def test_make_log_sends_a_blank_reading_as_not_available(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A CSV with a blank cell voltage and a blank current (which identify reads as missing)
    was refused ("empty, NaN or non-numeric values on line(s) ..."); each is now sent as its
    signal's not-available value: the decoder leaves the cell out of that sample and holds the
    last current for the missing one (within its staleness, as a frame that did not come)."""
    rows = ["t_s,current_A,v_cell_01,v_cell_02"]
    rows += [f"{k},{1.5 if k != 4 else ''},3.{k}00,{'' if k == 7 else '3.700'}" for k in range(10)]
    src = tmp_path / "in.csv"
    src.write_text("\n".join(rows) + "\n")
    out = tmp_path / "o.log"
    assert main(["make-log", str(src), "--out", str(out), "--t0", "1e9"]) == 0
    assert "2 empty or NaN reading(s) sent as their signal's not-available value" in (
        capsys.readouterr().out
    )
    samples = samples_from_log(out, default_mapping(), 2)
    times = [round(s.t_s - 1e9) for s in samples]
    assert times == list(range(10)) and samples[4].current_A == pytest.approx(1.5)
    at7 = samples[7].cell_voltages_V
    assert at7[0] == pytest.approx(3.7) and np.isnan(at7[1])


def test_make_log_rate_hz_resamples(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    t = np.arange(11) * 1.0
    monkeypatch.setattr(
        make_log, "load_csv", lambda path: _fake_csv(t, t.copy(), np.full((11, 1), 3.5))
    )
    out = tmp_path / "o.log"
    assert main(["make-log", "x.csv", "--out", str(out), "--rate-hz", "4", "--t0", "1e9"]) == 0
    samples = samples_from_log(out, default_mapping(), 1)
    assert len(samples) == 41
    np.testing.assert_allclose([s.current_A for s in samples], np.arange(41) * 0.25, atol=5e-4)


def test_make_log_bad_mapping_is_one_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert (
        main(
            [
                "make-log",
                "x.csv",
                "--out",
                str(tmp_path / "o"),
                "--mapping",
                str(tmp_path / "none.toml"),
            ]
        )
        == 2
    )
    assert "mapping file not found" in capsys.readouterr().err
