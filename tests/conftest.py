"""Suite-wide setup: BLAS on one thread, as the `dt` command line runs (dt_runtime.threads)."""
from dt_runtime.threads import limit_blas_threads

limit_blas_threads()
