"""A small seeded laser-tracker campaign of a 7-axis arm, the Franka Panda, with its own forward
kinematics: the published modified (Craig) DH table (Franka's control_parameters documentation)
written out here, not the project's chain, so the twin's kinematics are tested against it.

The truth: the nominal table with small joint zero offsets (0.3 mrad, 1 sigma) and link length
errors (0.1 mm on every a and d), an SMR on the flange at TOOL_M (flange frame); the tracker
measures the SMR with 0.02 mm noise per axis in the robot frame. The commanded TCP is the nominal
FK of the joints with the SMR offset the controller was told (TOOL_M).

    truth = write_campaign(tmp_path, seed=3)   # panda.csv (contract table), panda_joints.csv + mapping
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

H = np.pi / 2
# (a_{i-1} m, d_i m, alpha_{i-1} rad), Craig's convention; then the flange 0.107 m along z
TABLE = ((0.0, 0.333, 0.0), (0.0, 0.0, -H), (0.0, 0.316, H), (0.0825, 0.0, H), (-0.0825, 0.384, -H),
         (0.0, 0.0, H), (0.088, 0.0, H))
FLANGE_M = 0.107
TOOL_M = np.array([0.012, -0.006, 0.095])  # the SMR in the flange frame
# joint ranges used (rad): within the Panda's limits, away from the wrist singularity
LO = np.array([-2.0, -1.2, -2.0, -2.8, -2.0, 0.6, -2.0])
HI = np.array([2.0, 1.2, 2.0, -0.6, 2.0, 3.2, 2.0])


def _rx(a):
    c, s = np.cos(a), np.sin(a)
    return np.array([[1, 0, 0, 0], [0, c, -s, 0], [0, s, c, 0], [0, 0, 0, 1.0]])


def _rz(a):
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0, 0], [s, c, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1.0]])


def _t(x, y, z):
    T = np.eye(4)
    T[:3, 3] = (x, y, z)
    return T


def flange(q, dq=None, da=None, dd=None):
    """The flange pose (4x4) of one joint vector: T = prod Rx(alpha) Tx(a) Rz(q) Tz(d), then Tz(0.107)."""
    dq = np.zeros(7) if dq is None else dq
    da = np.zeros(7) if da is None else da
    dd = np.zeros(7) if dd is None else dd
    T = np.eye(4)
    for i, (a, d, alpha) in enumerate(TABLE):
        T = T @ _rx(alpha) @ _t(a + da[i], 0, 0) @ _rz(q[i] + dq[i]) @ _t(0, 0, d + dd[i])
    return T @ _t(0, 0, FLANGE_M)


@dataclass
class Truth:
    q: np.ndarray
    commanded: np.ndarray  # m
    measured: np.ndarray  # m
    dq: np.ndarray
    da: np.ndarray
    dd: np.ndarray
    tool: np.ndarray
    files: dict


def write_campaign(directory: Path, seed: int = 3, n_points: int = 50, reps: int = 4,
                   noise_m: float = 2e-5) -> Truth:
    """n_points random joint configurations, each measured `reps` times in a shuffled order:
    panda.csv (x, y, z, speed, q1..q7, mx, my, mz, point_id, rep; mm and rad) and, for the
    import path without commanded positions, panda_joints.csv (q1..q7 in degrees, mx..mz) with
    panda_mapping.yaml (robot: panda)."""
    rng = np.random.default_rng(seed)
    dq = rng.normal(0, 3e-4, 7)
    da = rng.normal(0, 1e-4, 7)
    dd = rng.normal(0, 1e-4, 7)
    pts = rng.uniform(LO, HI, (n_points, 7))
    order = rng.permutation(np.repeat(np.arange(n_points), reps))
    rep = np.zeros(len(order), int)
    seen: dict[int, int] = {}
    for i, p in enumerate(order):
        rep[i] = seen.get(int(p), 0)
        seen[int(p)] = rep[i] + 1
    q = pts[order]
    cmd = np.array([(T := flange(qq))[:3, 3] + T[:3, :3] @ TOOL_M for qq in q])
    true = np.array([(T := flange(qq, dq, da, dd))[:3, 3] + T[:3, :3] @ TOOL_M for qq in q])
    meas = true + rng.normal(0, noise_m, true.shape)
    speed = rng.choice([100.0, 250.0, 500.0], len(q))
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    head = ["point_id", "rep", "x", "y", "z", "speed", *[f"q{j}" for j in range(1, 8)], "mx", "my", "mz"]
    lines = [",".join(head)]
    for i in range(len(q)):
        lines.append(",".join([str(order[i]), str(rep[i]), *(f"{v * 1e3:.6f}" for v in cmd[i]), f"{speed[i]:g}",
                               *(f"{v:.9f}" for v in q[i]), *(f"{v * 1e3:.6f}" for v in meas[i])]))
    (directory / "panda.csv").write_text("\n".join(lines) + "\n")
    jl = ["point;rep;" + ";".join(f"A{j} [deg]" for j in range(1, 8)) + ";X;Y;Z"]
    for i in range(len(q)):
        jl.append(";".join([str(order[i]), str(rep[i]), *(f"{v:.8f}" for v in np.degrees(q[i])),
                            *(f"{v * 1e3:.6f}" for v in meas[i])]))
    (directory / "panda_joints.csv").write_text("\n".join(jl) + "\n")
    (directory / "panda_mapping.yaml").write_text(
        'format_version: 1\nseparator: ";"\n'
        "columns:\n  point_id: point\n  rep: rep\n  mx: X\n  my: Y\n  mz: Z\n"
        "  joints: [" + ", ".join(f'"A{j} [deg]"' for j in range(1, 8)) + "]\n"
        "units: {joints: deg, measurement: mm}\nmeasured_frame: robot\nrobot: panda\n")
    files = {"table": directory / "panda.csv", "joints": directory / "panda_joints.csv",
             "mapping": directory / "panda_mapping.yaml"}
    return Truth(q, cmd, meas, dq, da, dd, TOOL_M, files)
