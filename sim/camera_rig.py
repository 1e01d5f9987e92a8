"""Simulated multi-camera marker rig: pinhole cameras, projection and synthetic 8-bit images.

The truth side of the MVS. A `RigConfig` (configs/cameras.yaml) places eight calibrated pinhole
cameras (OpenCV model: K, distortion k1 k2 p1 p2 k3) in the world (robot base frame, metres) and
describes the five-marker cluster on the gripper in the tool/TCP frame. `SimCameraImages` renders,
for a tool pose, each camera's image: bright, blurred, pixel-integrated Gaussian marker blobs on
a dark noisy background, with seeded, switchable faults (occlusions, spurious reflections,
dropped cameras, exposure noise). `SimCameraImages.calibration()` gives what a calibrated rig
knows: each camera's intrinsics and its extrinsics in the rig's own (MVS) frame, which carries a
small systematic scale error with respect to the world.

This module knows nothing of the processing side (drivers.mvs)."""
from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np
from pydantic import Field, model_validator
from scipy.special import ndtr

from dt_kernel.config import Frozen, load_yaml, validate
from sim.instruments import Pose

Occluder = Callable[[np.ndarray, np.ndarray], np.ndarray]
"""occluded(cam_center (3,) world m, points (n,3) world m) -> bool (n,): True where hidden."""


# ----------------------------------------------------------------------------- config schema
class Intrinsics(Frozen):
    """A camera's intrinsics: focal lengths ``fx``, ``fy`` and principal point ``cx``, ``cy`` (px),
    distortion (k1, k2, p1, p2, k3)."""
    fx: float = Field(gt=0)
    fy: float = Field(gt=0)
    cx: float
    cy: float
    dist: tuple[float, float, float, float, float] = (0.0, 0.0, 0.0, 0.0, 0.0)

    def K(self) -> np.ndarray:
        """The camera matrix.

        Returns
        -------
        ndarray
            (3, 3) px.
        """
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])


class CameraConfig(Frozen):
    """One camera's placement: ``position_m`` and ``look_at_m`` (m, world), ``roll_deg`` about the
    optical axis, and its own intrinsics (None: the rig's shared ones).
    """
    name: str
    position_m: tuple[float, float, float]
    look_at_m: tuple[float, float, float]
    roll_deg: float = 0.0
    intrinsics: Intrinsics | None = None  # None: the rig's shared intrinsics


class ImageConfig(Frozen):
    """The image size (px)."""
    width: int = Field(2048, gt=0)
    height: int = Field(1088, gt=0)


class MarkerConfig(Frozen):
    """The marker cluster: ``diameter_m`` (m) and ``positions_m`` (m, tool/TCP frame; at least 3)."""
    diameter_m: float = Field(0.014, gt=0)
    positions_m: tuple[tuple[float, float, float], ...]

    @model_validator(mode="after")
    def _enough(self):
        if len(self.positions_m) < 3:
            raise ValueError("needs at least 3 markers for a rigid fit")
        return self


class RenderConfig(Frozen):
    """Rendering and its faults: background, read noise and peak (digital numbers), blur and jitter
    (px), relative exposure noise, spurious blobs per image (and the share near a marker),
    occlusion and dropout probabilities, markers always occluded (indices), cameras always
    dropped (names).
    """
    background_dn: float = Field(6.0, ge=0, le=255)
    read_noise_dn: float = Field(1.5, ge=0)
    peak_dn: float = Field(190.0, gt=0, le=255)
    blur_px: float = Field(0.8, ge=0)
    jitter_px: float = Field(0.06, ge=0)
    exposure_noise: float = Field(0.05, ge=0, le=0.5)
    spurious_per_image: int = Field(0, ge=0)
    spurious_near_marker: float = Field(0.34, ge=0, le=1)
    occlusion_probability: float = Field(0.0, ge=0, le=1)
    occluded_markers: tuple[int, ...] = ()
    dropout_probability: float = Field(0.0, ge=0, le=1)
    dropped_cameras: tuple[str, ...] = ()


class ProcessingConfig(Frozen):
    """Settings the processing side reads (it re-validates them with its own light schema)."""

    centroid_sigma_px: float = Field(0.065, gt=0)
    roi_half_px: int = Field(12, ge=4)
    min_markers: int = Field(3, ge=3)
    min_cameras: int = Field(3, ge=2)


class RigConfig(Frozen):
    """The whole rig (configs/cameras.yaml)."""

    image: ImageConfig = ImageConfig()
    intrinsics: Intrinsics
    cameras: tuple[CameraConfig, ...]
    rig_pose: Pose
    scale_error: float = Field(1.0e-4, ge=-0.01, le=0.01)
    markers: MarkerConfig
    render: RenderConfig = RenderConfig()
    processing: ProcessingConfig = ProcessingConfig()

    @model_validator(mode="after")
    def _names(self):
        names = [c.name for c in self.cameras]
        if len(set(names)) != len(names):
            raise ValueError(f"camera names must be unique, got {names}")
        for n in self.render.dropped_cameras:
            if n not in names:
                raise ValueError(f"dropped camera {n!r} is not one of {names}")
        for i in self.render.occluded_markers:
            if not 0 <= i < len(self.markers.positions_m):
                raise ValueError(f"occluded marker {i} out of range")
        return self


DEFAULT_CONFIG = Path(__file__).resolve().parent.parent / "configs" / "cameras.yaml"


def load_rig_config(path: str | Path = DEFAULT_CONFIG) -> RigConfig:
    """Read and validate a rig config.

    Parameters
    ----------
    path : str or Path
        configs/cameras.yaml by default.

    Returns
    -------
    RigConfig

    Raises
    ------
    ConfigError
        When the file cannot be read or does not validate.
    """
    return load_yaml(path, RigConfig)


def validate_rig(data: dict, source: str = "<config>") -> RigConfig:
    """Validate a plain mapping into a RigConfig.

    Parameters
    ----------
    data : dict
    source : str
        Names the config in errors.

    Returns
    -------
    RigConfig

    Raises
    ------
    ConfigError
        Naming the key, value and what is allowed.
    """
    return validate(RigConfig, data, source)


def with_render(cfg: RigConfig, **changes) -> RigConfig:
    """A copy of ``cfg`` with render settings changed (validated), e.g. spurious_per_image=3.

    Parameters
    ----------
    cfg : RigConfig
    **changes
        RenderConfig fields and their new values.

    Returns
    -------
    RigConfig

    Raises
    ------
    ConfigError
        When a change does not validate.
    """
    data = cfg.model_dump()
    data["render"].update(changes)
    return validate_rig(data, "<with_render>")


# ----------------------------------------------------------------------------- camera model
class PinholeCamera:
    """One calibrated camera: x_cam = R @ x + t (x in the frame the camera is expressed in)."""

    def __init__(self, name: str, K: np.ndarray, dist: np.ndarray, R: np.ndarray, t: np.ndarray,
                 size: tuple[int, int]):
        self.name, self.K, self.dist = name, np.asarray(K, float), np.asarray(dist, float)
        self.R, self.t = np.asarray(R, float), np.asarray(t, float)
        self.size = size  # (width, height)
        self.rvec = cv2.Rodrigues(self.R)[0]

    @property
    def center(self) -> np.ndarray:
        """The camera's centre (m) in the frame its extrinsics are expressed in: -R^T t."""
        return -self.R.T @ self.t

    def project(self, X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Distorted pixel coordinates of points and their depth.

        Parameters
        ----------
        X : ndarray
            (n, 3) or (3,) m, in the camera's reference frame.

        Returns
        -------
        uv : ndarray
            (n, 2) px.
        depth : ndarray
            (n,) m, along the optical axis.
        """
        X = np.atleast_2d(np.asarray(X, float))
        uv = cv2.projectPoints(X.reshape(-1, 1, 3), self.rvec, self.t, self.K, self.dist)[0]
        return uv.reshape(-1, 2), (X @ self.R.T + self.t)[:, 2]

    def as_dict(self) -> dict:
        """Plain-data form (lists) for handing the calibration across layers."""
        return {"name": self.name, "K": self.K.tolist(), "dist": self.dist.tolist(),
                "R": self.R.tolist(), "t": self.t.tolist(), "size": list(self.size)}


def look_at(position, target, roll_deg: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """World->camera (R, t) for a camera at ``position`` looking at ``target``, world z up.

    Camera axes (OpenCV): z forward along the optical axis, x right, y down in the image.

    Parameters
    ----------
    position : array_like
        (3,) m.
    target : array_like
        (3,) m.
    roll_deg : float
        Rotation about the optical axis (deg).

    Returns
    -------
    R : ndarray
        (3, 3).
    t : ndarray
        (3,) m.
    """
    c, tgt = np.asarray(position, float), np.asarray(target, float)
    z = tgt - c
    z /= np.linalg.norm(z)
    x = np.cross(z, [0.0, 0.0, 1.0])
    if np.linalg.norm(x) < 1e-9:  # looking straight down/up
        x = np.array([1.0, 0.0, 0.0])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    R = np.vstack([x, y, z])
    a = np.radians(roll_deg)
    Rz = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])
    R = Rz @ R
    return R, -R @ c


def rig_cameras_world(cfg: RigConfig) -> list[PinholeCamera]:
    """The cameras with extrinsics in the world frame (the simulator's truth).

    Parameters
    ----------
    cfg : RigConfig

    Returns
    -------
    list of PinholeCamera
    """
    cams = []
    for c in cfg.cameras:
        intr = c.intrinsics or cfg.intrinsics
        R, t = look_at(c.position_m, c.look_at_m, c.roll_deg)
        cams.append(PinholeCamera(c.name, intr.K(), np.array(intr.dist), R, t,
                                  (cfg.image.width, cfg.image.height)))
    return cams


def world_to_mvs(cfg: RigConfig) -> tuple[np.ndarray, np.ndarray, float]:
    """The rig frame: x_mvs = (1 + s) R^T (x_world - t).

    Parameters
    ----------
    cfg : RigConfig

    Returns
    -------
    R : ndarray
        (3, 3).
    t : ndarray
        (3,) m.
    s : float
        The scale error.
    """
    R, t = cfg.rig_pose.matrix()
    return R, t, cfg.scale_error


def rig_cameras_mvs(cfg: RigConfig) -> list[PinholeCamera]:
    """The cameras as the calibrated rig knows them: extrinsics in the MVS frame.

    With x_w = R_m x_mvs / (1+s) + t_m, x_cam = R_c x_w + t_c; scaling x_cam by (1+s) leaves
    the projection unchanged, so R' = R_c R_m and t' = (1+s)(R_c t_m + t_c).

    Parameters
    ----------
    cfg : RigConfig

    Returns
    -------
    list of PinholeCamera
    """
    Rm, tm, s = world_to_mvs(cfg)
    out = []
    for c in rig_cameras_world(cfg):
        out.append(PinholeCamera(c.name, c.K, c.dist, c.R @ Rm, (1 + s) * (c.R @ tm + c.t), c.size))
    return out


# ----------------------------------------------------------------------------- rendering
def _render_blobs(img: np.ndarray, uv: np.ndarray, sigma: np.ndarray, peak: np.ndarray,
                  rng: np.random.Generator) -> None:
    """Add pixel-integrated Gaussian blobs (centres uv (n,2) px, pixel centres at integers) in place.

    Pixel (i, j) integrates the Gaussian over [j-0.5, j+0.5] x [i-0.5, i+0.5], so the intensity
    centroid of a blob is its centre to well below 0.01 px (sub-pixel accurate ground truth).
    Photon (shot) noise is added to the blob signal.
    """
    H, W = img.shape
    for (u, v), s, a in zip(uv, sigma, peak):
        r = int(np.ceil(4.0 * s)) + 1
        u0, v0 = int(round(u)), int(round(v))
        x0, x1, y0, y1 = max(u0 - r, 0), min(u0 + r + 1, W), max(v0 - r, 0), min(v0 + r + 1, H)
        if x0 >= x1 or y0 >= y1:
            continue
        xs, ys = np.arange(x0, x1), np.arange(y0, y1)
        gx = ndtr((xs + 0.5 - u) / s) - ndtr((xs - 0.5 - u) / s)
        gy = ndtr((ys + 0.5 - v) / s) - ndtr((ys - 0.5 - v) / s)
        # Amplitude so the peak pixel of a centred blob is about `a`.
        amp = a / (ndtr(0.5 / s) - ndtr(-0.5 / s)) ** 2
        sig = amp * np.outer(gy, gx)
        sig = sig + rng.normal(0.0, 1.0, sig.shape) * np.sqrt(np.maximum(sig, 0.0) * 0.05)
        win = img[y0:y1, x0:x1].astype(np.float32) + sig
        img[y0:y1, x0:x1] = np.clip(np.rint(win), 0, 255).astype(np.uint8)


class SimCameraImages:
    """Renders the rig's eight 8-bit images for a tool pose (truth in the world frame).

    `render(R, p)` -> (images, info): images is a list (one per camera) of uint8 (H, W) arrays,
    or None for a camera that delivered no frame; info holds the truth used (marker pixel
    centres, which markers were visible where) for scoring. Every draw uses the instance's own
    generator seeded with `seed`; the same seed and pose sequence gives the same images.
    """

    NOISE_PAD = 64

    def __init__(self, cfg: RigConfig, seed: int = 0, occluded: Occluder | None = None):
        self.cfg = cfg
        self.cams = rig_cameras_world(cfg)
        self.markers = np.array(cfg.markers.positions_m, float)
        self.occluded = occluded
        self._rng = np.random.default_rng([seed, 505])
        W, H = cfg.image.width, cfg.image.height
        r = cfg.render
        # Background: a seeded bank of dark-level + read-noise pixels; each frame takes a random
        # window of it (fresh noise per frame at a fraction of the cost of drawing 2.2 MP).
        bank = r.background_dn + self._rng.normal(0.0, r.read_noise_dn, (H + self.NOISE_PAD, W + self.NOISE_PAD))
        self._bank = np.clip(np.rint(bank), 0, 255).astype(np.uint8)

    def calibration(self) -> list[PinholeCamera]:
        """Cameras as the calibrated rig knows them (MVS frame)."""
        return rig_cameras_mvs(self.cfg)

    def marker_world(self, R: np.ndarray, p: np.ndarray) -> np.ndarray:
        """The markers' world positions at a tool pose.

        Parameters
        ----------
        R : ndarray
            (3, 3) tool orientation, world frame.
        p : ndarray
            (3,) m, the TCP, world frame.

        Returns
        -------
        ndarray
            (n_markers, 3) m.
        """
        return np.asarray(p, float) + self.markers @ np.asarray(R, float).T

    def _background(self) -> np.ndarray:
        H, W = self.cfg.image.height, self.cfg.image.width
        dy, dx = self._rng.integers(0, self.NOISE_PAD, 2)
        img = self._bank[dy:dy + H, dx:dx + W]
        if self._rng.random() < 0.5:
            img = img[::-1, ::-1]
        return np.ascontiguousarray(img)

    def render(self, R: np.ndarray, p: np.ndarray, points: np.ndarray | None = None):
        """Images of the marker cluster at tool pose (R, p) (world); or of arbitrary ``points``.

        Parameters
        ----------
        R : ndarray
            (3, 3) tool orientation, world frame.
        p : ndarray
            (3,) m, the TCP, world frame.
        points : ndarray or None
            (n, 3) m, world; replaces the cluster (calibration boards and wands).

        Returns
        -------
        images : list of ndarray or None
            One uint8 (H, W) image per camera, None for a camera that delivered no frame.
        info : dict
            The truth used: ``uv`` (per camera, (n, 2) px), ``visible`` (per camera, (n,) bool),
            ``points_world`` ((n, 3) m).
        """
        r, rng = self.cfg.render, self._rng
        X = self.marker_world(R, p) if points is None else np.atleast_2d(np.asarray(points, float))
        n = len(X)
        d_m = self.cfg.markers.diameter_m
        images: list[np.ndarray | None] = []  # None: a dropped camera
        visible, truth_uv = [], []
        for cam in self.cams:
            dropped = cam.name in r.dropped_cameras or rng.random() < r.dropout_probability
            uv, depth = cam.project(X)
            vis = depth > 0.05
            if points is None and r.occluded_markers:
                vis[list(r.occluded_markers)] = False
            if r.occlusion_probability > 0:
                vis &= rng.random(n) >= r.occlusion_probability
            if self.occluded is not None:
                vis &= ~np.asarray(self.occluded(cam.center, X), bool)
            W, H = cam.size
            vis &= (uv[:, 0] > -0.5) & (uv[:, 0] < W - 0.5) & (uv[:, 1] > -0.5) & (uv[:, 1] < H - 0.5)
            truth_uv.append(uv)
            visible.append(vis & (not dropped))
            if dropped:
                images.append(None)
                continue
            img = self._background()
            gain = 1.0 + r.exposure_noise * rng.standard_normal()
            # Projected marker radius -> blob sigma (a uniform disc of radius rho has sigma rho/2).
            rho = 0.5 * d_m * cam.K[0, 0] / np.maximum(depth, 0.05)
            sig = np.sqrt((rho / 2.0) ** 2 + r.blur_px ** 2)
            jit = rng.normal(0.0, r.jitter_px, (n, 2))
            peak = np.clip(r.peak_dn * gain * (1.0 + 0.03 * rng.standard_normal(n)), 1.0, 255.0)
            blobs_uv, blobs_sig, blobs_peak = [uv[vis] + jit[vis]], [sig[vis]], [peak[vis]]
            k = r.spurious_per_image
            if k:
                near = rng.random(k) < r.spurious_near_marker
                spur = rng.uniform([0, 0], [W - 1, H - 1], (k, 2))
                if np.any(vis):
                    anchors = uv[vis][rng.integers(0, int(vis.sum()), k)]
                    off = rng.uniform(6.0, 25.0, k)
                    ang = rng.uniform(0, 2 * np.pi, k)
                    spur[near] = (anchors + np.c_[off * np.cos(ang), off * np.sin(ang)])[near]
                blobs_uv.append(spur)
                blobs_sig.append(rng.uniform(1.0, 3.0, k))
                blobs_peak.append(rng.uniform(0.4, 1.0, k) * r.peak_dn)
            _render_blobs(img, np.vstack(blobs_uv), np.concatenate(blobs_sig),
                          np.concatenate(blobs_peak), rng)
            images.append(img)
        info = {"uv": truth_uv, "visible": visible, "points_world": X}
        return images, info


def sample_volume(n: int, seed: int, lo=(0.55, -0.45, 0.2), hi=(1.25, 0.45, 0.9)) -> np.ndarray:
    """Uniformly random TCP positions in the DOE-like working volume.

    Parameters
    ----------
    n : int
    seed : int
    lo, hi : array_like
        (3,) m, the box's corners (world).

    Returns
    -------
    ndarray
        (n, 3) m.
    """
    return np.random.default_rng([seed, 606]).uniform(lo, hi, (n, 3))


def random_tool_rotation(rng: np.random.Generator, base: np.ndarray | None = None,
                         max_deg: float = 15.0) -> np.ndarray:
    """``base`` tilted by a random rotation of up to ``max_deg``.

    Parameters
    ----------
    rng : numpy.random.Generator
    base : ndarray or None
        (3, 3); sim.kinematics.TOOL_DOWN when None.
    max_deg : float
        deg.

    Returns
    -------
    ndarray
        (3, 3).
    """
    from scipy.spatial.transform import Rotation

    if base is None:
        base = np.array([[0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0]])  # TOOL_DOWN
    v = rng.normal(size=3)
    v *= np.radians(rng.uniform(0, max_deg)) / np.linalg.norm(v)
    return Rotation.from_rotvec(v).as_matrix() @ base
