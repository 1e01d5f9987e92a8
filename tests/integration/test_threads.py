"""The library limits BLAS threads inside its own fits (dt_runtime.common.threads.blas_limited) and
gives the caller's setting back. The suite runs on one thread (conftest): each test first lifts it
to two, as a user's process on two cores starts."""
import threading

import numpy as np
import pytest
from threadpoolctl import threadpool_limits

from dt_kernel.errors import ConfigError
from dt_runtime.analysis.crossval import cross_validate, folds_of
from dt_runtime.common import threads
from dt_runtime.common.threads import blas_limited
from dt_runtime.models import gp as gpmod
from dt_runtime.models.gp import MultiOutputGP
from dt_runtime.models.hybrid import HybridModel


def counts() -> list[int]:
    return [get() for get, _ in threads._blas_libraries()]


@pytest.fixture
def two_threads(monkeypatch):
    monkeypatch.delenv(threads.ENV, raising=False)
    with threadpool_limits(2, user_api="blas"):
        assert set(counts()) == {2}
        yield


def test_fits_and_cross_validation_run_on_one_thread_and_restore_the_callers(two_threads, monkeypatch):
    seen = []
    orig = gpmod.collapsed_factor

    def spy(*a, **k):  # inside every GP fit
        seen.append(tuple(counts()))
        return orig(*a, **k)

    monkeypatch.setattr(gpmod, "collapsed_factor", spy)
    rng = np.random.default_rng(0)
    X = rng.uniform(-1, 1, (60, 3))
    Y = np.column_stack([np.sin(2 * X[:, 0]), X[:, 1] * X[:, 2], np.cos(X[:, 2])]) * 1e-3
    gp = MultiOutputGP(n_restarts=0).fit(X, Y)
    assert set(counts()) == {2}  # the caller's setting is back
    gp.predict(X)
    HybridModel((), "tcp").fit(X, Y)
    groups = np.arange(len(X))
    cv = cross_validate(HybridModel((), "tcp"), X, Y, groups, folds_of(groups, 3, 0))
    assert np.isfinite(cv.residual).all()
    assert len(seen) == 3 + 3 + 4 * 3  # three outputs: the GP, the hybrid, the CV's full fit and folds
    assert set(seen) == {(1,) * len(counts())}
    assert set(counts()) == {2}


def test_nested_entries_restore_once_and_errors_restore_too(two_threads):
    with blas_limited:
        assert set(counts()) == {1}
        with blas_limited:
            assert set(counts()) == {1}
        assert set(counts()) == {1}  # the inner exit does not restore under the outer one
    assert set(counts()) == {2}

    @blas_limited
    def boom():
        assert set(counts()) == {1}
        raise ValueError("inside")

    with pytest.raises(ValueError, match="inside"):
        boom()
    assert set(counts()) == {2} and blas_limited._depth == 0


def test_threads_overlapping_restore_after_the_last_leaves(two_threads):
    inside, leave = threading.Event(), threading.Event()
    seen = []

    def worker():  # a fit in a worker thread is limited too (not only in the first thread that set one)
        with blas_limited:
            seen.append(set(counts()))
            inside.set()
            leave.wait(10)

    t = threading.Thread(target=worker)
    t.start()
    inside.wait(10)
    with blas_limited:
        leave.set()
        t.join(10)
        assert set(counts()) == {1}  # the worker left first: still limited for this one
    assert seen == [{1}] and set(counts()) == {2}


def test_dt_blas_threads_sets_the_limit_which_never_raises_the_callers(monkeypatch):
    monkeypatch.setenv(threads.ENV, "2")
    with threadpool_limits(2, user_api="blas"):
        with blas_limited:
            assert set(counts()) == {2}
    with threadpool_limits(1, user_api="blas"):
        with blas_limited:
            assert set(counts()) == {1}
    monkeypatch.setenv(threads.ENV, "zero")
    with pytest.raises(ConfigError, match="DT_BLAS_THREADS.*zero"):
        with blas_limited:
            pass
    assert blas_limited._depth == 0


def test_the_benchmark_runs_the_session_as_a_users_process_would(monkeypatch):
    from benchmarks import blas_threads as bench

    for v in ("DT_BLAS_THREADS", "OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS"):
        monkeypatch.setenv(v, "1")
    env = bench.user_env()
    assert not set(bench.THREAD_VARS) & set(env)  # nothing limits the threads
    assert bench.user_env(DT_BLAS_THREADS="2")["DT_BLAS_THREADS"] == "2"  # the baseline lifts the limit
    outer, nested = bench.enter_cost(200)  # CPU us per call (the benchmark reports them; no timing test here)
    assert outer > 0 and nested > 0
