"""`backlash`: play in the joints, against the direction from which each joint arrived.

The error is J_j (w_j / 2) g_j, g_j in [-1, 1] the engagement of joint j (`engagement`); how
each joint arrived depends on the move (joint or linear TCP moves), and which moves and what
play are chosen by profile likelihood. The model: `Backlash`; docs/effects.md ("backlash").
"""
from __future__ import annotations

import hashlib
from collections import OrderedDict

import numpy as np
from scipy.spatial.transform import Rotation

from dt_runtime.frames.kinematics import Chain
from dt_runtime.models.effects.base import Block, Effect, Inputs, approach, carry_forward

MOVES = ("joint moves", "linear TCP moves")
# The play that shapes partial engagement (rad): 0 (every joint fully engaged, the sign model) and
# 20 urad .. 4 mrad (cobot and industrial gearboxes: tens to hundreds of urad).
PLAY_GRID_RAD = np.concatenate([[0.0], np.geomspace(2e-5, 4e-3, 24)])
_CACHE: OrderedDict = OrderedDict()  # arrivals of recent joint tables (profile likelihood rebuilds the block)


def arrivals(q: np.ndarray, chain: Chain, linear: bool) -> tuple[np.ndarray, np.ndarray]:
    """Per row and joint: the sign of the motion as the joint arrived (n, dof) and its travel since
    it last reversed (rad; inf where unknown: fully engaged). A joint that did not move keeps both.

    Parameters
    ----------
    q : ndarray
        (n, dof) joint angles, rows in time order, rad.
    chain : Chain
        The robot's kinematic chain.
    linear : bool
        The rows were reached by linear TCP moves (else joint moves).

    Returns
    -------
    sign : ndarray
        (n, dof).
    travel : ndarray
        (n, dof), rad.
    """
    key = (hashlib.sha1(np.ascontiguousarray(q, dtype=float).tobytes()).hexdigest(), id(chain), chain.dof, linear)
    if key in _CACHE:
        _CACHE.move_to_end(key)
        return _CACHE[key]
    out = _linear(q, chain) if linear else _joint(q)
    _CACHE[key] = out
    if len(_CACHE) > 8:
        _CACHE.popitem(last=False)
    return out


def approach_signs(q: np.ndarray) -> np.ndarray:
    """Per row and joint, the sign of the joint's motion into the pose on a joint move (n, dof): the
    change from the previous row, a joint that did not move keeping its last direction (rows in time
    order). The side each joint's play rests on; the replicate floor pairs revisits by it.

    Parameters
    ----------
    q : ndarray
        (n, dof) joint angles, rows in time order.

    Returns
    -------
    ndarray
        (n, dof) of -1, 0, +1.
    """
    return np.sign(approach(q, per_column=True))


def _joint(q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    d = np.zeros_like(q)
    d[1:] = q[1:] - q[:-1]
    return _accumulate(approach_signs(q), np.abs(d), np.zeros(q.shape, bool), np.abs(d))


def _linear(q: np.ndarray, chain: Chain) -> tuple[np.ndarray, np.ndarray]:
    n, dof = q.shape
    _, _, T = chain.frames(q)
    p, R = T[:, :3, 3], T[:, :3, :3]
    twist = np.zeros((n, 6))
    if n > 1:
        twist[1:, :3] = p[1:] - p[:-1]
        twist[1:, 3:] = Rotation.from_matrix(R[1:] @ np.transpose(R[:-1], (0, 2, 1))).as_rotvec()
        twist[0] = twist[1]
    Jp = np.linalg.pinv(chain.jacobian6(q))
    v = np.einsum("nja,na->nj", Jp, twist)  # dq/ds at the end of the line (s: 0 -> 1 along the move)
    # dv/ds = -J^+ (dJ/ds) J^+ xi at the end, dJ/ds by a difference back along the path
    h = 1e-4
    dJ = (chain.jacobian6(q) - chain.jacobian6(q - h * v)) / h
    a = -np.einsum("nja,nab,nb->nj", Jp, dJ, v)
    moved = (np.linalg.norm(twist[:, :3], axis=1) + 0.1 * np.linalg.norm(twist[:, 3:], axis=1)) > 1e-9
    tiny = np.abs(v) <= 1e-9 * np.maximum(np.abs(v).max(axis=1, keepdims=True), 1e-300)
    still = (~moved)[:, None] | tiny
    sign = np.sign(carry_forward(v, still, per_column=True))
    # A reversal inside the move: the extremum of q_j(s) lies delta = v / a back from the end.
    with np.errstate(divide="ignore", invalid="ignore"):
        delta = np.where(np.abs(a) > 0, v / a, np.inf)
        inside = (delta > 0) & (delta < 1) & ~still
        since = np.where(inside, v ** 2 / (2 * np.abs(a)), np.inf)
    travel = np.zeros_like(q)
    travel[1:] = np.abs(q[1:] - q[:-1])
    return _accumulate(sign, travel, inside, since)


def _accumulate(sign: np.ndarray, travel: np.ndarray, inside: np.ndarray, since: np.ndarray):
    """Travel since the last reversal, row by row: restarted by a reversal inside a move (`since`) or
    between moves (the arrival sign changed), else growing by the move's travel."""
    n, dof = sign.shape
    tau = np.empty_like(travel)
    tau[0] = np.inf
    for i in range(1, n):
        same = sign[i] == sign[i - 1]
        t = np.where(same, tau[i - 1] + travel[i], travel[i])
        tau[i] = np.where(inside[i], since[i], t)
    return sign, tau


def engagement(q: np.ndarray, chain: Chain, linear: bool, play_rad: float) -> np.ndarray:
    """The engagement g (n, dof) in [-1, 1] of every joint (`Backlash`); play 0: the sign.

    Parameters
    ----------
    q : ndarray
        (n, dof) joint angles, rows in time order, rad.
    chain : Chain
        The robot's kinematic chain.
    linear : bool
        The rows were reached by linear TCP moves (else joint moves).
    play_rad : float
        The play, rad.

    Returns
    -------
    ndarray
        (n, dof).
    """
    sign, tau = arrivals(q, chain, linear)
    if play_rad <= 0:
        return sign
    return sign * np.clip(2 * tau / play_rad - 1, -1.0, 1.0)


class Backlash(Effect):
    """Half the play against the direction of approach, dq_j = -(w_j / 2) g_j, the direction read
    from the previous row (rows in time order).

    A joint with play w rests, once it has moved at least w in one direction, w/2 behind its
    command (against that direction). After a reversal it moves the play across first: having
    travelled tau since the reversal, its output lags by w/2 - tau (tau < w), so a joint whose
    motion reversed just before the end of a move still rests near the side it came from. For
    each row and joint this is the engagement g in [-1, 1] (the sign of the arrival direction
    times clip(2 tau / w - 1, -1, 1)), and the error is J_j (w_j / 2) g_j.

    How each joint arrived depends on the move: joint moves (joints interpolated) arrive in the
    sign of their change; linear TCP moves (the TCP on a straight line, the orientation turning
    at a constant rate: a controller's movel) arrive in the sign of the joint velocity at the end
    of the line, J6(q)^+ [dp; dtheta], and a joint may reverse during the move (its travel since
    then from the velocity and acceleration at the end). Which moves the data came from (`moves`)
    and the play that shapes the partial engagement (`play_rad`, 0: always fully engaged) are
    chosen by profile likelihood.
    """

    name = "backlash"
    columns = ("joints",)
    factor = "the direction from which each joint approached"
    varies_with = ("direction",)
    hyper = {"moves": np.array([0.0, 1.0]), "play_rad": PLAY_GRID_RAD}
    hyper_units = {"moves": "", "play_rad": "rad"}
    hyper_choices = {"moves": MOVES}

    def regressors(self, inp: Inputs, chain: Chain, moves: float = 0.0, play_rad: float = 0.0) -> Block:
        """The block: each joint's width times half its engagement sign, through the Jacobian.

        Parameters
        ----------
        inp : Inputs
            The data's columns.
        chain : Chain
            The robot's kinematic chain.
        moves : float, optional
            >= 0.5: the rows were reached by linear TCP moves, else by joint moves (`MOVES`).
        play_rad : float, optional
            The play over which the engagement goes from -1 to 1, rad (0: the sign).

        Returns
        -------
        Block
            Parameters width_q1..width_qN, rad, non-negative.
        """
        q = inp.column("joints")
        J = chain.jacobian(q)
        g = engagement(q, chain, linear=bool(moves >= 0.5), play_rad=play_rad)
        A = J * (0.5 * g)[:, None, :]
        dof = J.shape[2]
        return Block(self.name, A, tuple(f"width_q{j + 1}" for j in range(dof)), ("rad",) * dof, nonnegative=True)
