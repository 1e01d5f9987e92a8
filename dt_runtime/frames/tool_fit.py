"""The tool (SMR) offset in the flange frame, fitted from the data when the robot config gives none.

A catalogue arm or a bare URDF ends at the flange; the laser tracker measures the reflector on
the tool. `fit_tool` solves for the offset by linear least squares (the method: its docstring;
docs/robots.md, "The tool offset, fitted when not given").
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from dt_kernel.errors import DataError
from dt_kernel.units import MM_PER_M
from dt_runtime.frames.kinematics import Chain

# A flange direction along which the orientations spread (RMS) by less than this (rad) is a
# direction the poses keep: the tool offset along it is a constant shift for them (~3 deg).
MIN_SPREAD_RAD = 0.05
# The minimum-norm solution on standardised columns, the offset's columns FAVOUR_TOOL times longer so
# that a direction shared with geometric parameters goes to it; singular values below RCOND of the
# largest (aliases, and near-aliases that would amplify the file's rounding) are left out.
FAVOUR_TOOL = 1e3
RCOND = 1e-8
WHAT_TO_DO = "give tool_xyz_m in the robot config, or measure poses with other wrist orientations"


@dataclass(frozen=True)
class ToolFit:
    """A fitted tool offset (m, flange frame) with its standard uncertainty per axis (m; 0 for a
    component kept at the config's value), the 3D RMS of the residual of the offset alone (m), the
    rows used, what the positions were ('measured', 'commanded') and the components the poses
    could not determine (`undetermined`: 'x', 'y', 'z' or a flange direction) with why."""

    offset: np.ndarray
    u: np.ndarray
    residual_rms: float
    n: int
    fitted_from: str
    undetermined: tuple[str, ...] = ()
    why: str = ""

    def to_dict(self) -> dict:
        """The fit as a JSON-ready dict, in mm, in the flange frame."""
        return {"xyz_mm": [float(v) * MM_PER_M for v in self.offset], "u_mm": [float(v) * MM_PER_M for v in self.u],
                "residual_rms_mm": self.residual_rms * MM_PER_M, "n": self.n, "from": self.fitted_from,
                "frame": "flange", "undetermined": list(self.undetermined), "why": self.why}

    def line(self) -> str:
        """One line for stderr and the notes."""
        xyz = ", ".join(f"{a} {v * MM_PER_M:.3f} +/- {s * MM_PER_M:.3f}" for a, v, s in zip("xyz", self.offset, self.u))
        text = (f"tool offset fitted from {self.n} {self.fitted_from} positions (flange frame, mm): {xyz}; "
                f"residual 3D RMS {self.residual_rms * MM_PER_M:.3f} mm")
        if self.undetermined:
            text += f"; {self.note()}"
        return text

    def note(self) -> str:
        """The undetermined components in one sentence, with why and what to do ('' when none)."""
        if not self.undetermined:
            return ""
        return (f"tool {', '.join(self.undetermined)} not determined by these poses ({self.why}): kept at the "
                f"config's value (0, none given); {WHAT_TO_DO}")


def _names(E: np.ndarray) -> tuple[str, ...]:
    """Flange directions (columns of E, orthonormal) as axis names when they span axes, else vectors."""
    if E.shape[1] == 0:
        return ()
    P = E @ E.T  # projector onto the undetermined subspace
    axes = [a for a, k in zip("xyz", range(3)) if P[k, k] > 0.99]
    if len(axes) == E.shape[1]:
        return tuple(axes)
    return tuple("(" + ", ".join(f"{v:.2f}" for v in e) + ")" for e in E.T)


def spread(R: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The flange directions (3, 3, columns) and the RMS angle (rad) by which the poses turn each:
    the right singular vectors of the stacked deviations R_i - mean(R); a direction e with spread ~0
    has R_i e the same for every pose.

    Parameters
    ----------
    R : ndarray
        (n, 3, 3) flange orientations.

    Returns
    -------
    directions : ndarray
        (3, 3), one per column.
    rms_angle : ndarray
        (3,), rad.
    """
    D = (R - R.mean(axis=0)).reshape(-1, 3)
    _, sv, Vt = np.linalg.svd(D, full_matrices=True)
    s = np.zeros(3)
    s[:len(sv)] = sv / np.sqrt(len(R))
    return Vt.T, s


def _geometric(chain: Chain, q: np.ndarray) -> np.ndarray:
    """(n, 3, p): the TCP's first-order sensitivity to every joint's zero offset and to small
    translations and rotations of every joint frame (in that frame's axes), as models.effects.geometric."""
    pos, rot, T = chain.frames(q)
    p = T[:, None, :3, 3] - pos  # (n, dof, 3) levers
    cols = [chain.jacobian(q)]
    for j in range(chain.dof):
        R = rot[:, j]
        lx = np.zeros((len(q), 3, 3))  # the skew matrix of the lever: (R w) x l = -[l]x R w
        lx[:, 0, 1], lx[:, 0, 2], lx[:, 1, 2] = -p[:, j, 2], p[:, j, 1], -p[:, j, 0]
        lx -= lx.transpose(0, 2, 1)
        cols += [R, -np.einsum("nab,nbc->nac", lx, R)]
    return np.concatenate(cols, axis=2)


def _solve(X: np.ndarray, y: np.ndarray, favour: int) -> tuple[np.ndarray, np.ndarray]:
    """Minimum-norm least squares on standardised columns (the first `favour` columns weighted up):
    the solution and the standard uncertainties of its first `favour` entries."""
    scale = np.linalg.norm(X, axis=0)
    scale[scale == 0] = 1.0
    scale[:favour] /= FAVOUR_TOOL
    U, S, Vt = np.linalg.svd(X / scale, full_matrices=False)
    keep = S > RCOND * S[0]
    V, S, U = Vt[keep].T, S[keep], U[:, keep]
    beta = V @ ((U.T @ y) / S)
    res = y - (X / scale) @ beta
    cov = float(res @ res) / max(len(y) - int(keep.sum()), 1) * (V / S ** 2) @ V.T
    return beta / scale, np.sqrt(np.diag(cov)[:favour]) / scale[:favour]


def fit_tool(chain: Chain, q: np.ndarray, p: np.ndarray, fitted_from: str = "measured") -> ToolFit:
    """The tool offset of `chain` (whose tool is its flange) from joint angles q (n, dof) and TCP
    positions p (n, 3) in the robot frame (m); rows with a non-finite value are left out.
    `fitted_from`: 'measured' (the arm's geometric error fitted alongside) or 'commanded' (the
    controller's nominal TCP: the offset and a constant shift only).

    With joint angles q_i and TCP positions p_i in the robot frame, the flange's nominal position
    p_f and orientation R_f, the offset o solves, by linear least squares:

        p_i = p_f(q_i) + R_f(q_i) o + t [+ G(q_i) theta]

    - t, a constant shift, is always a possibility (the base or the instrument's frame): the part
      of o along a flange direction that the poses never turn (the tool kept one orientation) is
      the same for these poses as t, so it cannot be determined. Such components keep the config's
      value (zero: the config gives none) and `ToolFit.undetermined` names them with why and what
      to do.
    - theta, the arm's first-order geometric error (`_geometric`, as models.effects.geometric),
      only for *measured* positions: a commanded TCP is the controller's nominal kinematics and
      carries no arm error. theta is rank deficient; the minimum-norm solution with o's columns
      weighted up sends what the data cannot tell from a tool offset (a shift of the last frame
      along its axis) to o.

    Standard uncertainties from the covariance of the retained singular directions, s from the
    residual.

    Parameters
    ----------
    chain : Chain
        A chain whose tool is its flange.
    q : ndarray
        (n, dof) joint angles, rad.
    p : ndarray
        (n, 3) TCP positions in the robot frame, m.
    fitted_from : str, optional
        'measured' or 'commanded'.

    Returns
    -------
    ToolFit
    """
    q = np.asarray(q, dtype=float)
    p = np.asarray(p, dtype=float)
    if q.ndim != 2 or q.shape[1] != chain.dof or p.shape != (len(q), 3):
        raise DataError(f"tool offset fit: {q.shape[-1] if q.ndim == 2 else '?'} joint columns for the "
                        f"{chain.dof} joints of {chain.name}, or positions of another shape {p.shape}")
    ok = np.all(np.isfinite(q), axis=1) & np.all(np.isfinite(p), axis=1)
    n = int(ok.sum())
    if n < 2:
        raise DataError(f"tool offset fit: {n} rows with joint angles and positions; it needs at least 2")
    q, p = q[ok], p[ok]
    T = chain.frames(q)[2]
    R = T[:, :3, :3]
    d = p - T[:, :3, 3]
    dirs, s = spread(R)
    det, und = dirs[:, s >= MIN_SPREAD_RAD], dirs[:, s < MIN_SPREAD_RAD]
    why = "" if not und.shape[1] else (
        "the tool kept one orientation" if und.shape[1] == 3 else
        f"the flange turns only about that direction; about the others by less than "
        f"{np.rad2deg(MIN_SPREAD_RAD):.0f} deg")
    cols = [np.einsum("nab,bk->nak", R, det), np.broadcast_to(np.eye(3), (n, 3, 3))]  # o along det, then t
    measured = fitted_from.startswith("measured")
    if measured and 3 * n >= 2 * (6 + _geometric(chain, q[:1]).shape[2]):
        cols.append(_geometric(chain, q))
    elif measured:
        fitted_from += " (offset alone: too few rows for the arm's geometric error)"
    X = np.concatenate(cols, axis=2).reshape(3 * n, -1)
    k = det.shape[1]
    o, u = np.zeros(3), np.zeros(3)
    if k:
        beta, u_det = _solve(X, d.reshape(-1), k)
        o = det @ beta[:k]
        u = np.sqrt((det ** 2) @ (u_det ** 2))
    r = d - np.einsum("nab,b->na", R, o)
    rms = float(np.sqrt(np.mean(np.sum(r ** 2, axis=1))))
    return ToolFit(o, u, rms, n, fitted_from, _names(und), why)
