"""Measurement data for analysis: read a measurement table (or a foreign file through an import
mapping) with the facts about it (source, skipped rows, registration, simulation sidecar), and
its measurement noise floor (`floor_of`; the replicates' in `analysis.replicates`).

Rows are used in file order, which must be time order: the backlash and dynamic regressors
read the direction of approach from the previous row.
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from dt_kernel.errors import DataError
from dt_kernel.units import M_PER_MM
from dt_runtime.analysis.replicates import TO_MEASURE, ReplicateFloor, replicate_floor  # noqa: F401 (re-exported)
from dt_runtime.common.paths import CONFIGS
from dt_runtime.measurements.dataset import Dataset, read_meta_sidecar, read_table
from dt_runtime.metrology.stats import rms3

DEFAULT_ROBOT = CONFIGS / "robots" / "cobot_hc20_like.yaml"


@dataclass
class Data:
    """A loaded measurement set and the facts about it (source, rows, skipped rows, registration
    report of an import, sidecar facts).
    """
    dataset: Dataset
    info: dict  # source, rows, skipped rows, registration report (import), sidecar facts


def load_data(path: str | Path, mapping: str | Path | None = None, skip_bad: bool = False,
              robot: str | Path | None = None) -> Data:
    """The contract CSV, or a foreign file read through `mapping` (registered if needed; `robot`,
    else the mapping's `robot:`, gives the commanded TCP of a file that has only joint angles).
    `info['robot']`: the mapping's robot config, which the analysis uses when no --robot is given.

    Parameters
    ----------
    path : str or Path
        The data file.
    mapping : str or Path, optional
        An import mapping.
    skip_bad : bool, optional
        Skip bad rows instead of raising.
    robot : str or Path, optional
        The robot, for a file with only joint angles.

    Returns
    -------
    Data
    """
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
    """3D RMS of the stated measurement standard uncertainty (m), if the data states it.

    Parameters
    ----------
    u : ndarray or None
        (n, 3) stated standard uncertainty, m.

    Returns
    -------
    float or None
    """
    if u is None or not np.all(np.isfinite(u)):
        return None
    return rms3(u)


def floor_of(d: Data) -> float | None:
    """The measurement noise floor (m): the simulator's, else the stated uncertainty's (ux..uz),
    else the instrument's maximum permissible error (`info['mpe_mm']`, `--mpe-mm`): an MPE that
    bounds each coordinate's error is a rectangular distribution of standard uncertainty MPE/sqrt(3)
    per axis, whose 3D RMS over three axes is the MPE itself; else the scatter of replicates
    (`analysis.replicates.replicate_floor`: repeated readings of one visit, else revisits under the
    same conditions). Where it came from is recorded in `info['noise_floor']`; with none of these,
    `info['noise_floor']['to_measure']` says what to measure.

    Parameters
    ----------
    d : Data
        The data (its info is updated).

    Returns
    -------
    float or None
    """
    sim = d.info.get("simulation")
    rep = replicate_floor(d.dataset)
    found: tuple[float, str] | None = None
    if sim and sim.get("noise_floor_mm") is not None:
        found = sim["noise_floor_mm"] * M_PER_MM, "the simulation's measurement noise"
    elif (stated := noise_floor(d.dataset.u)) is not None:
        found = stated, "the stated measurement uncertainty ux..uz"
    elif d.info.get("mpe_mm") is not None:
        found = float(d.info["mpe_mm"]) * M_PER_MM, "the instrument's MPE (--mpe-mm)"
    elif rep is not None:
        found = rep.value_m, rep.source()
    d.info["noise_floor"] = {"mm": None if found is None else found[0] / M_PER_MM,
                             "source": None if found is None else found[1],
                             "replicates": None if rep is None else rep.to_dict()}
    if found is None:
        d.info["noise_floor"]["to_measure"] = TO_MEASURE
    return None if found is None else found[0]


def refit_sessions(d: Data) -> np.ndarray | None:
    """Per row, the session whose registration was fitted on its own points (-1: given or none),
    or None when no row's was: the rows a model is scored on after re-registration.

    Parameters
    ----------
    d : Data
        The data.

    Returns
    -------
    ndarray or None
    """
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


def session_names(d: Data) -> dict[int, str]:
    """Each session's name by index: the import's (`info['session_files'][i]['name']`), else its file's.

    Parameters
    ----------
    d : Data
        The data.

    Returns
    -------
    dict of int to str
    """
    files = d.info.get("session_files") or []
    return {i: str(f.get("name") or Path(f["file"]).name) for i, f in enumerate(files)}


def session_index(value: str | int, names: dict[int, str], what: str) -> int:
    """A session named on the command line (its index, or its name / file name) as its index.

    Parameters
    ----------
    value : str or int
        As given.
    names : dict of int to str
        The sessions' names.
    what : str
        The option, for the error.

    Returns
    -------
    int
    """
    for sid, name in names.items():
        if str(value) in (str(sid), name, Path(name).name, Path(name).stem):
            return sid
    raise DataError(f"{what} {value!r}: no such session; the sessions: "
                    + ", ".join(f"{sid} ({name})" for sid, name in names.items()))


def select_sessions(d: Data, exclude: Sequence[str | int] = (),
                    reference: str | int | None = None) -> tuple[Data, dict[int, str], int]:
    """The data without the `exclude`d sessions (`--exclude-session`), the remaining sessions'
    names by index, and the reference session's index (`--reference-session`; default the first):
    what the session terms are measured against.

    Parameters
    ----------
    d : Data
        The data.
    exclude : sequence of str or int, optional
        Sessions left out.
    reference : str or int, optional
        The reference session.

    Returns
    -------
    data : Data
    names : dict of int to str
    reference : int
    """
    names = session_names(d)
    if exclude:
        if not names:
            raise DataError("--exclude-session: the data are one session (give several --data files)")
        drop = {session_index(v, names, "--exclude-session") for v in exclude}
        ds = d.dataset
        keep = ~np.isin(ds.extra["session"].astype(int), list(drop))
        if not keep.any():
            raise DataError("--exclude-session: no session left")
        d = Data(ds.select(np.flatnonzero(keep)), d.info | {"excluded_sessions": [names[s] for s in sorted(drop)]})
        names = {s: n for s, n in names.items() if s not in drop}
    ref = min(names) if names else 0
    if reference is not None:
        if not names:
            raise DataError("--reference-session: the data are one session (give several --data files)")
        ref = session_index(reference, names, "--reference-session")
    return d, names, ref
