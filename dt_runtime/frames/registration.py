"""Rigid registration of instrument frames to the global frame GL (paper Sect. 2.3).

`RigidTransform` (Eq. 3), `fit_rigid` (Eq. 4, never a reflection), `three_line_frame` (the
paper's three-line method), `registration_residuals` (Eqs. 5-7), `ResidualStats` (Table 2),
`reproducibility` (Eq. 12) and `register_instrument`, all of them for one instrument.
Units: whatever the caller passes (SI, metres, inside the code); `to_dict(unit="mm")` converts.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from dt_kernel.errors import DataError
from dt_kernel.units import AXES


def _frozen(a: np.ndarray) -> np.ndarray:
    a = np.array(a, dtype=float)  # a private copy, so callers cannot mutate a transform
    a.setflags(write=False)
    return a


@dataclass(frozen=True)
class RigidTransform:
    """p_target = s R p_source + t (s = 1 for a rigid transform)."""

    R: np.ndarray
    t: np.ndarray
    s: float = 1.0

    def __post_init__(self):
        R, t = np.asarray(self.R, dtype=float), np.asarray(self.t, dtype=float)
        if R.shape != (3, 3) or t.shape != (3,):
            raise DataError(f"RigidTransform needs R (3, 3) and t (3,), got {R.shape} and {t.shape}")
        if not (np.all(np.isfinite(R)) and np.all(np.isfinite(t)) and np.isfinite(self.s) and self.s > 0):
            raise DataError("RigidTransform: R, t must be finite and the scale s positive")
        object.__setattr__(self, "R", _frozen(R))
        object.__setattr__(self, "t", _frozen(t))
        object.__setattr__(self, "s", float(self.s))

    def apply(self, points: np.ndarray) -> np.ndarray:
        """Map one point (3,) or many (n, 3).

        Parameters
        ----------
        points : ndarray
            (3,) or (n, 3).

        Returns
        -------
        ndarray
            The mapped points, same shape.
        """
        p = np.asarray(points, dtype=float)
        if p.shape[-1:] != (3,) or p.ndim > 2:
            raise DataError(f"apply: expected (3,) or (n, 3) points, got shape {p.shape}")
        return self.s * p @ self.R.T + self.t

    def inverse(self) -> RigidTransform:
        """The inverse map, x -> (R^T (x - t)) / s.

        Returns
        -------
        RigidTransform
        """
        Ri = self.R.T
        return RigidTransform(Ri, -(Ri @ self.t) / self.s, 1.0 / self.s)

    def compose(self, other: RigidTransform) -> RigidTransform:
        """self after other: x -> self(other(x)) (matrix product self.matrix @ other.matrix).

        Parameters
        ----------
        other : RigidTransform
            The transform applied first.

        Returns
        -------
        RigidTransform
        """
        return RigidTransform(self.R @ other.R, self.s * self.R @ other.t + self.t, self.s * other.s)

    @property
    def matrix(self) -> np.ndarray:
        """Homogeneous 4x4 (Eq. 3); the upper-left block is s R."""
        M = np.eye(4)
        M[:3, :3] = self.s * self.R
        M[:3, 3] = self.t
        return M

    @classmethod
    def from_matrix(cls, M: np.ndarray, atol: float = 1e-6) -> RigidTransform:
        """Inverse of `matrix`; refuses a block that is not a scaled rotation.

        Parameters
        ----------
        M : ndarray
            Homogeneous 4x4.
        atol : float, optional
            Tolerance of the checks.

        Returns
        -------
        RigidTransform

        Raises
        ------
        DataError
            When M is not homogeneous or its block is not a scaled rotation.
        """
        M = np.asarray(M, dtype=float)
        if M.shape != (4, 4) or not np.allclose(M[3], [0, 0, 0, 1], atol=atol):
            raise DataError(f"from_matrix: expected a homogeneous 4x4 matrix, got shape {M.shape}")
        A = M[:3, :3]
        det = np.linalg.det(A)
        if not np.isfinite(det) or det <= 0:
            raise DataError(f"from_matrix: the 3x3 block has determinant {det:g} (reflection or singular)")
        s = det ** (1.0 / 3.0)
        R = A / s
        if not np.allclose(R @ R.T, np.eye(3), atol=atol):
            raise DataError("from_matrix: the 3x3 block is not a (scaled) rotation")
        return cls(R, M[:3, 3], s)

    @classmethod
    def identity(cls) -> RigidTransform:
        """The identity transform.

        Returns
        -------
        RigidTransform
        """
        return cls(np.eye(3), np.zeros(3))

    def rotation_angle_to(self, other: RigidTransform) -> float:
        """Angle (rad) of the rotation between self.R and other.R.

        Parameters
        ----------
        other : RigidTransform
            The other transform.

        Returns
        -------
        float
        """
        D = self.R @ other.R.T
        sin = np.linalg.norm([D[2, 1] - D[1, 2], D[0, 2] - D[2, 0], D[1, 0] - D[0, 1]]) / 2.0
        return float(np.arctan2(sin, (np.trace(D) - 1.0) / 2.0))  # accurate near 0, unlike arccos

    def to_dict(self) -> dict:
        """The transform as a JSON-ready dict {R, t, s}."""
        return {"R": self.R.tolist(), "t": self.t.tolist(), "s": float(self.s)}

    @classmethod
    def from_dict(cls, d: dict) -> RigidTransform:
        """The transform `to_dict` wrote (s defaults to 1).

        Parameters
        ----------
        d : dict
            With keys R (3x3), t (3) and optionally s.

        Returns
        -------
        RigidTransform

        Raises
        ------
        DataError
            When a key is missing or malformed.
        """
        try:
            return cls(np.array(d["R"], dtype=float), np.array(d["t"], dtype=float), float(d.get("s", 1.0)))
        except (KeyError, TypeError, ValueError) as exc:
            raise DataError(f"RigidTransform.from_dict: needs keys R (3x3) and t (3), got {d!r}") from exc


def _check(points: np.ndarray, name: str) -> np.ndarray:
    p = np.asarray(points, dtype=float)
    if p.ndim != 2 or p.shape[1] != 3:
        raise DataError(f"{name}: expected an (n, 3) array of points, got shape {p.shape}")
    if not np.all(np.isfinite(p)):
        raise DataError(f"{name}: contains NaN or infinite coordinates")
    return p


def fit_rigid(source: np.ndarray, target: np.ndarray, weights: np.ndarray | None = None,
              scale: bool = False) -> RigidTransform:
    """Least-squares T with T(source) ~ target, minimising the (weighted) SSE of Eq. 4.

    Kabsch (Umeyama 1991 when scale=True). The sign correction D keeps det(R) = +1, so
    mirrored data give the best proper rotation, never a reflection.

    Parameters
    ----------
    source, target : ndarray
        (n, 3) paired points.
    weights : ndarray, optional
        (n,) weight per pair.
    scale : bool, optional
        Fit a scale factor too.

    Returns
    -------
    RigidTransform
    """
    P, Q = _check(source, "source"), _check(target, "target")
    if len(P) != len(Q):
        raise DataError(f"source has {len(P)} points, target {len(Q)}")
    if weights is None:
        w = np.ones(len(P))
    else:
        w = np.asarray(weights, dtype=float)
        if w.shape != (len(P),) or not np.all(np.isfinite(w)) or np.any(w < 0) or w.sum() <= 0:
            raise DataError("weights: need one finite, non-negative weight per point, not all zero")
    use = w > 0
    span = np.ptp(P[use], axis=0).max() if use.any() else 0.0
    if use.sum() < 3 or np.linalg.matrix_rank(P[use] - P[use].mean(0), tol=1e-9 * max(span, 1e-300)) < 2:
        raise DataError("need at least 3 non-collinear points to fit a rigid transform")
    w = w / w.sum()
    mp, mq = w @ P, w @ Q
    Pc, Qc = P - mp, Q - mq
    H = (Pc * w[:, None]).T @ Qc  # cross-covariance
    U, S, Vt = np.linalg.svd(H)
    D = np.diag([1.0, 1.0, 1.0 if np.linalg.det(Vt.T @ U.T) > 0 else -1.0])  # no reflections
    R = Vt.T @ D @ U.T
    s = float(np.sum(S * np.diag(D)) / np.sum(w * np.sum(Pc ** 2, axis=1))) if scale else 1.0
    return RigidTransform(R, mq - s * R @ mp, s)


@dataclass(frozen=True)
class RigidUncertainty:
    """The uncertainty of a rigid transform fitted to paired points (`rigid_uncertainty`):
    covariance of a small rotation (rad, about the target frame's axes) and translation (m), from
    the fit's own residual, and its degrees of freedom (3 n - 6)."""

    T: RigidTransform
    cov: np.ndarray  # (6, 6): [omega (rad), dt (m)]
    dof: int
    residual_rms_m: float  # 3D RMS of the fit's residual

    def at(self, points: np.ndarray) -> np.ndarray:
        """Standard uncertainty (m, per target axis) of T(p) at each point.

        Parameters
        ----------
        points : ndarray
            (n, 3) source points, m.

        Returns
        -------
        ndarray
            (n, 3), m.
        """
        J = rigid_jacobian(self.T.apply(np.asarray(points, dtype=float).reshape(-1, 3)))
        return np.sqrt(np.maximum(np.einsum("nap,pq,naq->na", J, self.cov, J), 0.0))


def rigid_jacobian(q: np.ndarray) -> np.ndarray:
    """The derivative of a small rigid change, omega x q + dt, with respect to [omega, dt] at points q.

    Parameters
    ----------
    q : ndarray
        (n, 3) points, m (for a fitted T: the mapped points T(p)).

    Returns
    -------
    ndarray
        (n, 3, 6).
    """
    n = len(q)
    J = np.zeros((n, 3, 6))
    x, y, z = q[:, 0], q[:, 1], q[:, 2]
    # -[q]x: the cross product omega x q written as a matrix acting on omega
    J[:, 0, 1], J[:, 0, 2] = z, -y
    J[:, 1, 0], J[:, 1, 2] = -z, x
    J[:, 2, 0], J[:, 2, 1] = y, -x
    J[:, :, 3:] = np.eye(3)
    return J


def rigid_uncertainty(source: np.ndarray, target: np.ndarray) -> RigidUncertainty:
    """`fit_rigid` of the pairs and the covariance of its six parameters, s^2 (J^T J)^-1 with s^2
    the residual's variance per coordinate on 3 n - 6 degrees of freedom (Gauss-Markov: the
    points' errors independent with one variance).

    Parameters
    ----------
    source, target : ndarray
        (n, 3) paired points, m; n >= 3 non-collinear.

    Returns
    -------
    RigidUncertainty

    Raises
    ------
    DataError
        Fewer than 3 non-collinear points.
    """
    P, Q = _check(source, "source"), _check(target, "target")
    T = fit_rigid(P, Q)
    r = Q - T.apply(P)
    dof = 3 * len(P) - 6
    J = rigid_jacobian(T.apply(P))
    N = np.einsum("nap,naq->pq", J, J)
    s2 = float(np.sum(r ** 2)) / dof if dof > 0 else float("inf")
    cov = s2 * np.linalg.pinv(N)
    return RigidUncertainty(T, cov, dof, float(np.sqrt(np.mean(np.sum(r ** 2, axis=1)))))


def _line_direction(points: np.ndarray, distances: np.ndarray, name: str) -> np.ndarray:
    """Principal direction of a 3D line fit, oriented towards increasing distance."""
    if len(np.unique(distances)) < 2:
        raise DataError(f"{name}: a registration line needs points at 2 or more distinct distances")
    c = points - points.mean(0)
    d = np.linalg.svd(c, full_matrices=False)[2][0]
    if np.dot(c.T @ (distances - distances.mean()), d) < 0:
        d = -d
    return d


def three_line_frame(points_x, points_y, points_z, distances_x, distances_y, distances_z,
                     min_cos: float = 0.9) -> RigidTransform:
    """Instrument frame -> GL from the three orthogonal registration lines (Sect. 2.3, Fig. 7).

    points_k: (n_k, 3) instrument coordinates of the TCP moved a distance distances_k (n_k,)
    along the robot's k axis from the common start point. GL's axes are the measured
    directions of motion (x; y made orthogonal to x; z = x cross y, checked against the
    measured z line: cosine >= min_cos) and its origin the common start point, fitted by least
    squares so that every point sits at its nominal GL position d * unit_k.

    Parameters
    ----------
    points_x, points_y, points_z : ndarray
        (n_k, 3) instrument coordinates along each line.
    distances_x, distances_y, distances_z : ndarray
        (n_k,) distance of each point from the start, m.
    min_cos : float, optional
        Least cosine between the constructed and the measured z direction.

    Returns
    -------
    RigidTransform
        Instrument frame -> GL.
    """
    sets = []
    for p, d, a in ((points_x, distances_x, "x"), (points_y, distances_y, "y"), (points_z, distances_z, "z")):
        p = _check(p, f"points_{a}")
        d = np.asarray(d, dtype=float).ravel()
        if d.shape != (len(p),) or not np.all(np.isfinite(d)):
            raise DataError(f"distances_{a}: need one finite distance per point ({len(p)}), got shape {d.shape}")
        sets.append((p, d))
    dx, dy, dz = (_line_direction(p, d, f"line {a}") for (p, d), a in zip(sets, AXES))
    ex = dx
    ey = dy - ex * np.dot(dy, ex)
    if np.linalg.norm(ey) < 0.1:
        raise DataError("registration lines x and y are (nearly) parallel")
    ey /= np.linalg.norm(ey)
    ez = np.cross(ex, ey)
    if np.dot(ez, dz) < min_cos:
        ang = np.degrees(np.arccos(np.clip(np.dot(ez, dz), -1, 1)))
        raise DataError("registration lines are not a right-handed orthogonal triad "
                        f"(measured z line is {ang:.1f} deg from x cross y)")
    R_inst = np.column_stack([ex, ey, ez])  # GL axes in instrument coordinates
    # p_i = o + R_inst g_i with g_i = d_i unit_k the nominal GL coordinates; least squares in o
    # (R fixed) is the mean of p_i - R_inst g_i.
    g = np.vstack([np.outer(d, np.eye(3)[k]) for k, (_, d) in enumerate(sets)])
    p = np.vstack([pts for pts, _ in sets])
    origin = np.mean(p - g @ R_inst.T, axis=0)
    # GL coordinates: R_inst^T (p - origin).
    return RigidTransform(R_inst.T, -R_inst.T @ origin)


def gl_nominal(axes, distances) -> np.ndarray:
    """Nominal GL coordinates of registration points: d * unit_k, (n, 3).

    Parameters
    ----------
    axes : array-like
        (n,) 'x', 'y' or 'z'.
    distances : array-like
        (n,) distance along the axis.

    Returns
    -------
    ndarray
        (n, 3).
    """
    axes = np.asarray(axes)
    d = np.asarray(distances, dtype=float)
    out = np.zeros((len(d), 3))
    for k, a in enumerate(AXES):
        out[axes == a, k] = d[axes == a]
    bad = ~np.isin(axes, AXES)
    if bad.any():
        raise DataError(f"registration axis must be one of {AXES}, got {axes[bad][0]!r}")
    return out


def registration_residuals(T: RigidTransform, points_instrument: np.ndarray,
                           points_gl: np.ndarray) -> np.ndarray:
    """Eqs. 5-7: e = T p_instrument - p_GL, (n, 3).

    Parameters
    ----------
    T : RigidTransform
        Instrument -> GL.
    points_instrument : ndarray
        (n, 3).
    points_gl : ndarray
        (n, 3) nominal.

    Returns
    -------
    ndarray
        (n, 3).
    """
    p, q = _check(points_instrument, "points"), _check(points_gl, "points_gl")
    if len(p) != len(q):
        raise DataError(f"points has {len(p)} rows, points_gl {len(q)}")
    return T.apply(p) - q


@dataclass(frozen=True)
class ResidualStats:
    """Per-axis mean and standard deviation (ddof=1) of residuals (Table 2), in input units."""

    mean: np.ndarray
    std: np.ndarray
    n: int

    @property
    def dof(self) -> int:
        """Degrees of freedom of the standard deviation, n - 1."""
        return self.n - 1

    @classmethod
    def of(cls, e: np.ndarray) -> ResidualStats:
        """The statistics of (n, 3) residuals.

        Parameters
        ----------
        e : ndarray
            (n, 3), n >= 2.

        Returns
        -------
        ResidualStats

        Raises
        ------
        DataError
            With fewer than 2 residuals, or non-finite ones.
        """
        e = _check(e, "residuals")
        if len(e) < 2:
            raise DataError("residual statistics need at least 2 residuals")
        return cls(np.mean(e, axis=0), np.std(e, axis=0, ddof=1), len(e))

    def to_dict(self, unit: str = "mm") -> dict:
        """{x: {mean_mm, std_mm}, y: ..., z: ..., n, dof} (input assumed in metres).

        Parameters
        ----------
        unit : str, optional
            'mm', 'm' or 'um'; names the keys and scales the values.

        Returns
        -------
        dict
        """
        f = {"mm": 1e3, "m": 1.0, "um": 1e6}.get(unit)
        if f is None:
            raise ValueError(f"unit must be 'mm', 'm' or 'um', got {unit!r}")
        return {a: {f"mean_{unit}": float(self.mean[k] * f), f"std_{unit}": float(self.std[k] * f)}
                for k, a in enumerate(AXES)} | {"n": int(self.n), "dof": int(self.dof)}


def reproducibility(values: np.ndarray, groups: np.ndarray) -> tuple[np.ndarray, int]:
    """Eq. 12: per axis sqrt(mean over locations of the replication variance, ddof=1), and dof.

    dof = sum(n_i - 1). Locations with a single replication carry no variance and are skipped.

    Parameters
    ----------
    values : ndarray
        (n, 3) repeated measurements.
    groups : ndarray
        (n,) location label of each value.

    Returns
    -------
    u : ndarray
        (3,) reproducibility per axis, in the unit of `values`.
    dof : int
    """
    v = _check(values, "values")
    groups = np.asarray(groups)
    if groups.shape != (len(v),):
        raise DataError(f"groups: need one label per value ({len(v)}), got shape {groups.shape}")
    variances, dof = [], 0
    for g in np.unique(groups):
        m = groups == g
        if m.sum() >= 2:
            variances.append(np.var(v[m], axis=0, ddof=1))
            dof += int(m.sum()) - 1
    if not variances:
        raise DataError("reproducibility needs at least one location with 2 or more replications")
    return np.sqrt(np.mean(variances, axis=0)), dof


@dataclass(frozen=True)
class Registration:
    """One instrument registered to GL: transform, residuals (Eqs. 5-7) and Table 2 stats."""

    transform: RigidTransform
    residuals: np.ndarray
    stats: ResidualStats
    method: str

    def to_dict(self, unit: str = "mm") -> dict:
        """The registration as a JSON-ready dict: method, transform and residual statistics.

        Parameters
        ----------
        unit : str, optional
            Unit of the residual statistics ('mm', 'm' or 'um').

        Returns
        -------
        dict
        """
        return {"method": self.method, "transform": self.transform.to_dict(),
                "residuals": self.stats.to_dict(unit)}


def register_instrument(points_inst: np.ndarray, points_gl: np.ndarray, method: str = "three_line",
                        axes=None, distances=None, weights=None) -> Registration:
    """Register one instrument to GL.

    Non-finite measurements (lost tracker beam, occluded marker) are dropped.

    Parameters
    ----------
    points_inst : ndarray
        (n, 3) measured in the instrument's frame.
    points_gl : ndarray
        (n, 3) nominal in GL.
    method : str, optional
        'three_line' (the paper's) or 'least_squares' (Kabsch on the pairs, Eq. 4).
    axes : array-like, optional
        'x'|'y'|'z' per point, for 'three_line'; read off points_gl when omitted (exactly one
        non-zero coordinate per point).
    distances : array-like, optional
        Distance along the axis per point, m, for 'three_line'; read off points_gl when omitted.
    weights : array-like, optional
        Per point, for 'least_squares'.

    Returns
    -------
    Registration
    """
    p = np.asarray(points_inst, dtype=float)
    q = _check(points_gl, "points_gl")
    if p.shape != q.shape:
        raise DataError(f"points_inst has shape {p.shape}, points_gl {q.shape}")
    ok = np.all(np.isfinite(p), axis=1)
    if method == "three_line":
        if axes is None or distances is None:
            nz = np.abs(q) > 1e-12
            if not np.all(nz.sum(axis=1) <= 1):
                raise DataError("three_line: points_gl are not on the GL axes; pass axes and distances")
            k = np.argmax(nz, axis=1)
            axes = np.array(AXES)[k]
            distances = q[np.arange(len(q)), k]
        axes, distances = np.asarray(axes), np.asarray(distances, dtype=float)
        sets = []
        for a in AXES:
            m = ok & (axes == a)
            sets.append((p[m], distances[m]))
        T = three_line_frame(sets[0][0], sets[1][0], sets[2][0], sets[0][1], sets[1][1], sets[2][1])
    elif method == "least_squares":
        T = fit_rigid(p[ok], q[ok], None if weights is None else np.asarray(weights, dtype=float)[ok])
    else:
        raise DataError(f"method must be 'three_line' or 'least_squares', got {method!r}")
    e = registration_residuals(T, p[ok], q[ok])
    return Registration(T, e, ResidualStats.of(e), method)
