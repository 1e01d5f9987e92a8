"""Gaussian Process Regression error maps (paper Sect. 3.2): constant mean, ARD squared-
exponential kernel, white noise; hyperparameters by maximum marginal likelihood (L-BFGS-B on
log-parameters with the analytic gradient).

Exact speed-up for calibration data: the paper's DOE repeats every input (62 points x 3 speeds x
9 replications = 1,674 rows, 186 distinct inputs). With n_i replicates of input i, mean y_i and
within-group sum of squares SS_i, the likelihood factorises exactly:

  log p(y) = log N(ybar | m, K + s2 diag(1/n_i))
             + sum_i [ -(n_i - 1)/2 log(2 pi s2) - 1/2 log n_i - SS_i / (2 s2) ]

so the cubic work is on distinct inputs only; the posterior is unchanged. When distinct inputs
exceed `sparse_threshold`, hyperparameters are learned on a seeded subset; beyond `exact_limit`
the posterior is the subset-of-regressors (DTC) projection onto `n_inducing` inducing inputs.

Follows scikit-learn's estimator contract; the per-command path is `MultiOutputGP.predictor()`.
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
from scipy import linalg, optimize

from dt_runtime.errors import DataError, ModelError

FORMAT_VERSION = 1
LOG2PI = np.log(2 * np.pi)


def _collapse(X: np.ndarray, y: np.ndarray):
    """Distinct rows of X, their replicate counts, mean targets and within-group SS."""
    U, inv, counts = np.unique(X, axis=0, return_inverse=True, return_counts=True)
    inv = inv.ravel()
    sums = np.bincount(inv, weights=y, minlength=len(U))
    ybar = sums / counts
    ss = np.bincount(inv, weights=(y - ybar[inv]) ** 2, minlength=len(U)).sum()
    return U, counts.astype(float), ybar, float(ss)


def _sqdist_per_dim(A: np.ndarray, B: np.ndarray) -> np.ndarray:
    return (A[:, None, :] - B[None, :, :]) ** 2  # (n, m, d)


class GPRegressor:
    """One output. Inputs are standardised internally; length scales are reported in input units."""

    def __init__(self, *, n_restarts: int = 1, seed: int = 0, max_iter: int = 200,
                 sparse_threshold: int = 3000, exact_limit: int = 6000, n_inducing: int = 1500,
                 noise_floor: float = 1e-10):
        self.n_restarts = n_restarts
        self.seed = seed
        self.max_iter = max_iter
        self.sparse_threshold = sparse_threshold  # distinct inputs used to learn hyperparameters
        self.exact_limit = exact_limit  # beyond this many distinct inputs the posterior is DTC
        self.n_inducing = n_inducing
        self.noise_floor = noise_floor

    # --- likelihood -------------------------------------------------------------------------
    @staticmethod
    def _nll(theta, D2, counts, ybar, ss, N):
        d = D2.shape[2]
        ell2 = np.exp(2 * theta[:d])
        sf2, sn2 = np.exp(theta[d]), np.exp(theta[d + 1])
        E = np.exp(-0.5 * np.einsum("ijk,k->ij", D2, 1 / ell2))
        K = sf2 * E + np.diag(sn2 / counts)
        try:
            L = linalg.cholesky(K, lower=True, check_finite=False)
        except linalg.LinAlgError:
            return 1e25, np.zeros_like(theta)
        alpha = linalg.cho_solve((L, True), ybar, check_finite=False)
        U = len(ybar)
        nll = 0.5 * ybar @ alpha + np.log(np.diag(L)).sum() + 0.5 * U * LOG2PI
        # Within-replicate part of the exact likelihood.
        nll += 0.5 * (N - U) * (LOG2PI + np.log(sn2)) + 0.5 * np.log(counts).sum() + ss / (2 * sn2)
        W = np.outer(alpha, alpha) - linalg.cho_solve((L, True), np.eye(U), check_finite=False)
        WE = W * E * sf2
        g = np.empty_like(theta)
        g[:d] = -0.5 * np.einsum("ij,ijk->k", WE, D2) / ell2
        g[d] = -0.5 * np.sum(WE)
        g[d + 1] = -0.5 * sn2 * np.sum(np.diag(W) / counts) + 0.5 * (N - U) - ss / (2 * sn2)
        return nll, g

    def log_marginal_likelihood(self, theta: np.ndarray | None = None) -> float:
        theta = self._theta if theta is None else np.asarray(theta)
        D2 = _sqdist_per_dim(self._U, self._U)
        return -self._nll(theta, D2, self._counts, self._ybar, self._ss, self._N)[0]

    # --- fit / predict ----------------------------------------------------------------------
    def fit(self, X, y, theta: np.ndarray | None = None) -> "GPRegressor":
        """Fit; with `theta` given (log length scales, log signal var, log noise var, in the
        standardised space), the hyperparameters are kept and only the posterior is computed."""
        X = np.asarray(X, dtype=float)
        y = np.asarray(y, dtype=float).ravel()
        if X.ndim != 2 or len(X) != len(y) or len(y) < 2:
            raise DataError(f"GP fit needs X (n, d) and y (n,) with n >= 2; got {X.shape} and {y.shape}")
        if not (np.all(np.isfinite(X)) and np.all(np.isfinite(y))):
            raise DataError("GP fit: X or y contains NaN or infinite values")
        self.x_mean_ = X.mean(0)
        self.x_scale_ = X.std(0)
        self.x_scale_[self.x_scale_ == 0] = 1.0
        self.mean_ = float(y.mean())  # constant mean
        self.y_scale_ = float(y.std()) or 1.0
        Xs = (X - self.x_mean_) / self.x_scale_
        ys = (y - self.mean_) / self.y_scale_
        U, counts, ybar, ss = _collapse(Xs, ys)
        self._N = len(ys)
        d = X.shape[1]
        if theta is None:
            sub = np.arange(len(U))
            if len(U) > self.sparse_threshold:
                sub = np.random.default_rng(self.seed).choice(len(U), self.sparse_threshold, replace=False)
            theta = self._optimise(U[sub], counts[sub], ybar[sub], ss, d)
        self._theta = np.asarray(theta, dtype=float)
        self._U, self._counts, self._ybar, self._ss = U, counts, ybar, ss
        self.length_scales_ = np.exp(self._theta[:d]) * self.x_scale_
        self.signal_var_ = float(np.exp(self._theta[d])) * self.y_scale_ ** 2
        self.noise_var_ = float(np.exp(self._theta[d + 1])) * self.y_scale_ ** 2
        self._posterior()
        return self

    def _optimise(self, U, counts, ybar, ss, d) -> np.ndarray:
        D2 = _sqdist_per_dim(U, U)
        N = self._N
        rng = np.random.default_rng(self.seed)
        starts = [np.r_[np.zeros(d), 0.0, np.log(0.01)]]
        starts += [np.r_[rng.uniform(-1.5, 1.0, d), rng.uniform(-1, 1), rng.uniform(-7, -2)]
                   for _ in range(self.n_restarts)]
        floor = np.log(max(self.noise_floor, 1e-12))
        bounds = [(-5, 5)] * d + [(-8, 5), (floor, 2)]
        best = None
        for s in starts:
            r = optimize.minimize(self._nll, s, args=(D2, counts, ybar, ss, N), jac=True,
                                  method="L-BFGS-B", bounds=bounds, options={"maxiter": self.max_iter})
            if best is None or r.fun < best.fun:
                best = r
        self.log_marginal_likelihood_ = float(-best.fun)
        return best.x

    def _kernel(self, A: np.ndarray, B: np.ndarray) -> np.ndarray:
        d = A.shape[1]
        ell2 = np.exp(2 * self._theta[:d])
        return np.exp(self._theta[d]) * np.exp(-0.5 * np.einsum("ijk,k->ij", _sqdist_per_dim(A, B), 1 / ell2))

    def _posterior(self) -> None:
        d = self._U.shape[1]
        sn2 = np.exp(self._theta[d + 1])
        U, counts, ybar = self._U, self._counts, self._ybar
        if len(U) <= self.exact_limit:
            K = self._kernel(U, U) + np.diag(sn2 / counts)
            L = linalg.cholesky(K, lower=True)
            self._Xb = U
            self._alpha = linalg.cho_solve((L, True), ybar)
            self._Kinv = linalg.cho_solve((L, True), np.eye(len(U)))
        else:
            # DTC / subset of regressors on inducing inputs Z (seeded subset of distinct inputs).
            Z = U[np.random.default_rng(self.seed).choice(len(U), self.n_inducing, replace=False)]
            Kzz = self._kernel(Z, Z) + 1e-8 * np.eye(len(Z)) * np.exp(self._theta[d])
            Kzu = self._kernel(Z, U)
            Lam = counts / sn2  # precision of each distinct-input mean
            A = Kzz + (Kzu * Lam) @ Kzu.T
            La = linalg.cholesky(A, lower=True)
            self._Xb = Z
            self._alpha = linalg.cho_solve((La, True), Kzu @ (Lam * ybar))
            # var = k** - kz^T (Kzz^-1 - A^-1) kz
            self._Kinv = linalg.inv(Kzz) - linalg.cho_solve((La, True), np.eye(len(Z)))
        if not hasattr(self, "log_marginal_likelihood_"):
            self.log_marginal_likelihood_ = float(self.log_marginal_likelihood()) if len(U) <= 3000 else float("nan")

    def predict(self, X, return_std: bool = False):
        X = np.asarray(X, dtype=float)
        if X.ndim != 2 or X.shape[1] != len(self.x_mean_):
            raise DataError(f"GP predict: expected X with {len(self.x_mean_)} columns, got shape {X.shape}")
        Xs = (X - self.x_mean_) / self.x_scale_
        k = self._kernel(Xs, self._Xb)
        mean = self.mean_ + self.y_scale_ * (k @ self._alpha)
        if not return_std:
            return mean
        sf2 = np.exp(self._theta[Xs.shape[1]])
        var = sf2 - np.einsum("ij,jk,ik->i", k, self._Kinv, k)
        return mean, self.y_scale_ * np.sqrt(np.clip(var, 0, None))

    # --- persistence helpers --------------------------------------------------------------
    def _state(self) -> tuple[dict, dict]:
        meta = {"theta": self._theta.tolist(), "x_mean": self.x_mean_.tolist(), "x_scale": self.x_scale_.tolist(),
                "mean": self.mean_, "y_scale": self.y_scale_, "N": self._N, "ss": self._ss,
                "length_scales": self.length_scales_.tolist(), "signal_var": self.signal_var_,
                "noise_var": self.noise_var_, "log_marginal_likelihood": self.log_marginal_likelihood_}
        arrays = {"Xb": self._Xb, "alpha": self._alpha, "Kinv": self._Kinv}
        return meta, arrays

    @classmethod
    def _from_state(cls, meta: dict, arrays: dict) -> "GPRegressor":
        g = cls()
        g._theta = np.array(meta["theta"])
        g.x_mean_, g.x_scale_ = np.array(meta["x_mean"]), np.array(meta["x_scale"])
        g.mean_, g.y_scale_, g._N, g._ss = meta["mean"], meta["y_scale"], meta["N"], meta["ss"]
        g.length_scales_ = np.array(meta["length_scales"])
        g.signal_var_, g.noise_var_ = meta["signal_var"], meta["noise_var"]
        g.log_marginal_likelihood_ = meta["log_marginal_likelihood"]
        g._Xb, g._alpha, g._Kinv = arrays["Xb"], arrays["alpha"], arrays["Kinv"]
        return g


class FastPredictor:
    """Per-command predictor: mean and std of every output at one point from precomputed arrays."""

    def __init__(self, models: list[GPRegressor]):
        self._m = [(g.x_mean_, g.x_scale_, np.exp(-2 * g._theta[:-2]) * -0.5, np.exp(g._theta[-2]),
                    g._Xb, g._alpha, g._Kinv, g.mean_, g.y_scale_) for g in models]

    def __call__(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        n = len(self._m)
        mean, std = np.empty(n), np.empty(n)
        for i, (xm, xs, neg_half_inv_ell2, sf2, Xb, alpha, Kinv, m0, ys) in enumerate(self._m):
            diff = Xb - (x - xm) / xs
            k = sf2 * np.exp((diff * diff) @ neg_half_inv_ell2)
            mean[i] = m0 + ys * (k @ alpha)
            var = sf2 - k @ (Kinv @ k)
            std[i] = ys * np.sqrt(var if var > 0 else 0.0)
        return mean, std


class MultiOutputGP:
    """One GPRegressor per output column (the paper: one model per axis)."""

    def __init__(self, *, seed: int = 0, n_restarts: int = 1, input_names: tuple[str, ...] | None = None,
                 output_names: tuple[str, ...] | None = None, **gp_kwargs):
        self.seed = seed
        self.n_restarts = n_restarts
        self.input_names = input_names
        self.output_names = output_names
        self.gp_kwargs = gp_kwargs

    def fit(self, X, Y, thetas: list[np.ndarray] | None = None) -> "MultiOutputGP":
        Y = np.asarray(Y, dtype=float)
        if Y.ndim != 2:
            raise DataError(f"MultiOutputGP.fit: Y must be (n, k), got shape {Y.shape}")
        self.models_ = [GPRegressor(seed=self.seed + j, n_restarts=self.n_restarts, **self.gp_kwargs)
                        .fit(X, Y[:, j], None if thetas is None else thetas[j]) for j in range(Y.shape[1])]
        return self

    @property
    def thetas_(self) -> list[np.ndarray]:
        return [g._theta.copy() for g in self.models_]

    def predict(self, X, return_std: bool = False):
        out = [g.predict(X, return_std) for g in self.models_]
        if not return_std:
            return np.column_stack(out)
        return np.column_stack([o[0] for o in out]), np.column_stack([o[1] for o in out])

    def predictor(self) -> FastPredictor:
        return FastPredictor(self.models_)

    def save(self, stem: str | Path) -> None:
        stem = Path(stem)
        metas, arrays = [], {}
        for j, g in enumerate(self.models_):
            m, a = g._state()
            metas.append(m)
            arrays.update({f"{k}_{j}": v for k, v in a.items()})
        meta = {"format_version": FORMAT_VERSION, "kind": "cobot-dt MultiOutputGP",
                "kernel": "constant mean + ARD squared exponential + white noise",
                "input_names": self.input_names, "output_names": self.output_names, "models": metas}
        stem.with_suffix(".json").write_text(json.dumps(meta, indent=1))
        np.savez(stem.with_suffix(".npz"), **arrays)

    @classmethod
    def load(cls, stem: str | Path) -> "MultiOutputGP":
        stem = Path(stem)
        try:
            meta = json.loads(stem.with_suffix(".json").read_text())
            arrays = np.load(stem.with_suffix(".npz"), allow_pickle=False)
        except (OSError, json.JSONDecodeError, ValueError) as exc:
            raise ModelError(f"{stem}: cannot read GP model ({exc})") from exc
        if meta.get("format_version") != FORMAT_VERSION:
            raise ModelError(f"{stem.with_suffix('.json')}: format_version {meta.get('format_version')!r}, "
                             f"this version reads {FORMAT_VERSION}")
        m = cls(input_names=meta.get("input_names"), output_names=meta.get("output_names"))
        m.models_ = [GPRegressor._from_state(mm, {k: arrays[f"{k}_{j}"] for k in ("Xb", "alpha", "Kinv")})
                     for j, mm in enumerate(meta["models"])]
        return m
