"""The daemon's start SOC, fitted over its first window once that window has been seen.

Offline, ``bmsid identify`` reads a record's first ``WINDOW_S`` before it starts the engine and
fits the start SOC there when the first voltage misleads (``offline/start_soc.py``: a start
under load, or at rest with the voltage still relaxing). A gateway cannot wait 20 minutes
before it publishes, so the daemon starts at once from the first voltage (IR-corrected, the
observer converging) and keeps the samples it fed; when they span the window it makes the same
fit, and where one holds it builds a new bank from the fitted start, replays the kept samples
through it and carries on with that bank: from then on the daemon's estimates are those an
offline run of the same record gives. What was published during the window stays published;
the step at the swap is logged and counted (``start_refits``).

A configured ``soc0`` stays as it is: only the RC branches' voltages at the first sample are
fitted there, which a loaded start needs as much (``identify --soc0`` does the same). Only a
fresh start is refitted (a restore re-anchors from the voltage at restart:
``estimate/state.py``), and only while the kept samples stay within
``MAX_HEAD_CELL_SAMPLES`` (32 MB of voltages: 1,200 s of 96 cells at 30 Hz); a faster bus keeps
the first voltage's start, and says so.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field

from bmsid.estimate.rest_anchor import next_noise
from bmsid.estimate.start_fit import MAX_HEAD_CELL_SAMPLES, first_load_s, head_end_s
from bmsid.samples import SampleBlock

log = logging.getLogger(__name__)


@dataclass
class StartHead:
    """The samples a fresh bank was fed, until they span its start window (see the module doc;
    after a leading rest longer than half of ``WINDOW_S``, ``WINDOW_S`` from just before the
    load: ``start_fit.window_start``)."""

    #: the rest limit, A (|I| at most this is rest: the cell's soc_init.rest_current_C x Ah)
    rest_limit_A: float = 0.0
    blocks: list[SampleBlock] = field(default_factory=list)
    cell_samples: int = 0
    #: False once the window is complete or given up: nothing more is kept
    open: bool = True
    #: when the first load came, s (None: not yet)
    load_s: float | None = None
    #: the current sensor's noise so far (std A, the last current A): a bus's blocks are
    #: a few samples each, too few for their own estimate (``rest_anchor.next_noise``)
    noise_sd_A: float = 0.0
    i_prev_A: float = math.nan
    t_prev_s: float = math.nan

    def add(self, block: SampleBlock) -> SampleBlock | None:
        """Keep ``block``; the whole head once the kept samples span the window, else None."""
        if not self.open or not len(block):
            return None
        self.blocks.append(block)
        self.cell_samples += len(block) * block.n_cells
        if self.load_s is None:
            self.load_s = first_load_s(
                block.t_s, block.current_A, self.rest_limit_A, self.noise_sd_A
            )
            for t, i in zip(block.t_s.tolist(), block.current_A.tolist(), strict=True):
                self.noise_sd_A = next_noise(
                    self.noise_sd_A, i, self.i_prev_A, self.rest_limit_A, t - self.t_prev_s
                )
                self.i_prev_A, self.t_prev_s = i, t
        first, last = float(self.blocks[0].t_s[0]), float(block.t_s[-1])
        if last >= head_end_s(first, self.load_s, last):
            self.open = False
            head = SampleBlock.concat(self.blocks)
            self.blocks = []
            return head
        if self.cell_samples > MAX_HEAD_CELL_SAMPLES:
            log.warning(
                "start SOC not refitted: %d cell-samples in the first %.0f s are more than the "
                "%d kept for it (a fast bus, or a long rest before the load); SOC goes on from "
                "the first voltage and the observer",
                self.cell_samples, last - first, MAX_HEAD_CELL_SAMPLES,
            )  # fmt: skip
            self.open = False
            self.blocks = []
        return None
