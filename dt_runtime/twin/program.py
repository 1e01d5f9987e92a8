"""A cell's program corrected offline (`dt correct`): every target of a program file gets the
twin's corrected command, the expanded uncertainty (95 %) of the position it reaches and
whether it lies in the calibrated volume, for offline programming tools.

Program file (CSV, UTF-8, comma, header row): `x, y, z` (mm, robot frame), `speed` (mm/s) and an
optional `point_id`. The corrected file repeats them and adds `cx, cy, cz` (the command, mm),
`Ux, Uy, Uz` (mm, 95 %, per GL axis), `inside` (1 or 0) and `distance_mm` (signed distance of
the command to the DOE hull, negative inside).
"""
from __future__ import annotations

import csv
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from dt_kernel.errors import DataError
from dt_kernel.units import M_PER_MM, MM_PER_M
from dt_runtime.measurements.cells import CellError, ColumnSpec, parse_rows, read_header
from dt_runtime.twin.twin import Correction, Twin

MAX_TARGETS = 1_000_000  # a program is read whole: bound what that may cost


@dataclass(frozen=True)
class Program:
    target: np.ndarray  # (n,3) m, robot frame
    speed: np.ndarray  # (n,) m/s
    point_id: list[str]
    line: list[int]  # source line of each target

    @property
    def n(self) -> int:
        return len(self.target)


def read_program(path: str | Path) -> Program:
    """Read a program file; a bad cell names file, line, column and value."""
    path = Path(path)
    if not path.is_file():
        raise DataError(f"{path}: no such program file")
    header = read_header(path, ",")
    specs = [ColumnSpec(k, k, scale=M_PER_MM) for k in ("x", "y", "z")] + [ColumnSpec("speed", "speed", scale=M_PER_MM)]
    if "point_id" in header:
        specs.append(ColumnSpec("point_id", "point_id", kind="str"))

    def check(row: dict) -> None:
        if not row["speed"] > 0:
            err = CellError("speed must be > 0 mm/s")
            err.column = "speed"  # type: ignore[attr-defined]
            raise err

    vals, lines, _, _ = parse_rows(path, ",", ".", specs, row_check=check)
    n = len(lines)
    if n == 0:
        raise DataError(f"{path}: the program has no targets")
    if n > MAX_TARGETS:
        raise DataError(f"{path}: {n} targets, more than the {MAX_TARGETS} a program may hold")
    ids = [str(v) for v in vals["point_id"]] if "point_id" in vals else [str(i + 1) for i in range(n)]
    return Program(np.column_stack([vals[k] for k in ("x", "y", "z")]), np.asarray(vals["speed"], float), ids,
                   list(lines))


def correct_program(twin: Twin, program: Program) -> list[Correction]:
    return [twin.correct(t, v) for t, v in zip(program.target, program.speed)]


def write_corrected(path: str | Path, program: Program, corrections: list[Correction]) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(path.suffix + ".part")  # a crash leaves no half-written program
    with tmp.open("w", newline="", encoding="utf-8") as f:
        w = csv.writer(f)
        w.writerow(["point_id", "x", "y", "z", "speed", "cx", "cy", "cz", "Ux", "Uy", "Uz", "inside", "distance_mm"])
        for pid, t, v, c in zip(program.point_id, program.target, program.speed, corrections):
            w.writerow([pid, *_mm(t), f"{v * MM_PER_M:.6g}", *_mm(c.command), *_mm(c.U), int(c.inside),
                        "" if not np.isfinite(c.distance_m) else f"{c.distance_m * MM_PER_M:.3f}"])
    tmp.replace(path)
    return path


def _mm(a: np.ndarray) -> list[str]:
    return [f"{float(x) * MM_PER_M:.6f}" for x in a]
