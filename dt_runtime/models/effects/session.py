"""Session terms: what can differ between the sessions of one campaign (each file measured with
its own set-up) without being the robot's error (`tool`, `base`, `joints`: `term_regressors`).

They are nuisance terms: fitted so that sessions that disagree do not corrupt the error map,
never deployed (a command has no session; the model predicts the reference session's robot).
See docs/campaigns.md ("Sessions that disagree").
"""
from __future__ import annotations

import numpy as np

from dt_kernel.errors import DataError
from dt_kernel.geometry import skew
from dt_runtime.frames.kinematics import Chain
from dt_runtime.models.effects.base import Block, Inputs

TERMS = ("tool", "base", "joints")
EFFECT = "session_{}"  # the effect name of a term's parameters (Design.params)


def term_regressors(term: str, inp: Inputs, chain: Chain | None) -> tuple[np.ndarray, tuple[str, ...], tuple[str, ...]]:
    """The term's regressors on every row (n, 3, p), its parameter names and units.

    - `tool`: the SMR or probe re-mounted: a constant offset d_s in the flange frame,
      e = -R_tcp(q) d_s (the measured point moves with the tool's orientation, so a rigid
      registration cannot take it up).
    - `base`: the set-up's rigid part (the registration realised differently):
      e = -t_s + [p]x w_s, a translation and a small rotation of the whole session.
    - `joints`: the joint zeros changed between sessions (re-homing, an encoder slipped):
      e = -J(q) dq_s.

    Each session other than the reference gets its own parameters (regressors times its indicator,
    `block`); rows of the reference session, of an unseen session or without a session column get
    none.

    Parameters
    ----------
    term : str
        'tool', 'base' or 'joints'.
    inp : Inputs
        The data's columns.
    chain : Chain or None
        The robot's kinematic chain.

    Returns
    -------
    A : ndarray
        (n, 3, p).
    names, units : tuple of str
    """
    if term == "base":
        p = inp.commanded
        A = np.concatenate([-np.broadcast_to(np.eye(3), (len(p), 3, 3)), skew(p)], axis=2)
        return A, ("dx", "dy", "dz", "rx", "ry", "rz"), ("m",) * 3 + ("rad",) * 3
    if chain is None or inp.joints is None:
        raise DataError(f"the session term '{term}' needs the joint angles and the robot's kinematic model")
    if term == "tool":
        R = chain.frames(inp.joints)[2][:, :3, :3]
        return -R, ("dx", "dy", "dz"), ("m",) * 3
    if term == "joints":
        J = chain.jacobian(inp.joints)
        dof = J.shape[2]
        return -J, tuple(f"dq{j + 1}" for j in range(dof)), ("rad",) * dof
    raise DataError(f"unknown session term {term!r}; allowed: {', '.join(TERMS)}")


def session_column(inp: Inputs) -> np.ndarray | None:
    """The data's session number per row, or None without a session column.

    Parameters
    ----------
    inp : Inputs
        The data's columns.

    Returns
    -------
    ndarray or None
        (n,) int.
    """
    s = inp.get("session")
    return None if s is None else np.asarray(s).astype(int)


def block(term: str, inp: Inputs, chain: Chain | None, sessions: tuple[int, ...]) -> Block:
    """The term's block for `sessions` (the non-reference sessions of the training data): one set
    of parameters per session, zero on every other row (a deployed command has no session: the
    regressors are not even built, so it needs none of their inputs).

    Parameters
    ----------
    term : str
        'tool', 'base' or 'joints'.
    inp : Inputs
        The data's columns.
    chain : Chain or None
        The robot's kinematic chain.
    sessions : tuple of int
        The sessions with parameters.

    Returns
    -------
    Block
    """
    s = session_column(inp)
    ind = [np.zeros(inp.n) if s is None else (s == sid).astype(float) for sid in sessions]
    _, names, units = _shape(term, chain, inp)
    all_names = tuple(f"s{sid}_{n}" for sid in sessions for n in names)
    all_units = tuple(u for _ in sessions for u in units)
    if not any(i.any() for i in ind):
        return Block(EFFECT.format(term), np.zeros((inp.n, 3, len(all_names))), all_names, all_units)
    A0, _, _ = term_regressors(term, inp, chain)
    A = np.concatenate([A0 * i[:, None, None] for i in ind], axis=2) if ind else np.zeros((inp.n, 3, 0))
    return Block(EFFECT.format(term), A, all_names, all_units)


def _shape(term: str, chain: Chain | None, inp: Inputs) -> tuple[int, tuple[str, ...], tuple[str, ...]]:
    """The term's parameter count, names and units without building its regressors."""
    if term == "base":
        return 6, ("dx", "dy", "dz", "rx", "ry", "rz"), ("m",) * 3 + ("rad",) * 3
    if term == "tool":
        return 3, ("dx", "dy", "dz"), ("m",) * 3
    if term == "joints":
        dof = chain.dof if chain is not None else (inp.joints.shape[1] if inp.joints is not None else 6)
        return dof, tuple(f"dq{j + 1}" for j in range(dof)), ("rad",) * dof
    raise DataError(f"unknown session term {term!r}; allowed: {', '.join(TERMS)}")


def absorb(term: str, inp: Inputs, chain: Chain | None, residual: np.ndarray) -> tuple[np.ndarray, int]:
    """`residual` with the term's part fitted to it by least squares and removed (a held-out
    session scored after its own tool offset, set-up or joint zeros are measured again, as its
    registration is): the residual and the degrees of freedom absorbed.

    Parameters
    ----------
    term : str
        'tool', 'base' or 'joints'.
    inp : Inputs
        The data's columns.
    chain : Chain or None
        The robot's kinematic chain.
    residual : ndarray
        (n, 3), m.

    Returns
    -------
    residual : ndarray
        (n, 3), m.
    dof : int
    """
    A, names, _ = term_regressors(term, inp, chain)
    M = A.reshape(-1, A.shape[2])
    theta, *_ = np.linalg.lstsq(M, residual.ravel(), rcond=None)
    return residual - (M @ theta).reshape(-1, 3), len(names)
