"""Where a point program's commands come from: a target source gives the next target (or
set-point) with its speed, one per tick (`TargetSource.next`).

The sources: the cell's program (`ProgramTargets`, repeated from the start when done), and the
simulation stand-ins, a circle streamed at the loop rate (`CircleTargets`, set-points
v / rate_hz apart) and seeded random points in a box (`RandomTargets`); `targets_for` picks one
from the runtime config's `path` section. A path program (`path.kind: path`) is streamed by
`service.path_run` instead.
"""
from __future__ import annotations

from typing import NamedTuple, Protocol

import numpy as np

from dt_runtime.programs.program import Program
from dt_runtime.service.runtime_config import PathConfig


class Target(NamedTuple):
    """One command: `position` (3,) m in the robot frame, `speed` m/s, and `step`, the
    program's row (its conditions' columns), None off a program."""

    position: np.ndarray  # (3,) m, robot frame
    speed: float  # m/s
    step: int | None  # the program's row (its conditions' columns), None off a program


class TargetSource(Protocol):
    """What the daemon's point loop takes its targets from."""

    def next(self) -> Target:
        """The next target to command (a source never runs out: it repeats or goes on)."""
        ...


class ProgramTargets:
    """The cell's program, row after row, from the start again when done."""

    def __init__(self, program: Program):
        self.program, self._step = program, 0

    def next(self) -> Target:
        """The program's next row (the first again after the last)."""
        i = self._step % self.program.n
        self._step += 1
        return Target(self.program.target[i], float(self.program.speed[i]), i)


class CircleTargets:
    """A horizontal circle at `speeds[0]` of the maximum speed, one set-point per tick.

    Parameters
    ----------
    pc : PathConfig
        Its centre and radius (m) and `speeds`.
    max_speed : float
        The robot's maximum speed, m/s.
    rate_hz : float
        The loop's rate, Hz.
    """

    def __init__(self, pc: PathConfig, max_speed: float, rate_hz: float):
        self._v = pc.speeds[0] * max_speed
        self._dphi = self._v / rate_hz / pc.circle_radius_m
        self._c, self._r, self._phase = np.array(pc.circle_center_m), pc.circle_radius_m, 0.0

    def next(self) -> Target:
        """The next set-point on the circle, v / rate_hz further along."""
        self._phase += self._dphi
        return Target(self._c + self._r * np.array([np.cos(self._phase), np.sin(self._phase), 0.0]), self._v, None)


class RandomTargets:
    """Uniform points in the box, each at one of `speeds` (seeded: `path.seed`).

    Parameters
    ----------
    pc : PathConfig
        The box (m), `speeds` and `seed`.
    max_speed : float
        The robot's maximum speed, m/s.
    """

    def __init__(self, pc: PathConfig, max_speed: float):
        self._lo, self._hi = np.array(pc.box_min_m), np.array(pc.box_max_m)
        self._speeds, self._max_speed = pc.speeds, max_speed
        self._rng = np.random.default_rng(pc.seed)

    def next(self) -> Target:
        """The next random point, at a random one of `speeds` times the maximum speed."""
        target = self._rng.uniform(self._lo, self._hi)
        return Target(target, float(self._rng.choice(self._speeds)) * self._max_speed, None)


def targets_for(pc: PathConfig, program: Program | None, max_speed: float, rate_hz: float) -> TargetSource:
    """The runtime config's source: the program when there is one, else the path's kind.

    Parameters
    ----------
    pc : PathConfig
        The runtime config's `path`.
    program : Program or None
        The point program read from `path.program`.
    max_speed : float
        The robot's maximum speed, m/s.
    rate_hz : float
        The loop's rate, Hz.

    Returns
    -------
    TargetSource
        `ProgramTargets`, `CircleTargets` or `RandomTargets`.
    """
    if program is not None:
        return ProgramTargets(program)
    if pc.kind == "circle":
        return CircleTargets(pc, max_speed, rate_hz)
    return RandomTargets(pc, max_speed)


def probe_point(pc: PathConfig, program: Program | None) -> np.ndarray:
    """A point on the path, where the start-up probes the twin's maps (nothing is consumed).

    Parameters
    ----------
    pc : PathConfig
        The runtime config's `path`.
    program : Program or None
        The point program, when there is one.

    Returns
    -------
    ndarray
        (3,) m, robot frame: the program's first target, the circle's centre or the box's centre.
    """
    if program is not None:
        return program.target[0]
    if pc.kind == "circle":
        return np.array(pc.circle_center_m)
    return (np.array(pc.box_min_m) + np.array(pc.box_max_m)) / 2
