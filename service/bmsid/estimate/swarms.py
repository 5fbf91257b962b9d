"""The swarm side of the fusion: the window of recent ticks and when each cell's swarm runs.

Each cell gets an LPSO swarm (``estimate/lpso.py``) every ``swarm_period_s``, staggered across
the bank by its cell index so few cells run at once; a running swarm evaluates
``fits_per_update`` particles per tick (each one a variable-projection window fit,
``estimate/varpro.py``), so its cost is spread over many ticks. The fusion stage decides what a
fit costs and what a finished swarm changes; this module buffers, schedules and holds the
running swarms (as arrays: ``swarm_kernel.py`` evaluates and moves them all in one call).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import numpy.typing as npt

from bmsid.estimate import lpso
from bmsid.estimate.varpro import Window
from bmsid.model.ecm import rc_decay

FloatArray = npt.NDArray[np.float64]
BoolArray = npt.NDArray[np.bool_]

#: The swarm events (a swarm due or ending) of the fused loop's ticks, by the key the loop is
#: given (``block_run`` registers the stage's around each call): (t s, period s, current std A,
#: the window buffer's head and count) -> when the next swarm is due, s.
LOOP_EVENTS: dict[int, Callable[[float, float, float, npt.NDArray[np.int64]], float]] = {}


def loop_events(key: int, t_s: float, period_s: float, std_A: float, head_count: Any) -> float:
    """A tick's swarm events, called by the fused loop (compiled) in object mode."""
    return LOOP_EVENTS[key](t_s, period_s, std_A, head_count)


@dataclass
class RunningSwarms:
    """The running swarms of a bank, one row per cell (a structure of arrays: one compiled call
    a tick evaluates and moves them all, ``swarm_kernel.py``).

    Per cell: the swarm (``lpso.Swarm``: positions x, ln tau (P, 2), velocities, personal and
    global bests), the fitness of its current positions (``done_fits`` of them evaluated), the
    window snapshot it fits (rows current A, y V, h M V, weights; ``win_len`` ticks of period
    ``dt_s``), the poles of its current positions, and the random numbers of every move and the
    inertia of every iteration, drawn at the start from the swarm's own generator in the order
    ``lpso.swarm_tell`` draws them (so a move needs no generator).
    """

    n_cells: int
    n_particles: int
    n_iter_max: int
    window_size: int
    active: BoolArray = field(init=False)

    def __post_init__(self) -> None:
        n, p, it, d = self.n_cells, self.n_particles, self.n_iter_max, 2
        self.active = np.zeros(n, dtype=bool)
        self.x, self.v, self.pbest = (np.zeros((n, p, d)) for _ in range(3))
        self.pbest_f, self.fitness = np.zeros((n, p)), np.zeros((n, p))
        self.gbest, self.gbest_f = np.zeros((n, d)), np.full(n, np.inf)
        self.lo, self.hi = np.zeros((n, d)), np.zeros((n, d))
        self.iteration, self.n_iter = np.zeros(n, dtype=np.int64), np.zeros(n, dtype=np.int64)
        self.done_fits = np.zeros(n, dtype=np.int64)
        self.rand = np.zeros((n, it, 2, p, d))  # per iteration r1, r2 of Eq. 28
        self.inertia = np.zeros((n, it))
        self.dt_s = np.ones(n)
        # the poles of the current positions: a = exp(-dt / tau) of the smaller and larger tau
        self.a1, self.a2 = np.zeros((n, p)), np.zeros((n, p))
        self.t_lo, self.t_hi = np.ones((n, p)), np.ones((n, p))
        self.win = np.zeros((n, 4, self.window_size))
        self.win_len = np.zeros(n, dtype=np.int64)
        # a swarm run to its end at its start (FusionStage.ahead): the ticks it still takes
        # (its result is applied at the tick its last move would have come); 0 where stepped
        self.left = np.zeros(n, dtype=np.int64)

    def start(
        self, c: int, sw: lpso.Swarm, rng: np.random.Generator, p: lpso.SwarmParams,
        window: Window, weights: FloatArray,
    ) -> None:  # fmt: skip
        """Cell ``c`` runs the new swarm ``sw`` (drawn from ``rng``) over ``window``."""
        self.x[c], self.v[c], self.pbest[c], self.pbest_f[c] = sw.x, sw.v, sw.pbest, sw.pbest_f
        self.gbest[c], self.gbest_f[c] = sw.gbest, sw.gbest_f
        self.lo[c], self.hi[c] = sw.lo, sw.hi
        self.iteration[c], self.n_iter[c], self.done_fits[c] = sw.iteration, sw.n_iter, 0
        # what swarm_tell draws, move after move: r1 then r2, each shaped as x
        self.rand[c, : sw.n_iter] = rng.random((sw.n_iter, 2, *sw.x.shape))
        self.inertia[c, : sw.n_iter] = [lpso.inertia(k, sw.n_iter, p) for k in range(sw.n_iter)]
        n_w = window.current_A.shape[0]
        self.win[c, :, :n_w] = window.current_A, window.y_V, window.hm_V, weights
        self.win_len[c], self.dt_s[c] = n_w, window.dt_s
        self.active[c], self.left[c] = True, 0
        self.refresh_poles(np.array([c]))

    def refresh_poles(self, cells: npt.NDArray[np.intp]) -> None:
        """The poles of the cells' current positions (numpy's exp: the compiled one differs
        from it in the last bit for a few percent of arguments)."""
        if cells.shape[0] == 1:  # one cell (a swarm run ahead): its rows, no fancy indexing
            c = int(cells[0])
            taus1 = np.exp(self.x[c])
            lo, hi = self.t_lo[c], self.t_hi[c]
            np.minimum(taus1[:, 0], taus1[:, 1], out=lo)
            np.maximum(taus1[:, 0], taus1[:, 1], out=hi)
            np.exp(-self.dt_s[c] / lo, out=self.a1[c])  # rc_decay's operations
            np.exp(-self.dt_s[c] / hi, out=self.a2[c])
            return
        taus = np.exp(self.x[cells])
        t_lo = np.minimum(taus[:, :, 0], taus[:, :, 1])
        t_hi = np.maximum(taus[:, :, 0], taus[:, :, 1])
        dt = self.dt_s[cells][:, None]
        self.t_lo[cells], self.t_hi[cells] = t_lo, t_hi
        self.a1[cells], self.a2[cells] = rc_decay(dt, t_lo), rc_decay(dt, t_hi)


@dataclass
class WindowBuffer:
    """Ring buffer of identification ticks (shared current A; per-cell V - OCV, h M, valid;
    the pack's 1 / temperature, 1/K, and the tick's time, s, written by ticks with a
    temperature only: the compiled loop pushes only ticks without one and leaves both as they
    were, a slot's time then tells that they are a tick's ``size`` pushes older)."""

    size: int
    n_cells: int
    current_A: FloatArray = field(init=False)
    y_V: FloatArray = field(init=False)
    hm_V: FloatArray = field(init=False)
    valid: BoolArray = field(init=False)
    inv_T_K: FloatArray = field(init=False)
    t_s: FloatArray = field(init=False)
    head: int = 0
    count: int = 0

    def __post_init__(self) -> None:
        self.current_A = np.zeros(self.size)
        self.y_V = np.zeros((self.n_cells, self.size))
        self.hm_V = np.zeros((self.n_cells, self.size))
        self.valid = np.zeros((self.n_cells, self.size), dtype=bool)
        self.inv_T_K = np.full(self.size, math.nan)
        self.t_s = np.full(self.size, math.nan)

    def push(
        self, i: float, y: FloatArray, hm: FloatArray, valid: BoolArray,
        inv_T_K: float = math.nan, t_s: float = math.nan,
    ) -> None:  # fmt: skip
        j = self.head
        self.current_A[j] = i
        self.y_V[:, j] = y
        self.hm_V[:, j] = hm
        self.valid[:, j] = valid
        if not math.isnan(inv_T_K):  # as the compiled loop: a tick without one writes none
            self.inv_T_K[j], self.t_s[j] = inv_T_K, t_s
        self.head = (j + 1) % self.size
        self.count = min(self.count + 1, self.size)

    def inv_temperature(self, dt_s: float, window_s: float, t_now_s: float) -> FloatArray:
        """1 / temperature (1/K) of the ticks of :meth:`window`, NaN where unknown: a slot's
        temperature counts where its time is its place's (a slot refilled by a tick without
        one kept the time of a tick at least ``size`` pushes older, or of one before a jump of
        the clock)."""
        idx = self.order()[-(int(window_s / dt_s) + 1) :]
        age = (idx.shape[0] - 1 - np.arange(idx.shape[0])) * dt_s
        fresh = np.abs(self.t_s[idx] - (t_now_s - age)) < 0.5 * self.size * dt_s
        return np.where(fresh, self.inv_T_K[idx], math.nan)

    def order(self) -> npt.NDArray[np.intp]:
        """Indices of the buffered ticks, oldest first."""
        start = (self.head - self.count) % self.size
        return (start + np.arange(self.count)) % self.size

    def clear(self) -> None:
        self.count = 0

    def n_valid(self, c: int, last: float = math.inf) -> int:
        """Buffered ticks with a valid (learnable) voltage of cell ``c`` among the ``last``
        pushed (all held ones by default, or where more were pushed than are held)."""
        order = self.order()
        if last < order.shape[0]:
            order = order[order.shape[0] - int(last) :]
        return int(self.valid[c, order].sum())

    def n_steps(self, window_s: float, dt_s: float, min_step_A: float) -> int:
        """Current changes of at least ``min_step_A`` within the last ``window_s``."""
        idx = self.order()[-(int(window_s / dt_s) + 1) :]
        return int((np.abs(np.diff(self.current_A[idx])) >= min_step_A).sum())

    def window(
        self, c: int, dt_s: float, window_s: float, use_hysteresis: bool, use_offset: bool
    ) -> tuple[Window, FloatArray]:
        """Cell ``c``'s last ``window_s`` of ticks (period ``dt_s``) and its validity weights."""
        idx = self.order()[-(int(window_s / dt_s) + 1) :]
        valid = self.valid[c][idx]  # (a row, then a 1-D take: faster than [c, idx])
        w = Window(
            current_A=self.current_A[idx],  # (fancy indexing copies)
            y_V=np.where(valid, self.y_V[c][idx], 0.0),
            hm_V=self.hm_V[c][idx],
            dt_s=dt_s,
            use_hysteresis=use_hysteresis,
            use_offset=use_offset,
        )
        return w, valid.astype(np.float64)

    def state_dict(self) -> dict[str, Any]:
        return {
            "current_A": self.current_A.copy(), "y_V": self.y_V.copy(), "hm_V": self.hm_V.copy(),
            "valid": self.valid.copy(), "head": self.head, "count": self.count,
            "inv_T_K": self.inv_T_K.copy(), "t_s": self.t_s.copy(),
        }  # fmt: skip

    def load_state_dict(self, st: dict[str, Any]) -> bool:
        """Restore a buffer of the same size; False (buffer left empty) for another size."""
        if np.shape(st["y_V"]) != self.y_V.shape:
            self.clear()
            return False
        self.current_A[:] = st["current_A"]
        self.y_V[:] = st["y_V"]
        self.hm_V[:] = st["hm_V"]
        self.valid[:] = st["valid"]
        self.inv_T_K[:] = st.get("inv_T_K", math.nan)  # (checkpoints before: unknown)
        self.t_s[:] = st.get("t_s", math.nan)
        self.head = int(st["head"])
        self.count = int(st["count"])
        return True


class SwarmSchedule:
    """When each cell's next swarm is due, and the swarms running now.

    Args:
        n_cells: cells of the bank.
        phase: each cell's offset in [0, 1) of ``period_s`` (staggering across the bank).
        period_s: a swarm starts this often per cell.
        min_window_s: the first swarm of a segment waits for this much data.
        running: the bank's swarms (a cell whose swarm is active is not due).
    """

    def __init__(
        self, n_cells: int, phase: FloatArray, period_s: float, min_window_s: float,
        running: RunningSwarms,
    ) -> None:  # fmt: skip
        self.n = n_cells
        self.phase = phase
        self.period_s = period_s
        self.min_window_s = min_window_s
        self._first_due_s = 0.0
        self.next_swarm = np.zeros(n_cells)
        self.swarm_count = np.zeros(n_cells, dtype=np.int64)
        #: when each cell's last swarm started in this segment, s (NaN: none yet)
        self.last_start_s = np.full(n_cells, math.nan)
        self.running = running

    @property
    def next_swarm(self) -> FloatArray:
        """When each cell's next swarm is due, s (assigned whole: the earliest is kept)."""
        return self._next_swarm

    @next_swarm.setter
    def next_swarm(self, t_s: FloatArray) -> None:
        self._next_swarm = t_s
        # the earliest, which most ticks are before: one float compare a tick, not an array min
        self._first_due_s = float(t_s.min()) if t_s.size else math.inf

    def new_segment(self, t_s: float) -> None:
        """Histories restart at ``t_s``: running swarms end, the first is due after min_window."""
        self.running.active[:] = False
        self.next_swarm = t_s + self.min_window_s + self.phase * self.period_s
        self.last_start_s[:] = math.nan

    def has_data(self, c: int, t_s: float, buffer: WindowBuffer, dt_s: float) -> bool:
        """Whether cell ``c``'s due swarm starts at ``t_s`` (noted when it does): its window
        holds ``min_window_s`` of learnable ticks (period ``dt_s``: ticks in the OCV knees,
        without a voltage or while SOC is too uncertain to learn from weigh nothing), as much
        of them new since its last swarm. Refitting the same ticks only wanders where they say
        nothing: with the observer's learn gate shut after a rested start, swarms refitted the
        first 360 s of a DST every 600 s and tau2 went 2,090 -> 7,207 s (truth 600), 28 mV."""
        last = self.last_start_s[c]
        since = math.inf if math.isnan(last) else round((t_s - last) / dt_s)
        # the new ticks are among the held ones: enough new is enough in all
        if buffer.n_valid(c, since) * dt_s < self.min_window_s:
            return False
        self.last_start_s[c] = t_s
        return True

    def due(self, t_s: float) -> list[int]:
        """Cells whose swarm is due at ``t_s`` (and not running); their next time moves on by
        whole periods (a long stall does not queue up missed swarms)."""
        if t_s < self._first_due_s:
            return []
        idle = ~self.running.active
        nxt = self._next_swarm
        due = np.flatnonzero((t_s >= nxt) & idle)
        for c in due:
            nxt[c] += self.period_s * max(1.0, np.ceil((t_s - nxt[c]) / self.period_s))
        self.next_swarm = nxt  # the earliest moved on
        return [int(c) for c in due]

    def n_running(self) -> int:
        return int(np.count_nonzero(self.running.active))

    def state_dict(self) -> dict[str, Any]:
        """Running swarms are not saved: after a restore they start again at their next time."""
        return {
            "next_swarm": self.next_swarm.copy(), "swarm_count": self.swarm_count.copy(),
            "last_start_s": self.last_start_s.copy(),
        }  # fmt: skip

    def load_state_dict(self, st: dict[str, Any]) -> None:
        for k in ("next_swarm", "swarm_count", "last_start_s"):
            if k not in st:  # from before ``last_start_s``: none yet
                continue
            cur = getattr(self, k)
            arr = np.asarray(st[k], dtype=cur.dtype)
            if arr.shape != cur.shape:
                raise ValueError(f"checkpoint field swarms/{k} has shape {arr.shape}")
            setattr(self, k, arr.copy())
        self.running.active[:] = False

    def reset(self, mask: BoolArray) -> None:
        """The masked cells drop a running swarm (their next one starts on schedule)."""
        self.running.active[mask] = False
