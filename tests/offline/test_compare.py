"""``bmsid compare``: Table 2, SOC-band and consistency files from short synthetic runs; the pure
report functions (labels, tables, consistency) on known numbers."""

from __future__ import annotations

import csv
import json
import math
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from test_identify_cli import _trace, synthetic_columns, write_csv

from bmsid.cli.main import main
from bmsid.config.cell import paper_cell, save_cell_config
from bmsid.estimate.guard import WATCHED
from bmsid.estimate.types import VARIANTS, EstimateBlock, Quality
from bmsid.offline.report import (
    CONSISTENCY_PARAMS,
    HeldShare,
    Table2Row,
    consistency,
    consistency_csv,
    consistency_markdown,
    label_dataset,
    soc_band_rows,
    soc_bands_csv,
    soc_bands_markdown,
    table2_csv,
    table2_markdown,
    unique_displays,
)
from bmsid.offline.scoring import EvalWindow, RunScorer


@pytest.fixture(scope="module")
def dst_bus_csvs(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path, Path]:
    """A DST and a BBDST file of the paper's cell at 25 C, and that cell's config."""
    tmp = tmp_path_factory.mktemp("cmp")
    cfg = tmp / "cell.toml"
    save_cell_config(paper_cell(), cfg)
    dst = write_csv(tmp / "syn_dst_25C.csv", synthetic_columns(1500, seed=1))
    cols = synthetic_columns(1500, seed=2, bus=True)
    bus = write_csv(tmp / "syn_bbdst_25C.csv.gz", cols)
    return dst, bus, cfg


@pytest.fixture(scope="module")
def compare_out(
    dst_bus_csvs: tuple[Path, Path, Path], tmp_path_factory: pytest.TempPathFactory
) -> Path:
    dst, bus, cfg = dst_bus_csvs
    out = tmp_path_factory.mktemp("cmp_out") / "out"
    argv = ["compare", str(dst), str(bus), "--cell-config", str(cfg), "--out", str(out)]
    assert main(argv) == 0
    return out


def test_compare_writes_table2(compare_out: Path) -> None:
    with (compare_out / "table2.csv").open(encoding="utf-8") as fh:
        rows = list(csv.DictReader(fh))
    assert len(rows) == 2 * len(VARIANTS)
    assert {r["dataset"] for r in rows} == {"DST 25C", "BBDST 25C"}
    assert {r["algorithm"] for r in rows} == set(VARIANTS)
    for r in rows:
        assert r["temperature_C"] == "25.0"
        for key in (
            "max_abs_error_V", "rmse_V", "mape_pct", "runtime_s", "rmse_whole_V",
            "rmse_startup_V", "rmse_after_startup_V",
        ):  # fmt: skip
            assert math.isfinite(float(r[key])) and float(r[key]) >= 0
        assert int(r["n_samples"]) == 1500  # default window: the whole record
        assert r["rmse_V"] == r["rmse_whole_V"]
    md = (compare_out / "table2.md").read_text(encoding="utf-8")
    assert "| hy-affrls-lpso (paper) | 21.4 | 28.4 |" in md  # the paper's 25 C DST / BBDST
    assert "| RMSE whole / mV | RMSE first 10 % / mV | RMSE after 10 % / mV |" in md
    assert "| RMSE in window / mV |" in md and "evaluation window (all ticks)" in md
    assert (compare_out / "rmse.png").read_bytes()[:4] == b"\x89PNG"
    for stem in ("syn_dst_25C", "syn_bbdst_25C"):
        for variant in VARIANTS:
            doc = json.loads((compare_out / stem / variant / "metrics.json").read_text())
            assert doc["algorithm"] == variant
            assert (compare_out / stem / variant / "voltage.png").exists()


def test_compare_writes_soc_bands(compare_out: Path) -> None:
    with (compare_out / "soc_bands.csv").open(encoding="utf-8") as fh:
        rows = list(csv.DictReader(fh))
    runs = {(r["dataset"], r["algorithm"]) for r in rows}
    assert runs == {(d, v) for d in ("DST 25C", "BBDST 25C") for v in VARIANTS}
    for d, v in runs:
        mine = [r for r in rows if (r["dataset"], r["algorithm"]) == (d, v)]
        assert sum(int(r["n_samples"]) for r in mine) == 1500  # the bands hold every tick
        assert all(math.isfinite(float(r["rmse_V"])) for r in mine)
    md = (compare_out / "soc_bands.md").read_text(encoding="utf-8")
    assert "per 10 % SOC band" in md and "SOC: the estimator's" in md
    assert "| DST 25C | hy-affrls-lpso |" in md and "| 90-100 % |" in md


def test_compare_scores_on_a_coulomb_count_from_a_known_start(
    dst_bus_csvs: tuple[Path, Path, Path], tmp_path: Path
) -> None:
    """--score-soc0: the window and the bands on the count from 95 %, not on the estimator's
    SOC (started here at a wrong 60 %)."""
    dst, _, cfg = dst_bus_csvs
    out = tmp_path / "out"
    argv = [
        "compare", str(dst), "--cell-config", str(cfg), "--out", str(out), "--algorithms",
        "non-hy-affrls", "--soc0", "0.6", "--score-soc0", "0.95", "--soc-window", "0.2,0.9",
    ]  # fmt: skip
    assert main(argv) == 0
    soc_true = synthetic_columns(1500, seed=1)["soc_true"]
    with (out / "table2.csv").open(encoding="utf-8") as fh:
        (row,) = list(csv.DictReader(fh))
    # The count from 95 % is the simulation's SOC (to the tick mean current).
    assert abs(int(row["n_samples"]) - int(np.sum((soc_true >= 0.2) & (soc_true <= 0.9)))) <= 2
    assert int(row["n_samples"]) < 1500
    summary = json.loads((out / "compare.json").read_text(encoding="utf-8"))
    (run,) = summary["runs"]
    assert run["scoring_soc"]["source"] == "coulomb_count"
    assert run["scoring_soc"]["soc0"] == 0.95
    assert "coulomb count" in (out / "table2.md").read_text(encoding="utf-8")
    assert "coulomb count" in (out / "soc_bands.md").read_text(encoding="utf-8")


def test_compare_bad_score_soc0_is_one_line(
    dst_bus_csvs: tuple[Path, Path, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    dst, _, cfg = dst_bus_csvs
    argv = ["compare", str(dst), "--cell-config", str(cfg), "--out", str(tmp_path / "o")]
    assert main([*argv, "--score-soc0", "95"]) == 2
    assert main([*argv, "--score-soc0", "0.9", "--score-soc0", "0.8"]) == 2
    errs = capsys.readouterr().err.strip().splitlines()
    assert len(errs) == 2
    assert errs[0].endswith("error: --score-soc0 is a fraction in [0, 1], got 95")
    assert errs[1].endswith("error: 2 --score-soc0 for 1 datasets: give 1 or 1")


def test_compare_writes_consistency(compare_out: Path) -> None:
    with (compare_out / "consistency.csv").open(encoding="utf-8") as fh:
        rows = list(csv.DictReader(fh))
    assert len(rows) == 2 * len(VARIANTS)
    assert {r["group"] for r in rows} == {"config paper-70Ah-NMC, data 25 C"}
    for r in rows:
        assert math.isfinite(float(r["consistency_error_pct"]))
        assert math.isfinite(float(r["trajectory_spread_pct"]))
        assert 0.0 <= float(r["held_pct"]) <= 100.0
    # Two profiles of one simulated cell: R0 agrees to a few percent after fusion.
    lpso = [r for r in rows if r["algorithm"] == "hy-affrls-lpso"]
    assert all(abs(float(r["R0_ohm_normalised"]) - 1) < 0.05 for r in lpso)
    assert (compare_out / "consistency_config_paper-70Ah-NMC_data_25_C.png").exists()
    assert "Fig. 14" in (compare_out / "consistency.md").read_text(encoding="utf-8")


def test_compare_bad_config_count_is_one_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    a = write_csv(tmp_path / "a.csv", synthetic_columns(30))
    cfg = tmp_path / "c.toml"
    save_cell_config(paper_cell(), cfg)
    argv = ["compare", str(a), str(a), str(a), "--out", str(tmp_path / "o")]
    assert main([*argv, "--cell-config", str(cfg), "--cell-config", str(cfg)]) == 2
    assert main([*argv, "--cell-config", str(cfg), "--algorithms", "affrls"]) == 2
    assert main(argv) == 2
    errs = capsys.readouterr().err.strip().splitlines()
    assert len(errs) == 3
    assert "2 --cell-config for 3 datasets" in errs[0]
    assert "unknown 'affrls'" in errs[1]
    assert "give --cell-config" in errs[2]


@pytest.mark.parametrize(
    ("name", "profile", "temp"),
    [
        ("dfn_nmc_dst_15C.csv.gz", "DST", 15.0),
        ("dfn_nmc_bbdst_35C.csv.gz", "BBDST", 35.0),
        ("calce_inr18650-20r_45C_BJDST_80soc.csv.gz", "BJDST", 45.0),
        ("a123_25C_DYN50.csv.gz", "DYN50", 25.0),
        ("run.csv", "run", None),
    ],
)
def test_label_dataset(name: str, profile: str, temp: float | None) -> None:
    lb = label_dataset(name)
    assert (lb.profile, lb.temperature_C) == (profile, temp)


def test_label_falls_back_to_temperature_column_and_stem() -> None:
    assert label_dataset("x_dst.csv", 24.96).temperature_C == 24.96
    labels = [label_dataset("a_dst_25C_80soc.csv"), label_dataset("a_dst_25C_50soc.csv")]
    assert unique_displays(labels) == ["a_dst_25C_80soc", "a_dst_25C_50soc"]


def test_table2_formats() -> None:
    rows = [
        Table2Row("DST 15C", "DST", 15.0, v, 100, 0.01 * (k + 1), 0.001 * (k + 1), 0.1, 2.0)
        for k, v in enumerate(VARIANTS)
    ]
    text = table2_csv(rows)
    assert text.splitlines()[0].startswith("dataset,profile,temperature_C,algorithm")
    assert len(text.splitlines()) == 4
    md = table2_markdown(rows, "all ticks")
    # whole, first 10 % and the rest not given: "-"; then the window's max, RMSE, MAPE, run time
    assert "| DST 15C | DST | 15 | hy-affrls-lpso | - | - | - | 30.0 | 3.00 | 0.100 | 2.0 |" in md
    assert "| hy-affrls-lpso (paper) | 11.8 |" in md
    full = Table2Row("DST 15C", "DST", 15.0, "hy-affrls", 90, 0.02, 0.002, 0.1, 2.0,
                     0.004, 0.009, 0.002)  # fmt: skip
    assert "| hy-affrls | 4.00 | 9.00 | 2.00 | 20.0 | 2.00 | 0.100 | 2.0 |" in table2_markdown(
        [full], "all ticks"
    )
    assert "rmse_whole_V,rmse_startup_V,rmse_after_startup_V" in table2_csv([full])


def test_soc_band_tables() -> None:
    bands = [
        {"band": b, "soc_lo": lo, "soc_hi": hi, "n_samples": n, "max_abs_error_V": 0.01,
         "rmse_V": r, "mape_pct": 0.1}
        for b, lo, hi, n, r in [("90-100 %", 0.9, 1.0, 5, 0.004), ("<0 %", None, 0.0, 2, 0.5)]
    ]  # fmt: skip
    rows = soc_band_rows("DST 15C", "DST", 15.0, "hy-affrls", bands)
    rows += soc_band_rows("DST 15C", "DST", 15.0, "non-hy-affrls", bands[:1])
    md = soc_bands_markdown(rows, "the estimator's")
    assert "| dataset | algorithm | <0 % | 90-100 % |" in md  # in SOC order
    assert "| DST 15C | hy-affrls | 500.00 (2) | 4.00 (5) |" in md
    assert "| DST 15C | non-hy-affrls | - | 4.00 (5) |" in md
    text = soc_bands_csv(rows)
    assert text.splitlines()[0].startswith("dataset,profile,temperature_C,algorithm,band,soc_lo")
    assert "DST 15C,DST,15.0,hy-affrls,<0 %,,0.0,2," in text
    assert "No tick was scored" in soc_bands_markdown([], "x")


@settings(max_examples=50, deadline=None)
@given(
    base=st.lists(st.floats(1e-4, 1e5), min_size=5, max_size=5),
    factors=st.lists(st.floats(0.5, 2.0), min_size=2, max_size=4),
)
def test_consistency_normalises_to_the_mean(base: list[float], factors: list[float]) -> None:
    medians = {
        f"d{k}": {p: b * f for p, b in zip(CONSISTENCY_PARAMS, base, strict=True)}
        for k, f in enumerate(factors)
    }
    # Constant trajectories at the medians: the spread equals the level error.
    flat = {d: {p: [v] * 3 for p, v in m.items()} for d, m in medians.items()}
    c = consistency("g", "hy-affrls", medians, flat)
    mean_f = float(np.mean(factors))
    for k, f in enumerate(factors):
        for p in CONSISTENCY_PARAMS:
            assert c.normalised[f"d{k}"][p] == pytest.approx(f / mean_f, rel=1e-9)
        assert c.error_pct[f"d{k}"] == pytest.approx(100 * abs(f / mean_f - 1), rel=1e-9, abs=1e-9)
        assert c.spread_pct[f"d{k}"] == pytest.approx(c.error_pct[f"d{k}"], rel=1e-9, abs=1e-9)
    same = consistency("g", "x", {"a": medians["d0"], "b": medians["d0"]})
    assert same.mean_error_pct == pytest.approx(0.0, abs=1e-9)
    assert math.isnan(same.spread_pct["a"])  # no trajectories given


def test_consistency_spread_counts_wandering() -> None:
    level = {p: 1.0 for p in CONSISTENCY_PARAMS}
    medians = {"a": level, "b": level}
    wandering = {p: [0.5, 1.0, 1.5, 1.0, 1.0] for p in CONSISTENCY_PARAMS}
    steady = {p: [1.0] * 5 for p in CONSISTENCY_PARAMS}
    c = consistency("g", "x", medians, {"a": wandering, "b": steady})
    assert c.error_pct == {"a": 0.0, "b": 0.0}
    assert c.spread_pct["b"] == 0.0
    assert c.spread_pct["a"] == pytest.approx(0.0)  # median of |dev| = 0 (3 of 5 at the level)
    c2 = consistency("g", "x", medians, {"a": {p: [1.2] * 5 for p in level}, "b": steady})
    assert c2.spread_pct["a"] == pytest.approx(20.0)


# ----------------------------------------------------------------------------- inputs (sweep D)
def _one_variant(path: Path, cfg: Path, out: Path, *extra: str) -> list[str]:
    return ["compare", str(path), "--cell-config", str(cfg), "--out", str(out),
            "--algorithms", "non-hy-affrls", *extra]  # fmt: skip


def test_compare_refuses_what_identify_refuses(
    dst_bus_csvs: tuple[Path, Path, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """compare ran no record checks: a sign-flipped file went into Table 2 at 676 mV, one in
    ms at 27 mV. Now identify's message, exit 2; the fix it names (``--columns``) works."""
    _, _, cfg = dst_bus_csvs
    cols = synthetic_columns(1500, seed=1)
    flipped = write_csv(tmp_path / "flip_dst_25C.csv", {**cols, "current_A": -cols["current_A"]})
    ms = write_csv(tmp_path / "ms_dst_25C.csv", {**cols, "t_s": 1000.0 * cols["t_s"]})
    assert main(_one_variant(flipped, cfg, tmp_path / "a")) == 2
    assert main(_one_variant(ms, cfg, tmp_path / "b")) == 2
    errs = capsys.readouterr().err.strip().splitlines()
    assert len(errs) == 2
    assert f"{flipped}: current sign looks flipped" in errs[0]
    assert errs[0].endswith("pass --charge-positive")
    assert f"{ms}: t_s looks like milliseconds" in errs[1]
    assert errs[1].endswith("--columns t_s=t_s*0.001")
    assert not (tmp_path / "a" / "table2.csv").exists()
    assert main(_one_variant(flipped, cfg, tmp_path / "c", "--charge-positive")) == 0
    assert main(_one_variant(ms, cfg, tmp_path / "d", "--columns", "t_s=t_s*0.001")) == 0


def test_compare_notes_nan_readings_as_identify(
    dst_bus_csvs: tuple[Path, Path, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    _, _, cfg = dst_bus_csvs
    cols = synthetic_columns(1500, seed=1)
    cols["voltage_V"][[100, 700]] = np.nan
    path = write_csv(tmp_path / "nan_dst_25C.csv", cols)
    assert main(_one_variant(path, cfg, tmp_path / "o")) == 0
    assert f"{path}: 2 empty or NaN current/voltage/temperature value(s) read as missing" in (
        capsys.readouterr().out
    )


def test_compare_reads_a_candump_log(dst_bus_csvs: tuple[Path, Path, Path], tmp_path: Path) -> None:
    """The README says compare reads candump logs; it read a .log as a CSV and failed. Now its
    row is identify's on the same log."""
    dst, _, cfg = dst_bus_csvs
    log = tmp_path / "syn_dst_25C.log"
    assert main(["make-log", str(dst), "--out", str(log), "--t0", "1.7e9"]) == 0
    assert main(_one_variant(log, cfg, tmp_path / "o")) == 0
    with (tmp_path / "o" / "table2.csv").open(encoding="utf-8") as fh:
        (row,) = list(csv.DictReader(fh))
    one = ["identify", str(log), "--cell-config", str(cfg), "--algorithm", "non-hy-affrls"]
    assert main([*one, "--out", str(tmp_path / "i")]) == 0
    doc = json.loads((tmp_path / "i" / "metrics.json").read_text(encoding="utf-8"))
    assert int(row["n_samples"]) == doc["n_samples"] == 1500
    assert float(row["rmse_V"]) == pytest.approx(doc["rmse_V"], rel=1e-6)


def test_compare_refuses_a_directory_and_a_file_twice(
    dst_bus_csvs: tuple[Path, Path, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A directory was 'no such file'; a file given twice shared one output folder and the
    consistency analysis found no group."""
    dst, _, cfg = dst_bus_csvs
    base = ["--cell-config", str(cfg), "--out", str(tmp_path / "o")]
    assert main(["compare", str(dst.parent), *base]) == 2
    assert main(["compare", str(dst), str(dst), *base]) == 2
    (tmp_path / "b").mkdir()
    other = write_csv(tmp_path / "b" / dst.name, synthetic_columns(30))
    assert main(["compare", str(dst), str(other), *base]) == 2
    errs = capsys.readouterr().err.strip().splitlines()
    assert len(errs) == 3
    assert errs[2].endswith(
        f"{other} and {dst} have one name (syn_dst_25C): their outputs would share one folder; "
        "rename one"
    )
    d = dst.parent
    assert errs[0].endswith(f"{d}: is a directory: give its files (e.g. {d}/*.csv)")
    assert errs[1].endswith(f"{dst}: given twice: give each dataset once")


# ----------------------------------------------------------------------------- held values (S1)
def held_share(trace: EstimateBlock, window: EvalWindow, cell: int) -> HeldShare:
    return HeldShare(*RunScorer.of_trace(trace, window).acc.held(cell))


def test_held_share_over_the_scored_ticks() -> None:
    """spread == error in every baseline row: one held last good value on 94 % of the ticks
    (tau1 on its bound) is the median over time. The share is measured on the scored ticks."""
    trace = _trace(np.linspace(1.0, 0.0, 10)[:, None])
    trace.quality[2:, 0] = Quality.OUT_OF_BOUNDS  # 8 of 10 held
    tau1 = 1 << WATCHED.index("tau1_s")
    trace["on_bound"][2:9, 0] = tau1
    trace["on_bound"][9, 0] = tau1 | (1 << WATCHED.index("R2_ohm"))
    h = held_share(trace, EvalWindow(), 0)
    assert (h.held, h.bound_param, h.bound) == (0.8, "tau1_s", 0.8) and h.flagged
    top = held_share(trace, EvalWindow(soc_lo=0.75), 0)  # SOC 1.0, 0.89, 0.78: one held
    assert top.held == pytest.approx(1 / 3) and not top.flagged
    assert held_share(_trace(np.ones((4, 1))), EvalWindow(), 0) == HeldShare(0.0)


def test_consistency_table_flags_held_rows() -> None:
    level = {p: 1.0 for p in CONSISTENCY_PARAMS}
    held = {"a": HeldShare(0.94, "tau1_s", 0.937), "b": HeldShare(0.1)}
    c = consistency("g", "non-hy-affrls", {"a": level, "b": level}, None, held)
    md = consistency_markdown([c])
    assert "| error / % | spread / % | held / % | on a bound |" in md
    assert "| 94 **!** | tau1 94 % |" in md and "| 10 | - |" in md
    assert "**!** held on 50 % or more of the scored ticks" in md
    lines = consistency_csv([c]).splitlines()
    assert lines[0].endswith(",held_pct,most_on_bound,most_on_bound_pct")
    assert lines[1].endswith(",94.0,tau1_s,93.7") and lines[2].endswith(",10.0,,0.0")
    assert "**!**" not in consistency_markdown([consistency("g", "x", {"a": level, "b": level})])


# ----------------------------------------------------------------------------- cell fit (S2)
def test_compare_warns_when_a_record_does_not_fit_its_cell(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """An LFP record run with an NMC config (a mixture of cells) ran without a word (61.7 %
    consistency error, 129 mV); the record checks now say it does not fit, in compare and
    identify alike; the LFP config's own run does not."""
    from test_pseudo_ocv import LFP, Q_AH, lfp_record

    from bmsid.offline.csvio import TesterData, write_tester_csv

    t, i, v = lfp_record()
    src = tmp_path / "lfp_dst_25C.csv"
    write_tester_csv(TesterData(t, i, v[:, None], ["voltage_V"]), src)
    nmc, lfp = tmp_path / "nmc.toml", tmp_path / "lfp.toml"
    save_cell_config(paper_cell().model_copy(update={"capacity_Ah": Q_AH}), nmc)
    save_cell_config(LFP.model_copy(update={"capacity_Ah": Q_AH}), lfp)
    assert main(_one_variant(src, nmc, tmp_path / "a")) == 0
    assert main(["identify", str(src), "--cell-config", str(nmc), "--out", str(tmp_path / "i"),
                 "--algorithm", "non-hy-affrls"]) == 0  # fmt: skip
    out = capsys.readouterr().out
    line = "WARNING: the record does not fit the cell config 'paper-70Ah-NMC' (NMC): a full-to"
    assert f"{src}: {line}" in out and out.count(line) == 2
    assert "LFP-like) moves 1.98 Ah; an NMC OCV cannot follow it: give this cell's config" in out
    assert main(_one_variant(src, lfp, tmp_path / "b")) == 0
    assert "does not fit" not in capsys.readouterr().out


def test_group_names_say_config_and_data_temperature() -> None:
    """``dfn-nmc-lgm50-25C_15C`` read as a contradiction; the 25 C data of a 25C-named config
    were ``dfn-nmc-lgm50-25C`` alone."""
    from bmsid.cli.compare import _file_stem, _group_name

    cell = paper_cell().model_copy(update={"name": "dfn-nmc-lgm50-25C"})
    names = [_group_name(label_dataset(f"dfn_nmc_dst_{t}C.csv"), cell) for t in (15, 25)]
    assert names == ["config dfn-nmc-lgm50-25C, data 15 C", "config dfn-nmc-lgm50-25C, data 25 C"]
    assert _group_name(label_dataset("run.csv"), cell) == "config dfn-nmc-lgm50-25C"
    assert _file_stem(names[0]) == "config_dfn-nmc-lgm50-25C_data_15_C"
