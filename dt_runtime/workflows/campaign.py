"""Run experiment plans on a cell through the drivers and collect the raw measurements.

Every positioning records the controller's commanded TCP (robot frame), the laser tracker's
point (tracker frame) and the MVS point (MVS frame). Registration maps all three into the
global frame GL (Sect. 2.3); the positioning errors then follow Eqs. 8-10.
"""
from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Protocol

import numpy as np

from drivers.base import CameraRig, LaserTracker, RobotController, read_exposed_after
from dt_kernel.errors import UnreachableError
from dt_runtime.common.progress import Progress
from dt_runtime.measurements.phase import PhaseData
from dt_runtime.twin.conditions import Conditions


class SimTruth(Protocol):
    """What `run_rows` reads from a simulated world (drivers.simulated.SimWorld) for scoring."""

    @property
    def t(self) -> float:
        """The simulated clock (s)."""
        ...

    def truth_in_tracker_frame(self) -> np.ndarray:
        """(3,) m: where the TCP truly is, in the tracker frame (noise-free)."""
        ...

    def temperature(self) -> float:
        """The cell's temperature now (deg C)."""
        ...

    def payload(self) -> float:
        """The payload now (kg)."""
        ...


@dataclass
class Instruments:
    """The cell's drivers a campaign runs through.

    Attributes
    ----------
    robot : RobotController
        The robot controller.
    tracker : LaserTracker
        The laser tracker.
    camera : CameraRig or None
        The camera (MVS); None: positions measured by the tracker only (dt simulate).
    world : SimTruth or None
        The simulated world behind simulated drivers: truth for scoring.
    max_speed : float
        m/s: a plan row's speed fraction is of this.
    """

    robot: RobotController
    tracker: LaserTracker
    camera: CameraRig | None  # None: positions measured by the tracker only (dt simulate)
    world: SimTruth | None = None  # drivers.simulated.SimWorld when simulated: truth for scoring
    max_speed: float = 1.0  # m/s

    def activate(self) -> None:
        """Configure (with no options) and activate every driver that is not active yet."""
        for d in self.drivers():
            if d.state == "unconfigured":
                d.configure({})
            if d.state == "inactive":
                d.activate()

    def drivers(self) -> list:
        """The drivers present (robot, tracker and, if any, camera)."""
        return [d for d in (self.robot, self.tracker, self.camera) if d is not None]

    def close(self) -> None:
        """Close every driver."""
        for d in self.drivers():
            d.close()

    def conditions(self) -> Conditions:
        """The cell's state before the next command, as the error maps read it: the controller's
        joint angles and, on the simulated cell, its temperature, payload and clock (a real
        cell's come from a sensor driver or the program: `twin.conditions`)."""
        q = self.robot.read_joint_state().q
        w = self.world
        if w is None:
            return Conditions(joints=q)
        return Conditions(temperature=w.temperature(), payload=w.payload(), t=w.t, joints=q)


def check_reachable(world, targets: np.ndarray) -> None:
    """Report every unreachable target of a plan before anything moves.

    Parameters
    ----------
    world : SimWorld or None
        The simulated world that can tell (None: nothing is checked).
    targets : ndarray
        (n, 3) m, robot frame.

    Raises
    ------
    UnreachableError
        Listing up to 20 unreachable targets with the reason.
    """
    if world is None:
        return
    bad = world.unreachable(targets)
    if bad:
        lines = "\n".join(f"  target #{i}: {why}" for i, why in bad[:20])
        more = f"\n  ... and {len(bad) - 20} more" if len(bad) > 20 else ""
        raise UnreachableError(f"{len(bad)} of {len(targets)} plan targets are unreachable:\n{lines}{more}")


def run_rows(inst: Instruments, rows: Sequence, progress: Progress | None = None,
             label: str = "", command: Callable[[np.ndarray, float, Conditions], np.ndarray] | None = None,
             skip_unreachable: bool = False) -> PhaseData:
    """Position the robot at every row's target and measure it with both instruments.

    `command(target, speed, conditions)` maps a target to the command actually sent (identity
    by default; the corrected command for the twin's closed loop, given the cell's
    `Instruments.conditions`). Without a simulated world the temperature and payload columns
    are NaN (unknown: a real cell's campaign logs them from its own sensors). With skip_unreachable, a command the arm
    cannot reach leaves its row NaN and is listed in `refusals` instead of stopping the phase.

    Parameters
    ----------
    inst : Instruments
        The activated drivers.
    rows : sequence of PlanRow
        The plan's rows (target in m, robot frame; speed as a fraction of `inst.max_speed`).
    progress : Progress or None
        Where progress goes.
    label : str
        The phase's name (PhaseData.phase, messages).
    command : callable or None
        command(target, speed m/s, conditions) -> the command sent (m, robot frame).
    skip_unreachable : bool
        Skip unreachable commands instead of raising.

    Returns
    -------
    PhaseData
        Positions in m; NaN where an instrument refused (listed in `refusals`).

    Raises
    ------
    UnreachableError
        A command the arm cannot reach, unless `skip_unreachable`.
    """
    n = len(rows)
    cols = {k: np.full((n, 3), np.nan) for k in ("target", "p_rdk", "p_lt", "p_mvs", "truth_lt")}
    speed, t = np.zeros(n), np.zeros(n)
    temp, payload = np.full(n, np.nan), np.full(n, np.nan)
    q = np.zeros((n, 6))
    refusals: list[str] = []
    for i, row in enumerate(rows):
        v = row.speed_frac * inst.max_speed
        target = np.asarray(row.target, dtype=float)
        cmd = command(target, v, inst.conditions()) if command else target
        try:
            inst.robot.move_linear(cmd, v)
            arrived = time.monotonic()  # a streaming camera's frame must be exposed after this
        except UnreachableError as exc:
            if not skip_unreachable:
                raise
            refusals.append(f"{label} row {i}: unreachable ({exc})")
            speed[i] = v
            continue
        cols["target"][i] = target
        cols["p_rdk"][i] = inst.robot.read_commanded_tcp()
        q[i] = inst.robot.read_joint_state().q
        lt = inst.tracker.measure()
        if lt.ok:
            cols["p_lt"][i] = lt.point
        else:
            refusals.append(f"{label} row {i}: laser tracker {lt.status}")
        mv = read_exposed_after(inst.camera, arrived) if inst.camera is not None else None
        if mv is not None and mv.ok:
            cols["p_mvs"][i] = mv.point
        elif mv is not None:
            refusals.append(f"{label} row {i}: MVS refused ({mv.refused})")
        speed[i] = v
        t[i] = lt.t
        if inst.world is not None:
            cols["truth_lt"][i] = inst.world.truth_in_tracker_frame()
            temp[i] = inst.world.temperature()
            payload[i] = inst.world.payload()
        if progress:
            progress.step(label, i, n)
    return PhaseData(
        phase=label, point_id=np.array([r.point_id for r in rows]), rep=np.array([r.rep for r in rows]),
        target=cols["target"], speed=speed, p_rdk=cols["p_rdk"], p_lt=cols["p_lt"], p_mvs=cols["p_mvs"],
        t=t, q=q, temperature=temp, payload=payload,
        truth_lt=cols["truth_lt"] if inst.world is not None else None,
        axis=np.array([getattr(r, "axis", None) for r in rows], dtype=object),
        distance=np.array([getattr(r, "distance", np.nan) or np.nan for r in rows], dtype=float),
        refusals=refusals,
    )
