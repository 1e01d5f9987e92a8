"""Suite-wide setup: BLAS on one thread, as the `dt` command line runs (dt_runtime.common.threads)."""
from dt_runtime.common.threads import limit_blas_threads

limit_blas_threads()
