"""`python -m benchmarks.blas_threads [--json] [--baseline-timeout S]`: the docs/library.md session
(what a library user pastes; tests/integration/test_library_example.py runs it) on a loaded machine, in a
fresh process started as a user's script would be: no DT_BLAS_THREADS, no OPENBLAS_NUM_THREADS,
so OpenBLAS is free to use a thread per core.

- ours: the library limits BLAS inside its fits, cross-validations and predictions by itself
  (dt_runtime.common.threads.blas_limited: one thread, the caller's setting restored after);
- baseline, same run: the same session with DT_BLAS_THREADS = cores, which lifts that limit (the
  library before it limited itself). Stopped after --baseline-timeout seconds; then its time and
  the speedup are lower bounds (`baseline_timed_out`);
- reference: the user's old workaround, OPENBLAS_NUM_THREADS=1 in the environment.

The load: one busy Python loop per core, in other processes, for the whole run (the machine a
user shares with other jobs). Also the cost of entering and leaving the limit (`enter_exit_us`,
CPU time per call, the thread count changed and restored each time).

Keys: cores, load_processes, ours_s, ours_cpu_s, baseline_s, baseline_cpu_s, baseline_timed_out,
speedup (baseline / ours, wall), reference_one_thread_s, enter_exit_us, nested_enter_exit_us,
doctest_failed and load_avg_end (the 1-minute load average as each session ended)."""
from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path

from benchmarks._common import cli, emit

ROOT = Path(__file__).resolve().parents[1]
# The child: the page as a doctest from the repository's root (as tests/integration/test_library_example.py),
# printing its own wall and CPU time.
SESSION = """
import doctest, json, time
t0, c0 = time.perf_counter(), time.process_time()
r = doctest.testfile("docs/library.md", module_relative=False,
                     optionflags=doctest.ELLIPSIS | doctest.NORMALIZE_WHITESPACE, verbose=False)
print(json.dumps({"s": time.perf_counter() - t0, "cpu_s": time.process_time() - c0,
                  "attempted": r.attempted, "failed": r.failed}))
"""
THREAD_VARS = ("DT_BLAS_THREADS", "OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS",
               "BLIS_NUM_THREADS", "VECLIB_MAXIMUM_THREADS", "NUMEXPR_NUM_THREADS")


def user_env(**extra: str) -> dict:
    """The environment of a user's process: nothing limits the threads, unless `extra` does."""
    env = {k: v for k, v in os.environ.items() if k not in THREAD_VARS}
    env["MPLBACKEND"] = "Agg"
    return env | extra


def session(env: dict, timeout: float) -> dict:
    """The library session in a fresh process: its wall and CPU seconds, or the timeout, and the
    1-minute load average when it ended (the busy loops count 2 of it on 2 cores)."""
    t0 = time.perf_counter()
    try:
        p = subprocess.run([sys.executable, "-c", SESSION], cwd=ROOT, env=env, capture_output=True,
                           text=True, timeout=timeout)
    except subprocess.TimeoutExpired:
        return {"s": time.perf_counter() - t0, "cpu_s": None, "timed_out": True, "failed": None,
                "load_avg_end": os.getloadavg()[0]}
    if p.returncode != 0:
        raise RuntimeError(f"the library session failed ({p.returncode}): {p.stderr[-2000:]}")
    out = json.loads(p.stdout.strip().splitlines()[-1])
    return out | {"timed_out": False, "load_avg_end": os.getloadavg()[0]}


def enter_cost(n: int = 20000) -> tuple[float, float]:
    """CPU microseconds per `with blas_limited:` (outermost: limit set and restored; nested)."""
    from threadpoolctl import threadpool_limits

    from dt_runtime.common.threads import blas_limited

    with threadpool_limits(2, user_api="blas"):  # so the outermost entry has a limit to set
        with blas_limited:
            pass  # the first entry finds the libraries (once per process)
        c0 = time.process_time()
        for _ in range(n):
            with blas_limited:
                pass
        outer = (time.process_time() - c0) / n * 1e6
        with blas_limited:
            c0 = time.process_time()
            for _ in range(n):
                with blas_limited:
                    pass
            nested = (time.process_time() - c0) / n * 1e6
    return outer, nested


def run(baseline_timeout: float = 1800.0) -> dict:
    cores = os.cpu_count() or 1
    outer, nested = enter_cost()
    load = [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(cores)]
    try:
        time.sleep(1.0)  # the load running before the first session starts
        ours = session(user_env(), baseline_timeout)
        base = session(user_env(DT_BLAS_THREADS=str(cores)), baseline_timeout)
        ref = session(user_env(OPENBLAS_NUM_THREADS="1"), baseline_timeout)
    finally:
        for p in load:
            p.kill()
            p.wait()
    return {"cores": cores, "load_processes": len(load),
            "ours_s": ours["s"], "ours_cpu_s": ours["cpu_s"],
            "baseline_s": base["s"], "baseline_cpu_s": base["cpu_s"], "baseline_timed_out": base["timed_out"],
            "speedup": base["s"] / ours["s"], "reference_one_thread_s": ref["s"],
            "load_avg_end": {"ours": ours["load_avg_end"], "baseline": base["load_avg_end"],
                             "reference": ref["load_avg_end"]},
            "enter_exit_us": outer, "nested_enter_exit_us": nested,
            "doctest_failed": {"ours": ours["failed"], "baseline": base["failed"], "reference": ref["failed"]}}


def main() -> None:
    args = cli(__doc__, baseline_timeout=1800.0)
    emit(run(args.baseline_timeout), args.json,
         "docs/library.md session on a loaded machine, BLAS free: library's own limit vs lifted")


if __name__ == "__main__":
    main()
