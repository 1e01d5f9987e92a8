"""The numerical core of the GP (dt_runtime.models.gp): the squared-exponential kernel, the
replicate collapse and the exact collapsed log marginal likelihood with its analytic gradient
(the collapse is derived in `gp.GPRegressor`'s docstring, the gradient in `collapsed_nll`),
farthest-point inducing inputs."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import linalg
from scipy.linalg import lapack
from scipy.spatial.distance import cdist

LOG2PI = float(np.log(2 * np.pi))


def inv_from_chol(L: np.ndarray) -> np.ndarray:
    """K^-1 from its lower Cholesky factor (LAPACK potri), symmetrised.

    Parameters
    ----------
    L : ndarray
        (n, n) lower Cholesky factor of K.

    Returns
    -------
    ndarray
        (n, n).
    """
    Kinv, info = lapack.dpotri(L, lower=1)
    if info != 0:
        raise linalg.LinAlgError(f"potri failed ({info})")
    Kinv = np.tril(Kinv)
    return Kinv + np.tril(Kinv, -1).T


def distinct(X: np.ndarray):
    """Distinct rows of X, the index of each row's distinct row, and the replicate counts.

    Parameters
    ----------
    X : ndarray
        (N, d).

    Returns
    -------
    U : ndarray
        (n, d) distinct rows.
    inv : ndarray
        (N,) index into U.
    counts : ndarray
        (n,).
    """
    U, inv, counts = np.unique(X, axis=0, return_inverse=True, return_counts=True)
    return U, inv.ravel(), counts.astype(float)


def group_stats(inv: np.ndarray, counts: np.ndarray, y: np.ndarray):
    """Mean target and within-group sum of squares of every distinct input (`distinct`).

    Parameters
    ----------
    inv : ndarray
        (N,) index of each row's distinct input.
    counts : ndarray
        (n,) replicates per input.
    y : ndarray
        (N,) target.

    Returns
    -------
    ybar : ndarray
        (n,).
    ss : float
    """
    ybar = np.bincount(inv, weights=y, minlength=len(counts)) / counts
    ss = np.bincount(inv, weights=(y - ybar[inv]) ** 2, minlength=len(counts))
    return ybar, ss


def farthest_points(U: np.ndarray, m: int) -> np.ndarray:
    """Indices of m rows of U by farthest-point sampling, started at the row nearest the centroid.

    Parameters
    ----------
    U : ndarray
        (n, d).
    m : int
        How many.

    Returns
    -------
    ndarray
        (m,) indices.
    """
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
    """The squared-exponential kernel sf2 exp(-1/2 sum_k (a_k - b_k)^2 / ell_k^2).

    Parameters
    ----------
    A, B : ndarray
        (n, d) and (m, d) inputs.
    ell : ndarray
        (d,) length scales.
    sf2 : float
        Signal variance.

    Returns
    -------
    ndarray
        (n, m).
    """
    return sf2 * np.exp(-0.5 * cdist(A / ell, B / ell, "sqeuclidean"))


# --- likelihood ------------------------------------------------------------------------------
def sq_dists(U: np.ndarray) -> np.ndarray:
    """(d, n, n) per-dimension squared distances of the rows of U.

    Parameters
    ----------
    U : ndarray
        (n, d).

    Returns
    -------
    ndarray
    """
    # Written in place, one dimension at a time: the same numbers as stacking the (n, n) squares,
    # without a temporary per dimension and the stack's copy (~15 ms of a fold's fit at n 1,000).
    n, d = U.shape
    D2 = np.empty((d, n, n))
    for k in range(d):
        np.subtract.outer(U[:, k], U[:, k], out=D2[k])
        np.multiply(D2[k], D2[k], out=D2[k])
    return D2


@dataclass(frozen=True)
class Collapsed:
    """What the collapsed likelihood of one set of distinct inputs reads, fixed for a whole fit:
    D2 (d, n, n) the per-dimension squared distances of the standardised distinct inputs
    (computed once per fit, read by every evaluation), counts, ybar, the summed
    within-replicate squares ss and N, the number of rows."""

    D2: np.ndarray
    counts: np.ndarray
    ybar: np.ndarray
    ss: float
    N: int
    const: float  # the terms of nll that do not depend on theta

    @classmethod
    def of(cls, U: np.ndarray, counts: np.ndarray, ybar: np.ndarray, ss: float, N: int) -> Collapsed:
        """The fixed quantities of a fit from its distinct inputs.

        Parameters
        ----------
        U : ndarray
            (n, d) standardised distinct inputs.
        counts : ndarray
            (n,) replicates per input.
        ybar : ndarray
            (n,) mean target per input.
        ss : float
            Summed within-replicate squares.
        N : int
            Number of rows.

        Returns
        -------
        Collapsed
        """
        n = len(ybar)
        const = 0.5 * n * LOG2PI + 0.5 * (N - n) * LOG2PI + 0.5 * np.log(counts).sum()
        return cls(sq_dists(U), counts, ybar, float(ss), int(N), float(const))


def collapsed_factor(theta: np.ndarray, st: Collapsed):
    """The kernel of the distinct inputs and its Cholesky factor at theta: (nll, beta, alpha, L,
    K), or None where K is not positive definite. K = s_f^2 E + s_n^2 diag(1/n_i) (C order,
    exactly symmetric: LAPACK reads its transpose view, Fortran order, without a copy); L is its
    lower factor, zero above the diagonal; alpha = K^-1 (ybar - beta).

    Parameters
    ----------
    theta : ndarray
        Standardised log-parameters.
    st : Collapsed
        The fit's fixed quantities.

    Returns
    -------
    tuple or None
    """
    d = st.D2.shape[0]
    sf2, sn2 = np.exp(theta[d]), np.exp(theta[d + 1])
    if not (np.all(np.isfinite(theta)) and sf2 > 0 and sn2 > 0):
        return None
    K = np.tensordot(np.exp(-2 * theta[:d]), st.D2, axes=1)
    K *= -0.5
    np.exp(K, out=K)
    K *= sf2
    K[np.diag_indices(len(st.ybar))] += sn2 / st.counts
    L, info = lapack.dpotrf(K.T, lower=1, clean=1)
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
    # Within-replicate part (`gp.GPRegressor`'s docstring).
    nll += 0.5 * (st.N - len(st.ybar)) * np.log(sn2) + st.ss / (2 * sn2)
    if not np.isfinite(nll):
        return None
    return float(nll), beta, alpha, L, K


def collapsed_nll(theta: np.ndarray, st: Collapsed, want_grad: bool = True):
    """Negative exact log marginal likelihood of all N rows from the collapsed statistics, and
    its gradient in theta = [log l_1..log l_d, log s_f^2, log s_n^2] (standardised units).
    Returns (nll, grad or None, beta); (1e25, zeros, 0.0) where the kernel is not positive
    definite.

    Gradient (Rasmussen & Williams Eq. 5.9) with W = alpha alpha' - K^-1 and S = s_f^2 E:
      d/d log l_k = -1/2 sum_ij W_ij S_ij D2_kij / l_k^2,  d/d log s_f^2 = -1/2 sum_ij W_ij S_ij,
      d/d log s_n^2 = -1/2 s_n^2 sum_i W_ii / n_i + (the within-replicate part).
    The sums read W o S through one (n, n) array B built from the triangle of K^-1 that potri
    leaves (no symmetric copy): B = (alpha alpha' - 2 triu K^-1) o S off the diagonal, whose
    (i, j) + (j, i) is 2 W_ij S_ij, and W_ii S_ii on it; D2 is symmetric with a zero diagonal.
    The contraction with D2 sums exact squared distances: a direction the kernel no longer
    sees (a length scale at its bound over an input with a few levels) gets its true, tiny
    gradient, not the round-off of a difference of large sums (which sent L-BFGS-B elsewhere).

    Parameters
    ----------
    theta : ndarray
        Standardised log-parameters.
    st : Collapsed
        The fit's fixed quantities.
    want_grad : bool, optional
        Compute the gradient.

    Returns
    -------
    nll : float
    grad : ndarray or None
    beta : float
    """
    f = collapsed_factor(theta, st)
    if f is None:
        return 1e25, np.zeros_like(theta), 0.0
    nll, beta, alpha, L, K = f
    if not want_grad:
        return nll, None, beta
    d = st.D2.shape[0]
    inv_ell2 = np.exp(-2 * theta[:d])
    sf2, sn2 = np.exp(theta[d]), np.exp(theta[d + 1])
    T, info = lapack.dpotri(L, lower=1, overwrite_c=1)  # K^-1 on and below the diagonal, zeros above
    if info != 0:
        return 1e25, np.zeros_like(theta), 0.0
    Tt = T.T  # C order: K^-1 on and above the diagonal, zeros below
    tdiag = np.diagonal(Tt).copy()
    Tt *= -2.0
    B = np.outer(alpha, alpha)
    B += Tt
    B *= K
    B[np.diag_indices(len(tdiag))] = (alpha ** 2 - tdiag) * sf2  # W_ii S_ii (K's diagonal has the noise)
    g = np.empty_like(theta)
    g[:d] = -0.5 * np.tensordot(st.D2, B, axes=([1, 2], [0, 1])) * inv_ell2
    g[d] = -0.5 * B.sum()
    g[d + 1] = -0.5 * sn2 * np.sum((alpha ** 2 - tdiag) / st.counts) + 0.5 * (st.N - len(st.ybar)) \
        - st.ss / (2 * sn2)
    return nll, g, beta
