"""Robot controller over a serial line (pyserial), speaking `drivers.serial.protocol`
through `drivers.serial.link.SerialLink` (shared with the tracker driver). The protocol and
the config keys: docs/drivers.md ("Serial line protocol")."""
from __future__ import annotations

import math
import time
from typing import Any

import numpy as np
from pydantic import Field

from drivers.base import JointState, check_move
from drivers.serial import protocol as lp
from drivers.serial.device import SerialDevice
from drivers.serial.link import LinkConfig, SerialLink, ack_fields, refused  # noqa: F401 (re-exported)
from dt_kernel.config import Frozen


class ControllerLimits(Frozen):
    """Ranges the controller driver checks: ``tcp_abs_m`` (m, bound on |x|, |y|, |z| of targets and
    received TCPs), ``max_speed_m_s`` (m/s), ``joint_abs_rad`` (rad), ``n_joints``.
    """
    tcp_abs_m: float = Field(3.0, gt=0)
    max_speed_m_s: float = Field(2.0, gt=0)
    joint_abs_rad: float = Field(2 * math.pi, gt=0)
    n_joints: int = Field(6, ge=1, le=32)


class ControllerConfig(LinkConfig):
    """The serial controller's options: the line's (``LinkConfig``) and ``limits``."""
    limits: ControllerLimits = ControllerLimits()


class SerialController(SerialDevice[ControllerConfig]):
    """RobotController over the serial line protocol (docs/drivers.md, 'Serial line protocol')."""

    name = "serial controller"
    config_model = ControllerConfig

    def _check_move(self, target: Any, speed: Any) -> tuple[np.ndarray, float]:
        lim = self._cfg.limits
        return check_move(target, speed, lim.tcp_abs_m, lim.max_speed_m_s)

    def move_linear(self, target: np.ndarray, speed: float) -> None:
        """Linear move of the TCP (MOVL); returns when the controller reports it settled.

        Parameters
        ----------
        target : ndarray
            (3,) m, robot frame.
        speed : float
            m/s.

        Raises
        ------
        StateError
            When the driver is not ``active``.
        DriverError
            When the arguments are out of the limits, the controller refuses (NAK) or does not answer.
        UnreachableError
            When the controller refuses the target as unreachable.
        """
        self._require("active")
        target, speed = self._check_move(target, speed)
        reply = self._link.request("MOVL", *map(float, target), speed, timeout_s=self._cfg.move_timeout_s)
        ack_fields(self.name, "MOVL", reply, 0)

    def stream_setpoint(self, target: np.ndarray, speed: float) -> None:
        """Send one streamed set-point (SETP); the controller acknowledges at once.

        Parameters
        ----------
        target : ndarray
            (3,) m, robot frame.
        speed : float
            m/s.

        Raises
        ------
        StateError
            When the driver is not ``active``.
        DriverError
            As ``move_linear``.
        """
        self._require("active")
        target, speed = self._check_move(target, speed)
        ack_fields(self.name, "SETP", self._link.request("SETP", *map(float, target), speed), 0)

    def read_joint_state(self) -> JointState:
        """The encoder joint angles (GETJ).

        Returns
        -------
        JointState
            ``q`` (rad), ``t`` (s, controller clock), ``host_time`` at receipt.

        Raises
        ------
        StateError
            When the driver is not ``active``.
        DriverError
            When the reply is refused, malformed, or an angle is outside ±``joint_abs_rad``.
        """
        self._require("active")
        lim = self._cfg.limits
        reply = self._link.request("GETJ")
        host_time = time.monotonic()  # at receipt, before parsing
        f = ack_fields(self.name, "GETJ", reply, 1 + lim.n_joints)
        t = lp.parse_float(f[0], "GETJ t")
        q = np.array([lp.parse_float(v, f"GETJ q{i + 1}", -lim.joint_abs_rad, lim.joint_abs_rad)
                      for i, v in enumerate(f[1:])])
        return JointState(q=q, t=t, host_time=host_time)

    def read_commanded_tcp(self) -> np.ndarray:
        """The controller's own TCP from its nominal kinematics (GETT).

        Returns
        -------
        ndarray
            (3,) m, robot frame.

        Raises
        ------
        StateError
            When the driver is not ``active``.
        DriverError
            When the reply is refused, malformed, or a coordinate is outside ±``tcp_abs_m``.
        """
        self._require("active")
        b = self._cfg.limits.tcp_abs_m
        f = ack_fields(self.name, "GETT", self._link.request("GETT"), 4)
        lp.parse_float(f[0], "GETT t")
        return np.array([lp.parse_float(v, f"GETT {a}", -b, b) for a, v in zip("xyz", f[1:])])

    def status(self) -> dict[str, Any]:
        """The controller's state ('idle', 'moving', 'fault') and its count of finished moves."""
        self._require("active")
        f = ack_fields(self.name, "STATUS", self._link.request("STATUS"), 2)
        return {"state": lp.parse_status(f[0]), "moves": int(lp.parse_float(f[1], "STATUS moves", 0))}
