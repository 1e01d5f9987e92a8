"""The one correction law: a target (m, robot frame) -> the command that reaches it, the expanded
uncertainty (95 %) of the position it reaches (Eq. 11 there) and the calibrated-volume flag.

Every place a command or set-point is corrected calls `Corrector.correct`: the twin's API
(`Twin.correct`), point programs, paths (offline and streamed), the bus correction server and the
daemon's tick (behind the bounds of `twin.bounds`). How it is computed fast: docs/streaming.md.
"""
from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from scipy import special, stats

from dt_runtime.common import jit
from dt_runtime.frames.ik_kernel import OK as IK_OK
from dt_runtime.frames.ik_kernel import IKArrays
from dt_runtime.frames.newton_ik import NewtonIK
from dt_runtime.metrology.uncertainty import Budget
from dt_runtime.models.gp_kernel import GPArrays
from dt_runtime.twin.conditions import Conditions, command_inputs
from dt_runtime.twin.law_kernel import GP_X, fixed_point_geometric, fixed_point_gp
from dt_runtime.twin.twin import Correction, Twin

P95 = 0.975  # two-sided 95 % coverage: the t quantile at 0.5 + 0.95 / 2 (metrology.uncertainty)


@dataclass(frozen=True)
class Setpoint:
    """A corrected target.

    Attributes
    ----------
    command : ndarray
        (3,) m, robot frame: solves c - e_hat(c, v) = target.
    U : ndarray
        (3,) m, expanded uncertainty (95 %) of the position reached, per GL axis: Eq. 11 there times
        the twin's held-out conformal factor (`Twin.stated_U`).
    inside : bool
        The command lies in the calibrated volume (the DOE's hull plus its margin).
    distance_m : float
        Signed distance of the command to the DOE hull (m, < 0 inside; NaN for a twin without one).
    joints : ndarray or None
        The command's joints (rad) when the map reads them: the next set-point's IK starts there.
    sigma : ndarray
        (3,) m, e_LT_hat's standard uncertainty at the command (GL axes): Eq. 11's model term.
    """

    command: np.ndarray
    U: np.ndarray
    inside: bool
    distance_m: float
    joints: np.ndarray | None
    sigma: np.ndarray

    def correction(self, target: np.ndarray, budget: Budget | None = None) -> Correction:
        """This set-point as `Twin.correct` returns it.

        Parameters
        ----------
        target : ndarray
            (3,) m, the target that was corrected.
        budget : Budget or None
            The labelled Eq. 11 budget at the command (`Corrector.budget`), if wanted.

        Returns
        -------
        Correction
        """
        return Correction(np.asarray(target, dtype=float), self.command, self.U, self.inside, self.distance_m, budget)


class Corrector:
    """The correction law of one twin, with what can be precomputed taken out of the per-target
    work (docs/streaming.md, "One correction law").

    Parameters
    ----------
    twin : Twin
        The calibrated twin.
    iters : int
        At most this many fixed-point steps after the first evaluation.
    tol : float
        The fixed point stops when the command moves by less than this (m, per axis).
    predictor : MapPredictor or None
        The e_LT map's per-command predictor to use (it carries a thermal map's structure
        temperature from command to command); None: one of its own.
    compiled : bool
        Run the fixed point as one compiled call (`twin.law_kernel`) where it applies (a shared GP
        of TCP and speed; geometric terms + a shared GP or none) and numba is there; False: the
        numpy path only (the same numbers; `benchmarks.setpoint` times both).

    Attributes
    ----------
    evaluations : int
        Map evaluations made so far (either path): what a warm start saves.
    compiled : bool
        Whether the compiled path is in use.
    """

    def __init__(self, twin: Twin, iters: int = 6, tol: float = 1e-8, predictor=None, compiled: bool = True):
        self.twin, self.iters, self.tol = twin, iters, tol
        self.evaluations = 0
        self._Rt = twin.T_rdk.R.T  # GL axes -> robot axes
        self._map = twin.e_lt.predictor() if predictor is None else predictor
        self.needs = self._map.needs
        gp = twin.e_lt.gp_.predictor() if self._map.plain and twin.e_lt.gp_ is not None else None
        self._gp = gp if gp is not None and gp.shared else None
        self._chain = twin.e_lt.chain() if "joints" in self.needs else None
        self._newton = NewtonIK(self._chain, compiled=compiled) if self._chain is not None else None
        self._ik = self._newton.solve if self._newton is not None else None
        # A map of geometric terms (+ GP): its design row on floats (`geometric_row`), no Inputs
        model = twin.e_lt
        self._geo = (self._newton is not None and tuple(model.effects) == ("geometric",) and not model.nuisance
                     and model.theta_.size > 0 and model.gp_inputs in ("tcp_speed", "tcp", "joints", "none"))
        if self._geo:
            assert self._chain is not None
            self._theta, self._cov = model.theta_, model.theta_cov_
            g = model.gp_.predictor() if model.gp_ is not None else None
            self._geo_gp = g
            self._geo_shared = g is not None and g.shared
        self._x = np.empty(4)
        vol = twin.volume
        self._normals = None if vol is None else np.ascontiguousarray(vol.normals)
        self._offsets = None if vol is None else vol.offsets
        self._margin = 0.0 if vol is None else vol.margin_m
        pu = twin.position_u
        # the held-out conformal factor (`metrology.conformal`): every U this law states is scaled by it
        self._cf = twin.conformal.factor.tolist()
        self._U_global = twin.conformal.factor * twin.uncertainty.tcp_c.U
        self._pu = pu
        if pu is not None:
            us = np.array([c.u for c in pu.rest.components])
            dofs = np.array([c.dof for c in pu.rest.components])
            # Welch-Satterthwaite's terms u^4 / nu (metrology.uncertainty), the fixed ones summed once
            self._fast_u = bool(np.all(dofs > 0) and pu.model_dof > 0 and pu.extrapolation_dof > 0)
            if self._fast_u:
                self._rest_u2 = np.sum(us ** 2, axis=0).tolist()
                u4 = np.where(np.isfinite(dofs)[:, None], us ** 4 / dofs[:, None], 0.0)
                self._rest_u4 = np.sum(u4, axis=0).tolist()
                self._lam, self._kappa = pu.model_scale.tolist(), pu.extrapolation_scale.tolist()
                self._w_m = 1.0 / pu.model_dof if math.isfinite(pu.model_dof) else 0.0  # 1 / nu
                self._w_k = 1.0 / pu.extrapolation_dof if math.isfinite(pu.extrapolation_dof) else 0.0
        self._k_inf = float(stats.norm.ppf(P95))
        self.compiled = False
        if compiled and jit.enabled():  # the kinds it runs carry no state between commands (no thermal map)
            self._compile()

    # --- the compiled path (twin.law_kernel) ----------------------------------------------------
    def _compile(self) -> None:
        """Arrays and scratch of the compiled fixed point, when the map is one it runs; the kernels
        compiled (or loaded from numba's cache) now, not at the first set-point. A failure turns
        the compiled kernels off (`common.jit.disable`): the numpy path runs."""
        model = self.twin.e_lt
        try:
            self._ga: GPArrays | None = None
            if self._gp is not None:
                self._ga = GPArrays(self._gp)
                kind = "gp"
            elif self._geo and (self._geo_gp is None or self._geo_shared) and model.gp_inputs in (*GP_X, "none"):
                assert self._newton is not None
                self._ia = IKArrays(self._newton)
                self._ga = GPArrays(self._geo_gp) if self._geo_gp is not None else None
                self._gp_x = GP_X.get(model.gp_inputs, 0)
                self._geo_theta = np.ascontiguousarray(self._theta, dtype=float)
                self._geo_cov = np.ascontiguousarray(self._cov, dtype=float)
                self._geo_x = np.empty(max(4, self._ia.n))
                self._qs, self._mg, self._mgp = np.empty(self._ia.n), np.empty(3), np.empty(3)
                self._sig2 = np.empty(3)
                kind = "geometric"
            else:
                return
            self._Rt_c = np.ascontiguousarray(self._Rt, dtype=float)
            self._c0 = np.zeros(4)
            self._kind = kind
            self.compiled = True
            self._warm_up()
        except Exception as exc:  # noqa: BLE001 - numba could not compile or run it: the numpy path
            self.compiled = False
            jit.disable(f"{type(exc).__name__}: {exc}")

    def _warm_up(self) -> None:
        """One compiled correction at a point of the DOE (compiles the kernels, or loads them from
        numba's cache) and its U; its count undone: the first set-point costs what the others do."""
        x = self._ga.xm[:3].copy() if self._ga is not None and self._ga.d >= 3 else np.array([0.9, 0.0, 0.55])
        q = None
        if self._kind == "geometric":
            assert self._chain is not None
            q = np.zeros(self._chain.dof)
        r = self._fixed_point(x, 0.25, q, None)
        if r is not None:  # U's first evaluation (scipy's t quantile) paid here too
            self._setpoint(*r)
        self.evaluations = 0

    def _fixed_point(self, target: np.ndarray, v: float, q0: np.ndarray | None, warm: np.ndarray | None,
                     uncertainty: bool = True):
        """(command, sigma or None without `uncertainty`, joints) by the compiled fixed point, or
        None where the general path must answer (a joint-space map without joints; the IK did not
        converge: its error is the general path's)."""
        c0 = self._c0
        if warm is None:
            c0[:3], c0[3] = target, 0.0
        else:
            c0[:3], c0[3] = target + warm, 1.0
        c = np.empty(3)
        a = self._ga
        if self._kind == "gp":
            assert a is not None
            self.evaluations += fixed_point_gp(target, v, self._Rt_c, c0, self.iters, self.tol, self._x, a.Xb, a.xm,
                                               a.xs, a.nh, a.sf2, a.m0, a.ys, a.alpha, a.z, a.acc, a.K, a.m, c)
            return c, a.std() if uncertainty else None, None
        if q0 is None:
            return None
        k, g = self._ia, a if a is not None else _NO_GP
        n, status = fixed_point_geometric(
            target, v, self._Rt_c, c0, q0, self.iters, self.tol, self._gp_x, a is not None, self._geo_theta,
            self._geo_cov, self._geo_x, k.fixed, k.tool, k.At, k.has_At, k.axes, k.q, k.T, k.J, k.F, k.C, k.W, k.Jt,
            k.A, k.e, k.x, k.row, self._qs, self._mg, g.Xb, g.xm, g.xs, g.nh, g.sf2, g.m0, g.ys, g.alpha, g.z, g.acc,
            g.K, g.m, c, self._sig2)
        self.evaluations += n
        if status != IK_OK:
            return None
        if not uncertainty:
            return c, None, k.q.copy()
        var = self._sig2 if a is None else self._sig2 + a.std() ** 2
        return c, np.sqrt(np.maximum(var, 0.0)), k.q.copy()

    def _lt(self, c: np.ndarray, v: float, cond: Conditions | None, q_seed):
        """e_LT_hat's mean at c (GL axes), what its std needs (`_std`), and c's joints."""
        if self._gp is not None:
            x = self._x
            x[:3] = c
            x[3] = v
            m, K = self._gp.mean_kernel(x)
            return m, K, None
        if self._geo and cond is not None and cond.joints is not None:
            return self._lt_geometric(c, v, cond.joints if q_seed is None else q_seed)
        inp, q = command_inputs(c, v, self.needs, cond, self._chain, q_seed, self._ik)
        m, s = self._map(inp)
        return m, s, q

    def _lt_geometric(self, c: np.ndarray, v: float, q_seed):
        """`MapPredictor` on a geometric + GP map, for the command's row only (the geometric
        terms read no history): the joints, the design row, A theta plus the GP's mean."""
        assert self._newton is not None
        q = self._newton.solve(c, q_seed)
        A = geometric_row(self._newton, q)
        m = A @ self._theta
        g = self._geo_gp
        if g is None:
            return m, (A, None), q
        if self._geo_shared:
            if self.twin.e_lt.gp_inputs == "tcp_speed":
                x = self._x
                x[:3] = c
                x[3] = v
            else:
                x = q if self.twin.e_lt.gp_inputs == "joints" else np.asarray(c, dtype=float)
            mg, K = g.mean_kernel(x)
            return m + mg, (A, K), q
        xg = {"tcp_speed": np.array([c[0], c[1], c[2], v]), "tcp": np.asarray(c, dtype=float)}.get(
            self.twin.e_lt.gp_inputs, q)
        mg, sg = g(xg)
        return m + mg, (A, sg), q

    def _std(self, state) -> np.ndarray:
        """The std where `_lt` left `state`."""
        if self._gp is not None:
            return self._gp.std_of(state)
        if not (self._geo and isinstance(state, tuple)):
            return state
        A, gs = state
        var = np.einsum("ap,pq,aq->a", A, self._cov, A)  # as MapPredictor
        if gs is not None:
            g = self._geo_gp
            var = var + (g.std_of(gs) if g is not None and self._geo_shared else gs) ** 2
        return np.sqrt(np.maximum(var, 0.0))

    def correct(self, target: np.ndarray, v: float, cond: Conditions | None = None,
                warm: np.ndarray | None = None, uncertainty: bool = True) -> Setpoint:
        """The corrected set-point for a target.

        Parameters
        ----------
        target : ndarray
            (3,) m, robot frame.
        v : float
            Speed, m/s.
        cond : Conditions or None
            What the maps read beside the command (`Twin.needs`).
        warm : ndarray or None
            The previous set-point's correction (command - target, m): the fixed point starts
            there instead of at the target. Along a path the correction changes by micrometres
            between set-points, so it converges in one or two evaluations of the map instead of
            four or five (the same fixed point, to `tol`).
        uncertainty : bool
            False: the command (and the volume flag) only, U and sigma NaN: a streamed path sends
            commands, and the GP's variance reads a (U, U) matrix per output, more memory than
            stays in the cache between two set-points (`follow`).

        Returns
        -------
        Setpoint
        """
        target = np.asarray(target, dtype=float)
        if self.compiled:
            q0 = None if cond is None or cond.joints is None else np.asarray(cond.joints, dtype=float)
            r = self._fixed_point(target, float(v), q0, None if warm is None else np.asarray(warm, dtype=float),
                                  uncertainty)
            if r is not None:
                return self._setpoint(*r)
        Rt, tol = self._Rt, self.tol
        if warm is None:
            m, s, q = self._lt(target, v, cond, None)
            self.evaluations += 1
            c = target + Rt @ m
        else:
            c, q = target + warm, None
        for _ in range(self.iters):  # c_{n+1} = target + e_hat(c_n): the map contracts (grad e << 1)
            m, s, q = self._lt(c, v, cond, q)
            self.evaluations += 1
            c_new = target + Rt @ m
            done = np.abs(c_new - c).max() < tol
            c = c_new
            if done:
                break
        return self._setpoint(c, self._std(s) if uncertainty else None, q)

    def _setpoint(self, c: np.ndarray, sigma: np.ndarray | None, q: np.ndarray | None) -> Setpoint:
        """The set-point at command c: its distance to the DOE hull, U there (NaN without sigma),
        the volume flag."""
        if self._normals is None:
            dist = float("nan")
        else:
            dist = float(np.max(self._normals @ c + self._offsets))
        inside = self._normals is None or dist <= self._margin
        if sigma is None:
            return Setpoint(c, np.full(3, np.nan), inside, dist, q, np.full(3, np.nan))
        return Setpoint(c, self._expanded(sigma, dist), inside, dist, q, sigma)

    def budget(self, sp: Setpoint) -> Budget | None:
        """The labelled Eq. 11 budget at a corrected set-point (None for a twin without one).

        Parameters
        ----------
        sp : Setpoint
            What `correct` returned.

        Returns
        -------
        Budget or None
        """
        if self._pu is None:
            return None
        d = sp.distance_m
        return self._pu.budget_at(sp.sigma, max(d if math.isfinite(d) else 0.0, 0.0))

    def follow(self, times: np.ndarray, speeds: np.ndarray,
               joints: np.ndarray | None = None) -> Callable[[np.ndarray, float], np.ndarray]:
        """The law along a streamed path: (target m, t s) -> command m.

        Parameters
        ----------
        times : ndarray
            (n,) s, when each set-point of the path is meant.
        speeds : ndarray
            (n,) m/s, the programmed speed of each set-point.
        joints : ndarray or None
            Where the arm stands at the start (rad), for a map that reads joints: carried from
            set-point to set-point after.

        Returns
        -------
        callable
            Each call corrects at the speed of the set-point meant for t, warm-started from the
            previous call's correction; the command only (`correct`'s uncertainty=False).
        """
        last = len(times) - 1
        q = None if joints is None else np.asarray(joints, dtype=float)
        warm: np.ndarray | None = None

        def correct_one(target: np.ndarray, t: float) -> np.ndarray:
            nonlocal q, warm
            k = min(int(np.searchsorted(times, t - 1e-9)), last)
            r = self.correct(target, float(speeds[k]), None if q is None else Conditions(joints=q), warm,
                             uncertainty=False)
            if r.joints is not None:
                q = r.joints
            warm = r.command - target
            return r.command

        return correct_one

    def _expanded(self, sigma: np.ndarray, dist: float) -> np.ndarray:
        """The stated U at the position: the conformal factor times Eq. 11's U
        (`Twin.stated_U(PositionUncertainty.budget_at(...))`), on floats."""
        pu = self._pu
        if pu is None:
            return self._U_global
        d = max(dist if math.isfinite(dist) else 0.0, 0.0)
        if not self._fast_u:  # a zero degree of freedom somewhere: the budget's own arithmetic
            return self.twin.stated_U(pu.budget_at(sigma, d))
        U = []  # per axis on plain floats: three numbers do not pay numpy's per-call overhead
        for r2, r4, lam, kap, sg, cf in zip(self._rest_u2, self._rest_u4, self._lam, self._kappa, sigma.tolist(),
                                            self._cf):
            um2, ue2 = (lam * sg) ** 2, (kap * d) ** 2
            uc2 = r2 + um2 + ue2
            den = r4 + um2 * um2 * self._w_m + ue2 * ue2 * self._w_k
            # nu_eff = u_c^4 / sum(u_i^4 / nu_i); k from the t quantile (what stats.t.ppf evaluates)
            k = special.stdtrit(max(uc2 * uc2 / den, 1.0), P95) if den > 0 else self._k_inf
            U.append(cf * k * math.sqrt(uc2))
        return np.array(U)


class _NoGP:
    """Stand-in arrays for a geometric map without a GP (the kernel's GP arguments, unused)."""

    Xb, nh, alpha, K = np.zeros((1, 1)), np.zeros((1, 1)), np.zeros((1, 1)), np.zeros((1, 1))
    xm = xs = sf2 = m0 = ys = z = acc = m = np.zeros(1)


_NO_GP = _NoGP()


def geometric_row(ik: NewtonIK, q: np.ndarray) -> np.ndarray:
    """The geometric effect's regressors (`models.effects.geometric.Geometric.regressors`) for one
    joint vector (3, 7 dof + 3), on floats: -J (dof columns), per joint frame -R_j (its
    translation) and [lever]x R_j (its rotation), then -R_tcp (the tool's translation); tested
    equal (tests/unit/test_setpoint.py).

    Parameters
    ----------
    ik : NewtonIK
        The solver of the map's chain (its forward kinematics and joint frames).
    q : ndarray
        (dof,) rad, the joint angles.

    Returns
    -------
    ndarray
        (3, 7 dof + 3): one row per robot axis.
    """
    T, frames = ik.frames(q)
    px, py, pz = T[3], T[7], T[11]
    r0: list[float] = []
    r1: list[float] = []
    r2: list[float] = []
    f0: list[float] = []
    f1: list[float] = []
    f2: list[float] = []
    for (a00, a01, a02, x, a10, a11, a12, y, a20, a21, a22, z), (u, w, t) in zip(frames, ik.chain.axes):
        ax, ay, az = a00 * u + a01 * w + a02 * t, a10 * u + a11 * w + a12 * t, a20 * u + a21 * w + a22 * t
        lx, ly, lz = px - x, py - y, pz - z
        r0.append(-(ay * lz - az * ly))
        r1.append(-(az * lx - ax * lz))
        r2.append(-(ax * ly - ay * lx))
        f0 += (-a00, -a01, -a02, ly * a20 - lz * a10, ly * a21 - lz * a11, ly * a22 - lz * a12)
        f1 += (-a10, -a11, -a12, lz * a00 - lx * a20, lz * a01 - lx * a21, lz * a02 - lx * a22)
        f2 += (-a20, -a21, -a22, lx * a10 - ly * a00, lx * a11 - ly * a01, lx * a12 - ly * a02)
    return np.array([r0 + f0 + [-T[0], -T[1], -T[2]], r1 + f1 + [-T[4], -T[5], -T[6]],
                     r2 + f2 + [-T[8], -T[9], -T[10]]])
