"""The numerical core of the GP (dt_runtime.models.gp): the squared-exponential kernel, the
replicate collapse and the exact collapsed log marginal likelihood with its analytic gradient
(the collapse is derived in gp.py's module docstring, the gradient in `collapsed_nll`),
farthest-point inducing inputs."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import linalg
from scipy.linalg import blas, lapack
from scipy.spatial.distance import cdist

LOG2PI = float(np.log(2 * np.pi))


def inv_from_chol(L: np.ndarray) -> np.ndarray:
    """K^-1 from its lower Cholesky factor (LAPACK potri), symmetrised."""
    Kinv, info = lapack.dpotri(L, lower=1)
    if info != 0:
        raise linalg.LinAlgError(f"potri failed ({info})")
    Kinv = np.tril(Kinv)
    return Kinv + np.tril(Kinv, -1).T


def distinct(X: np.ndarray):
    """Distinct rows of X, the index of each row's distinct row, and the replicate counts."""
    U, inv, counts = np.unique(X, axis=0, return_inverse=True, return_counts=True)
    return U, inv.ravel(), counts.astype(float)


def group_stats(inv: np.ndarray, counts: np.ndarray, y: np.ndarray):
    """Mean target and within-group sum of squares of every distinct input (`distinct`)."""
    ybar = np.bincount(inv, weights=y, minlength=len(counts)) / counts
    ss = np.bincount(inv, weights=(y - ybar[inv]) ** 2, minlength=len(counts))
    return ybar, ss


def farthest_points(U: np.ndarray, m: int) -> np.ndarray:
    """Indices of m rows of U by farthest-point sampling, started at the row nearest the centroid."""
    m = min(m, len(U))
    idx = np.empty(m, dtype=np.intp)
    idx[0] = int(np.argmin(((U - U.mean(0)) ** 2).sum(1)))
    dmin = ((U - U[idx[0]]) ** 2).sum(1)
    # Dimensions as rows, buffers reused: the same sums in the same order as ((U - u)^2).sum(1)
    # (so the same points), 4x faster than reducing rows of d numbers.
    T = np.ascontiguousarray(U.T)
    diff, dj = np.empty_like(T), np.empty_like(dmin)
    for j in range(1, m):
        idx[j] = k = int(np.argmax(dmin))
        np.subtract(T, T[:, k:k + 1], out=diff)
        np.multiply(diff, diff, out=diff)
        np.sum(diff, axis=0, out=dj)
        np.minimum(dmin, dj, out=dmin)
    return idx


def se_kernel(A: np.ndarray, B: np.ndarray, ell: np.ndarray, sf2: float) -> np.ndarray:
    return sf2 * np.exp(-0.5 * cdist(A / ell, B / ell, "sqeuclidean"))


# --- likelihood ------------------------------------------------------------------------------
@dataclass(frozen=True)
class Collapsed:
    """What the collapsed likelihood of one set of distinct inputs reads, fixed for a whole fit:
    U (n, d) the standardised distinct inputs (centred: distances do not move and the gradient's
    contraction below loses less to round-off), counts, ybar and the summed within-replicate
    squares ss, N the number of rows, and [U, 1] for the gradient's contraction."""

    U: np.ndarray
    counts: np.ndarray
    ybar: np.ndarray
    ss: float
    N: int
    U1: np.ndarray
    const: float  # the terms of nll that do not depend on theta

    @classmethod
    def of(cls, U: np.ndarray, counts: np.ndarray, ybar: np.ndarray, ss: float, N: int) -> Collapsed:
        U = np.ascontiguousarray(U - U.mean(0))
        n = len(ybar)
        const = 0.5 * n * LOG2PI + 0.5 * (N - n) * LOG2PI + 0.5 * np.log(counts).sum()
        return cls(U, counts, ybar, float(ss), int(N), np.column_stack([U, np.ones(n)]), float(const))


def se_gram(theta: np.ndarray, U: np.ndarray) -> np.ndarray:
    """E (n, n), C order: exp(-1/2 sum_k (u_ik - u_jk)^2 / l_k^2) at theta's length scales, from
    one matrix product: -1/2 |z_i - z_j|^2 = [z_i, -h_i, 1] . [z_j, 1, -h_j], z = u / l,
    h = |z|^2 / 2 (no per-dimension distance matrices to keep or read). The diagonal is exactly 1."""
    n, d = U.shape
    Z = U * np.exp(-theta[:d])
    h = 0.5 * np.einsum("ij,ij->i", Z, Z)
    one = np.ones(n)
    R = np.column_stack([Z, -h, one]) @ np.column_stack([Z, one, -h]).T
    np.minimum(R, 0.0, out=R)  # round-off of near points
    R.flat[:: n + 1] = 0.0
    return np.exp(R, out=R)


def collapsed_factor(theta: np.ndarray, st: Collapsed):
    """The kernel of the distinct inputs and its Cholesky factor at theta: (nll, beta, alpha, L,
    K), or None where K is not positive definite. K = s_f^2 E + s_n^2 diag(1/n_i) is returned in
    Fortran order (the transpose view of a symmetric C array: LAPACK reads it without a copy); L
    is its lower factor, zero above the diagonal; alpha = K^-1 (ybar - beta)."""
    d = st.U.shape[1]
    sf2, sn2 = np.exp(theta[d]), np.exp(theta[d + 1])
    if not (np.all(np.isfinite(theta)) and sf2 > 0 and sn2 > 0):
        return None
    R = se_gram(theta, st.U)
    R *= sf2
    R.flat[:: len(st.ybar) + 1] += sn2 / st.counts
    K = R.T
    L, info = lapack.dpotrf(K, lower=1, clean=1)
    if info != 0:
        return None
    # The GLS constant mean and alpha from one solve with two right-hand sides (K^-1 is linear).
    Ki, info = lapack.dpotrs(L, np.column_stack([np.ones(len(st.ybar)), st.ybar]), lower=1)
    if info != 0:
        return None
    beta = float(Ki[:, 0] @ st.ybar / Ki[:, 0].sum())  # GLS constant mean
    alpha = Ki[:, 1] - beta * Ki[:, 0]
    r = st.ybar - beta
    nll = 0.5 * r @ alpha + np.log(np.diagonal(L)).sum() + st.const
    # Within-replicate part (gp.py's module docstring).
    nll += 0.5 * (st.N - len(st.ybar)) * np.log(sn2) + st.ss / (2 * sn2)
    if not np.isfinite(nll):
        return None
    return float(nll), beta, alpha, L, K


def collapsed_nll(theta: np.ndarray, st: Collapsed, want_grad: bool = True):
    """Negative exact log marginal likelihood of all N rows from the collapsed statistics, and
    its gradient in theta = [log l_1..log l_d, log s_f^2, log s_n^2] (standardised units).
    Returns (nll, grad or None, beta); (1e25, zeros, 0.0) where the kernel is not positive
    definite.

    Gradient (Rasmussen & Williams Eq. 5.9): d nll / d theta_j = -1/2 sum_ij (W o dK/dtheta_j)
    with W = alpha alpha' - K^-1, S = s_f^2 E, A = W o S (symmetric):
      d/d log l_k = -1/2 sum_ij A_ij (u_ik - u_jk)^2 / l_k^2
                  = -1/2 (2 sum_i u_ik^2 (A 1)_i - 2 u_k' A u_k) / l_k^2,
      d/d log s_f^2 = -1/2 1' A 1,  d/d log s_n^2 = -1/2 s_n^2 sum_i W_ii / n_i + (within part),
    so every length scale's sum comes out of one product A [U, 1] (n x (d+1)). A [U, 1] is
    alpha o (S (alpha o [U, 1])) minus (K^-1 o S)[U, 1], the latter by a symmetric product from
    the lower triangle of K^-1 that potri leaves: no full K^-1, no n x n x d array."""
    f = collapsed_factor(theta, st)
    if f is None:
        return 1e25, np.zeros_like(theta), 0.0
    nll, beta, alpha, L, K = f
    if not want_grad:
        return nll, None, beta
    d = st.U.shape[1]
    sf2, sn2 = np.exp(theta[d]), np.exp(theta[d + 1])
    noise = sn2 / st.counts  # K's diagonal is s_f^2 + noise
    T, info = lapack.dpotri(L, lower=1, overwrite_c=1)  # lower triangle of K^-1 (above: L's zeros)
    if info != 0:
        return 1e25, np.zeros_like(theta), 0.0
    tdiag = np.diagonal(T).copy()
    T *= K  # (K^-1 o K) lower; on the diagonal K's noise is not S's:
    T[np.diag_indices(len(tdiag))] = tdiag * sf2
    X = st.U1
    aX = alpha[:, None] * X
    # symm: a symmetric matrix from its lower triangle (T's upper is zero, not K^-1's)
    P = alpha[:, None] * (blas.dsymm(1.0, K, aX, lower=1) - noise[:, None] * aX)  # (alpha alpha' o S) X
    P -= blas.dsymm(1.0, T, X, lower=1)  # - (K^-1 o S) X
    rows = P[:, d]  # A 1
    g = np.empty_like(theta)
    g[:d] = -(np.einsum("ik,i->k", X[:, :d] ** 2, rows) - np.einsum("ik,ik->k", X[:, :d], P[:, :d])) \
        * np.exp(-2 * theta[:d])
    g[d] = -0.5 * rows.sum()
    g[d + 1] = -0.5 * sn2 * np.sum((alpha ** 2 - tdiag) / st.counts) + 0.5 * (st.N - len(st.ybar)) \
        - st.ss / (2 * sn2)
    return nll, g, beta
