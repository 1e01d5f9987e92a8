"""`NewtonIK`'s solve and the geometric effect's design row as compiled kernels (`common.jit`):
the same arithmetic as `frames.newton_ik.NewtonIK` (forward kinematics with every joint turning
about its own z, damped least-squares steps solved by a 6x6 Cholesky factorisation) and
`twin.corrector.geometric_row`, on preallocated arrays. Tested equal
(tests/unit/test_compiled_law.py)."""
from __future__ import annotations

import math

import numpy as np

from dt_runtime.common.jit import kernel

OK, UNREACHED, BIG_ROTATION = 0, 1, 2  # ik_solve's status: converged; not; a rotation error near pi


@kernel
def _rot_z_mul(T, B, c, s, C, out):  # pragma: no cover - compiled
    """C = T B (3x4 row-major), then out = C Rz(q) (c = cos q, s = sin q)."""
    for r in range(3):
        a0, a1, a2, a3 = T[4 * r], T[4 * r + 1], T[4 * r + 2], T[4 * r + 3]
        C[4 * r] = a0 * B[0] + a1 * B[4] + a2 * B[8]
        C[4 * r + 1] = a0 * B[1] + a1 * B[5] + a2 * B[9]
        C[4 * r + 2] = a0 * B[2] + a1 * B[6] + a2 * B[10]
        C[4 * r + 3] = a0 * B[3] + a1 * B[7] + a2 * B[11] + a3
    for r in range(3):
        t0, t1 = C[4 * r], C[4 * r + 1]
        out[4 * r] = t0 * c + t1 * s
        out[4 * r + 1] = t1 * c - t0 * s
        out[4 * r + 2] = C[4 * r + 2]
        out[4 * r + 3] = C[4 * r + 3]


@kernel
def _mul(a, b, out):  # pragma: no cover - compiled
    """out = a b, both 3x4 row-major affine transforms."""
    for r in range(3):
        a0, a1, a2, a3 = a[4 * r], a[4 * r + 1], a[4 * r + 2], a[4 * r + 3]
        out[4 * r] = a0 * b[0] + a1 * b[4] + a2 * b[8]
        out[4 * r + 1] = a0 * b[1] + a1 * b[5] + a2 * b[9]
        out[4 * r + 2] = a0 * b[2] + a1 * b[6] + a2 * b[10]
        out[4 * r + 3] = a0 * b[3] + a1 * b[7] + a2 * b[11] + a3


@kernel
def fk(fixed, tool, q, T, J, F, C, W):  # pragma: no cover - compiled
    """TCP transform T (12,) at q, every joint's position and world axis J (n, 6), and every joint's
    frame before its rotation in the z form F (n, 12). As `NewtonIK._fk`.

    Parameters
    ----------
    fixed, tool : ndarray
        (n, 12), (12,): the chain in its z form (`IKArrays`).
    q : ndarray
        (n,) rad.
    T, J, F : ndarray
        Written: (12,), (n, 6), (n, 12).
    C, W : ndarray
        (12,) scratch.
    """
    n = fixed.shape[0]
    for i in range(12):
        W[i] = 0.0
    W[0] = W[5] = W[10] = 1.0
    for j in range(n):
        _rot_z_mul(W, fixed[j], math.cos(q[j]), math.sin(q[j]), C, T)
        for i in range(12):
            F[j, i] = C[i]
            W[i] = T[i]
        J[j, 0], J[j, 1], J[j, 2] = C[3], C[7], C[11]
        J[j, 3], J[j, 4], J[j, 5] = C[2], C[6], C[10]
    _mul(W, tool, T)


@kernel
def _log(m0, m1, m2, m3, m4, m5, m6, m7, m8):  # pragma: no cover - compiled
    """Log map of a row-major 3x3 rotation (`newton_ik._log`); ok False above pi - 1e-3."""
    wx, wy, wz = (m7 - m5) * 0.5, (m2 - m6) * 0.5, (m3 - m1) * 0.5
    theta = math.acos(max(-1.0, min(1.0, (m0 + m4 + m8 - 1.0) * 0.5)))
    if theta < 1e-6:
        return wx, wy, wz, True
    if theta > math.pi - 1e-3:
        return 0.0, 0.0, 0.0, False
    f = theta / math.sin(theta)
    return wx * f, wy * f, wz * f, True


@kernel
def ik_solve(fixed, tool, g, q_seed, tol, max_iter, max_step, q, T, J, F, C, W, Jt, A, e, x):  # pragma: no cover
    """Joint angles q (n,) putting the TCP at g (3,) with the seed's orientation, from q_seed
    (`NewtonIK.solve` with R None).

    Parameters
    ----------
    fixed, tool : ndarray
        The chain in its z form (`IKArrays`).
    g, q_seed : ndarray
        (3,) m, (n,) rad.
    tol, max_iter, max_step : float, int, float
        As `NewtonIK.solve`; the largest step's norm (rad).
    q, T, J, F : ndarray
        Written: the joints and their forward kinematics (`fk`).
    C, W, Jt, A, e, x : ndarray
        Scratch: (12,), (12,), (n, 6), (6, 6), (6,), (6,).

    Returns
    -------
    tuple
        (status, Newton steps, position residual m, orientation residual rad): status OK,
        UNREACHED (as `NewtonIK.solve` raises) or BIG_ROTATION (a step's orientation error near pi:
        the caller's general path solves it).
    """
    n = fixed.shape[0]
    for j in range(n):
        q[j] = q_seed[j]
    fk(fixed, tool, q, T, J, F, C, W)
    r0, r1, r2, r3, r4, r5, r6, r7, r8 = T[0], T[1], T[2], T[4], T[5], T[6], T[8], T[9], T[10]
    it = 0
    ep2 = er2 = 0.0
    while True:
        e[0], e[1], e[2] = g[0] - T[3], g[1] - T[7], g[2] - T[11]
        q0, q1, q2, q4, q5, q6, q8, q9, q10 = T[0], T[1], T[2], T[4], T[5], T[6], T[8], T[9], T[10]
        e3, e4, e5, ok = _log(r0 * q0 + r1 * q1 + r2 * q2, r0 * q4 + r1 * q5 + r2 * q6, r0 * q8 + r1 * q9 + r2 * q10,
                              r3 * q0 + r4 * q1 + r5 * q2, r3 * q4 + r4 * q5 + r5 * q6, r3 * q8 + r4 * q9 + r5 * q10,
                              r6 * q0 + r7 * q1 + r8 * q2, r6 * q4 + r7 * q5 + r8 * q6, r6 * q8 + r7 * q9 + r8 * q10)
        if not ok:
            return BIG_ROTATION, it, 0.0, 0.0
        e[3], e[4], e[5] = e3, e4, e5
        ep2 = e[0] * e[0] + e[1] * e[1] + e[2] * e[2]
        er2 = e3 * e3 + e4 * e4 + e5 * e5
        if (ep2 < tol * tol and er2 < tol * tol) or it == max_iter:
            break
        lam2 = ep2 + er2 + 1e-18  # LAMBDA0^2 (newton_ik.LAMBDA0 = 1e-9)
        px, py, pz = T[3], T[7], T[11]
        for j in range(n):  # column j of J: axis x (p - p_j); axis
            dx, dy, dz = px - J[j, 0], py - J[j, 1], pz - J[j, 2]
            ax, ay, az = J[j, 3], J[j, 4], J[j, 5]
            Jt[j, 0], Jt[j, 1], Jt[j, 2] = ay * dz - az * dy, az * dx - ax * dz, ax * dy - ay * dx
            Jt[j, 3], Jt[j, 4], Jt[j, 5] = ax, ay, az
        for a in range(6):  # A = J J^T + lam2 I, lower triangle
            for b in range(a + 1):
                s = 0.0
                for j in range(n):
                    s += Jt[j, a] * Jt[j, b]
                A[a, b] = s + (lam2 if a == b else 0.0)
        for a in range(6):  # Cholesky, in place (lower)
            s = A[a, a]
            for k in range(a):
                s -= A[a, k] * A[a, k]
            if s <= 0.0:
                return UNREACHED, it, math.sqrt(ep2), math.sqrt(er2)
            d = math.sqrt(s)
            A[a, a] = d
            for b in range(a + 1, 6):
                s = A[b, a]
                for k in range(a):
                    s -= A[b, k] * A[a, k]
                A[b, a] = s / d
        for a in range(6):  # L y = e
            s = e[a]
            for k in range(a):
                s -= A[a, k] * x[k]
            x[a] = s / A[a, a]
        for a in range(5, -1, -1):  # L^T x = y
            s = x[a]
            for k in range(a + 1, 6):
                s -= A[k, a] * x[k]
            x[a] = s / A[a, a]
        norm2 = 0.0
        for j in range(n):  # dq = J^T x, kept in C's first n slots... in W? no: in q's step below
            s = 0.0
            for a in range(6):
                s += Jt[j, a] * x[a]
            Jt[j, 0] = s  # column 0 of Jt is not needed again this step
            norm2 += s * s
        norm = math.sqrt(norm2)
        f = 1.0 if norm <= max_step else max_step / norm
        for j in range(n):
            q[j] = q[j] + f * Jt[j, 0]
        fk(fixed, tool, q, T, J, F, C, W)
        it += 1
    ep, er = math.sqrt(ep2), math.sqrt(er2)
    if not (ep < tol and er < tol) and (ep > 1e-6 or er > 1e-5):
        return UNREACHED, it, ep, er
    return OK, it, ep, er


@kernel
def geometric_row(T, F, At, has_At, axes, C, row):  # pragma: no cover - compiled
    """The geometric effect's design row (3, 7 n + 3) at the joints `fk` left T and F for, as
    `twin.corrector.geometric_row`.

    Parameters
    ----------
    T, F : ndarray
        (12,), (n, 12): `fk`'s TCP transform and joint frames (z form).
    At, has_At : ndarray
        (n, 12), (n,): A_j^T as a 3x4 with no translation, used where has_At[j].
    axes : ndarray
        (n, 3): the chain's joint axes.
    C : ndarray
        (12,) scratch.
    row : ndarray
        Written: (3, 7 n + 3).
    """
    n = F.shape[0]
    px, py, pz = T[3], T[7], T[11]
    for j in range(n):
        if has_At[j]:
            _mul(F[j], At[j], C)
        else:
            for i in range(12):
                C[i] = F[j, i]
        a00, a01, a02, x, a10, a11, a12, y, a20, a21, a22, z = (C[0], C[1], C[2], C[3], C[4], C[5], C[6], C[7],
                                                               C[8], C[9], C[10], C[11])
        u, w, t = axes[j, 0], axes[j, 1], axes[j, 2]
        ax, ay, az = a00 * u + a01 * w + a02 * t, a10 * u + a11 * w + a12 * t, a20 * u + a21 * w + a22 * t
        lx, ly, lz = px - x, py - y, pz - z
        row[0, j] = -(ay * lz - az * ly)
        row[1, j] = -(az * lx - ax * lz)
        row[2, j] = -(ax * ly - ay * lx)
        o = n + 6 * j
        row[0, o], row[0, o + 1], row[0, o + 2] = -a00, -a01, -a02
        row[0, o + 3], row[0, o + 4], row[0, o + 5] = ly * a20 - lz * a10, ly * a21 - lz * a11, ly * a22 - lz * a12
        row[1, o], row[1, o + 1], row[1, o + 2] = -a10, -a11, -a12
        row[1, o + 3], row[1, o + 4], row[1, o + 5] = lz * a00 - lx * a20, lz * a01 - lx * a21, lz * a02 - lx * a22
        row[2, o], row[2, o + 1], row[2, o + 2] = -a20, -a21, -a22
        row[2, o + 3], row[2, o + 4], row[2, o + 5] = lx * a10 - ly * a00, lx * a11 - ly * a01, lx * a12 - ly * a02
    o = 7 * n
    row[0, o], row[0, o + 1], row[0, o + 2] = -T[0], -T[1], -T[2]
    row[1, o], row[1, o + 1], row[1, o + 2] = -T[4], -T[5], -T[6]
    row[2, o], row[2, o + 1], row[2, o + 2] = -T[8], -T[9], -T[10]


class IKArrays:
    """A `NewtonIK`'s chain as the kernels' arrays, with their scratch.

    Parameters
    ----------
    ik : NewtonIK
        The solver whose chain (in its z form) the kernels run.
    """

    def __init__(self, ik):
        n = ik.chain.dof
        self.n = n
        self.fixed = np.array(ik._fixed, dtype=float).reshape(n, 12)
        self.tool = np.array(ik._tool, dtype=float)
        self.At = np.zeros((n, 12))
        self.has_At = np.zeros(n, dtype=np.bool_)
        for j, a in enumerate(ik._At):
            if a is not None:
                self.At[j] = (*a[0:3], 0.0, *a[3:6], 0.0, *a[6:9], 0.0)
                self.has_At[j] = True
        self.axes = np.ascontiguousarray(np.asarray(ik.chain.axes, dtype=float).reshape(n, 3))
        self.q, self.T, self.J, self.F = np.empty(n), np.empty(12), np.empty((n, 6)), np.empty((n, 12))
        self.C, self.W, self.Jt, self.A = np.empty(12), np.empty(12), np.empty((n, 6)), np.empty((6, 6))
        self.e, self.x, self.row = np.empty(6), np.empty(6), np.empty((3, 7 * n + 3))

    def solve(self, g: np.ndarray, q_seed: np.ndarray, tol: float, max_iter: int, max_step: float) -> tuple:
        """`ik_solve` on these arrays; the joints in `self.q`, their forward kinematics in `self.T`,
        `self.F`.

        Parameters
        ----------
        g, q_seed : ndarray
            (3,) m target, (n,) rad seed.
        tol, max_iter, max_step : float, int, float
            As `ik_solve`.

        Returns
        -------
        tuple
            (status, steps, position residual m, orientation residual rad).
        """
        return ik_solve(self.fixed, self.tool, g, q_seed, tol, max_iter, max_step, self.q, self.T, self.J, self.F,
                        self.C, self.W, self.Jt, self.A, self.e, self.x)
