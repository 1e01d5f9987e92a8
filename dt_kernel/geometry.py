"""Small geometry shared by every layer: the skew matrix (kinematic effect terms, MVS cluster
fit) and the laser tracker's spherical coordinates (simulated and serial tracker drivers)."""
from __future__ import annotations

import numpy as np


def skew(v: np.ndarray) -> np.ndarray:
    """Skew-symmetric matrices [v]x of vectors: skew(a) @ b = a x b.

    Parameters
    ----------
    v : ndarray
        (..., 3).

    Returns
    -------
    ndarray
        (..., 3, 3).
    """
    S = np.zeros(v.shape[:-1] + (3, 3))
    S[..., 0, 1], S[..., 0, 2] = -v[..., 2], v[..., 1]
    S[..., 1, 0], S[..., 1, 2] = v[..., 2], -v[..., 0]
    S[..., 2, 0], S[..., 2, 1] = -v[..., 1], v[..., 0]
    return S


def spherical_to_cartesian(d: float, az: float, el: float) -> np.ndarray:
    """A tracker's spherical reading as a point in its own frame.

    Parameters
    ----------
    d : float
        Distance, m.
    az : float
        Azimuth, rad.
    el : float
        Elevation, rad.

    Returns
    -------
    ndarray
        (3,), m.
    """
    return np.array([d * np.cos(el) * np.cos(az), d * np.cos(el) * np.sin(az), d * np.sin(el)])
