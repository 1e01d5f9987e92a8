"""Gaussian Process Regression error maps (paper Sect. 3.2): constant mean, ARD squared-
exponential kernel, white noise; hyperparameters by maximum marginal likelihood (L-BFGS-B on
log-parameters with the analytic gradient, Cholesky via scipy.linalg).

    y = beta + f(x) + eps,   f ~ GP(0, s_f^2 exp(-1/2 sum_k (x_k - x'_k)^2 / l_k^2)),
    eps ~ N(0, s_n^2)

The constant mean beta is the generalised-least-squares (maximum-likelihood) estimate at the
current kernel, as MATLAB's fitrgp 'constant' basis does; by the envelope theorem the gradient
of the profiled likelihood is the partial gradient at that beta.

Exact speed-up for calibration data (not an approximation): the paper's DOE repeats every input
(62 points x 3 speeds x 9 replications = 1,674 rows, 186 distinct inputs). With n_i replicates
of input i, mean target ybar_i and within-group sum of squares SS_i, integrating out f_i gives

  log p(y) = log N(ybar | beta, K + s_n^2 diag(1/n_i))
             + sum_i [ -(n_i - 1)/2 log(2 pi s_n^2) - 1/2 log n_i - SS_i / (2 s_n^2) ]

so the cubic work is on distinct inputs only and the posterior of f is unchanged.

Large sets: when the distinct inputs exceed `sparse_threshold`, the posterior is the sparse
VFE/DTC projection (Titsias 2009) onto `n_inducing` inducing inputs chosen by farthest-point
sampling (deterministic, so every output of a MultiOutputGP shares them). Hyperparameters are
then (and whenever there are more than `n_hyper` distinct inputs) learned by the exact collapsed
marginal likelihood of a seeded random subset of `n_hyper` distinct inputs with their replicates.

Follows scikit-learn's estimator contract (no sklearn import: get_params/set_params are local);
the per-command path is `MultiOutputGP.predictor()`, a `FastPredictor` of plain numpy arrays.
Returned standard deviations are those of the latent error map f (the model's uncertainty);
the replication noise variance is `noise_var_`.
"""
from __future__ import annotations

import inspect
import json
from pathlib import Path

import numpy as np
from scipy import linalg, optimize
from scipy.linalg import lapack
from scipy.spatial.distance import cdist

from dt_kernel.errors import DataError, ModelError

FORMAT_VERSION = 2
LOG2PI = float(np.log(2 * np.pi))
_KIND = "cobot-dt MultiOutputGP"


# --- helpers ---------------------------------------------------------------------------------
def _as_2d(X, what: str) -> np.ndarray:
    try:
        X = np.asarray(X, dtype=float)
    except (TypeError, ValueError) as exc:
        raise DataError(f"{what}: not numeric ({exc})") from exc
    if X.ndim == 1:
        raise DataError(f"{what}: expected a 2-D array (n_samples, n_features), got shape {X.shape}; "
                        "use X.reshape(-1, 1) for one feature or X[None, :] for one sample")
    if X.ndim != 2 or X.shape[0] == 0 or X.shape[1] == 0:
        raise DataError(f"{what}: expected a 2-D array (n_samples, n_features), got shape {X.shape}")
    bad = ~np.isfinite(X)
    if bad.any():
        r, c = np.argwhere(bad)[0]
        raise DataError(f"{what}: {int(bad.sum())} NaN or infinite value(s), first at row {r}, column {c}")
    return X


def _names(obj) -> list[str] | None:
    cols = getattr(obj, "columns", None)
    return [str(c) for c in cols] if cols is not None else None


def _inv_from_chol(L: np.ndarray) -> np.ndarray:
    """K^-1 from its lower Cholesky factor (LAPACK potri), symmetrised."""
    Kinv, info = lapack.dpotri(L, lower=1)
    if info != 0:
        raise linalg.LinAlgError(f"potri failed ({info})")
    Kinv = np.tril(Kinv)
    return Kinv + np.tril(Kinv, -1).T


def _collapse(X: np.ndarray, y: np.ndarray):
    """Distinct rows of X, replicate counts, mean targets and per-group sums of squares."""
    U, inv, counts = np.unique(X, axis=0, return_inverse=True, return_counts=True)
    inv = inv.ravel()
    ybar = np.bincount(inv, weights=y, minlength=len(U)) / counts
    ss = np.bincount(inv, weights=(y - ybar[inv]) ** 2, minlength=len(U))
    return U, counts.astype(float), ybar, ss


def _farthest_points(U: np.ndarray, m: int) -> np.ndarray:
    """Indices of m rows of U by farthest-point sampling, started at the row nearest the centroid."""
    m = min(m, len(U))
    idx = np.empty(m, dtype=np.intp)
    idx[0] = int(np.argmin(((U - U.mean(0)) ** 2).sum(1)))
    dmin = ((U - U[idx[0]]) ** 2).sum(1)
    for j in range(1, m):
        idx[j] = int(np.argmax(dmin))
        np.minimum(dmin, ((U - U[idx[j]]) ** 2).sum(1), out=dmin)
    return idx


def _se(A: np.ndarray, B: np.ndarray, ell: np.ndarray, sf2: float) -> np.ndarray:
    return sf2 * np.exp(-0.5 * cdist(A / ell, B / ell, "sqeuclidean"))


class _Params:
    """Minimal scikit-learn get_params/set_params (parameters are the keyword-only __init__ args)."""

    @classmethod
    def _param_names(cls):
        sig = inspect.signature(cls.__init__)
        return [p for p in sig.parameters if p != "self"]

    def get_params(self, deep: bool = True) -> dict:
        return {k: getattr(self, k) for k in self._param_names()}

    def set_params(self, **params):
        for k, v in params.items():
            if k not in self._param_names():
                raise ValueError(f"invalid parameter {k!r} for {type(self).__name__}")
            setattr(self, k, v)
        return self

    def __repr__(self):
        return f"{type(self).__name__}({', '.join(f'{k}={v!r}' for k, v in self.get_params().items())})"


# --- likelihood ------------------------------------------------------------------------------
def collapsed_nll(theta: np.ndarray, D2: np.ndarray, counts: np.ndarray, ybar: np.ndarray,
                  ss: float, N: int, want_grad: bool = True):
    """Negative exact log marginal likelihood of all N rows from the collapsed statistics.

    theta = [log l_1..log l_d, log s_f^2, log s_n^2] (standardised units); D2 (d, U, U) holds the
    per-dimension squared distances of the distinct inputs. Returns (nll, grad, beta)."""
    d = D2.shape[0]
    inv_ell2 = np.exp(-2 * theta[:d])
    sf2, sn2 = np.exp(theta[d]), np.exp(theta[d + 1])
    U = len(ybar)
    E = np.exp(-0.5 * np.tensordot(inv_ell2, D2, axes=1))
    K = sf2 * E
    K[np.diag_indices(U)] += sn2 / counts
    try:
        L = linalg.cholesky(K, lower=True, check_finite=False)
    except (linalg.LinAlgError, ValueError):
        return 1e25, np.zeros_like(theta), 0.0
    one = np.ones(U)
    Ki1 = linalg.cho_solve((L, True), one, check_finite=False)
    beta = float(Ki1 @ ybar / (Ki1 @ one))  # GLS constant mean
    r = ybar - beta
    alpha = linalg.cho_solve((L, True), r, check_finite=False)
    nll = 0.5 * r @ alpha + np.log(np.diag(L)).sum() + 0.5 * U * LOG2PI
    # Within-replicate part (module docstring).
    nll += 0.5 * (N - U) * (LOG2PI + np.log(sn2)) + 0.5 * np.log(counts).sum() + ss / (2 * sn2)
    if not want_grad:
        return float(nll), None, beta
    W = np.outer(alpha, alpha) - _inv_from_chol(L)  # d lml / dK
    WK = W * K
    WE = WK - np.diag(np.diag(W) * sn2 / counts)  # W o (s_f^2 E)
    g = np.empty_like(theta)
    g[:d] = -0.5 * np.tensordot(D2, WE, axes=([1, 2], [0, 1])) * inv_ell2
    g[d] = -0.5 * WE.sum()
    g[d + 1] = -0.5 * sn2 * np.sum(np.diag(W) / counts) + 0.5 * (N - U) - ss / (2 * sn2)
    return float(nll), g, beta


def _d2(U: np.ndarray) -> np.ndarray:
    return np.stack([(U[:, k, None] - U[None, :, k]) ** 2 for k in range(U.shape[1])])


# --- single output ---------------------------------------------------------------------------
class GPRegressor(_Params):
    """One output. Inputs and output are standardised internally; the learned attributes are in
    input/output units: `length_scales_` (input units), `signal_var_`, `noise_var_` (output
    units squared), `mean_` (constant mean, output units), `log_marginal_likelihood_`.

    noise_floor: lower bound of the noise variance relative to the output variance.
    n_restarts: seeded random starts of L-BFGS-B in addition to the default start.
    sparse_threshold: above this many distinct inputs the posterior is sparse (VFE/DTC).
    n_inducing: inducing inputs of the sparse posterior.
    n_hyper: hyperparameters are learned on at most this many distinct inputs (seeded subset).
    """

    def __init__(self, *, noise_floor: float = 1e-10, n_restarts: int = 1, seed: int = 0,
                 max_iter: int = 200, sparse_threshold: int = 3000, n_inducing: int = 600,
                 n_hyper: int = 1000, min_length_scale: float = 0.1):
        self.min_length_scale = min_length_scale  # in units of each input's standard deviation
        self.noise_floor = noise_floor
        self.n_restarts = n_restarts
        self.seed = seed
        self.max_iter = max_iter
        self.sparse_threshold = sparse_threshold
        self.n_inducing = n_inducing
        self.n_hyper = n_hyper

    # --- fit ----------------------------------------------------------------------------
    def fit(self, X, y, theta=None) -> "GPRegressor":
        """Learn hyperparameters and the posterior. With `theta` (the standardised log-
        parameters, see `theta_`) the hyperparameters are kept and only the posterior is built."""
        X = _as_2d(X, "GPRegressor.fit X")
        y = np.asarray(y, dtype=float)
        if y.ndim == 2 and y.shape[1] == 1:
            y = y[:, 0]
        if y.ndim != 1 or len(y) != len(X):
            raise DataError(f"GPRegressor.fit: y must have shape ({len(X)},) to match X {X.shape}, got {y.shape}")
        if not np.all(np.isfinite(y)):
            raise DataError(f"GPRegressor.fit y: {int((~np.isfinite(y)).sum())} NaN or infinite value(s), "
                            f"first at row {int(np.argmax(~np.isfinite(y)))}")
        if len(y) < 2:
            raise DataError(f"GPRegressor.fit: need at least 2 rows, got {len(y)}")
        n, d = X.shape
        self.n_features_in_ = d
        self.n_train_ = n
        self.x_mean_ = X.mean(0)
        self.x_scale_ = X.std(0)
        self.x_scale_[self.x_scale_ == 0] = 1.0
        self.y_mean_ = float(y.mean())
        self.y_scale_ = float(y.std()) or 1.0
        Uraw, counts, ybar, ss = _collapse(X, (y - self.y_mean_) / self.y_scale_)
        U = (Uraw - self.x_mean_) / self.x_scale_
        self.n_unique_ = len(U)
        # Hyperparameters: exact collapsed likelihood, on a seeded subset if there are many inputs.
        sub = np.arange(len(U))
        if len(U) > self.n_hyper:
            sub = np.sort(np.random.default_rng(self.seed).choice(len(U), self.n_hyper, replace=False))
        Ns = int(counts[sub].sum())
        stats = (_d2(U[sub]), counts[sub], ybar[sub], float(ss[sub].sum()), Ns)
        if theta is None:
            theta = self._optimise(stats, d)
        theta = np.asarray(theta, dtype=float)
        if theta.shape != (d + 2,):
            raise ModelError(f"GPRegressor.fit: theta must have {d + 2} entries, got {theta.shape}")
        nll, _, beta = collapsed_nll(theta, *stats, want_grad=False)
        self.theta_ = theta
        self.log_marginal_likelihood_ = -nll  # of the (sub)set used for learning
        self._beta = beta
        self.length_scales_ = np.exp(theta[:d]) * self.x_scale_
        self.signal_var_ = float(np.exp(theta[d])) * self.y_scale_ ** 2
        self.noise_var_ = float(np.exp(theta[d + 1])) * self.y_scale_ ** 2
        self.mean_ = self.y_mean_ + self.y_scale_ * beta
        self.sparse_ = len(U) > self.sparse_threshold
        self._U, self._counts, self._ybar, self._ss = U, counts, ybar, ss
        try:
            self._posterior()
        except linalg.LinAlgError as exc:
            raise ModelError(f"GPRegressor.fit: kernel matrix not positive definite at the learned "
                             f"hyperparameters ({exc}); raise noise_floor") from exc
        return self

    def _optimise(self, stats, d: int) -> np.ndarray:
        rng = np.random.default_rng(self.seed)
        starts = [np.r_[np.zeros(d), 0.0, np.log(0.01)]]
        starts += [np.r_[rng.uniform(-1.5, 1.5, d), rng.uniform(-1.0, 1.0), rng.uniform(-9.0, -1.0)]
                   for _ in range(self.n_restarts)]
        floor = np.log(max(self.noise_floor, 1e-300))
        # Length scales below a tenth of an input's spread cannot be resolved by a calibration
        # plan (the DOE spacing is ~0.4 spread) and let the optimiser fall into a degenerate
        # optimum that fits each replicate mean as independent noise and predicts only the
        # mean between points (seen on e_MVS-LT, where the smooth signal is weak).
        bounds = [(np.log(self.min_length_scale), 6.0)] * d + [(-8.0, 5.0), (floor, 1.0)]
        starts = [np.clip(s, [b[0] for b in bounds], [b[1] for b in bounds]) for s in starts]
        best = None
        for s in starts:
            r = optimize.minimize(lambda t: collapsed_nll(t, *stats)[:2], s, jac=True, method="L-BFGS-B",
                                  bounds=bounds, options={"maxiter": self.max_iter})
            if best is None or r.fun < best.fun:
                best = r
        if best.fun >= 1e24:
            raise ModelError("GPRegressor.fit: marginal-likelihood optimisation failed from every start")
        return best.x

    def log_marginal_likelihood(self, theta=None, eval_gradient: bool = False):
        """Exact log marginal likelihood (all training rows, via the collapse) at `theta`
        (standardised log-parameters; default the learned ones), optionally with its gradient."""
        self._check_fitted()
        theta = self.theta_ if theta is None else np.asarray(theta, dtype=float)
        nll, g, _ = collapsed_nll(theta, _d2(self._U), self._counts, self._ybar, float(self._ss.sum()),
                                  self.n_train_, want_grad=eval_gradient)
        return (-nll, -g) if eval_gradient else -nll

    def _posterior(self) -> None:
        d = self.n_features_in_
        ell = np.exp(self.theta_[:d])
        sf2, sn2 = float(np.exp(self.theta_[d])), float(np.exp(self.theta_[d + 1]))
        U, counts, r = self._U, self._counts, self._ybar - self._beta
        if not self.sparse_:
            K = _se(U, U, ell, sf2)
            K[np.diag_indices(len(U))] += sn2 / counts
            L = linalg.cholesky(K, lower=True)
            self._Xb = U
            self._alpha = linalg.cho_solve((L, True), r)
            self._Q = _inv_from_chol(L)  # var = s_f^2 - k^T K^-1 k
            return
        # VFE/DTC posterior: Sigma = (Kzz + Kzu Lam Kuz)^-1, Lam = n_i / s_n^2;
        # mean = k_z^T Sigma Kzu Lam r;  var = s_f^2 - k_z^T (Kzz^-1 - Sigma) k_z.
        Z = U[_farthest_points(U, self.n_inducing)]
        M = len(Z)
        Kzz = _se(Z, Z, ell, sf2)
        Kzz[np.diag_indices(M)] += 1e-8 * sf2
        Lz = linalg.cholesky(Kzz, lower=True)
        sl = np.sqrt(counts / sn2)
        V = linalg.solve_triangular(Lz, _se(Z, U, ell, sf2), lower=True) * sl  # Lz^-1 Kzu Lam^1/2
        B = V @ V.T
        B[np.diag_indices(M)] += 1.0
        LB = linalg.cholesky(B, lower=True)
        c = linalg.cho_solve((LB, True), V @ (sl * r))
        self._Xb = Z
        self._alpha = linalg.solve_triangular(Lz, c, lower=True, trans="T")
        Lzi = linalg.solve_triangular(Lz, np.eye(M), lower=True)
        Mid = np.eye(M) - _inv_from_chol(LB)
        self._Q = Lzi.T @ Mid @ Lzi
        self._Q = 0.5 * (self._Q + self._Q.T)

    # --- predict ------------------------------------------------------------------------
    def _check_fitted(self):
        if not hasattr(self, "theta_"):
            raise ModelError(f"{type(self).__name__} is not fitted; call fit(X, y) first")

    def predict(self, X, return_std: bool = False):
        """Mean (n,) and, with return_std, the standard deviation (n,) of the latent error map."""
        self._check_fitted()
        X = _as_2d(X, "GPRegressor.predict X")
        if X.shape[1] != self.n_features_in_:
            raise DataError(f"GPRegressor.predict X: expected {self.n_features_in_} columns, got {X.shape[1]}")
        d = self.n_features_in_
        ell, sf2 = np.exp(self.theta_[:d]), float(np.exp(self.theta_[d]))
        k = _se((X - self.x_mean_) / self.x_scale_, self._Xb, ell, sf2)
        mean = self.mean_ + self.y_scale_ * (k @ self._alpha)
        if not return_std:
            return mean
        var = sf2 - np.einsum("ij,ij->i", k @ self._Q, k)
        return mean, self.y_scale_ * np.sqrt(np.clip(var, 0.0, None))

    def score(self, X, y) -> float:
        """Coefficient of determination R^2 (scikit-learn's regressor convention)."""
        y = np.asarray(y, dtype=float).ravel()
        res = np.sum((y - self.predict(X)) ** 2)
        return float(1 - res / np.sum((y - y.mean()) ** 2))

    # --- persistence helpers ------------------------------------------------------------
    _META = ("n_features_in_", "n_train_", "n_unique_", "y_mean_", "y_scale_", "_beta",
             "signal_var_", "noise_var_", "mean_", "log_marginal_likelihood_", "sparse_")
    _ARR = ("x_mean_", "x_scale_", "theta_", "length_scales_", "_Xb", "_alpha", "_Q")

    def _state(self) -> tuple[dict, dict]:
        meta = {k.lstrip("_"): getattr(self, k) for k in self._META}
        meta = {k: (bool(v) if isinstance(v, (bool, np.bool_)) else v) for k, v in meta.items()}
        meta["params"] = self.get_params()
        meta["theta"] = self.theta_.tolist()
        meta["length_scales"] = self.length_scales_.tolist()
        return meta, {k.strip("_"): getattr(self, k) for k in self._ARR}

    @classmethod
    def _from_state(cls, meta: dict, arrays: dict) -> "GPRegressor":
        g = cls(**meta["params"])
        for k in cls._META:
            setattr(g, k, meta[k.lstrip("_")])
        for k in cls._ARR:
            setattr(g, k, np.asarray(arrays[k.strip("_")], dtype=float))
        return g


# --- lean per-command predictor --------------------------------------------------------------
class FastPredictor:
    """Mean (k,) and latent std (k,) of every output at one input x (d,), from precomputed numpy
    arrays only. When all outputs share training inputs and scaling (always so for a
    MultiOutputGP), the k outputs are evaluated together: one distance matrix, one stacked
    matrix-vector product for the variances."""

    def __init__(self, models: list[GPRegressor]):
        g0 = models[0]
        self.d = g0.n_features_in_
        self.k = len(models)
        self.shared = all(np.array_equal(g._Xb, g0._Xb) and np.array_equal(g.x_mean_, g0.x_mean_)
                          and np.array_equal(g.x_scale_, g0.x_scale_) for g in models)
        self._xm, self._xs = g0.x_mean_.copy(), g0.x_scale_.copy()
        d = self.d
        self._neg_half_inv_ell2 = np.column_stack([-0.5 * np.exp(-2 * g.theta_[:d]) for g in models])  # (d,k)
        self._sf2 = np.array([np.exp(g.theta_[d]) for g in models])
        self._m0 = np.array([g.mean_ for g in models])
        self._ys = np.array([g.y_scale_ for g in models])
        if self.shared:
            self._Xb = np.ascontiguousarray(g0._Xb)
            self._alpha = np.column_stack([g._alpha for g in models])  # (U,k)
            self._Q = np.stack([g._Q for g in models])  # (k,U,U)
        else:
            self._per = [(g.x_mean_, g.x_scale_, g._Xb, g._alpha, g._Q) for g in models]

    def __call__(self, x) -> tuple[np.ndarray, np.ndarray]:
        x = np.asarray(x, dtype=float)
        if x.shape != (self.d,) or not np.isfinite(x).all():
            raise DataError(f"FastPredictor: x must be {self.d} finite numbers, got shape {x.shape}: {x}")
        if self.shared:
            diff = self._Xb - (x - self._xm) / self._xs
            K = self._sf2 * np.exp((diff * diff) @ self._neg_half_inv_ell2)  # (U,k)
            mean = self._m0 + self._ys * np.einsum("uk,uk->k", K, self._alpha)
            Kt = K.T
            var = self._sf2 - np.einsum("ku,ku->k", Kt, np.matmul(self._Q, Kt[:, :, None])[:, :, 0])
            return mean, self._ys * np.sqrt(np.maximum(var, 0.0))
        mean, std = np.empty(self.k), np.empty(self.k)
        for j, (xm, xs, Xb, alpha, Q) in enumerate(self._per):
            diff = Xb - (x - xm) / xs
            kv = self._sf2[j] * np.exp((diff * diff) @ self._neg_half_inv_ell2[:, j])
            mean[j] = self._m0[j] + self._ys[j] * (kv @ alpha)
            var = self._sf2[j] - kv @ (Q @ kv)
            std[j] = self._ys[j] * np.sqrt(max(var, 0.0))
        return mean, std


# --- several outputs -------------------------------------------------------------------------
class MultiOutputGP(_Params):
    """One GPRegressor per output column (the paper: one model per axis).

    `input_units`/`output_units` are recorded in the saved model (SI inside the code)."""

    def __init__(self, *, noise_floor: float = 1e-10, n_restarts: int = 1, seed: int = 0,
                 max_iter: int = 200, sparse_threshold: int = 3000, n_inducing: int = 600,
                 n_hyper: int = 1000, min_length_scale: float = 0.1, input_names=None,
                 output_names=None, input_units=None, output_units=None):
        self.min_length_scale = min_length_scale
        self.noise_floor = noise_floor
        self.n_restarts = n_restarts
        self.seed = seed
        self.max_iter = max_iter
        self.sparse_threshold = sparse_threshold
        self.n_inducing = n_inducing
        self.n_hyper = n_hyper
        self.input_names = input_names
        self.output_names = output_names
        self.input_units = input_units
        self.output_units = output_units

    _GP_PARAMS = ("noise_floor", "n_restarts", "max_iter", "sparse_threshold", "n_inducing", "n_hyper",
                  "min_length_scale")

    def fit(self, X, Y, *, input_names=None, output_names=None, thetas=None) -> "MultiOutputGP":
        in_names = input_names or _names(X) or self.input_names
        out_names = output_names or _names(Y) or self.output_names
        X = _as_2d(X, "MultiOutputGP.fit X")
        Y = np.asarray(Y, dtype=float)
        if Y.ndim == 1:
            Y = Y[:, None]
        if Y.ndim != 2 or len(Y) != len(X):
            raise DataError(f"MultiOutputGP.fit: Y must be ({len(X)}, k) to match X {X.shape}, got {Y.shape}")
        bad = ~np.isfinite(Y)
        if bad.any():
            r, c = np.argwhere(bad)[0]
            raise DataError(f"MultiOutputGP.fit Y: {int(bad.sum())} NaN or infinite value(s), "
                            f"first at row {r}, column {c}")
        for what, names, n in (("input_names", in_names, X.shape[1]), ("output_names", out_names, Y.shape[1])):
            if names is not None and len(names) != n:
                raise DataError(f"MultiOutputGP.fit: {len(names)} {what} {list(names)} for {n} columns")
        self.input_names_ = list(in_names) if in_names is not None else [f"x{i}" for i in range(X.shape[1])]
        self.output_names_ = list(out_names) if out_names is not None else [f"y{j}" for j in range(Y.shape[1])]
        kw = {p: getattr(self, p) for p in self._GP_PARAMS}
        self.models_ = [GPRegressor(seed=self.seed + j, **kw).fit(X, Y[:, j], None if thetas is None else thetas[j])
                        for j in range(Y.shape[1])]
        self.n_features_in_ = X.shape[1]
        return self

    @property
    def thetas_(self) -> list[np.ndarray]:
        return [g.theta_.copy() for g in self.models_]

    def _check_fitted(self):
        if not hasattr(self, "models_"):
            raise ModelError("MultiOutputGP is not fitted; call fit(X, Y) or load(stem) first")

    def predict(self, X, return_std: bool = False):
        """(n, k) means and, with return_std, (n, k) latent standard deviations."""
        self._check_fitted()
        out = [g.predict(X, return_std) for g in self.models_]
        if not return_std:
            return np.column_stack(out)
        return np.column_stack([o[0] for o in out]), np.column_stack([o[1] for o in out])

    def predictor(self) -> FastPredictor:
        self._check_fitted()
        return FastPredictor(self.models_)

    # --- persistence (JSON + NPZ, no pickle) ---------------------------------------------
    def save(self, stem) -> None:
        self._check_fitted()
        stem = Path(stem)
        metas, arrays = [], {}
        for j, g in enumerate(self.models_):
            m, a = g._state()
            metas.append(m)
            arrays.update({f"{k}_{j}": v for k, v in a.items()})
        meta = {"format_version": FORMAT_VERSION, "kind": _KIND,
                "kernel": "constant mean + signal_var * ARD squared exponential + white noise",
                "input_names": self.input_names_, "output_names": self.output_names_,
                "units": {"inputs": self.input_units or "SI", "outputs": self.output_units or "SI",
                          "length_scales": "input units", "signal_var/noise_var": "output units squared"},
                "params": self.get_params(), "models": metas}
        try:
            stem.with_suffix(".json").write_text(json.dumps(meta, indent=1))
            np.savez(stem.with_suffix(".npz"), **arrays)
        except OSError as exc:
            raise ModelError(f"{stem}: cannot write GP model ({exc})") from exc

    @classmethod
    def load(cls, stem) -> "MultiOutputGP":
        stem = Path(stem)
        jpath, npath = stem.with_suffix(".json"), stem.with_suffix(".npz")
        try:
            meta = json.loads(jpath.read_text())
        except (OSError, json.JSONDecodeError) as exc:
            raise ModelError(f"{jpath}: cannot read GP model metadata ({exc})") from exc
        if not isinstance(meta, dict) or meta.get("kind") != _KIND:
            raise ModelError(f"{jpath}: not a {_KIND} file (kind {meta.get('kind') if isinstance(meta, dict) else None!r})")
        v = meta.get("format_version")
        if v != FORMAT_VERSION:
            hint = "written by a newer version; upgrade cobot-dt" if isinstance(v, int) and v > FORMAT_VERSION \
                else "written by an older version; re-fit the model"
            raise ModelError(f"{jpath}: format_version {v!r} is not supported; this version reads "
                             f"{FORMAT_VERSION} ({hint})")
        try:
            with np.load(npath, allow_pickle=False) as z:
                arrays = {k: z[k] for k in z.files}
            m = cls(**meta["params"])
            m.input_names_, m.output_names_ = meta["input_names"], meta["output_names"]
            m.models_ = [GPRegressor._from_state(mm, {k.strip("_"): arrays[f"{k.strip('_')}_{j}"]
                                                      for k in GPRegressor._ARR})
                         for j, mm in enumerate(meta["models"])]
        except (OSError, ValueError, KeyError, TypeError) as exc:
            raise ModelError(f"{stem}: GP model files are incomplete or corrupt ({exc!r})") from exc
        m.n_features_in_ = m.models_[0].n_features_in_
        return m
