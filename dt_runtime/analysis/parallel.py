"""The cross-validations of one diagnosis step in worker processes (`Pool`): the candidates of a
step are independent, so on 2 cores two run at once. Results are the same as in one process.

How many workers: `DT_WORKERS` (the command line and the benchmarks default it to the machine's
cores); the library defaults to 1 (no pool) so that a caller's process stays as it is.
"""
from __future__ import annotations

import multiprocessing as mp
import os
from concurrent.futures import ProcessPoolExecutor

from dt_kernel.errors import ConfigError

ENV = "DT_WORKERS"
_EV = None  # the worker's Evaluator


def workers() -> int:
    """Worker processes for a diagnosis: $DT_WORKERS, default 1."""
    raw = os.environ.get(ENV, "1")
    try:
        n = int(raw)
    except ValueError:
        n = 0
    if n < 1:
        raise ConfigError("environment", ENV, raw, "a whole number >= 1")
    return n


def default_to_cores() -> None:
    """Entry points (the command line, the benchmarks): one worker per core unless DT_WORKERS says."""
    os.environ.setdefault(ENV, str(max(1, min(os.cpu_count() or 1, 8))))


def _init(problem, folds: int, seed: int) -> None:
    from dt_runtime.analysis.evaluation import Evaluator
    from dt_runtime.common.threads import limit_blas_threads

    global _EV
    limit_blas_threads(1)
    _EV = Evaluator(problem, folds, seed)


def _task(cfg, kind: str, starts, thetas):
    assert _EV is not None
    return _EV.compute(cfg, _EV.scheme(kind), starts, thetas)


def cross_validation(ev, cfg, kind: str, starts, thetas):
    """`Pool.map`'s task as a `submit` function: ev.compute on the scheme of that kind.

    Parameters
    ----------
    ev : Evaluator
        The worker's.
    cfg : Config
        The configuration.
    kind : str
        The scheme's kind.
    starts, thetas : list or None
        Warm starts, or fixed GP hyperparameters.

    Returns
    -------
    CvResult
    """
    return ev.compute(cfg, ev.scheme(kind), starts, thetas)


def hypers(ev, cfg, starts):
    """The GP hyperparameters of cfg fitted on all rows, (thetas, log_hypers) (ev.hypers).

    Parameters
    ----------
    ev : Evaluator
        The worker's.
    cfg : Config
        The configuration.
    starts : list or None
        Warm starts.

    Returns
    -------
    tuple
    """
    return ev.hypers(cfg, starts)


def _call(fn, args: tuple):
    assert _EV is not None
    return fn(_EV, *args)


class Pool:
    """Worker processes holding one diagnosis's problem.

    A pool lives for one diagnosis. Its workers are started fresh (spawn: no state of the parent's
    threads, bus sessions or locks is inherited), each builds the diagnosis's `Evaluator` once from
    the problem (its schemes are seeded, so the folds are the parent's), runs BLAS on one thread,
    and cross-validates what it is sent: a configuration, a scheme and the hyperparameter start or
    fixed hyperparameters the parent knows.
    """

    def __init__(self, problem, folds: int, seed: int, n: int):
        self.n = n
        self._ex = ProcessPoolExecutor(max_workers=n, mp_context=mp.get_context("spawn"), initializer=_init,
                                       initargs=(problem, folds, seed))

    def map(self, jobs: list[tuple]) -> list:
        """Cross-validate each (cfg, scheme kind, starts, thetas); results in order.

        Parameters
        ----------
        jobs : list of tuple
            (cfg, scheme kind, starts, thetas) each.

        Returns
        -------
        list of CvResult
        """
        futures = [self._ex.submit(_task, *job) for job in jobs]
        return [f.result() for f in futures]

    def call(self, fn, jobs: list[tuple]) -> list:
        """`fn(evaluator, *args)` for each args tuple of `jobs` in the workers (fn a module-level
        function, sent by name); results in order.

        Parameters
        ----------
        fn : callable
            A module-level function fn(evaluator, *args).
        jobs : list of tuple
            Its arguments, one tuple per call.

        Returns
        -------
        list
        """
        futures = [self._ex.submit(_call, fn, args) for args in jobs]
        return [f.result() for f in futures]

    def submit(self, fn, args: tuple):
        """`fn(evaluator, *args)` in a worker, as `call` does for one job, without waiting.

        Parameters
        ----------
        fn : callable
            A module-level function fn(evaluator, *args).
        args : tuple
            Its arguments.

        Returns
        -------
        concurrent.futures.Future
        """
        return self._ex.submit(_call, fn, args)

    def close(self) -> None:
        """Shut the worker processes down, cancelling what has not started."""
        self._ex.shutdown(wait=True, cancel_futures=True)
