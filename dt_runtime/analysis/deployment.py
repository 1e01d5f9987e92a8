"""A model deployed to a new session: the session's registration refitted on a few reference poses
with the model's correction applied, its uncertainty carried into Eq. 17, and every other row
scored after it (docs/campaigns.md, "Deploying to a new session").
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from dt_kernel.errors import DataError
from dt_runtime.frames.registration import RigidUncertainty, rigid_jacobian, rigid_uncertainty
from dt_runtime.measurements.dataset import Dataset
from dt_runtime.models.effects import as_inputs
from dt_runtime.models.hybrid import Design, HybridModel

DEFAULT_REFERENCE = 10  # reference poses per session: a few minutes of a tracker at the start of a day
MIN_TEST = 5  # rows left after the reference poses, else the session is not scored after registration
ABSOLUTE_T_S = 1e9  # s: a time this large is Unix time (after 2001-09-09): absolute, comparable across files
S_PER_H = 3600.0


@dataclass(frozen=True)
class Registered:
    """One session registered on its reference poses.

    Attributes
    ----------
    reference : ndarray
        (n,) bool: the rows of the reference poses (the registration saw them; not scored).
    fit : RigidUncertainty
        The refitted registration (measured -> commanded minus the predicted error) and its covariance.
    residual : ndarray
        (n, 3) m: every row's residual after the registration, e - e_hat.
    u : ndarray
        (n, 3) m: the registration's standard uncertainty at each row.
    """

    reference: np.ndarray
    fit: RigidUncertainty
    residual: np.ndarray
    u: np.ndarray

    @property
    def test(self) -> np.ndarray:
        """(n,) bool: the rows scored (not used by the registration)."""
        return ~self.reference


def reference_rows(points: np.ndarray, k: int) -> np.ndarray:
    """The rows of k reference poses spread over the session's points: farthest-point sampling over
    the distinct commanded points (to 1 um), from the one farthest from their centroid; every
    replicate row of a chosen point is a reference row.

    Parameters
    ----------
    points : ndarray
        (n, 3) commanded points, m.
    k : int
        Reference poses wanted (at least 3).

    Returns
    -------
    ndarray
        (n,) bool.

    Raises
    ------
    DataError
        Fewer than k + MIN_TEST distinct points, or k < 3.
    """
    if k < 3:
        raise DataError(f"--reference {k}: a registration needs at least 3 reference poses")
    P = np.asarray(points, dtype=float)
    keys, inverse = np.unique(np.round(P / 1e-6).astype(np.int64), axis=0, return_inverse=True)
    inverse = inverse.reshape(-1)
    if len(keys) < k + MIN_TEST:
        raise DataError(f"{len(keys)} distinct points: {k} reference poses leave fewer than {MIN_TEST} to score "
                        "the registration on")
    U = keys * 1e-6
    chosen = [int(np.argmax(np.sum((U - U.mean(axis=0)) ** 2, axis=1)))]
    d = np.sum((U - U[chosen[0]]) ** 2, axis=1)
    while len(chosen) < k:
        nxt = int(np.argmax(d))
        chosen.append(nxt)
        d = np.minimum(d, np.sum((U - U[nxt]) ** 2, axis=1))
    return np.isin(inverse, chosen)


def register(measured: np.ndarray, residual: np.ndarray, reference: np.ndarray) -> Registered:
    """The session's registration refitted on its reference rows against the commanded points
    minus the model's prediction (as `reregister.reregistered` on all rows), applied to every row.

    Parameters
    ----------
    measured : ndarray
        (n, 3) measured points in the data's frame, m.
    residual : ndarray
        (n, 3) the model's residual e - e_hat under the data's own registration, m.
    reference : ndarray
        (n,) bool, the reference rows (`reference_rows`).

    Returns
    -------
    Registered
    """
    m = np.asarray(measured, dtype=float)
    target = m + np.asarray(residual, dtype=float)  # c - e_hat
    ref = np.asarray(reference, dtype=bool)
    fit = rigid_uncertainty(m[ref], target[ref])
    return Registered(ref, fit, target - fit.T.apply(m), fit.at(m))


def combined_dof(u_a: np.ndarray, dof_a, u_b: np.ndarray, dof_b: float) -> np.ndarray:
    """Welch-Satterthwaite degrees of freedom of sqrt(u_a^2 + u_b^2), elementwise.

    Parameters
    ----------
    u_a : ndarray
        Standard uncertainties, m.
    dof_a : ndarray or float
        Their degrees of freedom (inf allowed).
    u_b : ndarray
        The other component, m.
    dof_b : float
        Its degrees of freedom.

    Returns
    -------
    ndarray
    """
    a2, b2 = np.asarray(u_a, dtype=float) ** 2, np.asarray(u_b, dtype=float) ** 2
    with np.errstate(divide="ignore", invalid="ignore"):
        den = a2 ** 2 / np.asarray(dof_a, dtype=float) + b2 ** 2 / float(dof_b)
        nu = np.where(den > 0, (a2 + b2) ** 2 / den, np.inf)
    return np.maximum(nu, 1.0)


def time_terms(m: HybridModel, ds: Dataset, new: np.ndarray) -> tuple[Design | None, dict | None]:
    """How a map's time terms (`HybridModel.time_effects`: a drift) are evaluated on the rows of
    sessions it was not trained on (`new`).

    With absolute time in both the training data (the model's time origin) and these rows (t of at
    least ABSOLUTE_T_S: Unix time), the terms are evaluated at that time; rows beyond the training's
    time are extrapolations, counted (their stated u grows with the term's covariance). Without it,
    a time term is a nuisance of the session it was found in: it is not applied to the new rows
    (their `t` counts from another origin, and a term evaluated there would claim a drift no clock
    measured).

    Parameters
    ----------
    m : HybridModel
        The fitted map.
    ds : Dataset
        The data compared.
    new : ndarray
        (n,) bool, the rows of sessions the map was not trained on.

    Returns
    -------
    design : Design or None
        The regressors to predict with (the time terms zeroed on the new rows), or None: as is.
    note : dict or None
        What was done, in words (`text`) and figures; None when the map has no time term or no
        row is new.
    """
    effects = m.time_effects()
    new = np.asarray(new, dtype=bool)
    if not effects or not new.any():
        return None, None
    t0 = getattr(m, "t_origin_", None)
    t_new = None if ds.t is None else ds.t[new]
    names = ", ".join(effects)
    if t0 is not None and t0 >= ABSOLUTE_T_S and t_new is not None and np.nanmin(t_new) >= ABSOLUTE_T_S:
        hi = (getattr(m, "domain_", None) or {}).get("t", [None, None])[1]
        beyond = 0 if hi is None else int(np.sum(t_new > hi))
        ahead_h = 0.0 if hi is None or not beyond else float((np.nanmax(t_new) - hi) / S_PER_H)
        text = (f"time term(s) {names} evaluated at the rows' absolute time"
                + (f"; {beyond} of {int(new.sum())} new rows lie up to {ahead_h:.1f} h beyond the training's "
                   "time: extrapolated (their u_model grows with the term's covariance)" if beyond else ""))
        return None, {"effects": list(effects), "applied": "absolute time", "rows": int(new.sum()),
                      "rows_beyond_training": beyond, "hours_beyond_training": ahead_h, "text": text}
    inp = as_inputs(ds)
    if inp.t is None:  # the terms' columns are zeroed below; any time builds them
        inp = replace(inp, t=np.zeros(inp.n))
    D = m.design_matrix(inp)
    cols = np.flatnonzero([e in effects for e, _, _, _ in D.params])
    A = D.A.copy()
    A[np.ix_(np.flatnonzero(new), np.arange(3), cols)] = 0.0
    why = "carry no time" if ds.t is None else "carry no absolute time (t below 1e9 s: not Unix time)"
    text = (f"time term(s) {names} fitted within the training session are not applied to the {int(new.sum())} rows "
            f"of other sessions: they {why}, so a drift there is that session's own (give t as Unix time in both "
            "files to carry it across)")
    return replace(D, A=A), {"effects": list(effects), "applied": "not applied: a nuisance of the training session",
                            "rows": int(new.sum()), "text": text}


@dataclass(frozen=True)
class Shift:
    """Whether failing readings are one rigid shift of the session (the instrument's set-up moved),
    not a change of the arm (`rigid_shift`).

    Attributes
    ----------
    rigid : bool
        A rigid transform explains the differences (its residual is consistent with u) and they
        were significant without it: re-reference the session instead of maintaining the arm.
    translation_mm : ndarray
        (3,) the fitted shift at the frame's origin, mm.
    rotation_mrad : ndarray
        (3,) the fitted small rotation, mrad.
    p_before, p_after : float
        chi^2 p-values of the differences against u before and after the rigid fit.
    n : int
        Readings used.
    text : str
        The verdict in words.
    chi2_after : float
        The weighted residual sum of squares after the rigid fit (`joint_alternative` compares with it).
    """

    rigid: bool
    translation_mm: np.ndarray
    rotation_mrad: np.ndarray
    p_before: float
    p_after: float
    n: int
    text: str
    chi2_after: float = float("nan")


MIN_SHIFT_READINGS = 6  # 3 n >= 2 x the 6 parameters of a rigid shift
P_SHIFT = 0.01  # significance of "the differences are there" and of "a rigid fit leaves more than u"


def rigid_shift(points: np.ndarray, diffs: np.ndarray, u: np.ndarray) -> Shift:
    """Are the differences d_i (measured minus predicted, m) at the points p_i one rigid shift,
    d_i = omega x p_i + dt (6 parameters, weighted least squares by 1/u), within their standard
    uncertainty u? A set-up that moved (a camera knocked, a tracker set up anew) shifts every
    reading rigidly; a changed arm (a joint offset of joints 2 to 6, a worn gear) does not. A
    rotation about the base's vertical axis through its origin is also what a first joint's zero
    offset does: the two cannot be told apart from positions alone (the text says so).

    Parameters
    ----------
    points : ndarray
        (n, 3) the readings' positions, m (the frame the differences are in).
    diffs : ndarray
        (n, 3) the differences, m.
    u : ndarray
        (n, 3) or (3,) their standard uncertainty, m.

    Returns
    -------
    Shift

    Raises
    ------
    DataError
        Fewer than MIN_SHIFT_READINGS readings, or a non-positive u.
    """
    from scipy import stats

    P, d = np.asarray(points, dtype=float).reshape(-1, 3), np.asarray(diffs, dtype=float).reshape(-1, 3)
    n = len(P)
    if n < MIN_SHIFT_READINGS or d.shape != P.shape:
        raise DataError(f"a rigid shift needs at least {MIN_SHIFT_READINGS} readings with 3 differences each, "
                        f"got {n}")
    w = 1.0 / np.broadcast_to(np.asarray(u, dtype=float), P.shape)
    if not np.all(np.isfinite(w)) or np.any(w <= 0):
        raise DataError("the readings' uncertainty must be finite and positive")
    A = (rigid_jacobian(P) * w[:, :, None]).reshape(-1, 6)
    b = (d * w).reshape(-1)
    theta, *_ = np.linalg.lstsq(A, b, rcond=None)
    chi_before, chi_after = float(b @ b), float(np.sum((b - A @ theta) ** 2))
    p_before = float(stats.chi2.sf(chi_before, 3 * n))
    p_after = float(stats.chi2.sf(chi_after, 3 * n - 6))
    rigid = p_before < P_SHIFT and p_after >= P_SHIFT
    rot, tr = theta[:3] * 1e3, theta[3:] * 1e3
    if rigid:
        text = (f"the {n} failing readings are one rigid shift of the set-up ({', '.join(f'{v:+.3f}' for v in tr)} mm, "
                f"{', '.join(f'{v:+.3f}' for v in rot)} mrad; what remains is within u): re-reference the session "
                "(a few reference poses) before asking for maintenance"
                + ("; a rotation about the vertical axis is also what a first-joint zero offset gives"
                   if abs(rot[2]) > 3 * max(abs(rot[0]), abs(rot[1]), 1e-9) else ""))
    elif p_before >= P_SHIFT:
        text = f"the {n} readings agree with the prediction within u: no shift"
    else:
        text = (f"the {n} failing readings are not one rigid shift (after the best one chi^2 p = {p_after:.2g}): "
                "the arm changed, not the set-up")
    return Shift(rigid, tr, rot, p_before, p_after, n, text, chi_after)


ALT_JOINTS = 2  # joint-offset alternatives: every single joint and every pair
P_ALTERNATIVE = 0.001  # a rigid shift beats a joint alternative when chi^2 falls by more than chi^2_6 at this level


def joint_alternative(jacobian: np.ndarray, diffs: np.ndarray, u: np.ndarray, chi2_rigid: float,
                      points: np.ndarray | None = None) -> dict:
    """Do changed joint zeros explain the differences about as well as the rigid shift (d_i =
    sum_j J_j(q_i) dq_j over one joint or a pair of joints, weighted least squares by 1/u)? Over
    the few poses of a service window a joint's offset can look like a rigid shift of the set-up
    (joint 1's is one exactly). The rigid shift is preferred only when its chi^2 is lower than the
    best alternative's by more than chi^2_6 at P_ALTERNATIVE: were the alternative true, adding the
    shift's 6 parameters to it would lower its chi^2 by a chi^2_6 variable, and the rigid fit alone
    can do no better than that (so a joint fault is called a shift with probability below
    P_ALTERNATIVE, for u as stated; a u stated too large only makes it rarer).

    Parameters
    ----------
    jacobian : ndarray
        (n, 3, dof) the position Jacobian of the TCP at each reading, in the differences' axes (m/rad).
    diffs : ndarray
        (n, 3) the differences, m.
    u : ndarray
        (n, 3) or (3,) their standard uncertainty, m.
    chi2_rigid : float
        The rigid fit's weighted residual sum of squares (`Shift.chi2_after`).
    points : ndarray, optional
        (n, 3) the readings' positions, m: with them, `nested` says whether a single joint whose
        motion is itself a rigid motion of these points (joint 1's zero) explains them as well: no
        number of readings tells it from a shift.

    Returns
    -------
    dict
        `joints` (1-based) of the best alternative, its `dq_mrad`, `chi2`, `p_value` (chi^2 on
        3 n - k dof), `margin` (its chi^2 minus the rigid fit's), `needed` (the margin a shift
        needs), `explains` (margin <= needed: the arm is not ruled out) and `nested`.
    """
    from itertools import combinations

    from scipy import stats

    J = np.asarray(jacobian, dtype=float)
    d = np.asarray(diffs, dtype=float).reshape(-1, 3)
    w = 1.0 / np.broadcast_to(np.asarray(u, dtype=float), d.shape)
    b = (d * w).reshape(-1)
    A = (J * w[:, :, None]).reshape(-1, J.shape[2])
    best: dict = {"joints": [], "dq_mrad": [], "chi2": float(b @ b)}
    for k in range(1, ALT_JOINTS + 1):
        for cols in combinations(range(J.shape[2]), k):
            M = A[:, cols]
            dq, *_ = np.linalg.lstsq(M, b, rcond=None)
            chi = float(np.sum((b - M @ dq) ** 2))
            if chi < best["chi2"]:
                best = {"joints": [c + 1 for c in cols], "dq_mrad": [float(v) * 1e3 for v in dq], "chi2": chi}
    needed = float(stats.chi2.isf(P_ALTERNATIVE, 6))
    margin = best["chi2"] - float(chi2_rigid)
    dof = max(3 * len(d) - len(best["joints"]), 1)
    nested = False  # a single joint whose motion is rigid (joint 1's) explains them as well
    if points is not None:
        R = (rigid_jacobian(np.asarray(points, dtype=float).reshape(-1, 3)) * w[:, :, None]).reshape(-1, 6)
        for j in range(A.shape[1]):
            a = A[:, j]
            # rigid to 1 %: the readings sit where the camera saw them, the joint moves the commanded TCP
            if not a @ a > 0 or np.linalg.norm(a - R @ np.linalg.lstsq(R, a, rcond=None)[0]) > 1e-2 * np.linalg.norm(a):
                continue
            chi = float(np.sum((b - a * (a @ b) / (a @ a)) ** 2))
            nested = nested or chi - float(chi2_rigid) <= needed
    return best | {"p_value": float(stats.chi2.sf(best["chi2"], dof)), "margin": margin, "needed": needed,
                   "explains": bool(margin <= needed), "nested": nested}
