"""Memory and wall time of ``bmsid identify`` on long records (issue 12): streamed input, streamed
metrics, decimated output.

Records (synthetic multi-day, ``bmsid.synthetic.multiday``: the paper's 70 Ah cell, 1 s samples,
written once into ``--data DIR`` and reused):

- ``n250k.csv``: 250,000 samples, one cell;
- ``n1m.csv``: 1,000,000 samples, one cell;
- ``c16_dDAYS.csv``: ``--pack-days`` days (default 3) of 16 cells (``v_cell_01..16``: the one
  cell's voltage, each cell offset by 0.5 mV steps and with its own 1 mV noise).

Each record is identified by the command a user types, ``python -m bmsid.cli.main identify
RECORD --out DIR`` (``hy-affrls-lpso``, defaults otherwise), in a child process timed by
``/usr/bin/time -v``: wall time and maximum resident set size side by side in one run, and the
resident set sampled every 2 s from ``/proc/PID/status`` (in ``--json``; the table shows it at
25, 50, 75 and 100 % of the run's wall time) to show whether it is flat.

``--baseline-tree DIR`` also runs the records of ``--baseline-only`` (default ``n250k``) with
another checkout's ``service/`` (e.g. ``git archive a7347e9 service | tar -x -C DIR``: the
whole-file ``identify`` before issue 12), one after the other in the same invocation.

    PYTHONPATH=service python bench/bench_streaming.py --data /tmp/bmsid-long [--pack-days 3]
        [--only n250k n1m c16] [--baseline-tree DIR [--baseline-only n250k]] [--json PATH]
"""

from __future__ import annotations

import argparse
import json
import os
import re
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

from bmsid.offline.csvio import TesterData, write_tester_csv
from bmsid.synthetic.multiday import DAY_S, MultidayOptions, generate
from bmsid.threads import one_blas_thread

one_blas_thread()  # the engine's matrices are small (bmsid/threads.py)

#: Cells of the pack record.
PACK_CELLS = 16
TIME_BIN = "/usr/bin/time"


def make_single(path: Path, n_samples: int) -> None:
    """A one-cell record of ``n_samples`` 1 s samples (whole days simulated, then cut)."""
    days = -(-n_samples // DAY_S)
    rec = generate(MultidayOptions(n_days=days, duration_s=n_samples))
    data = TesterData(
        t_s=rec.t_s, current_A=rec.current_A, cell_voltages_V=rec.voltage_V[:, None],
        cell_names=["voltage_V"],
    )  # fmt: skip
    write_tester_csv(data, path)


def make_pack(path: Path, n_days: int, n_cells: int = PACK_CELLS) -> None:
    """``n_days`` of ``n_cells`` cells: the one cell's voltage, cell k offset by k x 0.5 mV,
    each with its own 1 mV noise (seeded)."""
    rec = generate(MultidayOptions(n_days=n_days))
    rng = np.random.default_rng(12)
    v = rec.voltage_V[:, None] + 0.5e-3 * np.arange(n_cells)[None, :]
    v = v + rng.normal(0.0, 1e-3, v.shape)
    names = [f"v_cell_{c + 1:02d}" for c in range(n_cells)]
    write_tester_csv(TesterData(rec.t_s, rec.current_A, v, names), path)


def records(data: Path, pack_days: int) -> dict[str, Path]:
    """The benchmark records in ``data``, written when missing."""
    data.mkdir(parents=True, exist_ok=True)
    out = {
        "n250k": data / "n250k.csv",
        "n1m": data / "n1m.csv",
        "c16": data / f"c16_d{pack_days}.csv",
    }
    for key, path in out.items():
        if path.exists():
            continue
        print(f"writing {path} ...", flush=True)
        if key == "n250k":
            make_single(path, 250_000)
        elif key == "n1m":
            make_single(path, 1_000_000)
        else:
            make_pack(path, pack_days)
    return out


def _rss_sampler(pid_file: Path, samples: list[tuple[float, float]], stop: threading.Event) -> None:
    """Append (s since start, MB) of the identify process's VmRSS every 2 s."""
    t0 = time.monotonic()
    while not stop.wait(2.0):
        try:
            pid = int(pid_file.read_text())
            status = Path(f"/proc/{pid}/status").read_text()
        except (OSError, ValueError):
            continue
        m = re.search(r"VmRSS:\s+(\d+) kB", status)
        if m:
            samples.append((time.monotonic() - t0, int(m.group(1)) / 1024))


def run_identify(record: Path, out: Path, tree: Path | None = None) -> dict[str, object]:
    """``bmsid identify RECORD --out OUT`` under ``/usr/bin/time -v``: wall s, max RSS MB, the
    RSS trace, and the run's own figures from metrics.json; with ``tree``, that checkout's
    ``service/`` is imported instead of this one's."""
    pid_file = out.with_suffix(".pid")
    code = (
        "import os, sys; open(sys.argv[1], 'w').write(str(os.getpid())); "
        "from bmsid.cli.main import main; sys.exit(main(sys.argv[2:]))"
    )
    cmd = [TIME_BIN, "-v", sys.executable, "-c", code, str(pid_file), "identify", str(record),
           "--out", str(out)]  # fmt: skip
    samples: list[tuple[float, float]] = []
    stop = threading.Event()
    sampler = threading.Thread(target=_rss_sampler, args=(pid_file, samples, stop), daemon=True)
    sampler.start()
    t0 = time.perf_counter()
    env = dict(os.environ)
    if tree is not None:
        env["PYTHONPATH"] = str(tree / "service")
    proc = subprocess.run(cmd, capture_output=True, text=True, check=False, env=env)
    wall = time.perf_counter() - t0
    stop.set()
    sampler.join()
    if proc.returncode != 0:
        raise SystemExit(f"{record}: identify failed ({proc.returncode}):\n{proc.stderr[-2000:]}")
    m = re.search(r"Maximum resident set size \(kbytes\): (\d+)", proc.stderr)
    max_rss_MB = int(m.group(1)) / 1024 if m else float("nan")
    metrics = json.loads((out / "metrics.json").read_text())
    rss = [mb for _, mb in samples]
    quarters = [rss[min(len(rss) - 1, (k * len(rss)) // 4)] if rss else float("nan")
                for k in (1, 2, 3, 4)]  # fmt: skip
    return {
        "record": record.name + ("" if tree is None else f" ({tree.name})"),
        "wall_s": wall,
        "max_rss_MB": max_rss_MB,
        "rss_quarters_MB": quarters,
        "rss_trace": [[round(t, 1), round(mb, 1)] for t, mb in samples],
        "n_samples": metrics["n_input_samples"],
        "n_cells": len(metrics["cells"]),
        "loop_s": metrics["runtime_s"],
        "rmse_mV": 1e3 * metrics["overall"]["rmse_V"],
        "output": metrics.get("output"),
        "stdout_first_lines": proc.stdout.splitlines()[:3],
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, default=Path(tempfile.gettempdir()) / "bmsid-long")
    ap.add_argument("--pack-days", type=int, default=3)
    ap.add_argument("--only", nargs="*", choices=("n250k", "n1m", "c16"), default=None)
    ap.add_argument("--make-only", action="store_true", help="write the records and stop")
    ap.add_argument("--baseline-tree", type=Path, default=None)
    ap.add_argument("--baseline-only", nargs="*", choices=("n250k", "n1m", "c16"),
                    default=["n250k"])  # fmt: skip
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args(argv)
    recs = records(args.data, args.pack_days)
    if args.make_only:
        return 0
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for key in args.only or list(recs):
            print(f"identify {recs[key]} ...", flush=True)
            row = run_identify(recs[key], Path(tmp) / key)
            rows.append(row)
            print(json.dumps(row), flush=True)
        for key in args.baseline_only if args.baseline_tree else []:
            print(f"identify {recs[key]} with {args.baseline_tree} ...", flush=True)
            row = run_identify(recs[key], Path(tmp) / f"base-{key}", args.baseline_tree)
            rows.append(row)
            print(json.dumps(row), flush=True)
    print()
    print("| record | samples | cells | wall s | loop s | cell-samples/s | max RSS MB | "
          "RSS at 25 / 50 / 75 / 100 % of the run MB |")  # fmt: skip
    print("|---|---:|---:|---:|---:|---:|---:|---:|")
    for r in rows:
        n, nc, wall = int(str(r["n_samples"])), int(str(r["n_cells"])), float(str(r["wall_s"]))
        quarters = r["rss_quarters_MB"]
        assert isinstance(quarters, list)
        print(
            f"| {r['record']} | {n:,} | {nc} | {wall:.1f} | {float(str(r['loop_s'])):.1f} | "
            f"{n * nc / wall:,.0f} | {float(str(r['max_rss_MB'])):.0f} | "
            + " / ".join(f"{q:.0f}" for q in quarters)
            + " |"
        )
    if args.json:
        args.json.write_text(json.dumps(rows, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
