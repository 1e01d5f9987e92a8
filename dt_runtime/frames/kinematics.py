"""The robot's nominal kinematic model on the twin side: forward kinematics, Jacobians and the
inverse kinematics of a position (the joint angles a deployed twin's joint-space effects read).

Read from a URDF (our simulated cobot ships one) or a DH table in config (the UR10's ships
in configs/robots/ur10.yaml). Vectorised numpy: the effect regressors of the hybrid model need
the TCP and its sensitivity to every joint for thousands of rows at once.
"""
from __future__ import annotations

import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated

import numpy as np
from pydantic import Field
from scipy.spatial.transform import Rotation

from dt_kernel.config import Frozen, load_yaml
from dt_kernel.errors import ConfigError, DataError, UnreachableError

MAX_IK_STEP_RAD = 0.2  # a Newton step longer than this near a singularity is shortened


@dataclass(frozen=True)
class Chain:
    """Serial chain: per joint a fixed transform from the parent (4x4) and a joint axis (3,),
    then a fixed tool transform. Revolute joints only."""

    origins: tuple[np.ndarray, ...]
    axes: tuple[np.ndarray, ...]
    tool: np.ndarray
    name: str = "robot"
    # Candidate harmonics of the transmission error per joint revolution (the gear effect's
    # regressors): from the gearbox design (tooth, wave-generator and bearing orders).
    gear_harmonics: tuple[int, ...] = (1, 2, 3)
    # Links that expand with one coefficient each (the thermal effect, per link): groups of link
    # numbers (`segments`); empty: the arm expands uniformly about its base.
    thermal_links: tuple[tuple[int, ...], ...] = ()

    @property
    def dof(self) -> int:
        return len(self.axes)

    def frames(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Joint frames for a batch q (n, dof): origins (n, dof, 3) and orientations
        (n, dof, 3, 3) of every joint frame before its rotation, and the TCP transform (n, 4, 4)."""
        q = np.atleast_2d(q)
        n = len(q)
        T = np.broadcast_to(np.eye(4), (n, 4, 4)).copy()
        pos = np.zeros((n, self.dof, 3))
        rot = np.zeros((n, self.dof, 3, 3))
        for j in range(self.dof):
            T = T @ self.origins[j]
            pos[:, j] = T[:, :3, 3]
            rot[:, j] = T[:, :3, :3]
            T = T @ _rot_axis(self.axes[j], q[:, j])
        return pos, rot, T @ self.tool

    def segments(self, q: np.ndarray) -> np.ndarray:
        """The links as vectors in the world (n, dof + 1, 3), summing to the TCP: link 0 from the
        robot frame's origin to joint 1's frame, link j from joint j's frame to joint j + 1's,
        link dof from the last joint's frame to the TCP (the tool included)."""
        pos, _, T = self.frames(q)
        ends = np.concatenate([pos, T[:, None, :3, 3]], axis=1)
        return np.diff(ends, axis=1, prepend=np.zeros((len(ends), 1, 3)))

    def world_axes(self, rot: np.ndarray) -> np.ndarray:
        """Joint axes in the world (n, dof, 3) from frame orientations."""
        return np.einsum("njab,jb->nja", rot, np.array(self.axes))

    def fk(self, q: np.ndarray) -> np.ndarray:
        """TCP positions (n, 3) in metres."""
        return self.frames(q)[2][:, :3, 3]

    def jacobian(self, q: np.ndarray) -> np.ndarray:
        """Positional Jacobian dTCP/dq (n, 3, dof): axis_j x (p_tcp - p_j)."""
        pos, rot, T = self.frames(q)
        p = T[:, None, :3, 3]
        return np.cross(self.world_axes(rot), p - pos).transpose(0, 2, 1)

    def jacobian6(self, q: np.ndarray) -> np.ndarray:
        """Geometric Jacobian (n, 6, dof): TCP linear velocity (rows 0-2) and angular velocity
        (rows 3-5) per joint rate."""
        pos, rot, T = self.frames(q)
        ax = self.world_axes(rot)
        lin = np.cross(ax, T[:, None, :3, 3] - pos)
        return np.concatenate([lin, ax], axis=2).transpose(0, 2, 1)

    def pose(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """TCP position (3,) and orientation (3, 3) for one joint vector."""
        T = self.frames(np.asarray(q, dtype=float)[None, :])[2][0]
        return T[:3, 3], T[:3, :3]

    def ik(self, target: np.ndarray, q_seed: np.ndarray, R: np.ndarray | None = None,
           tol: float = 1e-9, max_iter: int = 50) -> np.ndarray:
        """Joint angles putting the TCP at `target` (m) with orientation R (default: the TCP's
        at q_seed: a linear move keeps the tool's orientation). Gauss-Newton on the 6-D pose
        error with the geometric Jacobian (rows: axis_j x (p - p_j); axis_j), from q_seed, so the
        solution stays on the seed's branch. UnreachableError if it does not converge."""
        target = np.asarray(target, dtype=float)
        q = np.array(q_seed, dtype=float)
        finite = bool(np.all(np.isfinite(target)) and np.all(np.isfinite(q)))
        if target.shape != (3,) or q.shape != (self.dof,) or not finite:
            raise DataError(f"ik: target must be 3 finite numbers and q_seed {self.dof}, got {target!r}, {q!r}")
        Rt = self.pose(q)[1] if R is None else np.asarray(R, dtype=float)
        for _ in range(max_iter):
            pos, rot, T = self.frames(q[None, :])
            p, Rq = T[0, :3, 3], T[0, :3, :3]
            err = np.concatenate([target - p, Rotation.from_matrix(Rt @ Rq.T).as_rotvec()])
            if np.linalg.norm(err[:3]) < tol and np.linalg.norm(err[3:]) < tol:
                return q
            ax = self.world_axes(rot)[0]  # (dof, 3)
            J = np.vstack([np.cross(ax, p - pos[0]).T, ax.T])
            dq = np.linalg.lstsq(J, err, rcond=None)[0]
            norm = float(np.linalg.norm(dq))
            q = q + (dq if norm <= MAX_IK_STEP_RAD else dq * (MAX_IK_STEP_RAD / norm))  # no leaps off the branch
        p, Rq = self.pose(q)
        res = float(np.linalg.norm(target - p))
        rres = float(np.linalg.norm(Rotation.from_matrix(Rt @ Rq.T).as_rotvec()))
        if res > 1e-6 or rres > 1e-5:
            raise UnreachableError(f"target {np.round(target * 1e3, 2).tolist()} mm: no joint angles of {self.name} "
                                   f"reach it from the seed (residual {res * 1e3:.3g} mm, {rres:.3g} rad)")
        return q


def _rot_axis(axis: np.ndarray, angles: np.ndarray) -> np.ndarray:
    R = Rotation.from_rotvec(np.outer(angles, axis)).as_matrix()
    out = np.zeros((len(angles), 4, 4))
    out[:, :3, :3] = R
    out[:, 3, 3] = 1.0
    return out


def _transform(xyz, rpy) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("xyz", rpy).as_matrix()  # URDF rpy: fixed-axis x, y, z
    T[:3, 3] = xyz
    return T


def _urdf_attr(path: Path, elem: ET.Element, child: str | None, attr: str) -> str:
    """Attribute `attr` of `elem` (or of its `child` element), which the URDF requires;
    a missing one is a ConfigError naming the element."""
    what = f"{elem.tag} '{elem.get('name', '?')}'"
    if child is not None:
        found = elem.find(child)
        if found is None:
            raise ConfigError(path, f"{what}/{child}", None, f"a <{child}> element (required by URDF)")
        elem, what = found, f"{what}/{child}"
    value = elem.get(attr)
    if value is None:
        raise ConfigError(path, f"{what}@{attr}", None, f"a '{attr}' attribute (required by URDF)")
    return value


def chain_from_urdf(path: str | Path, tool_link: str | None = None) -> Chain:
    """Chain from the base to `tool_link` (default: the last link) of a URDF."""
    path = Path(path)
    try:
        root = ET.parse(path).getroot()
    except (OSError, ET.ParseError) as exc:
        raise ConfigError(path, "<file>", str(path), f"a readable URDF ({exc})") from exc
    joints = {_urdf_attr(path, j, "child", "link"): j for j in root.iter("joint")}
    links = [_urdf_attr(path, lk, None, "name") for lk in root.iter("link")]
    tip = tool_link or links[-1]
    if tip not in links:
        raise ConfigError(path, "tool_link", tip, "one of " + ", ".join(links))
    seq = []
    link = tip
    while link in joints:
        seq.append(joints[link])
        link = _urdf_attr(path, joints[link], "parent", "link")
    seq.reverse()
    origins, axes = [], []
    pending = np.eye(4)
    for j in seq:
        o = j.find("origin")
        xyz = [float(v) for v in (o.get("xyz", "0 0 0") if o is not None else "0 0 0").split()]
        rpy = [float(v) for v in (o.get("rpy", "0 0 0") if o is not None else "0 0 0").split()]
        T = pending @ _transform(xyz, rpy)
        if j.get("type") in ("revolute", "continuous"):
            a = j.find("axis")
            origins.append(T)
            axis_xyz = _urdf_attr(path, j, "axis", "xyz") if a is not None else "1 0 0"
            axes.append(np.array([float(v) for v in axis_xyz.split()]))
            pending = np.eye(4)
        else:
            pending = T
    return Chain(tuple(origins), tuple(axes), pending, name=root.get("name", "robot"))


class DHRow(Frozen):
    a_m: float
    d_m: float
    alpha_rad: float
    theta_offset_rad: float = 0.0


class RobotModel(Frozen):
    """configs/robots/*.yaml: a URDF path or a standard DH table, plus a tool offset."""

    name: str
    urdf: str | None = None
    dh: list[DHRow] | None = None
    tool_xyz_m: tuple[float, float, float] = (0.0, 0.0, 0.0)
    # Pose of the kinematic base in the robot frame the data uses (e.g. ROS 'base' vs 'base_link').
    base_xyz_m: tuple[float, float, float] = (0.0, 0.0, 0.0)
    base_rpy_rad: tuple[float, float, float] = (0.0, 0.0, 0.0)
    # Orders of the transmission error per joint revolution the gear effect tests for: a
    # strain-wave gear of ratio N has its wave generator's orders at N and 2N (ratios to ~160).
    gear_harmonics: tuple[Annotated[int, Field(ge=1, le=1000)], ...] = (1, 2, 3)
    # Links whose thermal expansion the thermal effect fits with a coefficient each (groups of
    # link numbers, Chain.segments: 0 base to joint 1, ..., dof last joint to TCP), e.g.
    # [[1], [2], [3], [4, 5, 6]]; links in no group are taken not to expand. Empty: uniform.
    thermal_links: tuple[tuple[Annotated[int, Field(ge=0)], ...], ...] = ()


def chain_from_dh(rows: list[DHRow], tool_xyz=(0.0, 0.0, 0.0), name="robot") -> Chain:
    """Standard DH: T_i = Rz(theta_i + offset) Tz(d) Tx(a) Rx(alpha); joints rotate about z."""
    origins, axes = [], []
    prev = np.eye(4)
    for r in rows:
        # Joint i rotates about z of frame i-1; the fixed part of row i follows the rotation.
        origins.append(prev @ _transform([0, 0, 0], [0, 0, r.theta_offset_rad]))
        axes.append(np.array([0.0, 0.0, 1.0]))
        fixed = np.eye(4)
        fixed[:3, 3] = [r.a_m, 0.0, r.d_m]
        ca, sa = np.cos(r.alpha_rad), np.sin(r.alpha_rad)
        rx = np.eye(4)
        rx[1:3, 1:3] = [[ca, -sa], [sa, ca]]
        # Tz(d) Tx(a) commute into one translation (d along z, a along x) before Rx(alpha).
        prev = fixed @ rx
    tool = prev @ _transform(tool_xyz, [0, 0, 0])
    return Chain(tuple(origins), tuple(axes), tool, name=name)


def load_robot(path: str | Path) -> Chain:
    path = Path(path)
    m = load_yaml(path, RobotModel)
    if (m.urdf is None) == (m.dh is None):
        raise ConfigError(path, "urdf/dh", None, "exactly one of 'urdf' (a path) or 'dh' (a table)")
    if m.urdf is not None:
        chain = chain_from_urdf((path.parent / m.urdf).resolve())
        chain = Chain(chain.origins, chain.axes, chain.tool @ _transform(m.tool_xyz_m, [0, 0, 0]), m.name)
    else:
        assert m.dh is not None  # exactly one of urdf/dh is set, checked above
        chain = chain_from_dh(m.dh, m.tool_xyz_m, m.name)
    links = [j for g in m.thermal_links for j in g]
    if any(not g for g in m.thermal_links) or len(set(links)) != len(links) or any(j > chain.dof for j in links):
        raise ConfigError(path, "thermal_links", [list(g) for g in m.thermal_links],
                          f"non-empty groups of link numbers 0..{chain.dof}, each link in one group at most")
    base = _transform(m.base_xyz_m, m.base_rpy_rad)
    return Chain((base @ chain.origins[0],) + chain.origins[1:], chain.axes, chain.tool, chain.name,
                 tuple(m.gear_harmonics), tuple(tuple(g) for g in m.thermal_links))
