"""PyBullet model of the arm (DIRECT mode): forward/inverse kinematics and gravity torques.

Each `Arm` owns its own PyBullet client, so a nominal model (what the controller believes) and
an actual model (the perturbed geometry of the real arm) can live side by side.
"""
from __future__ import annotations

import os
import tempfile
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pybullet as pb

from dt_kernel.errors import ConfigError, UnreachableError

URDF_PATH = Path(__file__).parent / "assets" / "cobot.urdf"
GRAVITY = 9.80665  # m/s^2, standard gravity

# Tool pointing straight down: the tool x axis (along the forearm at zero pose) along world -z.
TOOL_DOWN = np.array([[0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0]])


def perturbed_urdf(joint_xyz: dict[str, np.ndarray], joint_rpy: dict[str, np.ndarray],
                   source: Path = URDF_PATH) -> str:
    """URDF text with every joint origin shifted.

    Parameters
    ----------
    joint_xyz : dict
        Joint name -> (3,) m added to the origin's xyz.
    joint_rpy : dict
        Joint name -> (3,) rad added to the origin's rpy.
    source : Path
        The URDF to perturb.

    Returns
    -------
    str

    Raises
    ------
    ConfigError
        When a joint has no name or no <origin>.
    """
    tree = ET.parse(source)
    for joint in tree.getroot().iter("joint"):
        name = joint.get("name")
        origin = joint.find("origin")
        if name is None or origin is None:
            raise ConfigError(source, "joint", name, "URDF joints with a 'name' and an <origin> to perturb")
        xyz = np.array([float(v) for v in origin.get("xyz", "0 0 0").split()])
        rpy = np.array([float(v) for v in origin.get("rpy", "0 0 0").split()])
        xyz = xyz + joint_xyz.get(name, 0.0)
        rpy = rpy + joint_rpy.get(name, 0.0)
        origin.set("xyz", " ".join(f"{v:.12g}" for v in xyz))
        origin.set("rpy", " ".join(f"{v:.12g}" for v in rpy))
    return ET.tostring(tree.getroot(), encoding="unicode")


class Arm:
    """One PyBullet body of the arm (its own DIRECT client). Positions in metres, angles in radians,
    robot base frame.

    Parameters
    ----------
    urdf_text : str or None
        A URDF to load (e.g. ``perturbed_urdf``'s); None loads ``urdf_path``.
    urdf_path : Path
        The URDF file.
    """

    def __init__(self, urdf_text: str | None = None, urdf_path: Path = URDF_PATH,
                 ):
        self.client = pb.connect(pb.DIRECT)
        pb.setGravity(0, 0, -GRAVITY, physicsClientId=self.client)
        if urdf_text is None:
            path = str(urdf_path)
            self.body = pb.loadURDF(path, useFixedBase=True, physicsClientId=self.client,
                                    flags=pb.URDF_USE_INERTIA_FROM_FILE)
        else:
            fd, path = tempfile.mkstemp(suffix=".urdf")
            try:
                with os.fdopen(fd, "w") as fh:
                    fh.write(urdf_text)
                self.body = pb.loadURDF(path, useFixedBase=True, physicsClientId=self.client,
                                        flags=pb.URDF_USE_INERTIA_FROM_FILE)
            finally:
                os.unlink(path)
        n = pb.getNumJoints(self.body, physicsClientId=self.client)
        infos = [pb.getJointInfo(self.body, j, physicsClientId=self.client) for j in range(n)]
        self.joints = [i[0] for i in infos if i[2] == pb.JOINT_REVOLUTE]
        self.joint_names = [infos[j][1].decode() for j in self.joints]
        self.lower = np.array([infos[j][8] for j in self.joints])
        self.upper = np.array([infos[j][9] for j in self.joints])
        self.tcp_link = n - 1
        self.flange_link = self.joints[-1]
        self.set_payload(0.0)
        self._q: np.ndarray | None = None  # the joint state PyBullet holds (None: unknown)
        self._zero_velocities = [[0.0] for _ in self.joints]
        self._fk: tuple[np.ndarray, np.ndarray] | None = None  # fk at _q, once computed

    @property
    def dof(self) -> int:
        """The number of revolute joints."""
        return len(self.joints)

    def set_payload(self, kg: float) -> None:
        """Payload carried at the TCP (drives the compliance torques).

        Parameters
        ----------
        kg : float
        """
        self.payload = float(kg)

    def _set(self, q: np.ndarray) -> None:
        # A Newton step asks fk and the Jacobian at the same q, and the check after it fk again:
        # the joints are reset (and fk recomputed) only when q changes.
        if self._q is not None and np.array_equal(q, self._q):
            return
        # One call for all joints (what resetJointState does joint by joint, at a quarter of the cost).
        pb.resetJointStatesMultiDof(self.body, self.joints, [[float(v)] for v in q],
                                    targetVelocities=self._zero_velocities, physicsClientId=self.client)
        self._q, self._fk = np.array(q, dtype=float), None

    def fk(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Forward kinematics of the TCP.

        Parameters
        ----------
        q : ndarray
            (dof,) rad.

        Returns
        -------
        p : ndarray
            (3,) m.
        R : ndarray
            (3, 3) orientation.
        """
        self._set(np.asarray(q, dtype=float))
        if self._fk is None:
            s = pb.getLinkState(self.body, self.tcp_link, computeForwardKinematics=True,
                                physicsClientId=self.client)
            self._fk = np.array(s[4]), np.array(pb.getMatrixFromQuaternion(s[5])).reshape(3, 3)
        return self._fk[0].copy(), self._fk[1].copy()

    def link_positions(self, q: np.ndarray) -> np.ndarray:
        """World positions of every link frame (for occlusion geometry and displays).

        Parameters
        ----------
        q : ndarray
            (dof,) rad.

        Returns
        -------
        ndarray
            (n_links, 3) m.
        """
        self._set(np.asarray(q, dtype=float))
        return np.array([pb.getLinkState(self.body, j, computeForwardKinematics=True,
                                         physicsClientId=self.client)[4]
                         for j in range(self.tcp_link + 1)])

    def jacobian(self, q: np.ndarray) -> np.ndarray:
        """Geometric Jacobian of the TCP: linear rows (m/rad) over angular rows (rad/rad).

        Parameters
        ----------
        q : ndarray
            (dof,) rad.

        Returns
        -------
        ndarray
            (6, dof).
        """
        ql = [float(v) for v in q]
        zeros = [0.0] * len(ql)
        self._set(np.asarray(ql))
        lin, ang = pb.calculateJacobian(self.body, self.tcp_link, [0.0, 0.0, 0.0], ql, zeros,
                                        zeros, physicsClientId=self.client)
        return np.vstack([np.array(lin), np.array(ang)])

    def gravity_torque(self, q: np.ndarray) -> np.ndarray:
        """Static joint torques holding the arm and payload against gravity.

        The arm's own weight comes from PyBullet's inverse dynamics; the payload at the TCP adds
        J_lin^T (0, 0, m g) (PyBullet's changeDynamics does not reach its inverse dynamics).

        Parameters
        ----------
        q : ndarray
            (dof,) rad.

        Returns
        -------
        ndarray
            (dof,) N m.
        """
        ql = [float(v) for v in q]
        zeros = [0.0] * len(ql)
        tau = np.array(pb.calculateInverseDynamics(self.body, ql, zeros, zeros,
                                                   physicsClientId=self.client))
        if self.payload:
            tau = tau + self.jacobian(q)[:3].T @ np.array([0.0, 0.0, self.payload * GRAVITY])
        return tau

    def ik(self, target: np.ndarray, R: np.ndarray = TOOL_DOWN, q_seed: np.ndarray | None = None,
           tol: float = 2e-7, max_iter: int = 30) -> np.ndarray:
        """Joint angles putting the TCP at ``target`` with orientation ``R``.

        PyBullet's damped IK gives a start on the elbow-up branch; Newton steps on the full 6-D pose
        error then converge to ``tol`` (PyBullet reports link poses in single precision, about 0.1 um
        here, well inside the 1 um resolution). With ``q_seed``, Newton is tried from it first.

        Parameters
        ----------
        target : ndarray
            (3,) m.
        R : ndarray
            (3, 3) orientation; tool down by default.
        q_seed : ndarray or None
            (dof,) rad, where the arm is.
        tol : float
            m (and 5 tol rad for the orientation).
        max_iter : int
            Newton steps.

        Returns
        -------
        ndarray
            (dof,) rad, wrapped to [-pi, pi).

        Raises
        ------
        UnreachableError
            Outside reach or joint limits.
        """
        target = np.asarray(target, dtype=float)
        if q_seed is not None:
            # A controller streaming set-points warm-starts from where the arm is: Newton alone
            # converges in a few steps and stays on the same branch.
            q = self._newton(target, R, np.asarray(q_seed, dtype=float), tol, 8)
            if q is not None:
                return self._checked(q, target, R)
        else:
            q_seed = np.array([np.arctan2(target[1], target[0]), 0.3, 0.3, 0.0, 0.9, 0.0])
        self._set(q_seed)
        quat = _quat_from_matrix(R)
        q = np.array(pb.calculateInverseKinematics(
            self.body, self.tcp_link, target.tolist(), quat, lowerLimits=self.lower.tolist(),
            upperLimits=self.upper.tolist(), jointRanges=(self.upper - self.lower).tolist(),
            restPoses=list(q_seed), maxNumIterations=200, residualThreshold=1e-6,
            physicsClientId=self.client))[: self.dof]
        self._q = None  # PyBullet's IK may leave other joint states behind
        q = self._newton(target, R, q, tol, max_iter, always=True)
        return self._checked(q, target, R)

    def _newton(self, target, R, q, tol, max_iter, always=False):
        """Newton steps on the 6-D pose error; None if not converged (unless `always`)."""
        for _ in range(max_iter):
            p, Rq = self.fk(q)
            err = np.concatenate([target - p, _rot_error(R, Rq)])
            if np.linalg.norm(err[:3]) < tol and np.linalg.norm(err[3:]) < tol * 5:
                return q
            try:
                q = q + np.linalg.solve(self.jacobian(q), err)
            except np.linalg.LinAlgError:  # singular pose: fall back to least squares
                q = q + np.linalg.lstsq(self.jacobian(q), err, rcond=None)[0]
        return q if always else None

    def _checked(self, q, target, R) -> np.ndarray:
        p, Rq = self.fk(q)
        if np.linalg.norm(target - p) > 1e-6 or np.linalg.norm(_rot_error(R, Rq)) > 1e-5:
            raise UnreachableError(
                f"target {np.round(target * 1e3, 2).tolist()} mm is out of reach "
                f"(IK residual {np.linalg.norm(target - p) * 1e3:.3g} mm)")
        q = (q + np.pi) % (2 * np.pi) - np.pi
        if np.any(q < self.lower) or np.any(q > self.upper):
            bad = [self.joint_names[i] for i in np.flatnonzero((q < self.lower) | (q > self.upper))]
            raise UnreachableError(
                f"target {np.round(target * 1e3, 2).tolist()} mm needs joints outside their "
                f"limits: {', '.join(bad)}")
        return q

    def close(self) -> None:
        """Disconnect the PyBullet client (once)."""
        if pb.isConnected(self.client):
            pb.disconnect(self.client)


def _rot_error(R_target: np.ndarray, R: np.ndarray) -> np.ndarray:
    """Rotation vector (world frame) taking R to R_target."""
    E = R_target @ R.T
    angle = np.arccos(np.clip((np.trace(E) - 1) / 2, -1.0, 1.0))
    v = np.array([E[2, 1] - E[1, 2], E[0, 2] - E[2, 0], E[1, 0] - E[0, 1]])
    if angle < 1e-12:
        return v / 2
    return angle / (2 * np.sin(angle)) * v


def _quat_from_matrix(R: np.ndarray) -> list[float]:
    from scipy.spatial.transform import Rotation

    return Rotation.from_matrix(R).as_quat().tolist()  # x, y, z, w as PyBullet expects
