"""``bmsid identify`` over many inputs: the local process pool and a real Dask cluster (a
``dask scheduler`` and two ``dask worker`` processes on loopback, started here), summary.csv,
failed inputs reported in one line while the rest finish, and the same numbers everywhere."""

from __future__ import annotations

import csv
import json
import os
import socket
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

import bmsid
from bmsid.cli.main import main
from bmsid.config.cell import paper_cell, save_cell_config
from bmsid.config.engine import ocv_model
from bmsid.model.simulator import simulate
from bmsid.offline import fleet
from bmsid.offline.csvio import TesterData, write_tester_csv
from bmsid.offline.identify import IdentifySpec, identify_file
from bmsid.offline.scoring import EvalWindow
from bmsid.profiles import dst_current
from bmsid.synthetic import TRUTH, paper_dst_case

N_SAMPLES = 400
NUMERIC = ("t_s", *fleet.SUMMARY_FIELDS, "quality", "rmse_mV", "R0_median_ohm", "input_r0_rank",
           "fleet_r0_rank")  # fmt: skip


@pytest.fixture(scope="module")
def inputs(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """Two 2-cell DST records (the second cell of ``b`` 30 % weaker), one in a subdirectory,
    a CSV without a voltage column, and the cell config."""
    d = tmp_path_factory.mktemp("fleet_in")
    (d / "site2").mkdir()
    paths = {"a": d / "pack_a.csv", "b": d / "site2" / "pack_b.csv"}
    for k, path in enumerate(paths.values()):
        run = paper_dst_case(N_SAMPLES, seed=k + 1, r0_spread=np.array([1.0, 1.0 + 0.3 * k]))
        data = TesterData(run.t_s, run.current_A, run.voltages_V, ["v_cell_01", "v_cell_02"])
        write_tester_csv(data, path)
    broken = d / "broken.csv"
    broken.write_text("t_s,current_A,volts\n0,1,3.7\n1,1,3.7\n", encoding="utf-8")
    paths["broken"] = broken
    save_cell_config(run.cell, d / "cell.toml")
    paths["cell"] = d / "cell.toml"
    paths["dir"] = d
    return paths


def _args(inputs: dict[str, Path], out: Path, *extra: str) -> list[str]:
    files = [str(inputs[k]) for k in ("a", "b", "broken")]
    return ["identify", *files, "--out", str(out), "--cell-config", str(inputs["cell"]), *extra]


def read_summary(out: Path) -> list[dict[str, str]]:
    with (out / "summary.csv").open(encoding="utf-8") as fh:
        return list(csv.DictReader(fh))


def numbers(rows: list[dict[str, str]]) -> dict[tuple[str, str], np.ndarray]:
    return {
        (r["input"], r["cell"]): np.array([float(r[c]) if r[c] else np.nan for c in NUMERIC])
        for r in rows
        if r["status"] == "ok"
    }


@pytest.fixture(scope="module")
def pool_run(
    inputs: dict[str, Path], tmp_path_factory: pytest.TempPathFactory
) -> tuple[Path, int, str, str]:
    """The three inputs on a pool of 2 processes: (out, exit code, stdout, stderr)."""
    out = tmp_path_factory.mktemp("fleet_out2")
    proc = subprocess.run(
        [sys.executable, "-m", "bmsid.cli.main", *_args(inputs, out, "--workers", "2")],
        capture_output=True, text=True, timeout=300, env=_env(), check=False,
    )  # fmt: skip
    return out, proc.returncode, proc.stdout, proc.stderr


def _env() -> dict[str, str]:
    """This bmsid (and this test module, for the failing tasks) first on every child's path."""
    here = [str(Path(bmsid.__file__).parents[1]), str(Path(__file__).parent)]
    old = os.environ.get("PYTHONPATH")
    return {**os.environ, "PYTHONPATH": os.pathsep.join([*here, *([old] if old else [])])}


def test_pool_reports_the_broken_input_and_finishes_the_rest(
    pool_run: tuple[Path, int, str, str], inputs: dict[str, Path]
) -> None:
    out, code, stdout, stderr = pool_run
    assert code == 1, stderr
    errors = [line for line in stderr.splitlines() if line.strip()]
    assert len(errors) == 1, stderr  # one line for the broken input, no traceback
    assert errors[0].startswith(f"bmsid identify: error: {inputs['broken']}: ")
    assert "voltage" in errors[0]
    assert "2 of 3 input(s) identified, 1 failed" in stdout
    rows = read_summary(out)
    assert [r["input"] for r in rows] == [str(inputs[k]) for k in ("a", "a", "b", "b", "broken")]
    assert rows[-1]["status"] == "failed" and rows[-1]["error"] in errors[0]
    assert not (out / rows[-1]["out_dir"]).exists()
    for r in rows[:-1]:
        sub = out / r["out_dir"]
        with (sub / "params.csv").open(encoding="utf-8") as fh:
            last = [p for p in csv.DictReader(fh) if p["cell"] == r["cell"]][-1]
        for name in ("t_s", *fleet.SUMMARY_FIELDS):  # the latest values the worker wrote
            assert float(r[name]) == pytest.approx(float(last[name]), rel=1e-5, abs=1e-9), name
        assert r["quality"] == last["quality"]
        metrics = json.loads((sub / "metrics.json").read_text(encoding="utf-8"))
        assert float(r["rmse_mV"]) == pytest.approx(1e3 * metrics["cells"][r["cell"]]["rmse_V"])
        assert metrics["input"] == str(inputs["a" if "pack_a" in r["input"] else "b"].resolve())


def test_summary_ranks_the_weakest_cells(pool_run: tuple[Path, int, str, str]) -> None:
    rows = [r for r in read_summary(pool_run[0]) if r["status"] == "ok"]
    r0 = {(r["input"], r["cell"]): float(r["R0_median_ohm"]) for r in rows}
    by_fleet = sorted(r0, key=lambda k: -r0[k])
    assert [int(r["fleet_r0_rank"]) for r in rows] == [by_fleet.index(k) + 1 for k in r0]
    for name in {r["input"] for r in rows}:
        mine = sorted(
            (r for r in rows if r["input"] == name), key=lambda r: -r0[r["input"], r["cell"]]
        )
        assert [r["input_r0_rank"] for r in mine] == ["1", "2"]
    weakest = max(r0, key=lambda k: r0[k])
    assert weakest[1] == "v_cell_02" and "pack_b" in weakest[0]  # its R0 is 30 % higher
    assert f"{1e3 * r0[weakest]:.3f} mOhm  v_cell_02" in pool_run[2]


def test_one_worker_gives_the_same_numbers(
    pool_run: tuple[Path, int, str, str], inputs: dict[str, Path], tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
) -> None:  # fmt: skip
    assert main(_args(inputs, tmp_path, "--workers", "1")) == 1
    one, two = numbers(read_summary(tmp_path)), numbers(read_summary(pool_run[0]))
    assert one.keys() == two.keys() and len(one) == 4
    for key in one:
        np.testing.assert_allclose(one[key], two[key], rtol=1e-9, err_msg=str(key))
    assert capsys.readouterr().err.count("\n") == 1


def test_each_input_gets_the_single_runs_record_checks(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A fleet ran no record checks: time in minutes and a flipped current sign came out
    ``ok`` (the flipped record ranked as the healthiest cell). Now such an input fails with
    the single run's message, the rest finish, and a warning's code reaches summary.csv."""
    # 2 h of DST (its rests read SOC) on a 2 Ah cell: the charge it moves tells the capacity
    t = np.arange(7200, dtype=np.float64)
    i = np.where(t < 60, 0.0, dst_current(t - 60, 4.0))
    sim = simulate(
        t, i, ocv_model(paper_cell()), capacity_Ah=2.0, gamma=30.0, soc0=0.9,
        R0_ohm=0.04, R1_ohm=0.03, tau1_s=30.0, R2_ohm=0.03, tau2_s=600.0,
    )  # fmt: skip
    v = (sim.v_V[0] + np.random.default_rng(3).normal(0.0, 1e-3, t.size))[:, None]
    names = ["voltage_V"]
    records = {
        "good.csv": TesterData(t, i, v, names),
        "minutes.csv": TesterData(t / 60.0, i, v, names),
        "flipped.csv": TesterData(t, -i, v, names),
    }
    for name, data in records.items():
        write_tester_csv(data, tmp_path / name)
    out = tmp_path / "out"
    # 4000 Ah for a 2 Ah cell: the charge the record moves says far less (a warning)
    args = ["identify", *(str(tmp_path / n) for n in records), "--out", str(out),
            "--capacity-ah", "4000", "--workers", "1"]  # fmt: skip
    assert main(args) == 1
    rows = {Path(r["input"]).name: r for r in read_summary(out)}
    assert rows["minutes.csv"]["status"] == "failed"
    assert rows["minutes.csv"]["error"].startswith("t_s looks like minutes")
    assert rows["flipped.csv"]["status"] == "failed"
    assert "current sign looks flipped" in rows["flipped.csv"]["error"]
    assert rows["good.csv"]["status"] == "ok"
    assert "capacity_mismatch" in rows["good.csv"]["warnings"].split(";")
    err = capsys.readouterr().err
    assert err.count("bmsid identify: error: ") == 2


# ----------------------------------------------------------------------------- a real cluster
def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def worker_bmsid() -> str:
    """Run on each worker: which bmsid it imports."""
    return bmsid.__file__


@pytest.fixture(scope="module")
def dask_scheduler(tmp_path_factory: pytest.TempPathFactory) -> Iterator[str]:
    """``dask scheduler`` and two ``dask worker --nthreads 1`` processes (the venv's CLI) on
    loopback: the scheduler's address. A missing dask fails the test (pip install -e '.[dev]')."""
    from distributed import Client

    cli = Path(sys.executable).with_name("dask")
    assert cli.exists(), f"{cli} not found: dask and distributed come with bmsid[dev]"
    logs = tmp_path_factory.mktemp("dask")
    address = f"tcp://127.0.0.1:{_free_port()}"
    commands = [
        [str(cli), "scheduler", "--host", "127.0.0.1", "--port", address.rsplit(":", 1)[1],
         "--no-dashboard"],
        *([str(cli), "worker", address, "--nthreads", "1", "--no-dashboard", "--host", "127.0.0.1",
           "--local-directory", str(logs / f"w{k}")] for k in range(2)),
    ]  # fmt: skip
    procs: list[subprocess.Popen[bytes]] = []
    try:
        for k, cmd in enumerate(commands):
            log = (logs / f"{k}.log").open("wb")
            procs.append(subprocess.Popen(cmd, env=_env(), stdout=log, stderr=subprocess.STDOUT))
            if k == 0:
                _wait_for_port(address, procs[0], logs / "0.log")
        with Client(address, timeout="60s", set_as_default=False) as client:
            client.wait_for_workers(2, timeout=120)
            assert set(client.run(worker_bmsid).values()) == {bmsid.__file__}
        yield address
    finally:  # workers first: without their scheduler they would wait to reconnect
        for group in (procs[1:], procs[:1]):
            for p in group:
                p.terminate()
            for p in group:
                try:
                    p.wait(timeout=20)
                except subprocess.TimeoutExpired:
                    p.kill()
                    p.wait()


def _wait_for_port(address: str, proc: subprocess.Popen[bytes], log: Path) -> None:
    host, port = address.removeprefix("tcp://").rsplit(":", 1)
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline:
        assert proc.poll() is None, log.read_text(errors="replace")
        try:
            socket.create_connection((host, int(port)), timeout=1).close()
            return
        except OSError:
            time.sleep(0.2)
    raise AssertionError(f"dask scheduler not listening: {log.read_text(errors='replace')}")


def test_dask_cluster_gives_the_pool_numbers(
    dask_scheduler: str, pool_run: tuple[Path, int, str, str], inputs: dict[str, Path],
    tmp_path: Path, capsys: pytest.CaptureFixture[str],
) -> None:  # fmt: skip
    code = main(_args(inputs, tmp_path, "--scheduler", dask_scheduler))
    stdout, stderr = capsys.readouterr()
    assert code == 1
    assert [line for line in stderr.splitlines() if line.strip()] == [
        line for line in pool_run[3].splitlines() if line.strip()
    ]
    assert "the Dask cluster at" in stdout
    dask_rows, pool_rows = read_summary(tmp_path), read_summary(pool_run[0])
    assert [(r["input"], r["out_dir"], r["status"]) for r in dask_rows] == [
        (r["input"], r["out_dir"], r["status"]) for r in pool_rows
    ]
    a, b = numbers(dask_rows), numbers(pool_rows)
    assert a.keys() == b.keys() and len(a) == 4
    for key in a:
        np.testing.assert_allclose(a[key], b[key], rtol=1e-9, err_msg=str(key))


@pytest.mark.parametrize(
    "window", [EvalWindow(), EvalWindow(skip_fraction=0.1, soc_lo=0.955, soc_hi=0.975)]
)
def test_a_streamed_task_summarises_as_the_kept_trace(
    inputs: dict[str, Path], tmp_path: Path, window: EvalWindow
) -> None:
    # several blocks: the streamed RMSE is summed block by block, the kept trace's at once
    spec = IdentifySpec(cell=paper_dst_case(10).cell, window=window, block_size=97)
    item = fleet.fleet_inputs([str(inputs["b"])])[0]
    streamed = fleet.identify_task(fleet.FleetTask(item, str(tmp_path / "streamed"), spec))
    kept = identify_file(item.path, spec, tmp_path / "kept")
    assert kept.trace is not None and kept.trace.n_ticks == N_SAMPLES
    ref = fleet.cell_summaries(kept, spec)
    assert streamed.ok and len(streamed.cells) == len(ref) == 2
    for got, want in zip(streamed.cells, ref, strict=True):
        assert (got.cell, got.t_s, got.quality) == (want.cell, want.t_s, want.quality)
        np.testing.assert_allclose(got.params, want.params, rtol=1e-9)
        np.testing.assert_allclose(got.rmse_mV, want.rmse_mV, rtol=1e-9)
        assert np.isfinite(got.rmse_mV) and got.rmse_mV > 0


# ----------------------------------------------------------------------------- failing tasks
def explode_on_b(task: fleet.FleetTask) -> fleet.InputSummary:
    """A task that raises past identify_task's handler for pack_b (a worker-side bug)."""
    if "pack_b" in task.input.path:
        raise RuntimeError("boom in the worker")
    return fleet.InputSummary(task.input, None, 1, ())


def die_on_b(task: fleet.FleetTask) -> fleet.InputSummary:
    if "pack_b" in task.input.path:
        os._exit(3)  # the worker process dies
    return fleet.InputSummary(task.input, None, 1, ())


def _tasks(inputs: dict[str, Path], out: Path) -> list[fleet.FleetTask]:
    spec = IdentifySpec(cell=paper_dst_case(10).cell)
    items = fleet.fleet_inputs([str(inputs["a"]), str(inputs["b"])])
    return [fleet.FleetTask(i, str(out / i.name), spec) for i in items]


def test_an_exception_in_a_worker_fails_that_input_only(
    dask_scheduler: str, inputs: dict[str, Path], tmp_path: Path
) -> None:
    tasks = _tasks(inputs, tmp_path)
    for results in (
        fleet.run_local(tasks, 2, explode_on_b),
        fleet.run_dask(tasks, dask_scheduler, explode_on_b),
    ):
        got = {s.input.given: s for s in results}
        assert got[str(inputs["a"])].ok
        assert got[str(inputs["b"])].error == "internal error: RuntimeError: boom in the worker"


def test_a_dead_worker_process_is_reported(inputs: dict[str, Path], tmp_path: Path) -> None:
    got = {s.input.given: s for s in fleet.run_local(_tasks(inputs, tmp_path), 1, die_on_b)}
    assert len(got) == 2
    assert (got[str(inputs["b"])].error or "").startswith("a worker process died")


# ----------------------------------------------------------------------------- inputs and options
def test_directories_globs_and_names(inputs: dict[str, Path]) -> None:
    d = inputs["dir"]
    found = fleet.expand_inputs([str(d), str(d / "*.csv"), str(inputs["b"])])
    assert found == [d / "broken.csv", d / "pack_a.csv", d / "site2" / "pack_b.csv"]
    assert fleet.expand_inputs([str(d / "**" / "pack_*.csv")]) == [
        d / "pack_a.csv", d / "site2" / "pack_b.csv",
    ]  # fmt: skip
    assert fleet.is_fleet([str(d)]) and fleet.is_fleet([str(d / "*.csv")])
    assert not fleet.is_fleet([str(inputs["a"])])
    name = fleet.out_name(inputs["b"])
    assert name.startswith("site2__pack_b.csv-") and name == fleet.out_name(inputs["b"])
    (d / "other").mkdir(exist_ok=True)
    twin = d / "other" / "site2" / "pack_b.csv"
    twin.parent.mkdir(exist_ok=True)
    assert fleet.out_name(twin).startswith("site2__pack_b.csv-") and fleet.out_name(twin) != name


def test_bad_arguments_are_one_line(
    inputs: dict[str, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
) -> None:  # fmt: skip
    base = ["identify", str(inputs["a"]), "--out", str(tmp_path)]
    cases = [
        (
            ["identify", str(tmp_path / "nope*.csv"), str(inputs["a"]), "--out", str(tmp_path)],
            "nope*.csv: the pattern matches no file",
        ),
        (
            [
                "identify",
                str(inputs["a"]),
                str(inputs["b"]),
                "--out",
                str(tmp_path),
                "--workers",
                "0",
            ],
            "--workers must be at least 1",
        ),
        ([*base, "--scheduler", "tcp://127.0.0.1:1", "--workers", "2"], "--workers sets"),
    ]
    monkeypatch.setitem(sys.modules, "distributed", None)  # as if dask were not installed
    cases.append(([*base, "--scheduler", "tcp://127.0.0.1:1"], "needs dask.distributed"))
    for argv, text in cases:
        assert main(argv) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and text in err[0], err


def test_a_worker_freezes_its_start_up_heap_once() -> None:
    # Each input's full garbage collection walked the start-up heap (200,000+ objects: 0.15-0.2
    # s of a one-hour input); a worker freezes it before its first input, and only then.
    code = """
import gc
from bmsid.estimate import jit
from bmsid.offline import fleet
fleet.settle_worker()
frozen = gc.get_freeze_count()
assert jit.MODE != "unset" and frozen > 50_000, (jit.MODE, frozen)
junk = [[i] for i in range(10_000)]
fleet.settle_worker()
assert gc.get_freeze_count() == frozen, (gc.get_freeze_count(), frozen)
print("ok")
"""
    out = subprocess.run(
        [sys.executable, "-c", code], check=False, capture_output=True, text=True, timeout=300,
        env={**os.environ, "PYTHONPATH": os.pathsep.join(sys.path)},
    )  # fmt: skip
    assert out.returncode == 0 and out.stdout.strip() == "ok", out.stderr[-2000:]


def test_cells_are_ranked_on_their_median_r0(tmp_path: Path) -> None:
    """Copies of one cell's voltage shifted by +-2 mV, and one with 10 % of R0 more: the weak
    one ranks first by its median R0 over the record, the copies agree (a sweep ranked three
    copies of one real column on their last-tick R0: 72.8 / 85.2 / 82.4 mOhm)."""
    run = paper_dst_case(3000, seed=3)
    v, i = run.voltages_V[:, 0], run.current_A
    r0 = TRUTH["R0_ohm"]
    cols = np.column_stack([v + 0.002, v - 0.002, v - 0.1 * r0 * i, v + 0.001])
    names = ["v_cell_01", "v_cell_02", "v_cell_03", "v_cell_04"]
    (tmp_path / "in").mkdir()
    write_tester_csv(TesterData(run.t_s, i, cols, names), tmp_path / "in" / "pack.csv")
    save_cell_config(run.cell, tmp_path / "cell.toml")
    out = tmp_path / "out"
    args = ["identify", str(tmp_path / "in"), "--out", str(out), "--workers", "1"]
    assert main([*args, "--cell-config", str(tmp_path / "cell.toml")]) == 0
    rows = {r["cell"]: r for r in read_summary(out)}
    median = {c: float(r["R0_median_ohm"]) for c, r in rows.items()}
    assert rows["v_cell_03"]["input_r0_rank"] == "1" and rows["v_cell_03"]["fleet_r0_rank"] == "1"
    assert median["v_cell_03"] == pytest.approx(1.1 * r0, rel=0.02)
    copies = [median[c] for c in ("v_cell_01", "v_cell_02", "v_cell_04")]
    assert max(copies) / min(copies) < 1.005
    assert median["v_cell_01"] == pytest.approx(r0, rel=0.02)
