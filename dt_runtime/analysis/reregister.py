"""Re-registration after correction: scoring a model fairly on a session whose registration was
fitted on that session's own data (`reregistered`, `by_session`).

See docs/campaigns.md ("Re-registration after correction").
"""
from __future__ import annotations

import numpy as np

from dt_runtime.frames.registration import RigidTransform, fit_rigid

DOF = 6  # a rigid transform: 3 rotations, 3 translations


def reregistered(measured: np.ndarray, residual: np.ndarray) -> tuple[np.ndarray, RigidTransform]:
    """Residual after refitting the rigid registration of `measured` (n, 3; robot frame) to the
    corrected commanded points measured + residual (= c - e_hat). Returns (residual, the refit T).

    A session's tracker -> robot registration was fitted to its points against the *uncorrected*
    commanded TCP, so it absorbed the rigid part (6 dof) of the robot's error in that session. A
    model trained on other sessions predicts the error including such a rigid part, which this
    session's data do not show: scored as is, the model would be charged with a difference no
    campaign could see. So the registration is fitted again with the model's correction applied,
    and the residual after that fit is the model's score:

        T* = argmin_T sum |(c_i - e_hat_i) - T(m_i)|^2,   r_i = (c_i - e_hat_i) - T*(m_i)

    With the held-out residual r0 = e - e_hat = c - m - e_hat, the target c - e_hat is m + r0. The
    figure absorbs 6 dof per session (the same the session's own fit absorbed from the uncorrected
    error), and it can only be lower than or equal to r0's RMS (T = 1 is one candidate).

    Parameters
    ----------
    measured : ndarray
        (n, 3) measured points, robot frame, m.
    residual : ndarray
        (n, 3) held-out residual, m.

    Returns
    -------
    residual : ndarray
        (n, 3), m.
    T : RigidTransform
    """
    m = np.asarray(measured, dtype=float)
    target = m + np.asarray(residual, dtype=float)
    T = fit_rigid(m, target)
    return target - T.apply(m), T


def by_session(measured: np.ndarray, residual: np.ndarray, session: np.ndarray,
               refit: set[int] | None = None) -> np.ndarray:
    """`residual` with the rows of every session in `refit` (default all) re-registered on their own.

    Parameters
    ----------
    measured : ndarray
        (n, 3), m.
    residual : ndarray
        (n, 3), m.
    session : ndarray
        (n,) session index.
    refit : set of int, optional
        The sessions re-registered.

    Returns
    -------
    ndarray
    """
    out = np.array(residual, dtype=float, copy=True)
    for s in np.unique(session):
        if refit is not None and int(s) not in refit:
            continue
        rows = session == s
        out[rows] = reregistered(measured[rows], residual[rows])[0]
    return out
