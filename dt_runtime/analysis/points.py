"""Rows of a measurement table seen per target point and per direction of approach: what the
compare report's residual maps and the dashboard's views (the error map's arrows, the
metrologist's residual map and its filters) aggregate and filter by, computed in one place."""
from __future__ import annotations

import numpy as np


def per_point(commanded: np.ndarray, values: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Replicates aggregated per commanded position (1 um): (positions, mean of `values` per
    position, row count per position).

    Parameters
    ----------
    commanded : ndarray
        (n, 3), m.
    values : ndarray
        (n, ...) per row.

    Returns
    -------
    positions, means, counts : ndarray
    """
    key = np.round(np.asarray(commanded, float) / 1e-6).astype(np.int64)
    _, first, inv = np.unique(key, axis=0, return_index=True, return_inverse=True)
    inv = inv.ravel()
    cnt = np.bincount(inv).astype(float)
    v = np.asarray(values, float).reshape(len(inv), -1)
    means = np.stack([np.bincount(inv, weights=v[:, k]) for k in range(v.shape[1])], axis=1) / cnt[:, None]
    return np.asarray(commanded)[first], means, cnt


def approach(q: np.ndarray) -> np.ndarray:
    """The direction from which each joint approached each row (rows in time order): the sign of
    its change from the previous row (-1, 0 still, +1), the first row taking the second's. What
    backlash and lag follow.

    Parameters
    ----------
    q : ndarray
        (n, dof) joint angles.

    Returns
    -------
    ndarray
        (n, dof).
    """
    q = np.asarray(q, float)
    d = np.sign(np.diff(q, axis=0, prepend=q[:1]))
    if len(d) > 1:
        d[0] = d[1]
    return d
