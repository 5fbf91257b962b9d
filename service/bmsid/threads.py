"""One BLAS thread per process (the imperative shell sets it; the engine only computes).

The engine's linear algebra is small: 5x5 RLS covariances, 7x7 window fits, and the SOC
observer's joint update of a pack (about 100x100 for 96 cells). OpenBLAS's threads do not pay
there, and on a busy machine they cost: a 96-cell fused bank ran 26,000-31,000 cell-samples/s
with OpenBLAS's default threads and 70,000-71,000 with one, each run alternated in one session on
this project's loaded 2-core VM (the observer's joint update took 18 ms a call instead of
~1). A process pool of several workers would also multiply the threads past the cores.

The compiled kernels' linear algebra (numba's ``np.linalg`` and ``@``) calls scipy's own
OpenBLAS, not numpy's, and a limit covers only the libraries loaded when it is set: scipy's is
loaded first. Before that, a 96-cell ``hy-affrls-lpso`` bank whose compiled observer update ran
on scipy's two threads took 102 ms a call instead of 1 on the loaded 2-core VM (16,600
cell-samples/s instead of 150,000).
"""

from __future__ import annotations


def one_blas_thread(*, compiled_kernels: bool = True) -> None:
    """Limit BLAS (OpenBLAS, MKL) to one thread in this process, from now on: numpy's, and
    with ``compiled_kernels`` scipy's (what the compiled kernels call), loaded here so that the
    limit covers it. A process that runs no estimator (the daemon beside its bank worker
    process) passes False: scipy's BLAS and its modules cost ~28 MB resident there."""
    if compiled_kernels:
        import scipy.linalg.cython_blas  # noqa: F401, PLC0415 (loads scipy's OpenBLAS)
    from threadpoolctl import threadpool_limits  # noqa: PLC0415 (loads the BLAS libraries)

    threadpool_limits(limits=1, user_api="blas")


def blas_threads() -> dict[str, int]:
    """The threads each loaded BLAS library may use (its path: threads), for the log."""
    from threadpoolctl import threadpool_info  # noqa: PLC0415

    return {
        i["filepath"]: int(i["num_threads"]) for i in threadpool_info() if i["user_api"] == "blas"
    }
