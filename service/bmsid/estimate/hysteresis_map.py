"""Piecewise-linear functions of SOC on a knot grid: the hysteresis half-gap M(z) per region.

Eq. 32's M(z) is a table from the OCV test; the SOC observer (``observer.py``) learns a
correction per knot, ``M(z) = M_table(z) + sum_k w_k(z) d_k`` with hat functions w_k, the table
its prior. The knots are the table's own and a 10 % grid, so the prior *is* the table and every
SOC region can move on its own. Pure numpy.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import numpy.typing as npt

FloatArray = npt.NDArray[np.float64]

#: Uniform knots (fractions of SOC) every map has besides the table's: ten SOC regions.
_GRID = np.linspace(0.0, 1.0, 11)


def map_knots(table_soc: FloatArray) -> FloatArray:
    """The table's knots (clipped to [0, 1]) and the 10 % grid points not within 1e-6 of one,
    sorted, knots closer than 1e-6 merged (no zero-width regions)."""
    table = np.unique(np.clip(np.asarray(table_soc, dtype=np.float64), 0.0, 1.0))
    grid = _GRID[np.abs(_GRID[:, None] - table[None, :]).min(axis=1) > 1e-6]
    k = np.sort(np.concatenate([table, grid]))
    return np.asarray(k[np.concatenate([[True], np.diff(k) > 1e-6])], dtype=np.float64)


def hat_matrix(knots: FloatArray, z: FloatArray) -> FloatArray:
    """W (len(z), K): the hat-function weights of each SOC (ends held), rows summing to 1."""
    zc = np.clip(np.asarray(z, dtype=np.float64), knots[0], knots[-1])
    j = np.clip(np.searchsorted(knots, zc, side="right") - 1, 0, knots.shape[0] - 2)
    f = (zc - knots[j]) / (knots[j + 1] - knots[j])
    w = np.zeros((zc.shape[0], knots.shape[0]))
    rows = np.arange(zc.shape[0])
    w[rows, j] = 1.0 - f
    w[rows, j + 1] += f
    return w


def map_rows(
    knots: FloatArray, zc: FloatArray, h: FloatArray, m_V: FloatArray, m_table_V: FloatArray,
    P: FloatArray, hz: FloatArray, anchor: npt.NDArray[np.bool_],
) -> tuple[FloatArray, npt.NDArray[np.bool_]]:  # fmt: skip
    """The cells' rows of H for the map, ``dv_c/dd_k = s h_c w_k(z_c)`` (V/V; s the published
    M over the table's, ``m_V / m_table_V``, 1 where the table is 0), and which cells teach it:
    anchored cells (the branches relaxed, the hysteresis not) whose SOC is known better than M
    there (``|dOCV/dz| std(z) <= std(M)``; a SOC error is an OCV error as well). The others take
    the map as consider states (``observer_ekf.joint_update``)."""
    n = zc.shape[0]
    scale = np.where(m_table_V > 0, m_V / np.maximum(m_table_V, 1e-12), 1.0)
    scale = np.where(np.isfinite(scale), scale, 1.0)
    W, var = hat_matrix(knots, zc), np.maximum(np.diag(P), 0.0)
    teach = anchor & (np.abs(hz) * np.sqrt(var[:n]) <= np.sqrt(W @ var[n + 1 : n + 1 + W.shape[1]]))
    return (scale * h)[:, None] * W, teach


def restore_covariance(
    P_prior: FloatArray, saved: dict[str, Any], n: int, knots: FloatArray
) -> tuple[FloatArray, bool]:
    """The observer's covariance from a checkpoint's ``saved`` state (its ``P``, ``knots``) for
    a filter of ``n`` cells, an offset, the map on ``knots`` and the hysteresis error; True when
    the checkpoint's map is on the same knots. Otherwise its SOC and offset block with
    ``P_prior``'s map block; a checkpoint from before the hysteresis error: ``P_prior``'s."""
    P_saved = np.asarray(saved["P"], dtype=np.float64)
    old = np.asarray(saved.get("knots", np.zeros(0)), dtype=np.float64)
    same = old.shape == knots.shape and np.allclose(old, knots)
    if same and P_saved.shape == P_prior.shape:
        return P_saved, True
    keep = n + 1 + knots.shape[0] if same else n + 1
    P = P_prior.copy()
    P[:keep, :keep] = P_saved[:keep, :keep]
    P[:keep, keep:] = P[keep:, :keep] = 0.0
    return P, same
