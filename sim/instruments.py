"""Simulated instruments: a laser tracker and a point-noise MVS stand-in.

Each has its own frame, placed in the cell by a pose (world = robot base frame). Noise levels
follow the instruments' calibration; every draw uses the instrument's own seeded generator.
The image-based camera rig (sim.camera_rig) can replace the point MVS behind the same driver.
"""
from __future__ import annotations

import numpy as np
from pydantic import Field
from scipy.spatial.transform import Rotation

from dt_kernel.config import Frozen


class Pose(Frozen):
    """Instrument frame in the world: position (m) and extrinsic xyz Euler angles (deg)."""

    position_m: tuple[float, float, float]
    rpy_deg: tuple[float, float, float] = (0.0, 0.0, 0.0)

    def matrix(self) -> tuple[np.ndarray, np.ndarray]:
        """The rotation and translation of the pose (instrument frame -> world).

        Returns
        -------
        R : ndarray
            (3, 3).
        t : ndarray
            (3,) m.
        """
        return Rotation.from_euler("xyz", self.rpy_deg, degrees=True).as_matrix(), np.array(self.position_m)


class TrackerConfig(Frozen):
    """The simulated laser tracker: its pose, the calibration's standard uncertainty u_const_m +
    u_per_m * L (m, L the distance in m) and the probability a measurement has its beam broken.
    """
    pose: Pose
    # Calibration standard uncertainty a + b * L (paper Sect. 2.5: 10 um + 0.02 um/m * L).
    u_const_m: float = Field(10e-6, ge=0)
    u_per_m: float = Field(0.02e-6, ge=0)
    beam_break_probability: float = Field(0.0, ge=0, le=1)


class PointMVSConfig(Frozen):
    """The point-noise MVS stand-in: its pose, noise per axis (m), scale error, bias (m, MVS frame)
    and dropout probability.
    """
    pose: Pose
    noise_m: float = Field(50e-6, ge=0)  # per axis, ~0.09 mm 3-D
    scale_error: float = Field(1.5e-4, ge=-0.01, le=0.01)  # small systematic scale error
    bias_m: tuple[float, float, float] = (0.0, 0.0, 0.0)
    dropout_probability: float = Field(0.0, ge=0, le=1)


class SimLaserTracker:
    """Measures the SMR (the TCP) in spherical coordinates (distance, azimuth, elevation)."""

    def __init__(self, truth, cfg: TrackerConfig, seed: int):
        self._truth, self.cfg = truth, cfg
        self._R, self._t = cfg.pose.matrix()
        self._rng = np.random.default_rng([seed, 303])

    def measure_spherical(self) -> tuple[float, float, float, str]:
        """Measure the SMR: distance, azimuth, elevation with the tracker's isotropic noise.

        Returns
        -------
        tuple
            (d m, azimuth rad, elevation rad, status); NaNs and ``beam_broken`` when the beam breaks.
        """
        if self._rng.random() < self.cfg.beam_break_probability:
            return float("nan"), float("nan"), float("nan"), "beam_broken"
        p = self._R.T @ (self._truth() - self._t)
        d = float(np.linalg.norm(p))
        u = self.cfg.u_const_m + self.cfg.u_per_m * d
        # Isotropic standard uncertainty u at the target: radial u, angular u / d.
        d_m = d + self._rng.normal(0, u)
        az = float(np.arctan2(p[1], p[0])) + self._rng.normal(0, u / d)
        el = float(np.arctan2(p[2], np.hypot(p[0], p[1]))) + self._rng.normal(0, u / d)
        return d_m, az, el, "ok"


class SimPointMVS:
    """Point-noise stand-in for the camera rig: the TCP in the MVS frame with noise and scale error."""

    def __init__(self, truth, cfg: PointMVSConfig, seed: int):
        self._truth, self.cfg = truth, cfg
        self._R, self._t = cfg.pose.matrix()
        self._rng = np.random.default_rng([seed, 404])
        self._bump = np.zeros(3)

    def bump(self, shift_m: np.ndarray) -> None:
        """Fault injection: the rig is knocked, its frame shifts (adds to earlier shifts).

        Parameters
        ----------
        shift_m : ndarray
            (3,) m, world frame.
        """
        self._bump = self._bump + np.asarray(shift_m, dtype=float)

    def measure(self) -> np.ndarray | None:
        """The TCP in the MVS frame with scale error, bias and noise.

        Returns
        -------
        ndarray or None
            (3,) m; None when the rig drops out.
        """
        if self._rng.random() < self.cfg.dropout_probability:
            return None
        p = self._R.T @ (self._truth() - self._t - self._bump)
        return (1.0 + self.cfg.scale_error) * p + np.array(self.cfg.bias_m) + self._rng.normal(
            0, self.cfg.noise_m, 3)
