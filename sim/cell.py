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
    """Read and validate a cell config (configs/cell.yaml).

    Parameters
    ----------
    path : str or Path

    Returns
    -------
    CellConfig

    Raises
    ------
    ConfigError
        When the file cannot be read or does not validate.
    """
    return load_yaml(path, CellConfig)


class SimCell:
    """One simulated cell: the plant, the laser tracker and the point MVS on one clock.

    Parameters
    ----------
    scenario : Scenario
    cell : CellConfig
    """
    def __init__(self, scenario: Scenario, cell: CellConfig):
        self.scenario, self.cell = scenario, cell
        self.clock = SimClock()
        self.plant = SimulatedCobot(scenario, self.clock)
        self.tracker = SimLaserTracker(self.plant.actual_tcp, cell.laser_tracker, scenario.seed)
        self.mvs = SimPointMVS(self.plant.actual_tcp, cell.mvs, scenario.seed)

    @classmethod
    def from_files(cls, scenario: str | Path | dict, cell: str | Path, seed: int | None = None,
                   source: str = "<scenario>") -> SimCell:
        """A cell from a scenario and a cell config.

        Parameters
        ----------
        scenario : str, Path or dict
            A YAML path, or its already-read mapping.
        cell : str or Path
            The cell config (YAML).
        seed : int or None
            Overrides the scenario's seed (plant noise, geometric draws, instruments).
        source : str
            Names a mapping scenario in errors.

        Returns
        -------
        SimCell

        Raises
        ------
        ConfigError
            When a file cannot be read or does not validate.
        """
        scn = validate(Scenario, scenario, source) if isinstance(scenario, dict) else load_scenario(scenario)
        if seed is not None:
            scn = scn.model_copy(update={"seed": int(seed)})
        return cls(scn, load_cell(cell))

    def close(self) -> None:
        """Release the plant's PyBullet clients."""
        self.plant.close()
