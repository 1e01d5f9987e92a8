"""Rigid registration of instrument frames to the global frame GL (paper Sect. 2.3).

- `fit_rigid`: least squares over point pairs (Kabsch; Umeyama with scale), Eq. 4.
- `three_line_frame`: the paper's three-point method: the TCP moves 100 mm along three
  orthogonal lines from a common origin; each instrument's view of those lines defines GL.
- Residuals (Eqs. 5-7, Table 2) and reproducibility from replications (Eq. 12).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from dt_runtime.errors import DataError


@dataclass(frozen=True)
class RigidTransform:
    """p_target = s R p_source + t (s = 1 for a rigid transform)."""

    R: np.ndarray
    t: np.ndarray
    s: float = 1.0

    def apply(self, points: np.ndarray) -> np.ndarray:
        p = np.asarray(points, dtype=float)
        return self.s * p @ self.R.T + self.t

    def inverse(self) -> "RigidTransform":
        Ri = self.R.T
        return RigidTransform(Ri, -(Ri @ self.t) / self.s, 1.0 / self.s)

    def compose(self, other: "RigidTransform") -> "RigidTransform":
        """self after other: x -> self(other(x))."""
        return RigidTransform(self.R @ other.R, self.s * self.R @ other.t + self.t, self.s * other.s)

    @property
    def matrix(self) -> np.ndarray:
        """Homogeneous 4x4 (Eq. 3)."""
        M = np.eye(4)
        M[:3, :3] = self.s * self.R
        M[:3, 3] = self.t
        return M

    @classmethod
    def identity(cls) -> "RigidTransform":
        return cls(np.eye(3), np.zeros(3))

    def to_dict(self) -> dict:
        return {"R": self.R.tolist(), "t": self.t.tolist(), "s": float(self.s)}

    @classmethod
    def from_dict(cls, d: dict) -> "RigidTransform":
        return cls(np.array(d["R"], dtype=float), np.array(d["t"], dtype=float), float(d.get("s", 1.0)))


def _check(points: np.ndarray, name: str) -> np.ndarray:
    p = np.asarray(points, dtype=float)
    if p.ndim != 2 or p.shape[1] != 3:
        raise DataError(f"{name}: expected an (n, 3) array of points, got shape {p.shape}")
    if not np.all(np.isfinite(p)):
        raise DataError(f"{name}: contains NaN or infinite coordinates")
    return p


def fit_rigid(source: np.ndarray, target: np.ndarray, weights: np.ndarray | None = None,
              scale: bool = False) -> RigidTransform:
    """Least-squares T with T(source) ~ target (Kabsch; Umeyama when scale=True)."""
    P, Q = _check(source, "source"), _check(target, "target")
    if len(P) != len(Q):
        raise DataError(f"source has {len(P)} points, target {len(Q)}")
    if len(P) < 3 or np.linalg.matrix_rank(P - P.mean(0), tol=1e-9) < 2:
        raise DataError("need at least 3 non-collinear points to fit a rigid transform")
    w = np.ones(len(P)) if weights is None else np.asarray(weights, dtype=float)
    w = w / w.sum()
    mp, mq = w @ P, w @ Q
    Pc, Qc = P - mp, Q - mq
    H = (Pc * w[:, None]).T @ Qc
    U, S, Vt = np.linalg.svd(H)
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(Vt.T @ U.T))])  # no reflections
    R = Vt.T @ D @ U.T
    s = float(np.trace(np.diag(S) @ D) / np.sum(w * np.sum(Pc ** 2, axis=1))) if scale else 1.0
    return RigidTransform(R, mq - s * R @ mp, s)


def _line_direction(points: np.ndarray, distances: np.ndarray) -> np.ndarray:
    """Principal direction of points, oriented towards increasing distance."""
    c = points - points.mean(0)
    d = np.linalg.svd(c, full_matrices=False)[2][0]
    if np.dot(c.T @ (distances - distances.mean()), d) < 0:
        d = -d
    return d


def three_line_frame(points_x, points_y, points_z, distances_x, distances_y, distances_z
                     ) -> RigidTransform:
    """Instrument frame -> GL from the three orthogonal registration lines.

    GL's axes are the measured directions of motion (x; y made orthogonal to x; z = x cross y,
    checked against the measured z line) and its origin the common start point, fitted so that
    every point sits at its nominal distance along its line (least squares).
    """
    sets = [(_check(p, f"points_{a}"), np.asarray(d, dtype=float))
            for p, d, a in ((points_x, distances_x, "x"), (points_y, distances_y, "y"),
                            (points_z, distances_z, "z"))]
    dx, dy, dz = (_line_direction(p, d) for p, d in sets)
    ex = dx
    ey = dy - ex * np.dot(dy, ex)
    ey /= np.linalg.norm(ey)
    ez = np.cross(ex, ey)
    if np.dot(ez, dz) < 0.9:
        raise DataError("registration lines are not a right-handed orthogonal triad "
                        f"(z line deviates by {np.degrees(np.arccos(np.clip(np.dot(ez, dz), -1, 1))):.1f} deg)")
    R_inst = np.column_stack([ex, ey, ez])  # GL axes in instrument coordinates
    # Origin: p_i = o + R_inst g_i with g_i the nominal GL coordinates; least squares -> mean.
    g = np.vstack([np.outer(d, np.eye(3)[k]) for k, (_, d) in enumerate(sets)])
    p = np.vstack([pts for pts, _ in sets])
    origin = np.mean(p - g @ R_inst.T, axis=0)
    # GL coordinates: R_inst^T (p - origin).
    return RigidTransform(R_inst.T, -R_inst.T @ origin)


def registration_residuals(T: RigidTransform, points_instrument: np.ndarray,
                           points_gl: np.ndarray) -> np.ndarray:
    """Eqs. 5-7: e = T p_instrument - p_GL, (n, 3)."""
    return T.apply(_check(points_instrument, "points")) - _check(points_gl, "points_gl")


@dataclass(frozen=True)
class ResidualStats:
    mean: np.ndarray
    std: np.ndarray
    n: int

    @property
    def dof(self) -> int:
        return self.n - 1

    @classmethod
    def of(cls, e: np.ndarray) -> "ResidualStats":
        return cls(np.mean(e, axis=0), np.std(e, axis=0, ddof=1), len(e))

    def to_dict(self, unit: str = "mm") -> dict:
        f = 1e3 if unit == "mm" else 1.0
        return {a: {f"mean_{unit}": float(self.mean[k] * f), f"std_{unit}": float(self.std[k] * f)}
                for k, a in enumerate("xyz")} | {"n": self.n}


def reproducibility(values: np.ndarray, groups: np.ndarray) -> tuple[np.ndarray, int]:
    """Eq. 12: sqrt(mean over locations of the replication variance), per axis, and its dof."""
    v = _check(values, "values")
    groups = np.asarray(groups)
    variances, dof = [], 0
    for g in np.unique(groups):
        m = groups == g
        if m.sum() >= 2:
            variances.append(np.var(v[m], axis=0, ddof=1))
            dof += int(m.sum()) - 1
    if not variances:
        raise DataError("reproducibility needs at least one location with 2 or more replications")
    return np.sqrt(np.mean(variances, axis=0)), dof
