"""One BLAS thread per process (``bmsid/threads.py``): numpy's and scipy's OpenBLAS, the one the
compiled kernels' linear algebra calls (a 96-cell bank's observer update on scipy's two threads
took 102 ms a call instead of 1 on a loaded 2-core machine)."""

from __future__ import annotations

import os
import subprocess
import sys


def test_every_blas_library_runs_one_thread_after_one_blas_thread() -> None:
    """In a fresh process (nothing loaded before): scipy's BLAS is loaded and limited too."""
    code = (
        "import sys\n"
        "from bmsid.threads import blas_threads, one_blas_thread\n"
        "one_blas_thread()\n"
        "assert 'scipy.linalg.cython_blas' in sys.modules\n"
        "blas = blas_threads()\n"
        "assert blas and set(blas.values()) == {1}, blas\n"
    )
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(sys.path)}
    subprocess.run([sys.executable, "-c", code], check=True, timeout=120, env=env)
