"""What the emulated NatNet server sees: the simulated rig's marker cluster, triangulated.

Motive reconstructs each marker from its centroids in the calibrated cameras. This source does
the same on the simulated rig (sim.camera_rig, configs/cameras.yaml) without rendering images:
each marker of the tool's cluster is projected into every calibrated camera (MVS frame), the
rig's centroid noise (render.jitter_px and the calibrated processing.centroid_sigma_px, one
sigma, per axis) is added to the pixels, and the marker is triangulated with the image
pipeline's N-view triangulation (drivers.mvs.triangulate). A marker seen by fewer than two
cameras is occluded. Visibility follows the rig's render settings (occluded markers,
occlusion and drop-out probabilities, dropped cameras) and an optional occluder (the arm's
links). Positions are in the MVS frame, with the rig's scale error, as SimCameraRig reports.
"""
from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from drivers.mvs.camera import Camera
from drivers.mvs.triangulate import CameraStack, triangulate
from sim.camera_rig import DEFAULT_CONFIG, Occluder, RigConfig, load_rig_config, rig_cameras_mvs, rig_cameras_world

PoseFn = Callable[[], tuple[np.ndarray, np.ndarray]]


@dataclass(frozen=True)
class MarkerObservation:
    """One capture: the cluster's markers in the MVS frame (NaN where occluded)."""

    X: np.ndarray  # (M,3) m, triangulated markers; NaN rows where occluded
    seen: np.ndarray  # (M,) bool, reconstructed from >= 2 cameras
    truth: np.ndarray  # (M,3) m, true marker positions (MVS frame), for scoring only
    tcp_truth: np.ndarray  # (3,) m, true TCP (MVS frame), for scoring only


class SimRigMarkers:
    """Triangulated markers of the simulated rig for the actual tool pose.

    Parameters
    ----------
    tool_pose : callable
        () -> (R (3, 3), p (3,) m): the actual tool orientation and TCP, world frame.
    config : str or RigConfig
        configs/cameras.yaml by default, or a validated RigConfig.
    seed : int
        Seeds every draw (noise, random occlusion); the same seed and poses give the same markers.
    occluded : callable or None
        occluded(cam_center (3,), points (n, 3)) -> (n,) bool, world frame.
    """

    def __init__(self, tool_pose: PoseFn, config: str | RigConfig = str(DEFAULT_CONFIG), seed: int = 0,
                 occluded: Occluder | None = None):
        self.cfg = config if isinstance(config, RigConfig) else load_rig_config(config)
        self._pose, self._occluded = tool_pose, occluded
        self._rng = np.random.default_rng([seed, 1511])
        self.markers = np.array(self.cfg.markers.positions_m, float)  # tool frame, origin = TCP
        self._world_cams = rig_cameras_world(self.cfg)
        self._stack = CameraStack([Camera.from_dict(c.as_dict()) for c in rig_cameras_mvs(self.cfg)])
        Rm, tm = self.cfg.rig_pose.matrix()
        self._Rm, self._tm, self._s = Rm, tm, self.cfg.scale_error
        r = self.cfg.render
        self.sigma_px = float(np.hypot(r.jitter_px, self.cfg.processing.centroid_sigma_px))

    def to_mvs(self, x_world: np.ndarray) -> np.ndarray:
        """World points in the rig's frame with its scale error: (1 + s) Rm^T (x_world - tm).

        Parameters
        ----------
        x_world : ndarray
            (..., 3) m.

        Returns
        -------
        ndarray
            (..., 3) m, MVS frame.
        """
        return (1.0 + self._s) * (np.asarray(x_world, float) - self._tm) @ self._Rm

    def capture(self, hidden: Sequence[int] = ()) -> MarkerObservation:
        """Triangulate the cluster once at the tool's current pose.

        Parameters
        ----------
        hidden : sequence of int
            Marker indices occluded from every camera (besides the render settings').

        Returns
        -------
        MarkerObservation
        """
        R, p = self._pose()
        R, p = np.asarray(R, float), np.asarray(p, float)
        Xw = p + self.markers @ R.T
        Xm = self.to_mvs(Xw)
        M, C = len(Xm), len(self._stack)
        uv, Xc = self._stack.project(Xm)  # ideal pixels (M,C,2), camera coordinates
        r, rng = self.cfg.render, self._rng
        W, H = self.cfg.image.width, self.cfg.image.height
        vis = (Xc[..., 2] > 0.05) & (uv[..., 0] > -0.5) & (uv[..., 0] < W - 0.5)
        vis &= (uv[..., 1] > -0.5) & (uv[..., 1] < H - 0.5)
        gone = [i for i in (*r.occluded_markers, *hidden) if 0 <= i < M]
        vis[gone] = False
        if r.occlusion_probability > 0:
            vis &= rng.random((M, C)) >= r.occlusion_probability
        for c, cam in enumerate(self._world_cams):
            if cam.name in r.dropped_cameras or rng.random() < r.dropout_probability:
                vis[:, c] = False
            elif self._occluded is not None:
                vis[:, c] &= ~np.asarray(self._occluded(cam.center, Xw), bool)
        noisy = uv + rng.normal(0.0, self.sigma_px, uv.shape)
        sig = np.full((M, C), self.sigma_px)
        X, _, _, ok = triangulate(self._stack, noisy, sig, vis)
        X[~ok] = np.nan
        return MarkerObservation(X, ok, Xm, self.to_mvs(p))
