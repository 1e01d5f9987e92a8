"""The lean per-command GP predictor: mean and latent std of every output at one input, from
precomputed numpy arrays only (no fitting code, no validation beyond the input's shape)."""
from __future__ import annotations

import numpy as np

from dt_kernel.errors import DataError


class FastPredictor:
    """Mean (k,) and latent std (k,) of every output at one input x (d,), from precomputed numpy
    arrays only. When all outputs share training inputs and scaling (always so for a
    MultiOutputGP), the k outputs are evaluated together: one distance matrix, one stacked
    matrix-vector product for the variances."""

    def __init__(self, models: list):  # fitted GPRegressor per output
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

    def mean_kernel(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The mean (k,) at x (d,) and the kernel vectors (U, k) its std needs (`std_of`): a
        fixed-point correction needs the mean at every step and the std only at its last. The
        same operations as `__call__`, so the same numbers; shared outputs only, x not checked.

        Parameters
        ----------
        x : ndarray
            (d,) one input.

        Returns
        -------
        mean : ndarray
            (k,).
        K : ndarray
            (U, k).
        """
        diff = self._Xb - (x - self._xm) / self._xs
        K = self._sf2 * np.exp((diff * diff) @ self._neg_half_inv_ell2)
        return self._m0 + self._ys * np.einsum("uk,uk->k", K, self._alpha), K

    def std_of(self, K: np.ndarray) -> np.ndarray:
        """The latent std (k,) where `mean_kernel` gave K.

        Parameters
        ----------
        K : ndarray
            From `mean_kernel`.

        Returns
        -------
        ndarray
            (k,).
        """
        Kt = K.T
        var = self._sf2 - np.einsum("ku,ku->k", Kt, np.matmul(self._Q, Kt[:, :, None])[:, :, 0])
        return self._ys * np.sqrt(np.maximum(var, 0.0))

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
