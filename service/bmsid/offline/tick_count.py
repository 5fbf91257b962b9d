"""How many ticks a bank will make of a record, from its sample times alone (the streamed run's
first pass, :func:`bmsid.offline.identify.scan_record`).

Whether a sample completes a tick depends only on the time base: the bins of ``id_period_s``,
gaps, time jumps back and dropped non-increasing or non-finite times
(``estimate/ticks.TickAssembler.push``); currents, voltages and the plausibility gates (which
only blank values) never decide it. So the count needs neither the assembler's arrays nor the
gates: this loop over plain floats is the assembler's clock alone (a property test holds the
two equal on random time bases). Pushing every sample through the assembler took 3.4 s of a
250,000-sample ``identify``; this takes a few per cent of it.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from bmsid.estimate.tuning import EstimatorTuning

FloatArray = npt.NDArray[np.float64]


@dataclass
class TickClock:
    """The assembler's raw and tick clocks (s): ``push_times`` counts the ticks of more times."""

    id_period_s: float
    gap_s: float
    t_raw: float | None = None
    t_tick: float = 0.0
    n_samples: int = 0
    n_ticks: int = 0
    t_first_s: float = math.nan
    t_last_s: float = math.nan

    @classmethod
    def for_tuning(cls, tuning: EstimatorTuning | None) -> TickClock:
        tun = tuning or EstimatorTuning()
        return cls(tun.id_period_s, tun.gap_s)

    def push_times(self, t_s: FloatArray) -> None:
        """Advance over the sample times ``t_s`` (s), as ``TickAssembler.push`` would."""
        period, gap = self.id_period_s, self.gap_s
        t_raw, t_tick, k = self.t_raw, self.t_tick, 0
        t_first, t_last = self.t_first_s, self.t_last_s
        for t in t_s.tolist():
            if not math.isfinite(t):
                continue
            if t_raw is not None:
                dt = t - t_raw
                if -gap <= dt <= gap:  # not a gap nor a jump back
                    if dt <= 0:
                        continue  # a non-increasing time: dropped
                    t_raw = t
                    if t - t_tick < period - 0.5 * dt:
                        continue  # the bin is not complete yet
            t_raw = t_tick = t  # a tick: the first sample, a gap, a jump back, a full bin
            if self.n_ticks + k == 0:
                t_first = t
            t_last = t
            k += 1
        self.t_raw, self.t_tick = t_raw, t_tick
        self.n_samples += int(t_s.shape[0])
        self.n_ticks += k
        self.t_first_s, self.t_last_s = t_first, t_last


def count_tick_times(times: Iterable[FloatArray], tuning: EstimatorTuning | None) -> TickClock:
    """The clock after every block of sample times in ``times`` (s)."""
    clock = TickClock.for_tuning(tuning)
    for t in times:
        clock.push_times(t)
    return clock
