"""Tick assembly of a whole block in one compiled call (issue 12): ``ticks.py``'s bins, gaps,
time jumps and coulomb steps for every sample of a ``SampleBlock`` at once.

``TickAssembler.push`` is a few dozen Python operations a sample; ``update_block`` in compiled
mode assembles every tick of its block first with :data:`ASSEMBLE` (the same operations in the
same order per sample: the same bits), then runs the stages over the tick arrays. The
assembler's state (clocks, the open bin, the raw steps not yet in a tick, the counters) is
read from and written back to the ``TickAssembler``, so a block may end mid-bin, the next
sample may come through ``push``, and checkpoints are unchanged.

The excitation measure (the running moments of the tick current) is not in the kernel: it uses
numpy's ``exp`` and Python's ``** 2``, which a compiled loop would round differently in the last
bit; :func:`assemble` runs that short recursion per tick in Python, with ``ticks.py``'s own
cached gains.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from bmsid.estimate import jit
from bmsid.estimate.ticks import Tick, TickAssembler, _excitation_gain
from bmsid.samples import SampleBlock

FloatArray = npt.NDArray[np.float64]
BoolArray = npt.NDArray[np.bool_]
IntArray = npt.NDArray[np.int64]

#: Columns of the per-tick floats: time, mean current, held current, step, nominal period,
#: mean temperature, current RMS variation (filled by :func:`assemble`), first, new segment.
T, CUR, IP, DT, PERIOD, TEMP, STD, FIRST, NEWSEG, N_TF = 0, 1, 2, 3, 4, 5, 6, 7, 8, 9
#: Layout of the assembler's scalars ``sc``: has a raw time, t_raw, i_raw, t_tick, i_tick,
#: bin_i, bin_n, dt_nom, bin_T, bin_Tn.
HAS_RAW, T_RAW, I_RAW, T_TICK, I_TICK, BIN_I, BIN_N, DT_NOM, BIN_T, BIN_TN, N_SC = range(11)
#: The counters the kernel increments, in ``TickAssembler.counters`` order.
COUNTERS = ("samples", "ticks", "non_increasing_time", "time_jumps_back", "nan_current",
            "nan_voltage", "gaps")  # fmt: skip


def _assemble_source(
    t_s: FloatArray, cur: FloatArray, v: FloatArray, temp: FloatArray, sc: FloatArray,
    bin_v: FloatArray, bin_vn: IntArray, steps_in: FloatArray, counts: IntArray, gap_s: float,
    id_period_s: float,
) -> tuple[int, FloatArray, FloatArray, BoolArray, IntArray, FloatArray, int]:  # fmt: skip
    """``TickAssembler.push`` over every sample; ``sc``, ``bin_v``, ``bin_vn`` and ``counts``
    updated in place. Returns (ticks, floats (m, N_TF), voltages (m, n), ok (m, n), step
    offsets (m + 1), the raw steps (k, 2), the number of steps)."""
    m, n = v.shape
    tf = np.zeros((m, N_TF))
    vo = np.empty((m, n))
    oko = np.empty((m, n), dtype=np.bool_)
    off = np.zeros(m + 1, dtype=np.int64)
    steps = np.empty((steps_in.shape[0] + m, 2))
    ns = steps_in.shape[0]
    steps[:ns] = steps_in
    nt = 0
    good = np.empty(n, dtype=np.bool_)
    vz = np.empty(n)
    for s in range(m):
        t, i, tc = t_s[s], cur[s], temp[s]
        counts[0] += 1
        if not math.isfinite(t):
            counts[2] += 1
            continue
        if not math.isfinite(i):
            counts[4] += 1
            i = sc[I_RAW]
        n_bad = 0
        for c in range(n):
            good[c] = math.isfinite(v[s, c])
            vz[c] = v[s, c] if good[c] else 0.0
            n_bad += 0 if good[c] else 1
        counts[5] += n_bad
        emit, first, new_seg, dt_tick, i_tick = False, False, False, 0.0, i
        raw_v = True  # the tick's voltages: the sample's own (first, gap) or the bin's mean
        if sc[HAS_RAW] == 0.0:
            sc[HAS_RAW], sc[T_RAW], sc[I_RAW], sc[T_TICK], sc[I_TICK] = 1.0, t, i, t, i
            emit, first, new_seg = True, True, True
        else:
            dt = t - sc[T_RAW]
            if dt < -gap_s or dt > gap_s:
                if dt < -gap_s:
                    counts[3] += 1
                else:
                    dt_tick = t - sc[T_TICK]
                counts[6] += 1  # _gap: the bin cleared, the raw steps kept for this tick
                sc[BIN_I], sc[BIN_N], sc[BIN_T], sc[BIN_TN] = 0.0, 0.0, 0.0, 0.0
                bin_v[:] = 0.0
                bin_vn[:] = 0
                sc[T_RAW], sc[I_RAW], sc[I_TICK] = t, i, 0.0
                emit, new_seg = True, True
            elif dt <= 0:
                counts[2] += 1
                continue
            else:
                steps[ns, 0], steps[ns, 1] = sc[I_RAW], dt
                ns += 1
                sc[T_RAW], sc[I_RAW] = t, i
                sc[BIN_I] += i
                sc[BIN_N] += 1.0
                if not math.isnan(tc):
                    sc[BIN_T] += tc
                    sc[BIN_TN] += 1.0
                if t - sc[T_TICK] < id_period_s - 0.5 * dt:
                    for c in range(n):
                        bin_v[c] += vz[c]
                        bin_vn[c] += 1 if good[c] else 0
                    continue
                raw_v = False
                if sc[BIN_N] == 1.0 and n_bad == 0:
                    for c in range(n):
                        vo[nt, c] = vz[c] + 0.0
                        oko[nt, c] = good[c]
                else:
                    for c in range(n):
                        bin_v[c] += vz[c]
                        bin_vn[c] += 1 if good[c] else 0
                        has = bin_vn[c] > 0
                        oko[nt, c] = has
                        vo[nt, c] = bin_v[c] / max(bin_vn[c], 1) if has else np.nan
                        bin_v[c] = 0.0
                        bin_vn[c] = 0
                i_tick = sc[BIN_I] / sc[BIN_N]
                dt_tick = t - sc[T_TICK]
                tc = sc[BIN_T] / sc[BIN_TN] if sc[BIN_TN] != 0.0 else np.nan
                sc[BIN_I], sc[BIN_N], sc[BIN_T], sc[BIN_TN] = 0.0, 0.0, 0.0, 0.0
                emit = True
        if not emit:
            continue
        if raw_v:
            for c in range(n):
                vo[nt, c] = v[s, c]
                oko[nt, c] = good[c]
        counts[1] += 1  # _tick
        if 0 < dt_tick <= gap_s:
            dn = sc[DT_NOM]
            sc[DT_NOM] = dt_tick if dn == 0.0 else dn + 0.05 * (dt_tick - dn)
        tf[nt, T], tf[nt, CUR], tf[nt, IP], tf[nt, DT] = t, i_tick, sc[I_TICK], dt_tick
        tf[nt, PERIOD] = max(sc[DT_NOM], id_period_s)
        tf[nt, TEMP] = tc
        tf[nt, FIRST], tf[nt, NEWSEG] = 1.0 if first else 0.0, 1.0 if new_seg else 0.0
        off[nt + 1] = ns
        sc[T_TICK], sc[I_TICK] = t, i_tick
        nt += 1
    return nt, tf[:nt], vo[:nt], oko[:nt], off[: nt + 1], steps[:ns], ns


def _warm(kernel: Callable[..., Any]) -> object:
    for n in (1, 2):
        kernel(np.arange(3.0), np.ones(3), np.ones((3, n)), np.full(3, np.nan), np.zeros(N_SC),
               np.zeros(n), np.zeros(n, dtype=np.int64), np.zeros((1, 2)),
               np.zeros(len(COUNTERS), dtype=np.int64), 30.0, 1.0)  # fmt: skip
    return None


ASSEMBLE = jit.Kernel("tick assembly", _assemble_source, _assemble_source, _warm)


@dataclass
class TickArrays:
    """Every tick of a block: ``tf`` (n_ticks, N_TF) floats, ``v`` and ``ok`` (n_ticks, n), the
    raw (current, interval) steps of tick k in ``steps[off[k]:off[k + 1]]``."""

    tf: FloatArray
    v: FloatArray
    ok: BoolArray
    off: IntArray
    steps: FloatArray

    @property
    def n(self) -> int:
        return int(self.tf.shape[0])

    def tick(self, k: int) -> Tick:
        """Tick ``k`` as ``TickAssembler.push`` returns it (for the stages' per-tick path)."""
        f = self.tf[k].tolist()
        st = self.steps[self.off[k] : self.off[k + 1]].tolist()
        return Tick(
            t_s=f[T], current_A=f[CUR], i_prev_A=f[IP], dt_s=f[DT], period_s=f[PERIOD],
            v_V=self.v[k].copy(), ok=self.ok[k].copy(),
            coulomb_steps=tuple((a, b) for a, b in st), current_std_A=f[STD],
            temperature_C=f[TEMP], first=bool(f[FIRST]), new_segment=bool(f[NEWSEG]),
        )  # fmt: skip


def assemble(ta: TickAssembler, block: SampleBlock) -> TickArrays:
    """Every tick ``block`` completes, by :data:`ASSEMBLE` (the assembler's state, counters and
    excitation moments advanced as ``push`` per sample would)."""
    n = ta.n
    m = len(block)
    temp = (np.full(m, np.nan) if block.temperature_C is None
            else np.ascontiguousarray(block.temperature_C, dtype=np.float64))  # fmt: skip
    sc = np.zeros(N_SC)
    if ta.t_raw is not None:
        sc[HAS_RAW], sc[T_RAW] = 1.0, ta.t_raw
    sc[I_RAW], sc[T_TICK], sc[I_TICK], sc[BIN_I] = ta.i_raw, ta.t_tick, ta.i_tick, ta.bin_i
    sc[BIN_N], sc[DT_NOM], sc[BIN_T], sc[BIN_TN] = ta.bin_n, ta.dt_nom, ta.bin_T, ta.bin_Tn
    steps_in = np.array(ta._steps, dtype=np.float64).reshape(-1, 2)
    counts = np.zeros(len(COUNTERS), dtype=np.int64)
    bin_v = np.ascontiguousarray(ta.bin_v, dtype=np.float64)
    bin_vn = np.ascontiguousarray(ta.bin_vn, dtype=np.int64)
    tun = ta.tuning
    nt, tf, v, ok, off, steps, ns = ASSEMBLE.impl(
        np.ascontiguousarray(block.t_s, dtype=np.float64),
        np.ascontiguousarray(block.current_A, dtype=np.float64),
        np.ascontiguousarray(block.cell_voltages_V, dtype=np.float64).reshape(m, n), temp, sc,
        bin_v, bin_vn, steps_in, counts, float(tun.gap_s), float(tun.id_period_s),
    )  # fmt: skip
    for name, c in zip(COUNTERS, counts.tolist(), strict=True):
        ta.counters[name] += c
    ta.t_raw = float(sc[T_RAW]) if sc[HAS_RAW] else None
    ta.i_raw, ta.t_tick, ta.i_tick = float(sc[I_RAW]), float(sc[T_TICK]), float(sc[I_TICK])
    ta.bin_i, ta.bin_n, ta.dt_nom = float(sc[BIN_I]), int(sc[BIN_N]), float(sc[DT_NOM])
    ta.bin_T, ta.bin_Tn = float(sc[BIN_T]), int(sc[BIN_TN])
    ta.bin_v, ta.bin_vn = bin_v, bin_vn
    ta._steps = [(a, b) for a, b in steps[off[nt] : ns].tolist()]
    # the excitation measure: TickAssembler._tick's moments, tick by tick in Python floats
    window, i_mean, i_var = tun.excitation_window_s, ta.i_mean, ta.i_var
    std = [0.0] * nt
    for k, (i, dt) in enumerate(zip(tf[:, CUR].tolist(), tf[:, DT].tolist(), strict=True)):
        g = _excitation_gain(dt, window) if dt > 0 else 0.0
        i_mean += g * (i - i_mean)
        i_var += g * ((i - i_mean) ** 2 - i_var)
        std[k] = math.sqrt(i_var) if i_var >= 0 else math.nan
    ta.i_mean, ta.i_var = i_mean, i_var
    tf[:, STD] = std
    return TickArrays(tf, v, ok, off, steps)
