"""Shared bits of the GP benchmarks: the sklearn baseline and output formatting."""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
import warnings
from pathlib import Path

import numpy as np


def sklearn_gp(d: int):
    """The baseline: ConstantKernel * RBF(ARD) + WhiteKernel, normalize_y, no optimizer restarts."""
    from sklearn.gaussian_process import GaussianProcessRegressor
    from sklearn.gaussian_process.kernels import RBF, ConstantKernel, WhiteKernel

    kernel = ConstantKernel(1.0, (1e-5, 1e5)) * RBF(np.ones(d), (1e-3, 1e3)) + WhiteKernel(1e-2, (1e-12, 1e1))
    return GaussianProcessRegressor(kernel, normalize_y=True, n_restarts_optimizer=0, random_state=0)


def fit_sklearn(X, Y, thetas=None):
    """One sklearn GPR per output column (as ours: one model per axis); inputs standardised as ours.
    With `thetas` (our standardised log-hyperparameters) the kernel is fixed, not optimised."""
    from sklearn.gaussian_process.kernels import RBF, ConstantKernel, WhiteKernel

    mu, sd = X.mean(0), X.std(0)
    d = X.shape[1]
    models = []
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        for j in range(Y.shape[1]):
            gp = sklearn_gp(d)
            if thetas is not None:
                t = np.asarray(thetas[j])
                gp.set_params(kernel=ConstantKernel(np.exp(t[d])) * RBF(np.exp(t[:d])) + WhiteKernel(np.exp(t[d + 1])),
                              optimizer=None)
            models.append(gp.fit((X - mu) / sd, Y[:, j]))
    return models, mu, sd


def cli(description: str, argv: list[str] | None = None, **options) -> argparse.Namespace:
    """Parse --json and the benchmark's own `options` (name=default, typed by the default); BLAS
    on one thread (or $DT_BLAS_THREADS), as the `dt` command line runs."""
    from dt_runtime.common.threads import limit_blas_threads

    limit_blas_threads()
    p = argparse.ArgumentParser(description=description)
    p.add_argument("--json", action="store_true", help="print one JSON object")
    for name, default in options.items():
        if isinstance(default, bool):  # a flag: off unless given
            p.add_argument(f"--{name.replace('_', '-')}", action="store_true", default=default)
            continue
        p.add_argument(f"--{name.replace('_', '-')}", type=type(default), default=default,
                       help=f"default {default}")
    return p.parse_args(argv)


def emit(res: dict, as_json: bool, title: str) -> None:
    if as_json:
        print(json.dumps(res))
        return
    print(title)
    for k, v in res.items():
        print(f"  {k:<22} {v:.4g}" if isinstance(v, float) else f"  {k:<22} {v}")


# Runs argv[1:] with stdout/stderr to the files argv[0] names (".out"/".err" appended) and prints
# the child's wait4 rusage. Why a launcher: on Linux a child started by vfork/fork + exec keeps its
# parent's RSS high-water mark in ru_maxrss (exec_mmap folds the old mm's peak into it), so a
# `dt fit` started straight from a 1 GB pytest process reports >= 1 GB. The launcher is a fresh,
# small process: its children's peak is their own.
_LAUNCHER = """import json, os, subprocess, sys, time
with open(sys.argv[1] + ".out", "wb") as fo, open(sys.argv[1] + ".err", "wb") as fe:
    t0 = time.perf_counter()
    p = subprocess.Popen(sys.argv[2:], stdout=fo, stderr=fe, stdin=subprocess.DEVNULL)
    _, status, ru = os.wait4(p.pid, 0)
    wall = time.perf_counter() - t0
print(json.dumps({"returncode": os.waitstatus_to_exitcode(status), "seconds": wall,
                  "cpu_seconds": ru.ru_utime + ru.ru_stime, "peak_rss_kib": ru.ru_maxrss}))
"""


def measured_run(cmd: list[str], stem: Path) -> dict:
    """Run `cmd` in a fresh process, its stdout/stderr to `stem`.out/.err; returns returncode,
    wall seconds, CPU seconds and peak_rss_gb of that process alone (see _LAUNCHER)."""
    out = subprocess.run([sys.executable, "-c", _LAUNCHER, str(stem), *cmd], capture_output=True, text=True,
                         check=True).stdout
    res = json.loads(out)
    res["peak_rss_gb"] = res.pop("peak_rss_kib") / 1024 ** 2  # ru_maxrss is in KiB on Linux
    return res
