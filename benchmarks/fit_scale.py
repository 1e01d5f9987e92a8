"""`python -m benchmarks.fit_scale [--json]`: the 3-axis GP on 12,000 distinct inputs (sparse
VFE/DTC posterior, hyperparameters from a seeded subset), and on 3,000 distinct inputs the sparse
model against the exact GP with the same hyperparameters (held-out RMSE ratio).

Keys: n_train, seconds, peak_rss_gb (whole process, measured right after the 12,000-row fit),
rmse_ratio_vs_exact (sparse / exact, held out, 3,000 rows)."""
from __future__ import annotations

import resource
import time

import numpy as np

from benchmarks._common import cli, emit
from benchmarks._data import scattered_dataset
from dt_runtime.gp import MultiOutputGP


def run(n_big: int = 12000, n_cmp: int = 3000, seed: int = 0) -> dict:
    X, Y = scattered_dataset(n_big, seed)
    t0 = time.perf_counter()
    MultiOutputGP(seed=seed, n_restarts=0).fit(X, Y)
    seconds = time.perf_counter() - t0
    peak_gb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024 ** 2  # KiB on Linux

    Xc, Yc = scattered_dataset(n_cmp, seed + 1)
    Xt, Yt = scattered_dataset(1000, seed + 2)
    kw = dict(seed=seed, n_restarts=0)
    exact = MultiOutputGP(**kw, sparse_threshold=n_cmp).fit(Xc, Yc)
    t0 = time.perf_counter()
    sparse = MultiOutputGP(**kw, sparse_threshold=n_cmp - 1).fit(Xc, Yc, thetas=exact.thetas_)
    t_sparse_cmp = time.perf_counter() - t0
    rmse = lambda m: float(np.sqrt(np.mean((m.predict(Xt) - Yt) ** 2)))
    return {"n_train": n_big, "seconds": seconds, "peak_rss_gb": peak_gb,
            "rmse_ratio_vs_exact": rmse(sparse) / rmse(exact), "n_compare": n_cmp,
            "exact_rmse_mm": rmse(exact) * 1e3, "sparse_rmse_mm": rmse(sparse) * 1e3,
            "sparse_posterior_s_at_compare": t_sparse_cmp,
            "n_inducing": sparse.n_inducing, "n_hyper": sparse.n_hyper}


def main() -> None:
    as_json = cli(__doc__)
    emit(run(), as_json, "GP fit at scale (3 outputs, distinct inputs)")


if __name__ == "__main__":
    main()
