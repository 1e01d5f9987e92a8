"""Shared bits of the benchmarks: the sklearn baseline, output formatting, and the machine a timing
figure was taken on (the reference workload, `Machine`)."""
from __future__ import annotations

import argparse
import contextlib
import json
import math
import os
import resource
import subprocess
import sys
import time
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


# --- the machine a figure was taken on ------------------------------------------------------------
# A timing figure alone says as much about the machine (its speed, the other processes on it) as
# about the code. Each timing benchmark also times this fixed workload in the same run, before and
# after its own work, and states its figures relative to it: a figure divided by the workload's time
# (or a rate times it) is about the code, and a regression shows as a ratio on any machine.
# REFERENCE_NOMINAL_S is the workload's best time on the 2-core machine docs/results.md's figures
# were taken on (AMD EPYC, 2 vCPU, shared); `speed` = nominal / measured (1.0 there, 0.5 on a
# machine twice slower).
REFERENCE_NOMINAL_S = 0.23


def _reference_python(n: int) -> float:
    """Plain Python as a control loop spends it: float arithmetic, small lists, dict and attribute
    look-ups, calls."""
    acc, d = 0.0, {"a": 1.0, "b": 2.0, "c": 3.0}
    v = [0.1, 0.2, 0.3]
    for i in range(n):
        x, y, z = v
        v = [y * 0.5 + 0.1, z * 0.25 + x, (x + y + z) / 3.0 + d["a"]]
        acc += math.sqrt(x * x + y * y + z * z) + d["b" if i & 1 else "c"]
    return acc


def _reference_numpy(n: int) -> float:
    """numpy as the hot path spends it: many calls on small arrays (3-vectors, 4x4 and 3x30
    matrices, a 60-point kernel row) and one BLAS-3 step (a 200x200 Cholesky, one thread)."""
    rng = np.random.default_rng(0)
    R, A, X = rng.normal(size=(4, 4)), rng.normal(size=(3, 30)), rng.normal(size=(60, 4))
    th, c = rng.normal(size=30), np.zeros(4)
    acc = 0.0
    for _ in range(n):
        c[:3] = R[:3, :3] @ c[:3] * 0.5 + A @ th * 1e-3
        k = np.exp(-0.5 * np.sum((X - c) ** 2, axis=1))
        acc += float(np.abs(k).max()) + float(np.linalg.norm(c))
    M = rng.normal(size=(200, 200))
    for _ in range(5):
        acc += float(np.linalg.cholesky(M @ M.T + 200 * np.eye(200))[-1, -1])
    return acc


def reference_workload() -> dict:
    """The fixed reference workload timed once: its wall and CPU seconds, and the plain-Python and
    numpy parts' wall seconds (REFERENCE_NOMINAL_S on the nominal machine).

    Returns
    -------
    dict
        `seconds`, `cpu_seconds`, `python_s`, `numpy_s`.
    """
    from threadpoolctl import threadpool_limits  # installed with scikit-learn

    with threadpool_limits(1, user_api="blas"):  # one BLAS thread whatever the benchmark uses
        c0, t0 = time.process_time(), time.perf_counter()
        _reference_python(600_000)
        t1 = time.perf_counter()
        _reference_numpy(12_000)
        t2 = time.perf_counter()
    return {"seconds": round(t2 - t0, 4), "cpu_seconds": round(time.process_time() - c0, 4),
            "python_s": round(t1 - t0, 4), "numpy_s": round(t2 - t1, 4)}


class Machine:
    """What a timing benchmark's figures were taken on: the reference workload timed before and
    after the benchmark's own work, the 1-min load averages at both ends, the process's CPU time
    (its own and its waited-for children's) and wall time in between.

    Use as `with Machine() as m: ...`, then `m.report()`; `m.ref_s` (the faster of the two timings:
    the machine's speed with the least interference) divides times and multiplies rates in
    `relative`.
    """

    def __enter__(self) -> Machine:
        self.load_start = os.getloadavg()[0]
        self.before = reference_workload()
        self._c0, self._t0 = _cpu_s(), time.perf_counter()
        return self

    def __exit__(self, *exc) -> None:
        self.cpu_s, self.wall_s = _cpu_s() - self._c0, time.perf_counter() - self._t0
        self.after = reference_workload()
        self.load_end = os.getloadavg()[0]

    @property
    def ref_s(self) -> float:
        return min(self.before["seconds"], self.after["seconds"])

    def report(self) -> dict:
        """The `machine` entry of a benchmark's result.

        Returns
        -------
        dict
            `reference_s` (the faster timing), `reference` {`before`, `after`}, `speed` (nominal /
            reference_s: 1.0 on the nominal machine, below 1 on a slower or busier one),
            `cpu_share` (the workload's CPU / wall time, the lower of the two: below 1 when other
            processes took turns on its core),
            `nominal_reference_s`, `load` {`start`, `end`}, `cores`, `cpu_s`, `wall_s`.
        """
        # the share of a core the workload got (CPU / wall): below 1 when other processes took turns
        share = min(r["cpu_seconds"] / r["seconds"] for r in (self.before, self.after))
        return {"reference_s": self.ref_s, "speed": round(REFERENCE_NOMINAL_S / self.ref_s, 3),
                "cpu_share": round(share, 3),
                "nominal_reference_s": REFERENCE_NOMINAL_S,
                "reference": {"before": self.before, "after": self.after},
                "load": {"start": round(self.load_start, 2), "end": round(self.load_end, 2)},
                "cores": os.cpu_count(), "cpu_s": round(self.cpu_s, 2), "wall_s": round(self.wall_s, 2)}

    def relative(self, times_s: dict | None = None, rates_hz: dict | None = None) -> dict:
        """Figures in units of the reference workload: a time divided by it, a rate times it (both
        dimensionless: a code regression changes them, a slower machine does not, to first order).

        Parameters
        ----------
        times_s : dict
            name -> seconds.
        rates_hz : dict
            name -> per second.

        Returns
        -------
        dict
            name -> the figure relative to `ref_s` (names of times end in `_per_ref`, rates in
            `_x_ref`); None stays None.
        """
        out = {}
        for k, v in (times_s or {}).items():
            out[f"{k}_per_ref"] = None if v is None else round(v / self.ref_s, 6)
        for k, v in (rates_hz or {}).items():
            out[f"{k}_x_ref"] = None if v is None else round(v * self.ref_s, 2)
        return out


def _cpu_s() -> float:
    """CPU seconds of this process and its waited-for children."""
    ch = resource.getrusage(resource.RUSAGE_CHILDREN)
    return time.process_time() + ch.ru_utime + ch.ru_stime


_SPIN = ("import sys, time\nend = time.monotonic() + float(sys.argv[1])\n"
         "while time.monotonic() < end:\n    pass\n")


@contextlib.contextmanager
def busy_core(on: bool = True, max_s: float = 1800.0):
    """Another process keeping one core busy (a Python spin loop) while inside, when `on`: the
    benchmark under load. The spinner ends by itself after `max_s` whatever happens here.

    Parameters
    ----------
    on : bool
        False: nothing is started (yields False).
    max_s : float
        The spinner's own time limit, s.
    """
    if not on:
        yield False
        return
    p = subprocess.Popen([sys.executable, "-c", _SPIN, str(max_s)], stdin=subprocess.DEVNULL)
    try:
        time.sleep(0.2)  # running before the measurement starts
        yield True
    finally:
        p.kill()
        p.wait()

