"""The numerical core of the GP (dt_runtime.models.gp): the squared-exponential kernel, the
replicate collapse and the exact collapsed log marginal likelihood with its analytic gradient
(the derivation is in gp.py's module docstring), farthest-point inducing inputs."""
from __future__ import annotations

import numpy as np
from scipy import linalg
from scipy.linalg import lapack
from scipy.spatial.distance import cdist

LOG2PI = float(np.log(2 * np.pi))


def inv_from_chol(L: np.ndarray) -> np.ndarray:
    """K^-1 from its lower Cholesky factor (LAPACK potri), symmetrised."""
    Kinv, info = lapack.dpotri(L, lower=1)
    if info != 0:
        raise linalg.LinAlgError(f"potri failed ({info})")
    Kinv = np.tril(Kinv)
    return Kinv + np.tril(Kinv, -1).T


def collapse(X: np.ndarray, y: np.ndarray):
    """Distinct rows of X, replicate counts, mean targets and per-group sums of squares."""
    U, inv, counts = np.unique(X, axis=0, return_inverse=True, return_counts=True)
    inv = inv.ravel()
    ybar = np.bincount(inv, weights=y, minlength=len(U)) / counts
    ss = np.bincount(inv, weights=(y - ybar[inv]) ** 2, minlength=len(U))
    return U, counts.astype(float), ybar, ss


def farthest_points(U: np.ndarray, m: int) -> np.ndarray:
    """Indices of m rows of U by farthest-point sampling, started at the row nearest the centroid."""
    m = min(m, len(U))
    idx = np.empty(m, dtype=np.intp)
    idx[0] = int(np.argmin(((U - U.mean(0)) ** 2).sum(1)))
    dmin = ((U - U[idx[0]]) ** 2).sum(1)
    for j in range(1, m):
        idx[j] = int(np.argmax(dmin))
        np.minimum(dmin, ((U - U[idx[j]]) ** 2).sum(1), out=dmin)
    return idx


def se_kernel(A: np.ndarray, B: np.ndarray, ell: np.ndarray, sf2: float) -> np.ndarray:
    return sf2 * np.exp(-0.5 * cdist(A / ell, B / ell, "sqeuclidean"))


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
    W = np.outer(alpha, alpha) - inv_from_chol(L)  # d lml / dK
    WK = W * K
    WE = WK - np.diag(np.diag(W) * sn2 / counts)  # W o (s_f^2 E)
    g = np.empty_like(theta)
    g[:d] = -0.5 * np.tensordot(D2, WE, axes=([1, 2], [0, 1])) * inv_ell2
    g[d] = -0.5 * WE.sum()
    g[d + 1] = -0.5 * sn2 * np.sum(np.diag(W) / counts) + 0.5 * (N - U) - ss / (2 * sn2)
    return float(nll), g, beta


def sq_dists(U: np.ndarray) -> np.ndarray:
    return np.stack([(U[:, k, None] - U[None, :, k]) ** 2 for k in range(U.shape[1])])
