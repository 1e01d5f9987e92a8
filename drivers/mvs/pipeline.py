"""The MVS pipeline: images -> centroids -> correspondences -> 3-D markers -> cluster pose -> TCP.

`MarkerTracker(model).measure(images, predicted_pose)`:

1. Correspondence. With a predicted pose (the twin's, MVS frame) each marker is projected into
   each camera and its blob is centroided in a small region of interest around it (fast path).
   Without one, or when that path finds too few markers, blobs are detected full frame,
   matched across views by epipolar geometry, triangulated, and labelled by the cluster's
   mutual distances; the pose found seeds the ROI path.
2. Undistortion of the centroids to ideal pixels; N-view triangulation per marker (DLT, then
   Gauss-Newton) with per-view outlier rejection.
3. Rigid fit of the cluster (weighted Kabsch) with per-marker outlier rejection; then the pose
   is refined on all kept pixels, views failing the residual gate are dropped, and the 6x6 pose
   covariance is propagated from the pixel noise. The TCP/SMR is the pose translation.
4. Quality and refusal: too few frames, markers or cameras, or a reprojection error
   inconsistent with the pixel noise refuse the measurement with the reason."""
from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np

from drivers.mvs.camera import RigModel
from drivers.mvs.cluster import fit_points, identify, refine_pose
from drivers.mvs.detect import detect_full_frame, detect_in_rois_multi
from drivers.mvs.triangulate import CameraStack, epipolar_candidates, triangulate


@dataclass(frozen=True)
class MvsMeasurement:
    """One measurement of the rig (MVS frame, metres): ``tcp`` (3,) m, ``cov`` (3, 3) m^2
    propagated from the pixel noise, ``R`` (3, 3) tool orientation, ``pose_cov`` (6, 6) [rotation
    vector rad, translation m], ``quality`` (markers_used, cameras_used, reproj_rms_px, ...) and
    ``refused`` (the reason, when no point is reported).
    """

    tcp: np.ndarray | None  # (3,) TCP/SMR point
    cov: np.ndarray | None  # (3,3) m^2 propagated from the pixel noise
    R: np.ndarray | None = None  # (3,3) tool orientation
    pose_cov: np.ndarray | None = None  # (6,6) [rotation vector rad, translation m]
    quality: Mapping[str, Any] = field(default_factory=dict)
    refused: str | None = None

    @property
    def ok(self) -> bool:
        """True when a TCP was measured (not refused)."""
        return self.refused is None and self.tcp is not None


def _distort(stack_k: np.ndarray, stack_d: np.ndarray, xn: np.ndarray) -> np.ndarray:
    """OpenCV distortion model, vectorised: normalised (M,C,2) -> image pixels (M,C,2)."""
    k1, k2, p1, p2, k3 = (stack_d[:, i] for i in range(5))
    x, y = xn[..., 0], xn[..., 1]
    r2 = x * x + y * y
    rad = 1 + k1 * r2 + k2 * r2 ** 2 + k3 * r2 ** 3
    xd = x * rad + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * rad + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    return np.stack([xd * stack_k[:, 0, 0] + stack_k[:, 0, 2], yd * stack_k[:, 1, 1] + stack_k[:, 1, 2]], axis=-1)


def _undistort(stack_k: np.ndarray, stack_d: np.ndarray, uv: np.ndarray, iters: int = 8) -> np.ndarray:
    """Inverse of `_distort` by fixed-point iteration (as cv2.undistortPoints): pixels -> ideal pixels."""
    k1, k2, p1, p2, k3 = (stack_d[:, i] for i in range(5))
    f = np.stack([stack_k[:, 0, 0], stack_k[:, 1, 1]], axis=-1)
    c = stack_k[:, :2, 2]
    xd = (uv - c) / f
    x, y = xd[..., 0].copy(), xd[..., 1].copy()
    for _ in range(iters):
        r2 = x * x + y * y
        rad = 1 + k1 * r2 + k2 * r2 ** 2 + k3 * r2 ** 3
        dx = 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
        dy = p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
        x = (xd[..., 0] - dx) / rad
        y = (xd[..., 1] - dy) / rad
    return np.stack([x, y], axis=-1) * f + c


class MarkerTracker:
    """Measures the TCP from the rig's images. Stateless between calls; thread-compatible."""

    def __init__(self, model: RigModel):
        self.model = model
        self.p = model.params
        self.stack = CameraStack(model.cameras)
        self.K = np.stack([c.K for c in model.cameras])
        self.D = np.stack([np.r_[c.dist, np.zeros(5)][:5] for c in model.cameras])

    # ------------------------------------------------------------------ correspondence
    def observe_predicted(self, images: Sequence[np.ndarray | None], R: np.ndarray, t: np.ndarray):
        """ROI centroids of every marker in every camera around the predicted pose.

        Views where two markers are predicted closer than two centroid windows are not used.

        Parameters
        ----------
        images : sequence of ndarray or None
            One 8-bit image or None per camera, in rig order.
        R : ndarray
            (3, 3), the tool's predicted orientation in the MVS frame.
        t : ndarray
            (3,) m, the tool's (TCP's) predicted position in the MVS frame.

        Returns
        -------
        uv : ndarray
            (M, C, 2) ideal px.
        sigma : ndarray
            (M, C) px (centroid repeatability and image noise combined).
        mask : ndarray
            (M, C) bool, the views found.
        """
        M, C = len(self.model.markers), len(self.stack)
        X = self.model.markers @ np.asarray(R).T + np.asarray(t)
        _, Xc = self.stack.project(X)
        pred = _distort(self.K, self.D, Xc[..., :2] / Xc[..., 2:3])  # (M,C,2)
        pred = np.where((Xc[..., 2:3] > 0), pred, np.nan)
        uv, s, mask = detect_in_rois_multi(images, pred, self.p.roi_half_px, self.p.window_half_px)
        # Markers predicted closer than two centroid windows in a view would bias each other's
        # centroid (or merge): that view of both is not used.
        d = np.linalg.norm(pred[:, None] - pred[None], axis=3)  # (M,M,C)
        d[np.arange(M), np.arange(M)] = np.inf
        mask &= ~(np.nanmin(np.where(np.isnan(d), np.inf, d), axis=1) < 2 * self.p.window_half_px)
        s0 = self.p.centroid_sigma_px
        sig = np.sqrt(s0 * s0 + s * s)
        for c in range(C):
            if mask[:, c].any():
                uv[:, c] = cv2.undistortPoints(uv[:, c].reshape(-1, 1, 2), self.K[c], self.D[c],
                                               P=self.K[c]).reshape(-1, 2)
        return uv, sig, mask

    def initial_pose_epipolar(self, images: Sequence[np.ndarray | None]):
        """Pose from unlabeled full-frame blobs (no prediction).

        Epipolar matching, triangulation, identification by the cluster's distances.

        Parameters
        ----------
        images : sequence of ndarray or None
            One 8-bit image or None per camera, in rig order.

        Returns
        -------
        tuple or None
            (R (3, 3), t (3,) m) of the tool in the MVS frame, or None when the cluster is not found.
        """
        blobs, sigs = [], []
        for c, img in enumerate(images):
            if img is None:
                blobs.append(np.zeros((0, 2)))
                sigs.append(np.zeros(0))
                continue
            u, s, ok = detect_full_frame(img, self.p.window_half_px)
            u = u[ok]
            ideal = _undistort(self.K[c:c + 1], self.D[c:c + 1], u[:, None, :])[:, 0] if len(u) else u
            blobs.append(ideal)
            sigs.append(np.sqrt(self.p.centroid_sigma_px ** 2 + s[ok] ** 2))
        X, _, _, _ = epipolar_candidates(self.stack, blobs, sigs, tol_px=1.0, min_support=3)
        if len(X) < 3:
            return None
        res = identify(self.model.markers, X, tol=self.p.cluster_tol_m)
        if res is None:
            return None
        return res[0], res[1]

    # ------------------------------------------------------------------ measurement
    def measure(self, images: Sequence[np.ndarray | None],
                predicted_pose: tuple[np.ndarray, np.ndarray] | None = None) -> MvsMeasurement:
        """Measure the TCP from one frame set.

        Parameters
        ----------
        images : sequence of ndarray or None
            One 8-bit image or None per camera, in rig order.
        predicted_pose : tuple of ndarray or None
            (R (3, 3), t (3,) m) of the tool in the MVS frame (the twin's prediction); None searches
            the full frames.

        Returns
        -------
        MvsMeasurement
            Refused, with the reason, when there are too few frames, markers or cameras or the
            reprojection is inconsistent with the pixel noise.
        """
        if len(images) != len(self.stack):
            return self._refuse(f"expected {len(self.stack)} images, got {len(images)}", {})
        n_frames = sum(img is not None for img in images)
        if n_frames < self.p.min_cameras:
            return self._refuse(f"only {n_frames} cameras delivered frames (needs {self.p.min_cameras})",
                                {"cameras_delivering": n_frames})
        first = None
        if predicted_pose is not None:
            first = self.measure_observations(*self.observe_predicted(images, *predicted_pose))
            if first.ok or "markers" not in (first.refused or ""):
                return first
            path = "roi->epipolar"  # the prediction may be off: look for the cluster everywhere
        else:
            path = "epipolar"
        init = self.initial_pose_epipolar(images)
        if init is None:
            reason = "no marker cluster found by epipolar matching"
            if first is not None:
                return self._refuse(f"{first.refused}; {reason}", {**first.quality, "path": path})
            return self._refuse(reason, {"path": path})
        meas = self.measure_observations(*self.observe_predicted(images, *init))
        q = dict(meas.quality)
        q["path"] = path
        if not meas.ok and first is not None:
            return MvsMeasurement(None, None, quality=q, refused=f"{first.refused}; then: {meas.refused}")
        return MvsMeasurement(meas.tcp, meas.cov, meas.R, meas.pose_cov, q, meas.refused)

    def _refuse(self, reason: str, quality: Mapping[str, Any]) -> MvsMeasurement:
        q = {"markers_used": 0, "cameras_used": 0, "reproj_rms_px": float("nan")}
        q.update(quality)
        return MvsMeasurement(None, None, quality=q, refused=reason)

    def measure_observations(self, uv: np.ndarray, sig: np.ndarray, mask: np.ndarray) -> MvsMeasurement:
        """Triangulate, fit the cluster and propagate the covariance from labelled observations.

        Parameters
        ----------
        uv : ndarray
            (M, C, 2) ideal px.
        sig : ndarray
            (M, C) px.
        mask : ndarray
            (M, C) bool, the views found.

        Returns
        -------
        MvsMeasurement
        """
        p, model = self.p, self.model.markers
        X, cov, mask, ok = triangulate(self.stack, uv, sig, mask, gate=p.gate_sigma, min_views=p.min_views)
        q: dict[str, Any] = {"markers_seen": int(ok.sum())}
        if ok.sum() < p.min_markers:
            return self._refuse(f"only {int(ok.sum())} markers seen by >= {p.min_views} cameras"
                                f" (needs {p.min_markers})", q)
        # Rigid fit with per-marker outlier rejection (Mahalanobis distance to the fitted model).
        R, t, idx, refused = fit_points(model, X, cov, np.flatnonzero(ok), p.gate_sigma, p.min_markers)
        if refused:
            return self._refuse(refused, q)
        keep = np.zeros(len(model), bool)
        keep[idx] = True
        mk = mask & keep[:, None]
        # Pose on the pixels; drop views failing the gate once, then refit.
        for _ in range(2):
            R, t, pcov, r = refine_pose(self.stack, model, R, t, uv, sig, mk)
            rn = np.linalg.norm(r, axis=2)
            bad = mk & (rn > p.gate_sigma)
            if not bad.any():
                break
            mk = mk & ~bad
        used_markers = int((mk.sum(1) >= p.min_views).sum())
        used_cams = int(mk.any(0).sum())
        n_obs = int(mk.sum())
        chi2_rms = float(np.sqrt((r[mk] ** 2).sum() / max(2 * n_obs - 6, 1)))
        px_res = r * np.where(mk, sig, 0.0)[..., None]
        q.update({"markers_used": used_markers, "cameras_used": used_cams, "views_used": n_obs,
                  "reproj_rms_px": float(np.sqrt((px_res[mk] ** 2).mean())) if n_obs else float("nan"),
                  "chi2_rms": chi2_rms})
        if used_markers < p.min_markers:
            return self._refuse(f"only {used_markers} markers left after outlier rejection"
                                f" (needs {p.min_markers})", q)
        if used_cams < p.min_cameras:
            return self._refuse(f"only {used_cams} cameras see the cluster (needs {p.min_cameras})", q)
        if rn[mk].max() > p.gate_sigma or chi2_rms > p.chi2_rms_max:
            return self._refuse(f"reprojection inconsistent with the pixel noise"
                                f" (normalised rms {chi2_rms:.2f} > {p.chi2_rms_max})", q)
        return MvsMeasurement(t.copy(), pcov[3:, 3:].copy(), R, pcov, q, None)
