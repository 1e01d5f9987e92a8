"""Campaigns that test a diagnosis the way the twin is deployed (issue 21): the model is judged on
measurements it did not see, taken the way a cell brings them (new regions, new sessions, later
times). The arm is tests/support/ur10_generator.py's (a UR10 from its published DH table with its own
forward kinematics and geometric errors), not the twin's model.

    train, test = grid_scan(seed=1)          # a raster scan, time follows position; 20 new poses later
    sessions, tasks, truth = remounted(seed=1)   # two training sessions, the SMR re-mounted in one
    train, test = approach_backlash(seed=1)  # backlash by approach direction, movel paths integrated

Each returns contract Datasets in time order (write them with measurements.dataset.write_table).
"""
from __future__ import annotations

import numpy as np

from dt_runtime.measurements.dataset import Dataset
from tests.support import ur10_generator as gen

NOISE_MM = 0.015
# The wrist of every pose below: tool pointing down-ish, as a tracker campaign holds it.
WRIST = np.array([-1.6, 1.57, 0.3])


def _arm(seed: int) -> dict:
    """The true arm's geometric errors (as ur10_generator: DH lengths +-0.2 mm, angles +-0.2 mrad)."""
    arm = np.random.default_rng(1000 + seed)
    return {"a": gen.A + arm.normal(0, 2e-4, 6) * (gen.A != 0), "d": gen.D + arm.normal(0, 2e-4, 6),
            "alpha": gen.ALPHA + arm.normal(0, 2e-4, 6), "theta0": arm.normal(0, 2e-4, 6)}


def _tool_point(q: np.ndarray, offset: np.ndarray, kw: dict) -> np.ndarray:
    """The point `offset` (m, flange frame) from the flange of the generator's arm."""
    q = np.atleast_2d(q)
    a, d, alpha = kw.get("a", gen.A), kw.get("d", gen.D), kw.get("alpha", gen.ALPHA)
    th0 = kw.get("theta0", np.zeros(6))
    n = len(q)
    T = np.broadcast_to(np.diag([-1.0, -1.0, 1.0, 1.0]), (n, 4, 4)).copy()
    for i in range(6):
        th = q[:, i] + th0[i]
        ct, st, ca, sa = np.cos(th), np.sin(th), np.cos(alpha[i]), np.sin(alpha[i])
        Ti = np.zeros((n, 4, 4))
        Ti[:, 0, 0], Ti[:, 0, 1], Ti[:, 0, 2], Ti[:, 0, 3] = ct, -st * ca, st * sa, a[i] * ct
        Ti[:, 1, 0], Ti[:, 1, 1], Ti[:, 1, 2], Ti[:, 1, 3] = st, ct * ca, -ct * sa, a[i] * st
        Ti[:, 2, 1], Ti[:, 2, 2], Ti[:, 2, 3] = sa, ca, d[i]
        Ti[:, 3, 3] = 1.0
        T = T @ Ti
    return T[:, :3, 3] + T[:, :3, :3] @ (np.array([0.0, 0.0, gen.TOOL]) + offset)


def _dataset(q, t, commanded, actual, rng, speed=None, u=True, point_id=None, rep=None, temperature=None,
             source="") -> Dataset:
    noise = rng.normal(0, NOISE_MM * 1e-3, (len(q), 3))
    return Dataset(commanded=commanded, error=commanded - (actual + noise), joints=q, t=t, speed=speed,
                   temperature=temperature, point_id=point_id, rep=rep,
                   u=np.full((len(q), 3), NOISE_MM * 1e-3) if u else None, source=source)


def _sag(q: np.ndarray) -> np.ndarray:
    """An error no catalogue term has the form of: the upper arm and forearm bend under their own
    weight (no payload column to read), joint-space deflection ~ cos of the links' angles."""
    dq = np.zeros_like(q)
    dq[:, 1] = 2.5e-4 * np.cos(q[:, 1])
    dq[:, 2] = 1.5e-4 * np.cos(q[:, 1] + q[:, 2])
    return dq


# --------------------------------------------------------------------------- a raster scan
def grid_scan(seed: int = 1, side: int = 10, n_test: int = 20, dt_s: float = 10.0) -> tuple[Dataset, Dataset]:
    """`side`^3 poses on a joint grid (q1, q2, q3; the wrist fixed) scanned in raster order, none
    repeated, one pose per `dt_s`: time follows position. The arm: geometric errors plus gravity sag
    of its own links (smooth in the pose), no drift. The test file: `n_test` new poses inside the
    grid, measured after the scan in random order."""
    rng = np.random.default_rng(seed)
    geo = _arm(seed)
    g1, g2, g3 = np.linspace(-0.6, 0.6, side), np.linspace(-1.9, -1.1, side), np.linspace(-1.9, -1.0, side)
    Q = np.array([(a, b, c) for a in g1 for b in g2 for c in g3])  # q3 fastest, q1 slowest
    q = np.column_stack([Q, np.tile(WRIST, (len(Q), 1))])
    t = np.arange(len(q)) * dt_s

    def measure(q, t):
        return _dataset(q, t, gen.fk(q), gen.fk(q + _sag(q), **geo), rng,
                        point_id=np.arange(len(q)), rep=np.zeros(len(q), int))

    train = measure(q, t)
    lo, hi = np.array([g1[0], g2[0], g3[0]]), np.array([g1[-1], g2[-1], g3[-1]])
    qt = np.column_stack([lo + (hi - lo) * rng.random((n_test, 3)), np.tile(WRIST, (n_test, 1))])
    test = measure(qt, t[-1] + 600.0 + np.arange(n_test) * dt_s)
    return train, test


# --------------------------------------------------------------------------- sessions
def _random_poses(rng, n: int) -> np.ndarray:
    lo = np.array([-1.2, -2.2, -2.2, -2.4, 0.8, -2.5])
    hi = np.array([1.2, -0.9, -0.8, -0.8, 2.3, 2.5])
    return lo + (hi - lo) * rng.random((n, 6))


def remounted(seed: int = 1, n_points: int = 150, passes: int = 2, n_tasks: int = 3, task_points: int = 40,
              smr_offset_mm=(0.45, -0.30, 0.35)) -> tuple[list[Dataset], list[Dataset], dict]:
    """Two training sessions of one arm, in the robot frame (a given registration), the SMR
    re-mounted for the second: its centre sits `smr_offset_mm` (flange frame) from where it was.
    Task sessions (new poses) are measured with the first mounting. Returns the training sessions,
    the task sessions and the truth ({'smr_offset_mm', 'session': 1})."""
    rng = np.random.default_rng(seed)
    geo = _arm(seed)
    off = np.asarray(smr_offset_mm, float) * 1e-3

    def session(n, offset, t0):
        targets = _random_poses(rng, n)
        order = np.concatenate([rng.permutation(n) for _ in range(passes)])
        q = targets[order]
        t = t0 + np.arange(len(q)) * 30.0
        actual = _tool_point(q, offset, geo)
        return _dataset(q, t, gen.fk(q), actual, rng, point_id=order, rep=np.repeat(np.arange(passes), n))

    train = [session(n_points, np.zeros(3), 0.0), session(n_points, off, 86400.0)]
    tasks = [session(task_points, np.zeros(3), 86400.0 * (2 + k)) for k in range(n_tasks)]
    return train, tasks, {"smr_offset_mm": list(smr_offset_mm), "session": 1}


# --------------------------------------------------------------------------- backlash on paths
def _hysteresis(path: np.ndarray, width: np.ndarray, start: np.ndarray) -> np.ndarray:
    """The output side of a joint with play `width` driven along `path` (steps, dof): the output
    follows the input only once the input has crossed the play (a deadband), integrated step by
    step. Returns the output at the path's end."""
    out = start.copy()
    half = width / 2
    for qi in path:
        out = np.clip(out, qi - half, qi + half)
    return out


def approach_backlash(seed: int = 1, n_points: int = 40, passes: int = 4, readings: int = 2,
                      play_mrad=(0.30, 0.25, 0.25, 0.0, 0.0, 0.0), speeds=(0.1, 0.25, 0.5), n_test_points: int = 40,
                      u: bool = False) -> tuple[Dataset, Dataset]:
    """Backlash by approach direction, the arm's motion integrated: every move to the next pose is
    a linear move (the TCP on a straight line, the orientation slerped: 100 steps of the nominal
    arm's inverse kinematics), and each joint's play is a deadband driven along that joint path,
    so a joint that reverses during the move rests against the side of its last motion (not of its
    net change), partly engaged when the reversal came late. Each visit is measured `readings` times
    (the tracker's repeated readings: replicates of one approach). The speed of each move is drawn
    from `speeds` (nothing depends on it). No uncertainty columns unless `u`. The test file: new
    poses of the same arm, another path."""
    geo = _arm(seed)
    width = np.asarray(play_mrad) * 1e-3

    def campaign(rng, n, t0):
        base = np.array([0.0, -1.5, -1.5, -1.7, 1.57, 0.3])
        targets = base + rng.uniform(-1, 1, (n, 6)) * np.array([0.6, 0.3, 0.35, 0.3, 0.3, 0.6])
        order = np.concatenate([rng.permutation(n) for _ in range(passes)])
        qs = targets[order]
        paths = _linear_paths(np.vstack([qs[:1], qs[:-1]]), qs, 100)
        v = rng.choice(np.asarray(speeds, float), len(qs))
        side = qs[0].copy()
        sides = []
        for path in paths:
            side = _hysteresis(path, width, side)
            sides.append(side.copy())
        dist = np.linalg.norm(gen.fk(qs) - gen.fk(np.vstack([qs[:1], qs[:-1]])), axis=1)
        t_visit = t0 + np.cumsum(np.maximum(dist / v, 0.5) + 2.0)
        k = np.repeat(np.arange(len(qs)), readings)
        q = qs[k]
        dq = (np.array(sides) - qs)[k]  # the output's lag behind the commanded joint
        t = t_visit[k] + np.tile(np.arange(readings), len(qs))
        return _dataset(q, t, gen.fk(q), gen.fk(q + dq, **geo), rng, speed=v[k], u=u, point_id=order[k],
                        rep=(k // n))

    train = campaign(np.random.default_rng(seed), n_points, 0.0)
    test = campaign(np.random.default_rng(seed + 50), n_test_points, 1e5)
    return train, test


def _pose(q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """TCP position (n, 3) and orientation (n, 3, 3) of the generator's nominal arm."""
    p = _tool_point(q, np.zeros(3), {})
    R = np.stack([_tool_point(q, e * 1e-3, {}) - p for e in np.eye(3)], axis=2) / 1e-3
    return p, R


def _linear_paths(q0: np.ndarray, q1: np.ndarray, steps: int) -> np.ndarray:
    """Joint paths (m, steps, 6) of linear moves from q0 to q1 (m, 6): the TCP on a straight line,
    the orientation turning about one axis at a constant rate (slerp), as a controller's movel.
    Newton steps on the nominal arm's 6-D pose, for every step of every move at once, from the
    paths interpolated in joints (the branch of q0 and q1)."""
    from scipy.spatial.transform import Rotation, Slerp

    m = len(q0)
    s = (np.arange(steps) + 1.0) / steps
    (p0, R0), (p1, R1) = _pose(q0), _pose(q1)
    q = (q0[:, None, :] + s[None, :, None] * (q1 - q0)[:, None, :]).reshape(-1, 6)
    target = (p0[:, None, :] + s[None, :, None] * (p1 - p0)[:, None, :]).reshape(-1, 3)
    Rt = Rotation.concatenate([Slerp([0.0, 1.0], Rotation.from_matrix(np.stack([a, b])))(s)
                               for a, b in zip(R0, R1)])
    h = 1e-6
    for _ in range(6):
        p, R = _pose(q)
        Rinv = Rotation.from_matrix(R).inv()
        err = np.concatenate([target - p, (Rt * Rinv).as_rotvec()], axis=1)
        J = np.empty((len(q), 6, 6))
        for j in range(6):
            dq = np.zeros(6)
            dq[j] = h
            pj, Rj = _pose(q + dq)
            J[:, :3, j] = (pj - p) / h
            J[:, 3:, j] = (Rotation.from_matrix(Rj) * Rinv).as_rotvec() / h
        q += np.linalg.solve(J, err[:, :, None])[:, :, 0]
    q = q.reshape(m, steps, 6)
    q[:, -1] = q1  # each move ends at its commanded joints
    return q
