"""Fast inverse kinematics of one pose, warm-started: the per-set-point IK of a corrected path.

`Chain.ik` solves the same problem (TCP at a target position, the tool's orientation held) with
general-purpose calls (a batched forward kinematics, scipy's rotation vector, `lstsq`): ~0.5 ms
per call. A path's set-points lie a fraction of a millimetre apart, so the previous set-point's
joints are an excellent start and one or two Newton steps converge; what costs is the overhead
per step. `NewtonIK` precomputes the chain as stacked arrays and evaluates, per step, all joint
rotations at once (Rodrigues' formula, R = I + sin q K + (1 - cos q) K^2), the chain's cumulative
products in place, the analytic geometric Jacobian (rows: axis_j x (p - p_j); axis_j) and a
damped least-squares step (Levenberg-Marquardt with the damping lambda^2 = |e|^2 + LAMBDA0^2 after
Sugihara, "Solvability-unconcerned inverse kinematics by the Levenberg-Marquardt method", IEEE
T-RO 27(5), 2011: quadratic convergence near the solution, bounded steps near a singularity).

It converges to the same solution as `Chain.ik` (the same pose, the same branch from the same
seed; for a 6-axis arm the solution is locally unique, so the joints agree to ~1e-9), with the
same tolerances and the same UnreachableError when it does not.
"""
from __future__ import annotations

import math

import numpy as np

from dt_kernel.errors import DataError, UnreachableError
from dt_runtime.frames.kinematics import MAX_IK_STEP_RAD, Chain

LAMBDA0 = 1e-9  # damping floor (Sugihara's bias): keeps J J^T + lambda^2 I invertible at a singularity


def _skew(a: np.ndarray) -> np.ndarray:
    return np.array([[0.0, -a[2], a[1]], [a[2], 0.0, -a[0]], [-a[1], a[0], 0.0]])


def rotvec(M: np.ndarray) -> np.ndarray:
    """The rotation vector (axis * angle, rad) of rotation matrix M: the log map, exact for angles
    below pi - 1e-3 (a Newton step's orientation error is tiny); scipy's for larger ones."""
    w = np.array([M[2, 1] - M[1, 2], M[0, 2] - M[2, 0], M[1, 0] - M[0, 1]]) * 0.5  # sin(theta) * axis
    c = max(-1.0, min(1.0, (M[0, 0] + M[1, 1] + M[2, 2] - 1.0) * 0.5))
    theta = math.acos(c)
    if theta < 1e-6:
        return w  # theta / sin(theta) = 1 + O(theta^2)
    if theta > math.pi - 1e-3:
        from scipy.spatial.transform import Rotation

        return np.asarray(Rotation.from_matrix(M).as_rotvec())
    return w * (theta / math.sin(theta))


class NewtonIK:
    """Position IK holding the tool's orientation, for one chain; `solve` per set-point."""

    def __init__(self, chain: Chain):
        self.chain = chain
        n = chain.dof
        self._O = np.ascontiguousarray(np.stack(chain.origins))  # (n, 4, 4) fixed part before each joint
        self._a = np.array(chain.axes, dtype=float)  # (n, 3) joint axes in their own frames
        self._K = np.stack([_skew(a) for a in self._a])  # (n, 3, 3): Rodrigues' K per joint
        self._K2 = self._K @ self._K
        self._I = np.eye(3)
        self._R4 = np.zeros((n, 4, 4))
        self._R4[:, 3, 3] = 1.0
        self._cum = np.empty((n, 4, 4))  # joint j's frame after the fixed part, before its rotation
        self._tool = np.ascontiguousarray(chain.tool)
        self._T = np.empty((4, 4))
        self._eye6 = np.eye(6)
        self.iterations = 0  # Newton steps of the last solve (the benchmark reports them)

    def _fk(self, q: np.ndarray) -> np.ndarray:
        """TCP transform (4, 4) at q; fills self._cum (the joint frames) for the Jacobian."""
        s, c = np.sin(q), np.cos(q)
        self._R4[:, :3, :3] = self._I + s[:, None, None] * self._K + (1.0 - c)[:, None, None] * self._K2
        cum, Os, R4 = self._cum, self._O, self._R4
        # cum_j = T_{j-1} O_j: its origin is joint j's position, cum_j R_j = T_j (R_j leaves axis j fixed)
        cum[0] = Os[0]
        T = Os[0] @ R4[0]
        for j in range(1, len(Os)):
            np.matmul(T, Os[j], out=cum[j])
            T = cum[j] @ R4[j]
        return np.matmul(T, self._tool, out=self._T)

    def solve(self, target: np.ndarray, q_seed: np.ndarray, R: np.ndarray | None = None,
              tol: float = 1e-9, max_iter: int = 50) -> np.ndarray:
        """Joint angles putting the TCP at `target` (m) with orientation R (default: the TCP's at
        q_seed), from q_seed. UnreachableError naming the target if it does not converge
        (beyond reach, or a singular pose the damped steps cannot leave)."""
        target = np.asarray(target, dtype=float)
        q = np.array(q_seed, dtype=float)
        if target.shape != (3,) or q.shape != (self.chain.dof,) or not (
                np.isfinite(target).all() and np.isfinite(q).all()):
            raise DataError(f"ik: target must be 3 finite numbers and q_seed {self.chain.dof}, got {target!r}, {q!r}")
        Rt = None if R is None else np.asarray(R, dtype=float)
        err = np.empty(6)
        for it in range(max_iter + 1):
            T = self._fk(q)
            p = T[:3, 3]
            if Rt is None:
                Rt = T[:3, :3].copy()  # the seed's orientation: its error is zero at the seed
                err[3:] = 0.0
            else:
                err[3:] = rotvec(Rt @ T[:3, :3].T)
            err[:3] = target - p
            ep = math.sqrt(err[0] ** 2 + err[1] ** 2 + err[2] ** 2)
            er = math.sqrt(err[3] ** 2 + err[4] ** 2 + err[5] ** 2)
            if (ep < tol and er < tol) or it == max_iter:
                break
            ax = np.einsum("jab,jb->ja", self._cum[:, :3, :3], self._a)  # world axes (n, 3)
            J = np.concatenate([np.cross(ax, p - self._cum[:, :3, 3]).T, ax.T])  # (6, n)
            lam2 = ep * ep + er * er + LAMBDA0 * LAMBDA0
            dq = J.T @ np.linalg.solve(J @ J.T + lam2 * self._eye6, err)
            norm = math.sqrt(float(dq @ dq))
            q += dq if norm <= MAX_IK_STEP_RAD else dq * (MAX_IK_STEP_RAD / norm)  # no leaps off the branch
        self.iterations = it
        if not (ep < tol and er < tol) and (ep > 1e-6 or er > 1e-5):  # Chain.ik's acceptance, the same
            raise UnreachableError(f"target {np.round(target * 1e3, 2).tolist()} mm: no joint angles of "
                                   f"{self.chain.name} reach it from the seed (residual {ep * 1e3:.3g} mm, "
                                   f"{er:.3g} rad after {it} Newton steps)")
        return q
