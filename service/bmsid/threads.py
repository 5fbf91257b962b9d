"""One BLAS thread per process (the imperative shell sets it; the engine only computes).

The engine's linear algebra is small: 5x5 RLS covariances, 7x7 window fits, and the SOC
observer's joint update of a pack (about 100x100 for 96 cells). OpenBLAS's threads do not pay
there, and on a busy machine they cost: a 96-cell fused bank ran 26,000-31,000 cell-samples/s
with OpenBLAS's default threads and 70,000-71,000 with one, each run alternated in one session on
this project's loaded 2-core VM (the observer's joint update took 18 ms a call instead of
~1). A process pool of several workers would also multiply the threads past the cores.
"""

from __future__ import annotations


def one_blas_thread() -> None:
    """Limit BLAS (OpenBLAS, MKL) to one thread in this process, from now on."""
    from threadpoolctl import threadpool_limits  # noqa: PLC0415 (loads the BLAS libraries)

    threadpool_limits(limits=1, user_api="blas")
