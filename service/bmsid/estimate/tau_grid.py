"""Least squares over a grid of RC time constants (the start fit's inner solve,
``start_fit.py``): Eq. 9 over a window is linear in (R0, R1, R2, one extra column, the branch
voltages at the start) for fixed (tau1, tau2), so each pair of a log-spaced grid is one linear
solve, the best physical one kept; a finer grid between its neighbours refines it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

FloatArray = npt.NDArray[np.float64]

#: Points of each time constant's finer grid between the best point's neighbours (odd: the
#: best point itself is one of them).
ZOOM_POINTS = 9
#: Bytes of least-squares columns solved at once (the time-constant pairs in chunks).
SOLVE_BYTES = 16_000_000
#: (RMSE V, the extra column's coefficient, c1 V, c2 V, j1, j2) of a grid's best solve
Fit = tuple[float, float, float, float, int, int]


def refined_fit(
    y: FloatArray, minus_i: FloatArray, col: FloatArray | None, grid: TauGrid,
    ok: npt.NDArray[np.bool_], decays: bool = True,
) -> Fit | None:  # fmt: skip
    """``best_fit`` over the grid at the samples ``ok``, then over a finer one between its
    best point's neighbours."""
    fit = best_fit(y, minus_i, col, grid.at(ok), decays)
    if fit is None:
        return None
    return min(fit, best_fit(y, minus_i, col, grid.around(fit[4], fit[5]).at(ok), decays) or fit)


def branch_states(i_held: FloatArray, dt: FloatArray, taus: FloatArray) -> FloatArray:
    """Unit-gain ZOH branch states (Eq. 8) for each time constant: (taus, samples), from 0.
    Evenly sampled (the usual record): one IIR filter per time constant (a rested start's
    refined grids made this loop most of a 96-cell pack's start fit)."""
    if dt.shape[0] and np.all(dt == dt[0]):
        # here, not at the top: the daemon's own process imports start_fit (its WINDOW_S)
        # and keeps scipy out
        from scipy.signal import lfilter  # noqa: PLC0415

        u = np.append(i_held, 0.0)  # x_(k+1) = a x_k + (1 - a) i_k as y_n of lfilter
        return np.stack([lfilter([0.0, 1.0 - a], [1.0, -a], u) for a in np.exp(-dt[0] / taus)])
    a = np.exp(-dt[None, :] / taus[:, None])
    x = np.zeros((taus.shape[0], dt.shape[0] + 1))
    for k in range(dt.shape[0]):
        x[:, k + 1] = a[:, k] * x[:, k] + (1.0 - a[:, k]) * i_held[k]
    return x


@dataclass(frozen=True)
class TauGrid:
    """A grid of time constants (s) and the branch columns over the window: unit-gain ZOH
    states ``x`` (taus, samples) and start decays ``d``; ``pairs`` keeps tau2 >= ratio tau1;
    ``window`` is what it was built from (a finer grid is built from it too)."""

    tau1: FloatArray
    tau2: FloatArray
    x1: FloatArray
    x2: FloatArray
    d1: FloatArray
    d2: FloatArray
    pairs: npt.NDArray[np.bool_]
    window: _Window

    @classmethod
    def of(
        cls, tau1: FloatArray, tau2: FloatArray, i_held: FloatArray, dt: FloatArray,
        t: FloatArray, ratio: float,
    ) -> TauGrid:  # fmt: skip
        since = (t - t[0])[None, :]
        return cls(
            tau1, tau2, branch_states(i_held, dt, tau1), branch_states(i_held, dt, tau2),
            np.exp(-since / tau1[:, None]), np.exp(-since / tau2[:, None]),
            tau2[None, :] >= ratio * tau1[:, None], _Window(i_held, dt, t, ratio),
        )  # fmt: skip

    def at(self, ok: npt.NDArray[np.bool_]) -> TauGrid:
        """The columns at the samples ``ok``."""
        return TauGrid(self.tau1, self.tau2, self.x1[:, ok], self.x2[:, ok], self.d1[:, ok],
                     self.d2[:, ok], self.pairs, self.window)  # fmt: skip

    def around(self, j1: int, j2: int) -> TauGrid:
        """A finer grid between the neighbours of the point (j1, j2): on the paper cell the
        coarse grid's step let a rested start's h0 take up its misfit (-0.5 for 0). Not for
        the loaded starts: entered mid-DST at 1,500 s it split the branches' 27.5 mV as
        23.8 (the coarse grid: within 2 mV)."""

        def between(tau: FloatArray, j: int) -> FloatArray:
            return np.geomspace(tau[max(j - 1, 0)], tau[min(j + 1, tau.shape[0] - 1)], ZOOM_POINTS)

        w = self.window
        return TauGrid.of(between(self.tau1, j1), between(self.tau2, j2), w.i_held, w.dt, w.t,
                          w.ratio)  # fmt: skip


@dataclass(frozen=True)
class _Window:
    """What a grid's columns come from: the held current (A), steps (s) and times (s) of the
    window, and the least tau2 / tau1."""

    i_held: FloatArray
    dt: FloatArray
    t: FloatArray
    ratio: float


def best_fit(
    y: FloatArray, minus_i: FloatArray, col: FloatArray | None, g: TauGrid, decays: bool = True
) -> Fit | None:
    """(RMSE V, the extra column's coefficient, c1 V, c2 V, j1, j2) of the best physical (R0, R1,
    R2 > 0) solve over the grid's ``pairs``; ``col`` is dz's (SOC) or h0's, None where SOC is
    known (coefficient 0, not fitted); without ``decays`` the branches start empty (c 0)."""
    j1, j2 = np.nonzero(g.pairs)
    n_p, n = j1.shape[0], y.shape[0]
    # pairs at once, in chunks of at most SOLVE_BYTES of columns (a 100 Hz record's window:
    # 120,000 samples, 29 MB a pair)
    step = max(1, SOLVE_BYTES // (8 * n * (6 if decays else 4)))
    parts = [_solve_pairs(y, minus_i, col, g, j1[a : a + step], j2[a : a + step], decays)
             for a in range(0, n_p, step)]  # fmt: skip
    th = np.concatenate([p[0] for p in parts])
    rmse = np.concatenate([p[1] for p in parts])
    ok = (th[:, 0] > 0) & (th[:, 1] > 0) & (th[:, 2] > 0) & np.isfinite(th).all(axis=1)
    ok &= np.isfinite(rmse)
    if not ok.any():
        return None
    b = int(np.flatnonzero(ok)[np.argmin(rmse[ok])])  # the first of equal ones, as in pair order
    coef = 0.0 if col is None else float(th[b, 3])
    c1, c2 = (float(th[b, -2]), float(th[b, -1])) if decays else (0.0, 0.0)
    return float(rmse[b]), coef, c1, c2, int(j1[b]), int(j2[b])


def _solve_pairs(
    y: FloatArray, minus_i: FloatArray, col: FloatArray | None, g: TauGrid,
    j1: npt.NDArray[np.intp], j2: npt.NDArray[np.intp], decays: bool,
) -> tuple[FloatArray, FloatArray]:  # fmt: skip
    """Each pair's least-squares coefficients (pairs, columns) and RMSE (V): one batched QR."""
    n_p, n = j1.shape[0], y.shape[0]
    cols = [np.broadcast_to(minus_i, (n_p, n)), -g.x1[j1], -g.x2[j2]]
    cols += [] if col is None else [np.broadcast_to(col, (n_p, n))]
    cols += [g.d1[j1], g.d2[j2]] if decays else []
    A = np.stack(cols, axis=2)  # (pairs, samples, columns)
    try:
        q, r = np.linalg.qr(A)
        th = np.linalg.solve(r, np.einsum("pnk,n->pk", q, y)[..., None])[..., 0]
    except np.linalg.LinAlgError:  # a pair's columns dependent: each by the minimum-norm solve
        th = np.stack([np.linalg.lstsq(a, y, rcond=None)[0] for a in A])
    with np.errstate(all="ignore"):  # a near-singular pair's inf: not physical, dropped after
        rmse = np.sqrt(np.mean((y - np.einsum("pnk,pk->pn", A, th)) ** 2, axis=1))
    return th, rmse
