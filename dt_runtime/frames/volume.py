"""The calibrated volume: the convex hull of the DOE's commanded positions, widened by a margin.

A correction inside it interpolates what the laser tracker measured; outside it the error model
extrapolates, which the twin flags (and the daemon can refuse). The hull is kept as its facet
planes n . x + b <= 0 (outward unit normals), so a point's signed distance to the hull is
max_f (n_f . x + b_f): negative inside (minus the distance to the nearest facet plane), exact
outside wherever the nearest hull point lies on a facet, and a lower bound near edges and
corners, which only makes the margin test a little more permissive there.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy.spatial import ConvexHull, QhullError

from dt_kernel.errors import DataError, ModelError


@dataclass(frozen=True)
class CalibratedVolume:
    """The convex hull of the calibration DOE, as facet half-spaces, with a margin."""
    normals: np.ndarray  # (f, 3) outward unit normals of the hull's facets
    offsets: np.ndarray  # (f,) so that normals @ x + offsets <= 0 inside
    margin_m: float = 0.0  # a command this far outside the hull still counts as inside

    @classmethod
    def of_points(cls, points: np.ndarray, margin_m: float = 0.0) -> CalibratedVolume:
        """The hull of `points`; the DOE must span a volume (not a plane or a line).

        Parameters
        ----------
        points : ndarray
            (n, 3), m; non-finite rows are dropped; at least 4 remain.
        margin_m : float, optional
            How far outside the hull a command still counts as inside, m.

        Returns
        -------
        CalibratedVolume

        Raises
        ------
        DataError
            Too few points, a bad margin, or points that do not span a volume.
        """
        P = np.asarray(points, dtype=float)
        P = P[np.all(np.isfinite(P), axis=1)] if P.ndim == 2 else P
        if P.ndim != 2 or P.shape[1] != 3 or len(P) < 4:
            raise DataError(f"calibrated volume: need at least 4 finite 3D points, got shape {np.shape(points)}")
        if not np.isfinite(margin_m) or margin_m < 0:
            raise DataError(f"calibrated volume: margin {margin_m!r} m must be finite and >= 0")
        try:
            hull = ConvexHull(P)
        except QhullError as exc:
            raise DataError("calibrated volume: the DOE points do not span a volume (all on a plane or a line)") \
                from exc
        return cls(hull.equations[:, :3].copy(), hull.equations[:, 3].copy(), float(margin_m))

    def distance(self, points: np.ndarray) -> np.ndarray:
        """Signed distance (m) of each point to the hull itself (margin not applied): < 0 inside.

        Parameters
        ----------
        points : ndarray
            (3,) or (n, 3), m.

        Returns
        -------
        ndarray
            (n,).
        """
        P = np.atleast_2d(np.asarray(points, dtype=float))
        return np.max(P @ self.normals.T + self.offsets, axis=1)

    def inside(self, points: np.ndarray) -> np.ndarray:
        """Whether each point lies in the hull widened by the margin.

        Parameters
        ----------
        points : ndarray
            (3,) or (n, 3), m.

        Returns
        -------
        ndarray
            (n,) bool.
        """
        return self.distance(points) <= self.margin_m

    def to_dict(self) -> dict[str, Any]:
        """The volume as a JSON-ready dict {normals, offsets, margin_m}."""
        return {"normals": self.normals.tolist(), "offsets": self.offsets.tolist(), "margin_m": self.margin_m}

    @classmethod
    def from_dict(cls, d: Any, where: str = "calibrated volume") -> CalibratedVolume:
        """The volume `to_dict` wrote.

        Parameters
        ----------
        d : Mapping
            A dict from `to_dict`.
        where : str, optional
            What the error names.

        Returns
        -------
        CalibratedVolume

        Raises
        ------
        ModelError
            When the keys are missing or do not describe a 3D hull.
        """
        try:
            n = np.asarray(d["normals"], dtype=float)
            b = np.asarray(d["offsets"], dtype=float)
            margin = float(d.get("margin_m", 0.0))
        except (KeyError, TypeError, ValueError, AttributeError) as exc:
            raise ModelError(f"{where}: needs normals, offsets and margin_m ({exc!r})") from exc
        if n.ndim != 2 or n.shape[1] != 3 or b.shape != (len(n),) or len(n) < 4:
            raise ModelError(f"{where}: normals {n.shape} and offsets {b.shape} do not describe a 3D hull")
        return cls(n, b, margin)
