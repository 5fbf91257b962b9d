"""Offline identification as a library: one call per input, blocks in and out, results that do
not depend on the block size, what the CLI writes, and no import of the CLI from elsewhere."""

from __future__ import annotations

import ast
import json
import pickle
from pathlib import Path

import numpy as np
import pytest
from test_identify_cli import synthetic_columns, write_csv

from bmsid.cli.main import main
from bmsid.config.cell import paper_cell
from bmsid.estimate.fields import FIELD_NAMES
from bmsid.estimate.types import EstimateBlock
from bmsid.offline.csvio import read_tester_csv
from bmsid.offline.identify import (
    IdentifySpec,
    identify_file,
    identify_source,
    run_blocks,
    run_tester,
)
from bmsid.offline.inputs import LoadedInput, open_input
from bmsid.offline.outputs import OutputSpec
from bmsid.offline.scoring import EvalWindow, metrics_document
from bmsid.samples import SampleBlock

REPO = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def short_csv(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return write_csv(tmp_path_factory.mktemp("lib") / "syn_dst_25C.csv", synthetic_columns(700))


def test_spec_is_a_picklable_value() -> None:
    spec = IdentifySpec(
        cell=paper_cell(),
        variant="hy-affrls",
        soc0=0.9,
        window=EvalWindow(0.0, 0.2, 0.9),
        output=OutputSpec(plots="first", metadata={"input": "x.csv"}),
    )
    assert pickle.loads(pickle.dumps(spec)) == spec


def test_results_do_not_depend_on_the_block_size(short_csv: Path) -> None:
    spec = IdentifySpec(cell=paper_cell(), variant="hy-affrls-lpso")
    whole = identify_file(short_csv, spec)
    odd = identify_file(short_csv, IdentifySpec(cell=paper_cell(), block_size=37))
    assert whole.n_samples == odd.n_samples == 700
    assert whole.trace.n_ticks == odd.trace.n_ticks > 0
    for name in FIELD_NAMES:
        np.testing.assert_array_equal(whole.trace[name], odd.trace[name], err_msg=name)
    np.testing.assert_array_equal(whole.trace.quality, odd.trace.quality)
    # the convenience over in-memory columns is the same run
    mem = run_tester(read_tester_csv(short_csv), paper_cell(), "hy-affrls-lpso")
    np.testing.assert_array_equal(mem.trace["v_model_V"], whole.trace["v_model_V"])


def test_estimates_reach_the_sink_block_by_block(short_csv: Path) -> None:
    src = open_input(short_csv)
    got: list[EstimateBlock] = []
    fed: list[int] = []
    res = run_blocks(
        src.blocks(200), src.n_cells, paper_cell(), "non-hy-affrls", progress=fed.append,
        cell_names=src.cell_names, sink=got.append,
    )  # fmt: skip
    assert fed == [200, 200, 200, 100]
    assert len(got) == 4 and all(b.n_ticks for b in got)
    joined = EstimateBlock.concat(got, 1)
    np.testing.assert_array_equal(joined["R0_ohm"], res.trace["R0_ohm"])
    assert res.cell_names == ["voltage_V"]


def test_identify_file_writes_what_the_cli_writes(short_csv: Path, tmp_path: Path) -> None:
    cli, lib = tmp_path / "cli", tmp_path / "lib"
    assert main(["identify", str(short_csv), "--out", str(cli), "--algorithm", "hy-affrls"]) == 0
    res = identify_file(short_csv, IdentifySpec(cell=paper_cell(), variant="hy-affrls"), lib)
    assert (cli / "params.csv").read_bytes() == (lib / "params.csv").read_bytes()
    a = json.loads((cli / "metrics.json").read_text(encoding="utf-8"))
    b = json.loads((lib / "metrics.json").read_text(encoding="utf-8"))
    assert b["input"] == str(short_csv)
    for doc in (a, b):
        doc.pop("runtime_s")
        for c in doc["cells"].values():
            c.pop("runtime_s")
    # The CLI adds its own plausibility findings (the no-config warning) to the input checks.
    skip = ("cell_config", "tuning_overrides", "input_checks")
    assert {k: v for k, v in a.items() if k not in skip} == {
        k: v for k, v in b.items() if k != "input_checks"
    }
    assert a["input_checks"]["merged_repeats"] == b["input_checks"]["merged_repeats"] == 0
    assert b["rmse_V"] == metrics_document(res, EvalWindow())["rmse_V"]
    assert {p.name for p in lib.glob("*.png")} == {"parameters.png", "voltage.png"}


def test_a_run_without_a_tick_still_reports(tmp_path: Path) -> None:
    empty = SampleBlock.from_arrays(np.zeros(0), np.zeros(0), np.zeros((0, 2)))
    src = LoadedInput(source="empty.csv", samples=empty, cell_names=["a", "b"])
    out = tmp_path / "out"
    res = identify_source(src, IdentifySpec(cell=paper_cell()), out)
    assert res.trace.n_ticks == 0 and res.trace.n_cells == 2
    doc = json.loads((out / "metrics.json").read_text(encoding="utf-8"))
    assert doc["n_ticks"] == 0 and doc["n_input_samples"] == 0
    assert set(doc["cells"]) == {"a", "b"}
    assert len((out / "params.csv").read_text(encoding="utf-8").splitlines()) == 1  # header
    assert not list(out.glob("*.png"))


def test_no_module_outside_the_cli_imports_it() -> None:
    """Library, benches and scripts call ``bmsid.offline``; only ``bmsid.cli`` imports itself."""
    cli = REPO / "service" / "bmsid" / "cli"
    files = [
        p
        for root in (REPO / "service" / "bmsid", REPO / "bench", REPO / "scripts")
        for p in root.rglob("*.py")
        if cli not in p.parents
    ]
    assert len(files) > 20
    offenders = []
    for path in files:
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            names = (
                [a.name for a in node.names]
                if isinstance(node, ast.Import)
                else [node.module or ""]
                if isinstance(node, ast.ImportFrom)
                else []
            )
            if any(n == "bmsid.cli" or n.startswith("bmsid.cli.") for n in names):
                offenders.append(str(path.relative_to(REPO)))
    assert not offenders


def test_result_carries_the_start_values_measured_on_the_record(short_csv: Path) -> None:
    """A config without [initial]/[bounds]: the run measures them and says which it used."""
    cell = paper_cell().model_copy(update={"initial": None, "bounds": None})
    res = identify_file(short_csv, IdentifySpec(cell=cell, variant="hy-affrls"))
    assert res.start_values is not None and res.start_values.R0_ohm > 0
    assert identify_file(short_csv, IdentifySpec(cell=paper_cell())).start_values is None
