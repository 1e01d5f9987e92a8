"""Measurement data for analysis: read a measurement table (or a foreign file through an import
mapping) with the facts about it (source, skipped rows, registration, simulation sidecar), and
its measurement noise floor.

Rows are used in file order, which must be time order: the backlash and dynamic regressors
read the direction of approach from the previous row.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from dt_kernel.errors import DataError
from dt_kernel.units import M_PER_MM
from dt_runtime.common.paths import CONFIGS
from dt_runtime.measurements.dataset import Dataset, read_meta_sidecar, read_table
from dt_runtime.metrology.stats import rms3

DEFAULT_ROBOT = CONFIGS / "robots" / "cobot_hc20_like.yaml"


@dataclass
class Data:
    dataset: Dataset
    info: dict  # source, rows, skipped rows, registration report (import), sidecar facts


def load_data(path: str | Path, mapping: str | Path | None = None, skip_bad: bool = False,
              robot: str | Path | None = None) -> Data:
    """The contract CSV, or a foreign file read through `mapping` (registered if needed; `robot`,
    else the mapping's `robot:`, gives the commanded TCP of a file that has only joint angles).
    `info['robot']`: the mapping's robot config, which the analysis uses when no --robot is given."""
    path = Path(path)
    if not path.is_file():
        raise DataError(f"{path}: no such data file")
    info: dict = {"data": str(path)}
    if mapping is not None:
        from dt_runtime.measurements.importer import import_file, load_mapping, mapping_robot

        m = load_mapping(mapping)
        ds, report = import_file(path, mapping, skip_bad=skip_bad, robot=robot)
        mr = mapping_robot(m, Path(mapping))
        if mr is not None:
            info["robot"] = str(mr)
        info["registration"] = report.to_dict()
    else:
        ds = read_table(path, skip_bad=skip_bad)
        side = read_meta_sidecar(path)
        if side:
            info["simulation"] = side
    info["n"] = ds.n
    info["skipped_rows"] = [str(s) for s in ds.skipped]
    return Data(ds, info)


def noise_floor(u: np.ndarray | None) -> float | None:
    """3D RMS of the stated measurement standard uncertainty (m), if the data states it."""
    if u is None or not np.all(np.isfinite(u)):
        return None
    return rms3(u)


def floor_of(d: Data) -> float | None:
    """The measurement noise floor (m): the simulator's, else the stated uncertainty's (ux..uz),
    else the instrument's maximum permissible error (`info['mpe_mm']`, `--mpe-mm`): an MPE that
    bounds each coordinate's error is a rectangular distribution of standard uncertainty MPE/sqrt(3)
    per axis, whose 3D RMS over three axes is the MPE itself."""
    sim = d.info.get("simulation")
    if sim and sim.get("noise_floor_mm") is not None:
        return sim["noise_floor_mm"] * M_PER_MM
    stated = noise_floor(d.dataset.u)
    if stated is not None:
        return stated
    mpe = d.info.get("mpe_mm")
    return None if mpe is None else float(mpe) * M_PER_MM


def refit_sessions(d: Data) -> np.ndarray | None:
    """Per row, the session whose registration was fitted on its own points (-1: given or none),
    or None when no row's was: the rows a model is scored on after re-registration."""
    fitted = ("rigid", "rigid+offset")
    files = d.info.get("session_files")
    if files is None:
        method = (d.info.get("registration") or {}).get("method")
        return np.zeros(d.dataset.n, int) if method in fitted else None
    ok = [(f.get("registration") or {}).get("method") in fitted for f in files]
    if not any(ok):
        return None
    s = d.dataset.extra["session"].astype(int)
    return np.where(np.asarray(ok)[s], s, -1)
