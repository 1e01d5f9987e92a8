"""How many threads the linear algebra may use.

Every entry point runs BLAS on one thread unless DT_BLAS_THREADS says otherwise
(`limit_blas_threads`); the library's fits, cross-validations and predictions run inside
`blas_limited`, which restores the caller's setting on the way out.
"""
from __future__ import annotations

import contextlib
import functools
import os
import threading
from collections.abc import Callable

from dt_kernel.errors import ConfigError

# Why one thread: the twin's matrices are small (a DOE has ~200 distinct inputs; the effect
# regressors a few thousand rows by tens of columns) or factorised block by block (the sparse
# GP). OpenBLAS's threaded kernels synchronise at every block: on 2 cores they are slower than
# one thread even on an idle machine, and while another process holds a core they crawl
# (`dt diagnose` on 372 rows: 25 s with two threads, 6 s with one; a 186-input GP fit: 149 s
# instead of 0.5 s).
ENV = "DT_BLAS_THREADS"


def blas_threads() -> int:
    """The BLAS thread count to use: $DT_BLAS_THREADS, else 1.

    Returns
    -------
    int

    Raises
    ------
    ConfigError
        When the variable is not a whole number >= 1.
    """
    raw = os.environ.get(ENV, "1")
    try:
        n = int(raw)
    except ValueError:
        n = 0
    if n < 1:
        raise ConfigError("environment", ENV, raw, "a whole number >= 1")
    return n


def _load_blas() -> None:
    # threadpoolctl sees only the libraries already loaded: load numpy's and scipy's BLAS (scipy
    # bundles its own OpenBLAS) before looking.
    import numpy  # noqa: F401
    import scipy.linalg  # noqa: F401


def limit_blas_threads(n: int | None = None):
    """Limit BLAS to `n` threads for the rest of the process.

    Parameters
    ----------
    n : int, optional
        Thread count; default $DT_BLAS_THREADS, else 1.

    Returns
    -------
    threadpoolctl.threadpool_limits
        The limit object (it can be used to restore the previous setting).
    """
    _load_blas()
    from threadpoolctl import threadpool_limits  # installed with scikit-learn

    return threadpool_limits(n or blas_threads(), user_api="blas")


#: What the BLAS libraries (OpenBLAS, numpy's and scipy's own; MKL) read once, when they load.
LOAD_VARS = ("OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")  # BLAS only, as limit_blas_threads (user_api="blas")


def limit_blas_threads_when_loaded() -> None:
    """Limit BLAS to $DT_BLAS_THREADS (else 1) threads without loading it now: the `dt` entry
    point's way, so that `--help` or a bad argument answers before numpy and scipy are imported
    (seconds on a loaded machine). When neither is loaded yet the limit goes into the variables
    the libraries read as they load (LOAD_VARS, also inherited by child processes, which apply the
    same rule); when one already is, it is set as `limit_blas_threads` does.

    Raises
    ------
    ConfigError
        When $DT_BLAS_THREADS is not a whole number >= 1.
    """
    import sys

    n = blas_threads()
    if "numpy" in sys.modules or "scipy" in sys.modules:
        limit_blas_threads(n)
        return
    for var in LOAD_VARS:
        os.environ[var] = str(n)


@functools.lru_cache(maxsize=1)
def _blas_libraries() -> tuple[tuple[Callable[[], int | None], Callable[[int], object]], ...]:
    """(get, set) of the thread count of every loaded BLAS library, found once per process by
    threadpoolctl (finding them walks every loaded shared object: ~1 ms, too much per fit)."""
    _load_blas()
    from threadpoolctl import ThreadpoolController  # installed with scikit-learn

    # threadpoolctl >= 3.6 lets only the first thread that set a pthreads-OpenBLAS limit set it
    # again (silently ignoring the others): a fit in a worker thread would then run unlimited.
    # blas_limited serialises its own changes (depth count under a lock), so it uses the plain
    # setter where there is one.
    return tuple((lib.get_num_threads, getattr(lib, "_real_set_num_threads", lib.set_num_threads))
                 for lib in ThreadpoolController().select(user_api="blas").lib_controllers)


class _BlasLimited(contextlib.ContextDecorator):
    """`with blas_limited:` or `@blas_limited`: BLAS on at most $DT_BLAS_THREADS (default 1)
    threads inside, the caller's setting back on the way out.

    Re-entrant and shared by threads: the outermost entry sets the limit and the last exit
    restores it (the BLAS thread count is one setting per process), so a fit inside a
    cross-validation inside a diagnosis pays one lookup, not one per level. The limit never
    raises the caller's thread count."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._depth = 0
        self._restore: list[tuple[Callable[[int], object], int]] = []

    def __enter__(self) -> _BlasLimited:
        with self._lock:
            if self._depth == 0:
                n = blas_threads()
                restore = []
                for get, set_ in _blas_libraries():
                    current = get()
                    if current is not None and current > n:
                        set_(n)
                        restore.append((set_, current))
                self._restore = restore
            self._depth += 1
        return self

    def __exit__(self, *exc) -> None:
        with self._lock:
            self._depth -= 1
            if self._depth == 0:
                for set_, n in self._restore:
                    set_(n)
                self._restore = []


blas_limited = _BlasLimited()
