"""The calibrated camera model the rig knows, and the rig model the processing runs on.

A `Camera` maps a point X (MVS frame, m) to x_cam = R X + t and to pixels through K and the
OpenCV distortion (k1, k2, p1, p2, k3). Processing works in *ideal* (undistorted) pixel
coordinates: detected centroids are undistorted once, after which projection is the plain
pinhole model and is cheap to evaluate and differentiate.
"""
from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np

from dt_kernel.errors import ConfigError


@dataclass(frozen=True)
class Camera:
    name: str
    K: np.ndarray  # (3,3)
    dist: np.ndarray  # (5,)
    R: np.ndarray  # (3,3) MVS -> camera
    t: np.ndarray  # (3,)
    size: tuple[int, int]  # (width, height) px

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> Camera:
        try:
            K = np.asarray(d["K"], float).reshape(3, 3)
            R = np.asarray(d["R"], float).reshape(3, 3)
            t = np.asarray(d["t"], float).reshape(3)
            dist = np.asarray(d.get("dist", np.zeros(5)), float).reshape(-1)
            size = tuple(int(v) for v in d["size"])
        except (KeyError, ValueError, TypeError) as exc:
            raise ConfigError("<camera calibration>", "camera", dict(d).get("name"),
                              "K (3x3), R (3x3), t (3), dist, size") from exc
        if abs(np.linalg.det(R) - 1.0) > 1e-6:
            raise ConfigError("<camera calibration>", "R", R.tolist(), "a rotation matrix")
        return cls(str(d.get("name", "cam")), K, dist, R, t, size)  # type: ignore[arg-type]

    @property
    def center(self) -> np.ndarray:
        return -self.R.T @ self.t

    def project_ideal(self, X: np.ndarray) -> np.ndarray:
        """Ideal (undistorted) pixel coordinates (n,2) of points X (n,3)."""
        Xc = np.atleast_2d(X) @ self.R.T + self.t
        return (Xc[:, :2] / Xc[:, 2:3]) * np.diag(self.K)[:2] + self.K[:2, 2]

    def project(self, X: np.ndarray) -> np.ndarray:
        """Distorted (image) pixel coordinates (n,2) of points X (n,3)."""
        X = np.atleast_2d(np.asarray(X, float))
        uv = cv2.projectPoints(X.reshape(-1, 1, 3), cv2.Rodrigues(self.R)[0], self.t, self.K, self.dist)[0]
        return uv.reshape(-1, 2)

    def undistort(self, uv: np.ndarray) -> np.ndarray:
        """Image pixels (n,2) -> ideal pixels (n,2) (OpenCV iterative undistortion)."""
        uv = np.asarray(uv, np.float64).reshape(-1, 1, 2)
        if len(uv) == 0:
            return np.zeros((0, 2))
        return cv2.undistortPoints(uv, self.K, self.dist, P=self.K).reshape(-1, 2)


@dataclass(frozen=True)
class ProcessingParams:
    """Processing settings (configs/cameras.yaml `processing`, read with this light schema)."""

    centroid_sigma_px: float = 0.065  # calibrated centroid repeatability (1 sigma)
    roi_half_px: int = 12  # ROI half size around a predicted marker
    window_half_px: int = 8  # centroid window half size around the blob peak
    min_markers: int = 3
    min_cameras: int = 3
    min_views: int = 2  # views per marker for triangulation
    gate_sigma: float = 5.0  # per-observation outlier gate (normalised residual)
    chi2_rms_max: float = 2.0  # refuse when the normalised reprojection RMS exceeds this
    cluster_tol_m: float = 1.0e-3  # marker-to-model distance tolerance for identification

    @classmethod
    def from_mapping(cls, m: Mapping[str, Any] | None, source: str = "<processing>") -> ProcessingParams:
        m = dict(m or {})
        known = set(cls.__dataclass_fields__)
        for k, v in m.items():
            if k not in known:
                raise ConfigError(source, f"processing.{k}", v, "known keys: " + ", ".join(sorted(known)))
        try:
            p = cls(**{k: type(getattr(cls, k))(v) for k, v in m.items()})
        except (TypeError, ValueError) as exc:
            raise ConfigError(source, "processing", m, "numbers") from exc
        if p.centroid_sigma_px <= 0 or p.min_markers < 3 or p.min_cameras < 2 or p.min_views < 2:
            raise ConfigError(source, "processing", m,
                              "centroid_sigma_px > 0, min_markers >= 3, min_cameras >= 2, min_views >= 2")
        return p


@dataclass(frozen=True)
class RigModel:
    """What the processing knows: the calibrated cameras (MVS frame), the marker cluster
    (tool/TCP frame, origin = TCP/SMR) and the processing settings."""

    cameras: tuple[Camera, ...]
    markers: np.ndarray  # (m,3) m, tool frame
    marker_diameter_m: float = 0.014
    params: ProcessingParams = field(default_factory=ProcessingParams)

    @classmethod
    def build(cls, cameras: Sequence[Mapping[str, Any] | Camera], markers, marker_diameter_m: float = 0.014,
              processing: Mapping[str, Any] | ProcessingParams | None = None) -> RigModel:
        cams = tuple(c if isinstance(c, Camera) else Camera.from_dict(c) for c in cameras)
        mk = np.asarray(markers, float).reshape(-1, 3)
        if len(mk) < 3:
            raise ConfigError("<rig model>", "markers", mk.tolist(), "at least 3 markers")
        params = processing if isinstance(processing, ProcessingParams) else ProcessingParams.from_mapping(processing)
        return cls(cams, mk, float(marker_diameter_m), params)
