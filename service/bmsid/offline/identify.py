"""Offline identification as a library: a recording in, an :class:`IdentifyResult` and output
files out.

One call per input, :func:`identify_file` (or :func:`identify_source` for an opened input), with
everything that decides the result in an :class:`IdentifySpec`: a frozen, picklable value, so the
CLI (``bmsid identify``, ``bmsid compare``), the benches and a distributed task all run the same
function. The data flow is blocks all the way: the input yields
:class:`~bmsid.samples.SampleBlock` columns, the bank eats each block
(:meth:`~bmsid.estimate.bank.EstimatorBank.update_block`) and returns the
:class:`~bmsid.estimate.types.EstimateBlock` of the ticks it completed, and ``params.csv`` is
appended per block. The blocks are also kept, concatenated, for the metrics and the plots.

Pure apart from reading the input, writing into ``out`` and the clock read for the run time.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterable, Sequence
from contextlib import ExitStack
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
import numpy.typing as npt

from bmsid.config.cell import CellConfig
from bmsid.config.engine import build_bank
from bmsid.estimate.tuning import EstimatorTuning, Variant
from bmsid.estimate.types import EstimateBlock
from bmsid.offline.csvio import TesterData
from bmsid.offline.inputs import DEFAULT_BLOCK_SIZE, InputSource, LoadedInput, open_input
from bmsid.offline.outputs import OutputSpec, prepare_out_dir, write_metrics_json, write_plots
from bmsid.offline.scoring import EvalWindow, IdentifyResult, metrics_document
from bmsid.offline.writers import ParamsCsvWriter
from bmsid.samples import Sample, SampleBlock

FloatArray = npt.NDArray[np.float64]

#: Called with the number of samples consumed since the last call (progress bars).
Progress = Callable[[int], None]
#: Called with each block of estimates as the bank completes it (e.g. a params.csv writer).
EstimateSink = Callable[[EstimateBlock], None]


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
    n_cells : int
        Cells in a candump log (a CSV says it by its columns).
    block_size : int
        Samples per block fed to the bank (the results do not depend on it).
    output : OutputSpec
        What is written when the run is given an output directory.
    """

    cell: CellConfig
    variant: Variant = "hy-affrls-lpso"
    tuning: EstimatorTuning | None = None
    soc0: float | None = None
    window: EvalWindow = field(default_factory=EvalWindow)
    charge_positive: bool = False
    mapping: str | None = None
    n_cells: int = 1
    block_size: int = DEFAULT_BLOCK_SIZE
    output: OutputSpec = field(default_factory=OutputSpec)


def run_blocks(
    blocks: Iterable[SampleBlock],
    n_cells: int,
    cell: CellConfig,
    variant: Variant,
    tuning: EstimatorTuning | None = None,
    soc0: float | None = None,
    progress: Progress | None = None,
    cell_names: Sequence[str] | None = None,
    sink: EstimateSink | None = None,
) -> IdentifyResult:
    """Feed sample blocks in order to a new bank of ``n_cells`` cells.

    Parameters
    ----------
    blocks : iterable of SampleBlock
        The recording in time order (s, A with + = discharge, V).
    n_cells : int
        Voltage columns of every block.
    cell, variant, tuning, soc0
        The bank's setup (see :func:`~bmsid.config.engine.build_bank`).
    progress : callable or None
        Called with the samples of each block once the bank has eaten it.
    cell_names : sequence of str or None
        Cell names; None: ``cell_01``, ``cell_02``, ...
    sink : callable or None
        Called with each non-empty block of estimates as it is produced (before the next input
        block is read), e.g. ``ParamsCsvWriter.append``.

    Returns
    -------
    IdentifyResult
        ``runtime_s`` counts the bank's time only (no reading, writing or progress).
    """
    bank = build_bank(cell, n_cells, variant, tuning, soc0=soc0)
    parts: list[EstimateBlock] = []
    n = 0
    runtime = 0.0
    for block in blocks:
        start = time.perf_counter()
        est = bank.update_block(block)
        runtime += time.perf_counter() - start
        n += len(block)
        if est.n_ticks:
            parts.append(est)
            if sink is not None:
                sink(est)
        if progress is not None:
            progress(len(block))
    names = list(cell_names) if cell_names else [f"cell_{c + 1:02d}" for c in range(n_cells)]
    return IdentifyResult(
        variant=variant,
        trace=EstimateBlock.concat(parts, n_cells),
        soc_init_method=bank.soc_init_method,
        counters=dict(bank.counters),
        runtime_s=runtime,
        n_samples=n,
        cell_names=names,
    )


def identify_source(
    source: InputSource,
    spec: IdentifySpec,
    out: Path | None = None,
    progress: Progress | None = None,
) -> IdentifyResult:
    """Identify an opened recording; with ``out``, write its output files there.

    Parameters
    ----------
    source : InputSource
        The recording (e.g. from :func:`~bmsid.offline.inputs.open_input`).
    spec : IdentifySpec
        The run's setup; ``spec.output`` says what is written.
    out : Path or None
        Output directory (created): ``params.csv`` appended per block while the bank runs,
        then ``metrics.json`` (metrics over ``spec.window`` plus ``spec.output.metadata``) and
        the plots. None: nothing is written.
    progress : callable or None
        Called with the samples consumed, per block.

    Returns
    -------
    IdentifyResult
        Also written when the run completed no tick (metrics are then NaN, no plots).
    """
    with ExitStack() as stack:
        sink: EstimateSink | None = None
        if out is not None:
            prepare_out_dir(out)
            if spec.output.params_csv:
                writer = stack.enter_context(ParamsCsvWriter(out / "params.csv", source.cell_names))
                sink = writer.append
        result = run_blocks(
            source.blocks(spec.block_size), source.n_cells, spec.cell, spec.variant, spec.tuning,
            spec.soc0, progress, source.cell_names, sink,
        )  # fmt: skip
    if out is not None:
        doc = {**metrics_document(result, spec.window), **spec.output.metadata}
        write_metrics_json(doc, out / "metrics.json")
        title = spec.output.title or f"{Path(source.source).name} - {spec.variant}"
        write_plots(result, spec.window, out, title, spec.output.plots)
    return result


def identify_file(
    path: str | Path,
    spec: IdentifySpec,
    out: Path | None = None,
    progress: Progress | None = None,
) -> IdentifyResult:
    """Identify the recording at ``path`` (tester CSV or candump ``.log``, see
    :func:`~bmsid.offline.inputs.open_input`); see :func:`identify_source`.

    ``metrics.json`` records ``input`` (``path`` as given) unless ``spec.output.metadata`` sets
    it. Raises ``UserError`` for an unreadable input or output directory.
    """
    source = open_input(
        path, charge_positive=spec.charge_positive, mapping=spec.mapping, n_cells=spec.n_cells
    )
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
    return run_blocks(
        src.blocks(), src.n_cells, cell, variant, tuning, soc0, progress, src.cell_names
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
