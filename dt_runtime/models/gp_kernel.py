"""The GP predictor's arithmetic at one input as compiled kernels (`common.jit`): the same
operations as `FastPredictor.mean_kernel` and `std_of` on shared training inputs, written as loops
over preallocated arrays (no allocation per call). Tested equal to `FastPredictor`
(tests/unit/test_compiled_law.py)."""
from __future__ import annotations

import math

import numpy as np

from dt_runtime.common.jit import kernel


@kernel
def gp_mean(x, Xb, xm, xs, nh, sf2, m0, ys, alpha, z, acc, K, m):  # pragma: no cover - compiled
    """Mean m (k,) at x (d,) and the kernel vectors K (U, k) its std needs, as
    `FastPredictor.mean_kernel`: K = sf2 exp(((Xb - (x - xm) / xs)^2) nh).

    Parameters
    ----------
    x : ndarray
        (d,) the input.
    Xb, xm, xs, nh, sf2, m0, ys, alpha : ndarray
        The predictor's arrays (`GPArrays`).
    z, acc : ndarray
        (d,), (k,) scratch.
    K, m : ndarray
        Written: (U, k), (k,).
    """
    U, d = Xb.shape
    k = nh.shape[1]
    for i in range(d):
        z[i] = (x[i] - xm[i]) / xs[i]
    for j in range(k):
        m[j] = 0.0
    for u in range(U):
        for j in range(k):
            acc[j] = 0.0
        for i in range(d):
            t = Xb[u, i] - z[i]
            t2 = t * t
            for j in range(k):
                acc[j] += t2 * nh[i, j]
        for j in range(k):
            kv = sf2[j] * math.exp(acc[j])
            K[u, j] = kv
            m[j] += kv * alpha[u, j]
    for j in range(k):
        m[j] = m0[j] + ys[j] * m[j]


@kernel
def gp_var(K, Q, sf2, kt):  # pragma: no cover - compiled
    """The latent variance per output where `gp_mean` gave K: sf2 - K_j^T Q_j K_j (before the y
    scale; clipped at 0).

    Parameters
    ----------
    K, Q, sf2 : ndarray
        (U, k), (k, U, U), (k,).
    kt : ndarray
        (U,) scratch.

    Returns
    -------
    ndarray
        (k,).
    """
    U, k = K.shape
    out = np.empty(k)
    for j in range(k):
        for u in range(U):
            kt[u] = K[u, j]
        s = np.dot(kt, np.dot(Q[j], kt))
        out[j] = max(sf2[j] - s, 0.0)
    return out


class GPArrays:
    """A shared-input `FastPredictor`'s arrays, contiguous, with the scratch the kernels write.

    Parameters
    ----------
    p : FastPredictor
        A predictor with `shared` outputs.
    """

    def __init__(self, p):
        if not p.shared:
            raise ValueError("GPArrays: outputs with shared training inputs only")
        c = np.ascontiguousarray
        self.Xb, self.xm, self.xs = c(p._Xb, dtype=float), c(p._xm, dtype=float), c(p._xs, dtype=float)
        self.nh, self.sf2 = c(p._neg_half_inv_ell2, dtype=float), c(p._sf2, dtype=float)
        self.m0, self.ys, self.alpha = c(p._m0, dtype=float), c(p._ys, dtype=float), c(p._alpha, dtype=float)
        self.Q = c(p._Q, dtype=float)
        U, k = self.alpha.shape
        self.d, self.k = self.Xb.shape[1], k
        self.z, self.acc, self.K, self.m = np.empty(self.d), np.empty(k), np.empty((U, k)), np.empty(k)
        self.kt = np.empty(U)

    def std(self) -> np.ndarray:
        """The latent std (k,) at the input of the last `gp_mean` on these arrays."""
        return self.ys * np.sqrt(gp_var(self.K, self.Q, self.sf2, self.kt))
