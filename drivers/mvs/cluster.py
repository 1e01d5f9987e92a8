"""Rigid fit of the marker cluster: Kabsch, pose refinement on the pixels, covariance, identification.

The cluster geometry `m_i` is given in the tool frame whose origin is the TCP/SMR, so the
measured TCP is the translation of the fitted pose X_i = R m_i + t. The refined pose minimises
the normalised reprojection error of every kept observation directly; the inverse of its
Gauss-Newton normal matrix is the 6x6 pose covariance propagated from the pixel noise, whose
translation block is the TCP covariance.
"""
from __future__ import annotations

import itertools

import numpy as np

from drivers.mvs.triangulate import CameraStack
from dt_kernel.geometry import skew


def kabsch(model: np.ndarray, meas: np.ndarray, w: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Weighted least-squares rotation and translation with meas ~ R @ model + t.

    Parameters
    ----------
    model : ndarray
        (n, 3) points in the model frame.
    meas : ndarray
        (n, 3) the same points measured.
    w : ndarray or None
        (n,) weights (equal when None).

    Returns
    -------
    R : ndarray
        (3, 3), a proper rotation.
    t : ndarray
        (3,), in the unit of ``meas``.
    """
    w = np.ones(len(model)) if w is None else np.asarray(w, float)
    w = w / w.sum()
    cm, cx = w @ model, w @ meas
    Hm = (model - cm).T @ ((meas - cx) * w[:, None])
    U, _, Vt = np.linalg.svd(Hm)
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(Vt.T @ U.T))])
    R = Vt.T @ D @ U.T
    return R, cx - R @ cm


def _rotvec(w: np.ndarray) -> np.ndarray:
    th = np.linalg.norm(w)
    if th < 1e-12:
        return np.eye(3) + skew(w)
    k = skew(w / th)
    return np.eye(3) + np.sin(th) * k + (1 - np.cos(th)) * k @ k


def refine_pose(stack: CameraStack, model: np.ndarray, R: np.ndarray, t: np.ndarray, uv: np.ndarray,
                sig: np.ndarray, mask: np.ndarray, iters: int = 2):
    """Gauss-Newton pose refinement on the normalised reprojection error of every kept view.

    The perturbation is R = exp([w]x) R0, t = t0 + dt.

    Parameters
    ----------
    stack : CameraStack
        The cameras.
    model : ndarray
        (M, 3) m, marker cluster in the tool frame.
    R, t : ndarray
        (3, 3) and (3,) m, the starting pose (tool -> MVS).
    uv : ndarray
        (M, C, 2) ideal px, the observations.
    sig : ndarray
        (M, C) px, their standard deviations.
    mask : ndarray
        (M, C) bool, the observations kept.
    iters : int
        Gauss-Newton steps.

    Returns
    -------
    R : ndarray
        (3, 3).
    t : ndarray
        (3,) m.
    cov : ndarray
        (6, 6) [rotation vector rad, translation m], propagated from the pixel noise.
    residuals : ndarray
        (M, C, 2), normalised.
    """
    s = np.where(mask, sig, 1.0)[..., None]
    m = mask[..., None]
    for it in range(iters + 1):
        RM = model @ R.T  # (M,3) rotated model
        X = RM + t
        r, J_X = stack.residuals(X, uv, s, m)  # (M,C,2), (M,C,2,3)
        # d X / d w = -[R0 m]x, d X / d t = I
        J_w = -np.einsum("mcij,mjk->mcik", J_X, skew(RM))
        J = np.concatenate([J_w, J_X], axis=3).reshape(-1, 6)
        H = J.T @ J
        if it == iters:
            break
        g = J.T @ r.reshape(-1)
        d = np.linalg.solve(H + 1e-12 * np.eye(6), g)
        R = _rotvec(-d[:3]) @ R
        t = t - d[3:]
    cov = np.linalg.inv(H)
    return R, t, cov, r


def fit_points(model: np.ndarray, X: np.ndarray, cov: np.ndarray, idx, gate: float, min_markers: int):
    """Rigid fit of the cluster to measured 3-D markers with per-marker outlier rejection.

    Weighted Kabsch, then the marker farthest from the fitted model in Mahalanobis distance is
    dropped while it exceeds ``gate`` and more than ``min_markers`` remain.

    Parameters
    ----------
    model : ndarray
        (M, 3) m, tool frame.
    X : ndarray
        (M, 3) m, the measured markers (MVS frame).
    cov : ndarray
        (M, 3, 3) m^2, their covariances.
    idx : iterable of int
        The markers to use.
    gate : float
        Mahalanobis distance beyond which a marker is an outlier.
    min_markers : int
        Markers that must remain.

    Returns
    -------
    R : ndarray
        (3, 3).
    t : ndarray
        (3,) m.
    kept : list of int
        The markers kept.
    refusal : str or None
        Why the cluster does not fit its geometry, or None.
    """
    idx = list(idx)
    while True:
        w = 1.0 / np.trace(cov[idx], axis1=1, axis2=2)
        R, t = kabsch(model[idx], X[idx], w)
        e = X[idx] - (model[idx] @ R.T + t)
        d2 = np.einsum("ni,nij,nj->n", e, np.linalg.inv(cov[idx]), e)
        worst = int(np.argmax(d2))
        if d2[worst] <= gate ** 2:
            return R, t, idx, None
        if len(idx) <= min_markers:
            return R, t, idx, (f"marker cluster does not fit its geometry"
                               f" (marker {idx[worst]} off by {1e3 * np.linalg.norm(e[worst]):.2f} mm)")
        idx.pop(worst)


def point_fit_cov(model: np.ndarray, R: np.ndarray, cov: np.ndarray) -> np.ndarray:
    """6x6 covariance [rotation vector, translation] of a rigid fit to 3-D markers.

    Linearised as in ``refine_pose`` (X = exp([w]x) R m + t): J_i = [-[R m_i]x, I], and the
    covariance is the inverse of sum J_i^T cov_i^-1 J_i over the markers used.

    Parameters
    ----------
    model : ndarray
        (M, 3) m, the markers used, tool frame.
    R : ndarray
        (3, 3), the fitted rotation.
    cov : ndarray
        (M, 3, 3) m^2, the measured markers' covariances.

    Returns
    -------
    ndarray
        (6, 6) [rad, m].
    """
    H = np.zeros((6, 6))
    for m, c in zip(model @ R.T, cov):
        J = np.hstack([-skew(m), np.eye(3)])
        H += J.T @ np.linalg.solve(c, J)
    return np.linalg.inv(H)


def identify(model: np.ndarray, points: np.ndarray, tol: float = 1e-3):
    """Label unlabeled 3-D points with the cluster's markers by their mutual distances.

    For each triple of model markers and each ordered triple of points whose three distances
    match within ``tol``, a Kabsch pose is computed; the pose that brings the most markers within
    ``tol`` of a point (then the smallest residual) wins.

    Parameters
    ----------
    model : ndarray
        (M, 3) m, tool frame.
    points : ndarray
        (n, 3) m, the unlabeled points.
    tol : float
        m.

    Returns
    -------
    tuple or None
        (R (3, 3), t (3,) m, labels (n,) marker index or -1), or None when fewer than 3 markers
        are found.
    """
    n = len(points)
    if n < 3:
        return None
    Dm = np.linalg.norm(model[:, None] - model[None], axis=2)
    Dp = np.linalg.norm(points[:, None] - points[None], axis=2)
    best = None
    perms = np.array(list(itertools.permutations(range(n), 3)))
    for tri in itertools.combinations(range(len(model)), 3):
        i, j, k = tri
        ok = ((np.abs(Dp[perms[:, 0], perms[:, 1]] - Dm[i, j]) < tol)
              & (np.abs(Dp[perms[:, 1], perms[:, 2]] - Dm[j, k]) < tol)
              & (np.abs(Dp[perms[:, 0], perms[:, 2]] - Dm[i, k]) < tol))
        for p in perms[ok]:
            R, t = kabsch(model[list(tri)], points[p])
            pred = model @ R.T + t
            d = np.linalg.norm(pred[:, None] - points[None], axis=2)  # (Mm, n)
            j_near = np.argmin(d, axis=1)
            hit = d[np.arange(len(model)), j_near] < tol
            # one point per marker
            if len(set(j_near[hit])) < hit.sum():
                continue
            score = (hit.sum(), -d[np.arange(len(model)), j_near][hit].sum())
            if best is None or score > best[0]:
                labels = np.full(n, -1)
                labels[j_near[hit]] = np.flatnonzero(hit)
                best = (score, R, t, labels)
    if best is None or best[0][0] < 3:
        return None
    _, R, t, labels = best
    sel = labels >= 0
    R, t = kabsch(model[labels[sel]], points[sel])
    return R, t, labels
