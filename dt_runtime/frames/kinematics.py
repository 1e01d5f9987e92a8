"""The robot's nominal kinematic model on the twin side: forward kinematics, Jacobians and the
inverse kinematics of a position (the joint angles a deployed twin's joint-space effects read).

Read from a robot config YAML (`load_robot`): a URDF, a standard or modified (Craig) DH table,
a URDF-style joint table, or a catalogue arm (`frames.robots`); any number of revolute joints.
Vectorised numpy: the effect regressors need thousands of rows at once. See docs/robots.md.
"""
from __future__ import annotations

import xml.etree.ElementTree as ET
from dataclasses import dataclass, replace
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
    # Whether `tool` holds the TCP the data measure (a tool offset given or fitted), or only the
    # flange (a catalogue arm, a bare URDF): then the offset is fitted from the data (tool_fit).
    tool_given: bool = True

    @property
    def dof(self) -> int:
        """Number of joints."""
        return len(self.axes)

    @property
    def reach_m(self) -> float:
        """An upper bound of the TCP's distance from the base (m): the links' lengths summed (a
        revolute joint turns a link, never stretches it)."""
        return float(sum(np.linalg.norm(o[:3, 3]) for o in self.origins) + np.linalg.norm(self.tool[:3, 3]))

    def with_tool(self, offset) -> Chain:
        """This chain with the TCP moved by `offset` (m, in the current tool frame).

        The tool offset that `frames.tool_fit` fitted on a chain whose tool is its flange.

        Parameters
        ----------
        offset : array-like
            (3,), m.

        Returns
        -------
        Chain
        """
        T = np.eye(4)
        T[:3, 3] = np.asarray(offset, dtype=float)
        return replace(self, tool=self.tool @ T, tool_given=True)

    def frames(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Joint frames for a batch of joint vectors.

        Parameters
        ----------
        q : ndarray
            (n, dof) or (dof,), rad.

        Returns
        -------
        origins : ndarray
            (n, dof, 3) of every joint frame before its rotation.
        orientations : ndarray
            (n, dof, 3, 3).
        tcp : ndarray
            (n, 4, 4) TCP transforms.
        """
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
        """The links as vectors in the world, summing to the TCP.

        Link 0 runs from the robot frame's origin to joint 1's frame, link j from joint j's frame to
        joint j + 1's, link dof from the last joint's frame to the TCP (the tool included).

        Parameters
        ----------
        q : ndarray
            (n, dof), rad.

        Returns
        -------
        ndarray
            (n, dof + 1, 3), m.
        """
        pos, _, T = self.frames(q)
        ends = np.concatenate([pos, T[:, None, :3, 3]], axis=1)
        return np.diff(ends, axis=1, prepend=np.zeros((len(ends), 1, 3)))

    def world_axes(self, rot: np.ndarray) -> np.ndarray:
        """Joint axes in the world from frame orientations.

        Parameters
        ----------
        rot : ndarray
            (n, dof, 3, 3), from `frames`.

        Returns
        -------
        ndarray
            (n, dof, 3).
        """
        return np.einsum("njab,jb->nja", rot, np.array(self.axes))

    def fk(self, q: np.ndarray) -> np.ndarray:
        """TCP positions in metres.

        Parameters
        ----------
        q : ndarray
            (n, dof), rad.

        Returns
        -------
        ndarray
            (n, 3).
        """
        return self.frames(q)[2][:, :3, 3]

    def jacobian(self, q: np.ndarray) -> np.ndarray:
        """Positional Jacobian dTCP/dq: axis_j x (p_tcp - p_j).

        Parameters
        ----------
        q : ndarray
            (n, dof), rad.

        Returns
        -------
        ndarray
            (n, 3, dof).
        """
        pos, rot, T = self.frames(q)
        p = T[:, None, :3, 3]
        return np.cross(self.world_axes(rot), p - pos).transpose(0, 2, 1)

    def jacobian6(self, q: np.ndarray) -> np.ndarray:
        """Geometric Jacobian: TCP linear velocity (rows 0-2) and angular velocity (rows 3-5) per joint rate.

        Parameters
        ----------
        q : ndarray
            (n, dof), rad.

        Returns
        -------
        ndarray
            (n, 6, dof).
        """
        pos, rot, T = self.frames(q)
        ax = self.world_axes(rot)
        lin = np.cross(ax, T[:, None, :3, 3] - pos)
        return np.concatenate([lin, ax], axis=2).transpose(0, 2, 1)

    def pose(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """TCP position and orientation for one joint vector.

        Parameters
        ----------
        q : ndarray
            (dof,), rad.

        Returns
        -------
        position : ndarray
            (3,), m.
        orientation : ndarray
            (3, 3).
        """
        T = self.frames(np.asarray(q, dtype=float)[None, :])[2][0]
        return T[:3, 3], T[:3, :3]

    def ik(self, target: np.ndarray, q_seed: np.ndarray, R: np.ndarray | None = None,
           tol: float = 1e-9, max_iter: int = 50) -> np.ndarray:
        """Joint angles putting the TCP at `target` (m) with orientation R (default: the TCP's
        at q_seed: a linear move keeps the tool's orientation). Gauss-Newton on the 6-D pose
        error with the geometric Jacobian (rows: axis_j x (p - p_j); axis_j), from q_seed, so the
        solution stays on the seed's branch. UnreachableError if it does not converge.

        Parameters
        ----------
        target : ndarray
            (3,), m.
        q_seed : ndarray
            (dof,), rad: the start, whose branch the solution keeps.
        R : ndarray, optional
            (3, 3) orientation; default the TCP's at q_seed.
        tol : float, optional
            Convergence tolerance on position (m) and orientation (rad).
        max_iter : int, optional
            At most this many steps.

        Returns
        -------
        ndarray
            (dof,), rad.

        Raises
        ------
        UnreachableError
            When it does not converge.
        DataError
            When target or q_seed is not finite or has the wrong length.
        """
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
    """Rotations about the unit `axis` by `angles` (n,) as (n, 4, 4): Rodrigues' formula,
    R = I + sin q K + (1 - cos q) K^2 (scipy's Rotation costs ~50 us a call here, per joint)."""
    a = np.asarray(axis, dtype=float)
    K = np.array([[0.0, -a[2], a[1]], [a[2], 0.0, -a[0]], [-a[1], a[0], 0.0]])
    out = np.zeros((len(angles), 4, 4))
    out[:, :3, :3] = np.eye(3) + np.sin(angles)[:, None, None] * K + (1.0 - np.cos(angles))[:, None, None] * (K @ K)
    out[:, 3, 3] = 1.0
    return out


def _transform(xyz, rpy) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("xyz", rpy).as_matrix()  # URDF rpy: fixed-axis x, y, z
    T[:3, 3] = xyz
    return T


def _unit_axis(axis, where: str, path: str | Path) -> np.ndarray:
    a = np.asarray(axis, dtype=float)
    n = float(np.linalg.norm(a))
    if a.shape != (3,) or not np.isfinite(n) or n < 1e-9:
        raise ConfigError(path, where, list(np.ravel(a)), "a non-zero 3-vector (the joint's rotation axis)")
    return a / n


# --------------------------------------------------------------------------- URDF
# Joint types a chain to the tool link may hold: the twin's chains are revolute (continuous is a
# revolute joint without limits); fixed joints fold into the next transform.
URDF_ROTATING = ("revolute", "continuous")


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


def _read_urdf(path: Path):
    """The URDF's model as yourdfpy parses it (kinematics only: no meshes, no scene graph).

    yourdfpy recovers from broken XML and crashes on a joint without <child>; a user's file
    deserves the element at fault instead, so the elements and attributes the chain needs are
    checked first (ConfigError naming the file, the element and what URDF requires)."""
    try:
        root = ET.parse(path).getroot()
    except (OSError, ET.ParseError) as exc:
        raise ConfigError(path, "<file>", str(path), f"a readable URDF ({exc})") from exc
    if root.tag != "robot":
        raise ConfigError(path, "<root>", root.tag, "a <robot> element (URDF)")
    for lk in root.iter("link"):
        _urdf_attr(path, lk, None, "name")
    for j in root.iter("joint"):
        _urdf_attr(path, j, None, "name")
        _urdf_attr(path, j, None, "type")
        _urdf_attr(path, j, "parent", "link")
        _urdf_attr(path, j, "child", "link")
        if j.find("axis") is not None:
            _urdf_attr(path, j, "axis", "xyz")
    import yourdfpy  # here: 0.6 s of imports (trimesh) that a DH robot does not need

    try:
        return yourdfpy.URDF.load(str(path), build_scene_graph=False, load_meshes=False,
                                  load_collision_meshes=False).robot
    except Exception as exc:  # yourdfpy raises what its parsing meets (ValueError, KeyError, ...)
        raise ConfigError(path, "<file>", str(path), f"a URDF yourdfpy can read ({type(exc).__name__}: {exc})") \
            from exc


def chain_from_urdf(path: str | Path, tool_link: str | None = None) -> Chain:
    """Chain from the root link to `tool_link` (default: the last link) of a URDF, parsed by
    yourdfpy. Revolute and continuous joints turn; fixed joints fold into the next transform;
    any other joint type on the way (prismatic, floating, mimic) is a ConfigError.

    Parameters
    ----------
    path : str or Path
        The URDF file.
    tool_link : str, optional
        The link the chain ends at.

    Returns
    -------
    Chain
    """
    path = Path(path)
    robot = _read_urdf(path)
    links = [lk.name for lk in robot.links]
    if not links:
        raise ConfigError(path, "link", None, "at least one <link>")
    tip = tool_link or links[-1]
    if tip not in links:
        raise ConfigError(path, "tool_link", tip, "one of " + ", ".join(links))
    by_child = {j.child: j for j in robot.joints}
    seq = []
    link = tip
    while link in by_child:
        seq.append(by_child[link])
        link = by_child[link].parent
        if len(seq) > len(robot.joints):
            raise ConfigError(path, "joint", seq[-1].name, "a tree (the joints form a loop)")
    seq.reverse()
    origins, axes = [], []
    pending = np.eye(4)
    for j in seq:
        T = pending @ (np.eye(4) if j.origin is None else np.asarray(j.origin, dtype=float))
        if j.type in URDF_ROTATING and j.mimic is None:
            origins.append(T)
            axes.append(_unit_axis([1.0, 0.0, 0.0] if j.axis is None else j.axis, f"joint '{j.name}'/axis@xyz", path))
            pending = np.eye(4)
        elif j.type == "fixed":
            pending = T
        else:
            kind = f"{j.type} (mimic of {j.mimic.joint})" if j.mimic is not None else j.type
            raise ConfigError(path, f"joint '{j.name}'@type", kind,
                              f"revolute, continuous or fixed joints from the root to '{tip}' (the twin's chains "
                              "are revolute)")
    return Chain(tuple(origins), tuple(axes), pending, name=robot.name or "robot", tool_given=False)


# --------------------------------------------------------------------------- tables
class DHRow(Frozen):
    """One row of a DH table. Standard DH (`dh:`): T_i = Rz(q_i + theta_offset) Tz(d) Tx(a) Rx(alpha).
    Modified DH after Craig (`mdh:`): T_i = Rx(alpha) Tx(a) Rz(q_i + theta_offset) Tz(d), where a and
    alpha are Craig's a_{i-1}, alpha_{i-1} (the row of joint i in a vendor's Craig table)."""

    a_m: float
    d_m: float
    alpha_rad: float
    theta_offset_rad: float = 0.0


class JointOrigin(Frozen):
    """One revolute joint as a URDF gives it: the fixed transform from the previous joint's frame
    (xyz, fixed-axis roll-pitch-yaw) and the rotation axis in the joint's frame."""

    xyz_m: tuple[float, float, float]
    rpy_rad: tuple[float, float, float] = (0.0, 0.0, 0.0)
    axis: tuple[float, float, float] = (0.0, 0.0, 1.0)


class Source(Frozen):
    """Where a catalogue arm's numbers come from: a vendor document or the vendor's own
    description file, at a version or commit."""

    title: str
    url: str
    version: str
    licence: str | None = None
    notes: str = ""


class RobotModel(Frozen):
    """configs/robots/*.yaml: the nominal kinematics (exactly one of a URDF path, a standard or
    modified DH table, a URDF-style joint table, or a catalogue arm), the flange after the last
    joint, the tool offset and the base pose."""

    name: str
    vendor: str = ""
    description: str = ""
    sources: tuple[Source, ...] = ()
    urdf: str | None = None
    tool_link: str | None = None  # with urdf: the chain's last link (default: the URDF's last link)
    dh: list[DHRow] | None = None
    mdh: list[DHRow] | None = None
    joint_origins: list[JointOrigin] | None = None
    arm: str | None = None  # a catalogue arm (configs/robots/catalogue/<arm>.yaml) this config adds to
    # The flange (the tool's mounting frame) in the last joint's frame, after its rotation.
    flange_xyz_m: tuple[float, float, float] = (0.0, 0.0, 0.0)
    flange_rpy_rad: tuple[float, float, float] = (0.0, 0.0, 0.0)
    # The TCP (e.g. the SMR centre) in the flange frame. Not given: fitted from the data where the
    # data allow it (frames.tool_fit), else the TCP is the flange.
    tool_xyz_m: tuple[float, float, float] | None = None
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


KINEMATICS = ("urdf", "dh", "mdh", "joint_origins", "arm")


def chain_from_dh(rows: list[DHRow], tool_xyz=(0.0, 0.0, 0.0), name="robot") -> Chain:
    """Standard DH: T_i = Rz(theta_i + offset) Tz(d) Tx(a) Rx(alpha); joints rotate about z.

    Parameters
    ----------
    rows : list of DHRow
        One per joint.
    tool_xyz : tuple of float, optional
        The TCP in the last frame, m.
    name : str, optional
        The chain's name.

    Returns
    -------
    Chain
    """
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


def chain_from_mdh(rows: list[DHRow], name="robot") -> Chain:
    """Modified DH (Craig): T_i = Rx(alpha_{i-1}) Tx(a_{i-1}) Rz(theta_i + offset) Tz(d_i); joint i
    rotates about z of frame i. The chain's tool is frame n (the flange follows, `RobotModel`).

    Parameters
    ----------
    rows : list of DHRow
        One per joint (Craig's a_{i-1}, alpha_{i-1} in the row of joint i).
    name : str, optional
        The chain's name.

    Returns
    -------
    Chain
    """
    origins, axes = [], []
    prev = np.eye(4)
    for r in rows:
        # Rx(alpha) Tx(a) commute (a translation along the rotation's own axis).
        fixed = _transform([r.a_m, 0.0, 0.0], [r.alpha_rad, 0.0, 0.0])
        origins.append(prev @ fixed @ _transform([0, 0, 0], [0, 0, r.theta_offset_rad]))
        axes.append(np.array([0.0, 0.0, 1.0]))
        prev = _transform([0.0, 0.0, r.d_m], [0, 0, 0])  # Tz(d_i) after the joint's rotation
    return Chain(tuple(origins), tuple(axes), prev, name=name)


def chain_from_joint_origins(rows: list[JointOrigin], name="robot", path: str | Path = "<robot>") -> Chain:
    """A URDF-style table: joint i's frame is its origin (xyz, rpy) in joint i-1's frame after i-1's
    rotation; it turns about its axis. The chain's tool is the last joint's frame.

    Parameters
    ----------
    rows : list of JointOrigin
        One per joint.
    name : str, optional
        The chain's name.
    path : str or Path, optional
        The file the table came from, for errors.

    Returns
    -------
    Chain
    """
    origins = tuple(_transform(r.xyz_m, r.rpy_rad) for r in rows)
    axes = tuple(_unit_axis(r.axis, f"joint_origins.{i}.axis", path) for i, r in enumerate(rows))
    return Chain(origins, axes, np.eye(4), name=name)


def load_robot(path: str | Path) -> Chain:
    """The chain of a robot config YAML (configs/robots/*.yaml, the catalogue's entries among them).

    Parameters
    ----------
    path : str or Path
        The robot config YAML.

    Returns
    -------
    Chain

    Raises
    ------
    ConfigError
        Naming the file, key, value and what is allowed.
    """
    path = Path(path)
    m = load_yaml(path, RobotModel)
    given = [k for k in KINEMATICS if getattr(m, k) is not None]
    if len(given) != 1:
        raise ConfigError(path, "/".join(KINEMATICS), given or None,
                          "exactly one of 'urdf' (a path), 'dh' (standard DH table), 'mdh' (modified DH, Craig), "
                          "'joint_origins' (URDF-style joint table) or 'arm' (a catalogue name)")
    if m.tool_link is not None and m.urdf is None:
        raise ConfigError(path, "tool_link", m.tool_link, "only with 'urdf' (the URDF link the chain ends at)")
    if m.urdf is not None:
        chain = chain_from_urdf((path.parent / m.urdf).resolve(), m.tool_link)
    elif m.dh is not None:
        chain = chain_from_dh(m.dh, name=m.name)
    elif m.mdh is not None:
        chain = chain_from_mdh(m.mdh, name=m.name)
    elif m.joint_origins is not None:
        chain = chain_from_joint_origins(m.joint_origins, m.name, path)
    else:
        assert m.arm is not None  # exactly one kinematics is set, checked above
        from dt_runtime.frames.robots import catalogue_file  # the catalogue is configs: robots.py finds it

        chain = load_robot(catalogue_file(m.arm, path))
    if chain.dof == 0:
        raise ConfigError(path, "/".join(KINEMATICS), None, "at least one revolute joint")
    links = [j for g in m.thermal_links for j in g]
    if any(not g for g in m.thermal_links) or len(set(links)) != len(links) or any(j > chain.dof for j in links):
        raise ConfigError(path, "thermal_links", [list(g) for g in m.thermal_links],
                          f"non-empty groups of link numbers 0..{chain.dof}, each link in one group at most")
    tool = chain.tool @ _transform(m.flange_xyz_m, m.flange_rpy_rad)
    if m.tool_xyz_m is not None:
        tool = tool @ _transform(m.tool_xyz_m, [0, 0, 0])
    base = _transform(m.base_xyz_m, m.base_rpy_rad)
    return Chain((base @ chain.origins[0],) + chain.origins[1:], chain.axes, tool, m.name,
                 tuple(m.gear_harmonics), tuple(tuple(g) for g in m.thermal_links),
                 tool_given=m.tool_xyz_m is not None or (m.arm is not None and chain.tool_given))
