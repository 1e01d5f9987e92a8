"""The cell the daemon commands: its drivers (robot, tracker, camera: `Instruments`) and its clock.

`Cell` is a real cell: wall-clock time, nothing to inject, no truth. `SimCell` wraps the
simulated cell (drivers.simulated.SimWorld, itself over the simulator's `sim.cell.SimCell`): on
`realtime: false` its clock is the simulated one and a tick that moved nothing lets a period of
it pass; it injects the runtime config's faults (`sim.faults`) when their time comes, and scores
every command against the simulator's truth (`true_rms_mm`, as `dt demo` scores it). No
correction path reads that truth. `open_cell` builds whichever the config's drivers need, each
driver by `drivers.registry` (kind and options checked before anything opens).
"""
from __future__ import annotations

import dataclasses
import logging
import time
from contextlib import ExitStack
from pathlib import Path
from typing import Any

import numpy as np

from drivers import registry
from dt_runtime.common.paths import beside
from dt_runtime.service.runtime_config import Fault, RuntimeConfig
from dt_runtime.twin.conditions import Conditions
from dt_runtime.twin.twin import Twin
from dt_runtime.workflows.campaign import Instruments
from dt_runtime.workflows.simulate import load_scenario_file

log = logging.getLogger("dt.run")


class Cell:
    """Drivers and clock of a real cell: wall-clock time, no faults to inject, no truth.

    Parameters
    ----------
    inst : Instruments
        The cell's drivers (robot, tracker, camera), active.
    """

    world: Any = None  # the simulated world, SimCell only

    def __init__(self, inst: Instruments):
        self.inst = inst

    def now(self) -> float:
        """The daemon's time (s): the wall clock (UNIX time)."""
        return time.time()

    def idle(self, period_s: float) -> None:
        """A tick that moved nothing: on the wall clock, time passes by itself (nothing to do).

        Parameters
        ----------
        period_s : float
            The loop's period, s.
        """

    def conditions(self) -> Conditions:
        """The cell's conditions before the next command, at the daemon's time."""
        return dataclasses.replace(self.inst.conditions(), t=self.now())

    def inject_due_faults(self) -> None:
        """Fault injection: a real cell has none."""

    def score(self, target: np.ndarray) -> None:
        """The true error of the command that reached `target`: unknown on a real cell.

        Parameters
        ----------
        target : ndarray
            (3,) m, robot frame.
        """

    def truth(self) -> dict[str, Any]:
        """The summary's truth figures: none on a real cell."""
        return {}


class SimCell(Cell):
    """The simulated cell: its clock (unless paced on the wall clock), its faults, its truth.

    Parameters
    ----------
    inst : Instruments
        The simulated drivers, active.
    world : SimWorld
        The simulated world they run on.
    realtime : bool
        The runtime config's `realtime`: True keeps the wall clock.
    faults : list of Fault
        `sim.faults`, each injected once `at_s` seconds of the simulated clock have passed since
        the run's first tick (the world's clock already reads the registration and warm-up then).
    twin : Twin
        Its frames score the truth in GL (no correction reads the truth).
    """

    def __init__(self, inst: Instruments, world, realtime: bool, faults: list[Fault], twin: Twin):
        super().__init__(inst)
        self.world, self.realtime = world, realtime
        self._faults = sorted(faults, key=lambda f: f.at_s)
        self.t_start: float | None = None  # the world's clock at the run's first tick: at_s counts from it
        self._T_rdk, self._T_lt = twin.T_rdk, twin.T_lt  # the frames the truth is scored in (GL)
        self._true_sq: list[float] = []  # squared 3D true error of each command

    def now(self) -> float:
        """The daemon's time (s): the simulated clock, or the wall clock when `realtime`."""
        return time.time() if self.realtime else self.world.t

    def idle(self, period_s: float) -> None:
        """On the simulated clock, let a period pass (or a run of refused commands would never
        end in simulated time); nothing when `realtime`.

        Parameters
        ----------
        period_s : float
            The loop's period, s.
        """
        if not self.realtime:
            self.world.idle(period_s)

    def inject_due_faults(self) -> None:
        """Inject the faults whose time came (a joint offset, a camera shift), each once, logged:
        `at_s` counts simulated seconds from the run's first tick (this call's first), not the
        world's clock, which already reads the registration and warm-up when the run starts."""
        t = self.world.t
        if self.t_start is None:
            self.t_start = t
        while self._faults and self._faults[0].at_s <= t - self.t_start:
            f = self._faults.pop(0)
            log.warning("injecting fault %.1f s into the run (simulated clock t=%.1f s): %s", t - self.t_start, t,
                        f.model_dump(exclude_none=True))
            if f.joint_offset_rad is not None:
                self.world.inject_joint_offset(f.joint_offset_rad)
            if f.camera_shift_m is not None:
                self.world.bump_camera(f.camera_shift_m)

    def score(self, target: np.ndarray) -> None:
        """Record the true error in GL of the command that reached `target`, as `dt demo` scores
        it (target - truth).

        Parameters
        ----------
        target : ndarray
            (3,) m, robot frame.
        """
        e = self._T_rdk.apply(target) - self._T_lt.apply(self.world.truth_in_tracker_frame())
        self._true_sq.append(float(np.sum(e ** 2)))

    def truth(self) -> dict[str, Any]:
        """3D RMS of target - where the arm went, over every command, and their number."""
        if not self._true_sq:
            return {}
        return {"true_rms_mm": round(float(np.sqrt(np.mean(self._true_sq))) * 1e3, 5), "true_n": len(self._true_sq)}


def open_cell(cfg: RuntimeConfig, base: Path, source: str, world, twin: Twin, parts: ExitStack) -> Cell:
    """The cell of the config's drivers, activated; what it opens is registered on `parts`. A
    simulated driver runs on `world` (the caller's, left open) or on one built from `sim`.

    Parameters
    ----------
    cfg : RuntimeConfig
        The runtime config (`drivers`, `sim`, `realtime`, `limits`).
    base : Path
        The directory `sim`'s relative paths are resolved against.
    source : str
        Names the runtime config in errors.
    world : SimWorld or None
        The caller's simulated world, or None.
    twin : Twin
        The daemon's twin (a `SimCell` scores in its frames).
    parts : ExitStack
        The daemon's stack: the world it builds and the drivers are registered for closing.

    Returns
    -------
    Cell
        `SimCell` when a simulated world is in use, else `Cell`.

    Raises
    ------
    TwinError
        A driver could not be built or activated (DriverError, ConfigError), or the scenario
        could not be read.
    """
    def p(rel: str) -> Path:
        return beside(base, rel)

    if world is None and any(registry.needs_world(kind, name) for kind, name, _ in cfg.drivers.chosen()):
        from drivers.simulated.devices import SimWorld

        scenario, _ = load_scenario_file(p(cfg.sim.scenario))  # without dt simulate's `data:` block
        world = SimWorld(scenario, p(cfg.sim.cell), source=str(p(cfg.sim.scenario)))
        parts.callback(world.close)
    robot, tracker, camera = cfg.drivers.create(world, source)
    inst = Instruments(robot, tracker, camera, world=world,
                       max_speed=world.max_speed() if world else cfg.limits.max_speed_m_s)
    parts.callback(inst.close)
    inst.activate()
    if world is None:
        return Cell(inst)
    return SimCell(inst, world, cfg.realtime, list(cfg.sim.faults), twin)
