"""Gaussian Process Regression error maps (paper Sect. 3.2), one per output (`MultiOutputGP`).

Constant mean, ARD squared-exponential kernel, white noise, hyperparameters by maximum marginal
likelihood; replicated inputs are collapsed exactly and large sets use a sparse posterior (the
method: `GPRegressor`). Follows scikit-learn's estimator contract without importing it
(`dt_runtime.models.estimator`); the per-command path is `MultiOutputGP.predictor()`, a
`FastPredictor` of plain numpy arrays. See docs/effects.md ("The GP on what is left").
"""
from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
from scipy import linalg, optimize
from scipy.linalg import blas, lapack

from dt_kernel.errors import DataError, ModelError
from dt_runtime.common.safe_json import read_json
from dt_runtime.common.safe_npz import load_npz
from dt_runtime.common.threads import blas_limited
from dt_runtime.models.estimator import Params
from dt_runtime.models.gp_math import (
    Collapsed,
    collapsed_factor,
    collapsed_nll,
    distinct,
    farthest_points,
    group_stats,
    inv_from_chol,
    se_kernel,
)
from dt_runtime.models.gp_predictor import FastPredictor

__all__ = ["FORMAT_VERSION", "FastPredictor", "GPOptions", "GPRegressor", "MultiOutputGP", "collapsed_nll"]

FORMAT_VERSION = 2
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


# L-BFGS-B stops when no log-hyperparameter moves the log likelihood by more than 1e-3 per unit
# (1e-5 nats for a 1 % change): statistically nothing. Near the optimum the decrease the line
# search asks for falls below the likelihood's round-off (~3e-10 nats on 400 inputs), where
# scipy's 1e-5 lets it wander in the noise (once seen: 16 evaluations instead of 1 on
# tests/test_speed's warm start); a warm start at the optimum (a diagnose candidate's refit)
# now ends at once. Cold fits still end on the relative reduction of the likelihood (factr 1e7,
# scipy's default): on six UR10 Series C/D cross-validations 1e-3 moved no fitted log
# hyperparameter by more than 7e-5. Looser reductions were measured too: ftol 1e-7 saves 2-14 %
# of the evaluations and moves log length scales the data hardly bound by up to 2 (held-out RMS
# by < 1e-5 mm); 1e-6 saves 5-43 %, moves them by up to 5.4 and the held-out RMS by up to 4e-4
# mm. Not taken.
_GTOL = 1e-3

_CHUNK_ELEMENTS = 2 ** 22  # 32 MB of float64: the largest (rows, basis) kernel block built at once


def _chunks(n: int, width: int) -> list[slice]:
    """Row slices of at most _CHUNK_ELEMENTS / width rows covering range(n) (bounded memory)."""
    step = max(1, _CHUNK_ELEMENTS // max(width, 1))
    return [slice(i, min(i + step, n)) for i in range(0, n, step)]


def _names(obj) -> list[str] | None:
    cols = getattr(obj, "columns", None)
    return [str(c) for c in cols] if cols is not None else None


class Distinct:
    """The part of a fit that depends on X alone: its standardisation, distinct rows (standardised)
    with the row -> distinct index and replicate counts, and the inducing inputs of a sparse
    posterior. A MultiOutputGP's outputs share one (one np.unique, one farthest-point pass)."""

    def __init__(self, X: np.ndarray):
        self.x_mean = X.mean(0)
        self.x_scale = X.std(0)
        self.x_scale[self.x_scale == 0] = 1.0
        Uraw, self.inv, self.counts = distinct(X)
        self.U = (Uraw - self.x_mean) / self.x_scale
        self.n_rows = len(X)
        self._inducing: dict[int, np.ndarray] = {}

    def inducing(self, m: int) -> np.ndarray:
        """Indices of m inducing inputs in U (farthest-point sampling: deterministic).

        Parameters
        ----------
        m : int
            How many.

        Returns
        -------
        ndarray
        """
        if m not in self._inducing:
            self._inducing[m] = farthest_points(self.U, m)
        return self._inducing[m]


# --- options ---------------------------------------------------------------------------------
@dataclass(frozen=True)
class GPOptions:
    """The GP's fitting options (GPRegressor's documents each), as one typed, immutable value
    the hybrid model carries and saves. Its defaults are the one place the GP's default settings
    are written: GPRegressor's and MultiOutputGP's signatures read them (`DEFAULTS`)."""

    noise_floor: float = 1e-10
    n_restarts: int = 1
    max_iter: int = 200
    sparse_threshold: int = 3000
    n_inducing: int = 600
    n_hyper: int = 1000
    min_length_scale: float = 0.1

    def to_dict(self) -> dict:
        """Every option as a dict."""
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict | None) -> GPOptions:
        """From a saved dict (every option, or only the overridden ones: the older `gp_kw`).

        Parameters
        ----------
        d : dict or None
            The saved options.

        Returns
        -------
        GPOptions
        """
        d = dict(d or {})
        unknown = sorted(set(d) - set(cls.__dataclass_fields__))
        if unknown:
            raise ModelError(f"unknown GP option(s) {', '.join(unknown)}; known: {', '.join(cls.__dataclass_fields__)}")
        return cls(**d)


#: The GP's default fit settings; the estimators' signatures show them (scikit-learn's get_params
#: reads the signature), so they are read from here rather than written again.
DEFAULTS = GPOptions()


# --- single output ---------------------------------------------------------------------------
class GPRegressor(Params):
    """One output: a GP error map with constant mean, ARD squared-exponential kernel and white noise.

        y = beta + f(x) + eps,   f ~ GP(0, s_f^2 exp(-1/2 sum_k (x_k - x'_k)^2 / l_k^2)),
        eps ~ N(0, s_n^2)

    Hyperparameters by maximum marginal likelihood (L-BFGS-B on log-parameters with the analytic
    gradient, Cholesky via scipy.linalg). The constant mean beta is the generalised-least-squares
    (maximum-likelihood) estimate at the current kernel, as MATLAB's fitrgp 'constant' basis does;
    by the envelope theorem the gradient of the profiled likelihood is the partial gradient at
    that beta.

    Exact speed-up for calibration data (not an approximation): the paper's DOE repeats every input
    (62 points x 3 speeds x 9 replications = 1,674 rows, 186 distinct inputs). With n_i replicates
    of input i, mean target ybar_i and within-group sum of squares SS_i, integrating out f_i gives

      log p(y) = log N(ybar | beta, K + s_n^2 diag(1/n_i))
                 + sum_i [ -(n_i - 1)/2 log(2 pi s_n^2) - 1/2 log n_i - SS_i / (2 s_n^2) ]

    so the cubic work is on distinct inputs only and the posterior of f is unchanged.

    Large sets: when the distinct inputs exceed `sparse_threshold`, the posterior is the sparse
    VFE/DTC projection (Titsias 2009) onto `n_inducing` inducing inputs chosen by farthest-point
    sampling (deterministic, so every output of a MultiOutputGP shares them). Hyperparameters are
    then (and whenever there are more than `n_hyper` distinct inputs) learned by the exact
    collapsed marginal likelihood of a seeded random subset of `n_hyper` distinct inputs with their
    replicates.

    Inputs and output are standardised internally; the learned attributes are in input/output
    units: `length_scales_` (input units), `signal_var_`, `noise_var_` (output units squared),
    `mean_` (constant mean, output units), `log_marginal_likelihood_`. Returned standard
    deviations are those of the latent error map f (the model's uncertainty).

    Parameters
    ----------
    noise_floor : float
        Lower bound of the noise variance relative to the output variance.
    n_restarts : int
        Seeded random starts of L-BFGS-B in addition to the default start.
    seed : int
        Seed of the restarts and of the hyperparameter subset.
    max_iter : int
        L-BFGS-B iterations per start.
    sparse_threshold : int
        Above this many distinct inputs the posterior is sparse (VFE/DTC).
    n_inducing : int
        Inducing inputs of the sparse posterior.
    n_hyper : int
        Hyperparameters are learned on at most this many distinct inputs (seeded subset).
    min_length_scale : float
        Lower bound of the length scales, in units of each input's standard deviation.
    """

    def __init__(self, *, noise_floor: float = DEFAULTS.noise_floor, n_restarts: int = DEFAULTS.n_restarts,
                 seed: int = 0, max_iter: int = DEFAULTS.max_iter, sparse_threshold: int = DEFAULTS.sparse_threshold,
                 n_inducing: int = DEFAULTS.n_inducing, n_hyper: int = DEFAULTS.n_hyper,
                 min_length_scale: float = DEFAULTS.min_length_scale):
        self.min_length_scale = min_length_scale  # in units of each input's standard deviation
        self.noise_floor = noise_floor
        self.n_restarts = n_restarts
        self.seed = seed
        self.max_iter = max_iter
        self.sparse_threshold = sparse_threshold
        self.n_inducing = n_inducing
        self.n_hyper = n_hyper

    # --- fit ----------------------------------------------------------------------------
    @blas_limited  # BLAS on one thread inside (common.threads), the caller's setting restored
    def fit(self, X, y, theta=None, start=None, *, inputs: Distinct | None = None) -> GPRegressor:
        """Learn hyperparameters and the posterior. With `theta` (the standardised log-
        parameters, see `theta_`) the hyperparameters are kept and only the posterior is built.
        `start`: a warm start of the optimisation, the log hyperparameters in input/output
        units (`log_hyper_` of a GP fitted on a nearby problem); then it is the only start.
        `inputs`: `Distinct(X)` when the caller already has it (MultiOutputGP, for all outputs).

        Parameters
        ----------
        X : array-like
            (n, d) inputs.
        y : array-like
            (n,) target.
        theta : ndarray, optional
            Fixed standardised log-parameters.
        start : ndarray, optional
            Warm start, log hyperparameters in input/output units.
        inputs : Distinct, optional
            `Distinct(X)`, when already computed.

        Returns
        -------
        GPRegressor
            self.
        """
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
        D = inputs if inputs is not None else Distinct(X)
        if D.n_rows != n:
            raise DataError(f"GPRegressor.fit: inputs describe {D.n_rows} rows, X has {n}")
        self.n_features_in_ = d
        self.n_train_ = n
        self.x_mean_ = D.x_mean.copy()
        self.x_scale_ = D.x_scale.copy()
        self.y_mean_ = float(y.mean())
        self.y_scale_ = float(y.std()) or 1.0
        U, counts = D.U, D.counts
        ybar, ss = group_stats(D.inv, counts, (y - self.y_mean_) / self.y_scale_)
        self.n_unique_ = len(U)
        # Hyperparameters: exact collapsed likelihood, on a seeded subset if there are many inputs.
        sub = np.arange(len(U))
        if len(U) > self.n_hyper:
            sub = np.sort(np.random.default_rng(self.seed).choice(len(U), self.n_hyper, replace=False))
        stats = Collapsed.of(U[sub], counts[sub], ybar[sub], float(ss[sub].sum()), int(counts[sub].sum()))
        if theta is None:
            theta = self._optimise(stats, d, self._standardised(start, d))
        theta = np.asarray(theta, dtype=float)
        if theta.shape != (d + 2,):
            raise ModelError(f"GPRegressor.fit: theta must have {d + 2} entries, got {theta.shape}")
        factor = collapsed_factor(theta, stats)
        if factor is None:
            raise ModelError("GPRegressor.fit: kernel matrix not positive definite at the learned "
                             "hyperparameters; raise noise_floor")
        nll, beta, alpha, L, _ = factor
        self.theta_ = theta
        self.log_marginal_likelihood_ = -nll  # of the (sub)set used for learning
        self._beta = beta
        self.length_scales_ = np.exp(theta[:d]) * self.x_scale_
        self.signal_var_ = float(np.exp(theta[d])) * self.y_scale_ ** 2
        self.noise_var_ = float(np.exp(theta[d + 1])) * self.y_scale_ ** 2
        self.mean_ = self.y_mean_ + self.y_scale_ * beta
        self.sparse_ = len(U) > self.sparse_threshold
        self._U, self._counts, self._ybar, self._ss = U, counts, ybar, ss
        self._q, self._factor = None, None
        if not self.sparse_ and len(sub) == len(U):
            # The likelihood's kernel is the posterior's (same inputs, same theta): its factor and
            # alpha are the exact posterior's; K^-1 (`_Q`) follows from L when first asked for.
            self._Xb, self._alpha, self._factor = U, alpha, ("exact", L)
            return self
        try:
            self._posterior(D)
        except linalg.LinAlgError as exc:
            raise ModelError(f"GPRegressor.fit: kernel matrix not positive definite at the learned "
                             f"hyperparameters ({exc}); raise noise_floor") from exc
        return self

    def _standardised(self, start, d: int) -> np.ndarray | None:
        """A warm start (log hyperparameters in input/output units) in this fit's standardised
        units; None when there is none or it is for other inputs (another dimension)."""
        if start is None:
            return None
        start = np.asarray(start, dtype=float)
        if start.shape != (d + 2,) or not np.all(np.isfinite(start)):
            return None
        ly = 2 * np.log(self.y_scale_)
        return start - np.r_[np.log(self.x_scale_), ly, ly]

    @property
    def log_hyper_(self) -> np.ndarray:
        """[log l_1..l_d, log s_f^2, log s_n^2] in input/output units: a warm start for `fit`
        on a nearby problem (other rows or another residual; standardisation differs)."""
        self._check_fitted()
        return np.r_[np.log(self.length_scales_), np.log(self.signal_var_), np.log(self.noise_var_)]

    def _optimise(self, stats: Collapsed, d: int, warm: np.ndarray | None = None) -> np.ndarray:
        rng = np.random.default_rng(self.seed)
        if warm is not None:
            # Warm start (a forward-selection candidate differs from the model it extends by one
            # effect block, so the residual the GP sees hardly moves): the optimum nearest the
            # previous one is the continuation we want, and the random restarts, which exist to
            # escape a poor optimum from the blind default start, are not run.
            starts = [warm]
        else:
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
            r = optimize.minimize(lambda t: collapsed_nll(t, stats)[:2], s, jac=True, method="L-BFGS-B",
                                  bounds=bounds, options={"maxiter": self.max_iter, "gtol": _GTOL})
            if best is None or r.fun < best.fun:
                best = r
        if warm is not None and (best is None or best.fun >= 1e24):
            return self._optimise(stats, d)  # the warm start failed: the blind starts
        if best is None or best.fun >= 1e24:
            raise ModelError("GPRegressor.fit: marginal-likelihood optimisation failed from every start")
        return best.x

    def log_marginal_likelihood(self, theta=None, eval_gradient: bool = False):
        """Exact log marginal likelihood (all training rows, via the collapse) at `theta`
        (standardised log-parameters; default the learned ones), optionally with its gradient.

        Parameters
        ----------
        theta : ndarray, optional
            Standardised log-parameters.
        eval_gradient : bool, optional
            Also return the gradient.

        Returns
        -------
        float, or (float, ndarray)
        """
        self._check_fitted()
        theta = self.theta_ if theta is None else np.asarray(theta, dtype=float)
        st = Collapsed.of(self._U, self._counts, self._ybar, float(self._ss.sum()), self.n_train_)
        nll, g, _ = collapsed_nll(theta, st, want_grad=eval_gradient)
        return (-nll, -g) if eval_gradient else -nll

    def _posterior(self, D: Distinct) -> None:
        """alpha (the mean's weights) and the factors `_Q` is made from when first asked for
        (the variance; a cross-validation fold predicts means only)."""
        d = self.n_features_in_
        ell = np.exp(self.theta_[:d])
        sf2, sn2 = float(np.exp(self.theta_[d])), float(np.exp(self.theta_[d + 1]))
        U, counts, r = self._U, self._counts, self._ybar - self._beta
        if not self.sparse_:
            K = se_kernel(U, U, ell, sf2)
            K[np.diag_indices(len(U))] += sn2 / counts
            L = linalg.cholesky(K.T, lower=True, overwrite_a=True, check_finite=False)  # K.T: no copy
            self._Xb = U
            self._alpha = linalg.cho_solve((L, True), r, check_finite=False)
            self._factor = ("exact", L)  # var = s_f^2 - k^T K^-1 k
            return
        # VFE/DTC posterior: Sigma = (Kzz + Kzu Lam Kuz)^-1, Lam = n_i / s_n^2;
        # mean = k_z^T Sigma Kzu Lam r;  var = s_f^2 - k_z^T (Kzz^-1 - Sigma) k_z.
        Z = U[D.inducing(self.n_inducing)]
        M = len(Z)
        Kzz = se_kernel(Z, Z, ell, sf2)
        Kzz[np.diag_indices(M)] += 1e-8 * sf2
        Lz = linalg.cholesky(Kzz, lower=True, check_finite=False)
        sl = np.sqrt(counts / sn2)
        # V = Lz^-1 Kzu Lam^1/2 is (M, n): 4.8 GB at 10^6 inputs and 600 inducing, and the kernel
        # it is solved from as much again. Only B = I + V V' and V (Lam^1/2 r) are needed: sums
        # over the inputs, accumulated in column chunks of bounded size (same numbers). V V' by
        # syrk: its lower triangle only, half a product's work.
        B = np.eye(M, order="F")
        Vr = np.zeros(M)
        for c in _chunks(len(U), M):
            V = linalg.solve_triangular(Lz, se_kernel(Z, U[c], ell, sf2), lower=True, check_finite=False) * sl[c]
            B = blas.dsyrk(1.0, V.T, beta=1.0, c=B, trans=1, lower=1, overwrite_c=1)  # V.T: no copy
            Vr += V @ (sl[c] * r[c])
        LB, info = lapack.dpotrf(B, lower=1, clean=1, overwrite_a=1)  # reads the lower triangle
        if info != 0:
            raise linalg.LinAlgError(f"sparse posterior: B not positive definite ({info})")
        c = linalg.cho_solve((LB, True), Vr, check_finite=False)
        self._Xb = Z
        self._alpha = linalg.solve_triangular(Lz, c, lower=True, trans="T", check_finite=False)
        self._factor = ("sparse", Lz, LB)

    @property
    def _Q(self) -> np.ndarray:
        """The variance's matrix, var = s_f^2 - k^T Q k: K^-1 (exact) or Kzz^-1 - Sigma (sparse),
        made from the posterior's factors on first use (predict with return_std, predictor,
        save); a model read from a file carries it."""
        if self._q is None:
            if self._factor is None:
                raise ModelError(f"{type(self).__name__} is not fitted; call fit(X, y) first")
            if self._factor[0] == "exact":
                self._q = inv_from_chol(self._factor[1])
            else:
                _, Lz, LB = self._factor
                M = len(Lz)
                Lzi = linalg.solve_triangular(Lz, np.eye(M), lower=True)
                Q = Lzi.T @ (np.eye(M) - inv_from_chol(LB)) @ Lzi
                self._q = 0.5 * (Q + Q.T)
            self._factor = None  # Q replaces the factors (as much memory again)
        return self._q

    @_Q.setter
    def _Q(self, value: np.ndarray) -> None:
        self._q, self._factor = value, None

    _q: np.ndarray | None = None
    _factor: tuple | None = None

    def _precision_dot(self, B: np.ndarray) -> np.ndarray:
        """K^-1 B for the exact posterior's collapsed covariance K = K_f + s_n^2 diag(1/n_i) (the
        effects' GLS in models.hybrid): two triangular solves per column (2 n^2) from the
        factor, rather than K^-1 itself (n^3), unless K^-1 is already there."""
        if self.sparse_:
            raise ModelError("GPRegressor: a sparse posterior has no exact K^-1")
        if self._q is not None or self._factor is None:
            return self._Q @ B
        return linalg.cho_solve((self._factor[1], True), B, check_finite=False)

    # --- predict ------------------------------------------------------------------------
    def _check_fitted(self):
        if not hasattr(self, "theta_"):
            raise ModelError(f"{type(self).__name__} is not fitted; call fit(X, y) first")

    @blas_limited
    def predict(self, X, return_std: bool = False):
        """Mean (n,) and, with return_std, the standard deviation (n,) of the latent error map.

        Parameters
        ----------
        X : array-like
            (n, d) inputs.
        return_std : bool, optional
            Also return the standard deviation.

        Returns
        -------
        ndarray, or (ndarray, ndarray)
        """
        self._check_fitted()
        X = _as_2d(X, "GPRegressor.predict X")
        if X.shape[1] != self.n_features_in_:
            raise DataError(f"GPRegressor.predict X: expected {self.n_features_in_} columns, got {X.shape[1]}")
        d = self.n_features_in_
        ell, sf2 = np.exp(self.theta_[:d]), float(np.exp(self.theta_[d]))
        Xs = (X - self.x_mean_) / self.x_scale_
        mean = np.empty(len(X))
        std = np.empty(len(X)) if return_std else None
        # In row chunks: the cross-kernel is (rows, basis inputs), 4.8 GB for 10^6 rows at once.
        for c in _chunks(len(X), len(self._Xb)):
            k = se_kernel(Xs[c], self._Xb, ell, sf2)
            mean[c] = self.mean_ + self.y_scale_ * (k @ self._alpha)
            if std is not None:
                var = sf2 - np.einsum("ij,ij->i", k @ self._Q, k)
                std[c] = self.y_scale_ * np.sqrt(np.clip(var, 0.0, None))
        return (mean, std) if std is not None else mean

    def score(self, X, y) -> float:
        """Coefficient of determination R^2 (scikit-learn's regressor convention).

        Parameters
        ----------
        X : array-like
            (n, d) inputs.
        y : array-like
            (n,) target.

        Returns
        -------
        float
        """
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
    def _from_state(cls, meta: dict, arrays: dict) -> GPRegressor:
        g = cls(**meta["params"])
        for k in cls._META:
            setattr(g, k, meta[k.lstrip("_")])
        for k in cls._ARR:
            setattr(g, k, np.asarray(arrays[k.strip("_")], dtype=float))
        # Shapes that agree, or predict fails later (a member cut short: a traceback at the
        # first command): d inputs, m basis points.
        d, m = int(g.n_features_in_), len(g._Xb)
        want = {"x_mean": (d,), "x_scale": (d,), "length_scales": (d,), "theta": (d + 2,), "Xb": (m, d),
                "alpha": (m,), "Q": (m, m)}
        bad = [f"{k} {arrays[k].shape}" for k, shape in want.items() if arrays[k].shape != shape]
        if bad:
            raise ValueError(f"arrays of disagreeing shapes: {', '.join(bad)}; with {d} inputs and {m} basis "
                             f"points expected {', '.join(f'{k} {s}' for k, s in want.items())}")
        g._check_hyperparameters()
        return g

    #: The shortest length scale a loaded model may have, in units of its input's standard deviation:
    #: the fit never goes below min_length_scale (0.1); one near 0 predicts the mean everywhere but at
    #: the training points, with the prior's whole U (a twin edited so corrected 2.5 mm off, U 4.45 mm).
    MIN_LOADED_LENGTH_SCALE = 1e-6

    def _check_hyperparameters(self) -> None:
        """ValueError unless the loaded hyperparameters are a GP's: length scales, input and output
        scales, signal and noise variances positive and finite, the length scales those of theta
        (exp(theta) times the input scale: the one predict uses), none near 0."""
        d = int(self.n_features_in_)
        ell_std = np.exp(self.theta_[:d])
        checks = [("x_scale", self.x_scale_), ("length_scales", self.length_scales_), ("y_scale", self.y_scale_),
                  ("signal_var", self.signal_var_), ("noise_var", self.noise_var_)]
        for name, v in checks:
            a = np.asarray(v, dtype=float)
            if not (np.all(np.isfinite(a)) and np.all(a > 0)):
                raise ValueError(f"{name} {np.round(a, 9).tolist()} must be positive and finite (a GP's scales and "
                                 "variances are)")
        if np.any(ell_std < self.MIN_LOADED_LENGTH_SCALE):
            raise ValueError(f"theta's length scales {ell_std.tolist()} (in input standard deviations) must be at "
                             f"least {self.MIN_LOADED_LENGTH_SCALE:g}: near 0 the GP predicts nothing but its mean")
        if not np.allclose(self.length_scales_, ell_std * self.x_scale_, rtol=1e-6, atol=0):
            raise ValueError(f"length_scales {self.length_scales_.tolist()} disagree with theta's "
                             f"{(ell_std * self.x_scale_).tolist()} (exp(theta) times x_scale): the file was edited")



# --- several outputs -------------------------------------------------------------------------
class MultiOutputGP(Params):
    """One GPRegressor per output column (the paper: one model per axis).

    `input_units`/`output_units` are recorded in the saved model (SI inside the code)."""

    def __init__(self, *, noise_floor: float = DEFAULTS.noise_floor, n_restarts: int = DEFAULTS.n_restarts,
                 seed: int = 0, max_iter: int = DEFAULTS.max_iter, sparse_threshold: int = DEFAULTS.sparse_threshold,
                 n_inducing: int = DEFAULTS.n_inducing, n_hyper: int = DEFAULTS.n_hyper,
                 min_length_scale: float = DEFAULTS.min_length_scale, input_names=None,
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

    _GP_PARAMS = tuple(GPOptions.__dataclass_fields__)  # the options GPRegressor takes

    @blas_limited
    def fit(self, X, Y, *, input_names=None, output_names=None, thetas=None, starts=None) -> MultiOutputGP:
        """One GP per column of Y. thetas: fixed standardised hyperparameters per output (only
        the posterior is built); starts: warm starts per output (`log_hyper_`, GPRegressor.fit).

        Parameters
        ----------
        X : array-like
            (n, d) inputs.
        Y : array-like
            (n, k) targets.
        input_names, output_names : list of str, optional
            Names kept with the model.
        thetas : list of ndarray, optional
            Fixed hyperparameters per output.
        starts : list of ndarray, optional
            Warm starts per output.

        Returns
        -------
        MultiOutputGP
            self.
        """
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
        D = Distinct(X)  # the outputs share the inputs: one collapse and one inducing set for all
        self.models_ = [GPRegressor(seed=self.seed + j, **kw).fit(X, Y[:, j], None if thetas is None else thetas[j],
                                                                  None if starts is None else starts[j], inputs=D)
                        for j in range(Y.shape[1])]
        self.n_features_in_ = X.shape[1]
        return self

    @property
    def thetas_(self) -> list[np.ndarray]:
        """Per output, a copy of the fitted log-hyperparameters (standardised units)."""
        return [g.theta_.copy() for g in self.models_]

    @property
    def log_hypers_(self) -> list[np.ndarray]:
        """Per output, the hyperparameters in input/output units: warm starts (`fit(starts=...)`)."""
        return [g.log_hyper_ for g in self.models_]

    def _check_fitted(self):
        if not hasattr(self, "models_"):
            raise ModelError("MultiOutputGP is not fitted; call fit(X, Y) or load(stem) first")

    @blas_limited
    def predict(self, X, return_std: bool = False):
        """(n, k) means and, with return_std, (n, k) latent standard deviations.

        Parameters
        ----------
        X : array-like
            (n, d) inputs.
        return_std : bool, optional
            Also return the standard deviations.

        Returns
        -------
        ndarray, or (ndarray, ndarray)
        """
        self._check_fitted()
        out = [g.predict(X, return_std) for g in self.models_]
        if not return_std:
            return np.column_stack(out)
        return np.column_stack([o[0] for o in out]), np.column_stack([o[1] for o in out])

    def predictor(self) -> FastPredictor:
        """A fast predictor of the fitted outputs, for the per-command path.

        Returns
        -------
        FastPredictor

        Raises
        ------
        ModelError
            When not fitted.
        """
        self._check_fitted()
        return FastPredictor(self.models_)

    # --- persistence (JSON + NPZ, no pickle) ---------------------------------------------
    def save(self, stem) -> None:
        """Save as `stem`.json (metadata) and `stem`.npz (arrays); no pickle.

        Parameters
        ----------
        stem : str or Path
            Path without suffix.

        Raises
        ------
        ModelError
            When not fitted, holding non-finite values, or not writable.
        """
        self._check_fitted()
        stem = Path(stem)
        metas, arrays = [], {}
        for j, g in enumerate(self.models_):
            m, a = g._state()
            metas.append(m)
            arrays.update({f"{k}_{j}": v for k, v in a.items()})
        bad = [k for k, v in arrays.items() if not np.all(np.isfinite(v))]
        if bad or not all(math.isfinite(float(g.mean_)) for g in self.models_):
            raise ModelError(f"{stem}: the fitted GP holds NaN or infinite values ({', '.join(bad) or 'mean'}); "
                             "not saved: check the training data for absurd values")
        meta = {"format_version": FORMAT_VERSION, "kind": _KIND,
                "kernel": "constant mean + signal_var * ARD squared exponential + white noise",
                "input_names": self.input_names_, "output_names": self.output_names_,
                "units": {"inputs": self.input_units or "SI", "outputs": self.output_units or "SI",
                          "length_scales": "input units", "signal_var/noise_var": "output units squared"},
                "params": self.get_params(), "models": metas}
        try:
            stem.with_suffix(".json").write_text(json.dumps(meta, indent=1, allow_nan=False))
            np.savez(stem.with_suffix(".npz"), **arrays)
        except OSError as exc:
            raise ModelError(f"{stem}: cannot write GP model ({exc})") from exc

    @classmethod
    def load(cls, stem) -> MultiOutputGP:
        """Read a model `save` wrote, with bounded reads and checked shapes.

        Parameters
        ----------
        stem : str or Path
            Path without suffix.

        Returns
        -------
        MultiOutputGP

        Raises
        ------
        ModelError
            Naming the file for a wrong kind, format version or malformed content.
        """
        stem = Path(stem)
        jpath, npath = stem.with_suffix(".json"), stem.with_suffix(".npz")
        try:
            meta = read_json(jpath, "a GP model's metadata")  # bounded; every number finite
        except DataError as exc:
            raise ModelError(f"cannot read GP model metadata ({exc})") from exc
        if not isinstance(meta, dict) or meta.get("kind") != _KIND:
            kind = meta.get("kind") if isinstance(meta, dict) else None
            raise ModelError(f"{jpath}: not a {_KIND} file (kind {kind!r})")
        v = meta.get("format_version")
        if v != FORMAT_VERSION:
            hint = "written by a newer version; upgrade cobot-dt" if isinstance(v, int) and v > FORMAT_VERSION \
                else "written by an older version; re-fit the model"
            raise ModelError(f"{jpath}: format_version {v!r} is not supported; this version reads "
                             f"{FORMAT_VERSION} ({hint})")
        where = "parameters"
        try:
            # Names, sizes and dtypes checked before anything is read (common.safe_npz).
            arrays = load_npz(npath, {f"{k.strip('_')}_{j}" for j in range(len(meta["models"]))
                                      for k in GPRegressor._ARR})
            m = cls(**meta["params"])
            m.input_names_, m.output_names_ = meta["input_names"], meta["output_names"]
            m.models_ = []
            for j, mm in enumerate(meta["models"]):
                where = f"output {j}"  # which model a shape error is about
                m.models_.append(GPRegressor._from_state(mm, {k.strip("_"): arrays[f"{k.strip('_')}_{j}"]
                                                              for k in GPRegressor._ARR}))
        except ValueError as exc:
            raise ModelError(f"{stem}: GP model files are corrupt ({where}: {exc})") from exc
        except (OSError, KeyError, TypeError) as exc:
            raise ModelError(f"{stem}: GP model files are incomplete or corrupt ({exc!r})") from exc
        if not m.models_ or len({g.n_features_in_ for g in m.models_}) != 1:
            raise ModelError(f"{stem}: GP model files are corrupt ({len(m.models_)} output models with "
                             f"{sorted({g.n_features_in_ for g in m.models_})} inputs)")
        m.n_features_in_ = m.models_[0].n_features_in_
        return m
