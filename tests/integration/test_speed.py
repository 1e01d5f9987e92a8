"""What the speed-ups reuse must give the same numbers: the thermal profile's fixed part, the
sparse posterior and prediction in bounded chunks, the GP's warm start, the loop's reuse of the
previous step. (Timings are the benchmarks' business: benchmarks.ur10, benchmarks.fit_scale.)"""
import numpy as np
import pytest

from dt_runtime.models import gp as gpmod
from dt_runtime.models import hyper as hp
from dt_runtime.models.gp import GPRegressor, MultiOutputGP


def test_fixed_part_rss_equals_the_whole_design():
    rng = np.random.default_rng(0)
    B = rng.normal(size=(600, 7)) * rng.uniform(1e-3, 1e3, 7)
    B[:, 3] = 0.0  # a zero column, as rss_of drops it
    y = B @ rng.normal(size=7) + rng.normal(size=600)
    part = hp.FixedPart(B, y, 1e-4)
    for q in (1, 2):
        a = rng.normal(size=(600, q)) * 1e-5
        assert part.rss(a) == pytest.approx(hp.rss_of(np.hstack([B, a]), y, 1e-4), rel=1e-10)
    assert part.rss(np.zeros((600, 1))) == pytest.approx(hp.rss_of(B, y, 1e-4), rel=1e-10)
    empty = hp.FixedPart(np.zeros((600, 0)), y, 1e-4)
    assert empty.rss(np.zeros((600, 0))) == pytest.approx(float(y @ y))


def _data(n=900, seed=0):
    rng = np.random.default_rng(seed)
    X = rng.uniform(-1, 1, (n, 3))
    y = np.sin(2 * X[:, 0]) + 0.5 * X[:, 1] * X[:, 2] + 0.05 * rng.normal(size=n)
    return X, y


def test_sparse_posterior_and_prediction_in_chunks_are_the_same(monkeypatch):
    X, y = _data()
    opts = dict(sparse_threshold=100, n_inducing=60, n_hyper=300, n_restarts=0)
    whole = GPRegressor(**opts).fit(X, y)
    theta = whole.theta_
    Xt = _data(250, 1)[0]
    m0, s0 = whole.predict(Xt, return_std=True)
    monkeypatch.setattr(gpmod, "_CHUNK_ELEMENTS", 60 * 7)  # 7 rows per chunk
    chunked = GPRegressor(**opts).fit(X, y, theta=theta)
    assert chunked.sparse_
    m1, s1 = chunked.predict(Xt, return_std=True)
    np.testing.assert_allclose(m1, m0, rtol=1e-9, atol=1e-12)
    # the variance s_f^2 - k'Qk cancels to ~1e-4 of s_f^2 here: the summation order shows at ~1e-4
    np.testing.assert_allclose(s1, s0, rtol=1e-3)


def test_warm_start_reaches_the_optimum_in_fewer_evaluations(monkeypatch):
    X, y = _data(400)
    cold = GPRegressor(n_restarts=1).fit(X, y)
    calls = {"n": 0}
    orig = gpmod.collapsed_nll

    def counting(*a, **k):
        calls["n"] += 1
        return orig(*a, **k)

    monkeypatch.setattr(gpmod, "collapsed_nll", counting)
    # a nearby problem: the same inputs, the target shifted and scaled (standardisation differs)
    warm = GPRegressor(n_restarts=1).fit(X, 2 * y + 1, start=cold.log_hyper_ + np.r_[0, 0, 0, np.log(4), np.log(4)])
    n_warm = calls["n"]
    calls["n"] = 0
    again = GPRegressor(n_restarts=1).fit(X, 2 * y + 1)
    assert n_warm < calls["n"] / 3
    assert warm.log_marginal_likelihood_ == pytest.approx(again.log_marginal_likelihood_, abs=1e-3)
    np.testing.assert_allclose(warm.length_scales_, cold.length_scales_, rtol=1e-2)
    # a start for other inputs (another dimension) is ignored: the cold starts
    other = GPRegressor(n_restarts=0).fit(X, y, start=np.zeros(4))
    assert other.log_marginal_likelihood_ == pytest.approx(GPRegressor(n_restarts=0).fit(X, y)
                                                           .log_marginal_likelihood_)
    mo = MultiOutputGP(n_restarts=0).fit(X, np.column_stack([y, -y]))
    assert len(mo.log_hypers_) == 2 and mo.log_hypers_[0].shape == (5,)
