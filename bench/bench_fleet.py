"""Many logs on 1 and 2 workers, local process pool and Dask, side by side in one run.

Input: ``--inputs`` synthetic single-cell DST records of ``--hours`` each (the paper's 70 Ah
cell, 1 s, 1 mV noise, R0 a few % apart), written to a temporary directory with the project's
CSV writer. Each configuration identifies all of them with the default variant into a fresh
output root through :mod:`bmsid.offline.fleet` (``run_local`` / ``run_dask``: what ``bmsid
identify`` runs, without its interpreter start and imports, which are the same for every
configuration). The process pool's time includes starting its processes; a Dask cluster is
started beforehand (``dask scheduler`` and N ``dask worker --nthreads 1`` on loopback, the
venv's CLI), as an existing cluster would be. Configurations alternate within each round.
Prints the machine's load and the busiest other processes, since this 2-core machine is shared.
The kernel's autogroup scheduler shares the CPUs between sessions: by default every worker is in
this benchmark's session and they share its part; ``--own-sessions`` gives each worker a session
of its own, as separately started jobs would have.

    PYTHONPATH=service python bench/bench_fleet.py [--inputs 16 --hours 1.5 --rounds 1]
        [--own-sessions]
"""

from __future__ import annotations

import argparse
import os
import shutil
import socket
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator, Sequence
from contextlib import contextmanager, suppress
from pathlib import Path

import numpy as np

import bmsid
from bmsid.config.cell import save_cell_config
from bmsid.config.engine import ocv_model
from bmsid.offline import fleet
from bmsid.offline.csvio import TesterData, write_tester_csv
from bmsid.offline.identify import IdentifySpec
from bmsid.offline.inputs import load_config
from bmsid.synthetic import paper_dst_case
from bmsid.threads import one_blas_thread

one_blas_thread()  # the engine's matrices are small (bmsid/threads.py)

MODES = ("pool", "dask")
WORKERS = (1, 2)


def make_inputs(d: Path, n_inputs: int, hours: float) -> tuple[list[Path], Path]:
    """``n_inputs`` single-cell records and the cell config that made them."""
    n = int(hours * 3600)
    paths = []
    for k in range(n_inputs):
        run = paper_dst_case(n, seed=k + 1, r0_spread=np.array([1.0 + 0.02 * k]))
        path = d / f"pack_{k:02d}.csv"
        write_tester_csv(TesterData(run.t_s, run.current_A, run.voltages_V, ["voltage_V"]), path)
        paths.append(path)
    cfg = d / "cell.toml"
    save_cell_config(run.cell, cfg)
    ocv_model(run.cell)  # the config is complete (fails here, not in a worker)
    return paths, cfg


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@contextmanager
def dask_cluster(n_workers: int, scratch: Path, own_sessions: bool) -> Iterator[str]:
    """A scheduler and ``n_workers`` single-thread workers on loopback (with ``own_sessions``
    each worker in a session of its own): its address."""
    cli = str(Path(sys.executable).with_name("dask"))
    port = _free_port()
    address = f"tcp://127.0.0.1:{port}"
    service = str(Path(bmsid.__file__).parents[1])
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([service, os.environ.get("PYTHONPATH", "")])}
    log = (scratch / f"dask-{n_workers}.log").open("wb")
    cmds = [[cli, "scheduler", "--host", "127.0.0.1", "--port", str(port), "--no-dashboard"]]
    cmds += [
        [cli, "worker", address, "--nthreads", "1", "--no-dashboard", "--host", "127.0.0.1",
         "--local-directory", str(scratch / f"w{n_workers}-{k}")]
        for k in range(n_workers)
    ]  # fmt: skip
    procs = [
        subprocess.Popen(
            c, env=env, stdout=log, stderr=subprocess.STDOUT, start_new_session=own_sessions
        )
        for c in cmds
    ]
    try:
        from distributed import Client  # noqa: PLC0415 - only this benchmark's Dask part

        with Client(address, timeout="60s", set_as_default=False) as client:  # type: ignore[no-untyped-call]
            client.wait_for_workers(n_workers, timeout=120)
        yield address
    finally:
        for group in (procs[1:], procs[:1]):
            for p in group:
                p.terminate()
            for p in group:
                try:
                    p.wait(timeout=30)
                except subprocess.TimeoutExpired:
                    p.kill()
                    p.wait()
        log.close()


def own_session_task(task: fleet.FleetTask) -> fleet.InputSummary:
    """``identify_task`` in a session of its own (``--own-sessions``): the kernel's autogroup
    scheduler then shares the CPUs between the pool's workers as between separate jobs."""
    with suppress(OSError):  # already a session leader: from this worker's first task on
        os.setsid()
    return fleet.identify_task(task)


def run_once(
    mode: str,
    workers: int,
    tasks: Sequence[fleet.FleetTask],
    scheduler: str | None,
    own_sessions: bool,
) -> tuple[float, list[fleet.InputSummary]]:
    t0 = time.perf_counter()
    if mode == "pool":
        fn = own_session_task if own_sessions else fleet.identify_task
        got = list(fleet.run_local(tasks, workers, fn))
    else:
        assert scheduler is not None
        got = list(fleet.run_dask(tasks, scheduler))
    return time.perf_counter() - t0, got


def busiest_others(n: int = 8) -> list[str]:
    """The processes using the most CPU over one second now (``top``), as text: this
    benchmark's own processes and the other jobs on the machine."""
    out = subprocess.run(
        ["top", "-b", "-n", "2", "-d", "1", "-o", "%CPU", "-c", "-w", "220"],
        capture_output=True, text=True, check=False,
    ).stdout.splitlines()  # fmt: skip
    headers = [k for k, line in enumerate(out) if line.lstrip().startswith("PID")]
    if not headers:
        return ["(top not available)"]
    rows = [line for line in out[headers[-1] + 1 :] if line.strip()]
    return [" ".join(r.split()[8:9] + r.split()[11:])[:150] for r in rows[:n]]


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--inputs", type=int, default=16)
    ap.add_argument("--hours", type=float, default=1.5, help="length of each record")
    ap.add_argument("--rounds", type=int, default=1, help="alternating rounds of all runs")
    ap.add_argument(
        "--own-sessions", action="store_true",
        help="each worker process in a session of its own (the kernel's autogroup scheduler "
        "shares the CPUs between sessions: without it, all workers share this session's part)",
    )  # fmt: skip
    args = ap.parse_args(argv)
    with tempfile.TemporaryDirectory(prefix="bmsid-bench-fleet-") as tmp_name:
        tmp = Path(tmp_name)
        (tmp / "in").mkdir()
        paths, cfg = make_inputs(tmp / "in", args.inputs, args.hours)
        spec = IdentifySpec(cell=load_config(cfg))
        items = fleet.fleet_inputs([str(p) for p in paths])
        samples = args.inputs * int(args.hours * 3600)
        print(f"{args.inputs} inputs x {args.hours:g} h (1 cell, 1 s) = {samples} samples, "
              f"variant {spec.variant}, {os.cpu_count()} CPUs; load average before: "
              f"{' '.join(f'{x:.2f}' for x in os.getloadavg())}; workers in "
              f"{'sessions of their own' if args.own_sessions else 'this session'}")  # fmt: skip
        print("busiest processes before:")
        for line in busiest_others():
            print(f"  {line}")
        times: dict[tuple[str, int], list[float]] = {}
        reference: dict[str, tuple[float, ...]] = {}
        worst_diff = 0.0
        for r in range(args.rounds):
            for mode in MODES:
                for workers in WORKERS:
                    out = tmp / f"out-{mode}-{workers}-{r}"
                    tasks = [fleet.FleetTask(i, str(out / i.name), spec) for i in items]
                    if mode == "dask":
                        with dask_cluster(workers, tmp, args.own_sessions) as address:
                            wall, got = run_once(mode, workers, tasks, address, args.own_sessions)
                    else:
                        wall, got = run_once(mode, workers, tasks, None, args.own_sessions)
                    failed = [s.error for s in got if not s.ok]
                    if failed:
                        print(f"{mode} x{workers}: {len(failed)} failed: {failed[0]}")
                        return 1
                    for s in got:
                        vals = s.cells[0].params
                        ref = reference.setdefault(s.input.path, vals)
                        worst_diff = max(
                            worst_diff,
                            float(np.nanmax(np.abs(np.subtract(vals, ref)) / np.abs(ref))),
                        )
                    times.setdefault((mode, workers), []).append(wall)
                    rate = f"{args.inputs / wall:.3f} inputs/s, {samples / wall:,.0f} samples/s"
                    load = os.getloadavg()[0]
                    cpu = sum(s.cpu_s for s in got)
                    busy = sum(s.wall_s for s in got) / (workers * wall)
                    print(
                        f"round {r + 1}: {mode:4s} {workers} worker(s): {wall:6.1f} s, {rate}; "
                        f"tasks' CPU {cpu:.1f} s = {cpu / wall:.2f} cores on average; workers "
                        f"busy {100 * busy:.0f} %; 1-min load average at the end {load:.1f}"
                    )
                    shutil.rmtree(out)
        print(f"load average after: {' '.join(f'{x:.2f}' for x in os.getloadavg())}")
        print("busiest processes after:")
        for line in busiest_others():
            print(f"  {line}")
        print(f"largest relative difference of a latest parameter between runs: {worst_diff:.1e}")
        for mode in MODES:
            one, two = min(times[mode, 1]), min(times[mode, 2])
            print(f"{mode}: 1 worker {one:.1f} s, 2 workers {two:.1f} s (best of "
                  f"{args.rounds}): throughput ratio {one / two:.2f}x")  # fmt: skip
    return 0


if __name__ == "__main__":
    sys.exit(main())
