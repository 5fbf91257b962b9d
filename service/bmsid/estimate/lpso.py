"""Particle swarm with the linearised inertia schedule (LPSO, Eq. 24-30), ask/tell style.

The swarm is driven one iteration at a time (``swarm_tell``), so a caller can amortise it over
many real-time ticks. Positions stay inside the box [lo, hi]: particles that hit a wall stop there
and lose the outward velocity (the common PSO defect of escaping the bounds is excluded).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

FloatArray = npt.NDArray[np.float64]


@dataclass(frozen=True)
class SwarmParams:
    """c1, c2 (Eq. 28), w_max, w_min, shape n (Eq. 29), velocity clamp as a fraction of width."""

    c1: float = 1.5
    c2: float = 1.5
    w_max: float = 0.9
    w_min: float = 0.4
    shape: float = 0.5
    vmax_frac: float = 0.25


@dataclass(frozen=True)
class Swarm:
    """Swarm state (Eq. 24-27): positions x, velocities v, personal and global bests."""

    x: FloatArray  # (P, D)
    v: FloatArray
    pbest: FloatArray
    pbest_f: FloatArray  # (P,)
    gbest: FloatArray  # (D,)
    gbest_f: float
    iteration: int
    n_iter: int
    lo: FloatArray
    hi: FloatArray

    @property
    def done(self) -> bool:
        return self.iteration >= self.n_iter


def inertia(iteration: int, n_iter: int, p: SwarmParams) -> float:
    """Eq. 29 with iter/(n iter_max): large early (explore), ``w_min`` late (exploit)."""
    return float((p.w_max - p.w_min) * np.exp(-((iteration / (p.shape * n_iter)) ** 2)) + p.w_min)


def swarm_init(
    lo: FloatArray,
    hi: FloatArray,
    n_particles: int,
    n_iter: int,
    rng: np.random.Generator,
    seeds: FloatArray | None = None,
    spread: float = 0.5,
) -> Swarm:
    """Start a swarm: the rows of ``seeds`` first, then half scattered around the first seed
    (normal, std ``spread``), the rest uniform in the box (global exploration)."""
    d = lo.shape[0]
    x = lo + (hi - lo) * rng.random((n_particles, d))
    k = 0
    if seeds is not None and seeds.size:
        s = np.atleast_2d(seeds)[:n_particles]
        k = s.shape[0]
        x[:k] = s
        n_local = (n_particles - k) // 2
        x[k : k + n_local] = s[0] + spread * rng.standard_normal((n_local, d))
    x = np.clip(x, lo, hi)
    v = np.zeros_like(x)
    return Swarm(
        x=x,
        v=v,
        pbest=x.copy(),
        pbest_f=np.full(n_particles, np.inf),
        gbest=x[0].copy(),
        gbest_f=float("inf"),
        iteration=0,
        n_iter=n_iter,
        lo=lo,
        hi=hi,
    )


def swarm_tell(s: Swarm, f: FloatArray, rng: np.random.Generator, p: SwarmParams) -> Swarm:
    """Record the fitness of the current positions, then move the particles (Eq. 28, 30)."""
    r1 = rng.random(s.x.shape)
    r2 = rng.random(s.x.shape)
    w = inertia(s.iteration, s.n_iter, p)
    x, v, pbest, pbest_f, gbest, gbest_f = tell(
        s.x, s.v, s.pbest, s.pbest_f, s.gbest, s.gbest_f, f, r1, r2, w, s.lo, s.hi, p
    )
    # built directly: dataclasses.replace costs as much again
    return Swarm(
        x=x, v=v, pbest=pbest, pbest_f=pbest_f, gbest=gbest, gbest_f=gbest_f,
        iteration=s.iteration + 1, n_iter=s.n_iter, lo=s.lo, hi=s.hi,
    )  # fmt: skip


def tell(
    x: FloatArray, v: FloatArray, pbest: FloatArray, pbest_f: FloatArray, gbest: FloatArray,
    gbest_f: float, f: FloatArray, r1: FloatArray, r2: FloatArray, w: float, lo: FloatArray,
    hi: FloatArray, p: SwarmParams,
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray, FloatArray, float]:  # fmt: skip
    """``swarm_tell`` on arrays, its random numbers r1, r2 (uniform [0, 1), shaped as x) and
    inertia ``w`` given: the new x, v, personal bests and their fitness, global best and its
    fitness. The reference of the compiled move of a bank's swarms (``swarm_kernel.py``)."""
    f = np.where(np.isfinite(f), f, np.inf)
    better = f < pbest_f
    pbest = np.where(better[:, None], x, pbest)
    pbest_f = np.where(better, f, pbest_f)
    j = int(np.argmin(pbest_f))
    if pbest_f[j] < gbest_f:
        gbest, gbest_f = pbest[j].copy(), float(pbest_f[j])
    v = w * v + p.c1 * r1 * (pbest - x) + p.c2 * r2 * (gbest - x)
    vmax = p.vmax_frac * (hi - lo)
    v = np.clip(v, -vmax, vmax)
    x = x + v
    hit = (x < lo) | (x > hi)
    x = np.clip(x, lo, hi)
    v = np.where(hit, 0.0, v)
    return x, v, pbest, pbest_f, gbest, gbest_f
