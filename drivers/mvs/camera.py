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
    """A calibrated camera: ``K`` (3, 3) px, ``dist`` (k1, k2, p1, p2, k3), ``R`` (3, 3) and ``t`` (3,) m
    from the MVS frame to the camera (x_cam = R X + t), ``size`` (width, height) px.
    """
    name: str
    K: np.ndarray  # (3,3)
    dist: np.ndarray  # (5,)
    R: np.ndarray  # (3,3) MVS -> camera
    t: np.ndarray  # (3,)
    size: tuple[int, int]  # (width, height) px

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> Camera:
        """A camera from its calibration as plain data (``K``, ``R``, ``t``, ``size``, optional ``dist``, ``name``).

        Parameters
        ----------
        d : Mapping
            ``K`` 3x3, ``R`` 3x3 (a rotation), ``t`` (3,) m, ``size`` (width, height) px, ``dist`` (5,)
            (zeros when absent), ``name`` (``cam`` when absent).

        Returns
        -------
        Camera

        Raises
        ------
        ConfigError
            When a key is missing or malformed, or ``R`` is not a rotation (det != 1).
        """
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
        """The camera's centre in the MVS frame (m): -R^T t."""
        return -self.R.T @ self.t

    def project_ideal(self, X: np.ndarray) -> np.ndarray:
        """Ideal (undistorted) pixel coordinates of points: the plain pinhole model.

        Parameters
        ----------
        X : ndarray
            (n, 3) or (3,) m, MVS frame.

        Returns
        -------
        ndarray
            (n, 2) px.
        """
        Xc = np.atleast_2d(X) @ self.R.T + self.t
        return (Xc[:, :2] / Xc[:, 2:3]) * np.diag(self.K)[:2] + self.K[:2, 2]

    def project(self, X: np.ndarray) -> np.ndarray:
        """Distorted (image) pixel coordinates of points (OpenCV ``projectPoints``).

        Parameters
        ----------
        X : ndarray
            (n, 3) or (3,) m, MVS frame.

        Returns
        -------
        ndarray
            (n, 2) px.
        """
        X = np.atleast_2d(np.asarray(X, float))
        uv = cv2.projectPoints(X.reshape(-1, 1, 3), cv2.Rodrigues(self.R)[0], self.t, self.K, self.dist)[0]
        return uv.reshape(-1, 2)

    def undistort(self, uv: np.ndarray) -> np.ndarray:
        """Image pixels to ideal pixels (OpenCV iterative undistortion).

        Parameters
        ----------
        uv : ndarray
            (n, 2) px, image coordinates.

        Returns
        -------
        ndarray
            (n, 2) px, ideal coordinates ((0, 2) when ``uv`` is empty).
        """
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
        """The settings from a mapping; absent keys keep their defaults.

        Parameters
        ----------
        m : Mapping or None
            The ``processing`` section; values are converted to each default's type.
        source : str
            Names the config in errors.

        Returns
        -------
        ProcessingParams

        Raises
        ------
        ConfigError
            For an unknown key, a value that is not a number, or when not centroid_sigma_px > 0,
            min_markers >= 3, min_cameras >= 2 and min_views >= 2.
        """
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
        """A rig model from plain data.

        Parameters
        ----------
        cameras : sequence of Mapping or Camera
            The calibrated cameras; mappings go through ``Camera.from_dict``.
        markers : array_like
            (m, 3) m, the marker cluster in the tool frame (origin = TCP/SMR); at least 3.
        marker_diameter_m : float
            m.
        processing : Mapping or ProcessingParams or None
            The processing settings (defaults when None).

        Returns
        -------
        RigModel

        Raises
        ------
        ConfigError
            For a malformed camera, fewer than 3 markers or bad processing settings.
        """
        cams = tuple(c if isinstance(c, Camera) else Camera.from_dict(c) for c in cameras)
        mk = np.asarray(markers, float).reshape(-1, 3)
        if len(mk) < 3:
            raise ConfigError("<rig model>", "markers", mk.tolist(), "at least 3 markers")
        params = processing if isinstance(processing, ProcessingParams) else ProcessingParams.from_mapping(processing)
        return cls(cams, mk, float(marker_diameter_m), params)
