import json

import numpy as np
import pytest
from scipy import linalg

from dt_kernel.errors import DataError, ModelError
from dt_runtime.models.gp import GPRegressor, MultiOutputGP


def doe_like(rng, n_pts=40, reps=5, noise=1e-5):
    P = rng.uniform(-0.5, 0.5, (n_pts, 3))
    X = np.array([[*p, v] for p in P for v in (0.3, 0.6, 0.9) for _ in range(reps)])
    f = lambda X: 1e-3 * (0.8 * np.sin(3 * X[:, 0]) + 0.5 * np.cos(2 * X[:, 1] + X[:, 2]) + 0.1 * X[:, 3])
    return X, f(X) + rng.normal(0, noise, len(X)), f


def full_lml_and_grad(g, X, y, th):
    """Textbook exact log marginal likelihood on all rows (no collapse), GLS constant mean, and
    its analytic gradient (Rasmussen & Williams Eq. 5.9) in the same standardised space."""
    Xs, ys = (X - g.x_mean_) / g.x_scale_, (y - g.y_mean_) / g.y_scale_
    n, d = Xs.shape
    D2 = (Xs[:, None] - Xs[None]) ** 2
    E = np.exp(-0.5 * (D2 / np.exp(2 * th[:d])).sum(2))
    sf2, sn2 = np.exp(th[d]), np.exp(th[d + 1])
    K = sf2 * E + sn2 * np.eye(n)
    L = linalg.cholesky(K, lower=True)
    Ki1 = linalg.cho_solve((L, True), np.ones(n))
    r = ys - Ki1 @ ys / Ki1.sum()
    a = linalg.cho_solve((L, True), r)
    lml = -(0.5 * r @ a + np.log(np.diag(L)).sum() + 0.5 * n * np.log(2 * np.pi))
    W = np.outer(a, a) - linalg.cho_solve((L, True), np.eye(n))
    grad = [0.5 * np.sum(W * sf2 * E * D2[:, :, k]) / np.exp(2 * th[k]) for k in range(d)]
    grad += [0.5 * np.sum(W * sf2 * E), 0.5 * sn2 * np.trace(W)]
    return lml, np.array(grad)


def test_collapsed_likelihood_and_gradient_equal_full_data():
    X, y, _ = doe_like(np.random.default_rng(0), 20, 4)
    g = GPRegressor(n_restarts=0).fit(X, y)
    assert g.n_unique_ == 60 and g.n_train_ == 240
    for th in (g.theta_, g.theta_ + 0.3, g.theta_ - np.r_[0.5, 0, 0.2, 1, 0.1, 2.0]):
        lml, grad = g.log_marginal_likelihood(th, eval_gradient=True)
        ref, ref_grad = full_lml_and_grad(g, X, y, th)
        assert lml == pytest.approx(ref, rel=1e-8)
        # atol: the gradient is a difference of O(n) terms; at the optimum it is ~1e-4, so a
        # tolerance relative to it alone would test BLAS round-off (which varies with threads).
        assert np.allclose(grad, ref_grad, rtol=1e-6, atol=1e-6)


def test_gradient_matches_finite_differences():
    X, y, _ = doe_like(np.random.default_rng(1), 15, 3)
    g = GPRegressor(n_restarts=0).fit(X, y)
    th = g.theta_ + 0.1
    grad = g.log_marginal_likelihood(th, eval_gradient=True)[1]
    h = 1e-6
    for k in range(len(th)):
        e = np.zeros_like(th)
        e[k] = h
        num = (g.log_marginal_likelihood(th + e) - g.log_marginal_likelihood(th - e)) / (2 * h)
        assert grad[k] == pytest.approx(num, rel=1e-4, abs=1e-4)


def test_recovers_known_function_and_std_is_calibrated():
    rng = np.random.default_rng(2)
    noise = 2e-5
    X, y, f = doe_like(rng, 60, 3, noise=noise)
    m = MultiOutputGP(input_names=["x", "y", "z", "v"]).fit(X, np.column_stack([y, 2 * y]))
    Xt = np.column_stack([rng.uniform(-0.45, 0.45, (400, 3)), rng.choice([0.3, 0.6, 0.9], 400)])
    yt = f(Xt) + rng.normal(0, noise, 400)
    mu, sd = m.predict(Xt, return_std=True)
    assert np.sqrt(np.mean((mu[:, 0] - f(Xt)) ** 2)) < 0.05 * np.std(y)
    assert np.allclose(mu[:, 1], 2 * mu[:, 0], rtol=1e-3, atol=1e-3 * np.std(y))
    g = m.models_[0]
    assert g.noise_var_ == pytest.approx(noise ** 2, rel=0.3)  # replication noise recovered
    z = np.abs(yt - mu[:, 0]) / np.sqrt(sd[:, 0] ** 2 + g.noise_var_)
    assert 0.85 < np.mean(z < 1.96) < 0.995
    assert m.input_names_ == ["x", "y", "z", "v"] and m.output_names_ == ["y0", "y1"]


def test_fast_predictor_equals_predict_and_save_load_round_trip(tmp_path):
    X, y, _ = doe_like(np.random.default_rng(3), 20, 2)
    m = MultiOutputGP(output_names=["ex", "ey", "ez"], input_units="m, m, m, m/s").fit(X, np.column_stack([y, -y, 0.5 * y + X[:, 3] * 1e-4]))
    fast = m.predictor()
    assert fast.shared
    Xq = np.vstack([X[:5], X[:5] + 0.03])
    mu, sd = m.predict(Xq, return_std=True)
    for i in range(len(Xq)):
        a, b = fast(Xq[i])
        assert np.allclose(a, mu[i], rtol=0, atol=1e-12) and np.allclose(b, sd[i], rtol=1e-4, atol=1e-9)
    m.save(tmp_path / "gp")
    meta = json.loads((tmp_path / "gp.json").read_text())
    assert meta["output_names"] == ["ex", "ey", "ez"] and meta["units"]["inputs"] == "m, m, m, m/s"
    m2 = MultiOutputGP.load(tmp_path / "gp")
    mu2, sd2 = m2.predict(Xq, return_std=True)
    assert np.array_equal(mu2, mu) and np.array_equal(sd2, sd)
    assert np.array_equal(m2.predictor()(Xq[0])[0], fast(Xq[0])[0])
    assert m2.output_names_ == ["ex", "ey", "ez"]


def test_bad_inputs_and_versions(tmp_path):
    X, y, _ = doe_like(np.random.default_rng(4), 5, 2)
    y[3] = np.nan
    with pytest.raises(DataError, match="NaN.*row 3"):
        GPRegressor().fit(X, y)
    with pytest.raises(DataError, match="shape"):
        GPRegressor().fit(X[:, 0], y)
    with pytest.raises(DataError, match="Y must be"):
        MultiOutputGP().fit(X, np.zeros((len(X) - 1, 2)))
    with pytest.raises(ModelError, match="not fitted"):
        MultiOutputGP().predict(X)
    m = MultiOutputGP(n_restarts=0).fit(X[:10], X[:10, :2] * 1e-3)
    with pytest.raises(DataError, match="expected 4 columns"):
        m.predict(X[:, :3])
    with pytest.raises(DataError, match="finite"):
        m.predictor()(np.array([0.1, np.nan, 0.2, 0.3]))
    m.save(tmp_path / "gp")
    p = tmp_path / "gp.json"
    p.write_text(p.read_text().replace('"format_version": 2', '"format_version": 99'))
    with pytest.raises(ModelError, match="format_version 99.*newer"):
        MultiOutputGP.load(tmp_path / "gp")
    with pytest.raises(ModelError, match="cannot read"):
        MultiOutputGP.load(tmp_path / "missing")


def test_sparse_path_close_to_exact():
    rng = np.random.default_rng(5)
    X = rng.uniform(-1, 1, (1500, 2))
    f = lambda X: np.sin(2 * X[:, 0]) * np.cos(1.5 * X[:, 1])
    y = f(X) + rng.normal(0, 0.05, len(X))
    Xt = rng.uniform(-0.9, 0.9, (300, 2))
    exact = GPRegressor(n_restarts=0, n_hyper=600).fit(X, y)
    sparse = GPRegressor(n_restarts=0, n_hyper=600, sparse_threshold=1000, n_inducing=150).fit(X, y)
    assert sparse.sparse_ and not exact.sparse_ and len(sparse._Xb) == 150
    assert np.allclose(sparse.theta_, exact.theta_)  # same hyperparameters, only the posterior differs
    (m1, s1), (m2, s2) = exact.predict(Xt, return_std=True), sparse.predict(Xt, return_std=True)
    e1 = np.sqrt(np.mean((m1 - f(Xt)) ** 2))
    e2 = np.sqrt(np.mean((m2 - f(Xt)) ** 2))
    assert e2 < 1.2 * e1 + 0.002
    assert np.all(s2 >= s1 - 1e-6)  # VFE/DTC variance never undercuts the exact posterior's
    fast = MultiOutputGP(n_restarts=0, n_hyper=600, sparse_threshold=1000, n_inducing=150).fit(X, y[:, None]).predictor()
    mu, sd = fast(Xt[0])
    assert mu[0] == pytest.approx(m2[0], abs=1e-9) and sd[0] == pytest.approx(s2[0], abs=1e-7)


def test_weak_smooth_signal_with_replicates_is_not_fitted_as_noise():
    # e_MVS-LT-like data: a smooth field only ~2x the replication noise, 3 replicates per input.
    # An unbounded optimiser can fit each replicate mean as independent noise (length scales
    # -> 0) and then predicts only the mean between points.
    from dt_runtime.models.gp import MultiOutputGP

    rng = np.random.default_rng(5)
    P = rng.uniform(-0.5, 0.5, (60, 3))
    X = np.array([[*p, v] for p in P for v in (0.3, 0.6, 0.9) for _ in range(3)])
    f = lambda X: 1e-4 * np.sin(2 * X[:, 0] + X[:, 1])
    y = f(X) + rng.normal(0, 5e-5, len(X))
    m = MultiOutputGP(seed=0).fit(X, y[:, None])
    Xt = np.column_stack([rng.uniform(-0.45, 0.45, (200, 3)), rng.choice([0.3, 0.6, 0.9], 200)])
    rmse = np.sqrt(np.mean((m.predict(Xt)[:, 0] - f(Xt)) ** 2))
    assert rmse < 0.5 * np.std(f(Xt))


def textbook_posterior(g, X, y, Xq):
    """Latent mean and std at Xq of the exact GP on all rows (no collapse, no shared factor) at
    g's hyperparameters and constant mean, in output units."""
    d = X.shape[1]
    ell, sf2, sn2 = np.exp(g.theta_[:d]), np.exp(g.theta_[d]), np.exp(g.theta_[d + 1])
    Xs, Xqs = (X - g.x_mean_) / g.x_scale_, (Xq - g.x_mean_) / g.x_scale_

    def k(A, B):
        return sf2 * np.exp(-0.5 * (((A[:, None] - B[None]) / ell) ** 2).sum(2))

    L = linalg.cholesky(k(Xs, Xs) + sn2 * np.eye(len(X)), lower=True)
    ks = k(Xqs, Xs)
    mean = g.mean_ + g.y_scale_ * (ks @ linalg.cho_solve((L, True), (y - g.y_mean_) / g.y_scale_ - g._beta))
    v = linalg.solve_triangular(L, ks.T, lower=True)
    return mean, g.y_scale_ * np.sqrt(sf2 - (v ** 2).sum(0))


@pytest.mark.parametrize("n_hyper", [1000, 40])
def test_exact_posterior_equals_the_textbook_one(n_hyper):
    # n_hyper 1000: the likelihood's Cholesky factor at the learned theta is the posterior's;
    # 40 (< 90 distinct inputs): hyperparameters on a subset, the posterior factorised anew.
    rng = np.random.default_rng(6)
    X, y, _ = doe_like(rng, 30, 3, noise=1e-4)
    g = GPRegressor(n_restarts=0, n_hyper=n_hyper).fit(X, y)
    assert g.n_unique_ == 90 and not g.sparse_
    Xq = np.vstack([X[::7], np.column_stack([rng.uniform(-0.5, 0.5, (20, 3)), rng.uniform(0.3, 0.9, 20)])])
    mu, sd = g.predict(Xq, return_std=True)
    m_ref, s_ref = textbook_posterior(g, X, y, Xq)
    np.testing.assert_allclose(mu, m_ref, rtol=0, atol=1e-9 * np.std(y))
    np.testing.assert_allclose(sd, s_ref, rtol=1e-6, atol=1e-6 * np.sqrt(g.signal_var_))
    # K^-1 B by the factor (the effects' GLS) equals the variance's K^-1 times B
    B = rng.normal(size=(g.n_unique_, 4))
    np.testing.assert_allclose(g._precision_dot(B), g._Q @ B, rtol=1e-7, atol=1e-7 * np.abs(g._Q @ B).max())


def test_sparse_posterior_equals_the_vfe_formula():
    # Titsias' VFE/DTC posterior written out with plain inverses on a small problem:
    # Sigma = (Kzz + Kzu Lam Kuz)^-1, Lam = n_i / s_n^2; mean = k' Sigma Kzu Lam r;
    # var = s_f^2 - k' (Kzz^-1 - Sigma) k.
    rng = np.random.default_rng(7)
    X = np.repeat(rng.uniform(-1, 1, (300, 2)), rng.integers(1, 4, 300), axis=0)
    y = np.sin(2 * X[:, 0]) * np.cos(1.5 * X[:, 1]) + rng.normal(0, 0.05, len(X))
    g = GPRegressor(n_restarts=0, sparse_threshold=100, n_inducing=40).fit(X, y)
    assert g.sparse_ and len(g._Xb) == 40
    d = 2
    ell, sf2, sn2 = np.exp(g.theta_[:d]), np.exp(g.theta_[d]), np.exp(g.theta_[d + 1])

    def k(A, B):
        return sf2 * np.exp(-0.5 * (((A[:, None] - B[None]) / ell) ** 2).sum(2))

    Z, U = g._Xb, g._U
    Kzz = k(Z, Z) + 1e-8 * sf2 * np.eye(len(Z))
    Kzu, lam = k(Z, U), g._counts / sn2
    A = Kzz + (Kzu * lam) @ Kzu.T  # Sigma^-1; condition ~1e14 here: solves, not inverses
    Xq = rng.uniform(-0.9, 0.9, (50, 2))
    kq = k((Xq - g.x_mean_) / g.x_scale_, Z)
    mean = g.mean_ + g.y_scale_ * (kq @ np.linalg.solve(A, Kzu @ (lam * (g._ybar - g._beta))))
    var = sf2 - np.einsum("ij,ji->i", kq, np.linalg.solve(Kzz, kq.T) - np.linalg.solve(A, kq.T))
    mu, sd = g.predict(Xq, return_std=True)
    np.testing.assert_allclose(mu, mean, rtol=0, atol=1e-6 * np.std(y))
    np.testing.assert_allclose(sd, g.y_scale_ * np.sqrt(np.clip(var, 0, None)), rtol=0,
                               atol=1e-4 * np.sqrt(g.signal_var_))


def test_outputs_share_the_inputs_and_equal_single_output_fits():
    rng = np.random.default_rng(8)
    X = rng.uniform(-1, 1, (400, 3))
    Y = np.column_stack([np.sin(2 * X[:, 0]), X[:, 1] * X[:, 2]]) + rng.normal(0, 0.05, (400, 2))
    opts = dict(n_restarts=0, sparse_threshold=200, n_inducing=50, n_hyper=150)
    m = MultiOutputGP(seed=3, **opts).fit(X, Y)
    for j, g in enumerate(m.models_):
        alone = GPRegressor(seed=3 + j, **opts).fit(X, Y[:, j])
        assert np.array_equal(g.theta_, alone.theta_) and np.array_equal(g._Xb, alone._Xb)
        np.testing.assert_allclose(g.predict(X[:20]), alone.predict(X[:20]), rtol=0, atol=1e-12)


def test_gradient_at_short_and_long_length_scales_matches_finite_differences():
    # The length scales' gradient contracts through the inputs (sum_ij A_ij (u_i - u_j)^2 =
    # 2 u^2' A1 - 2 u'Au): checked where it cancels most (l = 0.1 spread) and where the kernel
    # ignores a dimension (l = e^6), on inputs far from their origin.
    X, y, _ = doe_like(np.random.default_rng(9), 25, 2)
    X[:, :3] += 1e3
    g = GPRegressor(n_restarts=0).fit(X, y)
    th = np.r_[np.log(0.1), 6.0, 0.0, np.log(0.3), 0.5, np.log(1e-3)]
    grad = g.log_marginal_likelihood(th, eval_gradient=True)[1]
    h = 1e-4  # the likelihood carries ~1e-10 of round-off (the kernel from one product): h >> 1e-10
    for k in range(len(th)):
        e = np.zeros_like(th)
        e[k] = h
        num = (g.log_marginal_likelihood(th + e) - g.log_marginal_likelihood(th - e)) / (2 * h)
        assert grad[k] == pytest.approx(num, rel=1e-5, abs=1e-5)


def test_a_direction_the_kernel_no_longer_sees_gets_its_true_tiny_gradient():
    # Speed has 3 levels 1.2 standard deviations apart: at a length scale of 0.1 the kernel
    # between levels is exp(-75), so the likelihood's slope along it is ~1e-30. A gradient
    # written as a difference of large sums (2 u^2'A1 - 2 u'Au) returned its round-off (~1e-10)
    # instead, whose sign decided whether L-BFGS-B left the bound: on the demo's e_MVS-LT map it
    # then converged to a worse optimum (nll 336 instead of 316).
    X, y, _ = doe_like(np.random.default_rng(10), 30, 3)
    g = GPRegressor(n_restarts=0).fit(X, y)
    th = np.r_[0.5, 0.3, 0.2, np.log(0.1), 1.0, np.log(1e-2)]
    grad = g.log_marginal_likelihood(th, eval_gradient=True)[1]
    assert abs(grad[3]) < 1e-20
    assert np.all(np.abs(grad[[0, 1, 2, 4, 5]]) > 1e-6)  # the others are ordinary numbers
