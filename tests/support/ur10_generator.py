"""A hidden-effect generator that is *not* the project's plant (issue 13): a UR10 from its
published DH table with its own geometric errors, written here with its own forward kinematics
and its own physics, so the diagnosis is tested on data its effect terms were not written from.

    rows = generate("backlash", seed=3)            # a contract Dataset, rows in time order
    write_table(rows, path)

Each campaign: `n_points` random joint configurations (elbow up, the wrist anywhere), visited
`passes` times, each pass in a new random order (so every point is approached from any
direction), one move per `dt_s` seconds; the speed and the payload change from row to row. With
`order="cycle"` it is a repeatability programme instead: one order of the points, each pass running
it forwards or backwards (so every point is approached from two sides), each point always at its
own speed and payload: revisits under the same conditions, which give the noise floor. The
error of every row is the true arm's TCP (errors below) minus the nominal one, plus the tracker's
noise (`noise_mm` per axis, stated in ux..uz). Hidden effects, one at a time:

- geometric (always): every DH length +-0.2 mm, every DH angle and joint zero +-0.2 mrad (1 sigma).
- thermal: every link length expands with the *structure's* temperature, which follows the logged
  air temperature through a first-order lag of 20..40 min (drawn per seed); 23e-6 /K (aluminium).
- compliance: the payload's real gravity torque tau = J^T (0, 0, -m g) bends joints 2..4
  (stiffness 1.5e5, 1.0e5, 4e4 N m/rad).
- gear: strain-wave transmission error at 101 per revolution on joints 2 and 3 (0.1 mrad).
- backlash: 0.25 mrad play on joints 1..3, against the direction each joint last moved.
- drift: joint 2 and 3 zeros creep 0.06 and -0.04 mrad/h.
- none: the clean control (geometric only).
"""
from __future__ import annotations

import numpy as np

from dt_runtime.measurements.dataset import Dataset

EFFECTS = ("none", "thermal", "compliance", "gear", "backlash", "drift")
# UR10 (CB3) published DH table: a (m), d (m), alpha (rad); the tool 109 mm along the flange z,
# the base turned pi about z (as in configs/robots/ur10.yaml, which the twin is given).
A = np.array([0.0, -0.612, -0.5723, 0.0, 0.0, 0.0])
D = np.array([0.1273, 0.0, 0.0, 0.163941, 0.1157, 0.0922])
ALPHA = np.array([np.pi / 2, 0.0, 0.0, np.pi / 2, -np.pi / 2, 0.0])
TOOL = 0.109
G = 9.80665


def fk(q: np.ndarray, a=A, d=D, alpha=ALPHA, theta0=None, scale=None, tool: float = TOOL,
       base_pi: bool = True) -> np.ndarray:
    """TCP positions (n, 3) of the standard-DH arm: T_i = Rz(q_i + theta0_i) Tz(d_i) Tx(a_i) Rx(alpha_i),
    lengths multiplied by `scale` (thermal expansion): (n,) for the whole arm, or (n, 7) per link
    (column i + 1 scales DH row i, column 6 the tool too; column 0, the base, has no length here).
    `tool`: the TCP along the flange's z (m); `base_pi`: the base turned pi about z (configs/robots/
    ur10.yaml's frame), else the DH base (the catalogue arm's)."""
    q = np.atleast_2d(q)
    n = len(q)
    th0 = np.zeros(6) if theta0 is None else theta0
    per_link = np.ones((n, 7)) if scale is None else np.asarray(scale, dtype=float)
    if per_link.ndim == 1:
        per_link = np.repeat(per_link[:, None], 7, axis=1)
    T = np.broadcast_to(np.diag([-1.0, -1.0, 1.0, 1.0]) if base_pi else np.eye(4), (n, 4, 4)).copy()
    for i in range(6):
        s = per_link[:, i + 1]
        th = q[:, i] + th0[i]
        ct, st, ca, sa = np.cos(th), np.sin(th), np.cos(alpha[i]), np.sin(alpha[i])
        Ti = np.zeros((n, 4, 4))
        Ti[:, 0, 0], Ti[:, 0, 1], Ti[:, 0, 2], Ti[:, 0, 3] = ct, -st * ca, st * sa, a[i] * ct * s
        Ti[:, 1, 0], Ti[:, 1, 1], Ti[:, 1, 2], Ti[:, 1, 3] = st, ct * ca, -ct * sa, a[i] * st * s
        Ti[:, 2, 1], Ti[:, 2, 2], Ti[:, 2, 3] = sa, ca, d[i] * s
        Ti[:, 3, 3] = 1.0
        T = T @ Ti
    return T[:, :3, 3] + T[:, :3, 2] * (tool * per_link[:, 6])[:, None]


def jacobian(q: np.ndarray, **kw) -> np.ndarray:
    """Positional Jacobian (n, 3, 6) by central differences (the generator's own, not the twin's)."""
    h = 1e-7
    cols = []
    for j in range(6):
        dq = np.zeros(6)
        dq[j] = h
        cols.append((fk(q + dq, **kw) - fk(q - dq, **kw)) / (2 * h))
    return np.stack(cols, axis=2)


def lagged(t: np.ndarray, air: np.ndarray, tau: float) -> np.ndarray:
    """The structure's temperature: dTs/dt = (T - Ts)/tau, integrated finely (1 s steps) from
    equilibrium (the generator's own integrator, not the twin's closed form)."""
    fine = np.arange(t[0], t[-1] + 1.0, 1.0)
    Tf = np.interp(fine, t, air)
    ts = np.empty_like(Tf)
    ts[0] = Tf[0]
    k = 1.0 / tau
    for i in range(1, len(fine)):  # Heun's method, 1 s steps << tau
        pred = ts[i - 1] + k * (Tf[i - 1] - ts[i - 1])
        ts[i] = ts[i - 1] + 0.5 * k * ((Tf[i - 1] - ts[i - 1]) + (Tf[i] - pred))
    return np.interp(t, fine, ts)


def generate(effect: str, seed: int, n_points: int = 60, passes: int = 4, dt_s: float = 60.0,
             noise_mm: float = 0.015, arm_seed: int | None = None, truth: dict | None = None,
             link_alpha: np.ndarray | None = None, order: str = "random", orientation: str = "varied",
             tool: float = TOOL, base_pi: bool = True, readings: int = 1, stated_u: bool = True) -> Dataset:
    """One campaign with the hidden `effect` (EFFECTS). `seed` draws the points, the path, the
    temperatures and the noise; `arm_seed` (default `seed`) the arm: a training and a test file
    of the same arm share it. `truth`, if given, receives the hidden values (e.g. tau_s).
    `link_alpha` (7,) 1/K: thermal expansion per link (fk's scale columns) instead of 23e-6 for all.
    `order`: "random" (every pass in a new order) or "cycle" (the repeatability programme, above).
    `orientation`: "varied" (the wrist anywhere) or "one" (q5, q6 fixed and q4 keeping the tool
    pointing down: the paper's DOE shape). `tool` (m along the flange's z) and `base_pi` (fk) shape
    the TCP the commanded positions are of. `readings`: each visit read that many times in a row
    (5 s apart: replicates under the same conditions). `stated_u`: write ux..uz (else no
    uncertainty columns)."""
    if effect not in EFFECTS:
        raise ValueError(f"effect {effect!r}; known: {EFFECTS}")
    if order not in ("random", "cycle"):
        raise ValueError(f"order {order!r}; known: random, cycle")
    arm = np.random.default_rng(1000 + (seed if arm_seed is None else arm_seed))
    rng = np.random.default_rng(seed)
    geo = {"a": A + arm.normal(0, 2e-4, 6) * (A != 0), "d": D + arm.normal(0, 2e-4, 6),
           "alpha": ALPHA + arm.normal(0, 2e-4, 6), "theta0": arm.normal(0, 2e-4, 6)}
    lo = np.array([-1.3, -2.3, -2.3, -2.6, 0.6, -2.5])
    hi = np.array([1.3, -0.9, -0.7, -0.6, 2.5, 2.5])
    targets = lo + (hi - lo) * rng.random((n_points, 6))
    rep = np.repeat(np.arange(passes), n_points)
    if order == "cycle":
        one = rng.permutation(n_points)
        visits = np.concatenate([one if rng.random() < 0.5 else one[::-1] for _ in range(passes)])
        moves = np.r_[True, visits[1:] != visits[:-1]]  # a reversal starts where the last pass ended: no move
        visits, rep = visits[moves], rep[moves]
    else:
        visits = np.concatenate([rng.permutation(n_points) for _ in range(passes)])
    if orientation == "one":
        targets[:, 4], targets[:, 5] = -np.pi / 2, 0.0
        targets[:, 3] = -np.pi / 2 - targets[:, 1] - targets[:, 2]
    elif orientation != "varied":
        raise ValueError(f"orientation {orientation!r}; known: varied, one")
    q_visit = targets[visits]  # the moves; each visit read `readings` times in a row
    row = np.repeat(np.arange(len(visits)), readings)
    visits, rep = visits[row], rep[row]
    q = targets[visits]
    n = len(q)
    t = np.repeat(np.arange(n // readings) * dt_s, readings) + np.tile(np.arange(readings) * 5.0, n // readings)
    hours = t / 3600
    # The air: a slow swing of +-2.5 K over ~3 h plus a warm-up ramp (logged as it is).
    air = 21.0 + 2.5 * np.sin(2 * np.pi * hours / rng.uniform(2.5, 3.5) + rng.uniform(0, 2 * np.pi)) + 0.4 * hours
    if order == "cycle":  # each point its own speed and payload
        speed = rng.choice([0.1, 0.25, 0.5], n_points)[visits]
        payload = rng.choice([0.0, 5.0, 10.0], n_points)[visits]
    else:
        speed = rng.choice([0.1, 0.25, 0.5], n // readings)[row]
        payload = rng.choice([0.0, 5.0, 10.0], n // readings)[row]
    dq = np.zeros((n, 6))
    scale: np.ndarray = np.ones(n)
    if effect == "thermal":
        tau = rng.uniform(20, 40) * 60
        if truth is not None:
            truth.update(tau_s=tau, alpha_per_K=23e-6, link_alpha=link_alpha)
        dT = lagged(t, air, tau) - 20.0
        scale = 1 + (23e-6 * dT if link_alpha is None else np.outer(dT, link_alpha))
    elif effect == "compliance":
        J = jacobian(q, **geo)
        torque = np.einsum("naj,a->nj", J, np.array([0.0, 0.0, -G])) * payload[:, None]
        k = np.array([np.inf, 1.5e5, 1.0e5, 4e4, np.inf, np.inf])
        dq += torque / k
    elif effect == "gear":
        dq[:, 1] += 1e-4 * np.sin(101 * q[:, 1] + 0.7)
        dq[:, 2] += 1e-4 * np.sin(101 * q[:, 2] + 2.1)
    elif effect == "backlash":
        move = np.diff(q_visit, axis=0, prepend=q_visit[:1] - rng.choice([-1, 1], 6) * 1e-3)
        dq[:, :3] += -0.5 * 2.5e-4 * np.sign(move[row, :3])  # repeated readings rest where the move left them
    elif effect == "drift":
        dq[:, 1] += 0.06e-3 * hours
        dq[:, 2] += -0.04e-3 * hours
    commanded = fk(q, tool=tool, base_pi=base_pi)
    actual = fk(q + dq, scale=scale, tool=tool, base_pi=base_pi, **geo)
    noise = rng.normal(0, noise_mm * 1e-3, (n, 3))
    error = commanded - (actual + noise)
    return Dataset(commanded=commanded, error=error, speed=speed, joints=q, temperature=air, payload=payload,
                   t=t, point_id=visits.astype(np.int64), rep=rep,
                   u=np.full((n, 3), noise_mm * 1e-3) if stated_u else None,
                   source=f"<ur10 generator {effect} seed {seed}>")


def noise_floor_mm(noise_mm: float = 0.015) -> float:
    """The generator's noise floor as a 3D RMS (mm)."""
    return float(np.sqrt(3) * noise_mm)
