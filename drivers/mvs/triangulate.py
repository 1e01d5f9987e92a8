"""N-view triangulation (DLT + Gauss-Newton on the reprojection error) and epipolar matching.

Observations are held per marker and camera in dense arrays with a mask:
`uv` (M, C, 2) ideal (undistorted) pixels, `sig` (M, C) their standard deviation in pixels,
`mask` (M, C) bool. Every step is batched over markers, so five markers cost one pass.
Residuals are normalised by sigma, so the Gauss-Newton normal matrix inverse is the
covariance of the point (m^2) propagated from the pixel noise.
"""
from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from drivers.mvs.camera import Camera


class CameraStack:
    """The rig's cameras as stacked arrays for batched projection."""

    def __init__(self, cameras: Sequence[Camera]):
        self.cameras = tuple(cameras)
        self.R = np.stack([c.R for c in cameras])  # (C,3,3)
        self.t = np.stack([c.t for c in cameras])  # (C,3)
        self.f = np.stack([np.diag(c.K)[:2] for c in cameras])  # (C,2)
        self.c = np.stack([c.K[:2, 2] for c in cameras])  # (C,2)
        self.P = np.concatenate([self.R, self.t[:, :, None]], axis=2)  # (C,3,4) normalised cameras
        self.centers = np.stack([c.center for c in cameras])

    def __len__(self) -> int:
        return len(self.cameras)

    def to_normalised(self, uv: np.ndarray) -> np.ndarray:
        """Ideal pixels to normalised image coordinates.

        Parameters
        ----------
        uv : ndarray
            (..., C, 2) ideal px.

        Returns
        -------
        ndarray
            (..., C, 2), dimensionless.
        """
        return (uv - self.c) / self.f

    def project(self, X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Project points into every camera (pinhole, no distortion).

        Parameters
        ----------
        X : ndarray
            (M, 3) m, MVS frame.

        Returns
        -------
        uv : ndarray
            (M, C, 2) ideal px.
        Xc : ndarray
            (M, C, 3) m, the points in each camera's frame.
        """
        Xc = np.einsum("cij,mj->mci", self.R, X) + self.t[None]
        return Xc[..., :2] / Xc[..., 2:3] * self.f + self.c, Xc

    def residuals(self, X: np.ndarray, uv: np.ndarray, s: np.ndarray, m: np.ndarray
                  ) -> tuple[np.ndarray, np.ndarray]:
        """Normalised reprojection residuals of points and their Jacobian.

        d proj / d Xc = f/z [[1, 0, -x/z], [0, 1, -y/z]], d Xc / d X = R.

        Parameters
        ----------
        X : ndarray
            (M, 3) m.
        uv : ndarray
            (M, C, 2) ideal px, the observations.
        s : ndarray
            (M, C, 1) px, their standard deviations.
        m : ndarray
            (M, C, 1) bool, the views used (others give zero residual and Jacobian).

        Returns
        -------
        r : ndarray
            (M, C, 2), normalised by ``s``.
        J : ndarray
            (M, C, 2, 3), d r / d X (1/m).
        """
        proj, Xc = self.project(X)
        r = np.where(m, (proj - uv) / s, 0.0)
        z = Xc[..., 2:3]
        x_z = Xc[..., :2] / z
        J_c = np.zeros(Xc.shape[:2] + (2, 3))
        J_c[..., 0, 0] = 1.0
        J_c[..., 1, 1] = 1.0
        J_c[..., :, 2] = -x_z
        J_c *= (self.f[None, :, :, None] / z[..., None])
        return r, np.einsum("mcij,cjk->mcik", J_c, self.R) / s[..., None] * m[..., None]


def dlt(stack: CameraStack, uv: np.ndarray, sig: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Linear (DLT) triangulation of M points from masked views; rows weighted by f / sigma.

    Parameters
    ----------
    stack : CameraStack
        The cameras.
    uv : ndarray
        (M, C, 2) ideal px.
    sig : ndarray
        (M, C) px.
    mask : ndarray
        (M, C) bool, the views used.

    Returns
    -------
    ndarray
        (M, 3) m, MVS frame.
    """
    xn = stack.to_normalised(uv)  # (M,C,2)
    P = stack.P[None]  # (1,C,3,4)
    a1 = xn[..., 0:1] * P[..., 2, :] - P[..., 0, :]
    a2 = xn[..., 1:2] * P[..., 2, :] - P[..., 1, :]
    wgt = np.where(mask, stack.f.mean(axis=1)[None] / np.where(mask, sig, 1.0), 0.0)[..., None]
    A = np.concatenate([a1 * wgt, a2 * wgt], axis=1)  # (M,2C,4)
    _, _, vt = np.linalg.svd(A)
    Xh = vt[:, -1, :]
    return Xh[:, :3] / Xh[:, 3:4]


def refine_points(stack: CameraStack, X: np.ndarray, uv: np.ndarray, sig: np.ndarray,
                  mask: np.ndarray, iters: int = 2):
    """Gauss-Newton on the normalised reprojection error, batched over points.

    Parameters
    ----------
    stack : CameraStack
        The cameras.
    X : ndarray
        (M, 3) m, the starting points.
    uv : ndarray
        (M, C, 2) ideal px.
    sig : ndarray
        (M, C) px.
    mask : ndarray
        (M, C) bool, the views used.
    iters : int
        Gauss-Newton steps.

    Returns
    -------
    X : ndarray
        (M, 3) m.
    cov : ndarray
        (M, 3, 3) m^2.
    residuals : ndarray
        (M, C, 2), normalised by sigma.
    """
    s = np.where(mask, sig, 1.0)[..., None]
    m = mask[..., None]
    for _ in range(iters + 1):
        r, J = stack.residuals(X, uv, s, m)  # (M,C,2), (M,C,2,3)
        H = np.einsum("mcia,mcib->mab", J, J)
        if _ == iters:
            break
        g = np.einsum("mcia,mci->ma", J, r)
        X = X - np.linalg.solve(H + 1e-12 * np.eye(3), g[..., None])[..., 0]
    cov = np.linalg.inv(H + 1e-18 * np.eye(3))
    return X, cov, r


def triangulate(stack: CameraStack, uv: np.ndarray, sig: np.ndarray, mask: np.ndarray,
                gate: float = 5.0, min_views: int = 2):
    """Triangulate with per-view outlier rejection.

    The worst view of a point is dropped while its normalised residual exceeds ``gate`` and more
    than ``min_views`` remain; a point left with a residual above the gate is not ok.

    Parameters
    ----------
    stack : CameraStack
        The cameras.
    uv : ndarray
        (M, C, 2) ideal px.
    sig : ndarray
        (M, C) px.
    mask : ndarray
        (M, C) bool, the views found (not modified).
    gate : float
        Normalised residual beyond which a view is an outlier.
    min_views : int
        Views a point needs.

    Returns
    -------
    X : ndarray
        (M, 3) m (NaN where a point has too few views).
    cov : ndarray
        (M, 3, 3) m^2.
    mask : ndarray
        (M, C) bool, the views kept.
    ok : ndarray
        (M,) bool, points with enough consistent views.
    """
    mask = mask.copy()
    M, C = mask.shape
    ok = mask.sum(1) >= min_views
    X = np.full((M, 3), np.nan)
    cov = np.full((M, 3, 3), np.nan)
    if not np.any(ok):
        return X, cov, mask, ok
    idx = np.flatnonzero(ok)
    mk = mask[idx]
    for _ in range(C):
        Xi = dlt(stack, uv[idx], sig[idx], mk)
        Xi, ci, r = refine_points(stack, Xi, uv[idx], sig[idx], mk)
        rn = np.linalg.norm(r, axis=2)
        # Residuals of an n-view fit shrink by ~sqrt((2n-3)/2n); gate on the raw norm anyway.
        worst = np.argmax(rn, axis=1)
        bad = (rn[np.arange(len(idx)), worst] > gate) & (mk.sum(1) > min_views)
        if not np.any(bad):
            break
        mk[np.flatnonzero(bad), worst[bad]] = False
    X[idx], cov[idx] = Xi, ci
    mask[idx] = mk
    # A 2-view point may still hold an outlier far off the epipolar line: refuse it.
    rn = np.linalg.norm(r, axis=2)
    ok[idx] = (mk.sum(1) >= min_views) & (rn.max(axis=1) <= gate)
    return X, cov, mask, ok


def epipolar_candidates(stack: CameraStack, blobs: Sequence[np.ndarray], blob_sig: Sequence[np.ndarray],
                        tol_px: float = 1.0, min_support: int = 3):
    """3-D candidate points from unlabeled blobs by epipolar matching.

    For every camera pair, blob pairs within ``tol_px`` of each other's epipolar line are
    triangulated; each candidate is re-projected into all cameras and collects the nearest
    blob within twice ``tol_px``. Candidates are refined on their support and de-duplicated greedily
    (most support first; a blob is used once).

    Parameters
    ----------
    stack : CameraStack
        The cameras.
    blobs : sequence of ndarray
        Per camera, (n_c, 2) ideal px.
    blob_sig : sequence of ndarray
        Per camera, (n_c,) px.
    tol_px : float
        Epipolar distance tolerance (px).
    min_support : int
        Views a candidate needs.

    Returns
    -------
    X : ndarray
        (n, 3) m.
    uv : ndarray
        (n, C, 2) ideal px.
    sig : ndarray
        (n, C) px.
    mask : ndarray
        (n, C) bool.
    """
    C = len(stack)
    cand = []
    for a in range(C):
        for b in range(a + 1, C):
            A, B = blobs[a], blobs[b]
            if len(A) == 0 or len(B) == 0:
                continue
            xa = stack.to_normalised(A[:, None, :].repeat(C, 1))[:, a]
            xb = stack.to_normalised(B[:, None, :].repeat(C, 1))[:, b]
            Rab = stack.R[b] @ stack.R[a].T
            tab = stack.t[b] - Rab @ stack.t[a]
            tx = np.array([[0, -tab[2], tab[1]], [tab[2], 0, -tab[0]], [-tab[1], tab[0], 0]])
            E = tx @ Rab
            ha, hb = np.c_[xa, np.ones(len(xa))], np.c_[xb, np.ones(len(xb))]
            lines = ha @ E.T  # epipolar lines in b (normalised)
            d = np.abs(hb @ lines.T) / np.linalg.norm(lines[:, :2], axis=1)[None]  # (nb, na)
            ib, ia = np.nonzero(d * stack.f[b].mean() < tol_px)
            for i, j in zip(ia, ib):
                cand.append((a, i, b, j))
    if not cand:
        return np.zeros((0, 3)), np.zeros((0, C, 2)), np.zeros((0, C)), np.zeros((0, C), bool)
    n = len(cand)
    uv = np.zeros((n, C, 2))
    sg = np.ones((n, C))
    mk = np.zeros((n, C), bool)
    for k, (a, i, b, j) in enumerate(cand):
        uv[k, a], uv[k, b] = blobs[a][i], blobs[b][j]
        sg[k, a], sg[k, b] = blob_sig[a][i], blob_sig[b][j]
        mk[k, a] = mk[k, b] = True
    X = dlt(stack, uv, sg, mk)
    proj, Xc = stack.project(X)
    sup_idx = np.full((n, C), -1)
    for c in range(C):
        if len(blobs[c]) == 0:
            continue
        dd = np.linalg.norm(proj[:, c, None, :] - blobs[c][None], axis=2)
        j = np.argmin(dd, axis=1)
        hit = (dd[np.arange(n), j] < tol_px * 2) & (Xc[:, c, 2] > 0)
        sup_idx[hit, c] = j[hit]
        uv[hit, c] = blobs[c][j[hit]]
        sg[hit, c] = blob_sig[c][j[hit]]
    mk = sup_idx >= 0
    support = mk.sum(1)
    order = np.argsort(-support, kind="stable")
    used: list[set[int]] = [set() for _ in range(C)]
    keep_k: list[int] = []
    for k in order:
        if support[k] < min_support:
            break
        cams = np.flatnonzero(mk[k])
        if any(sup_idx[k, c] in used[c] for c in cams):
            continue
        for cam in cams:
            used[cam].add(sup_idx[k, cam])
        keep_k.append(k)
    keep = np.array(keep_k, int)
    if len(keep) == 0:
        return np.zeros((0, 3)), np.zeros((0, C, 2)), np.zeros((0, C)), np.zeros((0, C), bool)
    X, _, mkk, ok = triangulate(stack, uv[keep], sg[keep], mk[keep])
    return X[ok], uv[keep][ok], sg[keep][ok], mkk[ok]
