"""A path program corrected offline (`dt correct --path`): every interpolated set-point gets the
twin's corrected command and the expanded uncertainty (95 %) of the position it reaches, with the
refusals of point programs (`programs.program`): conditions the maps need and the path lacks, set-points
beyond the workspace, a map that gives no finite correction.

The set-point table (CSV, UTF-8, comma, header row; mm, mm/s, s, the robot base frame): `t` (s from
the path's start), `segment` (0-based index into the path's `segments`, or the poses interval),
`x, y, z` (the interpolated target, mm), `speed` (the profile's speed there, mm/s), `cx, cy, cz`
(the corrected command, mm), `Ux, Uy, Uz` (mm, 95 %, per GL axis), `inside` (1/0) and
`distance_mm` (signed distance of the command to the DOE hull, negative inside).

Along a path the arm stands at the previous set-point's command: a map with joint-space effects
reads set-point k's joints by the inverse kinematics started from set-point k - 1's (the path's
`joints` for the first), and the previous command is the direction of approach.
"""
from __future__ import annotations

import csv
from pathlib import Path

import numpy as np

from dt_kernel.errors import DataError
from dt_kernel.units import MM_PER_M
from dt_runtime.programs.path import PathProgram, Setpoints
from dt_runtime.programs.program import Program, check_workspace, mm_cells
from dt_runtime.twin.conditions import Conditions, missing
from dt_runtime.twin.corrector import Corrector, Setpoint
from dt_runtime.twin.twin import Twin

COLUMNS = ("t", "segment", "x", "y", "z", "speed", "cx", "cy", "cz", "Ux", "Uy", "Uz", "inside", "distance_mm")
# Condition -> the path file's key that gives it
PATH_KEYS = {"joints": "joints (rad: where the arm stands at the start)", "temperature": "temperature (deg C)",
             "payload": "payload (kg)", "t": "t0 (s: the campaign's time at the path's start)"}


def label(sp: Setpoints, k: int) -> str:
    """Set-point k for a message: its index, time and segment.

    Parameters
    ----------
    sp : Setpoints
        The interpolated path.
    k : int
        0-based set-point index.

    Returns
    -------
    str
    """
    return f"set-point {k} (t {sp.t[k]:.4f} s, segment {int(sp.segment[k])})"


def correct_path(twin: Twin, path: PathProgram, sp: Setpoints) -> list[Setpoint]:
    """Every set-point corrected in order, each under the previous one's command and joints.

    Parameters
    ----------
    twin : Twin
        The calibrated twin.
    path : PathProgram
        The path (its conditions: joints, temperature, payload, t0).
    sp : Setpoints
        Its interpolation (`programs.path.interpolate`).

    Returns
    -------
    list of Setpoint
        One per set-point (m, robot frame).

    Raises
    ------
    DataError
        Naming what the twin needs and the path lacks, a `joints` of the wrong length, the
        set-points beyond the workspace, or the first set-point without a finite correction.
    """
    base = Conditions(temperature=path.temperature, payload=path.payload, t=path.t0, joints=path.joints)
    lack = missing(twin.needs, base)
    if lack:
        raise DataError(f"{path.source}: the twin's maps need {', '.join(lack)}; give "
                        + "; ".join(f"the path's key {PATH_KEYS.get(n, n)}" for n in lack))
    chain = twin.e_lt.chain() if "joints" in twin.needs else None
    if path.joints is not None and chain is not None and len(path.joints) != chain.dof:
        raise DataError(f"{path.source}: key 'joints': {len(path.joints)} values, the twin's robot has "
                        f"{chain.dof} joints")
    check_workspace(twin, Program(sp.p, sp.programmed, [label(sp, k) for k in range(sp.n)],
                                  [0] * sp.n, source=path.source, labels=True), path.source)
    corrector = Corrector(twin)  # its own: a thermal map's history is this path's
    out: list[Setpoint] = []
    q, prev = path.joints, None
    for k in range(sp.n):
        cond = Conditions(temperature=path.temperature, payload=path.payload,
                          t=None if path.t0 is None else path.t0 + float(sp.t[k]), joints=q, previous=prev)
        r = corrector.correct(sp.p[k], float(sp.programmed[k]), cond, None if prev is None else prev - sp.p[k - 1])
        if not (np.all(np.isfinite(r.command)) and np.all(np.isfinite(r.U))):
            raise DataError(f"{path.source}: {label(sp, k)}: the twin gives no finite correction there (command "
                            f"{np.round(r.command * MM_PER_M, 3).tolist()} mm, "
                            f"U {np.round(r.U * MM_PER_M, 3).tolist()} mm)")
        out.append(r)
        q = r.joints if r.joints is not None else q  # the arm stands at this command next
        prev = r.command
    return out


def write_setpoints(path: str | Path, sp: Setpoints, corrected: list[Setpoint]) -> Path:
    """The set-point table (module docstring), written atomically.

    Parameters
    ----------
    path : str or Path
        The CSV file; its directory is created if missing.
    sp : Setpoints
        The interpolated path.
    corrected : list of Setpoint
        One per set-point (`correct_path`).

    Returns
    -------
    Path
        The file written.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(path.suffix + ".part")  # a crash leaves no half-written table
    with tmp.open("w", newline="", encoding="utf-8") as f:
        w = csv.writer(f)
        w.writerow(COLUMNS)
        for k, r in enumerate(corrected):
            w.writerow([f"{sp.t[k]:.6f}", int(sp.segment[k]), *mm_cells(sp.p[k]),
                        f"{sp.speed[k] * MM_PER_M:.6g}", *mm_cells(r.command), *mm_cells(r.U), int(r.inside),
                        "" if not np.isfinite(r.distance_m) else f"{r.distance_m * MM_PER_M:.3f}"])
    tmp.replace(path)
    return path
