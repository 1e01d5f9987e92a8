"""The correction law's fixed point as one compiled call per set-point (`common.jit`), for the two
kinds of map the streaming loop corrects with: a GP on the TCP and speed (the paper's), and
geometric terms + a GP (a joint-space map: the IK of every command). `Corrector.correct` calls it
when it applies and keeps its numpy path for everything else; both are held to the plain law
(tests/unit/test_compiled_law.py, tests/unit/test_corrector.py)."""
from __future__ import annotations

from dt_runtime.common.jit import kernel
from dt_runtime.frames.ik_kernel import OK, geometric_row, ik_solve
from dt_runtime.frames.kinematics import MAX_IK_STEP_RAD
from dt_runtime.models.gp_kernel import gp_mean

GP_X = {"tcp_speed": 0, "tcp": 1, "joints": 2}  # what the GP of a geometric map reads


@kernel
def fixed_point_gp(target, v, Rt, c0, iters, tol, x, Xb, xm, xs, nh, sf2, m0, ys, alpha, z, acc, K, m,
                   c):  # pragma: no cover - compiled
    """c - R^T e_hat(c, v) = target by fixed-point steps on a GP of (TCP, speed) (`Corrector.correct`):
    from c0 (the target, or the target plus the previous set-point's correction: then no first
    evaluation at the target, `first` below). Leaves the command in c, the last evaluation's
    kernel vectors in K.

    Parameters
    ----------
    target, v, Rt : ndarray, float, ndarray
        (3,) m robot frame, m/s, GL axes -> robot axes.
    c0 : ndarray
        (4,): the start (3,) and a flag (1.0: a warm start, the first evaluation is skipped).
    iters, tol : int, float
        As `Corrector`.
    x : ndarray
        (4,) scratch: the GP's input.
    Xb, xm, xs, nh, sf2, m0, ys, alpha, z, acc, K, m : ndarray
        `models.gp_kernel.gp_mean`'s.
    c : ndarray
        Written: (3,) the command.

    Returns
    -------
    int
        The map evaluations made.
    """
    n_eval = 0
    for i in range(3):
        c[i] = c0[i]
    x[3] = v
    for it in range(iters + 1):
        if it == 0 and c0[3] != 0.0:  # warm: c0[3] flags that c0 is a warm start
            continue
        x[0], x[1], x[2] = c[0], c[1], c[2]
        gp_mean(x, Xb, xm, xs, nh, sf2, m0, ys, alpha, z, acc, K, m)
        n_eval += 1
        big = 0.0
        for i in range(3):
            cn = target[i] + (Rt[i, 0] * m[0] + Rt[i, 1] * m[1] + Rt[i, 2] * m[2])
            big = max(big, abs(cn - c[i]))
            c[i] = cn
        if it > 0 and big < tol:
            break
    return n_eval


@kernel
def fixed_point_geometric(target, v, Rt, c0, q0, iters, tol, gp_x, has_gp, theta, cov, x,
                          fixed, tool, At, has_At, axes, q, T, J, F, C, W, Jt, A, e, xs6, row, qs, mg,
                          Xb, xm, xsc, nh, sf2, m0, ys, alpha, z, acc, K, mgp,
                          c, sig2):  # pragma: no cover - compiled
    """The same fixed point on a geometric + GP map: per evaluation the command's joints (the IK
    from the previous evaluation's, the first from q0), the design row A(q), A theta plus the
    GP's mean. Leaves the command in c, its joints in q and Eq. 11's model variance per axis in
    sig2 (A cov A^T's diagonal, the GP's variance added by the caller).

    Parameters
    ----------
    target, v, Rt, c0, iters, tol : as `fixed_point_gp`
    q0 : ndarray
        (n,) rad: the joints the first IK starts from (the conditions').
    gp_x, has_gp : int, bool
        What the GP reads (`GP_X`), whether there is one.
    theta, cov : ndarray
        The geometric parameters and their covariance.
    x : ndarray
        Scratch: the GP's input (at least max(4, n)).
    fixed, tool, At, has_At, axes, q, T, J, F, C, W, Jt, A, e, xs6, row : ndarray
        `frames.ik_kernel.IKArrays`' (q, the joints, written).
    qs, mg : ndarray
        (n,), (3,) scratch.
    Xb, xm, xsc, nh, sf2, m0, ys, alpha, z, acc, K, mgp : ndarray
        `models.gp_kernel.gp_mean`'s (unused without a GP).
    c, sig2 : ndarray
        Written: (3,) the command, (3,) the geometric terms' variance per axis.

    Returns
    -------
    tuple
        (map evaluations, IK status: `ik_kernel.OK` or why the caller's general path must solve it).
    """
    n = fixed.shape[0]
    n_eval = 0
    for i in range(3):
        c[i] = c0[i]
    for j in range(n):
        qs[j] = q0[j]
    for it in range(iters + 1):
        if it == 0 and c0[3] != 0.0:
            continue
        # NewtonIK.solve's defaults: tol 1e-9, 50 steps; T and F are the forward kinematics at q
        status, _, _, _ = ik_solve(fixed, tool, c, qs, 1e-9, 50, MAX_IK_STEP_RAD, q, T, J, F, C, W, Jt, A, e, xs6)
        if status != OK:
            return n_eval, status
        geometric_row(T, F, At, has_At, axes, C, row)
        p = row.shape[1]
        for a in range(3):
            s = 0.0
            for k in range(p):
                s += row[a, k] * theta[k]
            mg[a] = s
        if has_gp:
            if gp_x == 2:
                for j in range(n):
                    x[j] = q[j]
            else:
                x[0], x[1], x[2] = c[0], c[1], c[2]
                if gp_x == 0:
                    x[3] = v
            gp_mean(x, Xb, xm, xsc, nh, sf2, m0, ys, alpha, z, acc, K, mgp)
            for a in range(3):
                mg[a] += mgp[a]
        n_eval += 1
        for j in range(n):
            qs[j] = q[j]
        big = 0.0
        for i in range(3):
            cn = target[i] + (Rt[i, 0] * mg[0] + Rt[i, 1] * mg[1] + Rt[i, 2] * mg[2])
            big = max(big, abs(cn - c[i]))
            c[i] = cn
        if it > 0 and big < tol:
            break
    p = row.shape[1]
    for a in range(3):
        s = 0.0
        for k in range(p):
            t = 0.0
            for b in range(p):
                t += cov[k, b] * row[a, b]
            s += row[a, k] * t
        sig2[a] = s
    return n_eval, OK
