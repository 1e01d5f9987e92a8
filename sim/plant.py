"""The simulated cobot plant: the controller's nominal model and the arm's actual behaviour.

The controller solves inverse kinematics on the nominal URDF; the arm really reaches the pose
of the *actual* (perturbed) kinematics at the commanded joint angles plus every switched-on
effect (see sim.effects) and repeatability noise. The plant is the truth: instruments measure
`actual_tcp()`; the twin never sees it directly.
"""
from __future__ import annotations

import numpy as np

from sim import effects as fx
from sim.kinematics import TOOL_DOWN, Arm, perturbed_urdf
from sim.scenario import Scenario


class SimClock:
    """Simulated time (s), shared by the plant and the instruments."""

    def __init__(self, t0: float = 0.0):
        self.t = t0

    def advance(self, dt: float) -> None:
        """Advance the clock.

        Parameters
        ----------
        dt : float
            s.
        """
        self.t += dt


class SimulatedCobot:
    """The simulated arm: a nominal model the controller solves IK on and the actual (perturbed) arm
    with the scenario's effects and repeatability noise. Positions in m, robot base frame.

    Parameters
    ----------
    scenario : Scenario
    clock : SimClock or None
        Shared with the instruments; a new one at t = 0 when None.
    """
    def __init__(self, scenario: Scenario, clock: SimClock | None = None):
        self.scn = scenario
        self.clock = clock or SimClock()
        self.nominal = Arm()
        names = self.nominal.joint_names
        if scenario.effects.geometric.enabled:
            xyz, rpy, self._joint_offsets = fx.geometric_perturbation(scenario, names)
            self.actual = Arm(urdf_text=perturbed_urdf(xyz, rpy))
        else:
            self._joint_offsets = np.zeros(len(names))
            self.actual = Arm()
        self._rng = np.random.default_rng([scenario.seed, 202])
        self._fault_offsets = np.zeros(len(names))
        self.q_cmd = self.nominal.ik(np.array([0.9, 0.0, 0.7]))
        self._last_dir = np.zeros(len(names))
        self._target = self.nominal.fk(self.q_cmd)[0]
        self._speed = 0.0
        self._approach = np.zeros(3)
        self._structure: tuple[float, float] | None = None  # (t, T) of the structure: thermal lag
        self._settle()

    # --- commands -----------------------------------------------------------------------
    def move_linear(self, target: np.ndarray, speed: float) -> None:
        """Move the TCP and settle there; the clock advances by the travel time plus the dwell.

        Parameters
        ----------
        target : ndarray
            (3,) m, robot frame.
        speed : float
            m/s, capped at the scenario's limit.

        Raises
        ------
        UnreachableError
            When the nominal IK has no solution.
        """
        self._go(target, speed, None)

    def servo_step(self, target: np.ndarray, speed: float, dt: float) -> None:
        """One control cycle of a streamed path (sim.servo).

        The clock advances ``dt``, without the dwell of a positioning; the effects see the speed
        (dynamic) and the direction of motion (backlash).

        Parameters
        ----------
        target : ndarray
            (3,) m, where the TCP is at the cycle's end.
        speed : float
            m/s, its speed then.
        dt : float
            s.

        Raises
        ------
        UnreachableError
            When the nominal IK has no solution.
        """
        self._go(target, speed, float(dt))

    def _go(self, target: np.ndarray, speed: float, dt: float | None) -> None:
        target = np.asarray(target, dtype=float)
        speed = float(min(speed, self.scn.max_speed_m_s))
        q_new = self.nominal.ik(target, q_seed=self.q_cmd)
        step = target - self._target
        dist = float(np.linalg.norm(step))
        dq = q_new - self.q_cmd
        # Direction of approach per joint; a joint that did not move keeps its last one.
        moved = np.abs(dq) > 1e-9
        self._last_dir = np.where(moved, np.sign(dq), self._last_dir)
        self._approach = step / dist if dist > 1e-9 else self._approach
        self.clock.advance(dist / max(speed, 1e-6) + self.scn.dwell_s if dt is None else dt)
        self.q_cmd, self._target, self._speed = q_new, target, speed
        self._settle()

    def inject_joint_offset(self, delta_rad: np.ndarray) -> None:
        """Fault injection: a step in the joint zero offsets (e.g. a slipped encoder).

        Parameters
        ----------
        delta_rad : ndarray
            (n_joints,) rad.
        """
        self._fault_offsets = self._fault_offsets + np.asarray(delta_rad, dtype=float)
        self._settle()

    # --- truth and controller view ------------------------------------------------------
    def _settle(self) -> None:
        scn, e = self.scn, self.scn.effects
        t = self.clock.t
        self.actual.set_payload(scn.payload_at(t))
        q = self.q_cmd + self._joint_offsets + self._fault_offsets
        if e.compliance.enabled:
            q = q + fx.compliance(scn, self.actual.gravity_torque(q))
        if e.gear.enabled:
            q = q + fx.gear(scn, self.q_cmd)
        if e.backlash.enabled:
            q = q + fx.backlash(scn, self._last_dir)
        if e.drift.enabled:
            q = q + fx.drift(scn, t)
        q = q + self._rng.normal(0.0, scn.joint_noise_rad, q.shape)
        p, R = self.actual.fk(q)
        if e.thermal.enabled:
            # The arm expands about its base mount (robot frame origin).
            p = p * (1.0 + fx.thermal_scale(scn, self.structure_temperature()))
        if e.dynamic.enabled:
            p = p + fx.dynamic(scn, self._speed, self._approach)
        self._actual_p, self._actual_R = p, R

    def actual_tcp(self) -> np.ndarray:
        """Where the TCP (SMR centre) really is, robot base frame (m). Truth."""
        return self._actual_p.copy()

    def tool_pose(self) -> tuple[np.ndarray, np.ndarray]:
        """Actual tool orientation (3,3) and TCP position (3,), robot base frame. Truth."""
        return self._actual_R.copy(), self._actual_p.copy()

    def controller_tcp(self) -> np.ndarray:
        """The controller's TCP from encoders and nominal kinematics, at its 1 um resolution."""
        res = self.scn.tcp_resolution_m
        return np.round(self._target / res) * res

    def joint_angles(self) -> np.ndarray:
        """The commanded joint angles (rad)."""
        return self.q_cmd.copy()

    def temperature(self) -> float:
        """The air temperature the cell logs (deg C)."""
        return self.temperature_at(self.clock.t)

    def temperature_at(self, t: float) -> float:
        """The air temperature at a time: base + ramp t + amplitude sin(2 pi t / period).

        Parameters
        ----------
        t : float
            s, simulated clock.

        Returns
        -------
        float
            deg C.
        """
        tm = self.scn.temperature
        h = t / 3600.0
        return tm.base_c + tm.ramp_c_per_h * h + tm.amplitude_c * np.sin(2 * np.pi * h / tm.period_h)

    def structure_temperature(self) -> float:
        """The arm structure's temperature (truth): the air's through a first-order lag of
        effects.thermal.lag_s, integrated in steps of at most 10 s from the previous call (in
        equilibrium with the air at the first)."""
        t, tau = self.clock.t, self.scn.effects.thermal.lag_s
        if tau <= 0:
            return self.temperature()
        if self._structure is None:
            self._structure = (t, self.temperature())
        t0, ts = self._structure
        grid = np.linspace(t0, t, max(1, int(np.ceil((t - t0) / 10.0))) + 1)
        air = [self.temperature_at(x) for x in grid]
        for k in range(len(grid) - 1):
            ts = fx.lag_step(ts, air[k], air[k + 1], float(grid[k + 1] - grid[k]), tau)
        self._structure = (t, ts)
        return ts

    def payload(self) -> float:
        """The payload now (kg)."""
        return self.scn.payload_at(self.clock.t)

    def check_reachable(self, targets: np.ndarray) -> list[tuple[int, str]]:
        """The targets the controller cannot reach, tool down (nothing moves).

        Parameters
        ----------
        targets : ndarray
            (n, 3) or (3,) m, robot frame.

        Returns
        -------
        list of (int, str)
            Index and reason of every unreachable target.
        """
        bad = []
        for i, tgt in enumerate(np.atleast_2d(targets)):
            try:
                self.nominal.ik(tgt, R=TOOL_DOWN)
            except Exception as exc:  # UnreachableError, reported not skipped
                bad.append((i, str(exc)))
        return bad

    def close(self) -> None:
        """Release both arms' PyBullet clients."""
        self.nominal.close()
        self.actual.close()
