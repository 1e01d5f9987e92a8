"""Registration on import (measurements in an instrument frame): the rigid transform
instrument -> robot fitted jointly with the probe/tool offset on the flange,

    R p_m + t = p_f + R_f o                                   (one 3-vector equation per row)

(the paper's Eqs. 3-4 with the tool offset as extra unknowns; Kabsch start, then
Levenberg-Marquardt), and the report of what a rigid registration cannot explain.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from dt_kernel.errors import DataError
from dt_kernel.units import M_PER_MM
from dt_runtime.frames.registration import RigidTransform, fit_rigid


@dataclass
class RegistrationReport:
    """What the import did and what is left after registration (lengths in mm).

    method: 'none' (robot-frame data), 'rigid' or 'rigid+offset'. rotation/translation map
    the instrument frame to the robot frame (p_robot = R p_inst + t, t in m); offset is the
    probe/tool offset on the flange (m, flange frame). rms_axis_mm / rms_3d_mm: the residual
    after registration (= the error left in the dataset). *_std: 1-sigma parameter
    uncertainties from the Gauss-Newton covariance s^2 (J^T J)^-1.
    """

    method: str
    n: int
    rms_axis_mm: np.ndarray
    rms_3d_mm: float
    rotation: np.ndarray = field(default_factory=lambda: np.eye(3))
    translation: np.ndarray = field(default_factory=lambda: np.zeros(3))
    offset: np.ndarray = field(default_factory=lambda: np.zeros(3))
    rotation_std_rad: np.ndarray | None = None
    translation_std_mm: np.ndarray | None = None
    offset_std_mm: np.ndarray | None = None
    n_skipped: int = 0
    seconds: float = 0.0
    notes: list[str] = field(default_factory=list)
    uncertainty: dict | None = None  # what ux..uz stated and the k that made them standard (importer)
    # The offset fitted for a robot whose config gives no tool (frames.tool_fit.ToolFit.to_dict):
    # the analysis appends it to the chain (cli.common.robot_of).
    tool_offset: dict | None = None

    @property
    def transform(self):
        """The instrument -> robot transform as a dt_runtime.frames.registration.RigidTransform."""
        return RigidTransform(self.rotation, self.translation)

    def to_dict(self) -> dict:
        """The report as a JSON-ready dict (lengths in mm)."""
        f = lambda a: None if a is None else [float(v) for v in np.ravel(a)]  # noqa: E731
        return {
            "method": self.method, "n": self.n, "n_skipped": self.n_skipped,
            "rms_3d_mm": float(self.rms_3d_mm),
            "rms_axis_mm": dict(zip("xyz", [float(v) for v in np.ravel(self.rms_axis_mm)])),
            "rotation": np.asarray(self.rotation).tolist(),
            "translation_mm": f(np.asarray(self.translation) / M_PER_MM),
            "offset_mm": f(np.asarray(self.offset) / M_PER_MM),
            "rotation_std_rad": f(self.rotation_std_rad), "translation_std_mm": f(self.translation_std_mm),
            "offset_std_mm": f(self.offset_std_mm), "seconds": self.seconds, "notes": list(self.notes),
        } | ({"uncertainty": self.uncertainty} if self.uncertainty is not None else {}) \
          | ({"tool_offset": self.tool_offset} if self.tool_offset is not None else {})


@dataclass
class RigidOffsetFit:
    """The fitted rigid transform instrument -> robot, the tool offset on the flange, the residuals
    R p_m + t - (p_f + R_f o) and the standard deviations of the fitted values.
    """
    rotation: np.ndarray
    translation: np.ndarray
    offset: np.ndarray
    residual: np.ndarray  # (n,3) R p_m + t - (p_f + R_f o)
    rotation_std: np.ndarray
    translation_std: np.ndarray
    offset_std: np.ndarray
    nfev: int
    offset_dof: int  # how many offset components the orientations let us fit (0-3)


def fit_rigid_offset(p_meas: np.ndarray, p_flange: np.ndarray, R_flange: np.ndarray | None = None,
                     offset_init: np.ndarray | None = None, fit_offset: bool = True,
                     loss: str = "linear", f_scale: float = 1e-3) -> RigidOffsetFit:
    """Least squares R p_meas + t = p_flange + R_flange o over R, t and (if fit_offset) o.

    Units: any one length unit for all inputs (SI in this project). R_flange None: o = 0.
    The offset is fitted only when the flange orientations vary enough to separate it from t.

    Parameters
    ----------
    p_meas : ndarray
        (n, 3) measured points, instrument frame.
    p_flange : ndarray
        (n, 3) commanded flange positions, robot frame.
    R_flange : ndarray, optional
        (n, 3, 3) commanded flange orientations.
    offset_init : ndarray, optional
        (3,) start of o (or its fixed value).
    fit_offset : bool, optional
        Fit o.
    loss : str, optional
        scipy least_squares loss.
    f_scale : float, optional
        Residual scale of a robust loss.

    Returns
    -------
    RigidOffsetFit
    """
    p_meas, p_flange = np.asarray(p_meas, float), np.asarray(p_flange, float)
    n = p_meas.shape[0]
    o0 = np.zeros(3) if offset_init is None else np.asarray(offset_init, float)
    if R_flange is None:
        fit_offset, Rf = False, None
        target0 = p_flange
    else:
        Rf = np.asarray(R_flange, float)
        target0 = p_flange + Rf @ o0
    start = fit_rigid(p_meas, target0)  # Kabsch start (Eq. 4)
    R0, t0 = start.R.copy(), start.t.copy()
    # o is identifiable only along directions in which the flange orientation varies: with
    # R_i = Rbar + D_i, R_i o = Rbar o + D_i o, and Rbar o is absorbed by t. Fit o in the span
    # of the right singular vectors of stack(D_i) whose RMS spread exceeds 1 mrad; keep the
    # other components at offset_init (e.g. rotations about one axis only: its component stays).
    basis = np.zeros((3, 0))
    if fit_offset and Rf is not None:  # fit_offset is forced False above when R_flange is None
        _, sv, Vt = np.linalg.svd((Rf - Rf.mean(0)).reshape(-1, 3), full_matrices=False)
        basis = Vt[sv / math.sqrt(n) > 1e-3].T
        fit_offset = basis.shape[1] > 0
    nb = basis.shape[1]
    k = 6 + nb

    def unpack(x):
        R = Rotation.from_rotvec(x[:3]).as_matrix() @ R0
        return R, x[3:6], o0 + basis @ x[6:]

    def resid(x):
        R, t, o = unpack(x)
        target = p_flange if Rf is None else p_flange + Rf @ o
        return (p_meas @ R.T + t - target).ravel()

    def jac(x):
        R, t, o = unpack(x)
        q = p_meas @ R.T  # d(exp(w) R0 p)/dw at small w = -[R p]x
        J = np.zeros((n, 3, k))
        J[:, 0, 1], J[:, 0, 2] = q[:, 2], -q[:, 1]
        J[:, 1, 0], J[:, 1, 2] = -q[:, 2], q[:, 0]
        J[:, 2, 0], J[:, 2, 1] = q[:, 1], -q[:, 0]
        J[:, :, 3:6] = np.eye(3)
        if nb:
            J[:, :, 6:] = -Rf @ basis
        return J.reshape(3 * n, k)

    x0 = np.r_[np.zeros(3), t0, np.zeros(nb)]
    # rotvec is re-linearised each call (exp(w) R0): the Jacobian above is exact at w = 0 and
    # a close approximation near it; restart from the solution once so w ends near 0.
    sol = None
    for _ in range(2):
        sol = least_squares(resid, x0, jac=jac, method="lm" if loss == "linear" else "trf",
                            loss=loss, f_scale=f_scale, x_scale="jac")
        R0 = unpack(sol.x)[0]
        x0 = np.r_[np.zeros(3), sol.x[3:]]
    assert sol is not None  # the loop above runs twice
    R, t, o = unpack(x0)
    r = resid(x0)
    J = jac(x0)
    dof = max(3 * n - k, 1)
    s2 = float(r @ r) / dof
    try:
        cov = s2 * np.linalg.inv(J.T @ J)
    except np.linalg.LinAlgError:
        cov = np.full((k, k), np.nan)
    std = np.sqrt(np.clip(np.diag(cov), 0, None))
    # offset covariance in flange coordinates (components not fitted have zero variance)
    o_std = np.sqrt(np.clip(np.diag(basis @ cov[6:, 6:] @ basis.T), 0, None)) if nb else np.zeros(3)
    return RigidOffsetFit(R, t, np.asarray(o, float), r.reshape(n, 3), std[:3], std[3:6],
                          o_std, int(sol.nfev), nb)




def read_transform(path, unit: str = "mm", maps: str = "instrument_to_robot") -> tuple[np.ndarray, np.ndarray]:
    """A given registration: a 4x4 homogeneous matrix in a text file (16 numbers, whitespace
    separated, row by row, like the UR10 series' Trafo_*.txt), translation in `unit` (mm or m).
    `maps`: instrument_to_robot (p_robot = R p_inst + t) or robot_to_instrument (inverted here).
    Returns (R, t in m). A block that is not a rotation (a scale, a reflection) is refused.

    Parameters
    ----------
    path : str or Path
        The matrix file.
    unit : str, optional
        Unit of the translation column, "mm" or "m".
    maps : str, optional
        "instrument_to_robot" or "robot_to_instrument".

    Returns
    -------
    R : ndarray
        (3, 3).
    t : ndarray
        (3,), m.
    """
    path = Path(path)
    try:
        nums = [float(v) for v in path.read_text(encoding="utf-8-sig").split()]
    except (OSError, UnicodeDecodeError) as exc:
        raise DataError(f"{path}: cannot read the registration ({exc})") from exc
    except ValueError as exc:
        raise DataError(f"{path}: not a 4x4 matrix of numbers ({exc})") from exc
    if len(nums) != 16:
        raise DataError(f"{path}: {len(nums)} numbers, a 4x4 homogeneous matrix has 16")
    M = np.asarray(nums).reshape(4, 4)
    M[:3, 3] *= M_PER_MM if unit == "mm" else 1.0
    try:
        T = RigidTransform.from_matrix(M)
    except DataError as exc:
        raise DataError(f"{path}: {exc}") from exc
    if abs(T.s - 1.0) > 1e-4:
        raise DataError(f"{path}: the 3x3 block scales by {T.s:.6g}: a registration is rigid (scale 1)")
    T = RigidTransform(T.R, T.t)
    if maps == "robot_to_instrument":
        T = T.inverse()
    return np.array(T.R), np.array(T.t)
