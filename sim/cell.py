"""The simulated cell: plant, laser tracker and MVS sharing one clock, built from configs."""
from __future__ import annotations

from pathlib import Path

from dt_kernel.config import Frozen, load_yaml, validate
from sim.instruments import PointMVSConfig, SimLaserTracker, SimPointMVS, TrackerConfig
from sim.plant import SimClock, SimulatedCobot
from sim.scenario import Scenario, load_scenario


class CellConfig(Frozen):
    """Instrument placement in the cell (configs/cell.yaml)."""

    laser_tracker: TrackerConfig
    mvs: PointMVSConfig


def load_cell(path: str | Path) -> CellConfig:
    return load_yaml(path, CellConfig)


class SimCell:
    def __init__(self, scenario: Scenario, cell: CellConfig):
        self.scenario, self.cell = scenario, cell
        self.clock = SimClock()
        self.plant = SimulatedCobot(scenario, self.clock)
        self.tracker = SimLaserTracker(self.plant.actual_tcp, cell.laser_tracker, scenario.seed)
        self.mvs = SimPointMVS(self.plant.actual_tcp, cell.mvs, scenario.seed)

    @classmethod
    def from_files(cls, scenario: str | Path | dict, cell: str | Path, seed: int | None = None,
                   source: str = "<scenario>") -> SimCell:
        """scenario: a YAML path, or its already-read mapping (`source` names it in errors);
        seed: overrides the scenario's seed (plant noise, geometric draws, instruments)."""
        scn = validate(Scenario, scenario, source) if isinstance(scenario, dict) else load_scenario(scenario)
        if seed is not None:
            scn = scn.model_copy(update={"seed": int(seed)})
        return cls(scn, load_cell(cell))

    def close(self) -> None:
        self.plant.close()
