"""How many threads the linear algebra may use.

The twin's matrices are small (a DOE has ~200 distinct inputs; the effect regressors a few
thousand rows by tens of columns) or factorised block by block (the sparse GP). OpenBLAS's
threaded kernels synchronise at every block: on 2 cores they are slower than one thread even on
an idle machine, and while another process holds a core they crawl (`dt diagnose` on 372 rows:
25 s with two threads, 6 s with one; a 186-input GP fit: 149 s instead of 0.5 s). So every entry
point (the `dt` command line, the benchmarks, the test suite) runs BLAS on one thread unless
DT_BLAS_THREADS says otherwise.
"""
from __future__ import annotations

import os

from dt_kernel.errors import ConfigError

ENV = "DT_BLAS_THREADS"


def blas_threads() -> int:
    raw = os.environ.get(ENV, "1")
    try:
        n = int(raw)
    except ValueError:
        n = 0
    if n < 1:
        raise ConfigError("environment", ENV, raw, "a whole number >= 1")
    return n


def limit_blas_threads(n: int | None = None):
    """Limit BLAS to n threads (default: $DT_BLAS_THREADS, else 1) for the rest of the process."""
    # threadpoolctl limits only the libraries already loaded: load numpy's and scipy's BLAS
    # (scipy may bundle its own OpenBLAS) before setting the limit.
    import numpy  # noqa: F401
    import scipy.linalg  # noqa: F401
    from threadpoolctl import threadpool_limits  # installed with scikit-learn

    return threadpool_limits(n or blas_threads(), user_api="blas")
