"""Offline identification as a library: a recording in, an :class:`IdentifyResult` and output
files out.

One call per input, :func:`identify_file` (or :func:`identify_source` for an opened input), with
everything that decides the result in an :class:`IdentifySpec`: a frozen, picklable value, so the
CLI (``bmsid identify``, ``bmsid compare``), the benches and a distributed task all run the same
function. The data flow is blocks all the way: the input yields
:class:`~bmsid.samples.SampleBlock` columns, the bank eats each block
(:meth:`~bmsid.estimate.bank.EstimatorBank.update_block`) and returns the
:class:`~bmsid.estimate.types.EstimateBlock` of the ticks it completed, and ``params.csv`` (or
``params.parquet``, every tick or one row per ``--every`` interval) is appended per block.

Two ways to keep what the metrics and plots need (``IdentifySpec.keep_trace``):

- kept (the library's default: ``compare``, the benches): the blocks are concatenated into the
  whole trace, scored at the end;
- streamed (``bmsid identify``): a first pass over the input counts the ticks the bank will make
  (:func:`scan_record`: the tick assembler's clock alone, no estimator),
  then each block of estimates goes to a :class:`~bmsid.offline.scoring.RunScorer` (running
  sums, min-max plot decimation) and is dropped: memory is bounded by the estimator's windows
  and the input's pieces, not by the record's length.

Both score with the same accumulators, so their metrics.json agree to float rounding.

Pure apart from reading the input, writing into ``out`` and the clock read for the run time.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterable, Mapping, Sequence
from contextlib import ExitStack
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from bmsid.config.cell import CellConfig
from bmsid.config.engine import build_bank, cell_model
from bmsid.estimate.cellmodel import BOUNDED, INITIAL
from bmsid.estimate.guard import WATCHED
from bmsid.estimate.startvalues import (
    PROBE_S,
    StartValues,
    min_step_for,
    start_values_from_record,
)
from bmsid.estimate.tuning import EstimatorTuning, Variant
from bmsid.estimate.types import EstimateBlock
from bmsid.gates import GateConfig, InputGate, gated_head
from bmsid.offline.csvio import ColumnMap, TesterData
from bmsid.offline.inputs import (
    DEFAULT_BLOCK_SIZE,
    InputSource,
    LoadedInput,
    StreamedInput,
    open_input,
)
from bmsid.offline.outputs import (
    OutputSpec,
    auto_every_s,
    prepare_out_dir,
    write_metrics_json,
    write_plots,
)
from bmsid.offline.scoring import EvalWindow, IdentifyResult, RunScorer, metrics_document
from bmsid.offline.start_soc import WINDOW_FIT, fitted_start_soc
from bmsid.offline.tick_count import count_tick_times
from bmsid.offline.writers import ParamsSink, open_params_writer
from bmsid.samples import Sample, SampleBlock

FloatArray = npt.NDArray[np.float64]

#: Called with the number of samples consumed since the last call (progress bars).
Progress = Callable[[int], None]
#: Called with each block of estimates as the bank completes it (e.g. a params.csv writer).
EstimateSink = Callable[[EstimateBlock], None]
#: Fewest identification ticks a record must give: a single tick has no dynamics (its model
#: voltage is read off its own voltage through the OCV curve), so its "error" scores nothing.
MIN_TICKS = 2


def too_short(n_ticks: int, n_samples: int) -> str | None:
    """Why a record of ``n_ticks`` identification ticks (from ``n_samples`` samples) is too
    short to identify anything; None when it is not (:data:`MIN_TICKS`)."""
    if n_ticks >= MIN_TICKS:
        return None
    return (
        f"{n_samples} sample(s), {n_ticks} identification tick(s): too little data to identify "
        f"anything (at least {MIN_TICKS} ticks: a single tick's model voltage is read off its "
        "own voltage, so there is no model error to score)"
    )


@dataclass(frozen=True)
class IdentifySpec:
    """Everything that decides an offline run, as plain values (picklable, no open files).

    Attributes
    ----------
    cell : CellConfig
        The cell type (OCV, hysteresis, capacity, bounds, start values).
    variant : str
        ``non-hy-affrls``, ``hy-affrls`` or ``hy-affrls-lpso``.
    tuning : EstimatorTuning or None
        Estimator tuning; None: the defaults.
    soc0 : float or None
        Initial SOC (fraction); None: the cell config's ``soc_init`` rule.
    window : EvalWindow
        Which ticks are scored.
    charge_positive : bool
        The input counts charge current positive.
    mapping : str or None
        Bus mapping TOML of a candump log; None: the default mapping.
    n_cells : int or None
        Cells in a candump log (None: as many as the log carries; a CSV says it by its
        columns).
    channel : str or None
        CAN channel of a candump log (needed when several carry the mapping's frames).
    columns : mapping or None
        Column map of a CSV whose names differ from bmsid's (``inputs.parse_columns``).
    block_size : int
        Samples per block fed to the bank (the results do not depend on it).
    output : OutputSpec
        What is written when the run is given an output directory.
    gates : GateConfig
        The plausibility gates before the estimators (``bmsid.gates``), as the daemon's.
    keep_trace : bool
        Keep every tick's estimates in the result (``IdentifyResult.trace``); False streams:
        a first pass counts the ticks, the metrics and plots are accumulated block by block
        and memory does not grow with the record (``bmsid identify``).
    """

    cell: CellConfig
    variant: Variant = "hy-affrls-lpso"
    tuning: EstimatorTuning | None = None
    soc0: float | None = None
    window: EvalWindow = field(default_factory=EvalWindow)
    charge_positive: bool = False
    mapping: str | None = None
    n_cells: int | None = None
    channel: str | None = None
    columns: Mapping[str, ColumnMap] | None = None
    block_size: int = DEFAULT_BLOCK_SIZE
    output: OutputSpec = field(default_factory=OutputSpec)
    gates: GateConfig = field(default_factory=GateConfig)
    keep_trace: bool = True


def input_gate(
    cell: CellConfig, n_cells: int, tuning: EstimatorTuning | None, gates: GateConfig,
    quiet: bool = False,
) -> InputGate:  # fmt: skip
    """Fresh plausibility gates for ``n_cells`` cells of type ``cell`` (limits from its OCV
    curve and capacity, the step check's age from the tuning's ``gap_s``); ``quiet`` for a
    pass before the run (its refusals are told by the run's gate)."""
    tun = tuning or EstimatorTuning()
    limits = gates.for_model(cell_model(cell, n_cells, None, tun), tun.gap_s)
    return InputGate(limits, n_cells, quiet)


def run_blocks(
    blocks: Iterable[SampleBlock],
    n_cells: int,
    cell: CellConfig,
    variant: Variant,
    tuning: EstimatorTuning | None = None,
    soc0: float | FloatArray | None = None,
    progress: Progress | None = None,
    cell_names: Sequence[str] | None = None,
    sink: EstimateSink | None = None,
    start: StartValues | None = None,
    gates: GateConfig | None = None,
    scorer: RunScorer | None = None,
    branch0_V: FloatArray | None = None,
    h0: FloatArray | None = None,
) -> IdentifyResult:
    """Feed sample blocks in order, through the plausibility gates, to a new bank of
    ``n_cells`` cells.

    Parameters
    ----------
    blocks : iterable of SampleBlock
        The recording in time order (s, A with + = discharge, V).
    n_cells : int
        Voltage columns of every block.
    cell, variant, tuning, soc0, branch0_V, h0
        The bank's setup (see :func:`~bmsid.config.engine.build_bank`).
    progress : callable or None
        Called with the samples of each block once the bank has eaten it.
    cell_names : sequence of str or None
        Cell names; None: ``cell_01``, ``cell_02``, ...
    sink : callable or None
        Called with each non-empty block of estimates as it is produced (before the next input
        block is read), e.g. a params writer's ``append``.
    start : StartValues or None
        Start values measured on the record (:func:`probe_start_values`) for what ``cell``
        leaves out.
    gates : GateConfig or None
        The plausibility gates; None: the defaults.
    scorer : RunScorer or None
        Streams: each block of estimates is added to it and dropped (the result's ``trace``
        is None, its ``summary`` the scorer). None: the blocks are kept as the ``trace``.

    Returns
    -------
    IdentifyResult
        ``runtime_s`` counts the gates' and the bank's time only (no reading, writing or
        progress); ``input_gates`` what the gates refused.
    """
    bank = build_bank(
        cell, n_cells, variant, tuning, soc0=soc0, start=start, branch0_V=branch0_V, h0=h0
    )
    gate = input_gate(cell, n_cells, tuning, gates or GateConfig())
    parts: list[EstimateBlock] = []
    n = 0
    runtime = 0.0
    for block in blocks:
        t0 = time.perf_counter()
        est = bank.update_block(gate.apply(block))
        runtime += time.perf_counter() - t0
        n += len(block)
        if est.n_ticks:
            if scorer is None:
                parts.append(est)
            else:
                scorer.add(est)
            if sink is not None:
                sink(est)
        if progress is not None:
            progress(len(block))
    names = list(cell_names) if cell_names else [f"cell_{c + 1:02d}" for c in range(n_cells)]
    return IdentifyResult(
        variant=variant,
        trace=EstimateBlock.concat(parts, n_cells) if scorer is None else None,
        soc_init_method=bank.soc_init_method,
        counters={**bank.counters, **gate.state.counters()},
        runtime_s=runtime,
        n_samples=n,
        cell_names=names,
        start_values=start,
        input_gates=gate.state.report(),
        summary=scorer,
        start_branch_V=bank.start_branch_V,
        start_h=bank.start_h,
        activation_energy_J_mol=bank.activation_energy_J_mol,
    )


@dataclass(frozen=True)
class RecordScan:
    """What one pass over a recording found before the run: input samples, the ticks the bank
    will make of them and the first and last tick's time (s;
    NaN without ticks)."""

    n_samples: int
    n_ticks: int
    t_first_s: float
    t_last_s: float

    @property
    def duration_s(self) -> float:
        """Time from the first to the last tick, s (0 with fewer than two)."""
        return self.t_last_s - self.t_first_s if self.n_ticks > 1 else 0.0


def scan_record(source: InputSource, spec: IdentifySpec) -> RecordScan:
    """One pass over ``source``: its samples, and the ticks the bank will make of them
    (``offline/tick_count.py``: the tick assembler's clock alone, exact); a streamed source
    knows its sample count, gaps and merges afterwards. Raises the reader's ``UserError`` for
    a bad row anywhere in the file, before any estimation."""
    clock = count_tick_times((b.t_s for b in source.blocks(spec.block_size)), spec.tuning)
    return RecordScan(clock.n_samples, clock.n_ticks, clock.t_first_s, clock.t_last_s)


def probe_start_values(
    blocks: Iterable[SampleBlock], cell: CellConfig, gate: InputGate | None = None,
    tuning: EstimatorTuning | None = None,
) -> StartValues | None:  # fmt: skip
    """Start values measured on the record's first ``PROBE_S`` seconds, when the cell config
    leaves start values or bounds out (None when it gives both, or the record has too few
    current steps: the config's capacity rule and default bounds then apply); through ``gate``
    (fresh plausibility gates) when given."""
    if cell.initial is not None and cell.bounds is not None:
        return None
    b = gated_head(blocks, PROBE_S, gate)
    if b is None:
        return None
    step_A = min_step_for(cell.capacity_Ah, (tuning or EstimatorTuning()).excitation_C)
    return start_values_from_record(b.t_s, b.current_A, b.cell_voltages_V, step_A)


def start_values_document(
    cell: CellConfig, start: StartValues | None, tuning: EstimatorTuning | None, n_cells: int
) -> dict[str, object]:
    """Where the run's start values and bounds came from, and what they were (SI units)."""
    model = cell_model(cell, n_cells, start, tuning)
    ini = {k: float(model.start(k)[0]) for k in INITIAL}
    bounds = {k: [float(model.lo[0, j]), float(model.hi[0, j])] for j, k in enumerate(BOUNDED)}
    return {
        "initial_from": "config" if cell.initial is not None else
        (start.source if start is not None else "capacity rule (R0 = 0.1 ohm Ah / capacity)"),
        "bounds_from": "config" if cell.bounds is not None else
        ("relative to the measured R0" if start is not None else "defaults"),
        "initial": ini,
        "bounds": bounds,
    }  # fmt: skip


def watched_bounds(
    cell: CellConfig, start: StartValues | None, tuning: EstimatorTuning | None, n_cells: int
) -> dict[str, tuple[FloatArray, FloatArray]]:
    """(lo, hi) per cell of each parameter the guard watches (``guard.WATCHED``)."""
    model = cell_model(cell, n_cells, start, tuning)
    return {name: model.bound(name) for name in WATCHED}


def bound_findings(
    trace: EstimateBlock,
    cell: CellConfig,
    start: StartValues | None,
    tuning: EstimatorTuning | None,
    cell_names: Sequence[str],
) -> dict[str, object]:
    """Where the estimator had parameters on their bounds (the guard's ``on_bound`` bits, within
    ``ON_BOUND_REL`` of a bound): per parameter the share of ticks (pooled over cells) and the
    cells that end the record on one. A parameter on a bound is a finding (the bound, not the
    data, decided it), never a published value: the guard published its branch's last good
    values instead; ``published_on_a_bound`` checks that in the published values themselves.
    (A streamed run accumulates the same, ``RunAccumulator.bound_findings``.)"""
    bounds = watched_bounds(cell, start, tuning, trace.n_cells)
    return RunScorer.of_trace(trace, EvalWindow(), bounds).acc.bound_findings(cell_names)


def identify_source(
    source: InputSource,
    spec: IdentifySpec,
    out: Path | None = None,
    progress: Progress | None = None,
    scan: RecordScan | None = None,
) -> IdentifyResult:
    """Identify an opened recording; with ``out``, write its output files there.

    Parameters
    ----------
    source : InputSource
        The recording (e.g. from :func:`~bmsid.offline.inputs.open_input`).
    spec : IdentifySpec
        The run's setup; ``spec.output`` says what is written, ``spec.keep_trace`` whether the
        run is streamed.
    out : Path or None
        Output directory (created): ``params.csv`` (or ``.parquet``) appended per block while
        the bank runs, then ``metrics.json`` (metrics over ``spec.window`` plus
        ``spec.output.metadata`` and, when rows were decimated, ``output``) and the plots.
        None: nothing is written.
    progress : callable or None
        Called with the samples consumed, per block.
    scan : RecordScan or None
        The streamed run's first pass when the caller made it already (:func:`scan_record`).

    Returns
    -------
    IdentifyResult
        Also written when the run completed no tick (metrics are then NaN, no plots).
    """
    probe_gate = input_gate(spec.cell, source.n_cells, spec.tuning, spec.gates, quiet=True)
    start = probe_start_values(source.blocks(spec.block_size), spec.cell, probe_gate, spec.tuning)
    # a start under load or still relaxing: its branches (and SOC, unless known) fitted over
    # the first window
    fresh_gate = input_gate(spec.cell, source.n_cells, spec.tuning, spec.gates, quiet=True)
    fitted = fitted_start_soc(
        source.blocks(spec.block_size), spec.cell, spec.tuning, start, fresh_gate, spec.soc0
    )
    soc_fitted = fitted is not None and fitted.soc_fitted
    soc0: float | FloatArray | None = spec.soc0
    if soc_fitted and fitted is not None:
        soc0 = fitted.soc0
    bounds = watched_bounds(spec.cell, start, spec.tuning, source.n_cells)
    scorer: RunScorer | None = None
    if not spec.keep_trace:
        scan = scan or scan_record(source, spec)
        scorer = RunScorer(scan.n_ticks, source.n_cells, spec.window, bounds)
    tick_s = (spec.tuning or EstimatorTuning()).id_period_s
    every, announced = params_interval(spec.output, scan, tick_s)
    with ExitStack() as stack:
        sink: EstimateSink | None = None
        if out is not None:
            prepare_out_dir(out)
            if spec.output.params_csv:
                writer: ParamsSink = open_params_writer(
                    out, source.cell_names, spec.output.params_format, every,
                    spec.output.every_mode,
                )  # fmt: skip
                stack.callback(writer.close)
                sink = writer.append
        result = run_blocks(
            source.blocks(spec.block_size), source.n_cells, spec.cell, spec.variant, spec.tuning,
            soc0, progress, source.cell_names, sink, start, spec.gates, scorer,
            None if fitted is None else fitted.branch_V, None if fitted is None else fitted.h0,
        )  # fmt: skip
    if soc_fitted:
        result = replace(result, soc_init_method=WINDOW_FIT)
    if fitted is not None:
        result = replace(result, start_fit_rmse_V=fitted.rmse_V)
    if out is not None:
        # a kept trace is scored once here, with the bounds, as the streamed run was
        scored = scorer or RunScorer.of_trace(result.kept_trace(), spec.window, bounds)
        result = replace(result, summary=scored)
        doc = {
            **metrics_document(result, spec.window),
            "start_values": start_values_document(spec.cell, start, spec.tuning, source.n_cells),
            "input_checks": {**source.input_report, "gates": result.input_gates},
            "bounds": scored.acc.bound_findings(result.cell_names),
            "output": _output_document(spec.output, every, announced),
            **spec.output.metadata,
        }
        write_metrics_json(doc, out / "metrics.json")
        title = spec.output.title or f"{Path(source.source).name} - {spec.variant}"
        write_plots(result, spec.window, out, title, spec.output.plots)
    return result


def params_interval(
    output: OutputSpec, scan: RecordScan | None, tick_s: float = 0.0
) -> tuple[float | None, bool]:
    """The parameter table's interval (s; None: every tick, as is one no longer than the tick
    ``tick_s``) and whether it is the default decimation of a long record
    (:func:`~bmsid.offline.outputs.auto_every_s`, which needs the streamed run's ``scan``), to
    be announced."""
    if output.every_s is not None:
        return (output.every_s if output.every_s > tick_s else None), False
    if scan is None:
        return None, False
    every = auto_every_s(scan.n_ticks, scan.duration_s)
    return every, every is not None


def _output_document(output: OutputSpec, every: float | None, announced: bool) -> dict[str, Any]:
    """The ``output`` entry of metrics.json: the parameter table's file and its rows."""
    name = "params.parquet" if output.params_format == "parquet" else "params.csv"
    return {
        "params_file": name if output.params_csv else None,
        "every_s": every,
        "every_mode": output.every_mode if every is not None else None,
        "default_decimation": announced,
        "rows": "every tick and cell" if every is None else
        f"one per {every:g} s and cell ({output.every_mode} value of each interval)",
    }  # fmt: skip


def open_spec_input(path: str | Path, spec: IdentifySpec) -> StreamedInput:
    """The recording at ``path`` opened with ``spec``'s input options (sign, mapping, cells,
    channel, columns)."""
    return open_input(
        path, charge_positive=spec.charge_positive, mapping=spec.mapping, n_cells=spec.n_cells,
        channel=spec.channel, columns=spec.columns,
    )  # fmt: skip


def identify_file(
    path: str | Path,
    spec: IdentifySpec,
    out: Path | None = None,
    progress: Progress | None = None,
    source: InputSource | None = None,
) -> IdentifyResult:
    """Identify the recording at ``path`` (tester CSV or candump ``.log``, see
    :func:`~bmsid.offline.inputs.open_input`); see :func:`identify_source`. ``source``: the
    recording already opened (:func:`open_spec_input`), so it is not read twice.

    ``metrics.json`` records ``input`` (``path`` as given) unless ``spec.output.metadata`` sets
    it. Raises ``UserError`` for an unreadable input or output directory.
    """
    source = open_spec_input(path, spec) if source is None else source
    meta = {"input": str(path), **spec.output.metadata}
    spec = replace(spec, output=replace(spec.output, metadata=meta))
    return identify_source(source, spec, out, progress)


# ----------------------------------------------------------------------------- conveniences
def run_arrays(
    t_s: FloatArray,
    current_A: FloatArray,
    voltages_V: FloatArray,
    cell: CellConfig,
    variant: Variant,
    tuning: EstimatorTuning | None = None,
    soc0: float | None = None,
    progress: Progress | None = None,
    cell_names: Sequence[str] | None = None,
) -> IdentifyResult:
    """Identify columns held in memory: time (s), pack current (A, + = discharge) and voltages
    (V, shape (n,) or (n, n_cells)); nothing is written."""
    v = np.asarray(voltages_V, dtype=np.float64)
    if v.ndim == 1:
        v = v[:, None]
    n = v.shape[0]
    if t_s.shape[0] != n or current_A.shape[0] != n:
        raise ValueError("t_s, current_A and voltages_V need the same number of samples")
    block = SampleBlock.from_arrays(t_s, current_A, v)
    names = list(cell_names) if cell_names else [f"cell_{c + 1:02d}" for c in range(v.shape[1])]
    src = LoadedInput(source="<arrays>", samples=block, cell_names=names)
    gate = input_gate(cell, src.n_cells, tuning, GateConfig())
    start = probe_start_values(src.blocks(), cell, gate, tuning)
    return run_blocks(
        src.blocks(),
        src.n_cells,
        cell,
        variant,
        tuning,
        soc0,
        progress,
        src.cell_names,
        start=start,
    )


def run_tester(
    data: TesterData,
    cell: CellConfig,
    variant: Variant,
    tuning: EstimatorTuning | None = None,
    soc0: float | None = None,
    progress: Progress | None = None,
) -> IdentifyResult:
    """``run_arrays`` over a tester file (cells named by their voltage columns)."""
    return run_arrays(
        data.t_s, data.current_A, data.cell_voltages_V, cell, variant, tuning, soc0, progress,
        data.cell_names,
    )  # fmt: skip


def run_samples(
    samples: Sequence[Sample],
    cell: CellConfig,
    variant: Variant,
    tuning: EstimatorTuning | None = None,
    soc0: float | None = None,
    progress: Progress | None = None,
) -> IdentifyResult:
    """``run_arrays`` over decoded CAN samples (the daemon's input type)."""
    if not samples:
        raise ValueError("no samples")
    b = SampleBlock.from_samples(samples)
    return run_arrays(b.t_s, b.current_A, b.cell_voltages_V, cell, variant, tuning, soc0, progress)
