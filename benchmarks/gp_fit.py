"""`python -m benchmarks.gp_fit [--json]`: fitting the 3-axis error map on the DOE (1,674 rows),
ours (exact replicate collapse) vs scikit-learn's GaussianProcessRegressor, same data and run.

Keys: n_train, ours_s, sklearn_s, speedup, rmse_ratio (ours / sklearn held-out RMSE); also the
CPU seconds of each fit (ours_cpu_s, sklearn_cpu_s, cpu_speedup: wall time on a shared machine
counts the other jobs)."""
from __future__ import annotations

import time

import numpy as np

from benchmarks._common import cli, emit, fit_sklearn
from benchmarks._data import doe_dataset, error_field, validation_dataset
from dt_runtime.models.gp import MultiOutputGP


def run(seed: int = 0) -> dict:
    X, Y = doe_dataset(seed)
    Xv, Yv = validation_dataset(seed + 1)
    t0, c0 = time.perf_counter(), time.process_time()
    ours = MultiOutputGP(seed=seed, n_restarts=0).fit(X, Y)
    t_ours, c_ours = time.perf_counter() - t0, time.process_time() - c0
    t0, c0 = time.perf_counter(), time.process_time()
    sk, mu, sd = fit_sklearn(X, Y)
    t_sk, c_sk = time.perf_counter() - t0, time.process_time() - c0
    r_ours = np.sqrt(np.mean((ours.predict(Xv) - Yv) ** 2))
    p_ours, p_sk = ours.predict(Xv), np.column_stack([m.predict((Xv - mu) / sd) for m in sk])
    r_sk = np.sqrt(np.mean((p_sk - Yv) ** 2))
    truth = error_field(Xv)  # noise-free held-out errors, known for the synthetic stand-in
    return {"n_train": int(len(X)), "n_unique": int(len(np.unique(X, axis=0))), "n_outputs": int(Y.shape[1]),
            "ours_s": t_ours, "sklearn_s": t_sk, "speedup": t_sk / t_ours,
            "ours_cpu_s": c_ours, "sklearn_cpu_s": c_sk, "cpu_speedup": c_sk / c_ours,
            "rmse_ratio": float(r_ours / r_sk), "ours_rmse_mm": float(r_ours * 1e3),
            "sklearn_rmse_mm": float(r_sk * 1e3),
            "ours_rmse_vs_truth_mm": float(np.sqrt(np.mean((p_ours - truth) ** 2)) * 1e3),
            "sklearn_rmse_vs_truth_mm": float(np.sqrt(np.mean((p_sk - truth) ** 2)) * 1e3)}


def main() -> None:
    as_json = cli(__doc__).json
    emit(run(), as_json, "GP fit: ours vs sklearn GaussianProcessRegressor (3 outputs, same data)")


if __name__ == "__main__":
    main()
