"""Many recordings, one output root: ``identify_file`` once per input, on a local process pool or
on a Dask distributed cluster, and a fleet summary of what came back.

Each input is one task, :func:`identify_task`: it runs :func:`~bmsid.offline.identify.identify_file`
(a black box here) with the run's :class:`~bmsid.offline.identify.IdentifySpec`, streamed (the
task keeps the last tick and the running sums, not the trace: a long input does not grow the
worker's memory), writes the input's outputs into its own subdirectory of the root, and returns
an :class:`InputSummary` of a few numbers per cell. Only the task (paths and the spec) and that
summary cross a process or network boundary, never samples or traces, so on a cluster every
worker must see the inputs and the output root at the same absolute paths (a shared
filesystem).

A failed input (unreadable, a bad column, an exception in the task or a worker that died) is an
``InputSummary`` with ``error`` set: one line, and the other inputs go on.
"""

from __future__ import annotations

import csv
import functools
import gc
import glob
import hashlib
import math
import multiprocessing
import os
import re
import threading
import time
import uuid
from collections.abc import Callable, Iterable, Iterator, Sequence
from concurrent.futures import Future, ProcessPoolExecutor, as_completed
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from bmsid.config.engine import ocv_model
from bmsid.errors import UserError
from bmsid.estimate import jit
from bmsid.estimate.tuning import EstimatorTuning
from bmsid.estimate.types import Quality
from bmsid.offline.identify import IdentifySpec, identify_file, open_spec_input, too_short
from bmsid.offline.inputs import StreamedInput, with_score_reference
from bmsid.offline.outputs import fit_warnings, start_warnings
from bmsid.offline.plausibility import check_head_samples
from bmsid.offline.record_checks import CheckedRecord, CheckOptions, check_record
from bmsid.offline.scoring import IdentifyResult
from bmsid.threads import one_blas_thread

#: What a directory argument contributes (searched recursively).
INPUT_SUFFIXES = (".csv", ".csv.gz", ".log", ".log.gz")
#: Parameters of each cell in summary.csv, latest published values (SI units).
SUMMARY_FIELDS = ("R0_ohm", "R1_ohm", "R2_ohm", "tau1_s", "tau2_s", "soc", "capacity_Ah")
SUMMARY_COLUMNS = (
    "input", "out_dir", "status", "error", "warnings", "cell", "t_s", *SUMMARY_FIELDS, "quality",
    "quality_name", "rmse_mV", "R0_median_ohm", "input_r0_rank", "fleet_r0_rank",
)  # fmt: skip
_GLOB_CHARS = re.compile(r"[*?\[]")


# ----------------------------------------------------------------------------- inputs
@dataclass(frozen=True)
class FleetInput:
    """One recording of a fleet run: ``path`` absolute (what workers open), ``given`` as the
    user's argument expanded (what lines and summary.csv show), ``name`` its subdirectory."""

    path: str
    given: str
    name: str


def is_fleet(arguments: Sequence[str]) -> bool:
    """Whether INPUT arguments ask for the fleet layout: several, a directory or a glob. Decided
    by the arguments' form, not by how many files they match, so a directory of one file still
    gets ``OUT/<name>/`` and ``summary.csv``."""
    if len(arguments) != 1:
        return True
    arg = arguments[0]
    return Path(arg).is_dir() or (not Path(arg).exists() and bool(_GLOB_CHARS.search(arg)))


def _recordings_under(directory: Path) -> list[Path]:
    return sorted(
        p for p in directory.rglob("*") if p.is_file() and p.name.lower().endswith(INPUT_SUFFIXES)
    )


def expand_inputs(arguments: Sequence[str]) -> list[Path]:
    """Files, directories (recursively, ``*.csv``, ``*.csv.gz``, ``*.log``, ``*.log.gz``) and
    glob patterns, in argument order, each argument's matches sorted, a file met twice kept
    once. UserError for an argument that matches nothing."""
    out: list[Path] = []
    seen: set[Path] = set()
    for arg in arguments:
        p = Path(arg)
        if p.is_file():
            found = [p]
        elif p.is_dir():
            found = _recordings_under(p)
            if not found:
                raise UserError(
                    f"{arg}: no .csv, .csv.gz, .log or .log.gz file under this directory"
                )
        elif _GLOB_CHARS.search(arg):
            found = []
            for m in sorted(glob.glob(arg, recursive=True)):
                mp = Path(m)
                found += _recordings_under(mp) if mp.is_dir() else [mp] if mp.is_file() else []
            if not found:
                raise UserError(f"{arg}: the pattern matches no file")
        else:
            raise UserError(f"{arg}: no such file or directory")
        for f in found:
            key = f.resolve()
            if key not in seen:
                seen.add(key)
                out.append(f)
    return out


def out_name(path: Path) -> str:
    """The subdirectory of one input: its parent's and its own name (readable), then 8 hex
    digits of its absolute path (unique: ``a/x.csv`` and ``b/a/x.csv`` differ). The same file
    gets the same name in every run, whatever else is on the command line."""
    absolute = path.resolve()
    readable = f"{absolute.parent.name}__{absolute.name}" if absolute.parent.name else absolute.name
    readable = re.sub(r"[^A-Za-z0-9._-]+", "_", readable).strip("._") or "input"
    digest = hashlib.sha1(str(absolute).encode("utf-8")).hexdigest()[:8]
    return f"{readable}-{digest}"


def fleet_inputs(arguments: Sequence[str]) -> list[FleetInput]:
    """The run's inputs with their subdirectory names (UserError on a name collision, which
    needs two paths whose SHA-1 prefixes and names agree)."""
    items = [FleetInput(str(p.resolve()), str(p), out_name(p)) for p in expand_inputs(arguments)]
    names: dict[str, str] = {}
    for item in items:
        if item.name in names:
            raise UserError(f"{item.given} and {names[item.name]} map to one name {item.name}")
        names[item.name] = item.given
    return items


# ----------------------------------------------------------------------------- one task
@dataclass(frozen=True)
class CellSummary:
    """A cell's latest published parameters (SI units, NaN where it has none), quality code,
    the fit's RMSE over the evaluation window (mV) and its median R0 there (ohm, values held on
    a bound or after a divergence left out, ``accumulate.StreamedMedian``; NaN where none is
    left): what cells are ranked on."""

    cell: str
    t_s: float
    params: tuple[float, ...]  # SUMMARY_FIELDS order
    quality: int
    rmse_mV: float
    r0_median_ohm: float = math.nan

    def value(self, name: str) -> float:
        return self.params[SUMMARY_FIELDS.index(name)]


@dataclass(frozen=True)
class InputSummary:
    """What a task returns: small, whatever the record's length."""

    input: FleetInput
    error: str | None = None
    n_samples: int = 0
    cells: tuple[CellSummary, ...] = ()
    #: Wall and CPU time of the task in its worker, s (their ratio shows what CPU it got).
    wall_s: float = 0.0
    cpu_s: float = 0.0
    #: Codes of the record checks' warnings (``record_checks``; the lines: its metrics.json),
    #: then of the run's (``outputs.start_warnings``, ``outputs.fit_warnings``).
    warnings: tuple[str, ...] = ()

    @property
    def ok(self) -> bool:
        return self.error is None


@dataclass(frozen=True)
class CellFromRecord:
    """A fleet run without a cell config: each input's cell is read off its own head, as
    ``bmsid identify`` of one file does (``record_checks.check_record``: the capacity, an LFP
    record's OCV, with ``--ocv-coeffs`` from the task's ``CheckOptions``), and the
    ``--score-soc0`` reference (fraction) counted with that input's capacity."""

    score_soc0: float | None = None


#: The record checks of a fleet run with one cell config for all (``--cell-config``).
GIVEN_CELL = CheckOptions(cell_config_given=True)


@dataclass(frozen=True)
class FleetTask:
    """One input to identify into ``out_dir`` (absolute) with ``spec``; picklable.
    ``from_record``: the cell is read off the input first (None: ``spec.cell`` for all);
    ``checks``: what the record checks need of the options (``record_checks``)."""

    input: FleetInput
    out_dir: str
    spec: IdentifySpec
    from_record: CellFromRecord | None = None
    checks: CheckOptions = GIVEN_CELL


def checked_spec(source: StreamedInput, task: FleetTask) -> tuple[IdentifySpec, CheckedRecord]:
    """The input's record checks (a single run's; UserError at the first error) and its spec,
    with the cell its head tells when ``task.from_record`` (unchanged where it tells none).
    The findings travel with ``source`` to its metrics.json."""
    spec = task.spec
    tuning = spec.tuning or EstimatorTuning()
    head = source.head(check_head_samples(source.n_cells))
    checked = check_record(head, spec.cell, task.checks, tuning, spec.gates)
    del head
    if checked.error is not None:
        raise UserError(checked.error.message)
    source.findings = (*source.findings, *checked.findings)
    how = task.from_record
    if how is not None and checked.note is not None:
        window = with_score_reference(spec.window, checked.cell, how.score_soc0, tuning.gap_s)
        meta = {**spec.output.metadata, "cell_config": checked.note}
        spec = replace(
            spec, cell=checked.cell, window=window, output=replace(spec.output, metadata=meta)
        )
    return spec, checked


def cell_summaries(result: IdentifyResult, spec: IdentifySpec) -> tuple[CellSummary, ...]:
    """Each cell's values at the last tick and its RMSE over ``spec.window``, from what a
    streamed run keeps (its last tick and its running sums over the window: the fleet's tasks
    stream) or from a kept trace (``IdentifySpec.keep_trace``); the same numbers either way,
    the RMSE to float rounding (sums added block by block)."""
    last = result.last_tick()
    if last is None:
        return ()
    scorer = result.scorer(spec.window)
    per_cell = scorer.scores().per_cell_window
    r0_median = scorer.acc.r0_median.median()
    return tuple(
        CellSummary(
            cell=name,
            t_s=float(last.t_s[0]),
            params=tuple(float(last[f][0, c]) for f in SUMMARY_FIELDS),
            quality=int(last.quality[0, c]),
            rmse_mV=1e3 * per_cell[c].rmse_V,
            r0_median_ohm=float(r0_median[c]),
        )
        for c, name in enumerate(result.cell_names)
    )


def error_text(exc: BaseException) -> str:
    """One line for a failed input: a UserError's message, an OSError's reason and file, or
    the type and message of anything else (a bug: ``bmsid identify INPUT`` alone shows where)."""
    if isinstance(exc, UserError):
        text = str(exc)
    elif isinstance(exc, BrokenProcessPool):
        text = f"a worker process died ({exc})"
    elif isinstance(exc, OSError):
        files = [str(f) for f in (exc.filename, exc.filename2) if f is not None]
        reason = exc.strerror or str(exc) or type(exc).__name__
        text = f"{reason}: {' -> '.join(files)}" if files else reason
    else:
        text = f"internal error: {type(exc).__name__}: {exc}"
    return re.sub(r"\s*\n\s*", " ", text.strip())  # one line, whatever the message holds


def failed(item: FleetInput, exc: BaseException) -> InputSummary:
    """The summary of an input that failed with ``exc``, its path named as the user gave it."""
    return InputSummary(item, error_text(exc).replace(item.path, item.given))


# pyplot (the plots) is not thread-safe and the per-tick loop holds the GIL: a Dask worker
# started with several threads still runs one identification at a time.
_ONE_AT_A_TIME = threading.Lock()


@functools.cache  # once per process
def settle_worker() -> None:
    """Once per worker process, before its first input: one BLAS thread (threads.py), the
    compiled kernels loaded, and the heap that far (bmsid's, numba's, matplotlib's, a Dask
    worker's objects: 200,000-250,000) frozen out of the cyclic garbage collector, as the
    daemon does. Unfrozen, each input's full collection walked them: 0.15-0.23 s of a ~1 s
    one-hour input, in a process of its own and in a Dask worker alike (measured)."""
    one_blas_thread()
    jit.ensure()
    gc.collect()
    gc.freeze()


def identify_task(task: FleetTask) -> InputSummary:
    """Run one input (in a worker): its outputs into ``task.out_dir``, a summary back; never
    raises for a bad input. The run is streamed whatever ``task.spec.keep_trace`` says (as
    ``bmsid identify`` of one file: a first pass counts the ticks, the default decimation of a
    long record's parameter table applies), so a worker's memory does not grow with the record."""
    spec = replace(task.spec, keep_trace=False)
    settle_worker()
    try:
        with _ONE_AT_A_TIME:
            wall, cpu = time.perf_counter(), time.process_time()
            source = open_spec_input(task.input.path, spec)  # read once, head and run
            spec, checked = checked_spec(source, replace(task, spec=spec))
            result = identify_file(task.input.path, spec, Path(task.out_dir), source=source)
            wall, cpu = time.perf_counter() - wall, time.process_time() - cpu
        if (short := too_short(result.n_ticks, result.n_samples)) is not None:
            raise UserError(short)
        cells = cell_summaries(result, spec)
    except Exception as exc:  # any failure is this input's, reported in one line
        return failed(task.input, exc)
    run = [*start_warnings(result, ocv_model(spec.cell)), *fit_warnings(result, spec.window)]
    warned = tuple(f.code for f in checked.findings if f.level == "warning")
    warned += tuple(dict.fromkeys(code for code, _ in run))  # a code once, for any cell
    return InputSummary(task.input, None, result.n_samples, cells, wall, cpu, warned)


TaskFn = Callable[[FleetTask], InputSummary]


# ----------------------------------------------------------------------------- executors
def default_workers(n_inputs: int) -> int:
    """min(inputs, the CPUs this process may use)."""
    cpus = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    return max(1, min(n_inputs, cpus or 1))


def run_local(
    tasks: Sequence[FleetTask], workers: int, fn: TaskFn = identify_task
) -> Iterator[InputSummary]:
    """The tasks on ``workers`` local processes, summaries yielded as they complete.

    Workers come from a fork server that has imported bmsid once (cheap starts, and no fork of
    a process whose threads, tqdm's or a caller's, may hold locks)."""
    ctx = multiprocessing.get_context("forkserver")
    ctx.set_forkserver_preload(["bmsid.offline.fleet"])
    with ProcessPoolExecutor(max_workers=workers, mp_context=ctx) as pool:
        futures = {pool.submit(fn, t): t for t in tasks}
        try:
            yield from _gather(as_completed(futures), futures)
        finally:  # on Ctrl-C or an abandoned run, start nothing more; running inputs end
            pool.shutdown(wait=True, cancel_futures=True)


def _gather(
    done: Iterable[Future[InputSummary]], futures: dict[Future[InputSummary], FleetTask]
) -> Iterator[InputSummary]:
    for fut in done:
        exc = fut.exception()
        if exc is None:
            yield fut.result()
        else:  # raised past the task's own handler, or the worker process died
            yield failed(futures[fut].input, exc)


def run_dask(
    tasks: Sequence[FleetTask], scheduler: str, fn: TaskFn = identify_task
) -> Iterator[InputSummary]:
    """The tasks on the Dask cluster at ``scheduler`` (one task each), summaries yielded as
    they complete. UserError when dask.distributed is missing or the scheduler cannot be
    reached."""
    try:  # an optional extra, and ~1 s of imports that a process-pool run does not pay
        from distributed import Client  # noqa: PLC0415
        from distributed import as_completed as dask_completed  # noqa: PLC0415
    except ImportError:
        raise UserError(
            "--scheduler needs dask.distributed, which is not installed: pip install 'bmsid[fleet]'"
        ) from None
    try:
        client = Client(scheduler, timeout="10s", set_as_default=False)  # type: ignore[no-untyped-call]
    except (OSError, TimeoutError, ValueError) as exc:
        raise UserError(f"--scheduler {scheduler}: cannot connect: {exc}") from None
    run = uuid.uuid4().hex[:8]  # keys unique per run: the same input of another run is new work
    with client:
        futures = {
            client.submit(fn, t, key=f"bmsid-identify-{t.input.name}-{run}", retries=0): t
            for t in tasks
        }
        done = dask_completed(futures, loop=client.loop)  # type: ignore[no-untyped-call]
        for fut in done:
            task = futures.pop(fut)
            if fut.status == "finished":
                summary: InputSummary = fut.result()
                yield summary
            else:  # the task raised, or its worker died more often than the scheduler allows
                yield failed(task.input, fut.exception())
            fut.release()


# ----------------------------------------------------------------------------- summary.csv
def _num(x: float, fmt: str = ".9g") -> str:
    return format(x, fmt) if math.isfinite(x) else ""


def weakest(summaries: Iterable[InputSummary], n: int) -> list[tuple[InputSummary, CellSummary]]:
    """The fleet's ``n`` cells of largest median R0 (cells without one left out)."""
    cells = [(s, c) for s in summaries for c in s.cells if math.isfinite(c.r0_median_ohm)]
    cells.sort(key=lambda sc: -sc[1].r0_median_ohm)
    return cells[:n]


def summary_rows(summaries: Sequence[InputSummary], worst: int) -> list[dict[str, str]]:
    """Rows of summary.csv in ``summaries`` order: one per cell of an identified input
    (``input_r0_rank`` 1 = the input's largest median R0; ``fleet_r0_rank`` 1..``worst`` for
    the fleet's largest), one with ``status`` failed and the ``error`` per failed input."""
    fleet_rank = {
        (s.input.path, c.cell): k + 1 for k, (s, c) in enumerate(weakest(summaries, worst))
    }
    rows: list[dict[str, str]] = []
    for s in summaries:
        head = {"input": s.input.given, "out_dir": s.input.name}
        if not s.ok:
            rows.append({**head, "status": "failed", "error": s.error or ""})
            continue
        r0 = np.array([c.r0_median_ohm for c in s.cells])
        order = sorted(
            (k for k in range(len(s.cells)) if math.isfinite(r0[k])), key=lambda k: -r0[k]
        )
        rank = {k: i + 1 for i, k in enumerate(order)}
        for k, c in enumerate(s.cells):
            rows.append({
                **head, "status": "ok", "error": "", "warnings": ";".join(s.warnings),
                "cell": c.cell, "t_s": _num(c.t_s, ".3f"),
                **{f: _num(c.value(f)) for f in SUMMARY_FIELDS},
                "quality": str(c.quality), "quality_name": Quality(c.quality).name.lower(),
                "rmse_mV": _num(c.rmse_mV), "R0_median_ohm": _num(c.r0_median_ohm),
                "input_r0_rank": str(rank.get(k, "")),
                "fleet_r0_rank": str(fleet_rank.get((s.input.path, c.cell), "")),
            })  # fmt: skip
    return rows


def write_summary(path: Path, summaries: Sequence[InputSummary], worst: int) -> None:
    """summary.csv (``SUMMARY_COLUMNS``; empty fields where there is no value)."""
    with path.open("w", newline="", encoding="utf-8") as fh:
        w = csv.DictWriter(fh, fieldnames=SUMMARY_COLUMNS, restval="")
        w.writeheader()
        w.writerows(summary_rows(summaries, worst))
