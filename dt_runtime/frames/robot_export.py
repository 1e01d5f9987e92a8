"""A kinematic chain written for other tools: URDF text (`urdf_text`), and a standard DH table in
the robot config format (`dh_table`; configs/robots/*.yaml, read back by `kinematics.load_robot`).

Both are exact representations of a revolute `Chain`'s TCP position kinematics, not fits.
See docs/robots.md and docs/cli.md ("dt export").
"""
from __future__ import annotations

from dataclasses import dataclass
from xml.sax.saxutils import escape

import numpy as np
from scipy.spatial.transform import Rotation

from dt_runtime.frames.kinematics import Chain

PARALLEL_SIN = 1e-12  # sine of the angle below which two axes count as parallel


def _num(x: float) -> str:
    """A float written so that it reads back bit for bit (repr), -0 as 0."""
    return repr(float(x) + 0.0)


def _xyz_rpy(T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    return T[:3, 3], Rotation.from_matrix(T[:3, :3]).as_euler("xyz")


def urdf_text(chain: Chain, name: str | None = None, comment: str = "",
              joint_limit_rad: float = 2 * np.pi) -> str:
    """The chain as a URDF: links base_link, link1..linkN, tcp; revolute joints j1..jN with the
    chain's origins and axes; a fixed joint `tcp_fixed` with the tool transform. Limits are
    +/- joint_limit_rad (the chain does not know the arm's limits; URDF requires some).

    One revolute joint per chain joint, its `<origin>` the chain's fixed transform from the parent
    (xyz, fixed-axis rpy as URDF defines them), its `<axis>` the chain's axis, then a fixed joint to
    the TCP link holding the tool transform.

    Parameters
    ----------
    chain : Chain
        The chain.
    name : str, optional
        The robot's name (default the chain's).
    comment : str, optional
        A comment written at the top.
    joint_limit_rad : float, optional
        The joints' limits, +/-.

    Returns
    -------
    str
    """
    name = name or chain.name
    out = ['<?xml version="1.0"?>']
    if comment:
        out.append("<!-- " + escape(comment.replace("--", "- -")) + " -->")
    out.append(f'<robot name="{escape(name)}">')
    links = ["base_link"] + [f"link{j + 1}" for j in range(chain.dof)] + ["tcp"]
    out += [f'  <link name="{lk}"/>' for lk in links]
    for j in range(chain.dof):
        xyz, rpy = _xyz_rpy(chain.origins[j])
        axis = np.asarray(chain.axes[j], dtype=float)
        out += [f'  <joint name="j{j + 1}" type="revolute">',
                f'    <parent link="{links[j]}"/>',
                f'    <child link="{links[j + 1]}"/>',
                f'    <origin xyz="{" ".join(map(_num, xyz))}" rpy="{" ".join(map(_num, rpy))}"/>',
                f'    <axis xyz="{" ".join(map(_num, axis))}"/>',
                f'    <limit lower="{_num(-joint_limit_rad)}" upper="{_num(joint_limit_rad)}" '
                'effort="0" velocity="0"/>',
                "  </joint>"]
    xyz, rpy = _xyz_rpy(chain.tool)
    out += ['  <joint name="tcp_fixed" type="fixed">',
            f'    <parent link="{links[-2]}"/>',
            '    <child link="tcp"/>',
            f'    <origin xyz="{" ".join(map(_num, xyz))}" rpy="{" ".join(map(_num, rpy))}"/>',
            "  </joint>",
            "</robot>", ""]
    return "\n".join(out)


@dataclass(frozen=True)
class DHTable:
    """A standard DH table with base pose and tool offset (the robot config's keys)."""

    rows: tuple[tuple[float, float, float, float], ...]  # (a_m, d_m, alpha_rad, theta_offset_rad)
    base_xyz_m: tuple[float, float, float]
    base_rpy_rad: tuple[float, float, float]
    tool_xyz_m: tuple[float, float, float]
    long_rows: tuple[int, ...] = ()  # 1-based rows with |d| or |a| > 10 x reach (nearly parallel axes)

    def yaml_text(self, name: str, gear_harmonics: tuple[int, ...] = (), comment: str = "") -> str:
        """The robot config YAML (configs/robots/*.yaml format; `load_robot` reads it).

        Parameters
        ----------
        name : str
            The robot's name.
        gear_harmonics : tuple of int, optional
            The config's candidate gear harmonics.
        comment : str, optional
            A comment written at the top.

        Returns
        -------
        str
        """
        out = [f"# {line}" if line else "#" for line in comment.splitlines()]
        out.append(f"name: {name}")
        out.append("dh:")
        for a, d, alpha, off in self.rows:
            out.append(f"  - {{a_m: {_num(a)}, d_m: {_num(d)}, alpha_rad: {_num(alpha)}, "
                       f"theta_offset_rad: {_num(off)}}}")
        out.append(f"tool_xyz_m: [{', '.join(map(_num, self.tool_xyz_m))}]")
        out.append(f"base_xyz_m: [{', '.join(map(_num, self.base_xyz_m))}]")
        out.append(f"base_rpy_rad: [{', '.join(map(_num, self.base_rpy_rad))}]")
        if gear_harmonics:
            out.append(f"gear_harmonics: [{', '.join(str(int(h)) for h in gear_harmonics)}]")
        return "\n".join(out) + "\n"


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v)


def _perpendicular(z: np.ndarray) -> np.ndarray:
    """A unit vector perpendicular to z: world x projected, else world y."""
    for c in (np.array([1.0, 0, 0]), np.array([0, 1.0, 0])):
        v = c - (c @ z) * z
        if np.linalg.norm(v) > 1e-6:
            return _unit(v)
    raise AssertionError("unreachable: x and y cannot both be parallel to a unit z")


def _angle(u: np.ndarray, v: np.ndarray, about: np.ndarray) -> float:
    """Signed angle from u to v about the unit vector `about` (u, v perpendicular to it)."""
    return float(np.arctan2(np.cross(u, v) @ about, u @ v))


def dh_table(chain: Chain) -> DHTable:
    """The chain's standard DH table (exact for the TCP position).

    T_i = Rz(q_i + theta_offset) Tz(d) Tx(a) Rx(alpha), as `chain_from_dh`: computed from the
    joint axes as lines in space at the zero pose (the common normal of consecutive axes), with
    the base pose (`base_xyz_m`, `base_rpy_rad`) placing DH frame 0 on the first axis and
    `tool_xyz_m` the TCP in the last frame. Any serial revolute chain has such a table, but
    standard DH is singular for parallel axes: two nominally parallel axes tilted towards each
    other by a small angle eps meet a distance ~ L / eps away, which becomes d. The table is
    still exact (double precision keeps the TCP to ~1e-12 m), but a tool may find such a d odd;
    every row whose |d| or |a| exceeds ten times the arm's reach is reported.

    Parameters
    ----------
    chain : Chain
        A serial revolute chain.

    Returns
    -------
    DHTable
    """
    pos, rot, T = chain.frames(np.zeros((1, chain.dof)))
    points = pos[0]
    z_axes = [_unit(rot[0, j] @ np.asarray(chain.axes[j], dtype=float)) for j in range(chain.dof)]
    reach = max(float(np.max(np.linalg.norm(points - points[0], axis=1))),
                float(np.linalg.norm(T[0, :3, 3] - points[0])), 1e-3)
    origin = points[0]  # frame 0: origin on axis 1
    x_prev: np.ndarray | None = None  # frame 0's x: chosen as frame 1's (theta_offset_1 = 0)
    rows: list[tuple[float, float, float, float]] = []
    frames: list[tuple[np.ndarray, np.ndarray]] = []  # (origin, x) of frames 0..n-1
    long_rows = []
    for k in range(chain.dof - 1):
        zk, zn, p = z_axes[k], z_axes[k + 1], points[k + 1]
        n = np.cross(zk, zn)
        w = p - origin
        if np.linalg.norm(n) > PARALLEL_SIN:
            x = _unit(n)
            b, dz, e = zk @ zn, zk @ (origin - p), zn @ (origin - p)
            den = 1.0 - b * b
            t_k, t_n = (b * e - dz) / den, (e - b * dz) / den
            d = float(t_k)
            new_origin = p + t_n * zn
        else:
            v = w - (w @ zk) * zk
            if np.linalg.norm(v) > 1e-12:  # parallel: the common normal through this origin
                x, d = _unit(v), 0.0
            else:  # the same line
                x = x_prev if x_prev is not None else _perpendicular(zk)
                d = float(w @ zk)
            new_origin = origin + d * zk + v
        if x_prev is not None and x @ x_prev < 0:
            x = -x  # the common normal's sense: the one closer to the previous x (fewer pi offsets)
        a = float((new_origin - (origin + d * zk)) @ x)
        if x_prev is None:
            x_prev = x
        frames.append((origin, x_prev))
        rows.append((a, d, _angle(zk, zn, x), _angle(x_prev, x, zk)))
        if max(abs(a), abs(d)) > 10 * reach:
            long_rows.append(k + 1)
        origin, x_prev = new_origin, x
    if x_prev is None:  # a one-joint chain
        x_prev = _perpendicular(z_axes[0])
    frames.append((origin, x_prev))
    rows.append((0.0, 0.0, 0.0, 0.0))  # the last frame turns with the last joint
    o_last, x_last = frames[-1]
    z_last = z_axes[-1]
    R_last = np.column_stack([x_last, np.cross(z_last, x_last), z_last])
    tool = R_last.T @ (T[0, :3, 3] - o_last)
    o0, x0 = frames[0]
    R0 = np.column_stack([x0, np.cross(z_axes[0], x0), z_axes[0]])
    rpy = Rotation.from_matrix(R0).as_euler("xyz")
    return DHTable(tuple(rows), _t3(o0), _t3(rpy), _t3(tool), tuple(long_rows))


def _t3(v: np.ndarray) -> tuple[float, float, float]:
    return float(v[0]), float(v[1]), float(v[2])
