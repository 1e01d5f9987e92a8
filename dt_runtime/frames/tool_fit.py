"""The tool (SMR) offset in the flange frame, fitted from the data when the robot config gives none.

A catalogue arm or a bare URDF ends at the flange; the laser tracker measures the reflector on
the tool. With the joint angles q_i and positions p_i of the TCP in the robot frame (measured, or
the controller's commanded TCP), the offset o solves, by linear least squares,

    p_i = p_f(q_i) + R_f(q_i) o + G(q_i) theta                 (one 3-vector equation per row)

with the flange's nominal position p_f and orientation R_f, and G theta the arm's own first-order
geometric error (every joint's zero offset, and small translations and rotations of every joint
frame: the `geometric` effect's model, models.effects.geometric, which this layer may not import).
Without theta the arm's error leaks into o: wrist errors average out only partly over the poses
(0.05-0.2 mm on a Panda with 0.5 mm of arm error, several times the naive uncertainty). theta
is rank deficient (consecutive frames' errors act alike); the solution is the minimum-norm one
with o's columns weighted so that what the data cannot tell apart from a tool offset (a shift of
the last joint's frame along its axis, its zero offset) goes to o: the fitted offset is the
effective tool. Its standard uncertainties come from the covariance s^2 V S^-2 V^T of the
retained singular directions, s from the residual (3n - rank degrees of freedom). With too few
rows for theta (3n < 2 (3 + p)) the offset alone is fitted (the mean of R_f^T (p_i - p_f), A^T A
= n I) and `fitted_from` says so.

Shortfall: the offset also shares directions with combinations of the other joints' errors (on
the synthetic Panda, tests/unit/test_tool_fit.py, arm errors of 0.3-0.6 mm RMS: up to 0.03 mm across
and 0.06 mm along the flange's axis, up to several times the stated u, which holds for noise alone). The geometric
effect's tool terms take up what is left when the model is fitted.

The residual RMS reported is that of the offset alone: the arm's error plus noise, which the twin
then models.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from dt_kernel.errors import DataError
from dt_kernel.units import MM_PER_M
from dt_runtime.frames.kinematics import Chain


@dataclass(frozen=True)
class ToolFit:
    """A fitted tool offset (m, flange frame) with its standard uncertainty per axis (m), the 3D
    RMS of the residual (m), the rows used and what the positions were ('measured', 'commanded')."""

    offset: np.ndarray
    u: np.ndarray
    residual_rms: float
    n: int
    fitted_from: str

    def to_dict(self) -> dict:
        return {"xyz_mm": [float(v) * MM_PER_M for v in self.offset], "u_mm": [float(v) * MM_PER_M for v in self.u],
                "residual_rms_mm": self.residual_rms * MM_PER_M, "n": self.n, "from": self.fitted_from,
                "frame": "flange"}

    def line(self) -> str:
        """One line for stderr and the notes."""
        xyz = ", ".join(f"{a} {v * MM_PER_M:.3f} +/- {s * MM_PER_M:.3f}" for a, v, s in zip("xyz", self.offset, self.u))
        return (f"tool offset fitted from {self.n} {self.fitted_from} positions (flange frame, mm): {xyz}; "
                f"residual 3D RMS {self.residual_rms * MM_PER_M:.3f} mm")


# The minimum-norm solution on standardised columns, the offset's columns FAVOUR_TOOL times longer so that
# a direction shared with geometric parameters costs the offset least and goes to it; singular values
# below RCOND of the largest (the geometric set's exact aliases) are left out.
FAVOUR_TOOL = 1e3
RCOND = 1e-10


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


def fit_tool(chain: Chain, q: np.ndarray, p: np.ndarray, fitted_from: str = "measured") -> ToolFit:
    """The tool offset of `chain` (whose tool is its flange) from joint angles q (n, dof) and TCP
    positions p (n, 3) in the robot frame (m); rows with a non-finite value are left out."""
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
    d = p - T[:, :3, 3]
    o = np.einsum("nba,nb->na", T[:, :3, :3], d).mean(axis=0)  # the offset alone: A^T A = n I
    r = d - np.einsum("nab,b->na", T[:, :3, :3], o)
    rms = float(np.sqrt(np.mean(np.sum(r ** 2, axis=1))))
    G = _geometric(chain, q)
    if 3 * n < 2 * (3 + G.shape[2]):
        s2 = float(np.sum(r ** 2)) / max(3 * n - 3, 1)
        return ToolFit(o, np.full(3, np.sqrt(s2 / n)), rms, n, fitted_from + " (offset alone: too few rows for "
                       "the arm's geometric error)")
    X = np.concatenate([T[:, :3, :3], G], axis=2).reshape(3 * n, -1)
    scale = np.linalg.norm(X, axis=0)
    scale[scale == 0] = 1.0
    scale[:3] /= FAVOUR_TOOL
    U, S, Vt = np.linalg.svd(X / scale, full_matrices=False)
    keep = S > RCOND * S[0]
    V, S, U = Vt[keep].T, S[keep], U[:, keep]
    beta = V @ ((U.T @ d.reshape(-1)) / S)
    res = d.reshape(-1) - (X / scale) @ beta
    cov = float(res @ res) / max(3 * n - int(keep.sum()), 1) * (V / S ** 2) @ V.T
    return ToolFit(beta[:3] / scale[:3], np.sqrt(np.diag(cov)[:3]) / scale[:3], rms, n, fitted_from)
