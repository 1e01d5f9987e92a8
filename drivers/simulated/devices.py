"""Simulated drivers: real implementations of the driver protocols over the sim/ cell.

Readings carry the simulated clock as the device's time (`t`) and the host's monotonic clock at
the moment the simulator answered (`host_time`, set when the reading is built).

A `SimWorld` owns one simulated cell (plant + instruments on one clock); the robot, tracker
and camera drivers built on it see the same arm. `SimWorld.truth_tcp()` is the simulator's
truth, offered so the twin can be *scored* in simulation; no correction path may use it.
"""
from __future__ import annotations

from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import pybullet as pb

from drivers.base import (
    Abortable,
    JointState,
    Lifecycle,
    RigReading,
    StreamStatus,
    TrackerReading,
    check_stream_params,
    reject_keys,
)
from dt_kernel.config import Frozen
from dt_kernel.errors import DriverError, StateError, UnreachableError
from dt_kernel.geometry import spherical_to_cartesian
from sim.cell import SimCell
from sim.kinematics import TOOL_DOWN
from sim.servo import ServoFollower


class SimWorld:
    """Handle on one simulated cell (sim.cell.SimCell), created from a scenario and a cell config.

    Parameters
    ----------
    scenario : str, Path or dict
        The scenario (a YAML file or its mapping).
    cell : str or Path
        The cell config (YAML).
    seed : int or None
        Overrides the scenario's seed.
    source : str
        Names the scenario in errors.
    """

    def __init__(self, scenario: str | Path | dict, cell: str | Path, seed: int | None = None,
                 source: str = "<scenario>"):
        self.cell = SimCell.from_files(scenario, cell, seed, source)
        self.scenario_name = self.cell.scenario.name
        self.camera_shift = np.zeros(3)
        self._lt_pose = self.cell.cell.laser_tracker.pose.matrix()  # fixed: scored every tick

    @property
    def t(self) -> float:
        """The simulated clock (s)."""
        return self.cell.clock.t

    def idle(self, dt: float) -> None:
        """Let simulated time pass with the arm standing still.

        A tick that commanded nothing: its clock must still run, or a refusing loop would never end.

        Parameters
        ----------
        dt : float
            s.
        """
        self.cell.clock.advance(float(dt))

    def truth_tcp(self) -> np.ndarray:
        """Where the TCP really is (m, robot base frame): the simulator's truth, for scoring only.

        Returns
        -------
        ndarray
            (3,) m.
        """
        return self.cell.plant.actual_tcp()

    def truth_in_tracker_frame(self) -> np.ndarray:
        """The true TCP expressed, noise-free, in the laser tracker's frame.

        The global frame GL is realised by the tracker's registration, so true errors are
        scored in GL by mapping this point through the twin's tracker registration.
        """
        R, t = self._lt_pose
        return R.T @ (self.truth_tcp() - t)

    def tool_pose(self):
        """The actual tool pose (truth), robot base frame.

        Returns
        -------
        R : ndarray
            (3, 3).
        p : ndarray
            (3,) m, the TCP.
        """
        return self.cell.plant.tool_pose()

    def predicted_tool_pose(self):
        """What the twin expects without truth: the commanded TCP with the programmed tool-down
        orientation (the camera pipeline looks for markers around it)."""
        return TOOL_DOWN, self.cell.plant.controller_tcp()

    def occluded(self, cam_center: np.ndarray, points: np.ndarray) -> np.ndarray:
        """Markers hidden from a camera by the arm's own links.

        PyBullet ray tests on the actual arm, from the camera centre to 2 mm short of each marker.

        Parameters
        ----------
        cam_center : ndarray
            (3,) m, world frame.
        points : ndarray
            (n, 3) m, the markers, world frame.

        Returns
        -------
        ndarray
            (n,) bool, True where the arm blocks the ray.
        """
        arm = self.cell.plant.actual
        pts = np.atleast_2d(points)
        d = pts - cam_center
        ends = pts - 2e-3 * d / np.linalg.norm(d, axis=1, keepdims=True)
        hits = pb.rayTestBatch([list(cam_center)] * len(pts), ends.tolist(), physicsClientId=arm.client)
        return np.array([h[0] == arm.body for h in hits])

    def temperature(self) -> float:
        """The air temperature the cell logs now (deg C)."""
        return self.cell.plant.temperature()

    def payload(self) -> float:
        """The payload now (kg, from the scenario's schedule)."""
        return self.cell.plant.payload()

    def tracker_u(self, distance_m: float) -> float:
        """The tracker's stated standard uncertainty at a distance: u_const + u_per_m * d.

        Parameters
        ----------
        distance_m : float
            m.

        Returns
        -------
        float
            m, isotropic.
        """
        c = self.cell.cell.laser_tracker
        return c.u_const_m + c.u_per_m * distance_m

    def joint_noise_rad(self) -> float:
        """The plant's joint repeatability noise (rad, one sigma), for the noise floor."""
        return self.cell.scenario.joint_noise_rad

    def effects_enabled(self) -> list[str]:
        """The names of the error effects the scenario switches on."""
        return self.cell.scenario.effects.enabled()

    def max_speed(self) -> float:
        """The scenario's TCP speed limit (m/s)."""
        return self.cell.scenario.max_speed_m_s

    def unreachable(self, targets: np.ndarray) -> list[tuple[int, str]]:
        """The targets the controller cannot reach (nothing moves).

        Parameters
        ----------
        targets : ndarray
            (n, 3) m, robot frame.

        Returns
        -------
        list of (int, str)
            Index and reason of every unreachable target.
        """
        return self.cell.plant.check_reachable(targets)

    def inject_joint_offset(self, delta_rad) -> None:
        """Fault injection: a step in the joint zero offsets (e.g. a slipped encoder).

        Parameters
        ----------
        delta_rad : array_like
            (n_joints,) rad, added to the offsets.
        """
        self.cell.plant.inject_joint_offset(np.asarray(delta_rad, dtype=float))

    def bump_camera(self, shift_m) -> None:
        """Fault injection: the camera rig is knocked, whichever MVS (point stand-in or image rig) reads it.

        Parameters
        ----------
        shift_m : array_like
            (3,) m, world frame; adds to earlier shifts.
        """
        self.camera_shift = self.camera_shift + np.asarray(shift_m, dtype=float)
        self.cell.mvs.bump(np.asarray(shift_m, dtype=float))

    def tool_pose_seen_by_camera(self):
        """The tool pose relative to the (possibly knocked) rig, for the image renderer."""
        R, p = self.tool_pose()
        return R, p - self.camera_shift

    def close(self) -> None:
        """Release the cell (its PyBullet clients)."""
        self.cell.close()


class NoOptions(Frozen):
    """A simulated driver's options: none (its faults come from the scenario)."""


class _OnWorld(Lifecycle):
    """A simulated driver: built on a SimWorld; its faults come from the scenario and the
    daemon's fault list, so `configure` accepts no keys (a stray key, e.g. a serial `url`
    left in place, is an error rather than silently ignored)."""

    needs_world = True
    config_model = NoOptions

    what = "driver"  # names the config in errors: "<simulated robot config>"

    def __init__(self, world: SimWorld | None = None, *, source: str | None = None):
        if world is None:
            raise DriverError(f"{type(self).__name__} runs on a simulated world: pass world=SimWorld(...)")
        self.world, self._source = world, source or f"<simulated {self.what} config>"

    def _on_configure(self, config: dict[str, Any]) -> None:
        reject_keys(config, self._source, (), f"the simulated {type(self).__name__}")


class SimRobot(Abortable, _OnWorld):
    """RobotController over the simulated plant."""

    what = "robot"

    @property
    def _plant(self):
        return self.world.cell.plant

    def move_linear(self, target: np.ndarray, speed: float) -> None:
        """Linear move of the simulated TCP; returns when settled (simulated time advances).

        Parameters
        ----------
        target : ndarray
            (3,) m, robot frame.
        speed : float
            m/s (the scenario's limit caps it).

        Raises
        ------
        StateError
            When the driver is not ``active``.
        DriverError
            When the arguments are not finite (speed <= 0 included), the move is aborted or the
            simulator fails.
        UnreachableError
            When the controller's inverse kinematics has no solution.
        """
        self._require("active")
        self._check_abort()
        target = np.asarray(target, dtype=float)
        if target.shape != (3,) or not np.all(np.isfinite(target)) or not np.isfinite(speed) or speed <= 0:
            raise DriverError(f"invalid move: target {target!r}, speed {speed!r}")
        try:
            self._plant.move_linear(target, speed)
        except UnreachableError:
            raise
        except Exception as exc:  # pybullet errors surface as DriverError
            raise DriverError(f"simulated controller failed: {exc}") from exc

    # --- streaming (drivers.base.SetpointStreamer) in simulated time ------------------------
    def start_stream(self, rate_hz: float, lookahead_s: float = 0.1, gain: float = 300.0) -> None:
        """Make the plant follow set-points through sim.servo's servo model, in simulated time.

        Each set-point advances the simulated clock by its time step, so the path's lag and overshoot
        are in the plant's truth. No watchdog: the simulated controller moves only when it is handed
        a set-point.

        Parameters
        ----------
        rate_hz : float
            Set-points per second (<= 1000 Hz); the first set-point's time step is 1/rate_hz.
        lookahead_s : float
            The servo's look-ahead time (s).
        gain : float
            The servo's proportional gain.

        Raises
        ------
        StateError
            When the driver is not ``active``.
        DriverError
            When a parameter is out of range or the driver is aborted.
        """
        self._require("active")
        self._check_abort()
        rate, la, g = check_stream_params(rate_hz, lookahead_s, gain, 1000.0)
        self._follower: ServoFollower | None = ServoFollower(self._plant.controller_tcp(), la, g)
        self._status = StreamStatus("streaming", 0, 0, "", rate, la, g)
        self._last_t: float | None = None

    def stream(self, target: np.ndarray, t: float) -> None:
        """Step the plant to one set-point; the simulated clock advances by ``t`` minus the last one's.

        Parameters
        ----------
        target : ndarray
            (3,) m, robot frame.
        t : float
            s, increasing.

        Raises
        ------
        StateError
            When the driver is not ``active`` or no stream was started.
        DriverError
            When the set-point is not finite, ``t`` does not follow the last one, the driver is aborted
            or the simulator fails.
        UnreachableError
            When the set-point is unreachable.
        """
        self._require("active")
        self._check_abort()
        follower = getattr(self, "_follower", None)
        if follower is None:
            raise StateError(f"{type(self).__name__}: stream() before start_stream()")
        target = np.asarray(target, dtype=float)
        if target.shape != (3,) or not np.all(np.isfinite(target)):
            raise DriverError(f"invalid set-point {target!r}")
        st = self._status
        dt = 1.0 / st.rate_hz if self._last_t is None else float(t) - self._last_t
        if not dt > 0:
            raise DriverError(f"set-point time {t} s does not follow the last one ({self._last_t} s)")
        x, v = follower.step(target, dt)
        try:
            self._plant.servo_step(x, float(np.linalg.norm(v)), dt)
        except UnreachableError:
            raise
        except Exception as exc:  # pybullet errors surface as DriverError
            raise DriverError(f"simulated controller failed: {exc}") from exc
        self._last_t = float(t)
        self._status = replace(st, sent=st.sent + 1, consumed=st.sent + 1, cycles_quiet=0)

    def stop_stream(self) -> None:
        """End the stream (the status becomes ``idle``); does nothing when none runs.

        Raises
        ------
        StateError
            When the driver is not ``active``.
        """
        self._require("active")
        if getattr(self, "_follower", None) is not None:
            self._follower = None
            self._status = replace(self._status, state="idle")

    def stream_status(self) -> StreamStatus:
        """What the driver knows of its stream (``idle`` before any).

        Returns
        -------
        StreamStatus
        """
        return getattr(self, "_status", StreamStatus("idle"))

    def read_joint_state(self) -> JointState:
        """The commanded joint angles (rad) at the simulated time.

        Returns
        -------
        JointState

        Raises
        ------
        StateError
            When the driver is not ``active``.
        """
        self._require("active")
        return JointState(q=self._plant.joint_angles(), t=self.world.t)

    def read_commanded_tcp(self) -> np.ndarray:
        """The controller's TCP (m, robot frame) at its 1 um resolution.

        Returns
        -------
        ndarray
            (3,) m.

        Raises
        ------
        StateError
            When the driver is not ``active``.
        """
        self._require("active")
        return self._plant.controller_tcp()


class SimTracker(_OnWorld):
    """LaserTracker over the simulated tracker: spherical measurement -> Cartesian, tracker frame."""

    what = "tracker"

    @property
    def _lt(self):
        return self.world.cell.tracker

    def measure(self) -> TrackerReading:
        """Measure the SMR with the simulated tracker.

        Returns
        -------
        TrackerReading
            ``point`` (3,) m in the tracker frame, NaN when the status is not ``ok``.

        Raises
        ------
        StateError
            When the driver is not ``active``.
        """
        self._require("active")
        d, az, el, status = self._lt.measure_spherical()
        point = spherical_to_cartesian(d, az, el) if status == "ok" else np.full(3, np.nan)
        return TrackerReading(point=point, spherical=(d, az, el), t=self.world.t, status=status)


class SimPointCamera(_OnWorld):
    """CameraRig over the point-noise MVS stand-in (the image pipeline replaces it)."""

    what = "camera"

    @property
    def _mvs(self):
        return self.world.cell.mvs

    def read(self) -> RigReading:
        """Measure the TCP with the point-noise MVS stand-in (m, MVS frame).

        Returns
        -------
        RigReading
            With an isotropic covariance of the stand-in's noise; refused when the rig drops out.

        Raises
        ------
        StateError
            When the driver is not ``active``.
        """
        self._require("active")
        p = self._mvs.measure()
        if p is None:
            return RigReading(point=None, t=self.world.t, refused="camera rig dropped out")
        u = self._mvs.cfg.noise_m
        return RigReading(point=p, t=self.world.t, cov=np.eye(3) * u * u,
                          quality={"markers_used": 5, "cameras_used": 8, "reproj_rms_px": 0.0})
