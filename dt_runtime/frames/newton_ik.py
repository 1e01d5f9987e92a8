"""Fast inverse kinematics of one pose, warm-started: the per-set-point IK of a corrected path.

`NewtonIK` solves what `Chain.ik` solves (TCP at a target position, the tool's orientation held)
on plain floats, with damped Newton steps from the previous set-point's joints; it reaches the
same solution with the same tolerances. See docs/cli.md ("Path programs").
"""
from __future__ import annotations

import math

import numpy as np
from scipy.linalg.lapack import dposv as _dposv

from dt_kernel.errors import DataError, UnreachableError
from dt_runtime.common import jit
from dt_runtime.frames.kinematics import MAX_IK_STEP_RAD, Chain

LAMBDA0 = 1e-9  # damping floor (Sugihara's bias): keeps J J^T + lambda^2 I invertible at a singularity
Affine = tuple[float, ...]  # 3x4 row-major: r00 r01 r02 px r10 r11 r12 py r20 r21 r22 pz


def rotvec(M: np.ndarray) -> np.ndarray:
    """The rotation vector (axis * angle, rad) of rotation matrix M (the log map).

    Parameters
    ----------
    M : ndarray
        (3, 3) rotation matrix.

    Returns
    -------
    ndarray
        (3,).
    """
    return np.array(_log(tuple(float(x) for x in np.asarray(M, dtype=float).ravel())))


def _log(m: tuple[float, ...]) -> tuple[float, float, float]:
    """Log map of a row-major 3x3 rotation: exact below pi - 1e-3 (a Newton step's orientation
    error is tiny), scipy's above."""
    wx, wy, wz = (m[7] - m[5]) * 0.5, (m[2] - m[6]) * 0.5, (m[3] - m[1]) * 0.5  # sin(theta) * axis
    theta = math.acos(max(-1.0, min(1.0, (m[0] + m[4] + m[8] - 1.0) * 0.5)))
    if theta < 1e-6:
        return wx, wy, wz  # theta / sin(theta) = 1 + O(theta^2)
    if theta > math.pi - 1e-3:
        from scipy.spatial.transform import Rotation

        r = Rotation.from_matrix(np.array(m).reshape(3, 3)).as_rotvec()
        return float(r[0]), float(r[1]), float(r[2])
    f = theta / math.sin(theta)
    return wx * f, wy * f, wz * f


def _z_to(a: np.ndarray) -> np.ndarray:
    """A rotation taking z to the unit vector a (the identity for z itself)."""
    z = np.array([0.0, 0.0, 1.0])
    v, c = np.cross(z, a), float(z @ a)
    if np.linalg.norm(v) < 1e-12:
        return np.eye(3) if c > 0 else np.diag([1.0, -1.0, -1.0])
    K = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])
    return np.eye(3) + K + K @ K / (1.0 + c)


def _affine(T: np.ndarray) -> Affine:
    return tuple(float(x) for x in np.asarray(T, dtype=float)[:3, :4].ravel())


def _mul(a: Affine, b: Affine) -> Affine:
    """The product of two 3x4 affine transforms."""
    a0, a1, a2, a3, a4, a5, a6, a7, a8, a9, a10, a11 = a
    b0, b1, b2, b3, b4, b5, b6, b7, b8, b9, b10, b11 = b
    return (a0 * b0 + a1 * b4 + a2 * b8, a0 * b1 + a1 * b5 + a2 * b9, a0 * b2 + a1 * b6 + a2 * b10,
            a0 * b3 + a1 * b7 + a2 * b11 + a3,
            a4 * b0 + a5 * b4 + a6 * b8, a4 * b1 + a5 * b5 + a6 * b9, a4 * b2 + a5 * b6 + a6 * b10,
            a4 * b3 + a5 * b7 + a6 * b11 + a7,
            a8 * b0 + a9 * b4 + a10 * b8, a8 * b1 + a9 * b5 + a10 * b9, a8 * b2 + a9 * b6 + a10 * b10,
            a8 * b3 + a9 * b7 + a10 * b11 + a11)


class NewtonIK:
    """Position IK holding the tool's orientation, for one chain; `solve` per set-point.

    `Chain.ik` solves the same problem with general-purpose batched calls (numpy forward
    kinematics, scipy's rotation vector, `lstsq`): ~0.5-1 ms per call. A path's set-points lie a
    fraction of a millimetre apart, so the previous set-point's joints are an excellent start and
    one or two Newton steps converge; what costs is the overhead of each step, which for a 6-joint
    chain is far larger in numpy's small-array calls than the arithmetic itself. So this class
    works on plain floats:

    - the chain is rewritten once so that every joint turns about its own z axis (joint j's fixed
      part O_j followed by a rotation A_j taking z to its axis: O_j R_a(q) = (O_j A_j) Rz(q) A_j^T,
      the A_j^T folded into the next fixed part), so a joint's rotation mixes two columns;
    - the forward kinematics keeps each joint's position and world axis: the analytic geometric
      Jacobian, rows axis_j x (p - p_j) and axis_j;
    - a damped least-squares step, dq = J^T (J J^T + lambda^2 I)^-1 e, with lambda^2 = |e|^2 +
      LAMBDA0^2 (Levenberg-Marquardt after Sugihara, "Solvability-unconcerned inverse kinematics
      by the Levenberg-Marquardt method", IEEE T-RO 27(5), 2011: quadratic convergence near the
      solution, bounded steps near a singularity), solved by a 6x6 Cholesky factorisation;
    - the forward kinematics of the last solution is kept: the next set-point starts there.

    It converges to the same solution as `Chain.ik` (the same pose, the same branch from the same
    seed; for a 6-axis arm the solution is locally unique, so the joints agree to ~1e-12 rad), with
    the same tolerances and the same UnreachableError when it does not.

    Parameters
    ----------
    chain : Chain
        The kinematic chain.
    compiled : bool
        Solve with the compiled kernel (`frames.ik_kernel`, the same steps) when numba is there and
        no orientation is given; False: on plain floats only.
    """

    def __init__(self, chain: Chain, compiled: bool = True):
        self.chain = chain
        n = chain.dof
        A = [_z_to(np.asarray(a, dtype=float) / np.linalg.norm(a)) for a in chain.axes]
        fixed = []
        prev_inv = np.eye(4)
        for j in range(n):
            Aj = np.eye(4)
            Aj[:3, :3] = A[j]
            fixed.append(_affine(prev_inv @ chain.origins[j] @ Aj))
            prev_inv = np.eye(4)
            prev_inv[:3, :3] = A[j].T
        self._fixed = tuple(fixed)
        # A_j^T per joint (None where the axis is z already): back from the z form to the chain's frames
        self._At = tuple(None if np.allclose(a, np.eye(3)) else tuple(a.T.ravel().tolist()) for a in A)
        self._tool = _affine(prev_inv @ chain.tool)
        self._last: tuple[tuple[float, ...], tuple] | None = None  # (q, its forward kinematics)
        self.iterations = 0  # Newton steps of the last solve (the benchmark reports them)
        self._k = None
        if compiled and jit.enabled():
            from dt_runtime.frames.ik_kernel import IKArrays

            try:
                self._k = IKArrays(self)
                self._k.solve(np.zeros(3), np.zeros(n), 1e-9, 1, MAX_IK_STEP_RAD)  # compiled (or cached) now
            except Exception as exc:  # noqa: BLE001 - numba could not compile it: plain floats
                self._k = None
                jit.disable(f"{type(exc).__name__}: {exc}")

    def _fk(self, q: tuple[float, ...]) -> tuple:
        """TCP transform (3x4) at q, and every joint's position and world axis (the Jacobian)."""
        T: Affine = (1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0)
        joints = []
        for B, qj in zip(self._fixed, q):
            t0, t1, t2, t3, t4, t5, t6, t7, t8, t9, t10, t11 = _mul(T, B)
            joints.append((t3, t7, t11, t2, t6, t10))  # position, axis (the z column)
            c, s = math.cos(qj), math.sin(qj)
            T = (t0 * c + t1 * s, t1 * c - t0 * s, t2, t3, t4 * c + t5 * s, t5 * c - t4 * s, t6, t7,
                 t8 * c + t9 * s, t9 * c - t8 * s, t10, t11)
        return _mul(T, self._tool), joints

    def frames(self, q) -> tuple[Affine, list[Affine]]:
        """The TCP transform at q and every joint's frame before its rotation (as `Chain.frames`).

        Parameters
        ----------
        q : array-like
            (dof,), rad.

        Returns
        -------
        tcp : tuple of float
            3x4 row-major.
        frames : list of tuple of float
            Per joint, 3x4 row-major (position and orientation).
        """
        T: Affine = (1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0)
        out = []
        for B, At, qj in zip(self._fixed, self._At, q):
            C = _mul(T, B)
            t0, t1, t2, t3, t4, t5, t6, t7, t8, t9, t10, t11 = C
            if At is not None:  # the chain's own frame: C A_j^T (A_j took z to the joint's axis)
                out.append(_mul(C, (*At[0:3], 0.0, *At[3:6], 0.0, *At[6:9], 0.0)))
            else:
                out.append(C)
            c, s = math.cos(qj), math.sin(qj)
            T = (t0 * c + t1 * s, t1 * c - t0 * s, t2, t3, t4 * c + t5 * s, t5 * c - t4 * s, t6, t7,
                 t8 * c + t9 * s, t9 * c - t8 * s, t10, t11)
        return _mul(T, self._tool), out

    def pose(self, q) -> tuple[np.ndarray, np.ndarray]:
        """TCP position and orientation at q (as `Chain.pose`).

        Parameters
        ----------
        q : array-like
            (dof,), rad.

        Returns
        -------
        position : ndarray
            (3,), m.
        orientation : ndarray
            (3, 3).
        """
        T, _ = self._fk(tuple(float(x) for x in q))
        return np.array([T[3], T[7], T[11]]), np.array([T[0:3], T[4:7], T[8:11]])

    def solve(self, target: np.ndarray, q_seed: np.ndarray, R: np.ndarray | None = None,
              tol: float = 1e-9, max_iter: int = 50) -> np.ndarray:
        """Joint angles putting the TCP at `target` with orientation R, from q_seed.

        Parameters
        ----------
        target : ndarray
            (3,), m.
        q_seed : ndarray
            (dof,), rad: the start (the previous set-point's joints).
        R : ndarray, optional
            (3, 3) orientation; default the TCP's at q_seed.
        tol : float, optional
            Convergence tolerance on position (m) and orientation (rad).
        max_iter : int, optional
            At most this many Newton steps.

        Returns
        -------
        ndarray
            (dof,), rad.

        Raises
        ------
        UnreachableError
            Naming the target if it does not converge (beyond reach, or a singular pose the damped
            steps cannot leave).
        DataError
            When target or q_seed is not finite or has the wrong length.
        """
        n = self.chain.dof
        try:  # plain floats from here on (numpy's per-call overhead is the cost at this size)
            g = tuple(map(float, target))
            q = tuple(map(float, q_seed))
        except (TypeError, ValueError) as exc:
            raise DataError(f"ik: target must be 3 finite numbers and q_seed {n}, got {target!r}, {q_seed!r}") from exc
        if len(g) != 3 or len(q) != n or not all(map(math.isfinite, g + q)):
            raise DataError(f"ik: target must be 3 finite numbers and q_seed {n}, got {target!r}, {q_seed!r}")
        k = self._k
        if k is not None and R is None:
            from dt_runtime.frames.ik_kernel import OK, UNREACHED

            status, it, ep, er = k.solve(np.array(g), np.array(q), tol, max_iter, MAX_IK_STEP_RAD)
            if status == OK:
                self.iterations = it
                return k.q.copy()
            if status == UNREACHED:
                self._unreachable(g, ep, er, it)
            # a rotation error near pi on the way: solved on plain floats below
        gx, gy, gz = g
        last = self._last
        T, joints = last[1] if last is not None and last[0] == q else self._fk(q)  # the seed's: kept
        Rt = None if R is None else tuple(float(x) for x in np.asarray(R, dtype=float).ravel())
        if Rt is None:
            Rt = (T[0], T[1], T[2], T[4], T[5], T[6], T[8], T[9], T[10])  # the seed's orientation
        r0, r1, r2, r3, r4, r5, r6, r7, r8 = Rt
        it = 0
        while True:
            e0, e1, e2 = gx - T[3], gy - T[7], gz - T[11]
            # orientation error: log(Rt Rq^T)
            q0, q1, q2, q4, q5, q6, q8, q9, q10 = T[0], T[1], T[2], T[4], T[5], T[6], T[8], T[9], T[10]
            e3, e4, e5 = _log((r0 * q0 + r1 * q1 + r2 * q2, r0 * q4 + r1 * q5 + r2 * q6, r0 * q8 + r1 * q9 + r2 * q10,
                               r3 * q0 + r4 * q1 + r5 * q2, r3 * q4 + r4 * q5 + r5 * q6, r3 * q8 + r4 * q9 + r5 * q10,
                               r6 * q0 + r7 * q1 + r8 * q2, r6 * q4 + r7 * q5 + r8 * q6, r6 * q8 + r7 * q9 + r8 * q10))
            ep2, er2 = e0 * e0 + e1 * e1 + e2 * e2, e3 * e3 + e4 * e4 + e5 * e5
            if (ep2 < tol * tol and er2 < tol * tol) or it == max_iter:
                break
            dq = self._step(T, joints, (e0, e1, e2, e3, e4, e5), ep2 + er2 + LAMBDA0 * LAMBDA0)
            norm = math.sqrt(sum(d * d for d in dq))
            f = 1.0 if norm <= MAX_IK_STEP_RAD else MAX_IK_STEP_RAD / norm  # no leaps off the branch
            q = tuple(a + f * d for a, d in zip(q, dq))
            T, joints = self._fk(q)
            it += 1
        self.iterations = it
        self._last = (q, (T, joints))
        ep, er = math.sqrt(ep2), math.sqrt(er2)
        if not (ep < tol and er < tol) and (ep > 1e-6 or er > 1e-5):  # Chain.ik's acceptance, the same
            self._unreachable(g, ep, er, it)
        return np.array(q)

    def _unreachable(self, g: tuple[float, ...], ep: float, er: float, it: int):
        raise UnreachableError(f"target {np.round(np.array(g) * 1e3, 2).tolist()} mm: no joint angles of "
                               f"{self.chain.name} reach it from the seed (residual {ep * 1e3:.3g} mm, "
                               f"{er:.3g} rad after {it} Newton steps)")

    def _step(self, T, joints, e, lam2: float) -> list[float]:
        """dq = J^T (J J^T + lam2 I)^-1 e, J the geometric Jacobian (6 x n) from the joint frames
        (LAPACK's Cholesky solve, dposv: one call, no checks on the way)."""
        px, py, pz = T[3], T[7], T[11]
        cols = []
        for jx, jy, jz, ax, ay, az in joints:  # column j: axis x (p - p_j); axis
            dx, dy, dz = px - jx, py - jy, pz - jz
            cols.append((ay * dz - az * dy, az * dx - ax * dz, ax * dy - ay * dx, ax, ay, az))
        Jt = np.array(cols)  # (n, 6): J transposed
        A = Jt.T @ Jt
        A.flat[::7] += lam2
        _, x, info = _dposv(A, np.array(e), lower=1)
        if info != 0:  # not positive definite: only if the damping underflowed
            raise UnreachableError(f"ik: singular step ({info}) at joints {np.round(T, 4).tolist()}")
        return (Jt @ x).tolist()
