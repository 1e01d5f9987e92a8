"""`python -m benchmarks.fit_scale [--json]`: `dt fit` on the UR10 laser-tracker data (Fraunhofer
IPA Series A, 11,911 rows, 619 grid points; every row's commanded TCP is distinct, so the
replicate collapse does not shrink the GP) against the exact GP, in one run.

1. Scale: the real `dt fit` command (a fresh process: startup, import and registration, fit,
   save, training RMS) on all rows, for the paper's model (GP on the TCP position) and for
   geometric effects + that GP. Wall seconds, CPU seconds and the process's peak RSS (wait4).
   At this size the GP is the sparse VFE/DTC one (dt_runtime.gp; 600 inducing inputs,
   hyperparameters from a seeded 1,000-input subset): the exact GP would need ~11 GB and ~hours.
2. Accuracy, where the exact GP still fits: 30 % of the grid points are held out whole (every
   repetition); n_cmp rows of the other points train (a) the exact GP (exact posterior,
   hyperparameters by the exact marginal likelihood of all n_cmp rows: the baseline) and
   (b) the sparse GP exactly as `dt fit` builds it at scale (forced sparse below its
   threshold). rmse_ratio_vs_exact = held-out 3D RMS (b) / (a), the worse of the two models.
   Also (c): the sparse posterior with (a)'s hyperparameters (the approximation alone).
3. The full sparse model trained on every row of the training points, held-out 3D RMS on the
   held-out points, with the as-is error RMS there for reference.

`--rows N` (e.g. 1000000): bounded memory instead. `dt fit` (paper model, GP on TCP and speed)
in a fresh process on N synthetic rows of a contract CSV (positions scattered in the DOE volume,
every row distinct; the smooth error field of benchmarks._data plus 0.01 mm noise), against the
same command on N/10 rows (the baseline, same run): wall and CPU seconds, peak RSS of the child
(wait4), their ratios; held out on fresh rows against the noise-free truth, the big model vs an
exact GP on 1,000 of its rows (rmse_ratio_vs_exact). Budget: peak RSS < 2 GB at 10^6 rows.

Keys: n_train, seconds (slowest model's `dt fit`, wall), peak_rss_gb (largest `dt fit` process),
rmse_ratio_vs_exact; per model `<model>_*`; the exact baseline's measured cost at n_cmp rows
and its cubic/quadratic extrapolation to n_train. Parts 2-3 run in 2 worker processes (one
BLAS thread each); part 1 runs alone."""
from __future__ import annotations

import json
import os
import resource
import sys
import tempfile
import time
from concurrent.futures import ProcessPoolExecutor
from multiprocessing import get_context
from pathlib import Path

import numpy as np

from benchmarks._common import cli, emit, measured_run
from benchmarks._data import (
    ORIGIN,
    UR10_MAPPING,
    UR10_ROBOT,
    UR10_SERIES_A,
    error_field,
    point_split,
    ur10_dataset,
    ur10_subset_file,
)
from dt_runtime.common.paths import ROOT

# name -> effect terms; both with the GP on the TCP position (gp_inputs "tcp"); the robot
# config (kinematics of the effect terms) is configs/robots/ur10.yaml unless run() is told.
MODELS = {"paper": (), "geometric": ("geometric",)}
BUDGET_S, BUDGET_GB = 60.0, 4.0


def _gb(maxrss_kib: float) -> float:
    return maxrss_kib / 1024 ** 2  # ru_maxrss is in KiB on Linux


def _rms3(e: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.sum(e ** 2, axis=1))))


def _load() -> float:
    try:
        return os.getloadavg()[0]
    except OSError:  # pragma: no cover
        return float("nan")


# --- 1. the `dt fit` command, alone, in a fresh process --------------------------------------
def dt_fit(data: Path, model: str, out_dir: Path, robot: Path = UR10_ROBOT) -> dict:
    """Run `dt fit` on `data` and measure the process: wall s, CPU s and peak RSS (wait4)."""
    effects = MODELS[model]
    cmd = [sys.executable, "-m", "dt_runtime.cli.main", "fit", "--data", str(data), "--mapping", str(UR10_MAPPING),
           "--gp-inputs", "tcp", "--out", str(out_dir / model), "--json", "--no-progress"]
    if effects:
        cmd += ["--effects", ",".join(effects), "--robot", str(robot)]
    run_ = measured_run(cmd, out_dir / model)
    if run_["returncode"] != 0:
        err = (out_dir / f"{model}.err").read_text()[-2000:]
        raise RuntimeError(f"dt fit ({model}) failed ({run_['returncode']}): {err}")
    res = json.loads((out_dir / f"{model}.out").read_text())
    return {"seconds": run_["seconds"], "cpu_seconds": run_["cpu_seconds"], "peak_rss_gb": run_["peak_rss_gb"],
            "fit_seconds": res["fit_seconds"], "n": res["n"], "train_rms_mm": res["train_rmse_mm"]}


# --- 2./3. analysis jobs (each in its own worker process) ------------------------------------
def _one_thread():
    from dt_runtime.common.threads import limit_blas_threads

    return limit_blas_threads(1)


def _model(name: str, robot: str, seed: int, gp_kw: dict | None = None):
    from dt_runtime.models.gp import GPOptions
    from dt_runtime.models.hybrid import HybridModel

    effects = MODELS[name]
    return HybridModel(effects, "tcp", seed=seed, robot=robot if effects else None,
                       gp_options=GPOptions(**(gp_kw or {})))


def compare_job(data: str, name: str, robot: str, train: np.ndarray, test: np.ndarray, seed: int,
                n_inducing: int | None = None) -> dict:
    """Exact GP vs the sparse GP (dt fit's settings at scale) on the same rows, held out."""
    with _one_thread():
        ds = ur10_dataset(data)
        tr, te = ds.select(train), ds.select(test)
        n = tr.n
        rss0 = _gb(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss)
        t0 = time.perf_counter()
        exact = _model(name, robot, seed, {"sparse_threshold": n, "n_hyper": n}).fit(tr)
        t_exact = time.perf_counter() - t0
        rss_exact = _gb(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss)
        kw = {"sparse_threshold": n - 1} | ({} if n_inducing is None else {"n_inducing": n_inducing})
        t0 = time.perf_counter()
        sparse = _model(name, robot, seed, kw).fit(tr)
        t_sparse = time.perf_counter() - t0
        same = _model(name, robot, seed, kw).fit(tr, thetas=exact.gp_.thetas_)
        assert not exact.gp_.models_[0].sparse_ and sparse.gp_.models_[0].sparse_
        rms = {k: _rms3(te.error - m.predict(te)) * 1e3
               for k, m in (("exact", exact), ("sparse", sparse), ("same_hyper", same))}
    return {"n_compare": n, "n_compare_test": te.n, "exact_rms_mm": rms["exact"], "sparse_rms_mm": rms["sparse"],
            "sparse_same_hyper_rms_mm": rms["same_hyper"], "rmse_ratio_vs_exact": rms["sparse"] / rms["exact"],
            "rmse_ratio_same_hyper": rms["same_hyper"] / rms["exact"], "exact_seconds": t_exact,
            "sparse_seconds": t_sparse, "exact_peak_rss_gb": rss_exact, "base_rss_gb": rss0,
            "n_inducing": int(sparse.gp_.models_[0]._Xb.shape[0])}


def heldout_job(data: str, name: str, robot: str, train: np.ndarray, test: np.ndarray, seed: int) -> dict:
    """dt fit's model on every row of the training points, held-out RMS on the other points."""
    with _one_thread():
        ds = ur10_dataset(data)
        tr, te = ds.select(train), ds.select(test)
        t0 = time.perf_counter()
        m = _model(name, robot, seed).fit(tr)
        t_fit = time.perf_counter() - t0
        return {"n_heldout_train": tr.n, "n_heldout_test": te.n, "heldout_fit_seconds": t_fit,
                "heldout_sparse": bool(m.gp_.models_[0].sparse_),
                "heldout_rms_mm": _rms3(te.error - m.predict(te)) * 1e3,
                "asis_rms_mm": _rms3(te.error) * 1e3}


# --- the benchmark ---------------------------------------------------------------------------
def run(n_big: int | None = None, n_cmp: int = 3000, holdout: float = 0.3, seed: int = 0,
        models: tuple[str, ...] = tuple(MODELS), workers: int = 2, n_inducing: int | None = None,
        robot: str | Path = UR10_ROBOT) -> dict:
    """n_big: rows for `dt fit` (None: all of Series A; fewer: a seeded row subset file);
    n_inducing: the compared sparse GP's (None: dt fit's default, 600)."""
    res: dict = {"data": str(UR10_SERIES_A.relative_to(ROOT)), "cores": os.cpu_count(),
                 "load_avg_1min_start": _load()}
    with tempfile.TemporaryDirectory(prefix="fit_scale_") as tmp:
        tmp = Path(tmp)
        data = UR10_SERIES_A if n_big is None else ur10_subset_file(n_big, tmp / "subset.csv", seed)
        # 1. the `dt fit` command, one model at a time, nothing else of ours running
        fits = {m: dt_fit(data, m, tmp, Path(robot)) for m in models}
        # 2./3. held-out accuracy, in parallel worker processes (a fresh process per job)
        ds = ur10_dataset(str(data))
        train, test = point_split(ds.point_id, holdout, seed)
        cmp_train = np.sort(np.random.default_rng(seed).choice(train, min(n_cmp, len(train)), replace=False))
        ctx = get_context("spawn")
        with ProcessPoolExecutor(workers, mp_context=ctx, max_tasks_per_child=1) as ex:
            cmp_f = {m: ex.submit(compare_job, str(data), m, str(robot), cmp_train, test, seed, n_inducing) for m in models}
            ho_f = {m: ex.submit(heldout_job, str(data), m, str(robot), train, test, seed) for m in models}
            cmps = {m: f.result() for m, f in cmp_f.items()}
            hos = {m: f.result() for m, f in ho_f.items()}
    n = next(iter(fits.values()))["n"]
    worst_fit = max(fits, key=lambda m: fits[m]["seconds"])
    worst_cmp = max(cmps, key=lambda m: cmps[m]["rmse_ratio_vs_exact"])
    c0 = cmps[models[0]]
    grow = n / c0["n_compare"]
    res.update({
        "n_train": n, "seconds": fits[worst_fit]["seconds"], "peak_rss_gb": max(f["peak_rss_gb"] for f in fits.values()),
        "rmse_ratio_vs_exact": cmps[worst_cmp]["rmse_ratio_vs_exact"],
        "within_budget": bool(all(f["seconds"] < BUDGET_S and f["peak_rss_gb"] < BUDGET_GB for f in fits.values())),
        "ratio_within_5pct": bool(all(c["rmse_ratio_vs_exact"] <= 1.05 for c in cmps.values())),
        "n_inducing": c0["n_inducing"], "n_compare": c0["n_compare"], "n_compare_test": c0["n_compare_test"],
        "n_heldout_points_frac": holdout,
        # the baseline, measured in this run at n_cmp rows, and scaled to n_train (time ~ n^3, memory ~ n^2)
        "exact_seconds_at_n_compare": c0["exact_seconds"], "sparse_seconds_at_n_compare": c0["sparse_seconds"],
        "exact_peak_rss_gb_at_n_compare": c0["exact_peak_rss_gb"],
        "exact_est_seconds_at_n_train": c0["exact_seconds"] * grow ** 3,
        "exact_est_rss_gb_at_n_train": c0["base_rss_gb"] + (c0["exact_peak_rss_gb"] - c0["base_rss_gb"]) * grow ** 2,
    })
    for m in models:
        f, c, h = fits[m], cmps[m], hos[m]
        res.update({f"{m}_seconds": f["seconds"], f"{m}_fit_seconds": f["fit_seconds"],
                    f"{m}_cpu_seconds": f["cpu_seconds"], f"{m}_peak_rss_gb": f["peak_rss_gb"],
                    f"{m}_train_rms_mm": f["train_rms_mm"],
                    f"{m}_exact_rms_mm": c["exact_rms_mm"], f"{m}_sparse_rms_mm": c["sparse_rms_mm"],
                    f"{m}_sparse_same_hyper_rms_mm": c["sparse_same_hyper_rms_mm"],
                    f"{m}_rmse_ratio_vs_exact": c["rmse_ratio_vs_exact"],
                    f"{m}_rmse_ratio_same_hyper": c["rmse_ratio_same_hyper"],
                    f"{m}_exact_seconds_at_n_compare": c["exact_seconds"],
                    f"{m}_heldout_rms_mm": h["heldout_rms_mm"], f"{m}_heldout_fit_seconds": h["heldout_fit_seconds"]})
    h0 = hos[models[0]]
    res.update({"n_heldout_train": h0["n_heldout_train"], "n_heldout_test": h0["n_heldout_test"],
                "heldout_sparse": h0["heldout_sparse"], "heldout_asis_rms_mm": h0["asis_rms_mm"],
                "load_avg_1min_end": _load()})
    return res


# --- `--rows N`: dt fit on N synthetic rows, bounded memory -----------------------------------
ROWS_BUDGET_GB = 2.0
ROWS_CHUNK = 100_000  # rows generated and written at a time


def synthetic_rows(n: int, seed: int, start: int = 0):
    """Rows `start`.. of a seeded synthetic campaign, in SI: commanded TCP scattered in the
    DOE volume (benchmarks._data: every row distinct, so the replicate collapse cannot shrink the
    GP), speed, time, the smooth error field of `error_field` plus 0.01 mm tracker noise.
    Returns (X (n, 4) [x, y, z, v], E (n, 3) error, E_true (n, 3) noise-free)."""
    rng = np.random.default_rng([seed, start])
    X = np.column_stack([rng.uniform(ORIGIN, ORIGIN + [1.0, 0.7, 0.7], (n, 3)), rng.uniform(0.2, 1.0, n)])
    truth = error_field(X)
    return X, truth + rng.normal(0.0, 1e-5, (n, 3)), truth


def write_rows(path: Path, n: int, seed: int) -> Path:
    """The contract CSV (mm, mm/s, s; UTF-8, header) of `synthetic_rows`, written in chunks so the
    generator's memory stays small whatever n."""
    with open(path, "w", encoding="utf-8") as f:
        f.write("x,y,z,speed,t,point_id,ex,ey,ez\n")
        for start in range(0, n, ROWS_CHUNK):
            k = min(ROWS_CHUNK, n - start)
            X, E, _ = synthetic_rows(k, seed, start)
            idx = np.arange(start, start + k)
            block = np.column_stack([X[:, :3] * 1e3, X[:, 3] * 1e3, idx * 0.5, idx, E * 1e3])
            np.savetxt(f, block, fmt=["%.4f"] * 4 + ["%.1f", "%d"] + ["%.5f"] * 3, delimiter=",")
    return path


def dt_fit_rows(data: Path, out_dir: Path, name: str) -> dict:
    """`dt fit` (paper model: GP on TCP and speed) on a contract CSV, in a fresh process: wall s,
    CPU s and peak RSS of that process (wait4 in a small launcher: the child's own peak)."""
    cmd = [sys.executable, "-m", "dt_runtime.cli.main", "fit", "--data", str(data), "--out", str(out_dir / name),
           "--json", "--no-progress"]
    run_ = measured_run(cmd, out_dir / name)
    if run_["returncode"] != 0:
        raise RuntimeError(f"dt fit ({name}) failed: {(out_dir / f'{name}.err').read_text()[-2000:]}")
    res = json.loads((out_dir / f"{name}.out").read_text())
    return {"seconds": run_["seconds"], "cpu_seconds": run_["cpu_seconds"], "peak_rss_gb": run_["peak_rss_gb"],
            "fit_seconds": res["fit_seconds"], "n": res["n"], "train_rms_mm": res["train_rmse_mm"]}


def run_rows(n: int, seed: int = 0, n_small: int | None = None, n_cmp: int = 1000, n_test: int = 2000) -> dict:
    """`dt fit` on n synthetic rows (a fresh process: import, fit, save, training RMS) against
    the same command on n_small rows (default n/10: the baseline, same run), each's peak RSS and
    wall time; held out (n_test fresh rows, against the noise-free truth) the big model against
    an exact GP (exact posterior and hyperparameters) on n_cmp of its rows."""
    from dt_runtime.common.threads import limit_blas_threads
    from dt_runtime.models.effects import Inputs
    from dt_runtime.models.gp import GPOptions
    from dt_runtime.models.hybrid import HybridModel

    n_small = n_small or max(n // 10, 1000)
    res: dict = {"mode": "rows", "n_train": n, "n_small": n_small, "cores": os.cpu_count(),
                 "load_avg_1min_start": _load(), "data": "synthetic contract CSV (benchmarks._data.error_field)"}
    with tempfile.TemporaryDirectory(prefix="fit_rows_") as tmp:
        tmp = Path(tmp)
        t0 = time.perf_counter()
        big, small = write_rows(tmp / "big.csv", n, seed), write_rows(tmp / "small.csv", n_small, seed)
        res["write_seconds"] = time.perf_counter() - t0
        res["file_mb"] = big.stat().st_size / 1e6
        fits = {"small": dt_fit_rows(small, tmp, "small"), "big": dt_fit_rows(big, tmp, "big")}
        with limit_blas_threads(1):
            Xt, _, Et = synthetic_rows(n_test, seed + 1)
            inp = Inputs(commanded=Xt[:, :3], speed=Xt[:, 3])
            big_m = HybridModel.load(tmp / "big")
            rms_big = _rms3(Et - big_m.predict(inp)) * 1e3
            Xc, Ec, _ = synthetic_rows(n_cmp, seed)  # the first n_cmp rows of the big file
            t1 = time.perf_counter()
            exact = HybridModel((), "tcp_speed", seed=seed, gp_options=GPOptions(
                sparse_threshold=n_cmp, n_hyper=n_cmp)).fit(Inputs(commanded=Xc[:, :3], speed=Xc[:, 3]), Ec)
            t_exact = time.perf_counter() - t1
            rms_exact = _rms3(Et - exact.predict(inp)) * 1e3
    b, s = fits["big"], fits["small"]
    res.update({"seconds": b["seconds"], "peak_rss_gb": b["peak_rss_gb"], "cpu_seconds": b["cpu_seconds"],
                "fit_seconds": b["fit_seconds"], "train_rms_mm": b["train_rms_mm"],
                "small_seconds": s["seconds"], "small_peak_rss_gb": s["peak_rss_gb"],
                "seconds_ratio_vs_small": b["seconds"] / s["seconds"],
                "rss_ratio_vs_small": b["peak_rss_gb"] / s["peak_rss_gb"],
                "heldout_rms_mm": rms_big, "exact_heldout_rms_mm": rms_exact, "n_compare": n_cmp,
                "exact_seconds_at_n_compare": t_exact, "rmse_ratio_vs_exact": rms_big / rms_exact,
                "within_budget": bool(b["peak_rss_gb"] < ROWS_BUDGET_GB), "budget_gb": ROWS_BUDGET_GB,
                "load_avg_1min_end": _load()})
    return res


def main() -> None:
    a = cli(__doc__, rows=0)
    if a.rows:
        emit(run_rows(a.rows), a.json, f"dt fit on {a.rows} synthetic rows: peak memory and time vs n/10 rows")
        return
    emit(run(), a.json, "dt fit at scale: UR10 Series A, sparse GP vs exact GP")


if __name__ == "__main__":
    main()
