import numpy as np
import pytest
from scipy import linalg

from dt_runtime.errors import DataError, ModelError
from dt_runtime.gp import GPRegressor, MultiOutputGP

RNG = np.random.default_rng(0)


def doe_like(n_pts=40, reps=5, noise=1e-5):
    P = RNG.uniform(-0.5, 0.5, (n_pts, 3))
    X = np.array([[*p, v] for p in P for v in (0.3, 0.6, 0.9) for _ in range(reps)])
    f = lambda X: 1e-3 * (0.8 * np.sin(3 * X[:, 0]) + 0.5 * np.cos(2 * X[:, 1] + X[:, 2]) + 0.1 * X[:, 3])
    return X, f(X) + RNG.normal(0, noise, len(X)), f


def full_lml(g, X, y):
    th = g._theta
    Xs, ys = (X - g.x_mean_) / g.x_scale_, (y - g.mean_) / g.y_scale_
    d = X.shape[1]
    K = np.exp(th[d]) * np.exp(-0.5 * (((Xs[:, None] - Xs[None]) ** 2) / np.exp(2 * th[:d])).sum(2))
    K += np.exp(th[d + 1]) * np.eye(len(ys))
    L = linalg.cholesky(K, lower=True)
    a = linalg.cho_solve((L, True), ys)
    return -(0.5 * ys @ a + np.log(np.diag(L)).sum() + 0.5 * len(ys) * np.log(2 * np.pi))


def test_collapsed_likelihood_equals_full_data_likelihood():
    X, y, _ = doe_like(20, 4)
    g = GPRegressor(n_restarts=0).fit(X, y)
    for th in (g._theta, g._theta + 0.3):
        assert g.log_marginal_likelihood(th) == pytest.approx(
            full_lml(GPRegressor(n_restarts=0).fit(X, y, theta=th), X, y), rel=1e-8)


def test_gradient_matches_finite_differences():
    X, y, _ = doe_like(15, 3)
    g = GPRegressor(n_restarts=0).fit(X, y)
    th = g._theta + 0.1
    grad = -np.array(GPRegressor._nll(th, (g._U[:, None] - g._U[None]) ** 2, g._counts, g._ybar, g._ss, g._N)[1])
    h = 1e-6
    for k in range(len(th)):
        e = np.zeros_like(th)
        e[k] = h
        num = (g.log_marginal_likelihood(th + e) - g.log_marginal_likelihood(th - e)) / (2 * h)
        assert grad[k] == pytest.approx(num, rel=1e-4, abs=1e-6)


def test_recovers_function_and_is_calibrated():
    X, y, f = doe_like(60, 3, noise=2e-5)
    m = MultiOutputGP().fit(X, np.column_stack([y, 2 * y]))
    Xt = np.column_stack([RNG.uniform(-0.45, 0.45, (300, 3)), RNG.choice([0.3, 0.6, 0.9], 300)])
    yt = f(Xt) + RNG.normal(0, 2e-5, 300)
    mu, sd = m.predict(Xt, return_std=True)
    rmse = np.sqrt(np.mean((mu[:, 0] - f(Xt)) ** 2))
    assert rmse < 0.1 * np.std(y)
    z = np.abs(yt - mu[:, 0]) / np.sqrt(sd[:, 0] ** 2 + m.models_[0].noise_var_)
    assert 0.85 < np.mean(z < 1.96) <= 1.0


def test_fast_predictor_equals_predict_and_round_trip(tmp_path):
    X, y, _ = doe_like(20, 2)
    m = MultiOutputGP().fit(X, np.column_stack([y, -y, 0.5 * y]))
    fast = m.predictor()
    mu, sd = m.predict(X[:5], return_std=True)
    for i in range(5):
        a, b = fast(X[i])
        assert np.allclose(a, mu[i], atol=1e-12) and np.allclose(b, sd[i], atol=1e-9)
    m.save(tmp_path / "gp")
    m2 = MultiOutputGP.load(tmp_path / "gp")
    assert np.array_equal(m2.predict(X), m.predict(X))


def test_bad_inputs_and_versions(tmp_path):
    X, y, _ = doe_like(5, 2)
    y[3] = np.nan
    with pytest.raises(DataError, match="NaN"):
        GPRegressor().fit(X, y)
    m = MultiOutputGP().fit(X[:10], np.zeros((10, 1)) + X[:10, :1])
    m.save(tmp_path / "gp")
    p = tmp_path / "gp.json"
    p.write_text(p.read_text().replace('"format_version": 1', '"format_version": 99'))
    with pytest.raises(ModelError, match="format_version 99"):
        MultiOutputGP.load(tmp_path / "gp")


def test_sparse_path_close_to_exact():
    rng = np.random.default_rng(1)
    X = rng.uniform(-1, 1, (1200, 2))
    f = lambda X: np.sin(2 * X[:, 0]) * np.cos(X[:, 1])
    y = f(X) + rng.normal(0, 0.05, len(X))
    Xt = rng.uniform(-0.9, 0.9, (300, 2))
    exact = GPRegressor(n_restarts=0).fit(X, y)
    sparse = GPRegressor(n_restarts=0, sparse_threshold=400, exact_limit=400, n_inducing=300)
    sparse.fit(X, y)
    assert len(sparse._Xb) == 300  # the DTC path really ran
    e1 = np.sqrt(np.mean((exact.predict(Xt) - f(Xt)) ** 2))
    e2 = np.sqrt(np.mean((sparse.predict(Xt) - f(Xt)) ** 2))
    assert e2 < 1.3 * e1 + 0.005
