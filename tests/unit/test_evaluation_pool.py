"""Evaluator.cv_many with a pool: a configuration wanted on several schemes has its GP
hyperparameters fitted once (one task), its cross-validations then run with them fixed, and the
figures are those one process gives. The pool here runs its tasks in this process (the same calls
the worker processes make: analysis.parallel's task functions), so the tasks can be counted."""
from __future__ import annotations

from concurrent.futures import Future

import numpy as np
import pytest

from dt_runtime.analysis import parallel
from dt_runtime.analysis.diagnose import DiagnoseOptions, prepare
from dt_runtime.analysis.evaluation import Config, Evaluator
from dt_runtime.common.paths import CONFIGS
from dt_runtime.models.gp import GPOptions
from tests.support import deploy_scenarios as sc


class InProcessPool:
    """A Pool's `submit` run at once on a separate Evaluator of the same problem (a worker's),
    recording each task's function and whether it was given hyperparameters."""

    def __init__(self, problem):
        self.worker = Evaluator(problem, 5, 0)
        self.tasks: list[tuple[str, object]] = []

    def submit(self, fn, args: tuple) -> Future:
        self.tasks.append((fn.__name__, args[0] if fn is parallel.hypers else (args[0], args[3] is not None)))
        fut: Future = Future()
        fut.set_result(fn(self.worker, *args))
        return fut


@pytest.fixture(scope="module")
def problem():
    train, _ = sc.approach_backlash(seed=2, n_points=16, passes=2, speeds=(0.25,))
    opts = DiagnoseOptions(effects=(), gp_inputs="tcp", robot=CONFIGS / "robots" / "ur10.yaml",
                           gp_options=GPOptions(n_restarts=0))
    return prepare(train, opts).problem


def test_shared_hyperparameters_are_fitted_once_and_give_the_one_process_figures(problem):
    one = Evaluator(problem, 5, 0)
    cfgs = [Config(("geometric",), "tcp"), Config((), "joints")]
    want = [one.cv(c, s).residual for c in cfgs for s in (one.points, one.deploy)]

    ev = Evaluator(problem, 5, 0)
    ev.pool = pool = InProcessPool(problem)
    got = [r.residual for r in ev.cv_many([(c, s, None) for c in cfgs for s in (ev.points, ev.deploy)])]

    fits = [a for name, a in pool.tasks if name == "hypers"]
    cvs = [a for name, a in pool.tasks if name == "cross_validation"]
    assert sorted(map(str, fits)) == sorted(map(str, cfgs))  # one hyperparameter fit per configuration
    assert len(cvs) == 4 and all(given for _, given in cvs)  # every cross-validation given them
    for w, g in zip(want, got):
        np.testing.assert_allclose(g, w, rtol=1e-10, atol=1e-15)
    for c in cfgs:
        for a, b in zip(ev._thetas[c], one._thetas[c]):
            np.testing.assert_allclose(a, b, rtol=1e-10)
        assert ev.cv(c, ev.points).log_hypers is not None  # a later step's warm start is kept


def test_a_configuration_on_one_scheme_is_sent_whole(problem):
    ev = Evaluator(problem, 5, 0)
    ev.pool = pool = InProcessPool(problem)
    cfgs = [Config(("geometric",), "tcp"), Config((), "tcp")]
    ev.cv_many([(c, ev.points, None) for c in cfgs])
    assert [name for name, _ in pool.tasks] == ["cross_validation"] * 2
    assert not any(given for _, (_, given) in pool.tasks)
