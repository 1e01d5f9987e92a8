"""A cell's point program corrected offline (`dt correct --targets`): every target of a program
file (CSV; mm, mm/s, rad, robot frame) gets the twin's corrected command, the expanded
uncertainty (95 %) of the position it reaches and whether it lies in the calibrated volume.

The program and corrected file formats and what is refused before anything is corrected:
docs/cli.md, "`dt correct`".
"""
from __future__ import annotations

import csv
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from dt_kernel.errors import DataError, TwinError
from dt_kernel.units import M_PER_MM, MM_PER_M
from dt_runtime.measurements.cells import CellError, ColumnSpec, parse_rows, read_header, refuse_near_misses
from dt_runtime.measurements.checks import DEGREES_HINT, MAX_JOINT_RAD, plausible_ranges, positions_in_mm
from dt_runtime.twin.conditions import SOURCES, Conditions, missing
from dt_runtime.twin.twin import Correction, Twin

MAX_TARGETS = 1_000_000  # a program is read whole: bound what that may cost
# Without a robot config the twin knows its workspace only as its calibrated volume: a target this
# far outside it (m) is not in the cell (wrong frame, wrong unit, a typo), not an extrapolation.
FAR_OUTSIDE_M = 0.5
PROGRAM_COLUMNS = ("x", "y", "z", "speed", "point_id", "temperature", "payload", "t")


@dataclass(frozen=True)
class Program:
    """A point program in SI (`read_program`): its targets and the conditions its columns give.

    Attributes
    ----------
    target : ndarray
        (n, 3) m, robot frame.
    speed : ndarray
        (n,) m/s.
    point_id : list of str
        Each target's id (its `point_id`, else its 1-based row number).
    line : list of int
        Each target's source line.
    temperature, payload, t : ndarray or None
        (n,) deg C, kg, s: the program's columns, when it has them.
    joints : ndarray or None
        (n, dof) rad: where the arm stands before each target.
    extra : dict or None
        Column name -> (n,): the columns the maps' declared effects read.
    source : str
        The file it was read from, for messages.
    labels : bool
        `point_id` says where each target is (a path's set-points), not a line.
    """

    target: np.ndarray  # (n,3) m, robot frame
    speed: np.ndarray  # (n,) m/s
    point_id: list[str]
    line: list[int]  # source line of each target
    temperature: np.ndarray | None = None  # (n,) deg C
    payload: np.ndarray | None = None  # (n,) kg
    t: np.ndarray | None = None  # (n,) s
    joints: np.ndarray | None = None  # (n, dof) rad, where the arm stands before each target
    extra: dict[str, np.ndarray] | None = None  # (n,) each: the columns the user's declared effects read
    source: str = "<program>"  # the file it was read from, for messages
    labels: bool = False  # point_id says where each target is (a path's set-points), not a line

    def where(self, i: int, what: str = "") -> str:
        """Target i for a message: its id and line (and `what` after the line).

        Parameters
        ----------
        i : int
            0-based target index.
        what : str
            Text added after the line.

        Returns
        -------
        str
        """
        if self.labels:
            return f"{self.point_id[i]}{': ' + what if what else ''}"
        return f"{self.point_id[i]} (line {self.line[i]}{': ' + what if what else ''})"

    def conditions(self, i: int, base: Conditions | None = None) -> Conditions:
        """Target i's conditions: the program's columns, else `base`'s (e.g. the sensors').

        Parameters
        ----------
        i : int
            0-based target index.
        base : Conditions or None
            What the cell gives where the program has no column.

        Returns
        -------
        Conditions
        """
        b = base or Conditions()

        def at(col: np.ndarray | None, default):
            return default if col is None else col[i]

        extra = dict(b.extra or {}) | {k: float(v[i]) for k, v in (self.extra or {}).items()}
        return Conditions(temperature=at(self.temperature, b.temperature), payload=at(self.payload, b.payload),
                          t=at(self.t, b.t), joints=at(self.joints, b.joints), previous=b.previous,
                          extra=extra or None)

    @property
    def n(self) -> int:
        """Number of targets."""
        return len(self.target)


def read_program(path: str | Path, needs: tuple[str, ...] = ()) -> Program:
    """Read a program file; a bad cell names file, line, column and value. `needs`: the
    conditions the twin's maps read (`Twin.needs`); those beyond the known columns (a declared
    effect's `humidity`) are read as numbers when the file has them.

    Parameters
    ----------
    path : str or Path
        The program file (CSV, docs/cli.md "`dt correct`"; mm, mm/s, rad).
    needs : tuple of str
        The conditions the twin's maps read (`Twin.needs`).

    Returns
    -------
    Program
        In SI (m, m/s).

    Raises
    ------
    DataError
        The file is missing, empty or holds more than MAX_TARGETS targets; a column misspells a
        program column; a cell is bad (named by file, line, column and value); positions look
        like metres, joint angles like degrees, or a speed, payload or temperature is implausible.
    """
    path = Path(path)
    if not path.is_file():
        raise DataError(f"{path}: no such program file")
    header = read_header(path, ",")
    specs = [ColumnSpec(k, k, scale=M_PER_MM) for k in ("x", "y", "z")] + [ColumnSpec("speed", "speed", scale=M_PER_MM)]
    if "point_id" in header:
        specs.append(ColumnSpec("point_id", "point_id", kind="str"))
    opt = [k for k in ("temperature", "payload", "t") if k in header]
    qcols = [f"q{j}" for j in range(1, 13) if f"q{j}" in header]
    known = {*PROGRAM_COLUMNS, "joints"}
    own = [k for k in needs if k not in known and k in header]
    specs += [ColumnSpec(k, k) for k in opt + qcols + own]
    names = [*PROGRAM_COLUMNS, *(f"q{j}" for j in range(1, 8)), *(k for k in needs if k != "joints")]
    refuse_near_misses(path, [c for c in header if c not in names and c not in qcols],
                       [c for c in names if c not in header], "dt correct's program columns: docs/cli.md")

    def fail(column: str, why: str) -> None:
        err = CellError(why)
        err.column = column  # type: ignore[attr-defined]
        raise err

    def check(row: dict) -> None:
        if not row["speed"] > 0:
            fail("speed", "speed must be > 0 mm/s")
        if "payload" in row and not row["payload"] >= 0:
            fail("payload", "payload must be >= 0 kg")
        for q in qcols:
            if abs(row[q]) > MAX_JOINT_RAD:
                fail(q, DEGREES_HINT)

    vals, lines, _, _ = parse_rows(path, ",", ".", specs, row_check=check)
    n = len(lines)
    if n == 0:
        raise DataError(f"{path}: the program has no targets")
    if n > MAX_TARGETS:
        raise DataError(f"{path}: {n} targets, more than the {MAX_TARGETS} a program may hold")
    ids = [str(v) for v in vals["point_id"]] if "point_id" in vals else [str(i + 1) for i in range(n)]
    def col(k: str) -> np.ndarray | None:
        return np.asarray(vals[k], float) if k in vals else None

    target = np.column_stack([vals[k] for k in ("x", "y", "z")])
    positions_in_mm({"x, y, z": target}, str(path), "a program holds positions in mm, robot frame")
    plausible_ranges({"speed": col("speed"), "payload": col("payload"), "temperature": col("temperature")},
                     target, str(path))
    return Program(target, np.asarray(vals["speed"], float), ids,
                   list(lines), col("temperature"), col("payload"), col("t"),
                   np.column_stack([vals[q] for q in qcols]) if qcols else None,
                   {k: np.asarray(vals[k], float) for k in own} or None, str(path))


def check_workspace(twin: Twin, program: Program, where: str) -> None:
    """DataError naming the targets outside the workspace: beyond the arm's reach (the twin's
    robot config), or, for a twin without one, farther than FAR_OUTSIDE_M from its calibrated
    volume. Such a target is not an extrapolation the twin can state an uncertainty for.

    Parameters
    ----------
    twin : Twin
        The twin (its robot config, else its calibrated volume, bounds the workspace).
    program : Program
        The targets (m, robot frame).
    where : str
        The program's name, for the message.

    Raises
    ------
    DataError
        Naming up to three of the targets outside the workspace. Nothing is checked for a twin
        with neither a robot config nor a calibrated volume.
    """
    try:
        chain = twin.e_lt.chain()
    except TwinError:  # the robot config is gone: the calibrated volume still bounds the cell
        chain = None
    if chain is not None:
        far = np.linalg.norm(program.target, axis=1)
        limit, what = chain.reach_m, f"the arm's reach ({chain.reach_m * MM_PER_M:.0f} mm from its base, robot " \
                                     f"config {chain.name}: its links summed)"
    elif twin.volume is not None:
        far = twin.volume.distance(program.target)
        limit, what = FAR_OUTSIDE_M, (f"the workspace: more than {FAR_OUTSIDE_M * MM_PER_M:.0f} mm outside the "
                                      "twin's calibrated volume (a twin without a robot config)")
    else:
        return
    bad = np.flatnonzero(far > limit)
    if bad.size:
        first = ", ".join(program.where(i, f"{np.round(program.target[i] * MM_PER_M, 1).tolist()} mm")
                          for i in bad[:3])
        raise DataError(f"{where}: {bad.size} of {program.n} {'set-points' if program.labels else 'targets'} lie "
                        f"beyond {what}: {first}"
                        f"{' ...' if bad.size > 3 else ''}; targets are in mm in the robot frame")


def correct_program(twin: Twin, program: Program) -> list[Correction]:
    """Every target corrected under its conditions (the program's columns).

    Parameters
    ----------
    twin : Twin
        The calibrated twin.
    program : Program
        The targets (`read_program`).

    Returns
    -------
    list of Correction
        One per target, in order (m, robot frame; U per GL axis).

    Raises
    ------
    DataError
        The twin's maps need columns the program lacks (named), a target lies outside the
        workspace (`check_workspace`), or the twin gives no finite correction at a target.
    """
    lack = missing(twin.needs, program.conditions(0)) if program.n else []
    if lack:
        own = [n for n in lack if n not in SOURCES]
        raise DataError(f"the twin's maps need {', '.join(lack)}; give them as program columns "
                        f"({', '.join('q1..q6' if n == 'joints' else n for n in lack)})"
                        + (f"; {', '.join(own)}: read by the map's declared effect(s) "
                           f"{', '.join(declared_readers(twin, own))}" if own else ""))
    check_workspace(twin, program, program.source)
    out = [twin.correct(t, v, program.conditions(i)) for i, (t, v) in enumerate(zip(program.target, program.speed))]
    for i, c in enumerate(out):  # a map that returns NaN or inf there: refused, not written
        if not (np.all(np.isfinite(c.command)) and np.all(np.isfinite(c.U))):
            raise DataError(f"{program.source}: target {program.point_id[i]} (line {program.line[i]}): the twin "
                            f"gives no finite correction there (command {np.round(c.command * MM_PER_M, 3).tolist()} "
                            f"mm, U {np.round(c.U * MM_PER_M, 3).tolist()} mm)")
    return out


def declared_readers(twin: Twin, columns: list[str]) -> list[str]:
    """The effects of the twin's maps that read any of `columns` (for the error message).

    Parameters
    ----------
    twin : Twin
        The twin.
    columns : list of str
        Column names.

    Returns
    -------
    list of str
        Effect names.
    """
    models = {e: m for m in (twin.e_lt, twin.e_mvs_lt) for e in m.effects}
    return [e for e, m in models.items() if set(m.effect(e).columns) & set(columns)]


def write_corrected(path: str | Path, program: Program, corrections: list[Correction]) -> Path:
    """Write the corrected program atomically (CSV: point_id, x, y, z, speed, cx, cy, cz, Ux, Uy,
    Uz, inside, distance_mm; mm and mm/s; docs/cli.md "`dt correct`").

    Parameters
    ----------
    path : str or Path
        The file; its directory is created if missing.
    program : Program
        The targets.
    corrections : list of Correction
        One per target (`correct_program`).

    Returns
    -------
    Path
        The file written.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(path.suffix + ".part")  # a crash leaves no half-written program
    with tmp.open("w", newline="", encoding="utf-8") as f:
        w = csv.writer(f)
        w.writerow(["point_id", "x", "y", "z", "speed", "cx", "cy", "cz", "Ux", "Uy", "Uz", "inside", "distance_mm"])
        for pid, t, v, c in zip(program.point_id, program.target, program.speed, corrections):
            w.writerow([pid, *mm_cells(t), f"{v * MM_PER_M:.6g}", *mm_cells(c.command), *mm_cells(c.U),
                        int(c.inside),
                        "" if not np.isfinite(c.distance_m) else f"{c.distance_m * MM_PER_M:.3f}"])
    tmp.replace(path)
    return path


def mm_cells(a: np.ndarray) -> list[str]:
    """CSV cells of lengths in m, written in mm to 1 nm.

    Parameters
    ----------
    a : ndarray
        Values in m.

    Returns
    -------
    list of str
    """
    return [f"{float(x) * MM_PER_M:.6f}" for x in a]
